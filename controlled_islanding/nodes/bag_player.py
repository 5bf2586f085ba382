"""bag_player: publish a rosbag2 bag's messages as they were recorded, as serialized CDR bytes.

Timing follows the bag's log times divided by `rate`; `as_fast_as_possible` drops the waits. /clock carries
the bag time of every message, for nodes running with use_sim_time. Ground-truth topics (/truth/...) are never
published unless `publish_truth` is set, so the graph under test cannot see the answer. Each bag topic is
played under its name relative to the player's namespace (a bag of /pmu/frames plays on /area1/pmu/frames in
/area1); /clock stays global unless remapped.

In as-fast-as-possible mode with `lockstep_on_requests` (the default), the player keeps the graph in step at
each islanding request: before publishing it, it waits until /rotor_angles has caught up with the newest PMU
frame played, and then until /coherent_groups has (coherency has taken every sample up to that frame: a
coherency node still working through a backlog, or through its first, slow computation, would otherwise get
the request seconds late and partitioning refuse it as stale, which real time never sees); after it, data
keeps flowing in bag order (frames delayed past the request still arrive after it, as in real time, up to
`lockstep_lead_s` of bag time past it) but /clock stays at the request time until a decision is out and
`decision_consumer` (breaker_command, which refuses a decision more than max_decision_age_s older than its
clock) has handled it, as its /diagnostics say at once (`decisions_handled`). A graph whose decision readers
include no such node (a test's probe) gets `lockstep_settle_s` of wall time instead: no fixed time is right for
a loaded breaker_command, which once took longer than the 0.1 s it had and refused GBnetwork's cut as stale. A
wait for the decision lasts at most `lockstep_timeout_s`, after which the request is sent again with its id
(twice at most: a restarted partitioning node lost it); a wait for rotor angles, groups or the consumer lasts
until they stop moving towards what is awaited for that long, since under load each stage can take longer than
any fixed time while it still catches up. So the decision
sees the data a real-time replay would, and no node sees it as stale on the replayed clock, however loaded the
machine is.

Elsewhere, as fast as possible, flow control holds at most `flow_window_frames` PMU frames unanswered: frame n
goes out only once /rotor_angles has answered frame n - W (pmu_ingestion publishes one RotorAngles per frame it
uses, stamped with the frame's time tag, and takes its frames in the order they were sent, so an answer to a
later frame means every earlier one was taken, used or refused). Without it the whole bag went out at once and
waited in the readers' queues, which keep the last 1000 frames (wire/qos.py): a bag longer than that would lose
its oldest frames at a reader that lags, and no fixed pace could say how much is too much on a loaded machine.
With no /rotor_angles publisher matched (a graph without pmu_ingestion), or once no answer has come for
`flow_stall_s` (frames refused one after another, say), the player stops waiting for answers, says so in its log
and report, and plays on as fast as it can.

While it waits (lockstep, flow control, or between messages), the player publishes the current /clock again every
`clock_heartbeat_s` of wall time: rclpy's time source reads /clock best effort, so a node can lose the last
/clock sample before a wait, and its clock would then stand still for the whole wait, holding every stamp more
than its `future_tolerance_s` ahead (a lockstep wait for data held that way could only time out).

As fast as possible, after each message of a latched (transient-local) topic - the network snapshot, a branch
status - the player waits until every matched reader has acknowledged it (`Publisher.wait_for_all_acked`, at most
`latched_ack_timeout_s`, logged) before it plays on. Such a message is sent once: a reader that misses its first
delivery gets it again only on the writer's next heartbeat (every 0.1 s in ros/spin.py's profile, 3 s by Fast
DDS's default, which an outside graph may keep), and its fragments (270 kB for the 2224-bus snapshot) share the
player's shared-memory segment with the PMU frames that follow at full speed, so a slow reader can lose them to
the flood. Once acknowledged, it is in the reader's history and cannot be lost.
"""

from __future__ import annotations

import json
import struct
import sys
import time
from collections import deque
from pathlib import Path

from builtin_interfaces.msg import Time
from controlled_islanding_msgs.msg import CoherentGroups, IslandingDecision, RotorAngles
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy
from rosbags.highlevel import AnyReader
from rosgraph_msgs.msg import Clock

from controlled_islanding import atomic
from controlled_islanding.ros.diagnostics import DECISIONS_HANDLED, Diagnostics
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.params import NodeSetupError, message_class
from controlled_islanding.ros.spin import spin_node
from controlled_islanding.wire import topics
from controlled_islanding.wire.bagmeta import other_definitions, unreadable
from controlled_islanding.wire.interfaces import typestore

