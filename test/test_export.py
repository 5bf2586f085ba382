"""Exported decisions apply in the tools they are written for: PYPOWER and pandapower solve each island, ANDES cuts."""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import yaml
from pypower.api import ppoption, runpf
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from controlled_islanding.cli import main
from controlled_islanding.core.grid import Grid
from controlled_islanding.evaluation import export
from controlled_islanding.sim.manifest import manifest_entries

BAGS = Path(__file__).resolve().parents[1] / 'bags'
SPLITS = [e for e in manifest_entries(BAGS / 'index.yaml') if e['expected_decision'].get('split')]


def case_of(entry: dict) -> str:
    return yaml.safe_load((BAGS / entry['scenario']).read_text())['case']


def _export_key(entry: dict) -> tuple:
    return case_of(entry), sorted(entry['expected_decision']['cut_branches']), sorted(
        entry.get('tripped_before_request', []))


# One test per distinct export: bags that differ only in PMU impairments share case, cut and outages.
DISTINCT = [e for i, e in enumerate(SPLITS) if _export_key(e) not in map(_export_key, SPLITS[:i])]


@cache
def system(case: str) -> object:
    return export.load_case(case)


def decision(entry: dict) -> export.Decision:
    return export.Decision.from_summary(entry['expected_decision'], entry.get('tripped_before_request', []))


def islands_of(grid: Grid) -> set[frozenset[int]]:
    index = {b: i for i, b in enumerate(grid.buses)}
    live = np.array([(index[br.from_bus], index[br.to_bus]) for br in grid.branches if br.in_service])
    a = coo_matrix((np.ones(len(live)), (live[:, 0], live[:, 1])), shape=(len(index), len(index)))
    _n, labels = connected_components(a, directed=False)
    return {frozenset(b for b, lab in zip(grid.buses, labels, strict=True) if lab == k) for k in set(labels)}


@pytest.mark.slow
@pytest.mark.parametrize('case', sorted({case_of(e) for e in SPLITS}))
def test_uncut_export_solves_to_the_simulators_own_power_flow(case: str) -> None:
    """The exported case is ANDES' case: PYPOWER, from a flat start, finds ANDES' own power flow solution.

    Every load and every shunt of a bus counts (EI 33 has two or more shunts at 68 of its 528 buses).
    """
    ss = system(case)
    buses = tuple(int(b) for b in ss.Bus.idx.v)
    ppc = export.matpower_case(ss, export.Decision((), (buses,), (0.0,)))
    ppc['bus'][:, 7], ppc['bus'][:, 8] = 1.0, 0.0
    result, ok = runpf(ppc, ppoption(VERBOSE=0, OUT_ALL=0))
    assert ok, f'{case}: the uncut export does not converge'
    np.testing.assert_allclose(result['bus'][:, 7], ss.Bus.v.v, atol=1e-4, err_msg=f'{case}: |V|, pu')
    ref = int(np.flatnonzero(ppc['bus'][:, 1] == 3)[0])  # a flat start puts the reference at 0 deg; ANDES may not
    angle_deg = np.degrees(ss.Bus.a.v)
    np.testing.assert_allclose(result['bus'][:, 8] - result['bus'][ref, 8], angle_deg - angle_deg[ref], atol=0.01,
                               err_msg=f'{case}: angle from the reference bus, deg')


@pytest.mark.slow
@pytest.mark.parametrize('entry', [pytest.param(e, id=e['name']) for e in DISTINCT])
def test_matpower_export_islands_each_solve(entry: dict, tmp_path: Path) -> None:
    d = decision(entry)
    ppc = export.matpower_case(system(case_of(entry)), d)
    path = export.write_matpower(ppc, tmp_path / 'islanded.m')
    # Read back by an independent parser: the open branches leave exactly the decision's islands.
    assert islands_of(Grid.from_matpower(str(path))) == {frozenset(isl) for isl in d.islands}
    for k, sub in enumerate(export.island_cases(ppc, d.islands)):
        assert (sub['bus'][:, 1] == 3).sum() == 1, f'island {k}: not exactly one reference bus'
        _result, ok = runpf(sub, ppoption(VERBOSE=0, OUT_ALL=0))
        assert ok, f'{entry["name"]}: island {k} power flow does not converge'
    load_before = export.matpower_case(system(case_of(entry)), export.Decision(d.cut_branch_ids, d.islands,
                                                                                (0.0,) * len(d.islands)))
    assert load_before['bus'][:, 2].sum() - ppc['bus'][:, 2].sum() == pytest.approx(sum(d.island_shed_mw), abs=0.5)


