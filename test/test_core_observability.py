"""Partial observability on six ANDES systems: decisions with generators that have no PMU (issue 17)."""

from __future__ import annotations

import numpy as np
import pytest
from breaker_cases import ANDES_CASES, andes_grid

from controlled_islanding.core.islanding import IslandingError, decide
from controlled_islanding.core.milp import ExactPartition
from controlled_islanding.core.observability import (
    ObservabilityError,
    infer_groups,
    largest_first,
    random_placement,
    reactance_distance,
)
from controlled_islanding.harness.benchmarks import regional_groups

# GBnetwork's MILP does not finish in a test's time (docs/benchmarks.md); its spectral decision does.
MILP_CASES = ['ieee14', 'pjm5bus', 'ieee39']


def _half_observed(grid):
    """Two regional groups; the largest half of the machines observed, and the largest of each region."""
    groups = regional_groups(grid, 2)
    observed = set(largest_first(grid, 0.5))
    for k in set(groups.values()):
        observed.add(max((g for g in grid.generators if groups[g.name] == k), key=lambda g: (g.p_max_mw, g.name)).name)
    return ({n: k for n, k in groups.items() if n in observed},
            sorted(set(groups) - observed), groups)


@pytest.fixture(params=sorted(ANDES_CASES), scope='module')
def system(request):
    grid = andes_grid(request.param)
    return (request.param, grid, *_half_observed(grid))


def test_unobserved_generators_constrain_nothing_and_land_somewhere(system):
    _, grid, groups, unobserved, _ = system
    decision = decide(grid, groups, unobserved=unobserved)
    assert decision.split
    assert decision.unobserved_generators == tuple(unobserved)
    by_name = {g.name: g for g in grid.generators}
    island_of_group = {}
    for name, k in groups.items():
        assert island_of_group.setdefault(k, decision.bus_island[by_name[name].bus]) == \
            decision.bus_island[by_name[name].bus]
    assert len(set(island_of_group.values())) == len(island_of_group)
    # Every machine's dispatch is counted once, in the island its bus landed in.
    assert sum(decision.island_generation_mw) == pytest.approx(sum(g.p_mw for g in grid.generators))


def test_a_generator_dropped_without_being_named_unobserved_is_an_error(system):
    _, grid, groups, unobserved, _ = system
    if not unobserved:
        pytest.skip('every machine is observed')
    with pytest.raises(IslandingError, match=unobserved[0]):
        decide(grid, groups, unobserved=unobserved[1:])
    with pytest.raises(IslandingError, match='both'):
        decide(grid, groups, unobserved=[*unobserved, next(iter(groups))])
    with pytest.raises(IslandingError, match='no generator is observed'):
        decide(grid, {}, unobserved=[g.name for g in grid.generators])


@pytest.mark.parametrize('case', MILP_CASES)
def test_fewer_constraints_never_make_the_exact_cut_worse(case):
    grid = andes_grid(case)
    groups, unobserved, full = _half_observed(grid)
    all_seen = ExactPartition(time_limit_s=20).fit(grid, full)
    partial = ExactPartition(time_limit_s=20).fit(grid, groups)
    assert partial.disruption_mw_ <= all_seen.disruption_mw_ + 1e-6


def test_inference_follows_the_network_not_the_names(system):
    _, grid, groups, unobserved, full = system
    inferred = infer_groups(grid, groups, unobserved)
    assert sorted(inferred) == unobserved
    assert set(inferred.values()) <= set(groups.values())
    by_name = {g.name: g for g in grid.generators}
    # A machine sharing a bus with an observed one is at distance 0 from it.
    obs_bus_group = {}
    for name, k in sorted(groups.items(), key=lambda kv: kv[1]):
        obs_bus_group.setdefault(by_name[name].bus, k)
    for name, k in inferred.items():
        if by_name[name].bus in obs_bus_group:
            assert k == obs_bus_group[by_name[name].bus]


def test_reactance_distance_is_a_metric_on_a_path():
    grid = andes_grid('ieee14')
    buses = list(grid.buses)[:6]
    d = reactance_distance(grid, buses, buses)
    assert np.allclose(d, d.T) and np.allclose(np.diag(d), 0.0, atol=1e-12)
    assert (d[~np.eye(len(buses), dtype=bool)] > 0).all()
    i, j, k = 0, 2, 4
    assert d[i, k] <= d[i, j] + d[j, k] + 1e-12


def test_placements_are_bounded_and_seeded():
    grid = andes_grid('ieee39')
    assert len(largest_first(grid, 0.25)) == round(0.25 * len(grid.generators))
    assert len(largest_first(grid, 0.01)) == 1
    caps = {g.name: g.p_max_mw for g in grid.generators}
    chosen = largest_first(grid, 0.5)
    assert min(caps[n] for n in chosen) >= max(caps[n] for n in caps if n not in chosen)
    a = random_placement(grid, 0.5, np.random.default_rng(3))
    assert a == random_placement(grid, 0.5, np.random.default_rng(3))
    for bad in (0.0, 1.5, float('nan')):
        with pytest.raises(ObservabilityError, match='coverage'):
            largest_first(grid, bad)
