"""Cut set, per-island balance and eq. 9 on the paper's IEEE 39 partitions."""

from __future__ import annotations

import pytest

from controlled_islanding.core.grid import Grid
from controlled_islanding.core.islanding import IslandingError, check_generator_groups, evaluate_partition

CASE1_ISLAND1 = {2, 3, 17, 18, 25, 26, 27, 28, 29, 30, 37, 38}   # Table I
CASE2_ISLAND1 = {15, 16, 19, 20, 21, 22, 23, 24, 33, 34, 35, 36}  # Table V


@pytest.fixture(scope='module')
def ieee39() -> Grid:
    return Grid.from_matpower('ieee39').with_flows()


def _two(grid: Grid, first: set[int]) -> dict[int, int]:
    return {b: 0 if b in first else 1 for b in grid.buses}


def test_case1_table1_and_table2(ieee39: Grid) -> None:
    grid = ieee39.with_outages(['16-17', '1-2'])
    d = evaluate_partition(grid, _two(grid, CASE1_ISLAND1))
    assert d.split and d.n_islands == 2
    assert d.cut_branch_ids == ('3-4',)
    assert d.island_generation_mw[0] == pytest.approx(1620.0)
    assert d.island_load_mw[0] == pytest.approx(1613.5)
    assert d.island_imbalance_mw[0] == pytest.approx(6.5)
    assert d.island_shed_mw == (0.0, 0.0)
    k = [b.branch_id for b in grid.branches].index('3-4')
    assert d.disrupted_mw == pytest.approx((abs(grid.p_from_mw[k]) + abs(grid.p_to_mw[k])) / 2)
    assert sum(d.island_generation_mw) == pytest.approx(sum(g.p_mw for g in grid.generators))
    assert sum(d.island_load_mw) == pytest.approx(sum(ld.p_mw for ld in grid.loads))


def test_case2_table6_sheds_in_island2(ieee39: Grid) -> None:
    grid = ieee39.with_outages(['13-14', '16-17'])
    d = evaluate_partition(grid, _two(grid, CASE2_ISLAND1))
    assert d.cut_branch_ids == ('14-15',)
    assert d.island_generation_mw[0] == pytest.approx(2350.0)
    assert d.island_load_mw[0] == pytest.approx(2159.1)
    assert d.island_shed_mw[0] == 0.0
    assert d.island_shed_mw[1] == pytest.approx(-d.island_imbalance_mw[1]) and d.island_shed_mw[1] > 0


def test_one_island_is_no_split(ieee39: Grid) -> None:
    d = evaluate_partition(ieee39, dict.fromkeys(ieee39.buses, 0))
    assert not d.split and d.cut_branches == () and d.disrupted_mw == 0.0


def test_out_of_service_branches_are_not_cut(ieee39: Grid) -> None:
    # Buses 16 and 17 apart with 16-17 already open: 16-17 must not be opened again.
    grid = ieee39.with_outages(['16-17'])
    d = evaluate_partition(grid, _two(grid, {17}))
    assert '16-17' not in d.cut_branch_ids
    assert set(d.cut_branch_ids) == {'17-18', '17-27'}


def test_flows_are_computed_when_absent(ieee39: Grid) -> None:
    bare = ieee39.without_flows().with_outages(['16-17', '1-2'])
    d = evaluate_partition(bare, _two(bare, CASE1_ISLAND1))
    assert d.disrupted_mw > 0.0


@pytest.mark.parametrize(('change', 'message'), [
    ({99: 0}, 'unknown bus'),
    ({1: None}, 'without an island'),
    ({1: 5}, 'island numbers'),
])
def test_bad_partitions_are_named(ieee39: Grid, change: dict, message: str) -> None:
    part = _two(ieee39, CASE1_ISLAND1)
    for bus, island in change.items():
        if island is None:
            del part[bus]
        else:
            part[bus] = island
    with pytest.raises(IslandingError, match=message):
        evaluate_partition(ieee39, part)


def test_bad_generator_groups_are_named(ieee39: Grid) -> None:
    groups = {g.name: 0 for g in ieee39.generators}
    with pytest.raises(IslandingError, match='G11'):
        check_generator_groups(ieee39, {**groups, 'G11': 1})
    with pytest.raises(IslandingError, match='G3'):
        check_generator_groups(ieee39, {n: k for n, k in groups.items() if n != 'G3'})
    with pytest.raises(IslandingError, match='0 .. 1'):
        check_generator_groups(ieee39, {**groups, 'G3': 2})