def _pair(branch_id: str) -> tuple[tuple[str, ...], str]:
    ends, _, n = branch_id.partition('#')
    return tuple(sorted(ends.split('-'))), n


# A cut with an outage (through the command); IEEE 39's transformers with their taps at the low side.
PANDAPOWER_BAGS = ('pjm5bus_bus3_unstable', 'ieee39_case2_g3_unstable')


@pytest.mark.slow
@pytest.mark.parametrize('name', PANDAPOWER_BAGS)
def test_pandapower_export_round_trips_and_each_island_solves_as_in_pypower(name: str, tmp_path: Path) -> None:
    import pandapower as pp
    import pandapower.topology as top
    from pandapower.toolbox import select_subnet

    entry = next(e for e in SPLITS if e['name'] == name)
    d = decision(entry)
    out = tmp_path / 'islanded.json'
    if name == PANDAPOWER_BAGS[0]:
        summary = tmp_path / 'summary.json'
        summary.write_text(json.dumps({**entry['expected_decision'], 'bag': f'bags/{entry["bag"]}'}))
        assert main(['export', str(summary), '--to', 'pandapower', '-o', str(out)]) == 0
    else:
        export.pandapower_json(export.pandapower_net(system(case_of(entry)), d), out)
    net = pp.from_json(str(out))
    opened = [n for kind in ('line', 'trafo', 'impedance') for n in net[kind].name[~net[kind].in_service.astype(bool)]]
    assert sorted(map(_pair, opened)) == sorted(map(_pair, [*d.cut_branch_ids, *d.outages]))
    assert {frozenset(map(int, c)) for c in top.connected_components(top.create_nxgraph(net))} == \
        {frozenset(isl) for isl in d.islands}
    ppc = export.matpower_case(system(case_of(entry)), d)
    for k, (buses, sub_ppc) in enumerate(zip(d.islands, export.island_cases(ppc, d.islands), strict=True)):
        island = select_subnet(net, list(buses))
        assert len(island.ext_grid) == 1, f'island {k}: not exactly one ext_grid'
        pp.runpp(island, numba=False)
        assert island.converged, f'{name}: island {k} does not converge in pandapower'
        # The same island solved by PYPOWER from the MATPOWER export: the conversion kept the network.
        result, ok = runpf(sub_ppc, ppoption(VERBOSE=0, OUT_ALL=0))
        assert ok
        vm = dict(zip(result['bus'][:, 0].astype(int), result['bus'][:, 7], strict=True))
        assert island.res_bus.vm_pu.to_dict() == pytest.approx(vm, abs=1e-6), f'island {k}'


@pytest.mark.slow
@pytest.mark.parametrize('name', ['gbnetwork_bus73_unstable', 'ei33_bus101048_pair_unstable'])
def test_pandapower_net_has_the_admittances_of_the_matpower_export(name: str) -> None:
    # GBnetwork's 613 transformers with charging and EI 33's 842 phase shifters; EI 33 does not solve as a whole
    # in pandapower or PYPOWER here (GBnetwork has since its loads were all exported), so the networks are
    # compared, not their power flows.
    from pandapower.converter.pypower.to_ppc import to_ppc
    from pypower.api import ext2int
    from pypower.makeYbus import makeYbus

    entry = next(e for e in SPLITS if e['name'] == name)
    ss, d = system(case_of(entry)), decision(entry)
    net = export.pandapower_net(ss, d)
    theirs = to_ppc(net, init='flat')
    ppc = export.matpower_case(ss, d)
    order = [net._pd2ppc_lookups['bus'][int(b)] for b in ppc['bus'][:, 0]]
    ours = ext2int(ppc)
    y_ours = makeYbus(ours['baseMVA'], ours['bus'], ours['branch'])[0]
    y_theirs = makeYbus(theirs['baseMVA'], theirs['bus'], theirs['branch'][:, :17].real)[0]
    assert abs(y_ours - y_theirs[order][:, order]).max() < 1e-9 * abs(y_ours).max()


