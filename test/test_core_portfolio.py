"""The portfolio partitioner: never worse than the paper's method or the MILP, ties to the paper, an honest budget."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest
from breaker_cases import andes_grid
from scipy.sparse.csgraph import connected_components

from controlled_islanding.core.grid import Branch, Generator, Grid, Load
from controlled_islanding.core.islanding import decide
from controlled_islanding.core.milp import ExactPartition
from controlled_islanding.core.observability import largest_first
from controlled_islanding.core.portfolio import PortfolioPartition, disruption_mw, isolating_cut_bound
from controlled_islanding.core.spectral import ConstrainedSpectralPartition, SpectralError, flow_weights
from controlled_islanding.harness.benchmarks import regional_groups


def observed_groups(grid: Grid, k: int, coverage: float) -> dict[str, int]:
    """Regional groups of the machines a largest-first PMU placement observes, renumbered 0 .. k'-1."""
    observed = set(largest_first(grid, coverage))
    groups = {n: g for n, g in regional_groups(grid, k).items() if n in observed}
    number = {g: i for i, g in enumerate(sorted(set(groups.values())))}
    return {n: number[g] for n, g in groups.items()}


def assert_valid(grid: Grid, groups: Mapping[str, int], labels: np.ndarray) -> None:
    """Each island is connected and holds its group's observed generators (the unobserved may be anywhere)."""
    idx = {b: i for i, b in enumerate(grid.buses)}
    for g in grid.generators:
        if g.name in groups:
            assert labels[idx[g.bus]] == groups[g.name], g.name
    adj = flow_weights(grid)
    for island in set(labels.tolist()):
        members = np.flatnonzero(labels == island)
        assert connected_components(adj[members][:, members], directed=False)[0] == 1, f'island {island}'


@pytest.mark.parametrize(('case', 'k', 'coverage'), [
    ('pjm5bus', 3, 1.0), ('ieee14', 3, 1.0), ('ieee39', 2, 0.5), ('ieee39', 3, 0.5), ('nordic44', 2, 0.5),
    ('nordic44', 3, 0.5), ('nordic44', 3, 1.0),
])
def test_never_worse_than_either_member_and_at_the_optimum(case: str, k: int, coverage: float) -> None:
    grid = andes_grid(case)
    groups = observed_groups(grid, k, coverage)
    assert len(set(groups.values())) >= 2
    model = PortfolioPartition().fit(grid, groups)
    spectral = disruption_mw(grid, ConstrainedSpectralPartition().fit(grid, groups).labels_)
    exact = ExactPartition(time_limit_s=60).fit(grid, groups)
    assert exact.optimal_
    assert_valid(grid, groups, model.labels_)
    cut = disruption_mw(grid, model.labels_)
    assert cut <= spectral + 1e-6
    assert cut == pytest.approx(exact.disruption_mw_, abs=1e-3)
    assert model.spectral_disruption_mw_ == pytest.approx(spectral, abs=1e-9)
    assert model.lower_bound_mw_ <= exact.disruption_mw_ + 1e-6
    # The decision carries the portfolio's line; the spectral member's eq. 6 fallback only when it is kept.
    unobserved = [g.name for g in grid.generators if g.name not in groups]
    decision = decide(grid, groups, PortfolioPartition(), unobserved=unobserved)
    assert decision.disrupted_mw == pytest.approx(cut, abs=1e-9)
    assert decision.partitioner_summary == model.summary_ and f'{model.winner_} kept' in model.summary_
    assert bool(decision.constraint_fallback) is (model.winner_ == 'spectral' and bool(model.spectral_.fallback_))


def test_the_exact_member_wins_where_the_spectral_cut_is_above_the_optimum() -> None:
    # Nordic 44, three regions, the largest half of the machines observed: measured 5663 MW spectral, 3031 MW optimal.
    grid = andes_grid('nordic44')
    groups = observed_groups(grid, 3, 0.5)
    model = PortfolioPartition().fit(grid, groups)
    assert model.winner_ == 'milp' and model.milp_method_ == 'highs' and model.milp_status_ == 'optimal'
    assert model.milp_gap_ == pytest.approx(0.0, abs=1e-6)
    assert model.milp_disruption_mw_ < 0.9 * model.spectral_disruption_mw_
    assert model.fallback_ == ''


