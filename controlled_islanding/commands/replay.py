"""`controlled-islanding replay BAG`: run a bag through the node graph, as separate processes over DDS."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from controlled_islanding import atomic
from controlled_islanding.cli import CliError
from controlled_islanding.graph import wan
from controlled_islanding.wire import topics

HELP = 'replay a bag through the ROS 2 node graph and print its islanding decision'
DESCRIPTION = """\
Start pmu_ingestion, coherency, partitioning and breaker_command (each its own process, with its
config/*.yaml), plus a recorder; arm the breaker node;
play BAG with bag_player (ground truth withheld); then print the decision: coherent groups, islands
with their buses, cut lines, disrupted MW, generation/load/shed per island, breaker commands, and the
latency from the islanding request to the breaker command, measured by one observer across processes.

The results folder holds the recorded output bag (output_bag/), the breaker audit log, every node's
log, rotor_angles.png (estimated angles coloured by group), network.png (islands and cut lines) and
summary.json; by default it is made under results/ in the current directory. Every child process is
stopped on exit, Ctrl-C or error.

DDS domain: if ROS_DOMAIN_ID is set, the graph joins it, so your own tools see its topics (discovery
stays on loopback unless ROS_AUTOMATIC_DISCOVERY_RANGE says otherwise); another graph on that domain
will see and disturb it, unless each runs in its own --namespace. With --isolate, or with ROS_DOMAIN_ID
unset, the graph gets a free private domain on loopback.

Namespace: with --namespace /area1 every node of the graph, the player and the recorder run in /area1
(/area1/pmu/frames, /area1/breaker_command/set_armed, ...), and the bag's clock is /area1/clock, so two
replays in two namespaces share one domain without crosstalk. /diagnostics stays global; each status is
named by its node's full name (/area1/pmu_ingestion).

Hosts: with --hosts pdc,control,substation the graph runs on three emulated hosts, each a network namespace of
its own (pdc: pmu_ingestion and the bag player; control: coherency and partitioning; substation:
breaker_command), joined by a user-space WAN with --wan-delay-ms, --wan-jitter-ms and --wan-loss-pct between
hosts; DDS discovers by multicast across it. Roles joined by '+' share a host (pdc+control,substation). The
observer and the recorder are a fourth host, the operator's, whose view is a tap without delay or loss. Needs
root; without it, says so and exits 2. docs/deployment.md describes the emulation and a real deployment.

Several bags (bags/*/): a regression run. Each bag gets a fresh graph of its own (the nodes keep state a
bag must not inherit: the breaker node's commanded breakers, the time of the last input) on a private
domain, in a child process, --jobs of them at once (default 2: a graph's start-up is mostly one process's
imports at a time, so two graphs keep two cores busier; 17 bags took 211 s instead of 331 s). One report with
a row per bag (decision, agreement with bags/index.yaml, speed, wall time) and the overall speed against real
time, start-up included, with the load average. Exit status 1 if any bag went wrong.

Examples (bag names from bags/index.yaml):
  controlled-islanding replay bags/ieee39_g6g7_unstable            real time
  controlled-islanding replay bags/ieee39_g6g7_unstable --fast --json
  controlled-islanding replay bags/*/ --fast --json            every bag, one report
  controlled-islanding replay bags/ieee39_g6g7_unstable --probe-hz 20   extra requests: a latency benchmark
  controlled-islanding replay bags/ieee39_g6g7_unstable --fast --namespace /area1   one area of several
  controlled-islanding replay bags/ieee39_case2_g3_unstable --fast --hosts pdc,control,substation \
      --wan-delay-ms 20 --wan-jitter-ms 5 --wan-loss-pct 1
"""

# After the bag ends, a request still unanswered this long (wall, s) is reported as undecided. The nodes
# give up after at most 2 s (coherency request_wait_s, partitioning groups_wait_s), so this is ample.
SETTLE_S = 8.0
INTERRUPTED = 'INTERRUPTED.json'  # in a results folder: the replay was stopped before its summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the replay options."""
    parser.add_argument('bag', type=Path, nargs='+',
                        help='rosbag2 bag directory (see bags/index.yaml); several (bags/*/) make a regression run')
    parser.add_argument('--json', action='store_true', help='print one JSON decision on stdout and nothing else')
    parser.add_argument('--jobs', type=int, default=2,
                        help='with several bags: graphs running at once (default 2; see "Several bags" above)')
    parser.add_argument('--fast', action='store_true', help='play as fast as possible (lockstep at requests)')
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor (default 1 = real time)')
    parser.add_argument('--results', type=Path, default=None,
                        help='results folder to create (default ./results/replay-<bag>-<UTC time>)')
    parser.add_argument('--isolate', action='store_true',
                        help='run on a free private ROS_DOMAIN_ID on loopback even if ROS_DOMAIN_ID is set')
    parser.add_argument('--probe-hz', type=float, default=0.0,
                        help='also send islanding requests at this rate once the first decision is out, '
                             'to measure latency over many requests (a benchmark; default 0 = none). Once the '
                             "cut is open the breaker refuses every probe's cut, so probes are timed to their "
                             'decision')
    parser.add_argument('--disarmed', action='store_true',
                        help='leave breaker_command disarmed: decisions are refused and audited, nothing is commanded')
    parser.add_argument('--repeat', type=int, default=1,
                        help='replay N times, each on a fresh node graph, and print the latency over all N '
                             '(a benchmark; results/<folder>/run-<i> per replay)')
    parser.add_argument('--no-figures', action='store_true', help='skip the figures')
    parser.add_argument('--no-record', action='store_true',
                        help='do not run the recorder (no output bag, so no figures): less load while benchmarking')
    parser.add_argument('--timeout', type=float, default=120.0, help='give up after this many wall seconds')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help='run the whole graph in this ROS namespace, e.g. /area1 (default: the root one)')
    parser.add_argument('--estimator', choices=('steady_state', 'dse'), default=None,
                        help="pmu_ingestion's rotor angle estimator: steady_state, or dse (a Kalman filter on each "
                             "machine's model from the snapshot's machine data); default: config/pmu_ingestion.yaml")
    parser.add_argument('--hosts', default=None, metavar='H1,H2,...',
                        help='run the graph on emulated hosts joined by an emulated WAN (needs root): comma-separated '
                             'hosts, each a role (pdc, control, substation) or roles joined by +')
    parser.add_argument('--wan-delay-ms', type=float, default=0.0, help='with --hosts: one-way delay between hosts, ms')
    parser.add_argument('--wan-jitter-ms', type=float, default=0.0,
                        help='with --hosts: each packet delayed uniformly within delay +- jitter, ms')
    parser.add_argument('--wan-loss-pct', type=float, default=0.0,
                        help='with --hosts: probability that a packet between hosts is lost, %%')
    parser.add_argument('--wan-seed', type=int, default=0, help='with --hosts: seed of the loss and jitter draws')


