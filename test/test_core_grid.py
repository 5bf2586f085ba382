"""Grid model: MATPOWER loading, outages and AC power flow through PYPOWER."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pypower.case39 import case39

from controlled_islanding.core.grid import Grid, GridError


@pytest.fixture(scope='module')
def ieee39() -> Grid:
    return Grid.from_matpower('ieee39')


def test_case39_counts_come_from_the_data(ieee39: Grid) -> None:
    ppc = case39()
    assert len(ieee39.buses) == ppc['bus'].shape[0]
    assert len(ieee39.branches) == ppc['branch'].shape[0]
    assert [g.bus for g in ieee39.generators] == [int(b) for b in ppc['gen'][:, 0]]
    assert ieee39.generators[0].name == 'G1' and ieee39.generators[0].bus == 30
    assert sum(ld.p_mw for ld in ieee39.loads) == pytest.approx(ppc['bus'][:, 2].sum())
    assert not ieee39.has_flows


def test_every_form_of_case_loads_the_same_grid(ieee39: Grid, tmp_path: Path) -> None:
    ppc = case39()
    m_file = tmp_path / 'mycase.m'
    lines = ['function mpc = mycase', "mpc.version = '2';", f'mpc.baseMVA = {ppc["baseMVA"]};  % MVA']
    for key in ('bus', 'gen', 'branch'):
        lines.append(f'mpc.{key} = [')
        lines += ['\t' + '\t'.join(repr(float(v)) for v in row) + ';' for row in ppc[key]]
        lines.append('];')
    m_file.write_text('\n'.join(lines) + '\n')
    for case in ('case39', ppc, m_file):
        other = Grid.from_matpower(case)
        assert other.buses == ieee39.buses
        assert other.branches == ieee39.branches
        assert other.generators == ieee39.generators
        assert other.loads == ieee39.loads


def test_parallel_branches_get_numbered_ids() -> None:
    ppc = case39()
    ppc['branch'] = np.vstack([ppc['branch'], ppc['branch'][0]])
    grid = Grid.from_matpower(ppc)
    assert grid.branches[-1].branch_id == '1-2#2'
    assert not grid.with_outages(['1-2']).branches[0].in_service  # an exact id wins over a bus pair
    with pytest.raises(GridError, match='parallel'):
        grid.with_outages([(2, 1)])
    assert not grid.with_outages(['1-2#2']).branches[-1].in_service


def test_outages_by_id_or_either_direction(ieee39: Grid) -> None:
    a = ieee39.with_outages(['16-17', (2, 1)])
    out = {b.branch_id for b in a.branches if not b.in_service}
    assert out == {'16-17', '1-2'}
    assert ieee39.with_outages(['17-16']).branches == ieee39.with_outages(['16-17']).branches
    assert all(b.in_service for b in ieee39.branches)  # the original is untouched


@pytest.mark.parametrize('bad', ['16-18', '99-1', 'line7', (3, 3)])
def test_unknown_outage_is_named(ieee39: Grid, bad: str | tuple[int, int]) -> None:
    with pytest.raises(GridError, match='outage'):
        ieee39.with_outages([bad])


@pytest.mark.parametrize('case', ['case9', 'case9Q', 'case24_ieee_rts', 'case300'])
def test_any_pypower_case_loads_and_solves(case: str) -> None:
    grid = Grid.from_matpower(case).with_flows()
    assert grid.has_flows and len(grid.buses) > 3 and grid.generators


def test_unknown_case_is_named() -> None:
    with pytest.raises(GridError, match='case77'):
        Grid.from_matpower('case77')
    with pytest.raises(GridError, match='does not exist'):
        Grid.from_matpower('/nonexistent/x.m')


def test_ac_flows_balance_and_follow_outages(ieee39: Grid) -> None:
    base = ieee39.with_flows()
    assert base.p_from_mw is not None and base.p_to_mw is not None
    # Losses are positive and small on every line.
    losses = base.p_from_mw + base.p_to_mw
    assert np.all(losses > -1e-6) and np.all(losses < 0.05 * np.abs(base.p_from_mw) + 1.0)
    # Kirchhoff at buses without generators: branch injections sum to minus the load.
    gen_buses = {g.bus for g in ieee39.generators}
    load = {ld.bus: ld.p_mw for ld in ieee39.loads}
    for bus in set(ieee39.buses) - gen_buses:
        out_mw = sum(base.p_from_mw[k] for k, b in enumerate(ieee39.branches) if b.from_bus == bus)
        out_mw += sum(base.p_to_mw[k] for k, b in enumerate(ieee39.branches) if b.to_bus == bus)
        assert out_mw == pytest.approx(-load.get(bus, 0.0), abs=1e-3)
    post = ieee39.with_outages(['16-17']).with_flows()
    k = [b.branch_id for b in ieee39.branches].index('16-17')
    assert post.p_from_mw[k] == 0.0 and base.p_from_mw[k] != 0.0
    assert not np.allclose(post.p_from_mw, base.p_from_mw)
    # Outages on a grid with flows keep the other flows and zero the tripped ones.
    kept = base.with_outages(['16-17'])
    assert kept.p_from_mw[k] == 0.0
    assert np.delete(kept.p_from_mw, k) == pytest.approx(np.delete(base.p_from_mw, k))


def test_islanded_network_power_flow_fails_loudly(ieee39: Grid) -> None:
    # Bus 30 hangs on branch 2-30 alone.
    with pytest.raises(GridError, match='did not converge'):
        ieee39.with_outages(['2-30']).with_flows()


def test_grid_without_case_data_cannot_compute_flows(ieee39: Grid) -> None:
    bare = Grid(ieee39.name, ieee39.base_mva, ieee39.buses, ieee39.branches, ieee39.generators, ieee39.loads)
    with pytest.raises(GridError, match='no MATPOWER case data'):
        bare.with_flows()


def test_inconsistent_grid_is_rejected(ieee39: Grid) -> None:
    with pytest.raises(GridError, match='shape'):
        Grid('x', 100.0, ieee39.buses, ieee39.branches, ieee39.generators, ieee39.loads,
             p_from_mw=np.zeros(3), p_to_mw=np.zeros(3))
    with pytest.raises(GridError, match='unknown bus'):
        Grid('x', 100.0, ieee39.buses[1:], ieee39.branches, ieee39.generators, ieee39.loads)
