"""Request -> breaker command latency across the emulated WAN, against loopback (`controlled-islanding bench --wan`).

Each setting (one-way delay, loss) replays a bag as fast as possible, `repeat` times, each on a fresh graph on the
hosts pdc, control and substation (controlled_islanding.graph.wan), and records per replay: the decision (split and
cut), the latency from the bag's request to the breaker command as the operator's tap sees them (both leave their
senders then; the path is pdc -> control for the request and control -> substation for the decision, two one-way
delays), and the breaker commands the audit log holds against those seen: a command seen twice is duplicated, one
recorded but never seen is lost. The loopback row is the same bag without --hosts, the reference decision.

`silence_detection` measures the time breaker_command takes to report a control centre gone silent
(`warn.control_centre_silent`, from the liveliness lease of /islanding/decision): a stand-in control centre (a
process holding partitioning's decision writer) on host control, the real breaker_command on host substation, and
an observer of /diagnostics on the operator's tap; the control centre is killed (SIGKILL: no goodbye, only the
lease tells) once the breaker has seen it alive for `alive_s`, during which any alarm is a false one.
"""

from __future__ import annotations

import json
import logging
import os
import select
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from controlled_islanding.graph import GraphError, wan

DELAYS_MS = (0.0, 10.0, 50.0)
LOSSES_PCT = (0.0, 1.0, 5.0)
HOSTS = 'pdc,control,substation'

log = logging.getLogger(__name__)


@dataclass
class Row:
    """What the replays of one setting gave."""

    label: str
    delay_ms: float | None = None
    loss_pct: float | None = None
    latencies_ms: list[float] = field(default_factory=list)
    decisions: list[tuple] = field(default_factory=list)  # (split, sorted cut branch ids) per replay
    duplicated: int = 0
    lost: int = 0
    failures: list[str] = field(default_factory=list)
    wan_lost_packets: int = 0
    wan_packets: int = 0


def _commands(summary: dict) -> tuple[int, int]:
    """Return (duplicated, lost) breaker commands of one replay: seen twice at the tap, or audited but never seen."""
    seen = [c['command_id'] for c in summary.get('breaker_commands', [])]
    audit = Path(summary['results_dir']) / 'breaker_audit.jsonl'
    records = [json.loads(line) for line in audit.read_text().splitlines()] if audit.exists() else []
    recorded = [c['command_id'] for r in records if r.get('event') == 'command' for c in r['commands']]
    return len(seen) - len(set(seen)), len(set(recorded) - set(seen))


def _replay_into(row: Row, bag: Path, results: Path, hosts: str | None, link: wan.LinkModel | None) -> None:
    from controlled_islanding.graph.replay import replay
    from controlled_islanding.graph.summary import graph_failure

    try:
        summary = replay(bag, results, fast=True, figures=False, quiet=True, record=False, hosts=hosts, link=link)
    except GraphError as exc:
        row.failures.append(str(exc).splitlines()[0])
        return
    failure = graph_failure(summary)
    if failure:
        row.failures.append(failure)
    if summary.get('split') is None or summary.get('undecided_requests'):
        row.failures.append(f'undecided requests {summary.get("undecided_requests")}')
    row.decisions.append((summary.get('split'), tuple(sorted(summary.get('cut_branch_ids', [])))))
    if summary.get('latency_request_to_command_ms') is not None:
        row.latencies_ms.append(summary['latency_request_to_command_ms'])
    duplicated, lost = _commands(summary)
    row.duplicated += duplicated
    row.lost += lost
    pairs = [p for k, p in summary.get('wan', {}).get('stats', {}).get('pairs', {}).items()
             if not k.endswith(f'->{wan.OPERATOR}')]
    row.wan_packets += sum(p['packets'] + p['dropped'] for p in pairs)
    row.wan_lost_packets += sum(p['dropped'] for p in pairs)


def run_bench(bag: Path, results: Path, repeat: int, delays_ms=DELAYS_MS, losses_pct=LOSSES_PCT,
              jitter_ms: float = 0.0) -> list[Row]:
    """Replay `bag` on loopback and across the emulated WAN in every setting; return one row per setting.

    Raises:
        WanError: The emulated WAN cannot be built here.

    """
    why = wan.unavailable_reason()
    if why:
        raise wan.WanError(why)
    rows = [Row('loopback')]
    for i in range(repeat):
        _replay_into(rows[0], bag, results / f'loopback-{i}', None, None)
        log.info('--wan: loopback %d/%d', i + 1, repeat)
    for delay in delays_ms:
        for loss in losses_pct:
            row = Row(f'{delay:g} ms, {loss:g} %', delay, loss)
            for i in range(repeat):
                link = wan.LinkModel(delay_ms=delay, jitter_ms=jitter_ms, loss_pct=loss, seed=i)
                _replay_into(row, bag, results / f'd{delay:g}-l{loss:g}-{i}', HOSTS, link)
                log.info('--wan: %s %d/%d', row.label, i + 1, repeat)
            rows.append(row)
    return rows


