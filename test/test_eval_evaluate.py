"""evaluate: the paper's two cases with every method, the MILP as yardstick, every committed bag, clear errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from controlled_islanding.cli import main
from controlled_islanding.evaluation.cases import PAPER_CASES, evaluate_paper_case
from controlled_islanding.evaluation.report import format_case
from controlled_islanding.sim.manifest import manifest_entries

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / 'bags'


def _committed_bags() -> list[Path]:
    return [BAGS / entry['bag'] for entry in manifest_entries(BAGS / 'index.yaml')]


@pytest.mark.parametrize('name', sorted(PAPER_CASES))
def test_paper_case_has_every_method_and_milp_is_never_worse(name):
    case = evaluate_paper_case(name)
    rows = {r.method: r for r in case.rows}
    spectral = rows['dtw (paper groups) + spectral']
    exact = rows['dtw (paper groups) + MILP optimum']
    assert {'correlation (paper groups) + spectral', 'community detection'} <= set(rows)
    assert spectral.decision is not None and exact.decision is not None
    assert exact.note == '' and exact.gap_pct == pytest.approx(0.0, abs=1e-9)
    assert exact.decision.disrupted_mw <= spectral.decision.disrupted_mw + 1e-6
    unrefined = rows['dtw (paper groups) + spectral, unrefined (the paper alone)']
    # The refinement only ever moves a bus when that lowers eq. 9.
    assert spectral.decision.disrupted_mw <= unrefined.decision.disrupted_mw + 1e-6
    for row in case.rows:
        if row.decision is not None and row.optimum_mw is not None:
            # No partition under the same groups can beat the proven optimum.
            assert row.decision.disrupted_mw >= row.optimum_mw - 1e-6
    table = format_case(case)
    for row in case.rows:
        assert row.method in table
    assert 'gap to MILP optimum (%)' in table and 'load to shed (MW)' in table


def test_paper_case1_matches_the_papers_table_iv_shape():
    rows = {r.method: r for r in evaluate_paper_case('paper_case1').rows}
    dtw = rows['dtw (paper groups) + spectral'].decision
    corr = rows['correlation (paper groups) + spectral'].decision
    # Table IV: the DTW groups give 1 line cut and 2 islands with no shedding; correlation 2 lines, 3 islands, shedding.
    assert (len(dtw.cut_branches), dtw.n_islands, sum(dtw.island_shed_mw)) == (1, 2, 0.0)
    assert (len(corr.cut_branches), corr.n_islands) == (2, 3) and sum(corr.island_shed_mw) > 0.0


def test_no_bag_is_an_error(capsys):
    assert main(['evaluate']) == 2
    assert 'give at least one BAG' in capsys.readouterr().err


def test_missing_and_unreadable_bags_are_errors(tmp_path, capsys):
    assert main(['evaluate', str(tmp_path / 'nope'), '--out', str(tmp_path / 'o')]) == 2
    assert 'no such bag' in capsys.readouterr().err
    broken = tmp_path / 'broken'
    broken.mkdir()
    (broken / 'metadata.yaml').write_text('this: [is not a bag\n')
    assert main(['evaluate', str(broken), '--out', str(tmp_path / 'o')]) == 2
    err = capsys.readouterr().err
    assert 'cannot read' in err and str(broken) in err


def test_bag_without_pmu_frames_is_an_error(tmp_path, capsys):
    source = next((b for b in _committed_bags() if b.is_dir()), None)
    if source is None:
        pytest.fail('no committed bag listed in bags/index.yaml to strip PMU frames from')
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    from controlled_islanding.wire import topics
    from controlled_islanding.wire.interfaces import typestore

    stripped = tmp_path / 'no_frames'
    store = typestore()
    with AnyReader([source], default_typestore=store) as reader, \
            Writer(stripped, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        out = {}
        for conn in reader.connections:
            if conn.topic != topics.PMU_FRAMES:
                out[conn.id] = writer.add_connection(conn.topic, conn.msgtype, msgdef=conn.msgdef.data,
                                                     rihs01=conn.digest)
        for conn, stamp, raw in reader.messages(connections=[c for c in reader.connections if c.id in out]):
            writer.write(out[conn.id], stamp, raw)
    assert main(['evaluate', str(stripped), '--out', str(tmp_path / 'o')]) == 2
    assert f'no {topics.PMU_FRAMES} messages' in capsys.readouterr().err


@pytest.mark.parametrize('study', ['--k-rules', '--observability'])
def test_a_generator_without_a_pmu_is_an_error_naming_the_bag_in_every_study(tmp_path, capsys, study):
    """The k-rule study and the observability sweep refuse such a bag as the tables do, with no traceback."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    from controlled_islanding.wire import topics
    from controlled_islanding.wire.interfaces import typestore

    source = next((b for b in _committed_bags() if b.is_dir()), None)
    if source is None:
        pytest.fail('no committed bag listed in bags/index.yaml to take a PMU from')
    blind = tmp_path / 'one_pmu_short'
    store = typestore()
    dropped = set()
    with AnyReader([source], default_typestore=store) as reader, \
            Writer(blind, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        # Each topic keeps the definition its bag was recorded with: raw messages are copied as they are.
        out = {c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest)
               for c in reader.connections}
        for conn, stamp, raw in reader.messages():
            if conn.topic == topics.PMU_FRAMES:
                msg = store.deserialize_cdr(raw, conn.msgtype)
                dropped.add(msg.measurements[0].station_id)
                msg.measurements = msg.measurements[1:]
                raw = store.serialize_cdr(msg, conn.msgtype)
            writer.write(out[conn.id], stamp, raw)
    assert len(dropped) == 1
    assert main(['evaluate', str(blind), study, str(tmp_path / 'page.md')]) == 2
    err = capsys.readouterr().err
    assert str(blind) in err and 'coherency needs every generator' in err, err
    assert 'Traceback' not in err
    assert not (tmp_path / 'page.md').exists()