@dataclass
class Observation:
    """What the observer saw, with wall arrival times (time.monotonic, s) in this one process."""

    requests: dict[str, float] = field(default_factory=dict)
    decisions: dict[str, tuple[float, object]] = field(default_factory=dict)  # request id -> (t, msg)
    commands: list[tuple[float, object]] = field(default_factory=list)
    groups: list = field(default_factory=list)
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)
    heartbeats_s: dict[str, float] = field(default_factory=dict)  # node -> arrival of its newest diagnostics
    restarts: list = field(default_factory=list)  # supervisor.RestartRecord, as the supervisor records them
    hangs: list = field(default_factory=list)  # supervisor.HangRecord
    wan: dict = field(default_factory=dict)  # with hosts: the emulated network, its namespaces and its statistics
    phases_unix: dict[str, float] = field(default_factory=dict)  # milestone -> wall time (time.time, s)
    cpu_s: dict[str, float] = field(default_factory=dict)  # child process -> its CPU time, s (the player: none)


def _say(quiet: bool, text: str) -> None:
    if not quiet:
        print(text, file=sys.stderr, flush=True)


def _bag_topics(bag: Path) -> dict[str, int]:
    """Return message counts by topic of the bag (the player withholds /truth topics)."""
    from rosbags.highlevel import AnyReader

    from controlled_islanding.wire.interfaces import typestore

    try:
        with AnyReader([bag], default_typestore=typestore()) as reader:
            counts: dict[str, int] = {}
            for c in reader.connections:
                counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
            return counts
    except Exception as exc:  # rosbags raises many error types for an unreadable bag
        raise CliError(f'bag {bag}: cannot read it as a rosbag2 bag: {exc}') from exc


def namespace_name(namespace: str) -> str:
    """Return a namespace as ROS writes it ('' for the root one, else '/area1'); raise CliError if invalid."""
    from rclpy.exceptions import InvalidNamespaceException
    from rclpy.validate_namespace import validate_namespace

    name = f'/{namespace.strip("/")}' if namespace.strip('/') else ''
    try:
        validate_namespace(name or '/')
    except InvalidNamespaceException as exc:
        raise CliError(f'--namespace {namespace!r} is not a ROS namespace: {exc}') from exc
    return name


