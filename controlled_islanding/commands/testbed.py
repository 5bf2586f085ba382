"""`controlled-islanding testbed SCENARIO.yaml`: the scenario closed-loop through the node graph and grid_sim."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from controlled_islanding import atomic
from controlled_islanding.cli import CliError
from controlled_islanding.wire import topics

HELP = 'run a scenario closed-loop (ANDES as the grid, the four nodes deciding) and compare with no action and MILP'
DESCRIPTION = """\
Start pmu_ingestion, coherency, partitioning and breaker_command (armed with a signed operator request, as
replay does) and grid_sim, which runs the scenario's ANDES simulation as the grid: it publishes the snapshot,
PMU frames, trips and the scenario's islanding request, executes the breaker commands in the running
simulation (breaker operating time, then the decision's load shed in islands short of generation and
generation rejection in islands with a surplus), keeps
simulating, and judges every island (docs/testbed.md and controlled_islanding/sim/closed_loop.py give the
rules: machines within pi rad of each other, frequency within 0.9633..1.03 pu of the case's nominal frequency
(57.8..61.8 Hz at 60 Hz, 48.17..51.5 Hz at 50 Hz), voltage 0.8..1.2 pu, no machine tripped).

Then the same scenario runs twice more in-process, with no graph: with no action, and with the exact MILP cut
(core/milp.py, the same generator groups as the decision) opened at the same time as the graph's cut, with its
own load shed. One table compares the three: islands that survived, load lost (shed, plus the load of every
island that did not survive), frequency nadir and peak, lowest voltage, request-to-opening time.
A figure per scenario shows the rotor angles coloured by the decision's islands and the bus voltages, for no
action and for the closed loop (as the paper's Figs. 6 and 11).

With --namespace /area1 the four nodes and grid_sim run in /area1 (/area1/pmu/frames, ..., /area1/clock), as
with `replay --namespace`; each result lists the graph's topic names.

Lockstep (default): the simulation does not step past the request until the decision and its commands came
(bounded waits); the graph's wall-clock latency is then charged to sim time. --rate R paces the simulation at R
times real time instead (ANDES may be slower than that on a busy machine).

Examples:
  controlled-islanding testbed bags/ieee14_g1_unstable.yaml
  controlled-islanding testbed bags/ieee39_g6g7_unstable.yaml --json
  controlled-islanding testbed --all-unstable --markdown docs/testbed.md --figures-dir docs/testbed
                                      every manifest scenario whose expected decision splits (long: minutes each)
"""

INTERRUPTED = 'INTERRUPTED.json'  # in a results folder: the run was stopped before its end


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the testbed options."""
    parser.add_argument('scenarios', type=Path, nargs='*', help='scenario YAML files (bags/*.yaml)')
    parser.add_argument('--all-unstable', action='store_true',
                        help='every scenario of bags/index.yaml whose expected decision splits')
    parser.add_argument('--json', action='store_true', help='print the results as JSON on stdout and nothing else')
    parser.add_argument('--markdown', type=Path, default=None, help='also write the table as a Markdown page')
    parser.add_argument('--figures-dir', type=Path, default=None,
                        help='write the figures here too (default: only in the results folder)')
    parser.add_argument('--figure-scenarios', default='',
                        help='comma-separated scenario names whose figures go to --figures-dir (default: all)')
    parser.add_argument('--results', type=Path, default=None,
                        help='results folder to create (default ./results/testbed-<UTC time>)')
    parser.add_argument('--rate', type=float, default=0.0, help='0 = lockstep (default); R > 0 = R x real time')
    parser.add_argument('--breaker-operating-s', type=float, default=0.05,
                        help='breaker command -> branch open, s (default 0.05, 3 cycles at 60 Hz)')
    parser.add_argument('--shed-delay-s', type=float, default=0.2, help='branch open -> load shed, s (default 0.2)')
    parser.add_argument('--run-after-s', type=float, default=3.0,
                        help='simulate at least this long after the request, s (default 3)')
    parser.add_argument('--render', type=Path, default=None, metavar='RESULTS',
                        help='run nothing: rebuild the table, --markdown and --figures-dir from a results folder of an '
                             'earlier (or still running) testbed run; scenarios not finished yet are listed as missing')
    parser.add_argument('--no-baselines', action='store_true', help='skip the no-action and MILP runs')
    parser.add_argument('--trigger', choices=('scenario', 'out-of-step'), default='scenario',
                        help="where the islanding request comes from: the scenario's time (default), or grid_sim's "
                             'out-of-step trigger on the measured rotor angles (sim/closed_loop.out_of_step)')
    parser.add_argument('--timeout', type=float, default=900.0, help='give up on one closed-loop run after this, s')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help='run the graph and grid_sim in this ROS namespace, e.g. /area1 (default: the root one)')
    parser.add_argument('--estimator', choices=('steady_state', 'dse'), default=None,
                        help="pmu_ingestion's rotor angle estimator, as replay --estimator (default: "
                             'config/pmu_ingestion.yaml)')


