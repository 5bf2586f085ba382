"""Replay one bag through the node graph, as separate processes over DDS, and write its results folder.

The four pipeline nodes and a recorder start under a supervisor (each its own process, with its config/*.yaml),
the breaker node is armed with a signed operator request, and bag_player plays the bag (ground truth withheld)
once the graph is wired. One observer (graph.observer) sees requests, decisions, commands and diagnostics; the
results folder gets the summary (graph.summary), the output bag, the audit log, the node logs and the figures.
With hosts, the graph runs on emulated hosts joined by an emulated WAN (graph.wan). With the trigger 'monitor', the
stability monitor runs beside the four nodes and is the only source of requests: the bag's own are not played.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import statistics
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

from controlled_islanding import atomic
from controlled_islanding.graph import GraphError, wan
from controlled_islanding.graph.observer import INTERNAL_TOPICS, Observation, Observer, start_pipeline
from controlled_islanding.graph.results import running
from controlled_islanding.graph.summary import graph_failure, percentile, render, summarize
from controlled_islanding.wire import topics
from controlled_islanding.wire.bagmeta import unreadable

log = logging.getLogger(__name__)

# After the bag ends, a request still unanswered this long (wall, s) is reported as undecided. The nodes
# give up after at most 2 s (coherency request_wait_s, partitioning groups_wait_s), so this is ample.
SETTLE_S = 8.0
# With the monitor as the trigger, nothing in the bag says a request is coming: after the bag ends, the graph gets this
# long (wall, s) for the last frames to reach the monitor and its request to appear; real time, a frame takes ms.
MONITOR_SETTLE_S = 1.0
# Once every request is decided, how long breaker_command may take to handle the decisions (wall, s); it takes
# milliseconds, so only a node without its audit log, or a dead one, reaches this.
BREAKER_WAIT_S = 5.0


@dataclass(frozen=True)
class ReplayOptions:
    """How one bag is replayed.

    Attributes:
        fast: As fast as possible (lockstep at requests), else at `rate`.
        rate: Playback speed against real time.
        probe_hz: Extra islanding requests a second once the first decision is out (a latency benchmark), Hz.
        timeout_s: Wall time after which the replay gives up, s.
        figures: Draw rotor_angles.png and network.png.
        quiet: Progress at debug level, not info.
        arm: Arm breaker_command (else decisions are refused and audited).
        record: Run the recorder (the output bag, and with it the figures).
        isolate: A private domain even if ROS_DOMAIN_ID is set.
        namespace: The graph's namespace ('' = the root one, else e.g. '/area1').
        estimator: pmu_ingestion's rotor angle estimator, 'steady_state' or 'dse'; None: its parameter file's.
        in_process: The nodes in this process (graph/composed.py), fresh ones in a fresh Context, not as processes
            under a supervisor: what a warm regression worker (graph/worker.py) runs.
        trigger: Where the islanding requests come from: 'bag' (the bag's own, the paper's operator) or 'monitor'
            (the stability monitor's alone; the bag's are withheld).

    """

    fast: bool = False
    rate: float = 1.0
    probe_hz: float = 0.0
    timeout_s: float = 120.0
    figures: bool = True
    quiet: bool = False
    arm: bool = True
    record: bool = True
    isolate: bool = True
    namespace: str = ''
    estimator: str | None = None
    in_process: bool = False
    trigger: str = 'bag'

    @property
    def monitor(self) -> bool:
        """Whether the stability monitor is the source of requests."""
        return self.trigger == 'monitor'

    def say(self, text: str, *args: object) -> None:
        """Log one progress line (debug when quiet)."""
        (log.debug if self.quiet else log.info)(text, *args)


def bag_topics(bag: Path) -> dict[str, int]:
    """Return message counts by topic of a bag.

    Raises:
        GraphError: The bag cannot be read.

    """
    from rosbags.highlevel import AnyReader

    from controlled_islanding.wire.interfaces import typestore

    try:
        with AnyReader([bag], default_typestore=typestore()) as reader:
            counts: dict[str, int] = {}
            for c in reader.connections:
                counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
            return counts
    except Exception as exc:  # rosbags raises many error types for an unreadable bag
        raise GraphError(f'cannot read the bag: {unreadable(bag, exc)}') from exc


def namespace_name(namespace: str) -> str:
    """Return a namespace as ROS writes it ('' for the root one, else '/area1').

    Raises:
        GraphError: It is not a ROS namespace.

    """
    from rclpy.exceptions import InvalidNamespaceException
    from rclpy.validate_namespace import validate_namespace

    name = f'/{namespace.strip("/")}' if namespace.strip('/') else ''
    try:
        validate_namespace(name or '/')
    except InvalidNamespaceException as exc:
        raise GraphError(f'--namespace {namespace!r} is not a ROS namespace: {exc}') from exc
    return name


def run_graph(bag: Path, results: Path, options: ReplayOptions, hosts: dict[str, tuple[str, ...]] | None = None,
              netns: dict[str, str] | None = None) -> tuple[Observation, dict]:
    """Run the node graph on a bag; return what the observer saw and the player's speed report.

    The graph runs in `options.namespace`, with its own /clock there (`<namespace>/clock`). With `hosts`
    (wan.parse_hosts), each host's nodes start in its network namespace `netns[host]` of an emulated WAN, and this
    process must be on the operator's (see _replay_on_hosts).

    Raises:
        GraphError: The bag is unreadable, a node died, or no decision came in time.

    """
    from controlled_islanding.graph.composed import ComposedGraph
    from controlled_islanding.graph.rosenv import graph_environment
    from controlled_islanding.graph.supervisor import GRAPH, MONITOR, PIPELINE_POLICY, PLAYER, RECORDER, Supervisor
    from controlled_islanding.ros.diagnostics import writers_matched
    from controlled_islanding.ros.spin import settle_heap
    from controlled_islanding.safety import signing

    # The demo and replays sign with the user's keys, made on first use, outside the repository.
    key_dir = signing.default_key_dir()
    signing.init_keys(key_dir)
    operator_key = signing.load_private_key(signing.key_paths(key_dir, 'operator').private)
    withheld = [topics.ISLANDING_REQUEST] if options.monitor else []
    nodes = (*GRAPH, MONITOR) if options.monitor else GRAPH
    # A composed graph's player has read the bag by the time the graph is wired; reading it here too would cost
    # as much CPU again (rosbags parses each topic's QoS from YAML).
    in_bag = {} if options.in_process else bag_topics(bag)
    ns = namespace_name(options.namespace)
    # Two replays on one domain have two bag clocks: each graph's /clock is its own.
    remaps = {topics.CLOCK: f'{ns}{topics.CLOCK}'} if ns else {}

    def on_host(executable: str) -> list[str]:
        return wan.prefix(netns[wan.host_of(hosts, executable)]) if hosts else []

    obs = Observation()
    obs.phases_unix['begun'] = time.time()
    logs = results / 'logs'
    report_file = results / 'player_report.json'
    with graph_environment(results / 'ros_log', options.isolate) as env:
        if hosts:
            env.update(wan.DDS_ENVIRONMENT)
        with contextlib.ExitStack() as stack:
            if options.in_process:
                # The observer joins the graph's Context: one participant, so wiring is exact, not waited out.
                sup = stack.enter_context(ComposedGraph(env, logs, namespace=ns, remaps=remaps))
                observer = stack.enter_context(Observer(env, 'replay_observer', ns, obs, context=sup.context))
            else:
                observer = stack.enter_context(Observer(env, 'replay_observer', ns, obs))
                sup = stack.enter_context(Supervisor(env, logs, PIPELINE_POLICY, namespace=ns, remaps=remaps))
            obs.restarts, obs.hangs = sup.restarts, sup.hangs
            start_pipeline(sup, results, key_dir, options.estimator, on_host, monitor=options.monitor)
            if options.record:
                sup.start(RECORDER, {'use_sim_time': True, 'output': results / 'output_bag'},
                          prefix=on_host(RECORDER.executable))
            # The player loads its bag and is discovered while the nodes start; it plays once told to.
            go_file = results / 'player_go.json'
            player = sup.start(PLAYER, {'bag': bag.resolve(), 'as_fast_as_possible': options.fast,
                                        'rate': options.rate, 'report_file': report_file,
                                        'clock_min_step_s': 0.05 if options.fast else 0.0, 'go_file': go_file,
                                        **({'withhold_topics': str(withheld)} if withheld else {})},
                               prefix=on_host(PLAYER.executable))
            obs.phases_unix['nodes_started'] = time.time()
            options.say('started %d nodes%s (logs in %s)', len(nodes), ' and the recorder' if options.record else '',
                        logs)
            observer.arm(operator_key, options.arm, 20.0, sup.check_alive)
            obs.phases_unix['armed'] = time.time()
            options.say('breaker_command %s; playing the bag', 'armed' if options.arm else 'left disarmed')

            def player_alive() -> None:
                if player.poll() is not None:
                    tail = sup.log_tail('bag_player')
                    separator = '\n' if '\n' in tail else ' '  # a refusal to start is one line, a traceback many
                    raise GraphError(f'bag_player failed:{separator}{tail}')

            def topic_name(t: str) -> str:
                return remaps.get(t, topics.in_namespace(t, ns))

            if options.in_process:
                _await_matched(observer, sup, player_alive, options.timeout_s)
                player_node = sup.node(PLAYER.executable)
                in_bag = Counter(t for t, _, _ in player_node.messages)
                counts = {t: sup.readers(topic_name(t), observer.node) for t in [*player_node.pubs, topics.CLOCK]}
            else:
                played = [t for t in in_bag if t not in topics.TRUTH_TOPICS and t not in withheld] + [topics.CLOCK]
                # The player starts once every subscriber now in the graph (this observer included) matches it.
                # Kundur at load 9 lost the rotor angles before its request without the writers' match
                # (writers_matched).
                counts = observer.wait_until_wired(
                    played, INTERNAL_TOPICS, 20.0, topic_name,
                    ready=lambda: all(writers_matched(obs.diagnostics.get(f'/{spec.executable}', {}),
                                                      observer.node.count_subscribers) for spec in nodes),
                    check=player_alive)
            obs.phases_unix['wired'] = time.time()
            atomic.write_text(go_file, json.dumps({'min_subscribers': [f'{t}={n}' for t, n in counts.items()]}))
            settle_heap()  # this observer's timestamps must not wait on a full garbage collection either
            _watch(observer, sup, player, options, 0 if options.monitor else in_bag.get(topics.ISLANDING_REQUEST, 0),
                   logs, results / 'breaker_audit.jsonl', nodes)
            if options.in_process and 'decided' in obs.phases_unix:
                # What each node counted once it has taken everything, read from the node itself.
                sup.settle()
                obs.diagnostics.update(sup.diagnostics())
            obs.phases_unix['stopped'] = time.time()
            obs.cpu_s = sup.cpu_s
    report = json.loads(report_file.read_text()) if report_file.exists() else {}
    return obs, report


def _await_matched(observer: Observer, graph: object, check: Callable[[], None], made_s: float,
                   timeout_s: float = 20.0) -> None:
    """Wait until a composed graph's nodes are made, then until its endpoints and its observer's are matched.

    Making may take up to made_s (the player reads its bag meanwhile). In one participant endpoints match as they
    are made (graph.unmatched), so only endpoints whose QoS cannot match reach timeout_s, which is logged.

    Raises:
        GraphError: A node failed (from check), or was not made within made_s.

    """
    def made() -> bool:
        check()
        return graph.made()

    def wired() -> bool:
        check()
        return not graph.unmatched(observer.node)

    if not observer.spin_for(made_s, made):
        raise GraphError(f'not made within {made_s:g} s: {"; ".join(graph.unmatched(observer.node))}')
    if not observer.spin_for(timeout_s, wired):
        log.warning('playing although not wired after %g s: %s', timeout_s, '; '.join(graph.unmatched(observer.node)))


def breaker_done(audit_log: Path, obs: Observation) -> bool:
    """Whether breaker_command has handled every decision seen, and every command it recorded for one was seen.

    Its audit log has a record for each decision it handles (a command, a refusal, no split), on disk before any
    command of it is published: the exact end of a decision's consequences, where a fixed wait only guesses it.
    """
    wanted = {msg.decision_id for _, msg in obs.decisions.values()}
    handled, commanded = set(), set()
    with contextlib.suppress(OSError):
        for line in audit_log.read_text().splitlines():
            try:
                record = json.loads(line)
            except ValueError:  # the line being written
                continue
            if record.get('decision_id') in wanted:
                handled.add(record['decision_id'])
                commanded.update(c['command_id'] for c in record.get('commands', []))
    return handled == wanted and commanded <= {c.command_id for _, c in obs.commands}


def _watch(observer: Observer, sup: object, player: subprocess.Popen, options: ReplayOptions, n_requests: int,
           logs: Path, audit_log: Path, nodes: tuple = ()) -> None:
    """Follow the play until every request is answered (or the bag ended SETTLE_S ago); send probe requests.

    With the monitor as the trigger, the play is over no sooner than MONITOR_SETTLE_S after the bag ended: the
    monitor's request for the last frames may still be on its way. `nodes`: the graph's, whose diagnostics are awaited.
    """
    from controlled_islanding_msgs.msg import IslandingRequest

    from controlled_islanding.ros.endpoints import qos_for

    obs = observer.obs
    probe_pub = observer.node.create_publisher(IslandingRequest, topics.relative(topics.ISLANDING_REQUEST),
                                               qos_for(topics.ISLANDING_REQUEST))
    deadline = time.monotonic() + options.timeout_s
    probe_period = 1.0 / options.probe_hz if options.probe_hz > 0 else None
    next_probe = None
    done_at = None
    exited_at = math.inf  # when the player was seen to have exited, monotonic s
    while time.monotonic() < deadline:
        # Messages wake the spin at once; the period only bounds how late the player's exit or a probe is seen.
        observer.spin_for(0.01 if probe_period else 0.05)
        sup.supervise(obs.heartbeats_s)
        bag_done = player.poll() is not None
        if bag_done and 'player_exited' not in obs.phases_unix:
            obs.phases_unix['player_exited'] = time.time()
            exited_at = time.monotonic()
        if bag_done and player.returncode != 0:
            raise GraphError(f'bag_player failed:\n{sup.log_tail("bag_player")}')
        answered = sum(1 for r in obs.requests if r in obs.decisions)
        if probe_period and obs.decisions and not bag_done:
            now = time.monotonic()
            next_probe = next_probe or now
            if now >= next_probe:
                probe = IslandingRequest(request_id=f'probe-{len(obs.requests)}', reason='latency probe')
                clock_s = obs.groups[-1].header.stamp if obs.groups else None
                if clock_s is not None:
                    probe.header.stamp = clock_s
                    obs.requests[probe.request_id] = time.monotonic()
                    probe_pub.publish(probe)
                next_probe += probe_period
        settled = not options.monitor or time.monotonic() - exited_at >= MONITOR_SETTLE_S
        if bag_done and settled and answered >= n_requests and all(r in obs.decisions for r in obs.requests):
            if not observer.spin_for(BREAKER_WAIT_S, lambda: breaker_done(audit_log, obs)):
                options.say('breaker_command handled not every decision within %g s', BREAKER_WAIT_S)
            # The summary gives each node's last /diagnostics (sent every second): wait, at most 1.5 s, for one
            # sent after the play, or a short bag's counts can predate its frames. A composed graph's are read
            # from its nodes instead (run_graph).
            limit = time.monotonic() + (0.0 if options.in_process else 1.5)
            while time.monotonic() < limit and any(
                    obs.heartbeats_s.get(f'/{spec.executable}', -math.inf) < exited_at for spec in nodes):
                observer.spin_for(0.05)
            obs.phases_unix['decided'] = time.time()
            return
        if bag_done:
            done_at = done_at or time.monotonic()
            if time.monotonic() - done_at > SETTLE_S:
                options.say('no decision for some requests %g s after the bag ended', SETTLE_S)
                return
    raise GraphError(f'no decision for every request within --timeout {options.timeout_s} s; logs in {logs}')


def write_figures(bag: Path, results: Path, summary: dict) -> list[Path]:
    """Draw rotor angles (estimated, from the output bag) by group and the network by island."""
    import numpy as np
    from rosbags.highlevel import AnyReader

    from controlled_islanding.evaluation import plots
    from controlled_islanding.wire.interfaces import typestore
    from controlled_islanding.wire.messages import grid_from_snapshot, stamp_s

    out_bag = results / 'output_bag'
    t, rows, names, grid, trips = [], [], None, None, []
    with AnyReader([out_bag], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic == topics.ROTOR_ANGLES:
                msg = reader.deserialize(raw, conn.msgtype)
                names = list(msg.generator_names)
                t.append(stamp_s(msg.header.stamp))
                rows.append(np.where(np.asarray(msg.valid, bool), np.asarray(msg.angle_rad, float), np.nan))
            elif conn.topic == topics.NETWORK_SNAPSHOT and grid is None:
                grid = grid_from_snapshot(reader.deserialize(raw, conn.msgtype))
            elif conn.topic == topics.BRANCH_STATUS:
                msg = reader.deserialize(raw, conn.msgtype)
                if not msg.in_service:
                    trips.append(msg.branch_id)
    written = []
    group_of = {}
    for i, members in enumerate(summary['coherent_groups'].get('groups', [])):
        group_of.update(dict.fromkeys(members, i))
    if rows and names:
        order = np.argsort(t)
        t_arr = np.asarray(t)[order]
        angles = np.vstack(rows)[order].T
        angles = angles - angles[:, :1]
        marks = {f'islanding request {i + 1}' if len(summary['decisions']) > 1 else 'islanding request':
                 d['request_stamp_s'] - t_arr[0] for i, d in enumerate(summary['decisions'])}
        written.append(plots.plot_rotor_angles(
            t_arr - t_arr[0], angles, names, [group_of.get(n, 0) for n in names], results / 'rotor_angles.png',
            title=f'estimated rotor angles, {bag.name}', marks_s=marks))
    if grid is not None and summary.get('split') is not None:
        grid = grid.with_outages(b for b in dict.fromkeys(trips) if b in {x.branch_id for x in grid.branches})
        bus_island = {b: isl['island'] for isl in summary['islands'] for b in isl['buses']}
        written.append(plots.plot_network(grid, bus_island, summary['cut_branch_ids'], results / 'network.png',
                                          title=f'islands and cut lines, {bag.name}'))
    return written


def replay(bag: Path, results: Path | None, *, fast: bool = False, rate: float = 1.0, probe_hz: float = 0.0,
           timeout_s: float = 120.0, figures: bool = True, quiet: bool = False, arm: bool = True,
           record: bool = True, isolate: bool = True, namespace: str = '', estimator: str | None = None,
           hosts: str | None = None, link: wan.LinkModel | None = None, force: bool = False,
           in_process: bool = False, trigger: str = 'bag') -> dict:
    """Replay a bag through the graph; write the results folder; return the summary.

    The options are ReplayOptions'. `hosts` (e.g. 'pdc,control,substation') runs the graph on emulated hosts
    joined by a WAN with `link`. `results` is claimed as graph/results.py says (`force`: replace a finished run).

    Raises:
        GraphError: Bad options, an unreadable bag, a failed node or a missing decision.

    """
    host_roles = None
    if hosts:
        try:
            host_roles = wan.parse_hosts(hosts)
        except ValueError as exc:
            raise GraphError(str(exc)) from exc
        why = wan.unavailable_reason()
        if why:
            raise GraphError(why)
    if hosts and in_process:
        raise GraphError('emulated hosts need each node in a process of its own, not in this one')
    if not bag.exists():
        raise GraphError(f'bag {bag} does not exist')
    if rate <= 0:
        raise GraphError(f'--rate {rate} must be positive')
    if trigger not in ('bag', 'monitor'):
        raise GraphError(f'--trigger {trigger!r} must be bag or monitor')
    if trigger == 'monitor' and (fast or probe_hz):
        # The player holds the graph in step only at requests it plays; at a request it did not play, its /clock
        # runs on, and breaker_command refuses a decision whose request is older than its max_decision_age_s.
        raise GraphError('--trigger monitor replays in real time (or at --rate): not with --fast or --probe-hz, since '
                         'the player holds the graph in step only at the requests it plays itself')
    options = ReplayOptions(fast=fast, rate=rate, probe_hz=probe_hz, timeout_s=timeout_s, figures=figures,
                            quiet=quiet, arm=arm, record=record, isolate=isolate, namespace=namespace_name(namespace),
                            estimator=estimator, in_process=in_process, trigger=trigger)
    if results is None:
        stamp = datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
        results = Path('results') / f'replay-{bag.name}-{stamp}'
    # Ctrl-C or SIGTERM (the supervisor turns it into KeyboardInterrupt) comes out with the nodes stopped; without
    # summary.json the folder is unfinished, and its marker says so to a reader, as a testbed's does.
    with running(results, force, bag=str(bag)) as results:
        if host_roles:
            return _replay_on_hosts(bag, results, host_roles, link or wan.LinkModel(), options)
        return _replay_here(bag, results, options)


def _replay_here(bag: Path, results: Path, options: ReplayOptions, hosts: dict[str, tuple[str, ...]] | None = None,
                 netns: dict[str, str] | None = None) -> dict:
    """Run the graph from this process, summarize, draw, and write the summary into `results` (made already)."""
    obs, report = run_graph(bag, results, options, hosts, netns)
    summary = summarize(bag, results, obs, report)
    summary['namespace'] = options.namespace
    summary['trigger'] = options.trigger
    summary['estimator'] = next((d['estimator'] for name, d in obs.diagnostics.items()
                                 if name.endswith('pmu_ingestion') and 'estimator' in d), options.estimator)
    if options.figures and options.record:
        try:
            summary['figures'] = [str(p) for p in write_figures(bag, results, summary)]
        except Exception as exc:  # a figure must never hide the decision
            options.say('figures failed: %s', exc)
    _write_summary(results, summary)
    return summary


def _write_summary(results: Path, summary: dict) -> None:
    atomic.write_text(results / 'summary.json', json.dumps(summary, indent=2, default=str))
    atomic.write_text(results / 'summary.txt', render(summary) + '\n')


def _replay_on_hosts(bag: Path, results: Path, hosts: dict[str, tuple[str, ...]], link: wan.LinkModel,
                     options: ReplayOptions) -> dict:
    """Build the emulated WAN, run the replay from a fresh process on the operator's host, add the WAN to it."""
    spec = results / 'replay_on_hosts.json'
    with wan.EmulatedWan(list(hosts), link, results) as net:
        spec.write_text(json.dumps({'bag': str(bag), 'results': str(results), 'options': asdict(options),
                                    'hosts': hosts, 'netns': net.namespaces}))
        status = net.run_on_operator([sys.executable, '-m', __name__, str(spec)])
        info = {'hosts': {h: list(r) for h, r in hosts.items()}, 'link': asdict(link),
                'addresses': net.addresses, 'namespaces': net.namespaces, 'views': net.views}
        net_stats = net.stats  # filled when the network is taken down, below
    error = results / 'replay_on_hosts.error'
    if status != 0 or not (results / 'summary.json').exists():
        why = error.read_text().strip() if error.exists() else f'the replay on the operator host exited with {status}'
        raise GraphError(why)
    summary = json.loads((results / 'summary.json').read_text())
    summary['wan'] = {**info, 'stats': net_stats}
    _write_summary(results, summary)
    return summary


