"""Cut set, per-island power balance and disrupted flow (eq. 9); the whole islanding decision.

Generation in an island is the scheduled dispatch of its generators (`Generator.p_mw`), not their
capacity: the paper's Table II (island 1 of case 1: 16.20 pu against 16.13 pu of load) and Table VI
(23.50 pu against 21.59 pu) are exactly MATPOWER case39's dispatch. Imbalance = generation - load;
load to shed = max(0, load - generation). Where it is shed, and which machines an island with a surplus trips, is
core/remedial.py's rule; every decision carries those actions.

Partial observability (the paper's abstract): a generator with no PMU has no coherent group. The caller names
it as unobserved; it carries no must-link or cannot-link constraint, its bus is placed by the flow-weighted
graph like a load bus, and its dispatch counts in whichever island it lands in.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from controlled_islanding.core.grid import Branch, Grid
from controlled_islanding.core.remedial import RemedialActions, remedial_actions


class IslandingError(ValueError):
    """A partition or a set of generator groups that does not fit the grid."""


@dataclass(frozen=True)
class IslandingDecision:
    """Where to split the grid and what each island looks like (mirrors msg IslandingDecision).

    Attributes:
        split: False for "no split" (one island, nothing to open).
        bus_island: Island (0-based) of every bus, by bus number.
        cut_branches: In-service branches joining two islands: the breakers to open.
        island_generation_mw: Scheduled generation per island, MW.
        island_load_mw: Load per island, MW.
        island_imbalance_mw: Generation minus load per island, MW.
        island_shed_mw: Load to shed per island so generation covers load, MW.
        disrupted_mw: Eq. 9, the sum over cut branches of (|P_from| + |P_to|) / 2, MW.
        remedial: The load to shed (where, how much) and the machines to trip (core/remedial.py); none without a
            split.
        unobserved_generators: Generators decided without a group (no PMU); their island is their bus's.
        constraint_fallback: Empty when the partitioner used eq. 6 as written; else why it departed from it (the
            spectral partitioner's group-balanced constraint weights when no beta exists, core/spectral.py).
        partitioner_summary: Empty when nothing was split; else the partitioner's own line (`summary_`: the
            portfolio's says which member's islands were kept, both disruptions and the exact member's status and
            gap, core/portfolio.py), or its class name when it has none.

    """

    split: bool
    bus_island: dict[int, int]
    cut_branches: tuple[Branch, ...]
    island_generation_mw: tuple[float, ...]
    island_load_mw: tuple[float, ...]
    island_imbalance_mw: tuple[float, ...]
    island_shed_mw: tuple[float, ...]
    disrupted_mw: float
    remedial: RemedialActions = RemedialActions()
    unobserved_generators: tuple[str, ...] = ()
    constraint_fallback: str = ''
    partitioner_summary: str = ''

    @property
    def n_islands(self) -> int:
        """Number of islands."""
        return len(self.island_generation_mw)

    @property
    def cut_branch_ids(self) -> tuple[str, ...]:
        """Ids of the branches to open."""
        return tuple(b.branch_id for b in self.cut_branches)

    def island_buses(self, island: int) -> list[int]:
        """Return the sorted bus numbers of one island."""
        return sorted(b for b, i in self.bus_island.items() if i == island)


class Partitioner(Protocol):
    """Anything that assigns every bus to the island of a generator group (scikit-learn style)."""

    labels_: np.ndarray

    def fit(self, grid: Grid, generator_groups: Mapping[str, int]) -> Partitioner:
        """Learn `labels_`, the island of each bus aligned with `grid.buses`."""
        ...


def evaluate_partition(grid: Grid, bus_island: Mapping[int, int]) -> IslandingDecision:
    """Evaluate a partition of the buses into islands.

    Args:
        grid: The grid; if it has no flows they are computed by AC power flow (`Grid.with_flows`).
        bus_island: Island of every bus; islands are numbered 0 .. n-1 with none empty.

    Returns:
        The decision: cut set, per-island balance, disrupted flow and remedial actions.

    Raises:
        IslandingError: A bus missing or unknown, or island numbers not 0 .. n-1.

    """
    buses = set(grid.buses)
    unknown = sorted(set(bus_island) - buses)
    if unknown:
        raise IslandingError(f'partition names unknown bus(es) {unknown} (not in {grid.name})')
    missing = sorted(buses - set(bus_island))
    if missing:
        raise IslandingError(f'partition leaves bus(es) {missing} without an island')
    islands = {int(i) for i in bus_island.values()}
    n = len(islands)
    if islands != set(range(n)):
        raise IslandingError(f'island numbers must be 0 .. {n - 1} with none empty, got {sorted(islands)}')
    if not grid.has_flows:
        grid = grid.with_flows()
    island_of = {int(b): int(i) for b, i in bus_island.items()}
    gen = np.zeros(n)
    for g in grid.generators:
        gen[island_of[g.bus]] += g.p_mw
    load = np.zeros(n)
    for ld in grid.loads:
        load[island_of[ld.bus]] += ld.p_mw
    cut = [k for k, b in enumerate(grid.branches)
           if b.in_service and island_of[b.from_bus] != island_of[b.to_bus]]
    assert grid.p_from_mw is not None and grid.p_to_mw is not None
    disrupted = float(sum((abs(grid.p_from_mw[k]) + abs(grid.p_to_mw[k])) / 2.0 for k in cut))
    return IslandingDecision(
        split=n > 1,
        bus_island=island_of,
        cut_branches=tuple(grid.branches[k] for k in cut),
        island_generation_mw=tuple(float(x) for x in gen),
        island_load_mw=tuple(float(x) for x in load),
        island_imbalance_mw=tuple(float(x) for x in gen - load),
        island_shed_mw=tuple(float(x) for x in np.maximum(0.0, load - gen)),
        disrupted_mw=disrupted,
        remedial=remedial_actions(grid, island_of),
    )


def check_generator_groups(grid: Grid, generator_groups: Mapping[str, int],
                           unobserved: Collection[str] = ()) -> dict[str, int]:
    """Validate generator groups against a grid.

    Args:
        grid: The grid.
        generator_groups: Group (0-based) of every observed generator, by generator name.
        unobserved: Names of the generators that have no group because nothing measured them. Being explicit
            keeps a generator dropped by mistake an error, never a silently unconstrained machine.

    Returns:
        The groups as a plain dict of ints.

    Raises:
        IslandingError: An unknown generator, one both grouped and unobserved, one neither, no generator
            observed, or group numbers not 0 .. k-1.

    """
    names = {g.name for g in grid.generators}
    unknown = sorted((set(generator_groups) | set(unobserved)) - names)
    if unknown:
        raise IslandingError(f'unknown generator(s) {unknown}; {grid.name} has {sorted(names)}')
    both = sorted(set(generator_groups) & set(unobserved))
    if both:
        raise IslandingError(f'generator(s) {both} are both in a group and listed as unobserved')
    missing = sorted(names - set(generator_groups) - set(unobserved))
    if missing:
        raise IslandingError(f'generator(s) {missing} are in no group and not listed as unobserved')
    if names and not generator_groups:
        raise IslandingError('no generator is observed: there are no groups to decide on')
    groups = {str(n): int(k) for n, k in generator_groups.items()}
    present = set(groups.values())
    if present != set(range(len(present))):
        raise IslandingError(f'group numbers must be 0 .. {len(present) - 1} with none empty, got {sorted(present)}')
    return groups


def decide(grid: Grid, generator_groups: Mapping[str, int],
           partitioner: Partitioner | None = None, unobserved: Collection[str] = ()) -> IslandingDecision:
    """Decide the islands for given coherent generator groups (Algorithm 1, steps 4 to 9, and the cut set).

    One group means "no split": every bus in island 0, nothing to open. Otherwise island i holds
    group i's generators.

    Args:
        grid: The grid with its current branch statuses; flows are computed by AC power flow if absent.
        generator_groups: Group (0-based) of every observed generator, by name.
        partitioner: The bus partitioner; default `ConstrainedSpectralPartition()`. It must leave generators
            missing from the groups unconstrained.
        unobserved: The generators without a group (see `check_generator_groups`).

    Returns:
        The decision.

    Raises:
        IslandingError: Bad groups.
        SpectralError: The partitioner cannot split the grid (e.g. a group with no path to its buses).

    """
    groups = check_generator_groups(grid, generator_groups, unobserved)
    if not grid.has_flows:
        grid = grid.with_flows()
    fallback = summary = ''
    if len(set(groups.values())) <= 1:
        decision = evaluate_partition(grid, dict.fromkeys(grid.buses, 0))
    else:
        if partitioner is None:
            from controlled_islanding.core.spectral import ConstrainedSpectralPartition

            partitioner = ConstrainedSpectralPartition()
        labels = partitioner.fit(grid, groups).labels_
        fallback = str(getattr(partitioner, 'fallback_', ''))
        summary = str(getattr(partitioner, 'summary_', '') or type(partitioner).__name__)
        decision = evaluate_partition(grid, {b: int(i) for b, i in zip(grid.buses, labels, strict=True)})
    return replace(decision, unobserved_generators=tuple(sorted(unobserved)), constraint_fallback=fallback,
                   partitioner_summary=summary)


def warm_up(partitioner: Partitioner | None = None) -> None:
    """Decide once on a small made-up grid, so that the compiled kernels are loaded before any real decision.

    numba loads each compiled kernel on its first call, and scipy its solvers: measured 5.7 s under load on the
    shared 2-core machine, whatever the grid's size (a 2224-bus decision took 1.3 s after it, 9.5 s without).
    A node that pays it in a callback looks hung to the supervisor, and a first request would pay it too.
    """
    from controlled_islanding.core.grid import Generator, Load

    # A ring, two groups of two machines on opposite halves joined by two light branches: at 8 buses, and at 120,
    # past the size at which the spectral fit leaves the dense solver for sparse LUs (the first 2224-bus decision
    # paid 6 ms more than the next without it). The light branches are the minimum cut, and both halves stay
    # connected, so the portfolio's exact member needs no MILP.
    for n in (8, 120):
        branches = tuple(Branch(f'{b}-{b % n + 1}', b, b % n + 1, x_pu=0.1) for b in range(1, n + 1))
        light = (n // 4 - 1, 3 * n // 4 - 1)
        flows = np.array([1.0 if i in light else 50.0 for i in range(n)])
        gens = (1, 2, n // 2 + 1, n // 2 + 2)
        grid = Grid('warm-up', 100.0, tuple(range(1, n + 1)), branches,
                    tuple(Generator(f'G{b}', b, 100.0, 200.0) for b in gens),
                    tuple(Load(b + 2, 100.0) for b in gens), p_from_mw=flows, p_to_mw=-flows)
        decide(grid, {f'G{gens[0]}': 0, f'G{gens[1]}': 0, f'G{gens[2]}': 1, f'G{gens[3]}': 1}, partitioner)
