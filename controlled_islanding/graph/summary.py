"""What one replay saw, as data and as text: the decision, its groups and breaker commands, latencies, phases.

`summarize` turns an Observation (graph.observer) into the summary.json of a results folder; `render` is its
text, as `replay` prints it and summary.txt holds it.
"""

from __future__ import annotations

import statistics
from dataclasses import asdict
from pathlib import Path

from controlled_islanding.graph import wan
from controlled_islanding.graph.observer import Observation


def decision_dict(request_id: str, obs: Observation) -> dict:
    """Return the decision answering one request, as the summary holds it: islands, cut, commands, latencies."""
    t_req = obs.requests.get(request_id)
    t_dec, msg = obs.decisions[request_id]
    commands = [(t, c) for t, c in obs.commands if c.decision_id == msg.decision_id]
    islands = []
    for i in range(len(msg.island_generation_mw)):
        islands.append({
            'island': i, 'buses': [int(b) for b, k in zip(msg.bus_numbers, msg.bus_island, strict=True) if k == i],
            'generation_mw': msg.island_generation_mw[i], 'load_mw': msg.island_load_mw[i],
            'imbalance_mw': msg.island_imbalance_mw[i], 'shed_mw': msg.island_shed_mw[i]})
    latency_cmd = (commands[-1][0] - t_req) * 1e3 if commands and t_req is not None else None
    return {
        'request_id': request_id, 'request_stamp_s': msg.request_stamp.sec + msg.request_stamp.nanosec * 1e-9,
        'decision_id': msg.decision_id, 'method': msg.method, 'split': bool(msg.split),
        'status': status_name(msg.status), 'status_detail': msg.status_detail,
        'n_islands': len(islands), 'islands': islands, 'cut_branch_ids': list(msg.cut_branch_ids),
        'disrupted_mw': msg.disrupted_mw,
        'unobserved_generators': dict(zip(msg.unobserved_generator_names,
                                          (int(i) for i in msg.unobserved_generator_island), strict=False)),
        'partitioner': msg.partitioner, 'constraint_fallback': msg.constraint_fallback,
        'remedial_actions': {'shed_mw_by_bus': {int(b): float(mw) for b, mw in zip(msg.shed_bus, msg.shed_mw,
                                                                                   strict=False)},
                             'trip_generators': list(msg.trip_generator_names)},
        'breaker_commands': [command_dict(c) for _, c in commands],
        'latency_request_to_command_ms': latency_cmd,
        'latency_request_to_decision_ms': (t_dec - t_req) * 1e3 if t_req is not None else None,
        'partitioning_compute_ms': msg.compute_time_s * 1e3,
    }


def command_dict(c: object) -> dict:
    """Return a BreakerCommand as the summary holds it: its action by name, and what it names."""
    names = {c.ACTION_OPEN: 'open', c.ACTION_CLOSE: 'close', c.ACTION_SHED_LOAD: 'shed',
             c.ACTION_TRIP_GENERATOR: 'trip'}
    out = {'command_id': c.command_id, 'breaker_id': c.breaker_id, 'branch_id': c.branch_id,
           'action': names.get(int(c.action), f'unset ({int(c.action)})')}
    if c.action == c.ACTION_SHED_LOAD:
        out.update(bus=int(c.bus), amount_mw=float(c.amount_mw))
    elif c.action == c.ACTION_TRIP_GENERATOR:
        out.update(bus=int(c.bus), generator=c.generator_name)
    return out


def status_name(status: int) -> str:
    """Return the IslandingDecision STATUS_* name of a status value, without the prefix."""
    from controlled_islanding_msgs.msg import IslandingDecision

    names = {getattr(IslandingDecision, n): n[len('STATUS_'):] for n in dir(IslandingDecision)
             if n.startswith('STATUS_')}
    return names.get(int(status), f'UNKNOWN_{int(status)}')