@dataclass
class LoopObservation:
    """What the testbed's observer saw of one closed-loop run (wall arrival times, time.monotonic, s)."""

    requests: dict[str, float] = field(default_factory=dict)
    decisions: dict[str, tuple[float, object]] = field(default_factory=dict)
    commands: list[tuple[float, object]] = field(default_factory=list)
    groups: list = field(default_factory=list)
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)
    heartbeats_s: dict[str, float] = field(default_factory=dict)
    restarts: list = field(default_factory=list)
    hangs: list = field(default_factory=list)
    graph_topics: list[str] = field(default_factory=list)


def _say(quiet: bool, text: str) -> None:
    if not quiet:
        print(text, file=sys.stderr, flush=True)


def run_closed_loop(scenario: Path, results: Path, *, rate: float, params: dict[str, float], timeout_s: float,
                    quiet: bool, namespace: str = '', estimator: str | None = None) -> tuple[LoopObservation, dict]:
    """Run the four nodes and grid_sim on one scenario; return what the observer saw and grid_sim's report.

    The graph runs in `namespace` ('' = the root one, else e.g. '/area1'), its clock on <namespace>/clock.
    `estimator` overrides pmu_ingestion's (None: its parameter file's).

    Raises:
        CliError: A node died, or grid_sim gave no report within timeout_s.

    """
    import rclpy
    from controlled_islanding_msgs.msg import BreakerCommand, CoherentGroups, IslandingDecision, IslandingRequest
    from controlled_islanding_msgs.srv import SetArmed
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.signals import SignalHandlerOptions

    from controlled_islanding.graph.rosenv import graph_environment
    from controlled_islanding.graph.supervisor import GRAPH, PIPELINE_POLICY, NodeSpec, Supervisor, SupervisorError
    from controlled_islanding.ros.endpoints import qos_for
    from controlled_islanding.safety import signing

    key_dir = Path(os.environ.get('CONTROLLED_ISLANDING_KEYS') or signing.default_key_dir())
    signing.init_keys(key_dir)
    operator_key = signing.load_private_key(signing.key_paths(key_dir, 'operator').private)
    obs = LoopObservation()
    logs = results / 'logs'
    report_file = results / 'grid_sim.json'
    clock_topic = f'{namespace}{topics.CLOCK}'
    remaps = {topics.CLOCK: clock_topic} if namespace else {}
    with graph_environment(results / 'ros_log', True) as env:
        saved = dict(os.environ)
        os.environ.update(env)
        context = rclpy.Context()
        rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node('testbed_observer', context=context, namespace=namespace or None)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)

        def spin_for(seconds: float, done=lambda: False) -> bool:
            end = time.monotonic() + seconds
            while not done() and time.monotonic() < end:
                executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))
            return done()

        def on_diag(msg: DiagnosticArray) -> None:
            for status in msg.status:
                name = status.name.removeprefix(namespace)
                obs.diagnostics[name] = {kv.key: kv.value for kv in status.values}
                obs.heartbeats_s[name] = time.monotonic()

        node.create_subscription(IslandingRequest, topics.relative(topics.ISLANDING_REQUEST),
                                 lambda m: obs.requests.setdefault(m.request_id, time.monotonic()),
                                 qos_for(topics.ISLANDING_REQUEST))
        node.create_subscription(IslandingDecision, topics.relative(topics.ISLANDING_DECISION),
                                 lambda m: obs.decisions.setdefault(m.request_id, (time.monotonic(), m)),
                                 qos_for(topics.ISLANDING_DECISION))
        node.create_subscription(BreakerCommand, topics.relative(topics.BREAKER_COMMANDS),
                                 lambda m: obs.commands.append((time.monotonic(), m)), qos_for(topics.BREAKER_COMMANDS))
        node.create_subscription(CoherentGroups, topics.relative(topics.COHERENT_GROUPS), obs.groups.append,
                                 qos_for(topics.COHERENT_GROUPS))
        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diag, qos_for(topics.DIAGNOSTICS))
        try:
            with Supervisor(env, logs, PIPELINE_POLICY, namespace=namespace, remaps=remaps) as sup:
                obs.restarts, obs.hangs = sup.restarts, sup.hangs
                sim = {'use_sim_time': True}
                extra = {'breaker_command': {'audit_log': results / 'breaker_audit.jsonl', 'key_dir': key_dir},
                         'partitioning': {'key_dir': key_dir}}
                if estimator is not None:
                    extra['pmu_ingestion'] = {'estimator': estimator}
                for spec in GRAPH:
                    sup.start(spec, {**sim, **extra.get(spec.executable, {})})
                _say(quiet, f'testbed: started {len(GRAPH)} nodes (logs in {logs})')
                arm_client = node.create_client(SetArmed, 'breaker_command/set_armed')
                if not arm_client.wait_for_service(timeout_sec=30.0):
                    sup.check_alive()
                    raise CliError(f'breaker_command did not offer {namespace}/breaker_command/set_armed within 30 s')
                future = None
                for _attempt in range(3):  # a response can be dropped before it matched our reader (replay.py)
                    request = signing.signed_arm_request(SetArmed.Request(), operator_key,
                                                         f'{namespace}/breaker_command', True, time.time())
                    future = arm_client.call_async(request)
                    if spin_for(5.0, future.done):
                        break
                if future is None or not future.done() or not future.result().accepted:
                    raise CliError('breaker_command did not arm')
                played = (topics.PMU_FRAMES, topics.NETWORK_SNAPSHOT, topics.BRANCH_STATUS, topics.ISLANDING_REQUEST,
                          topics.CLOCK)
                internal = (topics.ROTOR_ANGLES, topics.COHERENT_GROUPS, topics.ISLANDING_DECISION,
                            topics.BREAKER_COMMANDS)
                counts: dict[str, int] = {}
                wiring: dict[str, tuple[int, int]] = {}
                stable_since = begun = time.monotonic()
                def graph_name(t: str) -> str:
                    return clock_topic if t == topics.CLOCK else topics.relative(t)

                while time.monotonic() < begun + 30.0:  # wired once nothing changed for a second (replay.py)
                    now_counts = {t: node.count_subscribers(graph_name(t)) for t in played}
                    now_wiring = {t: (node.count_publishers(graph_name(t)), node.count_subscribers(graph_name(t)))
                                  for t in internal}
                    if now_counts != counts or now_wiring != wiring:
                        counts, wiring, stable_since = now_counts, now_wiring, time.monotonic()
                    elif time.monotonic() - stable_since >= 1.0 and all(min(w) > 0 for w in wiring.values()):
                        break
                    spin_for(0.1)
                obs.graph_topics = sorted(name for name, _ in node.get_topic_names_and_types())
                # grid_sim's own subscriptions (decision, commands, angles) add one subscriber to none of these.
                grid = sup.start(NodeSpec('grid_sim', 'grid_sim.yaml'), {
                    **sim, 'use_sim_time': False, 'scenario': scenario.resolve(), 'rate': rate,
                    'report_file': report_file, 'progress': not quiet, **params,
                    'min_subscribers': str([f'{t}={n}' for t, n in counts.items()])})
                _say(quiet, f'testbed: breaker_command armed; grid_sim simulating {scenario.name}')
                deadline = time.monotonic() + timeout_s
                while time.monotonic() < deadline:
                    spin_for(0.05)
                    sup.supervise(obs.heartbeats_s)
                    if grid.poll() is not None:
                        spin_for(0.3)
                        break
                else:
                    raise CliError(f'grid_sim did not finish within --timeout {timeout_s} s; logs in {logs}')
                if grid.returncode != 0 or not report_file.exists():
                    raise CliError(f'grid_sim failed (exit {grid.returncode}):\n{sup.log_tail("grid_sim")}')
        except SupervisorError as exc:
            raise CliError(str(exc)) from exc
        finally:
            node.destroy_node()
            context.try_shutdown()
            os.environ.clear()
            os.environ.update(saved)
    return obs, json.loads(report_file.read_text())