def run_graph(bag: Path, results: Path, *, fast: bool, rate: float, probe_hz: float, timeout_s: float,
              quiet: bool, arm: bool = True, record: bool = True, isolate: bool = True, namespace: str = '',
              estimator: str | None = None, hosts: dict[str, tuple[str, ...]] | None = None,
              netns: dict[str, str] | None = None) -> tuple[Observation, dict]:
    """Run the node graph on a bag; return what the observer saw and the player's speed report.

    The graph runs in `namespace` ('' = the root one), with its own /clock there (`<namespace>/clock`).
    `estimator` overrides pmu_ingestion's (None: its parameter file's). With `hosts` (wan.parse_hosts), each host's
    nodes start in its network namespace `netns[host]` of an emulated WAN, and this process must be on the
    operator's (see _replay_on_hosts).

    Raises:
        CliError: The bag is unreadable, a node died, or no decision came in time.

    """
    import rclpy
    from controlled_islanding_msgs.msg import BreakerCommand, CoherentGroups, IslandingDecision, IslandingRequest
    from controlled_islanding_msgs.srv import SetArmed
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.signals import SignalHandlerOptions

    from controlled_islanding.graph.rosenv import graph_environment
    from controlled_islanding.graph.supervisor import (
        GRAPH,
        PIPELINE_POLICY,
        PLAYER,
        RECORDER,
        Supervisor,
        SupervisorError,
    )
    from controlled_islanding.ros.diagnostics import writers_matched
    from controlled_islanding.ros.endpoints import qos_for
    from controlled_islanding.ros.spin import settle_heap
    from controlled_islanding.safety import signing

    # The demo and replays sign with the user's keys, made on first use, outside the repository.
    key_dir = signing.default_key_dir()
    signing.init_keys(key_dir)
    operator_key = signing.load_private_key(signing.key_paths(key_dir, 'operator').private)
    bag_topics = _bag_topics(bag)
    n_requests = bag_topics.get(topics.ISLANDING_REQUEST, 0)
    played = [t for t in bag_topics if t not in topics.TRUTH_TOPICS] + [topics.CLOCK]
    ns = namespace_name(namespace)
    # Two replays on one domain have two bag clocks: each graph's /clock is its own.
    remaps = {topics.CLOCK: f'{ns}{topics.CLOCK}'} if ns else {}

    def graph_topic(topic: str) -> str:
        return remaps.get(topic, topics.in_namespace(topic, ns))

    obs = Observation()
    obs.phases_unix['begun'] = time.time()
    logs = results / 'logs'
    with graph_environment(results / 'ros_log', isolate) as env:
        if hosts:
            env.update(wan.DDS_ENVIRONMENT)
        def on_host(executable: str) -> list[str]:
            return wan.prefix(netns[wan.host_of(hosts, executable)]) if hosts else []

        saved = dict(os.environ)
        os.environ.update(env)
        context = rclpy.Context()
        rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node('replay_observer', context=context, namespace=ns or None)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)

        def spin_for(seconds: float, done=lambda: False) -> bool:
            end = time.monotonic() + seconds
            while not done() and time.monotonic() < end:
                executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))
            return done()

        def on_request(msg: IslandingRequest) -> None:
            obs.requests.setdefault(msg.request_id, time.monotonic())

        def on_decision(msg: IslandingDecision) -> None:
            obs.decisions.setdefault(msg.request_id, (time.monotonic(), msg))

        def on_groups(msg: CoherentGroups) -> None:
            obs.groups.append(msg)

        def on_diag(msg: DiagnosticArray) -> None:
            for status in msg.status:
                # /diagnostics is global: only this graph's nodes, named as the supervisor names them.
                if not status.name.startswith(f'{ns}/'):
                    continue
                name = status.name[len(ns):]
                obs.diagnostics[name] = {kv.key: kv.value for kv in status.values}
                obs.heartbeats_s[name] = time.monotonic()

        def subscribe(msg_type: type, topic: str, callback) -> None:
            node.create_subscription(msg_type, topics.relative(topic), callback, qos_for(topic))

        subscribe(IslandingRequest, topics.ISLANDING_REQUEST, on_request)
        subscribe(IslandingDecision, topics.ISLANDING_DECISION, on_decision)
        subscribe(BreakerCommand, topics.BREAKER_COMMANDS, lambda m: obs.commands.append((time.monotonic(), m)))
        subscribe(CoherentGroups, topics.COHERENT_GROUPS, on_groups)
        subscribe(DiagnosticArray, topics.DIAGNOSTICS, on_diag)
        probe_pub = node.create_publisher(IslandingRequest, topics.relative(topics.ISLANDING_REQUEST),
                                          qos_for(topics.ISLANDING_REQUEST))
        report_file = results / 'player_report.json'
        try:
            with Supervisor(env, logs, PIPELINE_POLICY, namespace=ns, remaps=remaps) as sup:
                obs.restarts, obs.hangs = sup.restarts, sup.hangs
                sim = {'use_sim_time': True}
                extra = {'breaker_command': {'audit_log': results / 'breaker_audit.jsonl', 'key_dir': key_dir},
                         'partitioning': {'key_dir': key_dir}}
                if estimator is not None:
                    extra['pmu_ingestion'] = {'estimator': estimator}
                for spec in GRAPH:
                    sup.start(spec, {**sim, **extra.get(spec.executable, {})}, prefix=on_host(spec.executable))
                if record:
                    sup.start(RECORDER, {**sim, 'output': results / 'output_bag'}, prefix=on_host(RECORDER.executable))
                # The player loads its bag and is discovered while the nodes start; it plays once told to.
                go_file = results / 'player_go.json'
                player = sup.start(PLAYER, {'bag': bag.resolve(), 'as_fast_as_possible': fast, 'rate': rate,
                                            'report_file': report_file, 'clock_min_step_s': 0.05 if fast else 0.0,
                                            'go_file': go_file}, prefix=on_host(PLAYER.executable))
                obs.phases_unix['nodes_started'] = time.time()
                _say(quiet, f'replay: started {len(GRAPH)} nodes{" and the recorder" if record else ""} '
                            f'(logs in {logs})')
                arm_client = node.create_client(SetArmed, 'breaker_command/set_armed')
                if not arm_client.wait_for_service(timeout_sec=20.0):
                    sup.check_alive()
                    raise CliError(f'breaker_command did not offer {ns}/breaker_command/set_armed within 20 s')
                # The service can be discovered before it has matched our reply reader; Fast DDS then drops the
                # response ("failed to send response"). Arming is idempotent, so ask again, with a fresh nonce.
                for _attempt in range(3):
                    request = signing.signed_arm_request(SetArmed.Request(), operator_key, f'{ns}/breaker_command',
                                                         arm, time.time())
                    future = arm_client.call_async(request)
                    if spin_for(5.0, future.done):
                        break
                if not future.done() or not future.result().accepted or future.result().armed != arm:
                    why = future.result().message if future.done() else 'no answer to 3 requests within 15 s'
                    raise CliError(f'breaker_command did not switch to armed={arm}: {why}')
                obs.phases_unix['armed'] = time.time()
                _say(quiet, f'replay: breaker_command {"armed" if arm else "left disarmed"}; playing the bag')
                # The player starts once every subscriber now in the graph (this observer included) matches it.
                # The graph is wired once every internal topic has a writer and a reader, and nothing changed
                # for a second (matching follows discovery): an as-fast-as-possible replay misses nothing.
                internal = (topics.ROTOR_ANGLES, topics.COHERENT_GROUPS, topics.ISLANDING_DECISION,
                            topics.BREAKER_COMMANDS)
                counts: dict[str, int] = {}
                wiring: dict[str, tuple[int, int]] = {}

                def matched() -> bool:
                    # Kundur at load 9 lost the rotor angles before its request so (writers_matched).
                    return all(writers_matched(obs.diagnostics.get(f'/{spec.executable}', {}), node.count_subscribers)
                               for spec in GRAPH)

                stable_since = begun = time.monotonic()
                while time.monotonic() < begun + 20.0:
                    if player.poll() is not None:
                        raise CliError(f'bag_player failed:\n{sup.log_tail("bag_player")}')
                    now_counts = {t: node.count_subscribers(graph_topic(t)) for t in played}
                    now_wiring = {t: (node.count_publishers(graph_topic(t)), node.count_subscribers(graph_topic(t)))
                                  for t in internal}
                    if now_counts != counts or now_wiring != wiring:
                        counts, wiring, stable_since = now_counts, now_wiring, time.monotonic()
                    elif (time.monotonic() - stable_since >= 1.0 and all(min(w) > 0 for w in wiring.values())
                          and matched()):
                        break
                    spin_for(0.1)
                obs.phases_unix['wired'] = time.time()
                atomic.write_text(go_file, json.dumps({'min_subscribers': [f'{t}={n}' for t, n in counts.items()]}))
                settle_heap()  # this observer's timestamps must not wait on a full garbage collection either
                deadline = time.monotonic() + timeout_s
                probe_period = 1.0 / probe_hz if probe_hz > 0 else None
                next_probe = None
                done_at = None
                exited_at = math.inf  # when the player was seen to have exited, monotonic s
                while time.monotonic() < deadline:
                    spin_for(0.01)
                    sup.supervise(obs.heartbeats_s)
                    bag_done = player.poll() is not None
                    if bag_done and 'player_exited' not in obs.phases_unix:
                        obs.phases_unix['player_exited'] = time.time()
                        exited_at = time.monotonic()
                    if bag_done and player.returncode != 0:
                        raise CliError(f'bag_player failed:\n{sup.log_tail("bag_player")}')
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
                    if bag_done and answered >= n_requests and all(r in obs.decisions for r in obs.requests):
                        spin_for(0.3)  # let the last commands arrive
                        # The summary gives each node's last /diagnostics (sent every second): wait, at most 1.5 s,
                        # for one sent after the play, or a short bag's counts can predate its frames.
                        limit = time.monotonic() + 1.5
                        while time.monotonic() < limit and any(
                                obs.heartbeats_s.get(f'/{spec.executable}', -math.inf) < exited_at for spec in GRAPH):
                            spin_for(0.05)
                        obs.phases_unix['decided'] = time.time()
                        break
                    if bag_done:
                        done_at = done_at or time.monotonic()
                        if time.monotonic() - done_at > SETTLE_S:
                            _say(quiet, f'replay: no decision for some requests {SETTLE_S} s after the bag ended')
                            break
                else:
                    raise CliError(f'no decision for every request within --timeout {timeout_s} s; '
                                   f'logs in {logs}')
            obs.phases_unix['stopped'] = time.time()
            obs.cpu_s = sup.cpu_s
        except SupervisorError as exc:
            raise CliError(str(exc)) from exc
        finally:
            node.destroy_node()
            context.try_shutdown()
            os.environ.clear()
            os.environ.update(saved)
    report = json.loads(report_file.read_text()) if report_file.exists() else {}
    return obs, report