def refused(summary: dict) -> bool:
    """Return whether the decision is a refusal (the graph could not decide), not a split or no split."""
    return str(summary.get('status', '')).startswith('REFUSED') or summary.get('status') == 'UNSET'


def _groups_dict(obs: Observation, request_stamp: object | None) -> dict:
    """Describe the groups the decision used: the newest published up to its request (else the newest)."""
    from controlled_islanding.wire.messages import stamp_s

    if not obs.groups:
        return {}
    g = obs.groups[-1]
    if request_stamp is not None:
        # Within partitioning's freshness tolerance of the request: the groups it decided on.
        usable = [m for m in obs.groups if stamp_s(m.header.stamp) <= stamp_s(request_stamp) + 0.05]
        g = usable[-1] if usable else g
    return {'method': g.method, 'k': int(g.k), 'window_s': g.window_s,
            'groups': [[n for n, k in zip(g.generator_names, g.group, strict=True) if k == i] for i in range(g.k)],
            'unobserved': list(g.unobserved_generator_names)}


def request_dict(msg: object) -> dict:
    """Return an IslandingRequest as the summary holds it: stamp, predicted groups and first slip, signer."""
    from controlled_islanding.wire.messages import stamp_s

    k = max((int(g) for g in msg.group), default=-1) + 1
    slip = stamp_s(msg.predicted_first_slip)
    return {'request_id': msg.request_id, 'stamp_s': stamp_s(msg.header.stamp), 'reason': msg.reason,
            'groups': [[n for n, g in zip(msg.generator_names, msg.group, strict=True) if g == i] for i in range(k)],
            'predicted_first_slip_s': slip if slip > 0 else None, 'key_id': msg.key_id}


def percentile(values: list[float], q: float) -> float:
    """Return the q-th percentile (0..100) by linear interpolation."""
    data = sorted(values)
    pos = (len(data) - 1) * q / 100.0
    lo = int(pos)
    hi = min(lo + 1, len(data) - 1)
    return data[lo] + (data[hi] - data[lo]) * (pos - lo)


def summarize(bag: Path, results: Path, obs: Observation, report: dict) -> dict:
    """Return the machine-readable result: the bag's decision(s), groups, latency figures and replay speed."""
    bag_requests = [r for r in obs.requests if not r.startswith('probe-')]
    decisions = [decision_dict(r, obs) for r in bag_requests if r in obs.decisions]
    # A request that commanded nothing (a probe after the cut is open) is timed to its decision.
    answered = [decision_dict(r, obs) for r in obs.requests if r in obs.decisions]
    to_command = sum(d['latency_request_to_command_ms'] is not None for d in answered)
    latencies = [d['latency_request_to_command_ms'] if d['latency_request_to_command_ms'] is not None
                 else d['latency_request_to_decision_ms'] for d in answered]
    latencies = [x for x in latencies if x is not None]
    rejects = {name: {k: v for k, v in values.items() if k.startswith('rejected')}
               for name, values in obs.diagnostics.items()}
    out = dict(decisions[-1]) if decisions else {'split': None}
    out.update({
        'undecided_requests': [r for r in bag_requests if r not in obs.decisions],
        'bag': str(bag), 'results_dir': str(results),
        'coherent_groups': _groups_dict(obs, obs.decisions[decisions[-1]['request_id']][1].request_stamp
                                        if decisions else None),
        'decisions': decisions, 'latency_ms': {
            'n': len(latencies), 'median': statistics.median(latencies) if latencies else None,
            'p99': percentile(latencies, 99) if latencies else None, 'max': max(latencies) if latencies else None,
            'samples': latencies, 'to_command': to_command},
        'requests': [request_dict(obs.request_msgs[r]) for r in bag_requests if r in obs.request_msgs],
        'replay': report, 'phases_s': phases(obs.phases_unix, report), 'cpu_s': obs.cpu_s,
        'diagnostics_rejects': {k: v for k, v in rejects.items() if any(x != '0' for x in v.values())},
        'diagnostics': obs.diagnostics,  # each node's last /diagnostics values, for a failure's post-mortem
        'restarts': [asdict(r) for r in obs.restarts], 'hangs': [asdict(h) for h in obs.hangs],
    })
    return out