# The MILP optimum and the figures of a 2224-bus case take minutes, too long for the suite: it evaluates the bags
# of cases up to this many buses, and `controlled-islanding evaluate` (docs/evaluation.md) every bag.
EVALUATED_MAX_BUSES = 100


@pytest.mark.slow
def test_every_small_case_bag_gets_a_table_and_figures(tmp_path, capsys):
    from controlled_islanding.wire.bagdata import load_bag

    # One bag per case (the first listed): the rows and figures do not depend on the scenario; every bag is in
    # docs/evaluation.md, generated by `controlled-islanding evaluate`.
    by_case: dict[str, Path] = {}
    for b in _committed_bags():
        if b.is_dir() and len((grid := load_bag(b).grid).buses) <= EVALUATED_MAX_BUSES:
            by_case.setdefault(grid.name, b)
    bags = list(by_case.values())
    assert bags, f'bags/index.yaml lists no committed bag of a case with at most {EVALUATED_MAX_BUSES} buses'
    out = tmp_path / 'figures'
    assert main(['evaluate', *map(str, bags), '--json', '--out', str(out)]) == 0
    cases = json.loads(capsys.readouterr().out)
    assert [c['case'] for c in cases] == [b.name for b in bags]
    for case in cases:
        methods = [r['method'] for r in case['rows']]
        assert methods == ['dtw + spectral', 'correlation + spectral', 'dtw + spectral, unrefined (the paper alone)',
                           'community detection', 'dtw + MILP optimum']
        for key in ('rotor_angles', 'dtw_distance', 'shedding', 'network_dtw_spectral'):
            assert Path(case['figures'][key]).stat().st_size > 10_000
        exact = case['rows'][-1]['decision']
        spectral = case['rows'][0]['decision']
        assert exact['disrupted_mw'] <= spectral['disrupted_mw'] + 1e-6


def _bag(name: str) -> Path:
    path = BAGS / name
    if not path.is_dir():
        pytest.fail(f'bag {name} is not committed')
    return path


def test_detection_lead_is_measured_against_the_first_pole_slip():
    from controlled_islanding.evaluation import coherency_rules as study
    from controlled_islanding.wire.bagdata import load_bag

    entries = study.manifest_entries(BAGS / 'index.yaml')
    unstable = study.scenario_from_bag(load_bag(_bag('ieee39_g6g7_unstable')), entries['ieee39_g6g7_unstable'])
    assert unstable.truth_k == 2 and unstable.first_pole_slip_s is not None
    det = study.detect(unstable, rule='separation', window_s=3.0, max_groups=4, dtw_band=30, step_s=0.5)
    assert det.found_s is not None and det.kept_from_s is not None
    assert det.lead_s == pytest.approx(unstable.first_pole_slip_s - det.found_s)
    # Nothing separates before the fault (5 s), so nothing can be found before it.
    assert det.found_s > 5.0
    stable = study.scenario_from_bag(load_bag(_bag('ieee39_paper_case2')), entries['ieee39_paper_case2'])
    assert study.detect(stable, rule='separation', window_s=3.0, max_groups=4, dtw_band=30,
                        step_s=0.5).false_split_s is None
    # The relative silhouette rule does split this stable case: the sweep can tell rules apart.
    assert study.detect(stable, rule='silhouette', window_s=3.0, max_groups=4, dtw_band=30,
                        step_s=0.5).false_split_s is not None


def test_decimation_effect_counts_what_block_means_change():
    from controlled_islanding.evaluation import coherency_rules as study
    from controlled_islanding.harness.benchmarks import decimation_effect
    from controlled_islanding.wire.bagdata import load_bag

    entries = study.manifest_entries(BAGS / 'index.yaml')
    scenario = study.scenario_from_bag(load_bag(_bag('ieee39_g6g7_unstable')), entries['ieee39_g6g7_unstable'])
    short = study.Scenario(scenario.name, scenario.source, scenario.generator_names, scenario.t_s[:420],
                           scenario.angles_rad[:, :420], 6.5, scenario.truth, scenario.first_pole_slip_s)
    r = decimation_effect(short, 10.0, step_s=0.5)
    assert r['factor'] == 6 and r['windows'] == 420 - 180 and 0 <= r['differ'] <= r['windows']
    assert r['right_at_request'] == (True, True)
    assert all(d.found_s is not None for d in r['detection']) and len(r['fit_s']) == 2
    # Decimating to the stream's own rate is no decimation: nothing can differ.
    same = decimation_effect(short, 60.0, step_s=0.5)
    assert same['factor'] == 1 and same['differ'] == 0


