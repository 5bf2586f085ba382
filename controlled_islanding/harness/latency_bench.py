"""Request latency under background load, and what the nodes' scheduling priority does to its tail (`bench --latency`).

Each setting replays a bag in real time with islanding probes at `probe_hz` (`replay --probe-hz --repeat`), in a
child process whose node processes inherit its scheduling policy:

- no extra load: nothing of ours beside it (other work on the machine goes on);
- busy: one CPU-bound process of ours beside it (one core's worth of other work, the issue's condition);
- busy, SCHED_FIFO: the same, with the replay and its nodes under the real-time policy at `fifo_priority`, as a
  deployment would run them (systemd's CPUSchedulingPolicy=fifo, or chrt -f).

The settings take turns, round after round, so a change of the machine's load over the run falls on all of them.
A sample is the time from a request to the breaker command it caused, or to its decision when there was nothing to
command: after the bag's cut is open, the probes' decisions cut branches already out of service, which the breaker
node refuses without a command. So most samples cross three processes (request -> coherency -> partitioning ->
observer), and one per replay crosses all four.

Measured on 1 December 2026 (docs/benchmarks.md): the tail under one busy core came from scheduling, not from the
nodes' work: p99 26 to 32 ms as ordinary processes, 6.8 to 8.3 ms under SCHED_FIFO, in the same run.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from controlled_islanding.harness.benchmarks import load_average


class LatencyBenchError(RuntimeError):
    """A replay of the benchmark failed, or the real-time policy is not permitted here."""


@dataclass(frozen=True)
class Setting:
    """One way of running the replay."""

    label: str
    busy: bool
    fifo_priority: int | None = None


@dataclass
class Row:
    """What the replays of one setting gave."""

    setting: Setting
    samples_ms: list[float] = field(default_factory=list)
    to_command: int = 0
    decisions: set = field(default_factory=set)
    loads: list[str] = field(default_factory=list)


def settings(fifo_priority: int) -> tuple[Setting, ...]:
    """Return the three settings in the order they take turns."""
    return (Setting('no extra load', busy=False), Setting('one core busy', busy=True),
            Setting(f'one core busy, SCHED_FIFO {fifo_priority}', busy=True, fifo_priority=fifo_priority))


def _fifo(priority: int):
    """Return a preexec_fn that puts the child, and so everything it starts, under SCHED_FIFO at `priority`."""
    return lambda: os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))


def check_fifo_permitted(priority: int) -> None:
    """Raise LatencyBenchError unless this process may give a child the real-time policy at `priority`."""
    low, high = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
    if not low <= priority <= high:
        raise LatencyBenchError(f'SCHED_FIFO priority must be in {low} .. {high}, got {priority}')
    probe = subprocess.run([sys.executable, '-c', 'pass'], check=False, capture_output=True, text=True,
                           preexec_fn=_fifo(priority))
    if probe.returncode != 0:
        raise LatencyBenchError('this user may not use the SCHED_FIFO policy (needs CAP_SYS_NICE or an rtprio '
                                f'limit): {probe.stderr.strip().splitlines()[-1] if probe.stderr else "refused"}')


def _replay(bag: Path, results: Path, setting: Setting, repeat: int, probe_hz: float) -> dict:
    cmd = [sys.executable, '-m', 'controlled_islanding.cli', 'replay', str(bag), '--probe-hz', str(probe_hz),
           '--repeat', str(repeat), '--no-figures', '--no-record', '--isolate', '--json', '--results', str(results)]
    policy = None if setting.fifo_priority is None else _fifo(setting.fifo_priority)
    done = subprocess.run(cmd, check=False, capture_output=True, text=True, preexec_fn=policy)
    lines = done.stdout.strip().splitlines()
    if done.returncode != 0 or not lines:
        tail = (done.stderr.strip().splitlines() or ['no output'])[-1]
        raise LatencyBenchError(f'replay of {bag} ({setting.label}) failed with status {done.returncode}: {tail}')
    return json.loads(lines[-1])


def run_bench(bag: Path, results: Path, *, rounds: int, repeat: int, probe_hz: float = 10.0,
              fifo_priority: int = 5, say=print) -> list[Row]:
    """Replay `bag` `repeat` times per setting per round, the settings taking turns; return a row per setting."""
    rows = [Row(s) for s in settings(fifo_priority)]
    for r in range(rounds):
        for i, row in enumerate(rows):
            busy = (subprocess.Popen([sys.executable, '-c', 'while True: pass'])
                    if row.setting.busy else None)
            try:
                row.loads.append(load_average())
                out = _replay(bag, results / f'round{r + 1}-setting{i + 1}', row.setting, repeat, probe_hz)
            finally:
                if busy is not None:
                    busy.kill()
                    busy.wait()
            row.samples_ms += out['latency_ms']['samples']
            row.to_command += out['latency_ms']['to_command']
            # One replay prints its summary; several print their distinct decisions.
            decisions = out.get('distinct_decisions', [(out.get('split'), out.get('cut_branch_ids', []))])
            row.decisions.update((split, tuple(cut)) for split, cut in decisions)
            say(f'round {r + 1}/{rounds}, {row.setting.label}: {out["latency_ms"]["n"]} requests, '
                f'p99 {out["latency_ms"]["p99"]:.1f} ms ({row.loads[-1]})')
    return rows


def render(rows: list[Row]) -> str:
    """Return the table: per setting, the samples' median, p99 and max, and the p99 ratio against SCHED_FIFO."""
    fifo = next(r for r in rows if r.setting.fifo_priority is not None)
    fifo_p99 = float(np.percentile(fifo.samples_ms, 99)) if fifo.samples_ms else float('nan')
    lines = [f'  {"setting":<28} {"requests":>8} {"to cmd":>6} {"median ms":>9} {"p99 ms":>7} {"max ms":>7} '
             f'{"p99 / FIFO p99":>14}  decisions']
    for row in rows:
        s = row.samples_ms
        if not s:
            lines.append(f'  {row.setting.label:<28} no samples')
            continue
        p99 = float(np.percentile(s, 99))
        lines.append(f'  {row.setting.label:<28} {len(s):>8} {row.to_command:>6} {statistics.median(s):>9.1f} '
                     f'{p99:>7.1f} {max(s):>7.1f} {p99 / fifo_p99:>14.2f}  {sorted(row.decisions, key=str)}')
    lines.append('  target (issue 12): p99 <= 16.7 ms (one 60 fps frame) with 10 Hz probes while one other core '
                 'is busy')
    return '\n'.join(lines)