def _decision_dict(request_id: str, obs: Observation) -> dict:
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
        'breaker_commands': [{'command_id': c.command_id, 'breaker_id': c.breaker_id, 'branch_id': c.branch_id,
                              'action': 'open' if c.action == c.ACTION_OPEN else 'close'} for _, c in commands],
        'latency_request_to_command_ms': latency_cmd,
        'latency_request_to_decision_ms': (t_dec - t_req) * 1e3 if t_req is not None else None,
        'partitioning_compute_ms': msg.compute_time_s * 1e3,
    }


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
    decisions = [_decision_dict(r, obs) for r in bag_requests if r in obs.decisions]
    # A request that commanded nothing (a probe after the cut is open) is timed to its decision.
    answered = [_decision_dict(r, obs) for r in obs.requests if r in obs.decisions]
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
             ('wired', 'every node up, discovery unchanged for 1 s, every writer matched'),
             ('play_begun', 'player told to go, waited for its subscribers'),
             ('play_ended', 'play, lockstep waits included'),
             ('decided', 'linger, last decisions and diagnostics'), ('stopped', 'every process stopped')]
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
    groups = summary['coherent_groups']
    if groups:
        lines.append(f'coherent groups ({groups["method"]}, k={groups["k"]}, window {groups["window_s"]:.2f} s):')
        lines += [f'  group {i}: {", ".join(names)}' for i, names in enumerate(groups['groups'])]
        if groups.get('unobserved'):
            lines.append(f'  unobserved (no PMU data, in no group): {", ".join(groups["unobserved"])}')
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
    lines.append('breaker commands: ' + (', '.join(f'{c["action"]} {c["breaker_id"]}' for c in cmds) or 'none'))
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


