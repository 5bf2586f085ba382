"""Scenarios closed-loop: ANDES as the grid (grid_sim), the four nodes deciding, the breakers opening in it.

Each scenario then runs with no action and with the exact MILP cut, in-process, as baselines.

grid_sim publishes the snapshot, PMU frames, trips and the scenario's islanding request, executes the breaker
commands in the simulation (breaker operating time, then the load sheds and generator trips breaker_command
commanded for the decision), keeps simulating and judges every island (sim/closed_loop.py). The baselines apply
the same remedial-action rule (core/remedial.py) offline, through closed_loop.run_offline. The result of a
scenario is its decision, the three runs and a figure; evaluation/testbed_report.py makes the table and the page
from the results.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from controlled_islanding import atomic
from controlled_islanding.graph import GraphError, wan
from controlled_islanding.graph.chaos import FaultInjector
from controlled_islanding.graph.observer import INTERNAL_TOPICS, Observation, Observer, start_pipeline
from controlled_islanding.graph.processes import interrupted
from controlled_islanding.graph.replay import namespace_name
from controlled_islanding.graph.results import INTERRUPTED
from controlled_islanding.graph.summary import _groups_dict, decision_dict
from controlled_islanding.wire import topics

log = logging.getLogger(__name__)



@dataclass(frozen=True)
class TestbedSettings:
    """How the scenarios run.

    Attributes:
        rate: 0 = lockstep (the simulation waits for the graph at the request), R > 0 = R x real time.
        breaker_operating_s: Breaker command -> branch open, s.
        shed_delay_s: Branch open -> the decision's load sheds and generator trips, s.
        run_after_s: Simulate at least this long after the request, s.
        trigger: Where the request comes from: 'scenario' (its time), 'out-of-step' (grid_sim's trigger) or
            'monitor' (the stability monitor's, started beside the four nodes; grid_sim raises none).
        timeout_s: Give up on one closed-loop run after this, wall s.
        namespace: The graph's and grid_sim's namespace ('' = the root one).
        estimator: pmu_ingestion's rotor angle estimator; None: its parameter file's.
        no_baselines: Skip the no-action and MILP runs.
        oracle: Also search offline for the best found (evaluation/oracle.py; long: minutes to hours).
        oracle_step_s: The oracle's largest spacing of request times, s.
        oracle_remedies: Repeat a failed oracle run at a smaller step (OracleSettings.remedies).
        quiet: Progress at debug level, not info.
        hosts: Run the graph on emulated hosts joined by an emulated WAN, e.g. 'pdc,control,substation'
            (graph/wan.parse_hosts); None: all on this host.
        link: With hosts, what the WAN does to each packet.

    """

    __test__ = False  # not a pytest test class, for all its name

    rate: float = 0.0
    breaker_operating_s: float = 0.05
    shed_delay_s: float = 0.2
    run_after_s: float = 3.0
    trigger: str = 'scenario'
    timeout_s: float = 900.0
    namespace: str = ''
    estimator: str | None = None
    no_baselines: bool = False
    oracle: bool = False
    oracle_step_s: float = 0.05
    oracle_remedies: bool = False
    quiet: bool = False
    hosts: str | None = None
    link: wan.LinkModel = wan.LinkModel()


def _say(quiet: bool, text: str) -> None:
    (log.debug if quiet else log.info)('%s', text)


def run_closed_loop(scenario: Path, results: Path, *, rate: float, params: dict[str, float], timeout_s: float,
                    quiet: bool, namespace: str = '', estimator: str | None = None,
                    hosts: dict[str, tuple[str, ...]] | None = None, netns: dict[str, str] | None = None,
                    injector: FaultInjector | None = None, monitor: bool = False) -> tuple[Observation, dict]:
    """Run the four nodes and grid_sim on one scenario; return what the observer saw and grid_sim's report.

    The graph runs in `namespace` ('' = the root one, else e.g. '/area1'), its clock on <namespace>/clock.
    `estimator` overrides pmu_ingestion's (None: its parameter file's). With `hosts` (wan.parse_hosts), each host's
    nodes start in its network namespace `netns[host]` of an emulated WAN (grid_sim on the PDC's host, as the PMUs
    feed it), and this process must be on the operator's (run_on_hosts). `injector` carries out one fault
    (graph/chaos.py); after grid_sim ends, the run waits (at most RECOVERY_WAIT_S) for the graph to recover from it.
    With `monitor`, the stability monitor runs beside the four nodes (params' trigger should then be 'monitor').

    Raises:
        GraphError: A node died, or grid_sim gave no report within timeout_s.

    """
    from controlled_islanding.graph.rosenv import graph_environment
    from controlled_islanding.graph.supervisor import GRAPH, PIPELINE_POLICY, NodeSpec, Supervisor
    from controlled_islanding.safety import signing

    key_dir = signing.default_key_dir()
    signing.init_keys(key_dir)
    operator_key = signing.load_private_key(signing.key_paths(key_dir, 'operator').private)
    obs = Observation()
    logs = results / 'logs'
    report_file = results / 'grid_sim.json'
    remaps = {topics.CLOCK: f'{namespace}{topics.CLOCK}'} if namespace else {}
    own_remaps = injector.remaps(namespace) if injector else {}

    def on_host(executable: str) -> list[str]:
        return wan.prefix(netns[wan.host_of(hosts, executable)]) if hosts else []

    with graph_environment(results / 'ros_log', True) as env:
        if hosts:
            env.update(wan.DDS_ENVIRONMENT)
        with Observer(env, 'testbed_observer', namespace, obs) as observer, \
                Supervisor(env, logs, PIPELINE_POLICY, namespace=namespace, remaps=remaps) as sup:
            obs.restarts, obs.hangs = sup.restarts, sup.hangs
            start_pipeline(sup, results, key_dir, estimator, on_host,
                           lambda executable: own_remaps.get(executable, {}), monitor=monitor)
            _say(quiet, f'started {len(GRAPH) + monitor} nodes (logs in {logs})')
            if injector:
                injector.attach(observer, sup, remaps.get(topics.CLOCK, topics.CLOCK))
            observer.arm(operator_key, True, 30.0, sup.check_alive)
            played = (topics.PMU_FRAMES, topics.NETWORK_SNAPSHOT, topics.BRANCH_STATUS, topics.ISLANDING_REQUEST,
                      topics.CLOCK)
            counts = observer.wait_until_wired(played, INTERNAL_TOPICS, 30.0,
                                               lambda t: remaps.get(t, topics.in_namespace(t, namespace)),
                                               ready=injector.ready if injector else lambda: True)
            # grid_sim's own subscriptions (decision, commands, angles) add one subscriber to none of these.
            grid = sup.start(NodeSpec('grid_sim', 'grid_sim.yaml'), {
                'use_sim_time': False, 'scenario': scenario.resolve(), 'rate': rate, 'report_file': report_file,
                'progress': not quiet, **params, 'min_subscribers': str([f'{t}={n}' for t, n in counts.items()])},
                prefix=on_host('grid_sim'))
            _say(quiet, f'breaker_command armed; grid_sim simulating {scenario.name}'
                        + (f'; chaos: {injector.fault.describe()}' if injector else ''))
            try:
                _follow(observer, sup, grid, injector, timeout_s, logs)
            finally:
                if injector:
                    injector.release()
            if grid.returncode != 0 or not report_file.exists():
                raise GraphError(f'grid_sim failed (exit {grid.returncode}):\n{sup.log_tail("grid_sim")}')
    return obs, json.loads(report_file.read_text())


RECOVERY_WAIT_S = 150.0  # a node's start-up took 14-60 s under load (supervisor.PIPELINE_POLICY); ample beyond it


def _follow(observer: Observer, sup: object, grid: object, injector: FaultInjector | None, timeout_s: float,
            logs: Path) -> None:
    """Supervise until grid_sim ends, then, with a fault, until the graph recovered from it (or it cannot)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        observer.spin_for(0.05)
        sup.supervise(observer.obs.heartbeats_s)
        if injector:
            injector.step()
        if grid.poll() is not None:
            observer.spin_for(0.3)
            break
    else:
        raise GraphError(f'grid_sim did not finish within --timeout {timeout_s} s; logs in {logs}')
    if injector is None:
        return
    deadline = time.monotonic() + RECOVERY_WAIT_S
    while not injector.settled() and time.monotonic() < deadline:
        observer.spin_for(0.05)
        sup.supervise(observer.obs.heartbeats_s)
        injector.step()
    observer.spin_for(1.5)  # every node's /diagnostics once more, the breaker's view after the fault included


def _decision(obs: Observation, request_id: str) -> dict | None:
    return decision_dict(request_id, obs) if request_id in obs.decisions else None


def _coherent_groups(obs: Observation, request_id: str) -> dict:
    """Return the groups computed for this request, in replay's summary form (else the newest up to it)."""
    mine = [m for m in obs.groups if m.request_id == request_id]
    if mine:
        g = mine[-1]
        return {'method': g.method, 'k': int(g.k), 'window_s': g.window_s,
                'groups': [[n for n, k in zip(g.generator_names, g.group, strict=True) if k == i] for i in range(g.k)],
                'unobserved': list(g.unobserved_generator_names)}
    return _groups_dict(obs, obs.decisions[request_id][1].request_stamp if request_id in obs.decisions else None)


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
            'island_shed_mw': list(ev.island_shed_mw), 'remedial_actions': _actions_dict(ev.remedial),
            'disrupted_mw': ev.disrupted_mw, 'optimal': model.optimal_}


def _actions_dict(actions: Any) -> dict:
    return {'shed_mw_by_bus': actions.shed_by_bus, 'trip_generators': list(actions.trip_generators)}


def commanded_actions(decision: dict) -> Any:
    """Return the load sheds and generator trips breaker_command commanded for a decision (summary form)."""
    from controlled_islanding.core.remedial import RemedialActions

    commands = decision['breaker_commands']
    sheds = sorted((int(c['bus']), float(c['amount_mw'])) for c in commands if c['action'] == 'shed')
    return RemedialActions(tuple(b for b, _ in sheds), tuple(mw for _, mw in sheds),
                           tuple(c['generator'] for c in commands if c['action'] == 'trip'))


def check_scenario(path: Path) -> Any:
    """Return the scenario, checked against its case as `simulate` checks it, before any node starts.

    Raises:
        GraphError: The scenario is unreadable, or names a bus, branch or generator its case lacks (the message
            and hint are simulate's).

    """
    from controlled_islanding.sim.andes_sim import SimulationError, prepare_case
    from controlled_islanding.sim.scenario import ScenarioError, load_scenario

    try:
        scenario = load_scenario(path)
        prepare_case(scenario)
    except (ScenarioError, SimulationError) as exc:
        raise GraphError(str(exc)) from None
    return scenario


def run_scenario(path: Path, results: Path, args: TestbedSettings, cache: dict) -> dict:
    """Run one scenario closed-loop, then the baselines; return its result (figures go under results).

    `cache` keeps the no-action runs of the scenarios seen so far, by their simulation (variants share one), and
    the oracle's runs.

    Raises:
        GraphError: The scenario is unreadable, a node died, grid_sim gave no report in time, or an in-process
            run could not start.

    """
    from controlled_islanding.sim.closed_loop import ClosedLoopError

    try:
        if args.hosts:
            return _on_hosts(path, results, args)
        return _run_scenario(path, results, args, cache)
    except ClosedLoopError as exc:
        raise GraphError(f'{path}: {exc}') from exc


def host_roles(hosts: str) -> dict[str, tuple[str, ...]]:
    """Return host name -> roles of a --hosts value, if emulated hosts can be built here.

    Raises:
        GraphError: The value is not valid, or the emulated WAN cannot be built here (it needs root).

    """
    try:
        roles = wan.parse_hosts(hosts)
    except ValueError as exc:
        raise GraphError(str(exc)) from exc
    why = wan.unavailable_reason()
    if why:
        raise GraphError(why)
    return roles


def run_on_hosts(hosts: dict[str, tuple[str, ...]], link: wan.LinkModel, work_dir: Path, module: str,
                 spec: dict) -> dict:
    """Build the emulated WAN and run `python -m module SPEC` on the operator's host; return its JSON answer.

    The child gets `spec` plus 'hosts', 'netns' and 'wan_control' (the partition file), and writes its answer
    (or {'error': ...}) to spec['answer'], a file in `work_dir`. The answer gains 'wan': the network and its
    statistics.

    Raises:
        GraphError: The WAN could not be built, or the child failed (its error).

    """
    answer = work_dir / 'on_hosts_answer.json'
    spec_file = work_dir / 'on_hosts.json'
    work_dir.mkdir(parents=True, exist_ok=True)
    with wan.EmulatedWan(list(hosts), link, work_dir) as net:
        atomic.write_text(spec_file, json.dumps({**spec, 'hosts': hosts, 'netns': net.namespaces,
                                                 'wan_control': str(net.control_file), 'answer': str(answer)},
                                                default=str))
        status = net.run_on_operator([sys.executable, '-m', module, str(spec_file)])
        info = {'hosts': {h: list(r) for h, r in hosts.items()}, 'link': asdict(link), 'addresses': net.addresses,
                'namespaces': net.namespaces}
    result = json.loads(answer.read_text()) if answer.exists() else {
        'error': f'{module} on the operator host exited with {status} and no answer'}
    if 'error' in result:
        raise GraphError(result['error'])
    result['wan'] = {**info, 'stats': net.stats}
    return result


def on_hosts_main(spec_file: str, work: Callable[[dict], dict]) -> int:
    """Run `work(spec)` as run_on_hosts's child: its answer, or its GraphError, to the spec's answer file."""
    spec = json.loads(Path(spec_file).read_text())
    spec['hosts'] = {h: tuple(r) for h, r in spec['hosts'].items()}
    # This process is not the command line's: its progress goes to the same stderr, in the same form.
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter('testbed: %(message)s'))
    package = logging.getLogger('controlled_islanding')
    package.handlers[:] = [handler]
    package.setLevel(logging.INFO)
    package.propagate = False
    try:
        result = work(spec)
    except GraphError as exc:
        result = {'error': str(exc)}
    except KeyboardInterrupt:
        return 130
    atomic.write_text(Path(spec['answer']), json.dumps(result, indent=1, default=str))
    return 0 if 'error' not in result else 2


