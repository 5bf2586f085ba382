"""Which breakers a decision may open and which of its remedial actions may run, against the node's own network.

No rclpy: `plan_commands` (the cut) and `plan_actions` (load shedding, generator tripping) take the decision's
arrays and a core Grid, so the rules are testable in milliseconds and the node only adds signatures, time,
arming and the audit log around them.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

from controlled_islanding.core.grid import Branch, Grid
from controlled_islanding.core.remedial import bus_load_mw


class Refusal(ValueError):
    """A decision the breaker node must not execute; `reason` is the audit and diagnostics key."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


@dataclass(frozen=True)
class Command:
    """One breaker to open."""

    branch_id: str
    breaker_id: str


@dataclass(frozen=True)
class CutPlan:
    """The decision as checked: the islands and the breakers that form them."""

    commands: tuple[Command, ...]
    n_islands: int
    merged_entries: int  # cut entries that named a branch already named (duplicates, other spellings)


def _resolve(entry_id: str, ends: tuple[int, int], grid: Grid, by_id: Mapping[str, Branch],
             by_pair: Mapping[frozenset[int], list[Branch]]) -> Branch:
    branch = by_id.get(entry_id)
    if branch is None:
        # The same branch spelled from its other end ('31-6' for '6-31'): resolved through its two buses, but
        # only when exactly one branch joins them; parallel circuits must be named by their ids.
        candidates = by_pair.get(frozenset(ends), [])
        if len(candidates) != 1:
            raise Refusal('unknown_branch', f'cut branch {entry_id!r} ({ends[0]}-{ends[1]}) is not a branch of '
                                            f'the network snapshot {grid.name!r}')
        branch = candidates[0]
    if frozenset(ends) != frozenset((branch.from_bus, branch.to_bus)):
        raise Refusal('inconsistent_cut', f'cut branch {entry_id!r} is given as {ends[0]}-{ends[1]} but joins '
                                          f'{branch.from_bus}-{branch.to_bus} in the network snapshot')
    return branch


