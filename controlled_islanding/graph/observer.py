"""The operator's view of one running graph: what its nodes publish, seen by one rclpy node in a process of ours.

Replays and testbed runs both start a graph, arm its breaker node with a signed request, wait until it is wired,
and then watch requests, decisions, breaker commands, groups and /diagnostics arrive, timing each with one
clock (time.monotonic) in this one process, so that latencies across processes compare like with like.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field

from controlled_islanding.graph import GraphError
from controlled_islanding.wire import topics


@dataclass
class Observation:
    """What the observer saw, with wall arrival times (time.monotonic, s) in this one process."""

    requests: dict[str, float] = field(default_factory=dict)
    request_msgs: dict[str, object] = field(default_factory=dict)  # request id -> the first IslandingRequest of that id
    decisions: dict[str, tuple[float, object]] = field(default_factory=dict)  # request id -> (t, msg)
    decision_log: list[tuple[float, object]] = field(default_factory=list)  # every decision, a request's again too
    commands: list[tuple[float, object]] = field(default_factory=list)
    groups: list = field(default_factory=list)
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)
    heartbeats_s: dict[str, float] = field(default_factory=dict)  # node -> arrival of its newest diagnostics
    raised: dict[str, str] = field(default_factory=dict)  # '<node> <warn.|fault.key>' -> its text when first seen
    restarts: list = field(default_factory=list)  # supervisor.RestartRecord, as the supervisor records them
    hangs: list = field(default_factory=list)  # supervisor.HangRecord
    wan: dict = field(default_factory=dict)  # with hosts: the emulated network, its namespaces and its statistics
    phases_unix: dict[str, float] = field(default_factory=dict)  # milestone -> wall time (time.time, s)
    cpu_s: dict[str, float] = field(default_factory=dict)  # child process -> its CPU time, s (the player: none)
    graph_topics: list[str] = field(default_factory=list)  # topic names seen once the graph was wired


@contextlib.contextmanager
def process_environment(env: Mapping[str, str]) -> Iterator[None]:
    """Let this process see `env` while the block runs, and its own environment again after it.

    rcl reads the domain, discovery range and log directory from the environment when a context starts; the
    observer's context must be on its graph's domain, whatever the user's shell set.
    """
    saved = dict(os.environ)
    os.environ.update(env)
    try:
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


class Observer:
    """An rclpy node in a Context of its own on the graph's domain; `with Observer(...) as o:` opens and closes it.

    Args:
        env: The graph's environment (graph.rosenv), in force while the observer is open.
        name: The observer node's name.
        namespace: The graph's namespace ('' = the root one, else e.g. '/area1').
        obs: Where what is seen goes.
        context: The Context of a graph in this process (graph.composed) to join instead: one DDS participant
            for the graph and its observer, whose endpoints match the moment they are made.

    """

    def __init__(self, env: Mapping[str, str], name: str, namespace: str, obs: Observation,
                 context: object | None = None) -> None:
        self.env, self.name, self.namespace, self.obs = dict(env), name, namespace, obs
        self.context = context
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> Observer:
        import rclpy
        from controlled_islanding_msgs.msg import BreakerCommand, CoherentGroups, IslandingDecision, IslandingRequest
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.signals import SignalHandlerOptions

        from controlled_islanding.ros.endpoints import qos_for

        self._stack.enter_context(process_environment(self.env))
        if self.context is None:
            self.context = rclpy.Context()
            rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
            self._stack.callback(self.context.try_shutdown)
        self.node = rclpy.create_node(self.name, context=self.context, namespace=self.namespace or None)
        self._stack.callback(self.node.destroy_node)
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self._stack.callback(self.executor.shutdown, 1.0)
        self.executor.add_node(self.node)
        obs, ns = self.obs, self.namespace

        def on_diag(msg: DiagnosticArray) -> None:
            for status in msg.status:
                # /diagnostics is global: only this graph's nodes, named as the supervisor names them.
                if not status.name.startswith(f'{ns}/'):
                    continue
                name = status.name[len(ns):]
                obs.diagnostics[name] = {kv.key: kv.value for kv in status.values}
                obs.heartbeats_s[name] = time.monotonic()
                for key, value in obs.diagnostics[name].items():
                    if key.startswith(('warn.', 'fault.')):
                        obs.raised.setdefault(f'{name} {key}', value)

        def subscribe(msg_type: type, topic: str, callback: Callable[[object], None]) -> None:
            self.node.create_subscription(msg_type, topics.relative(topic), callback, qos_for(topic))

        def on_request(msg: IslandingRequest) -> None:
            obs.requests.setdefault(msg.request_id, time.monotonic())
            obs.request_msgs.setdefault(msg.request_id, msg)

        def on_decision(msg: IslandingDecision) -> None:
            seen = (time.monotonic(), msg)
            obs.decisions.setdefault(msg.request_id, seen)
            obs.decision_log.append(seen)

        subscribe(IslandingRequest, topics.ISLANDING_REQUEST, on_request)
        subscribe(IslandingDecision, topics.ISLANDING_DECISION, on_decision)
        subscribe(BreakerCommand, topics.BREAKER_COMMANDS, lambda m: obs.commands.append((time.monotonic(), m)))
        subscribe(CoherentGroups, topics.COHERENT_GROUPS, obs.groups.append)
        subscribe(DiagnosticArray, topics.DIAGNOSTICS, on_diag)
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._stack.close()

    def spin_for(self, seconds: float, done: Callable[[], bool] = lambda: False) -> bool:
        """Spin until `done()` or for `seconds` of wall time; return done()."""
        end = time.monotonic() + seconds
        while not done() and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))
        return done()

    def arm(self, operator_key: object, arm: bool, service_wait_s: float, check: Callable[[], None]) -> None:
        """Switch breaker_command to armed=`arm` with a signed operator request.

        Args:
            operator_key: The operator's Ed25519 private key.
            arm: Armed (True) or disarmed.
            service_wait_s: How long breaker_command may take to offer its service, s.
            check: Raises if the graph has failed meanwhile (Supervisor.check_alive).

        Raises:
            GraphError: No service within service_wait_s, or no accepting answer to 3 requests.

        """
        from controlled_islanding_msgs.srv import SetArmed

        from controlled_islanding.safety import signing

        target = f'{self.namespace}/breaker_command'
        client = self.node.create_client(SetArmed, 'breaker_command/set_armed')
        # Client.wait_for_service looks every 0.25 s; spinning looks as soon as anything arrives, and often.
        if not self.spin_for(service_wait_s, client.service_is_ready):
            check()
            raise GraphError(f'breaker_command did not offer {target}/set_armed within {service_wait_s:g} s')
        # The service can be discovered before it has matched our reply reader; Fast DDS then drops the response
        # ("failed to send response"). Arming is idempotent, so ask again, with a fresh nonce.
        for _attempt in range(3):
            request = signing.signed_arm_request(SetArmed.Request(), operator_key, target, arm, time.time())
            future = client.call_async(request)
            if self.spin_for(5.0, future.done):
                break
        if not future.done() or not future.result().accepted or future.result().armed != arm:
            why = future.result().message if future.done() else 'no answer to 3 requests within 15 s'
            raise GraphError(f'breaker_command did not switch to armed={arm}: {why}')

    def wait_until_wired(self, played: Iterable[str], internal: Iterable[str], timeout_s: float,
                         topic_name: Callable[[str], str], ready: Callable[[], bool] = lambda: True,
                         check: Callable[[], None] = lambda: None) -> dict[str, int]:
        """Wait until every internal topic has a writer and a reader and nothing changed for a second.

        Matching follows discovery: once the readers of the played topics and the ends of the internal ones stay
        the same for a second, and `ready()` holds, an as-fast-as-possible play misses nothing.

        Args:
            played: Topics the player (or grid_sim) will publish.
            internal: Topics between the nodes.
            timeout_s: The longest wait, s; what was seen then is returned.
            topic_name: A root-namespace topic's name in this graph.
            ready: A further condition (every writer matched, say).
            check: Raises if the graph has failed meanwhile.

        Returns:
            Readers per played topic when it was wired: the player waits for at least as many.

        """
        counts: dict[str, int] = {}
        wiring: dict[str, tuple[int, int]] = {}
        stable_since = begun = time.monotonic()
        while time.monotonic() < begun + timeout_s:
            check()
            now_counts = {t: self.node.count_subscribers(topic_name(t)) for t in played}
            now_wiring = {t: (self.node.count_publishers(topic_name(t)), self.node.count_subscribers(topic_name(t)))
                          for t in internal}
            if now_counts != counts or now_wiring != wiring:
                counts, wiring, stable_since = now_counts, now_wiring, time.monotonic()
            elif time.monotonic() - stable_since >= 1.0 and all(min(w) > 0 for w in wiring.values()) and ready():
                break
            self.spin_for(0.1)
        self.obs.graph_topics = sorted(name for name, _ in self.node.get_topic_names_and_types())
        return counts


INTERNAL_TOPICS = (topics.ROTOR_ANGLES, topics.COHERENT_GROUPS, topics.ISLANDING_DECISION, topics.BREAKER_COMMANDS)


def start_pipeline(sup: object, results: object, key_dir: object, estimator: str | None,
                   prefix: Callable[[str], list[str]] = lambda executable: [],
                   remaps: Callable[[str], dict[str, str]] = lambda executable: {}, monitor: bool = False) -> None:
    """Start the four pipeline nodes under a supervisor on sim time, the breaker node's audit log in `results`.

    `prefix(executable)` runs a node on its host; `remaps(executable)` gives a node remappings of its own. With
    `monitor`, the stability monitor too (graph/supervisor.MONITOR), signing its requests with key_dir's key.
    """
    from controlled_islanding.graph.supervisor import GRAPH, MONITOR

    sim = {'use_sim_time': True}
    extra = {'breaker_command': {'audit_log': results / 'breaker_audit.jsonl', 'key_dir': key_dir},
             'partitioning': {'key_dir': key_dir}, 'stability_monitor': {'key_dir': key_dir}}
    if estimator is not None:
        extra['pmu_ingestion'] = {'estimator': estimator}
    for spec in (*GRAPH, MONITOR) if monitor else GRAPH:
        sup.start(spec, {**sim, **extra.get(spec.executable, {})}, prefix=prefix(spec.executable),
                  remaps=remaps(spec.executable) or None)
