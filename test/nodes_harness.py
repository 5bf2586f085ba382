"""A probe for node tests: real node processes (via the supervisor) and an rclpy node in the test process."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import rclpy
from breaker_cases import made_test_keys
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from controlled_islanding.graph.rosenv import isolated_ros_environment, reserved_domain_id
from controlled_islanding.graph.supervisor import Supervisor
from controlled_islanding.ros.diagnostics import writers_matched
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.wire import topics

BUILD = Path(__file__).resolve().parents[1] / 'build'


@contextmanager
def default_context() -> Iterator[None]:
    """Initialise rclpy's default context on a domain no concurrent run holds; shut it down at the end."""
    with reserved_domain_id() as domain_id:
        rclpy.init(domain_id=domain_id)
        try:
            yield
        finally:
            rclpy.shutdown()


def ctrl_c_as_at_a_terminal() -> None:
    """Handle SIGINT by default, as under a terminal (a subprocess preexec_fn).

    A shell runs a background job (`cmd &`, nohup) with SIGINT ignored, and Python keeps an ignored SIGINT
    ignored, so a Ctrl-C test run from one would send a signal nobody hears.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Probe:
    """Publishes, collects and calls services on the graph under test; reads /diagnostics."""

    def __init__(self, domain_id: int) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('test_probe', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.pubs = {}
        self.received: dict[str, list] = {}
        self.diagnostics: dict[str, dict[str, str]] = {}
        self.levels: dict[str, tuple[bytes, str]] = {}  # status name -> (level, message)
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, qos_for(topics.DIAGNOSTICS))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.diagnostics[status.name.lstrip('/')] = {kv.key: kv.value for kv in status.values}
            self.levels[status.name.lstrip('/')] = (status.level, status.message)

    def publisher(self, msg_type: type, topic: str):
        """Return (and keep) a publisher with the topic's documented QoS."""
        if topic not in self.pubs:
            self.pubs[topic] = self.node.create_publisher(msg_type, topic, qos_for(topic))
        return self.pubs[topic]

    def collect(self, msg_type: type, topic: str) -> list:
        """Start collecting a topic; return the list messages are appended to."""
        bucket = self.received.setdefault(topic, [])
        self.node.create_subscription(msg_type, topic, bucket.append, qos_for(topic))
        return bucket

    def spin_until(self, predicate: Callable[[], bool], timeout_s: float = 10.0) -> bool:
        """Spin until predicate() is true or the time passes; return predicate()."""
        end = time.monotonic() + timeout_s
        while not predicate() and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)
        return predicate()

    def spin_for(self, seconds: float) -> None:
        """Spin for a while."""
        self.spin_until(lambda: False, seconds)

    def wait_matched(self, topic: str, count: int = 1, timeout_s: float = 20.0) -> None:
        """Wait until our publisher on topic has at least count subscribers."""
        assert self.spin_until(lambda: self.pubs[topic].get_subscription_count() >= count, timeout_s), \
            f'no subscriber matched {topic} within {timeout_s} s'

    def wait_wired(self, nodes: tuple[str, ...], timeout_s: float = 20.0) -> None:
        """Wait until every writer of each node matches every reader of its topic, as its /diagnostics say."""
        def wired() -> bool:
            return all(writers_matched(self.diagnostics.get(n, {}), self.node.count_subscribers) for n in nodes)

        if not self.spin_until(wired, timeout_s):
            seen = {n: {k: v for k, v in self.diagnostics.get(n, {}).items() if k.startswith('matched.')}
                    for n in nodes}
            raise AssertionError(f'writers not matched within {timeout_s} s: {seen}')

    def counter(self, node: str, key: str) -> int:
        """Return a diagnostics counter of a node (0 if not reported yet)."""
        return int(float(self.diagnostics.get(node, {}).get(key, '0')))

    def wait_counter(self, node: str, key: str, at_least: int, timeout_s: float = 10.0) -> int:
        """Wait until a node's diagnostics counter reaches a value; return it."""
        self.spin_until(lambda: self.counter(node, key) >= at_least, timeout_s)
        return self.counter(node, key)

    def burst(self, nodes: tuple[str, ...], topic: str, msg, count: int) -> dict[str, int]:
        """Publish msg count times back to back; return each node's growth of `lost.<topic>`.

        Asserts that every node accounted for each message, as received or as lost.
        """
        key = f'lost.{topic}'
        self.spin_for(1.5)  # the latest diagnostics of every node are in

        def accounted(node: str) -> int:
            return self.counter(node, 'received') + self.counter(node, key)

        before = {n: accounted(n) for n in nodes}
        lost_before = {n: self.counter(n, key) for n in nodes}
        for _ in range(count):
            self.pubs[topic].publish(msg)
        # The last message is always taken, and each one it overtook is then counted from the sequence numbers.
        for n in nodes:
            assert self.spin_until(lambda n=n: accounted(n) - before[n] >= count, 20.0), (n, accounted(n) - before[n])
        self.spin_for(1.5)
        assert {n: accounted(n) - before[n] for n in nodes} == {n: count for n in nodes}
        return {n: self.counter(n, key) - lost_before[n] for n in nodes}

    def call(self, srv_type: type, name: str, request, timeout_s: float = 20.0):
        """Call a service and return its response."""
        client = self.node.create_client(srv_type, name)
        assert client.wait_for_service(timeout_sec=timeout_s), f'service {name} not offered'
        future = client.call_async(request)
        assert self.spin_until(future.done, timeout_s), f'service {name} did not answer'
        return future.result()

    def close(self) -> None:
        """Destroy every node on the probe's executor, then shut the context down.

        A node left alive keeps the context's DDS participant, and its endpoints, visible to whatever runs next on
        the domain (a test's /clock forger was found in a later testbed's graph).
        """
        for node in list(self.executor.get_nodes()):
            node.destroy_node()
        self.context.try_shutdown()