def _decision(obs: LoopObservation, request_id: str) -> dict | None:
    from controlled_islanding.commands.replay import _decision_dict

    if request_id not in obs.decisions:
        return None
    return _decision_dict(request_id, obs)  # type: ignore[arg-type]  # same fields as replay.Observation


def _milp_cut(scenario: Any, decision: dict) -> dict:
    """Return the exact minimum-disruption partition for the decision's generator groups, on its network."""
    from controlled_islanding.core.islanding import evaluate_partition
    from controlled_islanding.core.milp import ExactPartition
    from controlled_islanding.sim.andes_sim import prepare_case

    case = prepare_case(scenario)
    grid = case.grid
    tripped = [bid for t, bid, up in case.scheduled_changes(scenario) if not up and t <= scenario.request_s]
    grid = grid.with_outages(tripped)
    bus_island = {b: isl['island'] for isl in decision['islands'] for b in isl['buses']}
    groups = {g.name: bus_island[g.bus] for g in grid.generators}
    model = ExactPartition(time_limit_s=60.0).fit(grid, groups)
    milp_island = dict(zip(grid.buses, (int(x) for x in model.labels_), strict=True))
    ev = evaluate_partition(grid, milp_island)
    return {'bus_island': milp_island, 'cut_branch_ids': list(ev.cut_branch_ids),
            'island_shed_mw': list(ev.island_shed_mw), 'disrupted_mw': ev.disrupted_mw, 'optimal': model.optimal_}