def render(rows: list[Row], repeat: int) -> str:
    """Return the rows as a markdown table (the one in docs/deployment.md)."""
    reference = set(rows[0].decisions)
    lines = ['| setting (one-way delay, loss) | replays decided | latency median ms | latency max ms | '
             'decision as loopback | commands duplicated / lost | WAN packets lost |',
             '|---|---|---|---|---|---|---|']
    for row in rows:
        lat = row.latencies_ms
        same = ('reference' if row is rows[0] else
                'yes' if row.decisions and set(row.decisions) == reference and len(reference) == 1 else
                f'no: {sorted(set(row.decisions), key=str)}')
        packets = (f'{row.wan_lost_packets} of {row.wan_packets}' if row.wan_packets else '-')
        lines.append(f'| {row.label} | {len(row.decisions) - sum(1 for d in row.decisions if d[0] is None)}/{repeat} '
                     f'| {statistics.median(lat):.1f} | {max(lat):.1f} | {same} | {row.duplicated} / {row.lost} '
                     f'| {packets} |' if lat else
                     f'| {row.label} | 0/{repeat} | - | - | {same} | {row.duplicated} / {row.lost} | {packets} |')
    failures = [f'- {row.label}: {f}' for row in rows for f in row.failures]
    if failures:
        lines += ['', 'Failures:', *failures]
    return '\n'.join(lines)


_CONTROL_CENTRE = """
import rclpy
from controlled_islanding_msgs.msg import IslandingDecision
from controlled_islanding.wire import topics
from controlled_islanding.ros.endpoints import qos_for
rclpy.init()
node = rclpy.create_node('partitioning')
node.create_publisher(IslandingDecision, topics.relative(topics.ISLANDING_DECISION), qos_for(topics.ISLANDING_DECISION))
rclpy.spin(node)
"""
_OBSERVER = """
import json, time, rclpy
from diagnostic_msgs.msg import DiagnosticArray
from controlled_islanding.ros.endpoints import qos_for
rclpy.init()
node = rclpy.create_node('observer')
def on(msg):
    for s in msg.status:
        if s.name == '/breaker_command':
            v = {kv.key: kv.value for kv in s.values}
            print(json.dumps([time.monotonic(), v.get('decision_writers_alive'), 'warn.control_centre_silent' in v]),
                  flush=True)
node.create_subscription(DiagnosticArray, '/diagnostics', on, qos_for('/diagnostics'))
rclpy.spin(node)
"""


def silence_detection(link: wan.LinkModel, work: Path, alive_s: float = 30.0) -> tuple[float | None, int]:
    """Return (s from killing the control centre to the breaker's warning, or None; false alarms while alive).

    Raises:
        WanError: The emulated WAN cannot be built here.

    """
    from controlled_islanding.graph.rosenv import isolated_ros_environment
    from controlled_islanding.graph.supervisor import GRAPH, node_command
    from controlled_islanding.safety import signing

    work.mkdir(parents=True, exist_ok=True)
    keys = work / 'keys'
    signing.init_keys(keys)
    breaker = next(s for s in GRAPH if s.executable == 'breaker_command')
    with isolated_ros_environment(work / 'ros_log') as env, wan.EmulatedWan(['control', 'substation'], link,
                                                                             work) as net:
        env.update(wan.DDS_ENVIRONMENT)
        argv = {'breaker': net.prefix('substation') + node_command(breaker, {'audit_log': work / 'audit.jsonl',
                                                                              'key_dir': keys}),
                'observer': net.prefix(wan.OPERATOR) + [sys.executable, '-c', _OBSERVER],
                'control': net.prefix('control') + [sys.executable, '-c', _CONTROL_CENTRE]}
        procs: dict[str, subprocess.Popen] = {}
        try:
            for name, command in argv.items():
                with open(work / f'{name}.log', 'ab') as log:
                    procs[name] = subprocess.Popen(command, env=env, stderr=log, stdin=subprocess.DEVNULL,
                                                   stdout=subprocess.PIPE if name == 'observer' else log)
            observer = procs['observer'].stdout
            alive_since = killed = None
            false_alarms = 0
            end = time.monotonic() + alive_s + 120.0
            while time.monotonic() < end:
                if alive_since is not None and killed is None and time.monotonic() - alive_since >= alive_s:
                    procs['control'].kill()
                    killed = time.monotonic()
                if not select.select([observer], [], [], 0.2)[0]:
                    continue
                t, alive, silent = json.loads(observer.readline() or 'null') or (None, None, None)
                if t is None:
                    break
                if alive == '1' and alive_since is None:
                    alive_since = t
                if silent and killed is None:
                    false_alarms += 1
                elif silent:
                    return t - killed, false_alarms
            return None, false_alarms
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    os.kill(proc.pid, signal.SIGKILL)
                proc.wait()
                if proc.stdout:
                    proc.stdout.close()


def silence_table(results: Path, repeat: int, settings=((0.0, 0.0), (10.0, 1.0), (50.0, 5.0))) -> str:
    """Return the silent-control-centre detection times, `repeat` runs per (delay ms, loss %), as markdown."""
    from controlled_islanding.wire.qos import DECISION_LEASE_S

    lines = [f'Time for breaker_command to report a killed control centre (liveliness lease {DECISION_LEASE_S:g} s), '
             f'{repeat} runs per setting, each after 30 s alive:', '',
             '| setting (one-way delay, loss) | detected after s (each run) | false alarms while alive |',
             '|---|---|---|']
    for delay, loss in settings:
        runs = [silence_detection(wan.LinkModel(delay, 0.0, loss, seed=i),
                                  results / f'silence-d{delay:g}-l{loss:g}-{i}') for i in range(repeat)]
        times = ', '.join('never' if t is None else f'{t:.2f}' for t, _ in runs)
        lines.append(f'| {delay:g} ms, {loss:g} % | {times} | {sum(f for _, f in runs)} |')
        log.info('--wan: silence %g ms, %g %% done', delay, loss)
    return '\n'.join(lines)