_STAMP_ROUNDING_NS = 1_000
_POLL_S = 0.02  # longest spin between two looks at a wait's condition, s

_UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'  # rmw_dds_common's name of an endpoint whose node is not yet known


class BagPlayerNode(Node):
    """Loads a bag into memory and plays it onto its topics."""

    def __init__(self, **node_options) -> None:
        super().__init__('bag_player', **node_options)
        self.declare_parameter('bag', '')
        self.declare_parameter('rate', 1.0)
        self.declare_parameter('as_fast_as_possible', False)
        self.declare_parameter('publish_truth', False)
        self.declare_parameter('publish_clock', True)
        self.declare_parameter('wait_for_subscribers_s', 10.0)
        self.declare_parameter('wait_for_subscriber_count', 1)
        self.declare_parameter('min_subscribers', [''])
        self.declare_parameter('lockstep_on_requests', True)
        self.declare_parameter('lockstep_timeout_s', 20.0)
        self.declare_parameter('lockstep_settle_s', 0.1)
        self.declare_parameter('decision_consumer', 'breaker_command')
        self.declare_parameter('lockstep_lead_s', 0.5)
        self.declare_parameter('report_file', '')
        self.declare_parameter('clock_min_step_s', 0.0)
        self.declare_parameter('clock_heartbeat_s', 0.05)
        self.declare_parameter('latched_ack_timeout_s', 5.0)
        self.declare_parameter('flow_window_frames', 30)
        self.declare_parameter('flow_stall_s', 2.0)
        # A file whose appearance starts the play (JSON {"min_subscribers": [...]}, which then replaces the
        # parameter): a replay starts the player with the graph, so loading the bag and being discovered overlap
        # the nodes' start-up, and tells it to go once the graph is wired.
        self.declare_parameter('go_file', '')
        self.declare_parameter('go_timeout_s', 300.0)
        # Topics another source feeds live (e.g. /pmu/frames from pdc_client): the bag's copy is not played.
        self.declare_parameter('withhold_topics', [''])
        bag = self.get_parameter('bag').value
        self.rate = float(self.get_parameter('rate').value)
        if not bag:
            raise NodeSetupError('parameter bag is empty; it must name a rosbag2 bag directory or .mcap file')
        if self.rate <= 0.0:
            raise NodeSetupError(f'parameter rate={self.rate} must be positive')
        self.afap = bool(self.get_parameter('as_fast_as_possible').value)
        self.lockstep = self.afap and bool(self.get_parameter('lockstep_on_requests').value)
        self.lockstep_timeout_s = float(self.get_parameter('lockstep_timeout_s').value)
        self.lockstep_settle_s = float(self.get_parameter('lockstep_settle_s').value)
        self.decision_consumer = str(self.get_parameter('decision_consumer').value)
        self.lockstep_lead_ns = int(float(self.get_parameter('lockstep_lead_s').value) * 1e9)
        self.report_file = self.get_parameter('report_file').value
        self.clock_step_ns = int(float(self.get_parameter('clock_min_step_s').value) * 1e9)
        self.clock_heartbeat_s = float(self.get_parameter('clock_heartbeat_s').value)
        if self.clock_heartbeat_s <= 0.0:
            raise NodeSetupError(f'parameter clock_heartbeat_s={self.clock_heartbeat_s} must be positive')
        self.latched_ack_timeout_s = float(self.get_parameter('latched_ack_timeout_s').value)
        self.flow_window = int(self.get_parameter('flow_window_frames').value) if self.afap else 0
        self.flow_stall_s = float(self.get_parameter('flow_stall_s').value)
        if self.flow_window < 0 or self.flow_stall_s <= 0.0:
            raise NodeSetupError(f'parameters flow_window_frames={self.flow_window} must be >= 0 (0: no flow control) '
                                 f'and flow_stall_s={self.flow_stall_s} positive')
        publish_truth = bool(self.get_parameter('publish_truth').value)
        self.messages: list[tuple[str, int, bytes]] = []
        self.pubs = {}
        try:
            with AnyReader([Path(bag)], default_typestore=typestore()) as reader:
                withheld = set(self.get_parameter('withhold_topics').value)
                chosen = [c for c in reader.connections if (publish_truth or c.topic not in topics.TRUTH_TOPICS)
                          and c.topic not in withheld]
                stale = other_definitions(chosen, typestore())
                if stale:
                    raise NodeSetupError(
                        f'bag {bag}: {", ".join(stale)} recorded with another definition than msg_schemas/ holds; '
                        'its messages would not decode in any subscriber: record or simulate the bag again')
                for conn in chosen:
                    if conn.topic not in self.pubs:
                        self.pubs[conn.topic] = self.create_publisher(
                            message_class(conn.msgtype), topics.relative(conn.topic), qos_for(conn.topic))
                self.messages = [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages(connections=chosen)]
        except NodeSetupError:
            raise
        except Exception as exc:  # rosbags raises many reader error types; all mean the bag is unusable
            raise NodeSetupError(f'cannot read the bag: {unreadable(bag, exc)}') from exc
        if not self.messages:
            raise NodeSetupError(f'bag {bag}: no messages on any topic to play')
        self.clock_pub = (self.create_publisher(Clock, topics.CLOCK, qos_for(topics.CLOCK))
                          if self.get_parameter('publish_clock').value else None)
        self.decisions = 0
        self.held_s: dict[str, float] = {}  # wall time spent in each lockstep wait
        self.ack_waits_s: list[float] = []  # wall time each latched message took to be acknowledged by every reader
        self.unacked: list[str] = []  # latched topics whose message some reader had not acknowledged in time
        self.latched = {t for t in self.pubs
                        if qos_for(t).durability == DurabilityPolicy.TRANSIENT_LOCAL}
        self.newest_angle_ns = -1
        self.newest_groups_ns = -1
        self.consumer_handled = 0  # decisions decision_consumer said it has handled
        self.frames_sent = 0  # PMU frames published so far
        self.answered_upto = -1  # the latest frame (by publication index) answered on /rotor_angles
        self.unanswered: dict[int, deque[int]] = {}  # frame time tag, ns -> indices of its unanswered frames
        self.flow_stalled_at: int | None = None  # the frame at which flow control gave up waiting
        self.clock_ns: int | None = None  # the bag time last published on /clock
        self.clock_sent_at = 0.0  # wall (monotonic) time it was last published, s
        self.lockstep_subs = []
        self.angles_sub = None
        if self.lockstep or self.flow_window:
            self.angles_sub = self.create_subscription(RotorAngles, topics.relative(topics.ROTOR_ANGLES),
                                                       self._on_angles, qos_for(topics.ROTOR_ANGLES))
        if self.lockstep:
            self.lockstep_subs = [
                self.create_subscription(IslandingDecision, topics.relative(topics.ISLANDING_DECISION),
                                         self._on_decision, qos_for(topics.ISLANDING_DECISION)),
                self.angles_sub,
                self.create_subscription(CoherentGroups, topics.relative(topics.COHERENT_GROUPS), self._on_groups,
                                         qos_for(topics.COHERENT_GROUPS))]
            self.consumer_status = f'{self.get_namespace().rstrip("/")}/{self.decision_consumer}'
            self.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics,
                                     qos_for(topics.DIAGNOSTICS))
        self.diag = Diagnostics(self)
        self.loaded_unix = time.time()
        self.get_logger().info(f'{len(self.messages)} messages on {len(self.pubs)} topics from {bag}')

    def _on_decision(self, _msg: IslandingDecision) -> None:
        self.decisions += 1

    def _on_angles(self, msg: RotorAngles) -> None:
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.newest_angle_ns = max(self.newest_angle_ns, stamp_ns)
        waiting = self.unanswered.get(stamp_ns)
        if waiting:
            self.answered_upto = max(self.answered_upto, waiting.popleft())
            if not waiting:
                del self.unanswered[stamp_ns]

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == self.consumer_status:
                for kv in status.values:
                    if kv.key == DECISIONS_HANDLED and kv.value.isdigit():
                        self.consumer_handled = max(self.consumer_handled, int(kv.value))

    def _consumer_reads_decisions(self) -> bool | None:
        """Return whether decision_consumer reads decisions; None while a reader's node is not yet known."""
        topic = self.resolve_topic_name(topics.relative(topics.ISLANDING_DECISION))
        readers = self.get_subscriptions_info_by_topic(topic)
        if any(info.node_name == self.decision_consumer and info.node_namespace == self.get_namespace()
               for info in readers):
            return True
        # A reader's node name comes on its own discovery topic, later than the reader itself under load.
        return None if any(info.node_name == _UNKNOWN_NODE for info in readers) else False

    def _await_handled(self, executor: SingleThreadedExecutor) -> None:
        """Hold until decision_consumer has handled every decision seen; lockstep_settle_s if none reads them."""
        self._hold(executor, 'the names of the decision readers', lambda: self._consumer_reads_decisions() is not None)
        if self._consumer_reads_decisions():
            self._hold(executor, f'decision handled by {self.decision_consumer}',
                       lambda: self.consumer_handled >= self.decisions, lambda: self.consumer_handled)
        else:
            self._spin_until(executor, time.monotonic() + self.lockstep_settle_s)

    def _on_groups(self, msg: CoherentGroups) -> None:
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.newest_groups_ns = max(self.newest_groups_ns, stamp_ns)

    def _publish_clock(self, clock_ns: int) -> None:
        assert self.clock_pub is not None
        self.clock_pub.publish(Clock(clock=Time(sec=clock_ns // 1_000_000_000, nanosec=clock_ns % 1_000_000_000)))
        self.clock_ns, self.clock_sent_at = clock_ns, time.monotonic()

    def _hold(self, executor: SingleThreadedExecutor, what: str, done, progress=lambda: None,
              timeout_s: float | None = None) -> bool:
        """Spin until done(), or until progress() (a stamp, say) has stood still for timeout_s; return done().

        timeout_s defaults to lockstep_timeout_s; a lockstep wait that ends without done() is logged here.
        """
        limit_s = self.lockstep_timeout_s if timeout_s is None else timeout_s
        t0 = last_move = time.monotonic()
        seen = progress()
        while not done() and time.monotonic() < last_move + limit_s:
            self._spin_until(executor, min(last_move + limit_s, time.monotonic() + 0.1), done)
            if progress() != seen:
                seen, last_move = progress(), time.monotonic()
        self.held_s[what] = self.held_s.get(what, 0.0) + time.monotonic() - t0
        if not done() and timeout_s is None:
            self.get_logger().warning(f'lockstep: no {what}, and no progress towards it for lockstep_timeout_s='
                                      f'{self.lockstep_timeout_s}')
        return done()

    def _await_window(self, executor: SingleThreadedExecutor) -> None:
        """Flow control: return once fewer than flow_window_frames frames are unanswered on /rotor_angles."""
        if not self.flow_window or self.frames_sent - 1 - self.answered_upto < self.flow_window:
            return
        if self.angles_sub.get_publisher_count() == 0:
            self.get_logger().info('no /rotor_angles publisher to answer frames: playing without flow control')
            self.flow_window = 0
            return
        if not self._hold(executor, 'flow control (frames answered on /rotor_angles)',
                          lambda: self.frames_sent - 1 - self.answered_upto < self.flow_window,
                          lambda: self.answered_upto, self.flow_stall_s):
            self.flow_stalled_at, self.flow_window = self.frames_sent, 0
            self.get_logger().warning(
                f'flow control: no answer on /rotor_angles to frames {self.answered_upto + 1} to '
                f'{self.frames_sent - 1} for flow_stall_s={self.flow_stall_s}; playing on without flow control')

    def _await_decision(self, executor: SingleThreadedExecutor, waiting_for: int, request: bytes) -> None:
        """Hold for the decision; re-send the request (same id) each time the wait times out, twice at most.

        A partitioning node restarted by the supervisor (hung under load, say) lost the volatile request it
        held; partitioning answers each request id once, so a repeat to a node that has it changes nothing.
        """
        for attempt in range(3):
            if attempt:
                self.get_logger().warning(f'lockstep: re-sending the islanding request ({attempt} of 2)')
                self.pubs[topics.ISLANDING_REQUEST].publish(request)
            self._hold(executor, 'decision', lambda: self.decisions >= waiting_for)
            if self.decisions >= waiting_for:
                return

    def _await_acks(self, executor: SingleThreadedExecutor, topic: str) -> None:
        """Spin until every matched reader acknowledged what `topic`'s writer sent, or latched_ack_timeout_s."""
        t0 = time.monotonic()
        deadline = t0 + self.latched_ack_timeout_s
        poll = Duration(nanoseconds=10_000_000)
        while not (acked := self.pubs[topic].wait_for_all_acked(poll)) and time.monotonic() < deadline:
            self._spin_until(executor, time.monotonic() + 0.001)
        waited_s = time.monotonic() - t0
        self.ack_waits_s.append(waited_s)
        if not acked:
            self.unacked.append(topic)
            self.get_logger().warning(f'{topic}: not acknowledged by every reader within latched_ack_timeout_s='
                                      f'{self.latched_ack_timeout_s}; playing on')
        elif waited_s > 0.5:
            self.get_logger().info(f'{topic}: acknowledged by every reader after {waited_s:.2f} s')

    @staticmethod
    def _frame_stamp_ns(raw: bytes, t_ns: int) -> int:
        # CDR: 4-byte encapsulation header, then header.stamp (int32 sec, uint32 nanosec), little endian.
        if len(raw) >= 12 and raw[1] == 1:
            sec, nanosec = struct.unpack_from('<iI', raw, 4)
            return sec * 1_000_000_000 + nanosec
        return t_ns

    def _spin_until(self, executor: SingleThreadedExecutor, deadline: float, done=lambda: False) -> None:
        while not done():
            now = time.monotonic()
            left = deadline - now
            if left <= 0:
                return
            if self.clock_ns is not None:
                beat = self.clock_sent_at + self.clock_heartbeat_s
                if now >= beat:
                    self._publish_clock(self.clock_ns)
                    beat = self.clock_sent_at + self.clock_heartbeat_s
                left = min(left, beat - now)
            # done() may turn on without any callback (a subscriber matched, a file appeared): look again often.
            executor.spin_once(timeout_sec=min(max(left, 0.0), _POLL_S))

    def await_go(self, executor: SingleThreadedExecutor) -> list[str] | None:
        """Spin until `go_file` exists; return its min_subscribers (None without a go_file).

        Raises:
            NodeSetupError: The file did not appear within go_timeout_s, or is not the expected JSON.

        """
        go_file = self.get_parameter('go_file').value
        if not go_file:
            return None
        path = Path(go_file)
        deadline = time.monotonic() + float(self.get_parameter('go_timeout_s').value)
        self._spin_until(executor, deadline, path.exists)
        if not path.exists():
            raise NodeSetupError(f'go_file {go_file} did not appear within go_timeout_s')
        try:
            return [str(x) for x in json.loads(path.read_text())['min_subscribers']]
        except (ValueError, KeyError, TypeError) as exc:
            raise NodeSetupError(f'go_file {go_file}: not {{"min_subscribers": [...]}}: {exc}') from exc

    def wait_for_subscribers(self, executor: SingleThreadedExecutor, min_subscribers: list[str] | None = None) -> None:
        """Wait for subscribers (`min_subscribers` 'topic=count', else `wait_for_subscriber_count`), or the time."""
        deadline = time.monotonic() + float(self.get_parameter('wait_for_subscribers_s').value)
        want = {t: int(self.get_parameter('wait_for_subscriber_count').value) for t in self.pubs}
        if min_subscribers is None:
            min_subscribers = self.get_parameter('min_subscribers').value
        for item in min_subscribers:
            topic, _, count = item.rpartition('=')
            if topic:
                want[topic] = int(count)
        # /clock too: nodes on use_sim_time must see the clock from the first message on.
        waited = dict(self.pubs, **({topics.CLOCK: self.clock_pub} if self.clock_pub is not None else {}))
        want.setdefault(topics.CLOCK, want[next(iter(self.pubs))])

        def ready() -> bool:
            return (all(p.get_subscription_count() >= want.get(t, 1) for t, p in waited.items())
                    and all(s.get_publisher_count() > 0 for s in self.lockstep_subs))

        self._spin_until(executor, deadline, ready)
        lonely = [f'{t} ({p.get_subscription_count()} of {want.get(t, 1)})' for t, p in waited.items()
                  if p.get_subscription_count() < want.get(t, 1)]
        if lonely:
            self.get_logger().warning(f'playing although too few subscribers match {", ".join(lonely)}')

    def play(self, executor: SingleThreadedExecutor) -> dict:
        """Publish every message at its time; return a report with the speed against real time."""
        t0_ns = self.messages[0][1]
        begun_unix = time.time()
        start = time.monotonic()
        last_frame_ns = -1
        frozen_at_ns = None  # lockstep: bag time stays here from a request until its decision is handled
        waiting_for = 0
        pending_request = b''
        for n, (topic, t_ns, raw) in enumerate(self.messages):
            if not self.afap:
                self._spin_until(executor, start + (t_ns - t0_ns) * 1e-9 / self.rate)
            request = topic == topics.ISLANDING_REQUEST
            if frozen_at_ns is not None and t_ns > frozen_at_ns + self.lockstep_lead_ns:
                # Nodes refuse stamps far ahead of their clock: data may run ahead of the frozen clock by
                # lockstep_lead_s, not more, so wait for the decision before going further.
                self._await_decision(executor, waiting_for, pending_request)
            if self.lockstep and request and last_frame_ns >= 0:
                # A loaded machine can make either stage take longer than any fixed time while it still moves on;
                # the wait ends early only when the stage stops moving (a dead or hung node).
                self._hold(executor, 'rotor angles up to the newest frame',
                           lambda f=last_frame_ns: self.newest_angle_ns >= f, lambda: self.newest_angle_ns)
                # Coherency stamps its groups with its newest sample's time as float seconds, which rounds a
                # POSIX stamp by up to ~0.2 us.
                self._hold(executor, 'coherent groups up to the newest frame',
                           lambda f=last_frame_ns: self.newest_groups_ns >= f - _STAMP_ROUNDING_NS,
                           lambda: self.newest_groups_ns)
            if frozen_at_ns is not None and self.decisions >= waiting_for:
                self._await_handled(executor)
                frozen_at_ns = None
            clock_ns = t_ns if frozen_at_ns is None else frozen_at_ns
            if self.clock_pub is not None and (self.clock_ns is None or request
                                               or clock_ns - self.clock_ns >= self.clock_step_ns):
                self._publish_clock(clock_ns)
            frame = topic == topics.PMU_FRAMES
            if frame:
                self._await_window(executor)
            self.pubs[topic].publish(raw)
            self.diag.arrived()
            if self.afap and topic in self.latched:
                self._await_acks(executor, topic)
            if frame:
                stamp_ns = self._frame_stamp_ns(raw, t_ns)
                last_frame_ns = max(last_frame_ns, stamp_ns)
                if self.flow_window:
                    self.unanswered.setdefault(stamp_ns, deque()).append(self.frames_sent)
                self.frames_sent += 1
            if self.lockstep and request:
                # Data keeps flowing in bag order (late frames arrive after the request, as in real time),
                # but /clock stops until the decision is out and handled, so nobody sees it as stale.
                frozen_at_ns, waiting_for, pending_request = t_ns, self.decisions + 1, raw
            if self.afap and n % 20 == 0:
                executor.spin_once(timeout_sec=0.0)
        if frozen_at_ns is not None:
            self._await_decision(executor, waiting_for, pending_request)
            self._await_handled(executor)
        wall_s = time.monotonic() - start
        bag_s = (self.messages[-1][1] - t0_ns) * 1e-9
        report = {'messages': len(self.messages), 'bag_duration_s': bag_s, 'wall_s': wall_s,
                  'speed_vs_real_time': bag_s / wall_s if wall_s > 0 else float('inf'),
                  'as_fast_as_possible': self.afap, 'rate': self.rate, 'lockstep_waits_s': self.held_s,
                  'latched_ack_waits_s': self.ack_waits_s, 'latched_unacked': self.unacked,
                  'flow_window_frames': int(self.get_parameter('flow_window_frames').value) if self.afap else 0,
                  'flow_stalled_at_frame': self.flow_stalled_at,
                  'loaded_unix': self.loaded_unix, 'play_begun_unix': begun_unix, 'play_ended_unix': time.time()}
        self.get_logger().info(f'played {len(self.messages)} messages: {bag_s:.2f} s of bag in {wall_s:.2f} s '
                               f'({report["speed_vs_real_time"]:.1f}x real time)')
        if self.report_file:
            atomic.write_text(self.report_file, json.dumps(report))
        return report


def play_once(node: BagPlayerNode, executor: SingleThreadedExecutor) -> None:
    """Wait for the go file and the subscribers, play the bag once, linger until every reader acknowledged it."""
    node.wait_for_subscribers(executor, node.await_go(executor))
    node.play(executor)
    # Reliable writers still hold what a reader has not acknowledged; leaving sooner would lose it.
    deadline = time.monotonic() + 0.5
    node._spin_until(executor, deadline, lambda: all(
        p.wait_for_all_acked(Duration(nanoseconds=5_000_000)) for p in node.pubs.values()))


def main(args: list[str] | None = None) -> int:
    """Run the bag_player: wait for subscribers, play the bag once, linger until every reader acknowledged it."""
    return spin_node(BagPlayerNode, args, run=play_once)

if __name__ == '__main__':
    sys.exit(main())