def run_scenario(path: Path, results: Path, args: argparse.Namespace, quiet: bool, cache: dict) -> dict:
    """Run one scenario closed-loop, then the baselines; return its result (figures go under results)."""
    import numpy as np

    from controlled_islanding.commands.replay import namespace_name
    from controlled_islanding.sim.closed_loop import LoopConfig, run_offline
    from controlled_islanding.sim.scenario import ScenarioError, load_scenario

    try:
        scenario = load_scenario(path)
    except ScenarioError as exc:
        raise CliError(str(exc)) from exc
    out = results / scenario.name
    out.mkdir(parents=True)
    config = LoopConfig(breaker_operating_s=args.breaker_operating_s, shed_delay_s=args.shed_delay_s,
                        run_after_s=args.run_after_s)
    params = {'breaker_operating_s': args.breaker_operating_s, 'shed_delay_s': args.shed_delay_s,
              'run_after_s': args.run_after_s, 'trigger': args.trigger.replace('-', '_')}
    _say(quiet, f'testbed {scenario.name}: closed loop')
    obs, report = run_closed_loop(path, out, rate=args.rate, params=params, timeout_s=args.timeout, quiet=quiet,
                                  namespace=namespace_name(args.namespace), estimator=args.estimator)
    decision = _decision(obs, report['request_id'])
    loop = report['outcome']
    if args.trigger != 'scenario':
        # The baselines and the figure answer the request grid_sim's trigger made, not the scenario's.
        scenario = replace(scenario, request_s=loop['request_s'],
                           end_s=max(scenario.end_s, loop['request_s'] + args.run_after_s))
    result: dict[str, Any] = {'scenario': scenario.name, 'path': str(path), 'decision': decision,
                              'closed_loop': loop, 'events': report['events'],
                              'restarts': [r.__dict__ for r in obs.restarts], 'runs': {'dtw': loop},
                              'graph_topics': obs.graph_topics,
                              'estimator': next((d['estimator'] for name, d in obs.diagnostics.items()
                                                 if name.endswith('pmu_ingestion') and 'estimator' in d), None)}
    traj = dict(np.load(f'{out / "grid_sim.json"}.npz'))
    trajectories = {'dtw': traj}
    if not args.no_baselines:
        key = (scenario.simulation_key(), args.run_after_s)
        if key not in cache:
            _say(quiet, f'testbed {scenario.name}: no action (ANDES in-process)')
            cache[key] = run_offline(scenario, 'no action', judged_from_s=loop['opened_s'] or scenario.request_s,
                                     config=config, progress=not quiet)
        none = cache[key]
        if loop['opened_s'] is not None and none.judged_from_s != loop['opened_s']:
            # The same run, judged over the closed loop's window: only the window start differs.
            none_summary = none.rejudged(loop['opened_s'], config).summary()
        else:
            none_summary = none.summary()
        result['runs']['no action'] = none_summary
        trajectories['no action'] = {'t_s': none.t_s, 'delta_rad': none.delta_rad, 'bus_v_pu': none.bus_v_pu}
        if decision and decision['split'] and loop['opened_s'] is not None:
            milp = _milp_cut(scenario, decision)
            result['milp_cut'] = milp
            same = (sorted(milp['cut_branch_ids']) == sorted(decision['cut_branch_ids']))
            if same:
                result['runs']['milp'] = dict(loop, label='milp (same cut as dtw: the closed-loop run)')
            else:
                _say(quiet, f'testbed {scenario.name}: MILP cut {milp["cut_branch_ids"]} (ANDES in-process)')
                m = run_offline(scenario, 'milp', cut_branch_ids=milp['cut_branch_ids'], bus_island=milp['bus_island'],
                                island_shed_mw=milp['island_shed_mw'], opened_s=loop['opened_s'], config=config,
                                progress=not quiet)
                result['runs']['milp'] = m.summary()
                trajectories['milp'] = {'t_s': m.t_s, 'delta_rad': m.delta_rad, 'bus_v_pu': m.bus_v_pu}
    result['figure'] = str(_figure(scenario, result, trajectories, traj, out / f'{scenario.name}_closed_loop.png'))
    atomic.write_text(out / 'result.json', json.dumps(result, indent=1, default=str))
    return result


def _figure(scenario: Any, result: dict, trajectories: dict, loop_traj: dict, path: Path) -> Path:
    from controlled_islanding.evaluation import plots

    decision = result['decision'] or {}
    bus_island = {b: isl['island'] for isl in decision.get('islands', []) for b in isl['buses']}
    names = [str(n) for n in loop_traj['generator_names']]
    gen_island = [bus_island.get(int(b), 0) for b in loop_traj['generator_buses']]
    panels = []
    for label in ('no action', 'dtw', 'milp'):
        if label not in trajectories or (label == 'milp' and 'milp' not in result['runs']):
            continue
        run = result['runs'][label]
        tr = trajectories[label]
        panels.append(plots.ClosedLoopPanel(
            label={'dtw': 'closed loop (DTW decision)', 'milp': 'exact MILP cut', 'no action': 'no action'}[label],
            t_s=tr['t_s'], delta_rad=tr['delta_rad'], bus_v_pu=tr['bus_v_pu'], opened_s=run.get('opened_s'),
            survived=run['all_survived']))
    return plots.plot_closed_loop(panels, names, gen_island, path, request_s=scenario.request_s,
                                  title=f'{scenario.name}: rotor angles by island and bus voltages')