def _ring(n: int, flow_mw: float) -> Grid:
    """Return a ring of n buses, each branch carrying the same flow: every connected split cuts two branches."""
    branches = tuple(Branch(f'{b}-{b % n + 1}', b, b % n + 1, x_pu=0.1) for b in range(1, n + 1))
    flows = np.full(n, flow_mw)
    return Grid(f'ring{n}', 100.0, tuple(range(1, n + 1)), branches,
                (Generator('G1', 1, 100.0, 200.0), Generator('G3', 3, 100.0, 200.0)),
                tuple(Load(b, 50.0) for b in range(1, n + 1)), p_from_mw=flows, p_to_mw=-flows)


def test_a_tie_keeps_the_paper_method_bus_for_bus() -> None:
    grid = _ring(6, 50.0)
    groups = {'G1': 0, 'G3': 1}
    model = PortfolioPartition().fit(grid, groups)
    spectral = ConstrainedSpectralPartition().fit(grid, groups)
    assert model.winner_ == 'spectral'
    np.testing.assert_array_equal(model.labels_, spectral.labels_)
    assert model.spectral_disruption_mw_ == pytest.approx(100.0) and model.lower_bound_mw_ == pytest.approx(100.0)


@pytest.mark.parametrize('case', ['ieee39', 'ieee14', 'pjm5bus'])
def test_full_observability_decisions_are_the_paper_method_where_it_is_optimal(case: str) -> None:
    grid = andes_grid(case)
    groups = observed_groups(grid, 2, 1.0)
    model = PortfolioPartition().fit(grid, groups)
    spectral = ConstrainedSpectralPartition().fit(grid, groups)
    assert model.winner_ == 'spectral' and model.milp_status_ in ('optimal', 'not needed')
    np.testing.assert_array_equal(model.labels_, spectral.labels_)


def test_isolating_cut_bound_with_two_groups_is_the_optimum_when_its_sides_are_connected() -> None:
    grid = andes_grid('ieee39')
    groups = observed_groups(grid, 2, 0.5)
    bound, labels = isolating_cut_bound(grid, groups)
    assert labels is not None
    assert_valid(grid, groups, labels)
    optimum = ExactPartition().fit(grid, groups).disruption_mw_
    assert bound <= optimum + 1e-9
    assert disruption_mw(grid, labels) == pytest.approx(optimum, abs=1e-3)


def test_budget_over_the_binaries_is_reported_and_the_paper_method_stands() -> None:
    grid = andes_grid('nordic44')
    groups = observed_groups(grid, 3, 0.5)
    model = PortfolioPartition(max_milp_binaries=100).fit(grid, groups)
    assert model.winner_ == 'spectral' and model.milp_status_ == 'skipped' and model.milp_disruption_mw_ is None
    assert f'{len(grid.buses) * 3} binary variables' in model.milp_reason_ and 'max_milp_binaries' in model.summary_
    np.testing.assert_array_equal(model.labels_, ConstrainedSpectralPartition().fit(grid, groups).labels_)


def test_node_limit_and_safety_net_are_reported() -> None:
    grid = andes_grid('nordic44')
    groups = observed_groups(grid, 3, 0.5)
    spectral = ConstrainedSpectralPartition().fit(grid, groups).labels_
    nodes = PortfolioPartition(node_limit=0).fit(grid, groups)
    assert nodes.milp_status_ == 'node_limit'
    if nodes.milp_disruption_mw_ is None:  # HiGHS stopped before any solution: the paper's method stands
        assert nodes.winner_ == 'spectral' and 'node_limit' in nodes.milp_reason_
        np.testing.assert_array_equal(nodes.labels_, spectral)
    safety = PortfolioPartition(safety_time_limit_s=1e-6).fit(grid, groups)
    assert safety.milp_status_ == 'time_limit' and 'safety-net time limit' in safety.milp_reason_
    assert safety.winner_ == 'spectral' and 'safety-net' in safety.summary_
    np.testing.assert_array_equal(safety.labels_, spectral)


def test_when_both_members_fail_the_error_names_both() -> None:
    # A line 1-2-3 with group 0 at both ends and group 1 in the middle: no connected island for group 0.
    grid = Grid('line3', 100.0, (1, 2, 3), (Branch('1-2', 1, 2), Branch('2-3', 2, 3)),
                (Generator('A', 1, 50.0, 60.0), Generator('B', 2, 50.0, 60.0), Generator('C', 3, 50.0, 60.0)),
                (Load(2, 150.0),), p_from_mw=np.array([50.0, -50.0]), p_to_mw=np.array([-50.0, 50.0]))
    with pytest.raises(SpectralError, match='exact partition: no partition of line3 keeps every group'):
        PortfolioPartition().fit(grid, {'A': 0, 'B': 1, 'C': 0})
