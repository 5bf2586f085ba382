"""Exact minimum-disruption partition: optimal against brute force, connected islands, honest about limits."""

from __future__ import annotations

import itertools

import networkx as nx
import pytest

from controlled_islanding.core.grid import Grid
from controlled_islanding.core.islanding import evaluate_partition
from controlled_islanding.core.milp import ExactPartition, MilpError


def _groups_by_bus(grid, *bus_sets):
    by_bus = {g.bus: g.name for g in grid.generators}
    return {by_bus[b]: k for k, buses in enumerate(bus_sets) for b in buses}


def _connected(grid, island):
    graph = nx.Graph()
    graph.add_edges_from((b.from_bus, b.to_bus) for b in grid.branches if b.in_service)
    for i in set(island.values()):
        members = [b for b, v in island.items() if v == i]
        if not nx.is_connected(graph.subgraph(members)):
            return False
    return True


def _brute_force(grid, groups):
    fixed = {g.bus: groups[g.name] for g in grid.generators}
    free = [b for b in grid.buses if b not in fixed]
    k = len(set(groups.values()))
    best = None
    for choice in itertools.product(range(k), repeat=len(free)):
        island = dict(fixed) | dict(zip(free, choice, strict=True))
        if _connected(grid, island):
            cost = evaluate_partition(grid, island).disrupted_mw
            best = cost if best is None else min(best, cost)
    return best


@pytest.mark.parametrize(('case', 'outages', 'bus_sets'), [
    ('case9', [], ([1], [2], [3])),
    ('case14', [], ([1, 2, 3], [6, 8])),
    ('case14', ['2-3'], ([1, 2], [3, 6, 8])),
])
def test_milp_matches_brute_force(case, outages, bus_sets):
    grid = Grid.from_matpower(case).with_outages(outages).with_flows()
    groups = _groups_by_bus(grid, *bus_sets)
    model = ExactPartition().fit(grid, groups)
    island = dict(zip(grid.buses, model.labels_.tolist(), strict=True))
    decision = evaluate_partition(grid, island)
    assert model.status_ == 'optimal' and model.optimal_ and model.gap_ == pytest.approx(0.0, abs=1e-6)
    assert decision.disrupted_mw == pytest.approx(model.disruption_mw_, abs=1e-6)
    assert decision.disrupted_mw == pytest.approx(_brute_force(grid, groups), abs=1e-6)
    assert set(model.cut_branch_ids_) == set(decision.cut_branch_ids)
    assert _connected(grid, island)
    for g in grid.generators:
        assert island[g.bus] == groups[g.name]


def test_one_group_is_no_split():
    grid = Grid.from_matpower('case9').with_flows()
    model = ExactPartition().fit(grid, dict.fromkeys((g.name for g in grid.generators), 0))
    assert set(model.labels_.tolist()) == {0} and model.cut_branch_ids_ == () and model.disruption_mw_ == 0.0


def test_infeasible_groups_are_reported():
    # In case 14 without branch 1-5, bus 1 (G1) hangs off bus 2 (G2) alone, so G1 cannot share a connected island
    # with G3 while G2 is on another island.
    grid = Grid.from_matpower('case14').with_outages(['1-5']).with_flows()
    groups = _groups_by_bus(grid, [1, 3], [2, 6, 8])
    with pytest.raises(MilpError, match='connected island'):
        ExactPartition().fit(grid, groups)


def test_bad_inputs_are_named():
    grid = Grid.from_matpower('case9').with_flows()
    with pytest.raises(MilpError, match='not in'):
        ExactPartition().fit(grid, {'G99': 0, 'G1': 1})
    with pytest.raises(MilpError, match='time_limit_s'):
        ExactPartition(time_limit_s=0).fit(grid, {'G1': 0})


def test_time_limit_is_stated_never_silent():
    grid = Grid.from_matpower('case300').with_flows()
    from controlled_islanding.core.community import CommunityPartition

    groups = CommunityPartition().fit(grid).generator_groups_
    try:
        model = ExactPartition(time_limit_s=0.05).fit(grid, groups)
    except MilpError as exc:
        assert 'time' in str(exc).lower()
    else:
        assert model.status_ == 'time_limit' and not model.optimal_ and model.gap_ >= 0.0