def _fmt(x: Any, spec: str) -> str:
    return '-' if x is None else format(x, spec)


def table_rows(results: list[dict]) -> list[list[str]]:
    """Return one row per scenario and run: the comparison table."""
    rows = []
    for r in results:
        for label in ('no action', 'dtw', 'milp'):
            run = r['runs'].get(label)
            if run is None:
                continue
            isl = run['islands']
            ok = sum(1 for i in isl if i['survived'])
            rows.append([r['scenario'], label, ', '.join(run['cut_branch_ids']) or 'none',
                         f'{ok}/{len(isl)}' + ('' if ok == len(isl) else ' (' + '; '.join(
                             w for i in isl for w in i['why_not'])[:80] + ')'),
                         f'{run["load_lost_mw"]:.0f} ({run["shed_mw"]:.0f} shed)', f'{run.get("rejected_mw", 0.0):.0f}',
                         f'{run["f_nadir_hz"]:.2f} / {run["f_peak_hz"]:.2f}', f'{run["v_min_pu"]:.3f}',
                         _fmt(run['request_to_opening_s'], '.3f')])
    return rows


def _span(span: list[float] | None) -> str:
    return f'{span[0]:+.3f} to {span[1]:+.3f} s' if span else ''


def failure_text(isl: dict) -> str:
    """Return what failed in a lost island and when, s after the cut (from its assessment, closed_loop.assess)."""
    gens = isl['generators']
    head = f'island {isl["island"]} ({", ".join(gens[:3])}{", ..." if len(gens) > 3 else ""}'
    head += f'; rejected {", ".join(isl["rejected"])})' if isl.get('rejected') else ')'
    if 'f_outside_s' not in isl:  # a result written before the timings were recorded
        return f'{head}: {"; ".join(isl["why_not"])}'
    out = []
    if isl['generators'] and isl['rejected'] and len(isl['rejected']) == len(isl['generators']):
        out.append(f'every machine tripped by generation rejection (island load {isl["load_mw"]:.0f} MW)')
    if not isl['coherent']:
        out.append(f'machines {isl["max_pair_swing_rad"]:.2f} rad apart')
    if isl['f_outside_s']:
        since = isl['f_outside_since_s']
        out.append(f'frequency {isl["f_nadir_hz"]:.2f}..{isl["f_peak_hz"]:.2f} Hz, out of band '
                   f'{_span(isl["f_outside_s"])}' + ('' if since is None else f', already out at the cut (since '
                                                                                f'{since:+.3f} s)'))
    if isl['v_outside_s']:
        out.append(f'voltage {isl["v_min_pu"]:.3f}..{isl["v_max_pu"]:.3f} pu, out of band '
                   f'{_span(isl["v_outside_s"])}, worst at bus {isl["v_worst_bus"]}')
    if isl['machines_tripped']:
        out.append(f'machines tripped: {", ".join(isl["machines_tripped"])}')
    out += [w for w in isl['why_not'] if w.startswith('simulation stopped')]
    return f'{head}: {"; ".join(out)}'


def failure_lines(results: list[dict]) -> list[str]:
    """Return a line per lost island of every closed-loop run, and of a MILP run whose cut differs."""
    out = []
    for r in results:
        for label in ('dtw', 'milp'):
            run = r['runs'].get(label)
            if run is None or (label == 'milp' and run.get('label', '').startswith('milp (same cut')):
                continue
            for isl in run['islands']:
                if not isl['survived']:
                    out.append(f'- {r["scenario"]} `{label}` {failure_text(isl)}.')
    return out


HEADER = ['scenario', 'run', 'cut', 'islands survived', 'load lost MW', 'generation tripped MW', 'f nadir / peak Hz',
          'V min pu',
          'request -> opening s']


def render(results: list[dict]) -> str:
    """Return the readable report: each decision, its commands, and the comparison table."""
    lines = []
    for r in results:
        d = r['decision']
        lines.append(f'{r["scenario"]}:')
        if d is None:
            lines.append('  no decision came')
        else:
            cut = f', cut {", ".join(d["cut_branch_ids"])}' if d['split'] else ''
            lines.append(f'  decision: {d["status"]}{cut}')
            for c in d['breaker_commands']:
                lines.append(f'  command {c["action"]} {c["breaker_id"]} ({c["branch_id"]})')
        for e in r['events']:
            if e['what'] in ('command', 'opened', 'shed scheduled'):
                lines.append('  ' + ', '.join(f'{k}={v:.3f}' if isinstance(v, float) else f'{k}={v}'
                                              for k, v in e.items()))
        for isl in r['closed_loop']['islands']:
            lines.append(f'  island {isl["island"]} ({", ".join(isl["generators"])}): '
                         f'{"survived" if isl["survived"] else "LOST: " + "; ".join(isl["why_not"])}')
    widths = [max(len(h), *(len(row[i]) for row in table_rows(results))) for i, h in enumerate(HEADER)] \
        if results else [len(h) for h in HEADER]
    lines.append('')
    lines.append('  '.join(h.ljust(w) for h, w in zip(HEADER, widths, strict=True)))
    for row in table_rows(results):
        lines.append('  '.join(c.ljust(w) for c, w in zip(row, widths, strict=True)))
    return '\n'.join(lines)


