"""testbed --oracle, the best found: its pure parts in milliseconds, and one small real search."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from controlled_islanding.evaluation.oracle import (
    Candidate,
    OracleError,
    Tried,
    dedupe,
    first_clearing_s,
    neighbour_groupings,
    partition_key,
    pick_best,
    pick_neighbours,
    request_times,
)
from controlled_islanding.sim.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]


def test_request_times_run_from_start_to_stop_both_included_at_most_one_step_apart():
    for start, stop, step in ((5.25, 5.8, 0.05), (1.2, 1.3, 0.05), (1.15, 1.533, 0.05), (1.3, 1.833, 0.2),
                              (1.1, 1.217, 1.0)):
        times = request_times(start, stop, step)
        gaps = np.diff(times)
        assert times[0] == start and math.isclose(times[-1], stop), times
        assert (gaps <= step + 1e-12).all() and np.allclose(gaps, gaps[0]), times
        assert len(times) == math.ceil((stop - start) / step - 1e-9) + 1  # no more times than the step needs
    assert len(request_times(5.25, 5.8, 0.05)) == 12
    assert request_times(1.2, 1.2, 0.05) == (1.2,)
    assert request_times(1.3, 1.1, 0.05) == (1.3,)  # a slip before the clearing: the clearing instant alone
    for bad in (0.0, -0.05, math.nan, math.inf):
        with pytest.raises(OracleError, match='positive'):
            request_times(1.0, 2.0, bad)


def test_the_window_starts_at_the_first_fault_clearing_on_several_systems_or_the_first_trip():
    expected = {'ieee39_g6g7_unstable': 5.25, 'kundur_bus9_unstable': 1.3, 'ieee39_case2_g3_unstable': 5.21,
                'ei33_bus101048_pair_unstable': 1.15, 'nordic44_bus6000_three_groups': 1.3,
                'pjm5bus_bus3_unstable': 1.12, 'ieee14_g1_unstable': 1.25, 'gbnetwork_bus73_unstable': 1.2}
    for name, clearing in expected.items():
        assert first_clearing_s(load_scenario(REPO / 'bags' / f'{name}.yaml')) == pytest.approx(clearing), name
    scenario = load_scenario(REPO / 'bags' / 'ieee39_g3_multitrip.yaml')
    assert first_clearing_s(replace(scenario, faults=())) == pytest.approx(5.21)  # its first trip
    with pytest.raises(OracleError, match='no fault and no trip'):
        first_clearing_s(replace(scenario, faults=(), trips=()))


def test_neighbours_of_the_truth_are_merges_nearest_moves_and_loosest_machines_alone():
    names = ['A', 'B', 'C', 'D', 'E', 'F']
    truth = [0, 0, 0, 1, 1, 2]
    dev = [0.0, 0.2, 1.5, 9.0, 9.4, 30.0]  # C lags its group towards D and E; F alone far away
    out = neighbour_groupings(names, truth, dev)
    assert out[0] == ('truth', 'truth', (0, 0, 0, 1, 1, 2))
    assert len({g for _, _, g in out}) == len(out)  # each grouping once
    merges = [g for kind, _, g in out if kind == 'merge']
    assert sorted(merges) == sorted([(0, 0, 0, 0, 0, 1), (0, 0, 0, 1, 1, 0), (0, 0, 0, 1, 1, 1)])
    moves = [(what, g) for kind, what, g in out if kind == 'move']
    # Nearest first by the truth's own complete-linkage distance: C to {D, E} is 7.9 rad, D to {A, B, C} 9.0.
    assert moves[:2] == [('C moved to the group of D+E (7.90 rad)', (0, 0, 1, 1, 1, 2)),
                         ('D moved to the group of A+B, ... (9.00 rad)', (0, 0, 0, 0, 1, 2))]
    assert len(moves) == 10  # A, B, C, D and E, each to either other group
    assert not any(what.startswith('F moved') for what, _ in moves)  # F alone: moving it is a merge
    alone = [(what, g) for kind, what, g in out if kind == 'alone']
    assert alone[0] == ('C alone (1.40 rad from its group on average)', (0, 0, 1, 2, 2, 3))
    two = neighbour_groupings(['G1', 'G2', 'G3'], [0, 0, 1], [0.0, 0.1, 7.0])
    assert not any(kind == 'merge' for kind, _, _ in two)  # two groups merged is no split, no action's row
    # G2 (6.9 rad from G3) moves before G1 (7.0); G1 alone and G2 alone are one grouping, three singletons.
    assert [g for _, _, g in two] == [(0, 0, 1), (0, 1, 1), (0, 1, 0), (0, 1, 2)]


def test_the_first_moves_and_machines_alone_that_give_a_cut_are_kept_trying_a_few_more_at_most():
    ranked = [('truth', 'truth', (0,)), ('merge', 'm1', (1,)), ('move', 'a', (2,)), ('move', 'b', (3,)),
              ('move', 'c', (4,)), ('move', 'd', (5,)), ('alone', 'x', (6,)), ('alone', 'y', (7,))]
    asked = []

    def gives_cut(what, groups):
        asked.append(what)
        return what not in {'a', 'm1', 'x'}

    kept = pick_neighbours(ranked, 2, 1, gives_cut)
    assert [what for _, what, _ in kept] == ['truth', 'm1', 'b', 'c', 'y']  # 'a' has no cut: 'c' takes its place
    assert asked == ['a', 'b', 'c', 'x', 'y']  # the truth and merges are kept unasked; 'd' never needed
    assert [w for _, w, _ in pick_neighbours(ranked, 1, 0, lambda w, g: False)] == ['truth', 'm1']
    asked.clear()
    pick_neighbours(ranked * 3, 1, 1, lambda w, g: asked.append(w) or False)
    assert asked.count('a') + asked.count('b') + asked.count('c') + asked.count('d') == 3  # 3 tries per kept one


def test_candidates_equal_up_to_island_numbering_are_run_once_with_their_sources_merged():
    a = {1: 0, 2: 0, 3: 1}
    b = {1: 1, 2: 1, 3: 0}  # a, numbered the other way
    c = {1: 0, 2: 1, 3: 1}
    assert partition_key(a) == partition_key(b) != partition_key(c)
    out = dedupe([Candidate(1.0, a, ['milp of truth']), Candidate(1.0, b, ['spectral of truth']),
                  Candidate(1.0, a, ['graph', 'milp of truth']), Candidate(1.05, a, ['milp of truth']),
                  Candidate(1.0, c, ['milp of A moved']), Candidate(1.0, a, ['graph'], topology=('1-2',))])
    assert [(x.request_s, x.sources) for x in out] == [
        (1.0, ['milp of truth', 'spectral of truth', 'graph']), (1.05, ['milp of truth']),
        (1.0, ['milp of A moved']), (1.0, ['graph'])]


def test_the_best_serves_the_most_ties_go_to_no_action_and_a_failed_run_is_never_picked():
    def tried(served, request_s, n_cut=1, sources=('x',)):
        return Tried(Candidate(request_s, None if request_s is None else {1: 0}, list(sources)), served, 1000.0,
                     tuple(f'{i}-{i + 1}' for i in range(n_cut if request_s is not None else 0)))

    none = tried(0.0, None)
    assert pick_best([]) is None and pick_best([tried(None, 1.0)]) is None
    assert pick_best([none, tried(0.0, 1.0)]) is none  # a cut that serves no more than doing nothing
    assert pick_best([none, tried(None, 1.0), tried(10.0, 1.2)]).served_mw == 10.0
    early, late = tried(50.0, 1.1), tried(50.0, 1.3)
    assert pick_best([late, early]) is early
    few = tried(50.0, 1.3, n_cut=1)
    assert pick_best([tried(50.0, 1.1, n_cut=3), few]) is few
    assert pick_best([tried(49.0, 1.0), tried(51.0, 1.5)]).served_mw == 51.0


def test_a_candidate_that_cannot_beat_the_best_so_far_is_not_run():
    from controlled_islanding.evaluation.oracle import run_candidate
    from controlled_islanding.sim.andes_sim import prepare_case
    from controlled_islanding.sim.closed_loop import LoopConfig

    scenario = load_scenario(REPO / 'bags' / 'kundur_bus9_unstable.yaml')
    grid = prepare_case(scenario).grid
    west = {1, 2, 5, 6, 7}  # Kundur's area 1: G1 and G2 (buses 1, 2) short of nothing, area 2 sheds
    islands = {b: 0 if b in west else 1 for b in grid.buses}
    outcome, cut, bound = run_candidate(scenario, grid, islands, 1.5, 'oracle', LoopConfig(), beat_mw=1e9)
    total = sum(ld.p_mw for ld in grid.loads)
    assert outcome is None and cut and 0 < bound <= total  # no ANDES run: it could serve at most bound
    outcome, cut, _ = run_candidate(scenario, grid, dict.fromkeys(grid.buses, 0), 1.5, 'oracle', LoopConfig())
    assert outcome is None and cut == ()  # one island: nothing to open, nothing run


@pytest.mark.slow
def test_a_small_search_on_kundur_runs_every_candidate_to_one_end_and_reports_the_best():
    """Two request times, the truth's MILP and spectral cuts and the graph's: three short ANDES runs of Kundur.

    Shortened (to 3 s, 1 s after the cut) so that the path runs in CI in seconds; then a second search, as the
    testbed makes for a variant of one simulation, reuses every run.
    """
    from controlled_islanding.evaluation.oracle import OracleSettings, search
    from controlled_islanding.evaluation.testbed_report import gap_lines, table_rows
    from controlled_islanding.sim.closed_loop import LoopConfig

    scenario = replace(load_scenario(REPO / 'bags' / 'kundur_bus9_unstable.yaml'), end_s=3.0, request_s=1.6)
    config = LoopConfig(run_after_s=1.0)
    graph = {b: 0 if b in {1, 2, 5, 6, 7} else 1 for b in range(1, 11)}  # Kundur's two areas, cut at 7-8
    said, runs = [], {}
    found = search(scenario, config, OracleSettings(max_step_s=1.0, max_moves=0, max_alone=0), graph_islands=graph,
                   runs=runs, say=said.append)
    assert found.first_pole_slip_s is not None and 1.3 < found.first_pole_slip_s < 2.0
    assert found.times_s == (1.3, found.first_pole_slip_s) and found.step_s == found.first_pole_slip_s - 1.3
    ran = [t for t in found.tried if t.outcome is not None]
    assert ran[0].candidate.sources == ['no action'] and len(ran) == 3 == found.runs_made
    assert sorted(ran[1].candidate.sources) == ['graph', 'milp of truth', 'spectral of truth']  # one cut, once a time
    for t in ran:  # every run ends at one time, at least run_after_s after its cut
        assert t.outcome.t_s[-1] == pytest.approx(found.end_s, abs=scenario.step_s)
        if t.candidate.request_s is not None:
            assert t.outcome.opened_s == pytest.approx(t.candidate.request_s + 0.05, abs=scenario.step_s)
            assert t.outcome.request_s == t.candidate.request_s
    assert found.end_s == 3.0 >= found.first_pole_slip_s + 1.0
    best = found.best
    assert best is not None and best.served_mw == max(t.served_mw for t in ran if t.served_mw is not None)
    assert any(' oracle 2/2: request' in s for s in said)  # progress, one line per candidate
    summary = json.loads(json.dumps(found.summary(), default=str))
    assert summary['label'] == 'oracle' and summary['load_served_mw'] == pytest.approx(best.served_mw)
    assert summary['request_s'] == best.candidate.request_s
    assert summary['cut_branch_ids'] == list(best.cut_branch_ids)
    assert summary['search']['request_times'] == 2 and summary['search']['runs'] == 3
    by_time = summary['search']['served_by_request_s']
    assert [t for t, _ in by_time] == list(found.times_s)  # how late a request could come and serve as much
    assert max(mw for _, mw in by_time if mw is not None) == pytest.approx(best.served_mw)

    again = search(scenario, config, OracleSettings(max_step_s=1.0, max_moves=0, max_alone=0), runs=runs,
                   say=said.append)
    assert again.runs_made == 0 and again.runs_reused == 3 and again.best.served_mw == best.served_mw

    result = {'scenario': scenario.name, 'runs': {'oracle': summary, 'no action': ran[0].outcome.summary()}}
    assert [r[1] for r in table_rows([result])] == ['no action', 'oracle']
    (line,) = gap_lines([result])
    assert f'best found {best.served_mw:.0f}' in line and '2 request times 1.300' in line, line
    assert 'dtw not run' in line and 'no action ' in line, line


def test_the_gap_to_the_best_found_is_stated_for_every_run_and_a_failed_run_is_undetermined():
    from types import SimpleNamespace

    from controlled_islanding.evaluation.testbed_report import gap_lines, markdown, table_rows

    def run(served, failed=None, **extra):
        isl = [{'island': 0, 'survived': served is not None and served > 0, 'why_not': [], 'generators': ['G1'],
                'load_mw': 1000.0, 'shed_mw': 0.0}]
        return {'cut_branch_ids': ['1-2'], 'islands': isl, 'load_lost_mw': None if failed else 1000.0 - served,
                'shed_mw': 0.0, 'f_nadir_hz': 59.0, 'f_peak_hz': 60.5, 'v_min_pu': 0.9, 'request_to_opening_s': 0.05,
                'simulation_failed': failed, 'load_served_mw': None if failed else served,
                'load_served_pct': None if failed else served / 10.0, 'pre_fault_load_mw': 1000.0, **extra}

    search = {'window_s': [1.3, 1.8], 'step_s': 0.05, 'request_times': 11, 'end_s': 4.8, 'first_pole_slip_s': 1.8,
              'groupings': [{'what': 'truth', 'groups': [['G1'], ['G2']]}], 'candidates': 20, 'runs': 21,
              'pruned': 2, 'failed': [], 'wall_s': 600.0}
    oracle = run(800.0, request_s=1.45, sources=['milp of truth'], search=search)
    result = {'scenario': 'kundur_x', 'events': [], 'runs': {
        'no action': run(0.0), 'dtw': run(500.0), 'milp': run(None, failed='simulation failed at 1.700 s: ANDES'),
        'oracle': oracle}}
    (line,) = gap_lines([result])
    assert 'best found 800 (80.0 %), cut 1-2 at request 1.450 s (milp of truth)' in line
    assert '11 request times 1.300 .. 1.800 s every 50 ms' in line and '10.0 min wall' in line
    assert 'no action 800 MW (80.0 % of the pre-fault load)' in line and 'dtw 300 MW (30.0 %' in line
    assert 'milp undetermined (its simulation failed)' in line
    result['runs']['dtw'] = run(900.0)  # the graph's request lies outside the searched window: it can do better
    assert 'dtw none, it serves 100 MW more than the search found' in gap_lines([result])[0]
    assert [r[1] for r in table_rows([result])] == ['no action', 'dtw', 'milp', 'oracle']
    assert table_rows([result])[-1][2] == '1-2 at request 1.450 s'
    args = SimpleNamespace(breaker_operating_s=0.05, shed_delay_s=0.2, run_after_s=3.0)
    page = markdown([result], args, [], Path('docs/testbed.md'), 'controlled-islanding testbed --oracle')
    assert 'The best found (`oracle`) and the gap of each run to it:' in page and 'no graph latency' in page
    assert 'no graph latency' not in markdown([dict(result, runs={'dtw': run(500.0)})], args, [],
                                              Path('docs/testbed.md'), 'controlled-islanding testbed')