def wan_line(info: dict) -> str:
    """Return one line on the emulated WAN: hosts, link model and what crossed it."""
    link, stats = info['link'], info.get('stats') or {}
    pairs = [p for k, p in stats.get('pairs', {}).items() if not k.endswith(f'->{wan.OPERATOR}')]
    sent = sum(p['packets'] + p['dropped'] for p in pairs)
    dropped = sum(p['dropped'] for p in pairs)
    return (f'emulated WAN: hosts {", ".join(info["hosts"])} (+ {wan.OPERATOR}); one-way delay {link["delay_ms"]:g} '
            f'+- {link["jitter_ms"]:g} ms, loss {link["loss_pct"]:g} %: {sent} packets between hosts, {dropped} lost')


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
           hosts: str | None = None, link: wan.LinkModel | None = None) -> dict:
    """Replay a bag through the graph; write the results folder; return the summary.

    `estimator` is pmu_ingestion's rotor angle estimator, 'steady_state' or 'dse' (None: its parameter file's).
    `hosts` (`--hosts`, e.g. 'pdc,control,substation') runs the graph on emulated hosts joined by a WAN with `link`.

    Raises:
        CliError: Bad arguments, an unreadable bag, a failed node or a missing decision.

    """
    host_roles = None
    if hosts:
        try:
            host_roles = wan.parse_hosts(hosts)
        except ValueError as exc:
            raise CliError(str(exc)) from exc
        why = wan.unavailable_reason()
        if why:
            raise CliError(why)
    if not bag.exists():
        raise CliError(f'bag {bag} does not exist')
    if rate <= 0:
        raise CliError(f'--rate {rate} must be positive')
    namespace = namespace_name(namespace)
    if results is None:
        stamp = datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
        results = Path('results') / f'replay-{bag.name}-{stamp}'
    results = results.resolve()
    if results.exists():
        raise CliError(f'results folder {results} exists; name a new one')
    results.mkdir(parents=True)
    options = {'fast': fast, 'rate': rate, 'probe_hz': probe_hz, 'timeout_s': timeout_s, 'figures': figures,
               'quiet': quiet, 'arm': arm, 'record': record, 'isolate': isolate, 'namespace': namespace,
               'estimator': estimator}
    try:
        if host_roles:
            return _replay_on_hosts(bag, results, host_roles, link or wan.LinkModel(), options)
        return _replay_here(bag, results, **options)
    except KeyboardInterrupt:
        # Ctrl-C or SIGTERM (the supervisor turns it into this), its nodes stopped by now: without summary.json the
        # folder is unfinished, and this file says so to a reader, as a testbed's does.
        atomic.write_text(results / INTERRUPTED, json.dumps({
            'interrupted_utc': datetime.now(UTC).isoformat(timespec='seconds'), 'bag': str(bag)}, indent=1) + '\n')
        raise