@contextmanager
def graph(name: str, specs_and_overrides: list) -> Iterator[tuple[Supervisor, Probe]]:
    """Start nodes on a private domain and yield (supervisor, probe); stop everything afterwards.

    Args:
        name: Run name, for the log directory under build/.
        specs_and_overrides: (NodeSpec, parameter overrides) pairs to start, or (NodeSpec, overrides,
            namespace) triples; a namespaced child's log is <namespace>.<executable>.log.

    """
    with isolated_ros_environment(BUILD / 'ros_log' / name) as env:
        # Nodes that sign or check signatures use keys this test run made, never the user's own.
        env = {**env, 'CONTROLLED_ISLANDING_KEYS': str(made_test_keys())}
        with Supervisor(env, BUILD / 'test_nodes' / name / f'{time.time_ns()}') as sup:
            for spec, overrides, *namespace in specs_and_overrides:
                ns = namespace[0].strip('/') if namespace else ''
                sup.start(spec, overrides, name=f'{ns.replace("/", ".")}.{spec.executable}' if ns else None,
                          namespace=ns)
            probe = Probe(int(env['ROS_DOMAIN_ID']))
            try:
                yield sup, probe
            finally:
                probe.close()


@contextmanager
def bag_writer(path: Path) -> Iterator[Callable[[str, object, int], bytes]]:
    """Open a new MCAP bag; yield put(topic, rclpy message, log time ns), which writes it and returns its bytes."""
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer

    from controlled_islanding.wire.interfaces import typestore

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}

        def put(topic: str, msg: object, t_ns: int) -> bytes:
            if topic not in conns:
                name = type(msg).__module__.split('.')[0] + '/msg/' + type(msg).__name__
                conns[topic] = writer.add_connection(topic, name, typestore=typestore())
            raw = serialize_message(msg)
            writer.write(conns[topic], t_ns, raw)
            return raw

        yield put