def markdown(results: list[dict], args: argparse.Namespace, figures: list[Path], page: Path) -> str:
    """Return the Markdown page of the table (docs/testbed.md)."""
    cmd = 'controlled-islanding testbed ' + ' '.join(sys.argv[2:])
    out = ['# Closed-loop testbed results', '',
           f'Generated by `{cmd}` on {datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")}; do not edit by hand.', '',
           'Each scenario ran three times in ANDES: `dtw` is the closed loop (grid_sim and the four nodes, the '
           'decision commanded by breaker_command and executed in the running simulation), `no action` the same '
           'scenario untouched, `milp` the exact minimum-disruption cut for the same generator groups opened at '
           'the same time. Rules (controlled_islanding/sim/closed_loop.py): an island survives when its machines '
           "stay within pi rad of each other (relative to the cut), its frequency within 0.9633..1.03 pu of the "
           "case's nominal frequency (57.8..61.8 Hz at 60 Hz, 48.17..51.5 Hz at 50 Hz: NERC PRC-024's limits, per "
           'unit), its bus '
           'voltages within 0.8..1.2 pu from 0.5 s after the cut, and no machine trips. Load lost = load shed + '
           "the load of every island that did not survive. Generation tripped: in every island whose machines' "
           'pre-fault output exceeds its load after the shed by more than 5 % of that load, machines are tripped at '
           'the time of the shed, largest output first, each only if it fits in the remaining surplus '
           '(closed_loop.generation_to_reject; a rejected machine is not judged after its trip); the `milp` row '
           'gets the same rule. `no action` is judged as one island over the same '
           f'window. Breaker operating time {args.breaker_operating_s} s, load shed {args.shed_delay_s} s after '
           f'the opening, simulated at least {args.run_after_s} s past the request.'
           + ('' if getattr(args, 'trigger', 'scenario') == 'scenario' else
              " The request is not the scenario's: grid_sim's out-of-step trigger made it, at the first step where "
              "the measured rotor angles (the graph's /rotor_angles, against the first received) showed two machines "
              'more than 90 deg apart with no PMU voltage below 0.5 pu (closed_loop.out_of_step); an answer that '
              'does not split re-arms it, and it asks again on newer angles while that holds (at most 20 requests); '
              'the baselines answer the last request.'), '',
           '| ' + ' | '.join(HEADER) + ' |', '|' + '---|' * len(HEADER)]
    out += ['| ' + ' | '.join(row) + ' |' for row in table_rows(results)]
    out += ['', 'Reading the table:',
            '- An island with a surplus no machine fits in (each is larger than the surplus) keeps it: tripping one '
            "would leave a deficit nobody sheds, so such an island can speed up past the band's top (61.8 Hz at "
            '60 Hz) and count as lost. Overspeed protection is modelled at 1.10 pu speed (66 Hz at 60 Hz, '
            "closed_loop.py): a machine past it is listed among the machines tripped, its time among the run's "
            'actions. It is recorded, not switched off in ANDES (which stopped converging when it was, on PJM 5-bus '
            "and Kundur), and it decides no verdict: the band's top is lower.",
            '- "V min" is ANDES\' voltage variable. Zero or negative voltages in islands right after an opening '
            'were a solver artefact, not a collapse: ANDES solves the network in polar power-balance form, where '
            'V = 0 (or V < 0 with the angle off by pi) satisfies a bus trivially, and Newton started from the '
            'voltages of a large swing landed there. The solver now starts each new island from the pre-fault '
            "voltages turned with its machines' mean rotor-angle advance (GridRun._warm_start), and restarts a bus "
            "still left at 0 V next to a live one from that neighbour's voltage (listed as 'solver reseed' among "
            "the actions); only the starting point changes, not the equations. A bus left with no in-service "
            "branch (an island of one bus) is outside ANDES' network equations: its voltage, and the machine on "
            'it, are not physical (IEEE 14: G1 alone on bus 1 has shown -60, 35 and -708042 pu, and ANDES once '
            'stopped converging 2 s after such a cut), and such an island is '
            'lost by definition once its machine is rejected. '
            "Per-island figures are in each scenario's result.json in the results folder.",
            "- The lockstep opening time is request + the graph's wall latency + the breaker time, so it varies "
            'by tens of ms between runs; outcomes that change across the g6g7 variants with the same physics show '
            'how sensitive a late cut is to it.',
            '- Why islands were lost (diagnosed 2026-12-01 from the per-island timings below and, for IEEE 39 G6-G7 '
            "and case 2 G3, the exciter outputs recorded through GridRun.run's hook): (1) the machines of the island "
            'were already outside the frequency band at the cut, accelerated by the fault or slipping poles since '
            'before the request, so nothing done after the cut caused it (IEEE 39 G6 and G7 from about 5.9 s, '
            'before the 7.0 s request and after the 5.37 s first slip; Kundur area 2 from 1.53 s, before its '
            '1.567 s request, in a run with the steady-state rotor angles that split it). '
            "(2) After a late cut the slip's voltage dips have driven the exciters up (G6 and G7 at 3.5-3.9 pu "
            'field at the 7.08 s cut, G3 of case 2 at its 6.0 pu ceiling at 8.09 s), and the field winds down over '
            "2 s or more: the island's voltage rises to 1.30 pu (G6-G7, G7 alone after G6's rejection) and 1.80 pu "
            '(G3). The load, constant impedance in ANDES, grows with the square of that voltage: about 840 MW '
            "from G7's 580 MW, so that island's frequency falls to 58.2 Hz. The out-of-step trigger "
            '(docs/testbed_out_of_step.md) first fires at 90 deg (about 5.39 s), which can come before coherency '
            'separates the pair: its separation rule waits until the pair stops decelerating (measured on '
            "grid_sim's frames: two groups from 5.55 s with the rule of commit 19fcf7e, from 5.43 s with 63828a7's "
            'runaway test, with one flicker to two groups at 5.38 s). A trigger answered with '
            'no split used to never ask again (the page before this change: one request, nothing cut); it now '
            're-arms and asks again on newer '
            'angles until an answer splits (the line under its table lists the requests). (3) A surplus no machine '
            'fits '
            'in stays (case 2: G3, 725 MW, on 120 MW of load, about 340 MW at 1.7 pu), and that island speeds up '
            'past the band 2.5 s after the cut. (4) An island with no load whose machines the rejection rule trips '
            '(IEEE 14 G1 alone on bus 1, IEEE 39 G3 multitrip, PJM bus 4, Nordic 44 bus 6000 with its four '
            'machines) is counted as lost by definition, at 0 MW of load lost. (5) The groups were wrong (PJM 5-bus: '
            'an island whose machines slip apart) or the graph did not split. GBnetwork, in runs on a loaded '
            "machine: coherency's grouping of its 394 machines did not reach partitioning within groups_wait_s "
            '(2 s), so partitioning refused the request (REFUSED_STALE_GROUPS); other runs split it (72-73). '
            'Nordic 44 asks at the clearing instant (1.3 s), before its final groups can be told (measured '
            "2026-12-01): on ANDES' own rotor angles the separation rule splits off bus 6000's four machines alone "
            'there (1.80 rad from rest), and the three final groups appear only from 1.60 s; the steady-state '
            "estimates, whose fault-on error hides part of that lead (1.51 rad, below the rule's pi/2), keep one "
            "group, on grid_sim's frames and the recorded bag's alike (they agree within 0.01 rad of rotor angle "
            'since fbd1a33, 0.08 rad before); the same fault cleared 30 ms earlier, which stays one group for 5 s (it '
            'slips at 6.9 s, into other groups), is split the same way 30 ms after its clearing, so a split there '
            'is no evidence yet. Cut off alone, bus 6000 '
            'leaves the main island with the machines of buses 5300 and 6100, which slip later, and it is lost. '
            '(6) EI 33: GENROU_53 and 54 have no turbine '
            'governor in EI_33.xlsx, so their island keeps the speed it had at the cut, and whether that is '
            "inside the band depends on where in the swing the graph's latency puts the cut (lost at 62.3 Hz in a "
            'run that cut 0.41 s after the request, survived at 0.17 s). (7) IEEE 14 (both): the main island is '
            'above 1.2 pu '
            'for the first 10-60 ms of its voltage window, which starts 0.5 s after the cut but only '
            "0.3 s after its 35 % load shed. The decision's load shed and the generation rejection ran as "
            'documented in every split.', '',
            "What failed, island by island (times in s after the cut; frequency is the machines' speed, judged from "
            "the cut; voltage from 0.5 s after it; 'already out at the cut' means the island's machines left the "
            'band before the cut, so no action after the cut caused it):', '']
    out += failure_lines(results) or ['- nothing: every island of every closed-loop run survived.']
    out += ['']
    for r in results:
        fired = [e for e in r['events'] if e['what'] == 'out-of-step trigger']
        if fired:
            first, last = fired[0], fired[-1]
            out += [f'- {r["scenario"]}: the out-of-step trigger requested islanding at {first["at_s"]:.3f} s, the '
                    f'measured angles {math.degrees(first["separation_rad"]):.0f} deg apart'
                    + ('.' if len(fired) == 1 else
                       f'; answered with no split, it re-armed and asked {len(fired)} times in all, the last at '
                       f'{last["at_s"]:.3f} s ({math.degrees(last["separation_rad"]):.0f} deg).')]
    out += ['']
    for fig in figures:
        out += [f'![{fig.stem}]({os.path.relpath(fig, page.parent)})', '']
    return '\n'.join(out)