def _on_hosts(path: Path, results: Path, args: TestbedSettings) -> dict:
    scenario = check_scenario(path)
    result = run_on_hosts(host_roles(args.hosts), args.link, results / scenario.name / 'wan', __name__,
                          {'path': str(path), 'results': str(results), 'settings': asdict(args)})
    atomic.write_text(results / scenario.name / 'result.json', json.dumps(result, indent=1, default=str))
    return result


def _scenario_on_host(spec: dict) -> dict:
    settings = dict(spec['settings'], link=wan.LinkModel(**spec['settings']['link']))
    return _run_scenario(Path(spec['path']), Path(spec['results']), TestbedSettings(**settings), {},
                         hosts=spec['hosts'], netns=spec['netns'])


def _run_scenario(path: Path, results: Path, args: TestbedSettings, cache: dict,
                  hosts: dict[str, tuple[str, ...]] | None = None, netns: dict[str, str] | None = None) -> dict:
    import numpy as np

    from controlled_islanding.sim.closed_loop import LoopConfig, run_offline

    quiet = args.quiet
    scenario = check_scenario(path)
    out = results / scenario.name
    out.mkdir(parents=True, exist_ok=hosts is not None)  # on hosts, the WAN's folder is in it already
    config = LoopConfig(breaker_operating_s=args.breaker_operating_s, shed_delay_s=args.shed_delay_s,
                        run_after_s=args.run_after_s)
    params = {'breaker_operating_s': args.breaker_operating_s, 'shed_delay_s': args.shed_delay_s,
              'run_after_s': args.run_after_s, 'trigger': args.trigger.replace('-', '_')}
    _say(quiet, f'{scenario.name}: closed loop')
    obs, report = run_closed_loop(path, out, rate=args.rate, params=params, timeout_s=args.timeout_s, quiet=quiet,
                                  namespace=namespace_name(args.namespace), estimator=args.estimator, hosts=hosts,
                                  netns=netns, monitor=args.trigger == 'monitor')
    decision = _decision(obs, report['request_id'])
    loop = report['outcome']
    if args.trigger != 'scenario' and math.isfinite(loop['request_s']):
        # The baselines and the figure answer the request grid_sim's trigger made, not the scenario's (with none,
        # the run was judged from the scenario's own request time, as the no-action run is).
        scenario = replace(scenario, request_s=loop['request_s'],
                           end_s=max(scenario.end_s, loop['request_s'] + args.run_after_s))
    result: dict[str, Any] = {'scenario': scenario.name, 'path': str(path), 'trigger': args.trigger,
                              'decision': decision, 'coherent_groups': _coherent_groups(obs, report['request_id']),
                              'commanded_actions': [] if decision is None else decision['breaker_commands'],
                              'closed_loop': loop, 'events': report['events'],
                              'restarts': [r.__dict__ for r in obs.restarts], 'runs': {'dtw': loop},
                              'graph_topics': obs.graph_topics,
                              'estimator': next((d['estimator'] for name, d in obs.diagnostics.items()
                                                 if name.endswith('pmu_ingestion') and 'estimator' in d), None)}
    traj = dict(np.load(f'{out / "grid_sim.json"}.npz'))
    trajectories = {'dtw': traj}
    if loop['simulation_failed'] is not None and decision and decision['split'] and loop['opened_s'] is not None:
        # The graph's answer stands; the simulation of it is redone offline, the same cut and commanded actions at
        # the same time, with closed_loop.REMEDIES.
        _say(quiet, f'{scenario.name}: the closed loop\'s {loop["simulation_failed"]}; its actions re-run offline')
        bus_island = {b: isl['island'] for isl in decision['islands'] for b in isl['buses']}
        again = run_offline(scenario, 'dtw', cut_branch_ids=loop['cut_branch_ids'], bus_island=bus_island,
                            actions=commanded_actions(decision), opened_s=loop['opened_s'], config=config,
                            progress=not quiet)
        if again.simulation_failed is None:
            loop = dict(again.summary(), remedy=f'the closed loop\'s {loop["simulation_failed"]}; its cut and '
                        f'actions re-run offline at the same time with {again.remedy or "the same step"}')
            result['runs']['dtw'] = loop
            traj = dict(traj, t_s=again.t_s, delta_rad=again.delta_rad, bus_v_pu=again.bus_v_pu)
            trajectories['dtw'] = traj
    if not args.no_baselines:
        key = (scenario.simulation_key(), args.run_after_s)
        if key not in cache:
            _say(quiet, f'{scenario.name}: no action (ANDES in-process)')
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
                _say(quiet, f'{scenario.name}: MILP cut {milp["cut_branch_ids"]} (ANDES in-process)')
                m = run_offline(scenario, 'milp', cut_branch_ids=milp['cut_branch_ids'], bus_island=milp['bus_island'],
                                opened_s=loop['opened_s'], config=config, progress=not quiet)
                result['runs']['milp'] = m.summary()
                trajectories['milp'] = {'t_s': m.t_s, 'delta_rad': m.delta_rad, 'bus_v_pu': m.bus_v_pu}
    if args.oracle:
        _oracle(scenario, config, args, decision, cache.get((scenario.simulation_key(), args.run_after_s)),
                cache.setdefault('oracle runs', {}), result, trajectories)
    result['figure'] = str(_figure(scenario, result, trajectories, traj, out / f'{scenario.name}_closed_loop.png'))
    atomic.write_text(out / 'result.json', json.dumps(result, indent=1, default=str))
    return result