def phases(marks_unix: dict[str, float], report: dict) -> dict[str, float]:
    """Return where one replay's wall time went, s, phase by phase, from the observer's and the player's marks."""
    marks = dict(marks_unix)
    marks.update({k: report[f'{k}_unix'] for k in ('play_begun', 'play_ended') if f'{k}_unix' in report})
    order = [('nodes_started', 'set-up and node processes spawned'), ('armed', 'breaker_command up and armed'),
             ('wired', 'every node up and wired (every writer matched)'),
             ('play_begun', 'player told to go, waited for its subscribers'),
             ('play_ended', 'play, lockstep waits included'),
             ('decided', 'last decisions, breaker commands and diagnostics'),
             ('stopped', 'nodes settled and stopped')]
    out, last = {}, marks.get('begun')
    for key, what in order:
        if key in marks and last is not None:
            out[what] = marks[key] - last
            last = marks[key]
    if 'begun' in marks and last is not None:
        out['total'] = last - marks['begun']
    return out


def graph_failure(summary: dict) -> str | None:
    """Return one line naming every pipeline node that died or hung during the replay, else None.

    A decision from a graph that lost a node, even one restarted in time, may rest on state the node lost.
    """
    if not summary.get('restarts'):
        return None
    what = [f'{r["name"]} {"hung" if r["cause"] == "hung" else "exited with status " + str(r["exit_status"])}'
            f'{" (restarted)" if r["new_pid"] else ""}' for r in summary['restarts']]
    return f'graph not healthy during the replay: {"; ".join(what)}; see restarts in summary.json and the node logs'