def _publish(results: list[dict], args: argparse.Namespace, missing: list[str]) -> None:
    """Copy the chosen figures to --figures-dir and write --markdown (called after every scenario)."""
    import shutil

    figures = []
    if args.figures_dir is not None:
        args.figures_dir.mkdir(parents=True, exist_ok=True)
        chosen = {n.strip() for n in args.figure_scenarios.split(',') if n.strip()}
        for r in results:
            if chosen and r['scenario'] not in chosen:
                continue
            figures.append(Path(shutil.copy(r['figure'], args.figures_dir / Path(r['figure']).name)))
    if args.markdown is not None:
        text = markdown(results, args, figures, args.markdown)
        if missing:
            text += f'\nNot in this table (not run, failed, or unfinished when written): {", ".join(missing)}.\n'
        atomic.write_text(args.markdown, text)


def _unstable() -> list[Path]:
    from controlled_islanding.sim.manifest import ManifestError, unstable_scenarios

    try:
        return unstable_scenarios()
    except ManifestError as exc:
        raise CliError(str(exc)) from exc


def run(args: argparse.Namespace) -> int:
    """Run the testbed subcommand."""
    if args.render is not None:
        done = sorted(args.render.glob('*/result.json'))
        if not done:
            raise CliError(f'{args.render}: no */result.json; is it a testbed results folder?')
        results = [json.loads(p.read_text()) for p in done]
        wanted = [p.stem for p in (list(args.scenarios) + (_unstable() if args.all_unstable else []))]
        missing = [n for n in wanted if n not in {r['scenario'] for r in results}]
        _publish(results, args, missing)
        print(json.dumps(results, default=str) if args.json else render(results))
        return 0
    paths = list(args.scenarios) + (_unstable() if args.all_unstable else [])
    if not paths:
        raise CliError('name at least one scenario YAML, or --all-unstable')
    for p in paths:
        if not p.exists():
            raise CliError(f'scenario {p} does not exist')
    if args.rate < 0:
        raise CliError(f'--rate {args.rate} must be 0 (lockstep) or positive')
    stamp = datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
    results_dir = (args.results or Path('results') / f'testbed-{stamp}').resolve()
    if results_dir.exists():
        raise CliError(f'results folder {results_dir} exists; name a new one')
    results_dir.mkdir(parents=True)
    from controlled_islanding.graph.processes import sigterm_as_interrupt

    with sigterm_as_interrupt():  # the baselines run with no supervisor open: a SIGTERM there is marked too
        return _run_all(paths, results_dir, args)


