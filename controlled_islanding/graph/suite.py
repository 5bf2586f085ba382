"""A regression run: many bags, each replayed on a fresh graph of its own, and one report with a row per bag.

Each bag gets a child process (`controlled-islanding replay BAG --json --isolate`) on a private domain, `jobs` at
a time: the nodes keep state a bag must not inherit (the breaker node's commanded breakers, the time of the last
input), and a graph's start-up is mostly one process's imports at a time, so two graphs keep two cores busier.
A row says the decision, its agreement with the manifest beside the bag, the bag's duration and the wall time.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from controlled_islanding.graph.processes import die_with_parent
from controlled_islanding.graph.summary import graph_failure, refused
from controlled_islanding.sim.manifest import entries_by_bag

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SuiteRun:
    """One replay of a regression run: its name (its results folder), its bag, and replay options for it."""

    name: str
    bag: Path
    options: tuple[str, ...] = ('--fast', '--no-figures')


def run_names(bags: list[Path]) -> list[str]:
    """Return a results folder name for each bag: its own name, with as many parent folders as tell it apart.

    Names are taken as given, not through symbolic links (a link is how a user names a copy), so site_a/run1 and
    site_b/run1 become site_a__run1 and site_b__run1, and bags/x stays x.

    Raises:
        ValueError: A bag is given twice.

    """
    parts = [Path(os.path.abspath(bag)).parts for bag in bags]
    depth = [1] * len(bags)
    while True:
        names = ['__'.join(p[-d:]) for p, d in zip(parts, depth, strict=True)]
        clashes = {n for n in names if names.count(n) > 1}
        if not clashes:
            return names
        deeper = [i for i, n in enumerate(names) if n in clashes and depth[i] < len(parts[i]) - 1]
        if not deeper:
            raise ValueError(f'bag {bags[names.index(next(iter(clashes)))]} is given twice')
        for i in deeper:
            depth[i] += 1


def replay_suite(runs: list[SuiteRun], base: Path, jobs: int = 2, quiet: bool = True,
                 hard_timeout_s: float = 600.0, done: Callable[[str, dict], None] = lambda name, row: None,
                 warm: bool = False) -> dict:
    """Replay each run on a fresh graph, in a child process on a private domain, `jobs` at a time; return one report.

    A child runs `controlled-islanding replay BAG --json --isolate --results base/<name> <options>`; its summary is
    base/<name>/summary.json. A child still running after hard_timeout_s is interrupted (it then stops its nodes).
    With `warm`, `jobs` long-lived workers (graph/worker.py) replay the runs instead, each bag on fresh nodes in a
    fresh Context in the worker's process; a worker that dies or runs past hard_timeout_s costs its bag, and
    another takes its place. `done(name, outcome)` is called as each run ends (a progress bar's step); `quiet`
    logs that at debug level.

    Returns:
        {'rows': one per run, in the given order, 'overall': speed, wall time, load average}.

    """
    base.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    begun = time.monotonic()
    finished: dict[str, dict] = {}

    def finish(name: str, outcome: dict) -> None:
        finished[name] = outcome
        (log.debug if quiet else log.info)('%s done (%d of %d)', name, len(finished), len(runs))
        done(name, outcome)

    (_warm_runs if warm else _process_runs)(runs, base, max(1, jobs), hard_timeout_s, finish)
    wall_s = time.monotonic() - begun
    manifests: dict[Path, dict] = {}  # each manifest read once: 0.2 s of CPU a read for ours
    rows = [_suite_row(run, base, finished.get(run.name, {}), manifests) for run in runs]
    bag_s = sum(r['bag_duration_s'] or 0.0 for r in rows)
    overall = {'runs': len(rows), 'ok': sum(1 for r in rows if r['ok']), 'jobs': jobs, 'warm': warm, 'wall_s': wall_s,
               'bag_duration_s': bag_s, 'speed_vs_real_time': bag_s / wall_s if wall_s > 0 else None,
               'serial_wall_s': sum(r['wall_s'] or 0.0 for r in rows), 'cpu_count': os.cpu_count(),
               'load_average_before': load_before, 'load_average_after': os.getloadavg(), 'results_dir': str(base)}
    return {'rows': rows, 'overall': overall}


def _process_runs(runs: list[SuiteRun], base: Path, jobs: int, hard_timeout_s: float,
                  finish: Callable[[str, dict], None]) -> None:
    """Replay each run in a `controlled-islanding replay` child process of its own, `jobs` at a time."""
    waiting = list(runs)
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    try:
        while waiting or running:
            while waiting and len(running) < jobs:
                run = waiting.pop(0)
                argv = [sys.executable, '-m', 'controlled_islanding.cli', 'replay', str(run.bag), '--json', '--isolate',
                        '--results', str(base / run.name), *run.options]
                with open(base / f'{run.name}.json', 'wb') as out, open(base / f'{run.name}.stderr', 'wb') as err:
                    running[run.name] = (subprocess.Popen(argv, stdout=out, stderr=err, stdin=subprocess.DEVNULL),
                                         time.monotonic())
            for name, (child, started) in list(running.items()):
                timed_out = child.poll() is None and time.monotonic() - started > hard_timeout_s
                if timed_out:
                    _interrupt(child)
                if child.poll() is not None:
                    del running[name]
                    finish(name, {'status': child.returncode, 'wall_s': time.monotonic() - started,
                                  'timed_out': hard_timeout_s if timed_out else None})
            time.sleep(0.05)
    finally:
        for child, _ in running.values():
            _interrupt(child)


class _Worker:
    """One warm worker process (graph/worker.py): its job now, and the answers it wrote so far."""

    def __init__(self, base: Path, number: int) -> None:
        self.log_file = base / f'worker-{number}.log'
        with open(self.log_file, 'ab') as err:
            self.child = subprocess.Popen([sys.executable, '-m', 'controlled_islanding.graph.worker'],
                                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err,
                                          preexec_fn=die_with_parent)
        os.set_blocking(self.child.stdout.fileno(), False)
        self.job: tuple[str, float] | None = None  # run name, when it was sent (monotonic s)
        self._buffer = b''

    def send(self, run: SuiteRun, base: Path) -> None:
        job = {'name': run.name, 'bag': str(run.bag), 'results': str(base / run.name), 'options': list(run.options),
               'stderr': str(base / f'{run.name}.stderr')}
        self.job = (run.name, time.monotonic())
        self.child.stdin.write((json.dumps(job) + '\n').encode())
        self.child.stdin.flush()

    def answers(self) -> list[dict]:
        with contextlib.suppress(BlockingIOError):
            while chunk := os.read(self.child.stdout.fileno(), 65536):
                self._buffer += chunk
        *lines, self._buffer = self._buffer.split(b'\n')
        return [json.loads(line) for line in lines if line.strip()]

    def log_tail(self, lines: int = 3) -> str:
        return '; '.join(self.log_file.read_text(errors='replace').strip().splitlines()[-lines:])


def _warm_runs(runs: list[SuiteRun], base: Path, jobs: int, hard_timeout_s: float,
               finish: Callable[[str, dict], None]) -> None:
    """Replay the runs on `jobs` warm workers, one bag at a time each; a dead or timed-out worker is replaced."""
    waiting = list(runs)
    workers: list[_Worker] = []
    started = 0
    try:
        while waiting or any(w.job for w in workers):
            while waiting and len(workers) < min(jobs, len(waiting) + sum(1 for w in workers if w.job)):
                workers.append(_Worker(base, started))
                started += 1
            for worker in workers:
                if worker.job is None and waiting:
                    try:
                        worker.send(waiting[0], base)
                        waiting.pop(0)
                    except BrokenPipeError:
                        worker.job = None  # it died idle; found below
            time.sleep(0.05)
            for worker in list(workers):
                for answer in worker.answers():
                    if 'name' in answer and worker.job is not None:
                        name, sent = worker.job
                        worker.job = None
                        finish(name, {'status': answer['status'], 'wall_s': time.monotonic() - sent,
                                      'timed_out': None})
                timed_out = (worker.job is not None and worker.child.poll() is None
                             and time.monotonic() - worker.job[1] > hard_timeout_s)
                if timed_out:
                    _interrupt(worker.child)
                if worker.child.poll() is not None:
                    workers.remove(worker)
                    if worker.job is not None:
                        name, sent = worker.job
                        finish(name, {'status': worker.child.returncode, 'wall_s': time.monotonic() - sent,
                                      'timed_out': hard_timeout_s if timed_out else None,
                                      'worker_died': None if timed_out else worker.child.returncode,
                                      'worker_log': worker.log_tail()})
    finally:
        for worker in workers:
            with contextlib.suppress(OSError):
                worker.child.stdin.close()  # an idle worker ends when its stdin does
        for worker in workers:
            with contextlib.suppress(subprocess.TimeoutExpired):
                worker.child.wait(timeout=5.0 if worker.job is None else 0.0)
            _interrupt(worker.child)


def _interrupt(child: subprocess.Popen) -> None:
    # SIGINT first: the child then stops its own nodes; SIGKILL only if it does not end.
    for action in (signal.SIGINT, signal.SIGKILL):
        if child.poll() is not None:
            return
        child.send_signal(action)
        with contextlib.suppress(subprocess.TimeoutExpired):
            child.wait(timeout=20.0)


def _suite_row(run: SuiteRun, base: Path, done: dict, manifests: dict[Path, dict]) -> dict:
    """Return one run's row: decision, agreement with the manifest, speed and wall time, or what went wrong."""
    row = {'name': run.name, 'bag': str(run.bag), 'results_dir': str(base / run.name),
           'exit_status': done.get('status'), 'wall_s': done.get('wall_s'), 'split': None, 'status': None,
           'cut_branch_ids': [], 'manifest': None, 'expected': None, 'refused': False,
           'bag_duration_s': None, 'play_wall_s': None, 'phases_s': {}, 'error': None, 'ok': False}
    summary_file = base / run.name / 'summary.json'
    if done.get('worker_died') is not None:
        row['error'] = (f'the warm worker replaying it died (exit status {done["worker_died"]}): '
                        f'{done.get("worker_log") or "no log"}')
        return row
    if done.get('timed_out'):
        row['error'] = f'timed out: still running after {done["timed_out"]:g} s of wall time, interrupted'
        return row
    if not summary_file.exists():
        err = base / f'{run.name}.stderr'
        tail = err.read_text(errors='replace').strip().splitlines()[-5:] if err.exists() else []
        row['error'] = '; '.join(tail) or ('not run' if not done else f'exit status {done.get("status")}')
        return row
    summary = json.loads(summary_file.read_text())
    rep = summary.get('replay') or {}
    row.update({'split': summary.get('split'), 'status': summary.get('status'),
                'cut_branch_ids': sorted(summary.get('cut_branch_ids', [])), 'phases_s': summary.get('phases_s', {}),
                'bag_duration_s': rep.get('bag_duration_s'), 'play_wall_s': rep.get('wall_s'),
                'error': graph_failure(summary) or (f'undecided requests {summary["undecided_requests"]}'
                                                    if summary.get('undecided_requests') else None)})
    if summary.get('trigger') == 'monitor' and not summary.get('requests') and row['error'] is None:
        # The monitor as the only source of requests, and it asked for none: the grid was left whole, a result
        # (a stable bag's right one), not a missing decision. Counted as failed, it made `replay --trigger monitor`
        # over held-out bags exit 1 on every bag that recovers.
        row['split'], row['status'] = False, 'NO_REQUEST'
    bag = run.bag.resolve()
    if bag.parent not in manifests:
        manifests[bag.parent] = entries_by_bag(bag.parent / 'index.yaml')
    entry = manifests[bag.parent].get(bag.name)
    if entry is not None and 'split' in entry.get('expected_decision', {}):
        expected = entry['expected_decision']
        row['expected'] = {'split': expected['split'], 'cut_branch_ids': sorted(expected.get('cut_branches', []))}
        row['manifest'] = ('agrees' if row['split'] == expected['split']
                           and row['cut_branch_ids'] == sorted(expected.get('cut_branches', [])) else 'DIFFERS')
    row['refused'] = refused(summary)
    row['ok'] = (row['error'] is None and row['split'] is not None and not row['refused']
                 and row['manifest'] != 'DIFFERS')
    return row


def failure_reason(row: dict) -> str | None:
    """Return why a row of replay_suite is not ok, in one line; None if it is ok."""
    if row['ok']:
        return None
    if row['error']:
        return row['error']
    if row['manifest'] == 'DIFFERS':
        def said(d: dict) -> str:
            return f'split, cut {", ".join(d["cut_branch_ids"]) or "none"}' if d['split'] else 'no split'

        return f'decision differs from the manifest: {said(row)}, the manifest says {said(row["expected"])}'
    if row.get('refused'):
        return f'the graph refused to decide: {row["status"]}'
    return 'no decision'


def render_suite(report: dict) -> str:
    """Return the regression run as a table, a row per bag, and its overall speed."""
    lines = [f'{"bag":<34} {"decision":<22} {"manifest":<8} {"bag s":>6} {"play s":>6} {"wall s":>6}  cut / error']
    for r in report['rows']:
        decision = r['status'] or ('no decision' if r['error'] is None else 'FAILED')
        cut = ', '.join(r['cut_branch_ids']) if r['split'] else '-'
        fmt = lambda x: f'{x:6.2f}' if x is not None else '     -'  # noqa: E731
        lines.append(f'{r["name"]:<34} {decision:<22} {r["manifest"] or "-":<8} {fmt(r["bag_duration_s"])} '
                     f'{fmt(r["play_wall_s"])} {fmt(r["wall_s"])}  {r["error"] or cut}')
    o = report['overall']
    lines.append(f'{o["ok"]} of {o["runs"]} bags ok; {o["bag_duration_s"]:.1f} s of bags in {o["wall_s"]:.1f} s '
                 f'of wall time, start-up included ({o["speed_vs_real_time"]:.2f}x real time; {o["jobs"]} graphs at '
                 f'once{", in warm workers" if o.get("warm") else ""}; {o["serial_wall_s"]:.1f} s one after another); '
                 f'load average {o["load_average_before"][0]:.2f} '
                 f'before, {o["load_average_after"][0]:.2f} after, {o["cpu_count"]} cores')
    failed = [(r['name'], failure_reason(r)) for r in report['rows'] if not r['ok']]
    if failed:
        lines.append(f'{len(failed)} failed:')
        lines += [f'  {name}: {why}' for name, why in failed]
    lines.append(f'results: {o["results_dir"]}')
    return '\n'.join(lines)


def junit_xml(report: dict, suite_name: str = 'controlled_islanding.replay') -> str:
    """Return the regression run as a JUnit XML report: one test case per bag, its reason on failure.

    The shape pytest's --junit-xml and launch_testing write (testsuites > testsuite > testcase, a <failure> with a
    message), so a CI that reads theirs reads this: a bag whose decision differs from the manifest, or that was
    refused, is a failure; one that could not be replayed (an error, a timeout, no decision) is an error.
    """
    from xml.etree import ElementTree as ET

    rows, o = report['rows'], report['overall']
    errors = [r for r in rows if not r['ok'] and (r['error'] or r['split'] is None)]
    root = ET.Element('testsuites')
    suite = ET.SubElement(root, 'testsuite', name=suite_name, tests=str(len(rows)),
                          failures=str(sum(1 for r in rows if not r['ok']) - len(errors)), errors=str(len(errors)),
                          skipped='0', time=f'{o["wall_s"]:.3f}')
    for r in rows:
        case = ET.SubElement(suite, 'testcase', classname=suite_name, name=r['name'], file=r['bag'],
                             time=f'{r["wall_s"] or 0.0:.3f}')
        why = failure_reason(r)
        if why is not None:
            kind = 'error' if r in errors else 'failure'
            ET.SubElement(case, kind, message=why, type=kind).text = f'{why}\nresults: {r["results_dir"]}'
        else:
            cut = ', '.join(r['cut_branch_ids']) if r['split'] else '-'
            ET.SubElement(case, 'system-out').text = (f'{r["status"]}; cut {cut}; manifest {r["manifest"] or "-"}; '
                                                      f'results: {r["results_dir"]}')
    ET.indent(root)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding='unicode') + '\n'