def render(summary: dict) -> str:
    """Return the readable decision."""
    lines = [f'bag: {summary["bag"]}']
    if summary.get('trigger') == 'monitor':
        lines += monitor_lines(summary)
    groups = summary['coherent_groups']
    if groups:
        lines.append(f'coherent groups ({groups["method"]}, k={groups["k"]}, window {groups["window_s"]:.2f} s):')
        lines += [f'  group {i}: {", ".join(names)}' for i, names in enumerate(groups['groups'])]
        if groups.get('unobserved'):
            lines.append(f'  unobserved (no PMU data, in no group): {", ".join(groups["unobserved"])}')
    if summary.get('split') is None and summary.get('trigger') == 'monitor' and not summary['requests']:
        lines.append(f'results: {summary["results_dir"]}')
        return '\n'.join(lines)
    if summary.get('split') is None:
        lines.append('NO DECISION: see the dropped inputs below and the node logs')
        lines += [f'dropped inputs at {name}: ' + ', '.join(f'{k}={v}' for k, v in rejects.items())
                  for name, rejects in summary['diagnostics_rejects'].items()]
        if graph_failure(summary):
            lines.append(f'FAILED: {graph_failure(summary)}')
        lines.append(f'results: {summary["results_dir"]}')
        return '\n'.join(lines)
    if refused(summary):
        lines.append(f'decision: {summary["status"]}: {summary.get("status_detail", "")}')
        if graph_failure(summary):
            lines.append(f'FAILED: {graph_failure(summary)}')
        lines.append(f'results: {summary["results_dir"]}')
        return '\n'.join(lines)
    split = f'SPLIT into {summary["n_islands"]} islands' if summary['split'] else 'no split'
    lines.append(f'decision: {split}')
    for isl in summary['islands']:
        lines.append(f'  island {isl["island"]}: generation {isl["generation_mw"]:.1f} MW, '
                     f'load {isl["load_mw"]:.1f} MW, shed {isl["shed_mw"]:.1f} MW; '
                     f'buses {", ".join(map(str, isl["buses"]))}')
    if summary.get('unobserved_generators'):
        lines.append('unconstrained (unobserved) generators, placed like load buses: ' + ', '.join(
            f'{n} -> island {i}' for n, i in summary['unobserved_generators'].items()))
    lines.append(f'cut lines: {", ".join(summary["cut_branch_ids"]) or "none"}')
    lines.append(f'disrupted power flow: {summary["disrupted_mw"]:.2f} MW')
    cmds = summary['breaker_commands']
    opens = [c for c in cmds if c['action'] not in ('shed', 'trip')]
    lines.append('breaker commands: ' + (', '.join(f'{c["action"]} {c["breaker_id"]}' for c in opens) or 'none'))
    sheds = [c for c in cmds if c['action'] == 'shed']
    trips = [c['generator'] for c in cmds if c['action'] == 'trip']
    if sheds or trips:
        lines.append(f'remedial actions commanded: shed {sum(c["amount_mw"] for c in sheds):.1f} MW at {len(sheds)} '
                     f'load buses; ' + (f'tripped {", ".join(trips)}' if trips else 'no machine tripped'))
    if summary['latency_request_to_command_ms'] is not None:
        lines.append(f'latency request -> breaker command: {summary["latency_request_to_command_ms"]:.1f} ms')
    else:
        lines.append(f'latency request -> decision: {summary["latency_request_to_decision_ms"]:.1f} ms '
                     '(nothing to command)')
    lat = summary['latency_ms']
    if lat['n'] > 1:
        lines.append(f'latency over {lat["n"]} requests, to the breaker command ({lat["to_command"]} of them) or '
                     f'else to the decision: median {lat["median"]:.1f} ms, p99 {lat["p99"]:.1f} ms')
    rep = summary['replay']
    if rep:
        lines.append(f'replay: {rep["bag_duration_s"]:.2f} s of bag in {rep["wall_s"]:.2f} s '
                     f'({rep["speed_vs_real_time"]:.1f}x real time)')
    for name, rejects in summary['diagnostics_rejects'].items():
        lines.append(f'dropped inputs at {name}: ' + ', '.join(f'{k}={v}' for k, v in rejects.items()))
    if summary.get('wan'):
        lines.append(wan_line(summary['wan']))
    if graph_failure(summary):
        lines.append(f'FAILED: {graph_failure(summary)}')
    lines.append(f'results: {summary["results_dir"]}')
    return '\n'.join(lines)


def monitor_lines(summary: dict) -> list[str]:
    """Return the stability monitor's requests (replay --trigger monitor), one line each, or that it made none."""
    if not summary['requests']:
        return ['stability monitor: no islanding request (no separation predicted with confidence)']
    out = []
    for r in summary['requests']:
        slip = r['predicted_first_slip_s']
        small = sorted(r['groups'], key=len)[:-1]
        out.append(f'stability monitor: request {r["request_id"]} at {r["stamp_s"]:.3f} s, {len(r["groups"])} '
                   f'groups predicted (' + '; '.join(', '.join(g) for g in small)[:300] + ' apart), first pole slip '
                   + (f'predicted {slip - r["stamp_s"]:.3f} s later' if slip else 'not predicted')
                   + ('' if r['key_id'] else ', UNSIGNED'))
    return out


def wan_line(info: dict) -> str:
    """Return one line on the emulated WAN: hosts, link model and what crossed it."""
    link, stats = info['link'], info.get('stats') or {}
    pairs = [p for k, p in stats.get('pairs', {}).items() if not k.endswith(f'->{wan.OPERATOR}')]
    sent = sum(p['packets'] + p['dropped'] for p in pairs)
    dropped = sum(p['dropped'] for p in pairs)
    return (f'emulated WAN: hosts {", ".join(info["hosts"])} (+ {wan.OPERATOR}); one-way delay {link["delay_ms"]:g} '
            f'+- {link["jitter_ms"]:g} ms, loss {link["loss_pct"]:g} %: {sent} packets between hosts, {dropped} lost')
