"""`replay BAG BAG ...`: the regression run's report, without starting a node graph."""

from __future__ import annotations

import argparse

import pytest

from controlled_islanding.commands import replay
from controlled_islanding.graph.suite import SuiteRun, render_suite, replay_suite
from controlled_islanding.graph.summary import phases


def test_phases_follow_the_marks_in_order_and_add_up_to_the_total():
    marks = {'begun': 100.0, 'nodes_started': 100.5, 'armed': 103.0, 'wired': 110.0, 'decided': 113.0,
             'stopped': 113.5}
    report = {'play_begun_unix': 110.25, 'play_ended_unix': 112.0}
    got = phases(marks, report)
    assert list(got.values()) == [0.5, 2.5, 7.0, 0.25, 1.75, 1.0, 0.5, 13.5]
    assert sum(list(got.values())[:-1]) == pytest.approx(got['total'])
    # A replay that failed before playing has no player marks: the phases it reached, no made-up ones.
    assert phases({'begun': 1.0, 'nodes_started': 2.0}, {}) == {'set-up and node processes spawned': 1.0,
                                                                'total': 1.0}


def test_a_bag_that_cannot_be_replayed_is_a_failed_row_and_a_bag_given_twice_is_refused(tmp_path):
    not_a_bag = tmp_path / 'not_a_bag'
    not_a_bag.mkdir()
    (not_a_bag / 'metadata.yaml').write_text('this is not rosbag2 metadata\n')
    report = replay_suite([SuiteRun('broken', not_a_bag)], tmp_path / 'run', jobs=1)
    (row,) = report['rows']
    assert not row['ok'] and row['exit_status'] == 2 and 'cannot read' in row['error'], row
    assert report['overall']['ok'] == 0 and report['overall']['runs'] == 1
    assert 'FAILED' in render_suite(report).splitlines()[1]
    parser = argparse.ArgumentParser()
    replay.add_arguments(parser)
    args = parser.parse_args([str(not_a_bag), str(not_a_bag), '--results', str(tmp_path / 'cli')])
    with pytest.raises(replay.CliError, match='given twice'):
        replay.run(args)


def test_bags_of_one_name_in_different_folders_or_linked_under_other_names_each_get_a_folder_of_their_own():
    from pathlib import Path

    from controlled_islanding.graph.suite import run_names

    # A user's run lists bags as they are laid out: the same recording name at two sites, copies made as links.
    bags = [Path('bags/x/'), Path('/data/site_a/run1'), Path('/data/site_b/run1'), Path('/old/site_a/run1'),
            Path('links/kundur_copy1'), Path('links/kundur_copy2')]
    assert run_names(bags) == ['x', 'data__site_a__run1', 'site_b__run1', 'old__site_a__run1', 'kundur_copy1',
                               'kundur_copy2']


def _row(name: str, **fields: object) -> dict:
    row = {'name': name, 'bag': f'bags/{name}', 'results_dir': f'results/{name}', 'exit_status': 0, 'wall_s': 3.5,
           'split': True, 'status': 'SPLIT', 'cut_branch_ids': ['6-11'], 'manifest': 'agrees',
           'expected': {'split': True, 'cut_branch_ids': ['6-11']}, 'refused': False, 'bag_duration_s': 5.0,
           'play_wall_s': 1.0, 'phases_s': {}, 'error': None, 'ok': True}
    row.update(fields)
    return row


def test_the_junit_report_has_a_case_per_bag_and_says_why_each_failed_one_failed():
    from xml.etree import ElementTree as ET

    from controlled_islanding.graph.suite import junit_xml

    rows = [_row('agrees'),
            _row('differs', manifest='DIFFERS', ok=False, cut_branch_ids=['1-2', '3-4']),
            _row('slow', split=None, status=None, ok=False, error='timed out: still running after 600 s'),
            _row('refused', split=False, status='REFUSED_STALE', manifest=None, expected=None, refused=True,
                 ok=False)]
    report = {'rows': rows, 'overall': {'wall_s': 12.0}}
    root = ET.fromstring(junit_xml(report))
    (suite,) = root.findall('testsuite')
    assert (suite.get('tests'), suite.get('failures'), suite.get('errors')) == ('4', '2', '1')
    cases = {c.get('name'): c for c in suite.findall('testcase')}
    assert list(cases) == ['agrees', 'differs', 'slow', 'refused']
    assert cases['agrees'].find('failure') is None and cases['agrees'].find('error') is None
    assert cases['differs'].find('failure').get('message') == (
        'decision differs from the manifest: split, cut 1-2, 3-4, the manifest says split, cut 6-11')
    assert 'timed out' in cases['slow'].find('error').get('message')
    assert 'REFUSED_STALE' in cases['refused'].find('failure').get('message')
    assert float(cases['slow'].get('time')) == 3.5
    # The text report ends with the same reasons, so a long run's failures need no scrolling.
    text = render_suite({'rows': rows, 'overall': {
        'ok': 1, 'runs': 4, 'bag_duration_s': 20.0, 'wall_s': 12.0, 'speed_vs_real_time': 1.7, 'jobs': 2,
        'serial_wall_s': 14.0, 'load_average_before': (1.0,), 'load_average_after': (2.0,), 'cpu_count': 2,
        'results_dir': 'results'}})
    assert '3 failed:\n  differs: decision differs' in text