@pytest.mark.slow
def test_pandapower_export_opens_parallel_lines_and_branches_the_converter_makes_impedances() -> None:
    # Kundur's cut is its three parallel 7-8 lines. Its step-up transformers have no off-nominal tap, so
    # pandapower's converter makes them impedances, which it would leave in service: opening 2-6 too leaves G2
    # on its own.
    import pandapower.topology as top

    entry = next(e for e in SPLITS if e['name'] == 'kundur_bus9_unstable')
    d = decision(entry)
    (g2_side,) = [isl for isl in d.islands if 2 in isl]
    islands = (*[isl for isl in d.islands if 2 not in isl], (2,), tuple(b for b in g2_side if b != 2))
    net = export.pandapower_net(system(case_of(entry)), export.Decision((*d.cut_branch_ids, '6-2'), islands,
                                                                        (0.0,) * len(islands)))
    opened = [n for kind in ('line', 'impedance') for n in net[kind].name[~net[kind].in_service.astype(bool)]]
    assert sorted(opened) == ['2-6', '7-8', '7-8#2', '7-8#3']
    assert {frozenset(map(int, c)) for c in top.connected_components(top.create_nxgraph(net))} == \
        {frozenset(isl) for isl in islands}


def test_branch_ids_match_in_either_orientation() -> None:
    ss = system(case_of(SPLITS[0]))
    a, b = int(ss.Line.bus1.v[0]), int(ss.Line.bus2.v[0])
    assert export.line_rows(ss, [f'{a}-{b}', f'{b}-{a}']) == [0, 0]
    with pytest.raises(export.ExportError, match="'1-999'"):
        export.line_rows(ss, ['1-999'])


@pytest.mark.slow
def test_andes_toggles_open_the_cut_in_a_time_domain_run(tmp_path: Path) -> None:
    import andes

    from controlled_islanding.sim.andes_sim import pycode_dir, quiet_andes

    entry = SPLITS[0]
    summary = tmp_path / 'summary.json'
    summary.write_text(json.dumps({**entry['expected_decision'], 'bag': f'bags/{entry["bag"]}'}))
    out = tmp_path / 'toggles.json'
    assert main(['export', str(summary), '--to', 'andes', '--at-s', '0.05', '-o', str(out)]) == 0
    rows = json.loads(out.read_text())
    assert len(rows) == len(entry['expected_decision']['cut_branches'])
    quiet_andes()
    ss = andes.load(andes.get_case(case_of(entry)), setup=False, no_output=True, default_config=True,
                    pycode_path=str(pycode_dir()))
    for row in rows:
        ss.add('Toggle', row)
    ss.setup()
    ss.PFlow.run()
    ss.TDS.config.tf = 0.1
    ss.TDS.config.no_tqdm = 1
    ss.TDS.run()
    idx = list(ss.Line.idx.v)
    assert all(ss.Line.u.v[idx.index(row['dev'])] == 0 for row in rows)


@pytest.mark.parametrize(('summary', 'args', 'named'), [
    ({'split': False, 'status': 'NO_SPLIT'}, ['--to', 'matpower'], 'not a split'),
    ({'split': True, 'cut_branch_ids': ['1-2'], 'islands': [[1]], 'bag': 'elsewhere'}, ['--to', 'matpower'],
     'give --case'),
    ({'split': True}, ['--to', 'andes'], '--at-s'),
])
def test_bad_input_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str], summary: dict, args: list[str],
                            named: str) -> None:
    path = tmp_path / 'summary.json'
    path.write_text(json.dumps(summary))
    assert main(['export', str(path), *args, '-o', str(tmp_path / 'x.m'), *(['--case', 'ieee14/ieee14_full.xlsx']
                                                                          if named == 'not a split' else [])]) == 2
    assert named in capsys.readouterr().err


def _close(got_mw: float, expected_mw: float) -> bool:
    return abs(got_mw - expected_mw) <= max(0.5, 0.005 * abs(expected_mw))