def _oracle(scenario: Any, config: Any, args: TestbedSettings, decision: dict | None, no_action: Any, runs: dict,
            result: dict, trajectories: dict) -> None:
    """Search for the best found (evaluation/oracle.py) and add it to the result as the run 'oracle'.

    `runs` keeps the searches' runs across scenarios: variants of one simulation share all but the graph's cut.
    """
    from controlled_islanding.evaluation.oracle import OracleError, OracleSettings, search

    _say(args.quiet, f'{scenario.name}: oracle, the best found (ANDES in-process, one run per candidate: long)')
    graph = ({b: isl['island'] for isl in decision['islands'] for b in isl['buses']}
             if decision and decision['split'] else None)
    try:
        found = search(scenario, config, OracleSettings(max_step_s=args.oracle_step_s, remedies=args.oracle_remedies),
                       graph_islands=graph,
                       no_action=no_action, runs=runs, say=lambda text: _say(args.quiet, text))
    except OracleError as exc:  # the closed loop's result stands; the page says why there is no best found
        log.warning('%s: no oracle: %s', scenario.name, exc)
        result['oracle_search'] = {'error': str(exc)}
        return
    best = found.summary()
    if best is None:  # no action's run failed too, and every candidate's
        result['oracle_search'] = found.search_summary()
        return
    result['runs']['oracle'] = best
    run = found.best.outcome
    trajectories['oracle'] = {'t_s': run.t_s, 'delta_rad': run.delta_rad, 'bus_v_pu': run.bus_v_pu}