def test_replay_junit_xml_writes_the_report_of_bags_that_cannot_be_replayed(tmp_path, capsys):
    from xml.etree import ElementTree as ET

    for name in ('bad_a', 'bad_b'):
        (tmp_path / name).mkdir()
        (tmp_path / name / 'metadata.yaml').write_text('this is not rosbag2 metadata\n')
    parser = argparse.ArgumentParser()
    replay.add_arguments(parser)
    report_file = tmp_path / 'ci' / 'replay.xml'
    report_file.parent.mkdir()
    args = parser.parse_args([str(tmp_path / 'bad_a'), str(tmp_path / 'bad_b'), '--results', str(tmp_path / 'run'),
                              '--junit-xml', str(report_file), '--jobs', '2'])
    assert replay.run(args) == 1
    assert 'bad_a: ' in capsys.readouterr().out
    suite = ET.parse(report_file).getroot().find('testsuite')
    assert (suite.get('tests'), suite.get('errors')) == ('2', '2')
    for case in suite.findall('testcase'):
        assert 'cannot read the bag' in case.find('error').get('message'), ET.tostring(case)


def test_a_replay_ends_once_the_breaker_log_holds_every_decision_and_each_command_recorded_was_seen(tmp_path):
    import json
    from types import SimpleNamespace

    from controlled_islanding.graph.observer import Observation
    from controlled_islanding.graph.replay import breaker_done

    obs = Observation()
    obs.decisions = {f'req-{i}': (float(i), SimpleNamespace(decision_id=f'd{i}')) for i in (1, 2)}
    log = tmp_path / 'breaker_audit.jsonl'
    assert not breaker_done(log, obs)  # no log yet
    records = [{'event': 'start'}, {'event': 'command', 'decision_id': 'd1', 'authenticated': True,
                                    'commands': [{'command_id': 'd1/CB-1'}, {'command_id': 'd1/CB-2'}]}]
    log.write_text(''.join(json.dumps(r) + '\n' for r in records))
    assert not breaker_done(log, obs)  # d2 not handled yet
    log.write_text(log.read_text() + json.dumps({'event': 'no_split', 'decision_id': 'd2'}) + '\n{"event": "ref')
    assert not breaker_done(log, obs)  # handled, but d1's commands not seen; a half-written last line is skipped
    obs.commands = [(3.0, SimpleNamespace(command_id='d1/CB-1'))]
    assert not breaker_done(log, obs)
    obs.commands.append((3.1, SimpleNamespace(command_id='d1/CB-2')))
    assert breaker_done(log, obs)


def test_the_progress_bar_is_drawn_on_a_terminal_that_says_it_is_zero_by_zero(monkeypatch, caplog):
    """A CI runner's pseudo-terminal (or `script`) often reports 0 columns and 0 rows; tqdm then drew nothing."""
    import logging
    import os
    import select

    from controlled_islanding.commands import progress_bar

    leader, follower = os.openpty()  # a new pseudo-terminal is 0 x 0
    with open(follower, 'w', closefd=True) as terminal, open(leader, 'rb', closefd=True) as screen:
        monkeypatch.setattr('sys.stderr', terminal)
        caplog.set_level(logging.INFO, logger='controlled_islanding')  # as the command line sets it
        with progress_bar(3, 'replay', 'bag') as bar:
            bar.update()
            bar.refresh()
            terminal.flush()
            # The kernel hands written bytes to the leader side a moment later: a read at once raced it under load.
            drawn = ''
            while '1/3' not in drawn and select.select([screen], [], [], 5.0)[0]:
                drawn += os.read(screen.fileno(), 65536).decode(errors='replace')
    assert '1/3' in drawn and 'bag' in drawn, repr(drawn)


def test_a_monitor_run_that_asks_for_nothing_is_a_no_split_row_and_a_missed_separation_still_fails(tmp_path):
    """`replay --trigger monitor` over bags: a bag whose grid recovers gets no request, and that is its result."""
    import json

    from controlled_islanding.graph.suite import _suite_row

    def row(name: str, expected: dict | None, requests: list) -> dict:
        (tmp_path / 'run' / name).mkdir(parents=True)
        (tmp_path / 'run' / name / 'summary.json').write_text(json.dumps({
            'split': None, 'status': None, 'trigger': 'monitor', 'requests': requests, 'undecided_requests': [],
            'replay': {'bag_duration_s': 5.0, 'wall_s': 5.0}, 'phases_s': {}, 'decisions': [], 'restarts': [],
            'hangs': []}))
        bag = tmp_path / 'bags' / name
        bag.mkdir(parents=True)
        manifests = {bag.parent.resolve(): {} if expected is None else {name: {'expected_decision': expected}}}
        return _suite_row(SuiteRun(name, bag), tmp_path / 'run', {'status': 0, 'wall_s': 9.0}, manifests)

    quiet = row('recovers', None, [])
    assert quiet['ok'] and (quiet['split'], quiet['status']) == (False, 'NO_REQUEST'), quiet
    stable = row('stable', {'split': False}, [])
    assert stable['ok'] and stable['manifest'] == 'agrees'
    missed = row('separates', {'split': True, 'cut_branches': ['6-11']}, [])
    assert not missed['ok'] and missed['manifest'] == 'DIFFERS'