def on_host_main(spec_file: str) -> int:
    """Run the replay that _replay_on_hosts describes in `spec_file`, from the operator's namespace."""
    spec = json.loads(Path(spec_file).read_text())
    results = Path(spec['results'])
    try:
        _replay_here(Path(spec['bag']), results, ReplayOptions(**spec['options']),
                     hosts={h: tuple(r) for h, r in spec['hosts'].items()}, netns=spec['netns'])
    except GraphError as exc:
        (results / 'replay_on_hosts.error').write_text(f'{exc}\n')
        return 2
    except KeyboardInterrupt:
        return 130
    return 0


def replay_repeatedly(bag: Path, base: Path, repeat: int, **options: object) -> dict:
    """Replay a bag `repeat` times, each on a fresh graph (base/run-<i>); return the latency over every request.

    Args:
        bag: The bag.
        base: The folder of the runs.
        repeat: How many replays.
        options: replay()'s keyword options.

    Returns:
        {'bag', 'results_dir', 'replays', 'distinct_decisions', 'latency_ms': {n, median, p99, max, samples,
        to_command}, 'speed_vs_real_time': {median, min}, 'failures': graph_failure of each run}.

    """
    latencies, speeds, outcomes, failures, to_command = [], [], set(), [], 0
    say = log.debug if options.get('quiet') else log.info
    for i in range(repeat):
        summary = replay(bag, base / f'run-{i}', **{**options, 'figures': False, 'quiet': True})
        outcomes.add((summary['split'], tuple(sorted(summary.get('cut_branch_ids', [])))))
        failures.append(graph_failure(summary))
        latencies += summary['latency_ms']['samples']  # the bag's requests and any --probe-hz ones
        to_command += summary['latency_ms']['to_command']
        if summary['replay']:
            speeds.append(summary['replay']['speed_vs_real_time'])
        say('replay %d/%d: split=%s cut=%s latency=%s ms', i + 1, repeat, summary['split'],
            summary.get('cut_branch_ids'), latencies[-1] if latencies else None)
    return {'bag': str(bag), 'results_dir': str(base), 'replays': repeat,
            'distinct_decisions': [list(o) for o in sorted(outcomes, key=str)],
            'latency_ms': {'n': len(latencies), 'median': statistics.median(latencies) if latencies else None,
                           'p99': percentile(latencies, 99) if latencies else None,
                           'max': max(latencies) if latencies else None,
                           'samples': latencies, 'to_command': to_command},
            'speed_vs_real_time': {'median': statistics.median(speeds) if speeds else None,
                                   'min': min(speeds) if speeds else None},
            'failures': failures}


if __name__ == '__main__':
    sys.exit(on_host_main(sys.argv[1]))