def _run_all(paths: list[Path], results_dir: Path, args: argparse.Namespace) -> int:
    quiet = args.json
    cache: dict = {}
    results: list[dict] = []
    failures: list[str] = []
    for i, path in enumerate(paths):
        _say(quiet, f'testbed: scenario {i + 1}/{len(paths)}: {path}')
        try:
            results.append(run_scenario(path, results_dir, args, quiet, cache))
        except CliError as exc:
            if len(paths) == 1:
                raise
            # One scenario's failure is a row of the table, not the end of it.
            _say(quiet, f'testbed {path.stem}: FAILED: {exc}')
            failures.append(f'{path.stem}: {str(exc).splitlines()[0]}')
            continue
        except KeyboardInterrupt:
            # Ctrl-C or SIGTERM (the supervisor turns it into this): its nodes are stopped by now. Without a
            # testbed.json the folder is unfinished; this file says so and why, for a reader and for --render.
            atomic.write_text(results_dir / INTERRUPTED, json.dumps({
                'interrupted_utc': datetime.now(UTC).isoformat(timespec='seconds'), 'during': path.stem,
                'finished': [r['scenario'] for r in results], 'failed': failures,
                'not_run': [p.stem for p in paths[i + 1:]]}, indent=1) + '\n')
            raise
        _publish(results, args, [p.stem for p in paths[i + 1:]] + failures)
    atomic.write_text(results_dir / 'testbed.json', json.dumps(results, indent=1, default=str))
    if args.json:
        print(json.dumps(results, default=str))
    else:
        print(render(results))
        print(f'results: {results_dir}')
    for failure in failures:
        print(f'testbed: FAILED: {failure}', file=sys.stderr)
    failed = bool(failures) or any(r['decision'] is None or r['restarts'] for r in results)
    return 1 if failed else 0