def plan_commands(grid: Grid, bus_numbers: Sequence[int], bus_island: Sequence[int], cut_ids: Sequence[str],
                  cut_from: Sequence[int], cut_to: Sequence[int], *, max_breakers: int,
                  open_breakers: Collection[str] = (), breaker_override: Mapping[str, str] | None = None,
                  ) -> CutPlan:
    """Check a split decision against the network and return the breakers to open.

    Args:
        grid: The network now, as this node knows it (tripped branches out of service).
        bus_numbers, bus_island: The decision's island of each bus.
        cut_ids, cut_from, cut_to: The decision's cut branches and their end buses.
        max_breakers: The most breakers one decision may open.
        open_breakers: Breakers already commanded open and not reported closed since.
        breaker_override: Branch id -> breaker id from a mapping file; it wins over the snapshot's breaker ids.

    Returns:
        The commands, one per breaker, each breaker once.

    Raises:
        Refusal: 'inconsistent_islands' (the island map does not cover exactly the snapshot's buses, or forms
            fewer than two islands), 'island_without_generation', 'unknown_branch', 'inconsistent_cut' (the cut
            is not exactly the in-service branches joining two islands), 'branch_out_of_service',
            'too_large' (more entries than twice the branches), 'too_many_breakers'.

    """
    if len(bus_numbers) != len(bus_island):
        raise Refusal('array_length', f'{len(bus_numbers)} bus_numbers but {len(bus_island)} bus_island')
    if not len(cut_ids) == len(cut_from) == len(cut_to):
        raise Refusal('array_length', f'{len(cut_ids)} cut_branch_ids, {len(cut_from)} cut_from_bus, '
                                      f'{len(cut_to)} cut_to_bus')
    island = {int(b): int(i) for b, i in zip(bus_numbers, bus_island, strict=True)}
    if len(island) != len(bus_numbers) or set(island) != set(grid.buses):
        missing, extra = set(grid.buses) - set(island), set(island) - set(grid.buses)
        raise Refusal('inconsistent_islands', f'the island map names {len(island)} distinct buses of '
                                              f'{len(bus_numbers)} entries; the snapshot has {len(grid.buses)} '
                                              f'(missing {sorted(missing)[:5]}, unknown {sorted(extra)[:5]})')
    islands = set(island.values())
    if len(islands) < 2:
        raise Refusal('inconsistent_islands', 'a split into fewer than two islands')
    powered = {island[g.bus] for g in grid.generators if g.p_max_mw > 0}
    dark = sorted(islands - powered)
    if dark:
        raise Refusal('island_without_generation', f'islands {dark[:5]} hold no generation: they would black out')

    by_id = {b.branch_id: b for b in grid.branches}
    by_pair: dict[frozenset[int], list[Branch]] = {}
    for b in grid.branches:
        by_pair.setdefault(frozenset((b.from_bus, b.to_bus)), []).append(b)
    boundary = [b for b in grid.branches if b.in_service and island[b.from_bus] != island[b.to_bus]]
    if len(cut_ids) > 2 * len(grid.branches):
        raise Refusal('too_large', f'{len(cut_ids)} cut entries for a network of {len(grid.branches)} branches')
    # Bounded before any per-entry work: a decision naming 100,000 branches costs one comparison.
    chosen: dict[str, Branch] = {}
    for entry_id, f, t in zip(cut_ids, cut_from, cut_to, strict=True):
        branch = _resolve(str(entry_id), (int(f), int(t)), grid, by_id, by_pair)
        chosen[branch.branch_id] = branch
    out = sorted(b.branch_id for b in chosen.values() if not b.in_service)
    if out:
        raise Refusal('branch_out_of_service', f'cut branches {out[:5]} are already out of service')
    want = {b.branch_id for b in boundary}
    if set(chosen) != want:
        raise Refusal('inconsistent_cut', f'the cut is not the set of branches between the islands: missing '
                                          f'{sorted(want - set(chosen))[:5]}, not between islands '
                                          f'{sorted(set(chosen) - want)[:5]}')
    override = breaker_override or {}
    commands: dict[str, Command] = {}
    for branch in sorted(chosen.values(), key=lambda b: b.branch_id):
        breaker = override.get(branch.branch_id) or branch.breaker
        commands.setdefault(breaker, Command(branch.branch_id, breaker))
    if len(commands) > max_breakers:
        raise Refusal('too_many_breakers', f'{len(commands)} breakers, more than max_breakers={max_breakers}')
    already = sorted(set(commands) & set(open_breakers))
    if already:
        raise Refusal('branch_out_of_service', f'breakers {already[:5]} were already commanded open')
    return CutPlan(tuple(commands.values()), len(islands), len(cut_ids) - len(chosen))


# A shed may exceed what is left of a bus's load by float rounding only: MW.
_SHED_TOLERANCE_MW = 1e-6


@dataclass(frozen=True)
class Action:
    """One remedial action: shed `amount_mw` of load at `bus`, or trip `generator`.

    Attributes:
        kind: 'shed' or 'trip'.
        device_id: What executes it: 'LS-<bus>' (the bus's load-shedding relay) or 'GCB-<generator>' (the
            machine's breaker); the second part of its command id.
        bus: The load bus (shed), or the machine's bus (trip).
        generator: The machine (trip), '' for a shed.
        amount_mw: Load to shed, MW; 0 for a trip.

    """

    kind: str
    device_id: str
    bus: int
    generator: str = ''
    amount_mw: float = 0.0