def _replay_here(bag: Path, results: Path, *, fast: bool, rate: float, probe_hz: float, timeout_s: float,
                 figures: bool, quiet: bool, arm: bool, record: bool, isolate: bool, namespace: str,
                 estimator: str | None, hosts: dict[str, tuple[str, ...]] | None = None,
                 netns: dict[str, str] | None = None) -> dict:
    """Run the graph from this process, summarize, draw, and write the summary into `results` (made already)."""
    obs, report = run_graph(bag, results, fast=fast, rate=rate, probe_hz=probe_hz, timeout_s=timeout_s,
                            quiet=quiet, arm=arm, record=record, isolate=isolate, namespace=namespace,
                            estimator=estimator, hosts=hosts, netns=netns)
    summary = summarize(bag, results, obs, report)
    summary['namespace'] = namespace
    summary['estimator'] = next((d['estimator'] for name, d in obs.diagnostics.items()
                                 if name.endswith('pmu_ingestion') and 'estimator' in d), estimator)
    if figures and record:
        try:
            summary['figures'] = [str(p) for p in write_figures(bag, results, summary)]
        except Exception as exc:  # a figure must never hide the decision
            _say(quiet, f'replay: figures failed: {exc}')
    _write_summary(results, summary)
    return summary


def _write_summary(results: Path, summary: dict) -> None:
    atomic.write_text(results / 'summary.json', json.dumps(summary, indent=2, default=str))
    atomic.write_text(results / 'summary.txt', render(summary) + '\n')


def _replay_on_hosts(bag: Path, results: Path, hosts: dict[str, tuple[str, ...]], link: wan.LinkModel,
                     options: dict) -> dict:
    """Build the emulated WAN, run the replay from a fresh process on the operator's host, add the WAN to it.

    The observer runs in a process of its own started in the operator's namespace: a DDS participant takes its
    network from the process it lives in, and one made earlier in this process (a test suite's, or a loopback
    replay's) left Fast DDS sending the new one's traffic to loopback only.
    """
    spec = results / 'replay_on_hosts.json'
    try:
        with wan.EmulatedWan(list(hosts), link, results) as net:
            spec.write_text(json.dumps({'bag': str(bag), 'results': str(results), 'options': options,
                                        'hosts': hosts, 'netns': net.namespaces}))
            child = subprocess.Popen([*net.prefix(wan.OPERATOR), sys.executable, '-c',
                                      'import sys; from controlled_islanding.commands.replay import on_host_main; '
                                      'sys.exit(on_host_main(sys.argv[1]))', str(spec)], stdin=subprocess.DEVNULL)
            try:
                while child.poll() is None:
                    net.check_alive()
                    time.sleep(0.2)
                status = child.returncode
            finally:
                # Interrupted: a terminal's Ctrl-C reached the child too, and a second SIGINT could cut its clean-up
                # short, so it gets a moment first; a SIGTERM or an emulator failure reached only us.
                for action in (None, signal.SIGINT, signal.SIGKILL):
                    if child.poll() is not None:
                        break
                    if action is not None:
                        child.send_signal(action)
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        child.wait(timeout=2.0 if action is None else 20.0)
            info = {'hosts': {h: list(r) for h, r in hosts.items()}, 'link': asdict(link),
                    'addresses': net.addresses, 'namespaces': net.namespaces, 'views': net.views}
            net_stats = net.stats  # filled when the network is taken down, below
    except wan.WanError as exc:
        raise CliError(str(exc)) from exc
    error = results / 'replay_on_hosts.error'
    if status != 0 or not (results / 'summary.json').exists():
        why = error.read_text().strip() if error.exists() else f'the replay on the operator host exited with {status}'
        raise CliError(why)
    summary = json.loads((results / 'summary.json').read_text())
    summary['wan'] = {**info, 'stats': net_stats}
    _write_summary(results, summary)
    return summary