def _figure(scenario: Any, result: dict, trajectories: dict, loop_traj: dict, path: Path) -> Path:
    from controlled_islanding.evaluation import plots

    decision = result['decision'] or {}
    bus_island = {b: isl['island'] for isl in decision.get('islands', []) for b in isl['buses']}
    names = [str(n) for n in loop_traj['generator_names']]
    gen_island = [bus_island.get(int(b), 0) for b in loop_traj['generator_buses']]
    panels = []
    for label in ('no action', 'dtw', 'milp', 'oracle'):
        if label not in trajectories or (label == 'milp' and 'milp' not in result['runs']):
            continue
        run = result['runs'][label]
        tr = trajectories[label]
        panels.append(plots.ClosedLoopPanel(
            label={'dtw': 'closed loop (DTW decision)', 'milp': 'exact MILP cut', 'no action': 'no action',
                   'oracle': 'best found (oracle)'}[label],
            t_s=tr['t_s'], delta_rad=tr['delta_rad'], bus_v_pu=tr['bus_v_pu'], opened_s=run.get('opened_s'),
            survived=run['all_survived'], failed=run.get('simulation_failed'),
            served_pct=run.get('load_served_pct'), request_s=run['request_s'] if label == 'oracle' else None))
    from controlled_islanding.sim.closed_loop import LoopConfig

    band = LoopConfig()
    return plots.plot_closed_loop(panels, names, gen_island, path, request_s=scenario.request_s,
                                  title=f'{scenario.name}: rotor angles by island and bus voltages',
                                  v_limits_pu=(band.v_min_pu, band.v_max_pu))