def check_islands_as_decided(decision_file: Path, decision: dict, out: Path, *args: str) -> None:
    """Export a decision file to MATPOWER and pandapower through the command, and check every island of both.

    The decision's cut is open and leaves its islands; each island holds the decision's load less its shed and
    its generators the decision's generation; solved (PYPOWER, pandapower), its generation is that load plus the
    island's losses.
    """
    import pandapower as pp
    import pandapower.topology as top
    from pandapower.toolbox import select_subnet

    out.mkdir(parents=True, exist_ok=True)
    m_file, net_file = out / 'islanded.m', out / 'islanded.json'
    assert main(['export', str(decision_file), *args, '--to', 'matpower', '-o', str(m_file)]) == 0
    assert main(['export', str(decision_file), *args, '--to', 'pandapower', '-o', str(net_file)]) == 0
    islands = decision['islands']
    buses = [isl['buses'] for isl in islands]
    ppc = Grid.from_matpower(str(m_file)).matpower
    net = pp.from_json(str(net_file))
    opened = [n for kind in ('line', 'trafo', 'impedance') for n in net[kind].name[~net[kind].in_service.astype(bool)]]
    assert set(map(_pair, decision['cut_branch_ids'])) <= set(map(_pair, opened))
    expected = {frozenset(b) for b in buses}
    assert {frozenset(map(int, c)) for c in top.connected_components(top.create_nxgraph(net))} == expected
    assert islands_of(Grid.from_matpower(str(m_file))) == expected
    for isl, sub, (load_mw, gen_mw) in zip(islands, export.island_cases(ppc, buses), export.island_power_mw(ppc, buses),
                                           strict=True):
        k, served_mw = isl['island'], isl['load_mw'] - isl['shed_mw']
        assert _close(load_mw, served_mw), f'island {k}: MATPOWER load {load_mw:.1f} MW, decision {served_mw:.1f} MW'
        assert _close(gen_mw, isl['generation_mw']), \
            f'island {k}: MATPOWER generation {gen_mw:.1f} MW, decision {isl["generation_mw"]:.1f} MW'
        part = select_subnet(net, isl['buses'])
        # pandapower's converter makes a negative load an uncontrollable sgen.
        negative = part.sgen[~part.sgen.controllable.astype(bool)]
        pp_load_mw = float(part.load.p_mw[part.load.in_service.astype(bool)].sum()
                           - negative.p_mw[negative.in_service.astype(bool)].sum())
        assert _close(pp_load_mw, served_mw), f'island {k}: pandapower load {pp_load_mw:.1f}, decision {served_mw:.1f}'
        result, ok = runpf(sub, ppoption(VERBOSE=0, OUT_ALL=0))
        assert ok, f'island {k}: PYPOWER power flow does not converge'
        on = result['branch'][:, 10] > 0
        losses_mw = float((result['branch'][on, 13] + result['branch'][on, 15]).sum()
                          + (result['bus'][:, 4] * result['bus'][:, 7] ** 2).sum())
        solved_mw = float(result['gen'][result['gen'][:, 7] > 0, 1].sum())
        # Shed so that generation covers load: a surplus left is taken up by the island's reference machine.
        assert _close(solved_mw, min(isl['generation_mw'], served_mw) + losses_mw), \
            f'island {k}: PYPOWER generation {solved_mw:.1f} MW for {served_mw:.1f} MW of load, {losses_mw:.1f} lost'
        pp.runpp(part, numba=False)
        pp_solved_mw = float(part.res_gen.p_mw.sum() + part.res_ext_grid.p_mw.sum()
                             + part.res_sgen.p_mw[part.sgen.controllable.astype(bool)].sum())
        assert pp_solved_mw == pytest.approx(solved_mw, abs=0.05), f'island {k}: pandapower and PYPOWER differ'


# A testbed run that ended before its request, as its result.json says it: no decision to export.
UNDECIDED_RUN = {'scenario': 'ieee14_g1_unstable', 'path': str(BAGS / 'ieee14_g1_unstable.yaml'), 'decision': None,
                 'closed_loop': {'request_s': 2.0, 'opened_s': None}, 'events': [], 'runs': {}}


