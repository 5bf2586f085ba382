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

from controlled_islanding.graph.summary import graph_failure, refused
from controlled_islanding.sim.manifest import entry_for_bag

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SuiteRun:
    """One replay of a regression run: its name (its results folder), its bag, and replay options for it."""

    name: str
    bag: Path
    options: tuple[str, ...] = ('--fast', '--no-figures')


def replay_suite(runs: list[SuiteRun], base: Path, jobs: int = 2, quiet: bool = True,
                 hard_timeout_s: float = 600.0, done: Callable[[str, dict], None] = lambda name, row: None) -> dict:
    """Replay each run on a fresh graph, in a child process on a private domain, `jobs` at a time; return one report.

    A child runs `controlled-islanding replay BAG --json --isolate --results base/<name> <options>`; its summary is
    base/<name>/summary.json. A child still running after hard_timeout_s is interrupted (it then stops its nodes).
    `done(name, outcome)` is called as each run ends (a progress bar's step); `quiet` logs that at debug level.

    Returns:
        {'rows': one per run, in the given order, 'overall': speed, wall time, load average}.

    """
    base.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    begun = time.monotonic()
    waiting = list(runs)
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    finished: dict[str, dict] = {}
    try:
        while waiting or running:
            while waiting and len(running) < max(1, jobs):
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
                    finished[name] = {'status': child.returncode, 'wall_s': time.monotonic() - started,
                                      'timed_out': hard_timeout_s if timed_out else None}
                    (log.debug if quiet else log.info)('%s done (%d of %d)', name, len(finished), len(runs))
                    done(name, finished[name])
            time.sleep(0.05)
    finally:
        for child, _ in running.values():
            _interrupt(child)
    wall_s = time.monotonic() - begun
    rows = [_suite_row(run, base, finished.get(run.name, {})) for run in runs]
    bag_s = sum(r['bag_duration_s'] or 0.0 for r in rows)
    overall = {'runs': len(rows), 'ok': sum(1 for r in rows if r['ok']), 'jobs': jobs, 'wall_s': wall_s,
               'bag_duration_s': bag_s, 'speed_vs_real_time': bag_s / wall_s if wall_s > 0 else None,
               'serial_wall_s': sum(r['wall_s'] or 0.0 for r in rows), 'cpu_count': os.cpu_count(),
               'load_average_before': load_before, 'load_average_after': os.getloadavg(), 'results_dir': str(base)}
    return {'rows': rows, 'overall': overall}


def _interrupt(child: subprocess.Popen) -> None:
    # SIGINT first: the child then stops its own nodes; SIGKILL only if it does not end.
    for action in (signal.SIGINT, signal.SIGKILL):
        if child.poll() is not None:
            return
        child.send_signal(action)
        with contextlib.suppress(subprocess.TimeoutExpired):
            child.wait(timeout=20.0)


def _suite_row(run: SuiteRun, base: Path, done: dict) -> dict:
    """Return one run's row: decision, agreement with the manifest, speed and wall time, or what went wrong."""
    row = {'name': run.name, 'bag': str(run.bag), 'results_dir': str(base / run.name),
           'exit_status': done.get('status'), 'wall_s': done.get('wall_s'), 'split': None, 'status': None,
           'cut_branch_ids': [], 'manifest': None, 'expected': None, 'refused': False,
           'bag_duration_s': None, 'play_wall_s': None, 'phases_s': {}, 'error': None, 'ok': False}
    summary_file = base / run.name / 'summary.json'
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
    entry = entry_for_bag(run.bag.resolve())
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
                 f'once; {o["serial_wall_s"]:.1f} s one after another); load average {o["load_average_before"][0]:.2f} '
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