def run_all(paths: list[Path], results_dir: Path, settings: TestbedSettings,
            after_each: Callable[[list[dict], list[str]], None] = lambda results, missing: None) -> tuple[
                list[dict], list[str]]:
    """Run every scenario into results_dir (made already); return the results and the failures, one line each.

    One scenario's failure is a line of the failures, not the end of the run (unless it is the only scenario: then
    its GraphError is raised). `after_each(results, missing)` is called after each scenario, `missing` naming
    those not in `results` (yet). Ctrl-C or SIGTERM marks the folder (INTERRUPTED.json) and is raised on.
    """
    cache: dict = {}
    results: list[dict] = []
    failures: list[str] = []
    for i, path in enumerate(paths):
        _say(settings.quiet, f'scenario {i + 1}/{len(paths)}: {path}')
        try:
            results.append(run_scenario(path, results_dir, settings, cache))
        except BaseException as exc:
            if isinstance(exc, KeyboardInterrupt) or interrupted() is not None:
                # Ctrl-C or SIGTERM (the supervisor turns it into this; inside rclpy it may come out as another
                # error): its nodes are stopped by now. Without a testbed.json the folder is unfinished; this file
                # says so and why, for a reader and for --render.
                atomic.write_text(results_dir / INTERRUPTED, json.dumps({
                    'interrupted_utc': datetime.now(UTC).isoformat(timespec='seconds'), 'during': path.stem,
                    'finished': [r['scenario'] for r in results], 'failed': failures,
                    'not_run': [p.stem for p in paths[i + 1:]]}, indent=1) + '\n')
                if isinstance(exc, KeyboardInterrupt):
                    raise
                raise KeyboardInterrupt(f'interrupted ({exc})') from exc
            if not isinstance(exc, GraphError) or len(paths) == 1:
                raise
            _say(settings.quiet, f'{path.stem}: FAILED: {exc}')
            failures.append(f'{path.stem}: {str(exc).splitlines()[0]}')
            continue
        after_each(results, [p.stem for p in paths[i + 1:]] + failures)
    atomic.write_text(results_dir / 'testbed.json', json.dumps(results, indent=1, default=str))
    return results, failures


if __name__ == '__main__':
    sys.exit(on_hosts_main(sys.argv[1], _scenario_on_host))