def test_k_rules_page_compares_every_rule(tmp_path, capsys):
    from controlled_islanding.core.k_rules import RULES

    page = tmp_path / 'rules.md'
    bags = [str(_bag('ieee39_paper_case2')), str(_bag('ieee39_g6g7_unstable'))]
    assert main(['evaluate', *bags, '--k-rules', str(page), '--lead-step-s', '1.0']) == 0
    text = page.read_text()
    assert text.startswith('# Choosing k') and 'do not edit by hand' in text
    header = next(line for line in text.splitlines() if line.startswith('| scenario | truth k |'))
    assert all(rule in header for rule in RULES)
    row = next(line for line in text.splitlines() if line.startswith('| ieee39_g6g7_unstable | 2 |'))
    assert row.count('right') + row.count('WRONG') == len(RULES)
    assert 'ieee39_paper_case2' in capsys.readouterr().out


@pytest.mark.slow
def test_closed_loop_column_runs_each_cut_once_in_andes_and_shows_what_a_split_does(tmp_path):
    """Kundur, area 1 slipping: its true groups' cut keeps each area in step, no action does not."""
    from controlled_islanding.core.islanding import decide
    from controlled_islanding.evaluation.cases import CaseReport, MethodResult, closed_loop_outcomes
    from controlled_islanding.evaluation.report import table_rows
    from controlled_islanding.sim.closed_loop import LoopConfig
    from controlled_islanding.wire.bagdata import load_bag

    name = 'kundur_bus9_unstable'
    entry = next(e for e in manifest_entries(BAGS / 'index.yaml') if e.get('bag') == name)
    bag = load_bag(BAGS / name)
    grid = bag.grid_at(float(bag.request_t_s[0]) + 1e-9)
    truth = {g: k for k, names in enumerate(entry['truth_groups']) for g in names}
    split, whole = decide(grid, truth), decide(grid, dict.fromkeys(truth, 0))
    case = CaseReport(name=name, source=name, grid=grid, truth_groups=truth,
                      rows=[MethodResult('dtw + spectral', truth, split, 0.0),
                            MethodResult('community detection', dict.fromkeys(truth, 0), whole, 0.0),
                            MethodResult('dtw + MILP optimum', truth, split, 0.0)])
    # Simulated to 2.5 s, not the scenario's 4 s, to keep the suite short: 0.9 s after the cut shows the slip.
    scenario = yaml.safe_load((BAGS / entry['scenario']).read_text()) | {'end_s': 2.5}
    (tmp_path / 'kundur.yaml').write_text(yaml.safe_dump(scenario))
    closed_loop_outcomes(case, tmp_path / 'kundur.yaml', LoopConfig(run_after_s=0.5))
    dtw, none, milp = (row.closed_loop for row in case.rows)
    assert none is case.no_action and milp is dtw  # one run per distinct cut
    assert not none['all_survived'] and none['islands'][0]['max_pair_swing_rad'] > math.pi
    assert dtw['opened_s'] == pytest.approx(float(bag.request_t_s[0]) + 0.05, abs=1 / 120 + 1e-6)
    assert sorted(tuple(i['generators']) for i in dtw['islands']) == [('GENROU_1', 'GENROU_2'),
                                                                       ('GENROU_3', 'GENROU_4')]
    assert all(i['max_pair_swing_rad'] < math.pi for i in dtw['islands'])
    cells = table_rows(case)
    assert cells[0][-1].startswith(f'{sum(i["survived"] for i in dtw["islands"])}/2')
    assert cells[1][-1].startswith('0/1 (island 0: machines')


def test_predictors_page_compares_the_predictors_frame_by_frame(tmp_path, capsys):
    page = tmp_path / 'prediction.md'
    bags = [str(_bag('ieee39_paper_case2')), str(_bag('ieee39_g6g7_unstable'))]
    assert main(['evaluate', *bags, '--predictors', str(page)]) == 0
    text = page.read_text()
    assert text.startswith('# Predicting the separation') and 'do not edit by hand' in text
    row = next(line for line in text.splitlines() if line.startswith('| ieee39_g6g7_unstable |'))
    assert row.count('right') >= 2, row  # SIME and the forecast name the final groups before the slip
    quiet = next(line for line in text.splitlines() if line.startswith('| ieee39_paper_case2 |'))
    assert quiet.count('quiet') == 3, quiet
    assert '## The predictor chosen' in text and 'ieee39_g6g7_unstable' in capsys.readouterr().out
