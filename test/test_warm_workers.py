"""Warm regression workers: bag after bag in one process, each on fresh nodes in a fresh Context, nothing shared."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import pytest

from controlled_islanding.graph.replay import bag_topics
from controlled_islanding.graph.suite import SuiteRun, replay_suite
from controlled_islanding.graph.worker import replay_options
from controlled_islanding.sim.manifest import manifest_entries
from controlled_islanding.wire import topics

REPO = Path(__file__).resolve().parents[1]
BAGS = {e['name']: REPO / 'bags' / e['bag'] for e in manifest_entries() if (REPO / 'bags' / e['bag']).exists()}
FAST = ('--fast', '--no-figures', '--no-record')


def test_a_worker_takes_the_replay_options_a_regression_run_passes_and_refuses_the_others():
    assert replay_options(['--fast', '--rate', '2', '--disarmed', '--no-record', '--timeout', '30']) == {
        'fast': True, 'rate': 2.0, 'timeout_s': 30.0, 'probe_hz': 0.0, 'arm': False, 'record': False,
        'figures': True, 'estimator': None}
    with pytest.raises(Exception, match='does not take --hosts'):
        replay_options(['--hosts', 'pdc,control'])


def _decision(summary: dict) -> dict:
    return {'split': summary['split'], 'status': summary['status'], 'cut': sorted(summary['cut_branch_ids']),
            'islands': {frozenset(i['buses']) for i in summary['islands']},
            'groups': summary['coherent_groups'].get('groups'),
            'commands': sorted(c['branch_id'] for c in summary['breaker_commands']),
            'disrupted_mw': round(summary['disrupted_mw'], 3) if summary['disrupted_mw'] is not None else None}


def _audit(summary: dict) -> list[dict]:
    path = Path(summary['results_dir']) / 'breaker_audit.jsonl'
    return [json.loads(line) for line in path.read_text().splitlines()]


def _kill_worker_when(folder: Path, stop: threading.Event) -> None:
    """SIGKILL this process's warm worker (by its PID) once it has begun the replay that makes `folder`."""
    while not stop.is_set():
        if folder.exists():
            for stat in Path('/proc').glob('[0-9]*/stat'):
                try:
                    ppid = int(stat.read_text().rsplit(')', 1)[1].split()[1])
                    cmdline = (stat.parent / 'cmdline').read_bytes()
                except (OSError, IndexError, ValueError):
                    continue
                if ppid == os.getpid() and b'controlled_islanding.graph.worker' in cmdline:
                    os.kill(int(stat.parent.name), signal.SIGKILL)
                    return
        time.sleep(0.05)


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.skipif(not {'kundur_bus9_unstable', 'ieee14_g1_unstable'} <= set(BAGS), reason='bags not present')
def test_bag_after_bag_in_one_worker_decides_and_commands_as_each_bag_alone_and_a_dead_worker_costs_one_bag(
        tmp_path):
    kundur, ieee14 = BAGS['kundur_bus9_unstable'], BAGS['ieee14_g1_unstable']
    stop = threading.Event()
    killer = threading.Thread(target=_kill_worker_when, args=(tmp_path / 'run' / 'killed', stop), daemon=True)
    killer.start()
    try:
        # One worker at a time: the first dies in 'killed'; its successor replays a, b and c, one after the other.
        not_a_bag = tmp_path / 'not_a_bag'
        not_a_bag.mkdir()
        (not_a_bag / 'metadata.yaml').write_text('this is not rosbag2 metadata\n')
        report = replay_suite([SuiteRun('killed', ieee14, FAST), SuiteRun('a', ieee14, FAST),
                               SuiteRun('b', kundur, FAST), SuiteRun('c', kundur, FAST),
                               SuiteRun('broken', not_a_bag, FAST)], tmp_path / 'run', jobs=1, warm=True)
    finally:
        stop.set()
    alone = replay_suite([SuiteRun('alone', kundur, FAST)], tmp_path / 'alone', jobs=1, warm=True)
    rows = {r['name']: r for r in report['rows']}
    assert not rows['killed']['ok'] and 'warm worker replaying it died (exit status -9)' in rows['killed']['error']
    assert all(rows[n]['ok'] for n in 'abc'), [rows[n]['error'] for n in 'abc']
    # A bag the player cannot read is a failed row that says so in one line, and the worker goes on.
    assert not rows['broken']['ok'] and 'bag_player failed: bag_player could not start: cannot read the bag: ' in \
        rows['broken']['error'] and 'Traceback' not in rows['broken']['error'], rows['broken']['error']
    worker_logs = {p.name: p.read_text() for p in (tmp_path / 'run').glob('worker-*.log')}
    assert len(worker_logs) == 2 and all(f'replaying {n}' in worker_logs['worker-1.log'] for n in 'abc')

    summaries = {n: json.loads((tmp_path / 'run' / n / 'summary.json').read_text()) for n in 'abc'}
    (alone_row,) = alone['rows']
    by_itself = json.loads((Path(alone_row['results_dir']) / 'summary.json').read_text())
    # Kundur after IEEE 14, and after itself (whose breakers a leaked breaker state would refuse to open again):
    # the decision and the commands it gets alone in a fresh worker.
    assert _decision(summaries['b']) == _decision(by_itself) and _decision(summaries['c']) == _decision(by_itself)
    assert _decision(by_itself)['commands'], 'the Kundur bag commands its cut'
    for name in 'bc':
        records = _audit(summaries[name])
        assert [r['event'] for r in records] == [r['event'] for r in _audit(by_itself)]
        assert {d['request_id'] for d in summaries[name]['decisions']} == {
            d['request_id'] for d in by_itself['decisions']}
    assert summaries['b']['breaker_commands'][0]['command_id'] != summaries['c']['breaker_commands'][0]['command_id']
    # A composed graph's summary holds what each node counted once it had taken every message of the bag (read
    # from the nodes after the play, not their last /diagnostics): every frame and the snapshot, nothing lost.
    for name, bag in (('a', ieee14), ('b', kundur), ('c', kundur)):
        ingestion = summaries[name]['diagnostics']['/pmu_ingestion']
        assert int(ingestion['received']) == bag_topics(bag)[topics.PMU_FRAMES] + 1, (name, ingestion)
        assert ingestion['lost./pmu/frames'] == '0' and ingestion['missing_frames'] == '0', (name, ingestion)