@pytest.mark.parametrize(('content', 'named'), [
    ({}, 'an empty JSON object'),
    ([], 'an empty JSON list'),
    (UNDECIDED_RUN, 'a testbed result of ieee14_g1_unstable of a run with no decision'),
    ([UNDECIDED_RUN], 'a testbed result of ieee14_g1_unstable of a run with no decision'),
    ([{'split': True}], 'not all testbed results'),
    ({'split': None, 'results_dir': 'r', 'bag': 'b', 'undecided_requests': ['b/request-1']}, 'with no decision'),
    ('a string', 'a JSON str'),
])
def test_what_is_not_a_decision_is_refused_saying_what_it_is(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                              content: object, named: str) -> None:
    path = tmp_path / 'result.json'
    path.write_text(json.dumps(content))
    assert main(['export', str(path), '--to', 'matpower', '-o', str(tmp_path / 'x.m')]) == 2
    err = capsys.readouterr().err
    assert 'error: not a decision: ' in err and named in err, err
    assert not (tmp_path / 'x.m').exists()


@pytest.mark.slow
def test_a_case_that_is_not_the_decisions_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # The decision of ieee14_g1_unstable (loads doubled) against the case as ANDES bundles it.
    entry = next(e for e in SPLITS if e['name'] == 'ieee14_g1_unstable')
    decision_file = tmp_path / 'summary.json'
    islands = [{'island': k, 'buses': buses, 'shed_mw': shed, 'load_mw': 0.0, 'generation_mw': 0.0}
               for k, (buses, shed) in enumerate(zip(entry['expected_decision']['islands'],
                                                      entry['expected_decision']['island_shed_mw'], strict=True))]
    ss, outages = export.scenario_case(BAGS / entry['scenario'])
    ppc = export.matpower_case(ss, export.Decision(tuple(entry['expected_decision']['cut_branches']),
                                                   tuple(map(tuple, entry['expected_decision']['islands'])),
                                                   (0.0,) * len(islands), outages))
    for isl, (load_mw, gen_mw) in zip(islands, export.island_power_mw(ppc, [i['buses'] for i in islands]),
                                      strict=True):
        isl.update(load_mw=load_mw, generation_mw=gen_mw)
    decision = {'split': True, 'islands': islands, 'cut_branch_ids': entry['expected_decision']['cut_branches']}
    decision_file.write_text(json.dumps(decision))
    check_islands_as_decided(decision_file, decision, tmp_path, '--case', str(BAGS / entry['scenario']))
    out = tmp_path / 'plain.m'
    assert main(['export', str(decision_file), '--case', case_of(entry), '--to', 'matpower', '-o', str(out)]) == 2
    assert 'it is not the case the decision was made on' in capsys.readouterr().err
    assert not out.exists()


def test_help_teaches_every_input(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(['export', '--help'])
    text = capsys.readouterr().out
    for taught in ('summary.json', 'output_bag', 'result.json', 'testbed --all-unstable --json', '--scenario ',
                   'not a decision', '--case bags/'):
        assert taught in text, taught


def test_the_decisions_shed_is_exported_at_the_buses_it_names_and_nowhere_else() -> None:
    """A decision's remedial actions shed at chosen buses (core/remedial.py's largest loads); export follows them."""
    ss = export.load_case('ieee14/ieee14_full.xlsx')
    buses = tuple(int(b) for b in ss.Bus.idx.v)
    whole = export.matpower_case(ss, export.Decision((), (buses,), (0.0,)))
    pd = dict(zip(whole['bus'][:, 0].astype(int), whole['bus'][:, 2], strict=True))
    qd = dict(zip(whole['bus'][:, 0].astype(int), whole['bus'][:, 3], strict=True))
    shed = {3: 0.5 * pd[3], 4: 0.25 * pd[4]}
    summary = {'split': True, 'cut_branch_ids': [], 'islands': [{'buses': list(buses), 'shed_mw': sum(shed.values())}],
               'remedial_actions': {'shed_mw_by_bus': {str(b): mw for b, mw in shed.items()}, 'trip_generators': []}}
    got = export.matpower_case(ss, export.Decision.from_summary(summary))['bus']
    for row in got:
        b = int(row[0])
        assert row[2] == pytest.approx(pd[b] - shed.get(b, 0.0)), f'bus {b}: P'
        assert row[3] == pytest.approx(qd[b] * (1 - shed.get(b, 0.0) / pd[b]) if b in shed else qd[b]), f'bus {b}: Q'
    summary['remedial_actions']['shed_mw_by_bus'] = {'3': pd[3] + 1.0}
    with pytest.raises(export.ExportError, match='bus 3'):
        export.matpower_case(ss, export.Decision.from_summary(summary))
