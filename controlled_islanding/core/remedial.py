"""The islands' own balancing after a cut: which load to shed, where and how much, and which machines to trip.

One rule wherever the actions are decided or taken: partitioning puts them in the signed decision
(core/islanding.evaluate_partition), breaker_command commands them, grid_sim applies what was commanded, and the
offline runs (sim/closed_loop.run_offline: the no-action, MILP and oracle rows) apply the actions of this same rule.
Everything is computed from the network a node holds (the snapshot): each generator's dispatch and each bus's load.

Load shedding. An island whose load exceeds its dispatched generation sheds the difference, spread over its load
buses in proportion to each bus's load (a bus's load is the sum of its loads in the snapshot; a bus whose sum is not
positive is not shed): no one bus is emptied, and each keeps its power factor, as the testbed shed before the
decision carried it. An island of more than MAX_SHED_BUSES load buses sheds at its largest ones only (ties by bus
number), adding the next largest while they cannot cover the deficit: every shed is a command, and a large
system's island of hundreds of load buses (GBnetwork's: 236) would otherwise exceed what breaker_command takes in
one decision (`max_actions`, 80), and the whole decision would be refused.

Generation rejection, the companion of load shedding in islanding schemes: in an island whose dispatched
generation exceeds its load after the shed by more than `margin` (5 % of that load by default, left to the
governors: with the usual 5 % droop it settles a fully loaded island about 0.15 Hz high), machines are tripped,
largest output first, each only if it fits in the remaining surplus (generation_to_reject), so rejection never
turns a surplus into a deficit that nobody sheds.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from controlled_islanding.core.grid import Grid

REJECTION_MARGIN = 0.05  # surplus left to the governors, as a fraction of the island's load after the shed
# Three short islands shed within breaker_command's max_actions (80) with room for the trips; an IEEE 39 island has
# at most 19 load buses, so every island of the small systems still sheds at each of its load buses.
MAX_SHED_BUSES = 20


@dataclass(frozen=True)
class RemedialActions:
    """What an islanding decision does beside opening its cut (mirrors the decision message's action fields).

    Attributes:
        shed_bus: Load buses to shed at, each once, in increasing bus order.
        shed_mw: Load to shed at each of them, MW (> 0, at most the bus's load).
        trip_generators: Machines to trip (generation rejection), each once, by island then largest output first.

    """

    shed_bus: tuple[int, ...] = ()
    shed_mw: tuple[float, ...] = ()
    trip_generators: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if len(self.shed_bus) != len(self.shed_mw):
            raise ValueError(f'{len(self.shed_bus)} shed buses but {len(self.shed_mw)} shed amounts')

    def __bool__(self) -> bool:
        return bool(self.shed_bus or self.trip_generators)

    @property
    def shed_by_bus(self) -> dict[int, float]:
        """Load to shed per bus, MW."""
        return dict(zip(self.shed_bus, self.shed_mw, strict=True))

    def shed_by_island(self, bus_island: Mapping[int, int]) -> dict[int, float]:
        """Return the load to shed per island, MW (islands with none left out)."""
        out: dict[int, float] = {}
        for bus, mw in zip(self.shed_bus, self.shed_mw, strict=True):
            island = int(bus_island[bus])
            out[island] = out.get(island, 0.0) + float(mw)
        return out


def bus_load_mw(grid: Grid) -> dict[int, float]:
    """Return each bus's load in the grid, MW: the sum of its loads (buses with none left out)."""
    out: dict[int, float] = {}
    for ld in grid.loads:
        out[int(ld.bus)] = out.get(int(ld.bus), 0.0) + float(ld.p_mw)
    return out


def generation_to_reject(machine_mw: Mapping[str, float], load_mw: float, shed_mw: float = 0.0,
                         margin: float = REJECTION_MARGIN) -> tuple[str, ...]:
    """Return the machines an island with a generation surplus trips (see the module docstring).

    The rule: surplus = generation - (load - shed). Nothing is tripped while surplus <= margin x (load - shed).
    Otherwise machines are taken largest output first, each only if its output fits in what is left of the
    surplus (so rejection never turns the surplus into a deficit, which would need a shed nobody planned),
    until the rest is within the margin or no machine fits. Largest first keeps the number of machines
    tripped small. An island with no load left trips every machine: there is nothing for them to serve.

    Args:
        machine_mw: Dispatched output of each machine of the island, MW (a NaN or non-positive one is never tripped).
        load_mw: Island load, MW.
        shed_mw: Load the decision sheds in the island, MW.
        margin: Surplus left to the governors, as a fraction of the island load after the shed.

    Returns:
        Names of the machines to trip, largest output first.

    """
    served = max(0.0, load_mw - shed_mw)
    known = {n: mw for n, mw in machine_mw.items() if math.isfinite(mw)}
    left = sum(known.values()) - served
    out: list[str] = []
    for name, mw in sorted(known.items(), key=lambda item: (-item[1], item[0])):
        if left <= margin * served + 1e-9:
            break
        if 0.0 < mw <= left + 1e-9:
            out.append(name)
            left -= mw
    return tuple(out)


def remedial_actions(grid: Grid, bus_island: Mapping[int, int], margin: float = REJECTION_MARGIN,
                     ) -> RemedialActions:
    """Return the load to shed and the machines to trip in each island of a partition (see the module docstring).

    Args:
        grid: The network (its generators' dispatch and its loads are what count; branch statuses do not).
        bus_island: Island of every bus of the grid.
        margin: Generation surplus an island keeps without tripping machines, as a fraction of its load after the
            shed.

    Returns:
        The actions; none for a partition into one island.

    Raises:
        ValueError: A bus of the grid has no island.

    """
    missing = sorted(set(grid.buses) - set(bus_island))
    if missing:
        raise ValueError(f'buses {missing[:5]} of {grid.name} have no island')
    islands = sorted({int(bus_island[b]) for b in grid.buses})
    if len(islands) < 2:
        return RemedialActions()
    loads = bus_load_mw(grid)
    shed: dict[int, float] = {}
    trips: list[str] = []
    for island in islands:
        members = {b for b in grid.buses if int(bus_island[b]) == island}
        machines = {g.name: float(g.p_mw) for g in grid.generators if g.bus in members}
        load = sum(mw for b, mw in loads.items() if b in members)
        deficit = load - sum(mw for mw in machines.values() if math.isfinite(mw))
        sheddable = _largest_covering({b: mw for b, mw in loads.items() if b in members and mw > 0}, deficit)
        total = sum(sheddable.values())
        shed_here = 0.0
        if deficit > 1e-9 and total > 0:
            fraction = min(1.0, deficit / total)
            for b, mw in sheddable.items():
                shed[b] = fraction * mw
            shed_here = fraction * total
        trips += generation_to_reject(machines, load, shed_here, margin)
    buses = sorted(shed)
    return RemedialActions(tuple(buses), tuple(shed[b] for b in buses), tuple(trips))


def _largest_covering(load_mw: Mapping[int, float], deficit_mw: float) -> dict[int, float]:
    """Return the MAX_SHED_BUSES largest loads (ties by bus), and the next largest while they sum below the deficit."""
    ranked = sorted(load_mw.items(), key=lambda item: (-item[1], item[0]))
    n = min(len(ranked), MAX_SHED_BUSES)
    total = sum(mw for _, mw in ranked[:n])
    while n < len(ranked) and total < deficit_mw:
        total += ranked[n][1]
        n += 1
    return dict(ranked[:n])