def on_host_main(spec_file: str) -> int:
    """Run the replay that _replay_on_hosts describes in `spec_file`, from the operator's namespace."""
    spec = json.loads(Path(spec_file).read_text())
    results = Path(spec['results'])
    try:
        _replay_here(Path(spec['bag']), results, **spec['options'],
                     hosts={h: tuple(r) for h, r in spec['hosts'].items()}, netns=spec['netns'])
    except CliError as exc:
        (results / 'replay_on_hosts.error').write_text(f'{exc}\n')
        return 2
    except KeyboardInterrupt:
        return 130
    return 0


def _link(args: argparse.Namespace) -> wan.LinkModel | None:
    wan_set = args.wan_delay_ms or args.wan_jitter_ms or args.wan_loss_pct
    if not args.hosts:
        if wan_set:
            raise CliError('--wan-delay-ms, --wan-jitter-ms and --wan-loss-pct need --hosts')
        return None
    try:
        return wan.LinkModel(args.wan_delay_ms, args.wan_jitter_ms, args.wan_loss_pct, args.wan_seed)
    except ValueError as exc:
        raise CliError(str(exc)) from exc


def run(args: argparse.Namespace) -> int:
    """Run the replay subcommand."""
    if len(args.bag) > 1:
        return _run_suite(args)
    args.bag = args.bag[0]
    if args.repeat < 1:
        raise CliError(f'--repeat {args.repeat} must be at least 1')
    if args.repeat > 1:
        return _run_repeated(args)
    summary = replay(args.bag, args.results, fast=args.fast, rate=args.rate, probe_hz=args.probe_hz,
                     timeout_s=args.timeout, figures=not args.no_figures, quiet=args.json, arm=not args.disarmed,
                     record=not args.no_record, isolate=args.isolate, namespace=args.namespace,
                     estimator=args.estimator, hosts=args.hosts, link=_link(args))
    if args.json:
        print(json.dumps(summary, default=str))
    else:
        print(render(summary))
    if graph_failure(summary):
        if args.json:  # render() already said it on stdout otherwise
            print(f'replay: FAILED: {graph_failure(summary)}', file=sys.stderr)
        return 1
    return 1 if summary['split'] is None or summary['undecided_requests'] or refused(summary) else 0


def _run_repeated(args: argparse.Namespace) -> int:
    stamp = datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
    base = (args.results or Path('results') / f'bench-{args.bag.name}-{stamp}').resolve()
    latencies, speeds, outcomes, failures, to_command = [], [], set(), [], 0
    for i in range(args.repeat):
        summary = replay(args.bag, base / f'run-{i}', fast=args.fast, rate=args.rate, probe_hz=args.probe_hz,
                         timeout_s=args.timeout, figures=False, quiet=True, arm=not args.disarmed,
                         record=not args.no_record, isolate=args.isolate, namespace=args.namespace,
                         estimator=args.estimator, hosts=args.hosts, link=_link(args))
        outcomes.add((summary['split'], tuple(sorted(summary.get('cut_branch_ids', [])))))
        failures.append(graph_failure(summary))
        latencies += summary['latency_ms']['samples']  # the bag's requests and any --probe-hz ones
        to_command += summary['latency_ms']['to_command']
        if summary['replay']:
            speeds.append(summary['replay']['speed_vs_real_time'])
        _say(args.json, f'replay {i + 1}/{args.repeat}: split={summary["split"]} '
                        f'cut={summary.get("cut_branch_ids")} latency={latencies[-1] if latencies else None} ms')
    result = {'bag': str(args.bag), 'results_dir': str(base), 'replays': args.repeat,
              'distinct_decisions': [list(o) for o in sorted(outcomes, key=str)],
              'latency_ms': {'n': len(latencies), 'median': statistics.median(latencies) if latencies else None,
                             'p99': percentile(latencies, 99) if latencies else None,
                             'max': max(latencies) if latencies else None,
                             'samples': latencies, 'to_command': to_command},
              'speed_vs_real_time': {'median': statistics.median(speeds) if speeds else None,
                                     'min': min(speeds) if speeds else None}}
    if args.json:
        print(json.dumps(result))
    else:
        lat, spd = result['latency_ms'], result['speed_vs_real_time']
        print(f'{args.repeat} replays of {args.bag} ({"as fast as possible" if args.fast else "real time"}): '
              f'{len(outcomes)} distinct decision(s) {result["distinct_decisions"]}')
        if lat['n']:
            print(f'latency over {lat["n"]} requests, to the breaker command ({to_command} of them) or else to the '
                  f'decision (nothing to command): median {lat["median"]:.1f} ms, p99 {lat["p99"]:.1f} ms, '
                  f'max {lat["max"]:.1f} ms')
        if spd['median'] is not None:
            print(f'speed against real time: median {spd["median"]:.1f}x, slowest {spd["min"]:.1f}x')
        print(f'results: {base}')
    for i, failure in enumerate(failures):
        if failure:
            print(f'replay {i + 1}/{args.repeat}: FAILED: {failure}', file=sys.stderr)
    return 0 if len(outcomes) == 1 and not any(failures) else 1


