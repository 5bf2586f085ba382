"""Baselines: correlation-coefficient coherency and community-detection islanding."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest

from controlled_islanding.core.community import CommunityError, CommunityPartition
from controlled_islanding.core.correlation import CorrelationCoherency, CorrelationError
from controlled_islanding.core.grid import Grid


def _swings(seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 4.0, 121)
    a = [np.sin(2.0 * t) + 0.05 * rng.standard_normal(t.size) for _ in range(3)]
    b = [-np.sin(2.0 * t) + 0.3 * t + 0.05 * rng.standard_normal(t.size) for _ in range(2)]
    return a + b


def test_correlation_splits_antiphase_groups():
    model = CorrelationCoherency().fit(_swings())
    assert model.n_groups_ == 2
    assert model.labels_.tolist() == [0, 0, 0, 1, 1]
    assert model.correlation_.shape == (5, 5) and np.allclose(np.diag(model.correlation_), 1.0)
    assert np.allclose(model.distance_matrix_, 1.0 - model.correlation_)


def test_correlation_tolerates_lost_samples():
    series = _swings()
    series[1][10:40] = np.nan
    series[4][::7] = np.nan
    assert CorrelationCoherency().fit(series).labels_.tolist() == [0, 0, 0, 1, 1]


def test_correlation_one_group_when_all_move_together():
    t = np.linspace(0.0, 3.0, 90)
    series = [np.sin(t) + 0.1 * k for k in range(4)]
    model = CorrelationCoherency().fit(series)
    assert model.n_groups_ == 1
    noisy = [s + 0.01 * np.random.default_rng(k).standard_normal(t.size) for k, s in enumerate(series)]
    assert CorrelationCoherency(coherent_above=0.95).fit(noisy).n_groups_ == 1


def test_correlation_rejects_bad_series():
    with pytest.raises(CorrelationError, match='lengths'):
        CorrelationCoherency().fit([np.zeros(5), np.zeros(6)])
    with pytest.raises(CorrelationError, match='no generator'):
        CorrelationCoherency().fit([])
    with pytest.raises(CorrelationError, match='valid samples'):
        CorrelationCoherency().fit([np.array([1.0, np.nan, np.nan, 2.0]), np.array([np.nan, 1.0, 2.0, 3.0])])


@pytest.mark.parametrize('outages', [[], ['16-17', '1-2'], ['13-14', '16-17']])
def test_community_islands_are_connected_and_hold_generators(outages):
    grid = Grid.from_matpower('case39').with_outages(outages)
    model = CommunityPartition().fit(grid)
    island = dict(zip(grid.buses, model.labels_.tolist(), strict=True))
    assert sorted(set(island.values())) == list(range(model.n_islands_))
    graph = nx.Graph((b.from_bus, b.to_bus) for b in grid.branches if b.in_service)
    for i in range(model.n_islands_):
        members = [b for b, v in island.items() if v == i]
        assert any(g.bus in members for g in grid.generators)
        assert nx.is_connected(graph.subgraph(members))
    assert model.generator_groups_ == {g.name: island[g.bus] for g in grid.generators}
    assert 0.0 < model.modularity_ < 1.0


def test_community_reproduces_papers_case2_groups():
    grid = Grid.from_matpower('case39').with_outages(['13-14', '16-17'])
    groups = CommunityPartition().fit(grid).generator_groups_
    found = {frozenset(n for n, k in groups.items() if k == i) for i in set(groups.values())}
    assert found == {frozenset({'G2', 'G3'}), frozenset({'G4', 'G5', 'G6', 'G7'}),
                     frozenset({'G1', 'G8', 'G9', 'G10'})}


def test_community_needs_generators():
    grid = Grid.from_matpower('case9')
    from dataclasses import replace

    with pytest.raises(CommunityError, match='no buses or no generators'):
        CommunityPartition().fit(replace(grid, generators=()))
