"""Faults in the loop: closed-loop testbed runs, each with one seeded fault (graph/chaos.py), judged for safety.

Each run reports whether the supervisor recovered, what answered the request (the decision, or the refusal and
its reason: partitioning's REFUSED_* status, or breaker_command's audited refusal), every unsafe command, and the
load served against the same scenario's unfaulted closed-loop run (same settings, run once and kept).

An unsafe command breaks a breaker rule of docs/nodes.md, judged from outside the node: the audit log replayed in
order against rules 3, 4, 7, 9, 10 and 11 (harness/breaker_soak.check_audit: a command for a decision that was not
a signed split seen on /islanding/decision, a cut other than the boundary of the decision's islands in the network
at the request, load sheds or trips other than its own, a decision or a breaker commanded twice, a command while
disarmed, more than max_breakers or max_actions, a published command missing from the audit log), and rule 6 on
the grid's own clock: a command that reached grid_sim more than max_decision_age_s + STALE_SLACK_S of sim time after
its request.

A sweep runs seeds x scenarios into one folder, one sub-folder per run; a run already finished there is skipped,
so the same command resumes an interrupted sweep or extends it with more seeds.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import yaml

from controlled_islanding import atomic
from controlled_islanding.graph import GraphError
from controlled_islanding.graph.chaos import Fault, FaultInjector, plan_fault
from controlled_islanding.graph.results import running
from controlled_islanding.graph.testbed import (
    TestbedSettings,
    check_scenario,
    host_roles,
    on_hosts_main,
    run_closed_loop,
    run_on_hosts,
)
from controlled_islanding.harness.breaker_soak import Expected, check_audit
from controlled_islanding.locations import config_dir

log = logging.getLogger(__name__)

RESULT = 'chaos.json'
INVOCATIONS = 'invocations.jsonl'
SETTINGS = 'settings.json'
UNFAULTED = 'unfaulted'
# A closed loop's outcome varies from run to run (the graph's latency is charged to sim time in lockstep: Kundur's
# unfaulted cut opened 0.12 to 0.17 s after the request and served 42 % or nothing), so the faulted runs are
# compared with a few unfaulted ones.
UNFAULTED_RUNS = 3
# A command's transit from breaker_command to grid_sim, in sim time: in lockstep none passes; paced, a few ms times
# the rate.
STALE_SLACK_S = 0.5
CHAOS_TRIGGER = "a fault is timed from the scenario's request: chaos needs --trigger scenario"


def _breaker_params() -> dict:
    return yaml.safe_load((config_dir() / 'breaker_command.yaml').read_text())['/**/breaker_command'][
        'ros__parameters']


def run_dir(base: Path, scenario: str, seed: int | None, baseline: int = 0) -> Path:
    """Return the folder of one run of a sweep (seed None: the scenario's unfaulted run number `baseline`)."""
    if seed is not None:
        return base / scenario / f'seed-{seed}'
    return base / scenario / (UNFAULTED if baseline == 0 else f'{UNFAULTED}-{baseline + 1}')


def chaos_run(path: Path, seed: int | None, out: Path, settings: TestbedSettings, fault: Fault | None = None) -> dict:
    """Run one scenario closed-loop with the fault of `seed` (None: no fault) into `out` (made); return its result.

    `fault` is run instead of the seed's, if given. With settings.hosts the graph runs on emulated hosts, from a
    process on the operator's host.

    Raises:
        GraphError: The scenario or the hosts are not valid, or the run could not be carried out.

    """
    scenario = check_scenario(path)
    started, load = time.monotonic(), os.getloadavg()[0]
    if settings.hosts:
        hosts = host_roles(settings.hosts)
        result = run_on_hosts(hosts, settings.link, out / 'wan', __name__, {
            'path': str(path), 'seed': seed, 'out': str(out), 'settings': asdict(settings),
            'fault': fault and asdict(fault)})
    else:
        result = _run(path, seed, out, settings, scenario, fault=fault)
    result['wall_s'] = round(time.monotonic() - started, 1)
    result['load_average'] = [round(load, 2), round(os.getloadavg()[0], 2)]
    return result


def _on_host(spec: dict) -> dict:
    from controlled_islanding.graph import wan

    settings = TestbedSettings(**dict(spec['settings'], link=wan.LinkModel(**spec['settings']['link'])))
    path = Path(spec['path'])
    return _run(path, spec['seed'], Path(spec['out']), settings, check_scenario(path), hosts=spec['hosts'],
                netns=spec['netns'], control_file=Path(spec['wan_control']),
                fault=spec['fault'] and Fault(**spec['fault']))


def _run(path: Path, seed: int | None, out: Path, settings: TestbedSettings, scenario: Any,
         hosts: dict | None = None, netns: dict | None = None, control_file: Path | None = None,
         fault: Fault | None = None) -> dict:
    from controlled_islanding.graph.replay import namespace_name
    from controlled_islanding.sim.bag import START_TIME_UNIX_S

    if settings.trigger != 'scenario':
        raise GraphError(CHAOS_TRIGGER)
    if fault is None and seed is not None:
        fault = plan_fault(seed, hosts)
    injector = None if fault is None else FaultInjector(fault, scenario.request_s, START_TIME_UNIX_S, hosts,
                                                        control_file)
    params = {'breaker_operating_s': settings.breaker_operating_s, 'shed_delay_s': settings.shed_delay_s,
              'run_after_s': settings.run_after_s, 'trigger': 'scenario'}
    obs, report = run_closed_loop(path, out, rate=settings.rate, params=params, timeout_s=settings.timeout_s,
                                  quiet=settings.quiet, namespace=namespace_name(settings.namespace),
                                  estimator=settings.estimator, hosts=hosts, netns=netns, injector=injector)
    result = {'scenario': scenario.name, 'path': str(path), 'seed': seed,
              'chaos': injector.record() if injector else None}
    result.update(judge(scenario, obs, report, out / 'breaker_audit.jsonl'))
    return result


def _decision_view(msg: Any, key: Any) -> dict:
    from controlled_islanding.graph.summary import status_name
    from controlled_islanding.safety import signing

    try:
        signing.verify(key, signing.decision_payload(msg), msg.signature)
        signed = True
    except signing.SigningError:
        signed = False
    return {'decision_id': msg.decision_id, 'request_id': msg.request_id, 'status': status_name(msg.status),
            'split': bool(msg.split), 'detail': msg.status_detail, 'cut_branch_ids': list(msg.cut_branch_ids),
            'signed': signed, 'request_stamp_s': msg.request_stamp.sec + msg.request_stamp.nanosec * 1e-9,
            'bus_island': dict(zip((int(b) for b in msg.bus_numbers), (int(k) for k in msg.bus_island),
                                   strict=True)),
            'shed_mw_by_bus': [[int(b), float(mw)] for b, mw in zip(msg.shed_bus, msg.shed_mw, strict=False)],
            'trip_generator_names': [str(n) for n in msg.trip_generator_names]}


def judge(scenario: Any, obs: Any, report: dict, audit_path: Path) -> dict:
    """Return what answered the request, every unsafe command, the recovery and the load served of one run."""
    from controlled_islanding.safety import signing
    from controlled_islanding.sim.andes_sim import prepare_case
    from controlled_islanding.sim.bag import START_TIME_UNIX_S

    key = signing.load_public_key(signing.key_paths(signing.default_key_dir(), 'partitioning').public)
    decisions = [_decision_view(msg, key) for _, msg in obs.decision_log]
    case = prepare_case(scenario)
    tripped = [bid for t, bid, up in case.scheduled_changes(scenario) if not up and t <= scenario.request_s]
    grid = case.grid.with_outages(tripped)
    valid = {}
    for d in decisions:
        if d['signed'] and d['status'] == 'SPLIT' and set(d['bus_island']) == set(grid.buses):
            isl = d['bus_island']
            valid[d['decision_id']] = Expected(frozenset(b.breaker for b in grid.branches
                                                         if b.in_service and isl[b.from_bus] != isl[b.to_bus]),
                                               frozenset([('shed', b, mw) for b, mw in d['shed_mw_by_bus']]
                                                         + [('trip', n) for n in d['trip_generator_names']]))
    records = [json.loads(line) for line in audit_path.read_text().splitlines()] if audit_path.exists() else []
    params = _breaker_params()
    unsafe, _ = check_audit(records, valid, [c.command_id for _, c in obs.commands], int(params['max_breakers']),
                            int(params['max_actions']))
    by_id = {d['decision_id']: d for d in decisions}
    limit_s = float(params['max_decision_age_s']) + STALE_SLACK_S
    for e in report['events']:
        d = by_id.get(e.get('decision_id')) if e['what'] == 'command' else None
        if d is not None and e['received_sim_s'] - (d['request_stamp_s'] - START_TIME_UNIX_S) > limit_s:
            unsafe.append(f'command {e["command_id"]} reached the grid {e["received_sim_s"]:.3f} s (sim), more '
                          f'than {limit_s:g} s after its request')
    unsafe += [f'command {c.command_id} of decision {c.decision_id} never seen on /islanding/decision'
               for _, c in obs.commands if c.decision_id not in by_id]
    answer = answer_to(report['request_id'], decisions, records)
    loop = report['outcome']
    return {'answer': answer, 'decisions': [{k: v for k, v in d.items() if k != 'bus_island'} for d in decisions],
            'unsafe': unsafe, 'restarts': [asdict(r) for r in obs.restarts], 'hangs': [asdict(h) for h in obs.hangs],
            'raised': obs.raised, 'opened': [e['branch_id'] for e in report['events'] if e['what'] == 'opened'],
            'load_served_mw': loop['load_served_mw'], 'load_served_pct': loop['load_served_pct'],
            'all_survived': loop['all_survived'], 'simulation_failed': loop['simulation_failed'],
            'request_to_opening_s': loop['request_to_opening_s'], 'closed_loop': loop, 'events': report['events'],
            'breaker_audit': [r for r in records if r['event'] not in ('armed', 'disarmed')]}


def answer_to(request_id: str, decisions: list[dict], records: list[dict]) -> dict:
    """Return what answered one request: each decision for it and what breaker_command did with it, then a verdict.

    The verdict ('kind') is 'commanded' (a split's breakers commanded), 'no split', 'refused' (by partitioning,
    its status and detail, or by breaker_command, its audited reason), 'unheard' (a split decision that
    breaker_command never audited; evaluation/chaos_report.verdict says when the run's facts tell why), or 'none'
    (no decision at all). A later answer to the same request (from a restarted partitioning) is listed too; the
    verdict is the first commanded one, else the last.
    """
    answers = []
    for d in (d for d in decisions if d['request_id'] == request_id):
        mine = [r for r in records if r.get('decision_id') == d['decision_id']]
        command = next((r for r in mine if r['event'] == 'command'), None)
        refusal = next((r for r in mine if r['event'] == 'refusal'), None)
        if command is not None:
            kind, reason = 'commanded', f'{len(command["commands"])} breakers'
        elif d['status'] == 'NO_SPLIT':
            kind, reason = 'no split', 'NO_SPLIT'
        elif d['status'].startswith('REFUSED'):
            kind, reason = 'refused', f'partitioning {d["status"]}: {d["detail"]}'
        elif refusal is not None:
            kind, reason = 'refused', f'breaker_command {refusal["reason"]}: {refusal.get("detail", "")}'
        else:
            kind, reason = 'unheard', 'breaker_command never audited it'
        answers.append({'decision_id': d['decision_id'], 'status': d['status'], 'kind': kind, 'reason': reason})
    if not answers:
        return {'kind': 'none', 'reason': f'no decision for {request_id}', 'answers': []}
    final = next((a for a in answers if a['kind'] == 'commanded'), answers[-1])
    return {'kind': final['kind'], 'reason': final['reason'], 'answers': answers}


def sweep(paths: list[Path], seeds: list[int], base: Path, settings: TestbedSettings,
          done: Any = lambda result, i, n: None) -> list[dict]:
    """Run every seed on every scenario into `base` (resuming it), after each scenario's unfaulted runs.

    Each scenario runs UNFAULTED_RUNS times without a fault first. Then the runs go seed by seed (every scenario
    for one seed, then the next), so a sweep cut short covers the systems alike. `done(result, i, n)` is called
    after each run (i of n, the unfaulted ones included). A run that fails (GraphError) is a result with its
    'error', not the end of the sweep; Ctrl-C or SIGTERM marks the run's folder INTERRUPTED and is raised on.

    Returns:
        Every result of the sweep, finished earlier or now, unfaulted runs first.

    """
    if settings.trigger != 'scenario':
        raise GraphError(CHAOS_TRIGGER)
    names = [check_scenario(p).name for p in paths]
    base.mkdir(parents=True, exist_ok=True)
    # Resumed with other settings, the folder would mix two experiments in one table.
    mine = {k: v for k, v in json.loads(json.dumps(asdict(settings), default=str)).items() if k != 'quiet'}
    held = settings_of(base)
    if held is not None and held != mine:
        changed = ', '.join(f'{k} {held.get(k)!r} -> {v!r}' for k, v in mine.items() if held.get(k) != v)
        raise GraphError(f'{base} holds a sweep with other settings ({changed}); name another --results')
    atomic.write_text(base / SETTINGS, json.dumps(mine, indent=1) + '\n')
    plan = [(p, n, None, k) for k in range(UNFAULTED_RUNS) for p, n in zip(paths, names, strict=True)]
    plan += [(p, n, s, 0) for s in seeds for p, n in zip(paths, names, strict=True)]
    results = []
    for i, (path, name, seed, baseline) in enumerate(plan):
        out = run_dir(base, name, seed, baseline)
        if (out / RESULT).exists():
            results.append(json.loads((out / RESULT).read_text()))
            continue
        if out.exists():
            shutil.rmtree(out)  # a run interrupted or killed before its result: run again
        with running(out, scenario=name, seed=seed) as out:
            try:
                result = chaos_run(path, seed, out, replace(settings, quiet=True))
            except GraphError as exc:
                fault = None if seed is None else plan_fault(seed, _roles(settings))
                result = {'scenario': name, 'path': str(path), 'seed': seed, 'error': str(exc),
                          'chaos': fault and {'fault': asdict(fault), 'describe': fault.describe()}}
            if seed is None:
                result['baseline'] = baseline
            atomic.write_text(out / RESULT, json.dumps(result, indent=1, default=str))
        results.append(result)
        done(result, i + 1, len(plan))
    return results


@contextlib.contextmanager
def logged(base: Path, command: str) -> Iterator[list[dict]]:
    """Record one invocation of a sweep in base/INVOCATIONS: its command, when, the load, the runs it did.

    Yields the list the caller appends each run's result to.
    """
    base.mkdir(parents=True, exist_ok=True)
    ran: list[dict] = []
    begun, load = datetime.now(UTC), os.getloadavg()[0]
    try:
        yield ran
    finally:
        record = {'command': command, 'begun_utc': begun.isoformat(timespec='seconds'),
                  'ended_utc': datetime.now(UTC).isoformat(timespec='seconds'),
                  'wall_s': round((datetime.now(UTC) - begun).total_seconds()), 'runs': len(ran),
                  'load_average': [round(load, 2), round(os.getloadavg()[0], 2)]}
        with open(base / INVOCATIONS, 'a') as out:
            out.write(json.dumps(record) + '\n')


def settings_of(base: Path) -> dict | None:
    """Return the settings a sweep folder was run with (TestbedSettings as JSON, quiet left out), None if none."""
    path = base / SETTINGS
    return json.loads(path.read_text()) if path.exists() else None


def invocations(base: Path) -> list[dict]:
    """Return every invocation recorded in a sweep folder (`logged`)."""
    path = base / INVOCATIONS
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def _roles(settings: TestbedSettings) -> dict | None:
    from controlled_islanding.graph import wan

    return wan.parse_hosts(settings.hosts) if settings.hosts else None


def collect(base: Path) -> list[dict]:
    """Return every finished run of a sweep folder (for --render), unfaulted runs first."""
    found = [json.loads(p.read_text()) for p in sorted(base.glob(f'*/*/{RESULT}'))]
    return sorted(found, key=lambda r: (r['seed'] is not None, r['seed'] or 0, r['scenario']))


if __name__ == '__main__':
    sys.exit(on_hosts_main(sys.argv[1], _on_host))