@dataclass(frozen=True)
class SuiteRun:
    """One replay of a regression run: its name (its results folder), its bag, and replay options for it."""

    name: str
    bag: Path
    options: tuple[str, ...] = ('--fast', '--no-figures')


def replay_suite(runs: list[SuiteRun], base: Path, jobs: int = 2, quiet: bool = True,
                 hard_timeout_s: float = 600.0) -> dict:
    """Replay each run on a fresh graph, in a child process on a private domain, `jobs` at a time; return one report.

    A child runs `controlled-islanding replay BAG --json --isolate --results base/<name> <options>`; its summary is
    base/<name>/summary.json. A child still running after hard_timeout_s is interrupted (it then stops its nodes).

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
                # Not through controlled_islanding.cli, which imports every subcommand: a second of CPU a bag.
                argv = [sys.executable, '-c', 'import sys; from controlled_islanding.commands.replay import '
                        'child_main; sys.exit(child_main(sys.argv[1:]))', str(run.bag), '--json', '--isolate',
                        '--results', str(base / run.name), *run.options]
                with open(base / f'{run.name}.json', 'wb') as out, open(base / f'{run.name}.stderr', 'wb') as err:
                    running[run.name] = (subprocess.Popen(argv, stdout=out, stderr=err, stdin=subprocess.DEVNULL),
                                         time.monotonic())
            for name, (child, started) in list(running.items()):
                if child.poll() is None and time.monotonic() - started > hard_timeout_s:
                    _interrupt(child)
                if child.poll() is not None:
                    del running[name]
                    finished[name] = {'status': child.returncode, 'wall_s': time.monotonic() - started}
                    _say(quiet, f'replay: {name} done ({len(finished)} of {len(runs)})')
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


def child_main(argv: list[str]) -> int:
    """Run one replay of a regression run: `replay` with these arguments, as the command line would."""
    parser = argparse.ArgumentParser(prog='controlled-islanding replay')
    add_arguments(parser)
    from controlled_islanding.graph.rosenv import RosEnvError

    try:
        return run(parser.parse_args(argv))
    except (CliError, RosEnvError) as exc:
        print(f'controlled-islanding replay: error: {exc}', file=sys.stderr)
        return 2


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
           'cut_branch_ids': [], 'manifest': None,
           'bag_duration_s': None, 'play_wall_s': None, 'phases_s': {}, 'error': None, 'ok': False}
    summary_file = base / run.name / 'summary.json'
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
    from controlled_islanding.sim.manifest import entry_for_bag

    entry = entry_for_bag(run.bag.resolve())
    if entry is not None and 'split' in entry.get('expected_decision', {}):
        expected = entry['expected_decision']
        row['manifest'] = ('agrees' if row['split'] == expected['split']
                           and row['cut_branch_ids'] == sorted(expected.get('cut_branches', [])) else 'DIFFERS')
    row['ok'] = (row['error'] is None and row['split'] is not None and not refused(summary)
                 and row['manifest'] != 'DIFFERS')
    return row


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
    lines.append(f'results: {o["results_dir"]}')
    return '\n'.join(lines)


def _run_suite(args: argparse.Namespace) -> int:
    for flag, value in (('--repeat', args.repeat != 1), ('--probe-hz', args.probe_hz), ('--hosts', args.hosts),
                        ('--namespace', args.namespace)):
        if value:
            raise CliError(f'{flag} takes one bag, not {len(args.bag)}')
    if args.jobs < 1:
        raise CliError(f'--jobs {args.jobs} must be at least 1')
    missing = [str(b) for b in args.bag if not b.exists()]
    if missing:
        raise CliError(f'bags do not exist: {", ".join(missing)}')
    options = ['--rate', str(args.rate), '--timeout', str(args.timeout)]
    options += [flag for flag, on in (('--fast', args.fast), ('--disarmed', args.disarmed),
                                      ('--no-record', args.no_record), ('--no-figures', args.no_figures)) if on]
    if args.estimator:
        options += ['--estimator', args.estimator]
    names = [b.resolve().name for b in args.bag]
    if len(set(names)) != len(names):
        raise CliError('two bags have the same name; each needs a results folder of its own')
    stamp = datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
    base = (args.results or Path('results') / f'replay-suite-{stamp}').resolve()
    if base.exists():
        raise CliError(f'results folder {base} exists; name a new one')
    report = replay_suite([SuiteRun(n, b, tuple(options)) for n, b in zip(names, args.bag, strict=True)], base,
                          jobs=args.jobs, quiet=args.json)
    (base / 'suite.json').write_text(json.dumps(report, indent=2, default=str))
    print(json.dumps(report, default=str) if args.json else render_suite(report))
    return 0 if all(r['ok'] for r in report['rows']) else 1