def plan_actions(grid: Grid, bus_numbers: Sequence[int], bus_island: Sequence[int], shed_bus: Sequence[int],
                 shed_mw: Sequence[float], trip_generators: Sequence[str], *, max_actions: int,
                 shed_before_mw: Mapping[int, float] | None = None, tripped_before: Collection[str] = (),
                 ) -> tuple[Action, ...]:
    """Check a split decision's remedial actions against the network and what was done before; return them.

    Call it after `plan_commands`, which checks the island map.

    Args:
        grid: The network now, as this node knows it.
        bus_numbers, bus_island: The decision's island of each bus (checked by plan_commands).
        shed_bus, shed_mw: Load to shed, MW, at each bus.
        trip_generators: Machines to trip.
        max_actions: The most actions one decision may take.
        shed_before_mw: Load already commanded shed at each bus, by earlier decisions (the audit log), MW.
        tripped_before: Machines already commanded tripped (the audit log).

    Returns:
        The actions, sheds in the decision's order, then trips.

    Raises:
        Refusal: 'array_length', 'too_large' (more entries than the network has buses or machines),
            'too_many_actions', 'duplicate_action' (a bus or machine named twice), 'bad_value' (an amount that is
            not finite and positive), 'unknown_load_bus' (not a bus of the snapshot with a positive load),
            'shed_beyond_load' (more than what is left of the bus's load after earlier sheds),
            'unknown_generator', 'generator_already_tripped', 'island_without_generation' (every machine of an
            island tripped while load is left in it).

    """
    if len(shed_bus) != len(shed_mw):
        raise Refusal('array_length', f'{len(shed_bus)} shed_bus but {len(shed_mw)} shed_mw')
    if len(shed_bus) > len(grid.buses) or len(trip_generators) > len(grid.generators):
        raise Refusal('too_large', f'{len(shed_bus)} sheds and {len(trip_generators)} trips for a network of '
                                   f'{len(grid.buses)} buses and {len(grid.generators)} machines')
    if len(shed_bus) + len(trip_generators) > max_actions:
        raise Refusal('too_many_actions', f'{len(shed_bus)} sheds and {len(trip_generators)} trips, more than '
                                          f'max_actions={max_actions}')
    loads = bus_load_mw(grid)
    before = shed_before_mw or {}
    actions: list[Action] = []
    seen: set[int] = set()
    for raw_bus, raw_mw in zip(shed_bus, shed_mw, strict=True):
        bus, mw = int(raw_bus), float(raw_mw)
        if bus in seen:
            raise Refusal('duplicate_action', f'bus {bus} is shed twice in one decision')
        seen.add(bus)
        if not (math.isfinite(mw) and mw > 0):
            raise Refusal('bad_value', f'shed at bus {bus}: {mw} MW is not a positive amount')
        load = loads.get(bus, 0.0)
        if load <= 0:
            raise Refusal('unknown_load_bus', f'shed at bus {bus}: not a bus with load in the network snapshot '
                                              f'{grid.name!r}')
        left = load - float(before.get(bus, 0.0))
        if mw > left + _SHED_TOLERANCE_MW:
            raise Refusal('shed_beyond_load', f'shed {mw:.3f} MW at bus {bus}, which has {load:.3f} MW of load, '
                                              f'{left:.3f} MW of it not shed before')
        actions.append(Action('shed', f'LS-{bus}', bus, amount_mw=mw))
    machines = {g.name: g for g in grid.generators}
    trips: set[str] = set()
    for raw in trip_generators:
        name = str(raw)
        if name in trips:
            raise Refusal('duplicate_action', f'machine {name[:64]!r} is tripped twice in one decision')
        trips.add(name)
        if name not in machines:
            raise Refusal('unknown_generator', f'trip {name[:64]!r}: not a machine of the network snapshot '
                                               f'{grid.name!r}')
        if name in tripped_before:
            raise Refusal('generator_already_tripped', f'machine {name!r} was commanded tripped before')
        actions.append(Action('trip', f'GCB-{name}', machines[name].bus, generator=name))
    island = {int(b): int(i) for b, i in zip(bus_numbers, bus_island, strict=True)}
    gone = trips | set(tripped_before)
    shed_now = {a.bus: a.amount_mw for a in actions if a.kind == 'shed'}
    for k in sorted(set(island.values())):
        members = [b for b, i in island.items() if i == k]
        running = [g for g in grid.generators if island.get(g.bus) == k and g.p_max_mw > 0 and g.name not in gone]
        served = sum(loads.get(b, 0.0) - float(before.get(b, 0.0)) - shed_now.get(b, 0.0) for b in members)
        if not running and served > _SHED_TOLERANCE_MW:
            raise Refusal('island_without_generation', f'island {k} keeps {served:.1f} MW of load but every machine '
                                                       f'of it would be tripped')
    return tuple(actions)
