"""What every node shares: per-topic QoS, bad-input accounting with /diagnostics, and the process main loop.

QoS per topic (reliable everywhere: a lost request, decision or command is a lost control action):
- /pmu/frames, /rotor_angles: KEEP_LAST 1000, volatile. Deep enough that an as-fast-as-possible replay
  of a whole window never drops a frame; live, a late frame is useless, so nothing is latched.
- /network/snapshot: KEEP_LAST 1, transient local: a late joiner gets the latest state.
- /coherent_groups: KEEP_LAST 16, transient local: coherency publishes the groups ending at a request and,
  moments later, periodic ones on newer data; with KEEP_LAST 1 a busy partitioning node lost the first to the
  second and refused the request as stale. 16 = the groupings partitioning keeps, each for its own time.
- /network/branch_status: KEEP_LAST 100, transient local: a late partitioning node still learns every trip.
- /islanding/request, /islanding/decision, /breaker/commands: KEEP_LAST 100, volatile. Never latched: a
  breaker node that starts late must not execute a decision made before it existed.
- /islanding/decision also has an AUTOMATIC liveliness lease of DECISION_LEASE_S: the topic is silent between
  requests by design, so only liveliness tells a breaker node that the control centre is gone (process dead,
  host or WAN down). A reader matches only writers offering a lease no longer than the one it requests.
- /diagnostics: KEEP_LAST 10, volatile (the diagnostic_aggregator convention).
- /clock: KEEP_LAST 1, volatile; rclpy's time source subscribes best effort, which a reliable writer serves.

Readers and writers allocate each DDS sample's buffer when it arrives and free it when it is taken
(Fast DDS history memory policy DYNAMIC, see `_dds_memory_profile`): under rmw_fastrtps' default
(PREALLOCATED_WITH_REALLOC) every pooled buffer keeps the largest size it ever held, so a KEEP_LAST 1000
reader that now and then gets a frame of 10,000 PMUs grows towards 1000 x 720 kB.

Reliable writers send a heartbeat every 0.1 s while a reader has not acknowledged a sample (same profile; Fast
DDS's default is 3 s). A reader that misses a sample's first delivery asks for it again only after a heartbeat:
in three IEEE 14 fast replays, each of the 6 branch statuses played was acknowledged by every reader only after
0.6-3.0 s with 3 s (bag_player's acknowledgement wait), after 0.04-0.17 s with 0.1 s; a request, decision or
command lost live would be as late.
"""

from __future__ import annotations

import functools
import gc
import importlib
import os
import tempfile
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration
from rclpy.exceptions import InvalidParameterValueException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy

from controlled_islanding.wire import topics
from controlled_islanding.wire.messages import Limits
from controlled_islanding.wire.timebounds import StampError, StampGate


class NodeSetupError(ValueError):
    """A node's parameters or message types are unusable."""


# rmw_fastrtps asserts AUTOMATIC liveliness every 2/3 of the lease, so one lost assertion outlasts it; a lease of
# 3 s at 2 s assertions gives a writer's silence away within 3-5 s (measured in docs/deployment.md).
DECISION_LEASE_S = 3.0


def _qos(depth: int, latched: bool = False, lease_s: float | None = None) -> QoSProfile:
    qos = QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
    if lease_s is not None:
        qos.liveliness = LivelinessPolicy.AUTOMATIC
        qos.liveliness_lease_duration = Duration(nanoseconds=int(lease_s * 1e9))
    return qos


TOPIC_QOS: dict[str, QoSProfile] = {
    topics.PMU_FRAMES: _qos(1000),
    topics.ROTOR_ANGLES: _qos(1000),
    topics.NETWORK_SNAPSHOT: _qos(1, latched=True),
    topics.COHERENT_GROUPS: _qos(16, latched=True),
    topics.BRANCH_STATUS: _qos(100, latched=True),
    topics.ISLANDING_REQUEST: _qos(100),
    topics.ISLANDING_DECISION: _qos(100, lease_s=DECISION_LEASE_S),
    topics.BREAKER_COMMANDS: _qos(100),
    topics.DIAGNOSTICS: _qos(10),
    topics.CLOCK: _qos(1),
    topics.TRUTH_ROTOR_ANGLES: _qos(1000),
    topics.TRUTH_COHERENT_GROUPS: _qos(1, latched=True),
}


def qos_for(topic: str) -> QoSProfile:
    """Return the documented QoS of a topic; unknown topics get reliable, volatile, depth 100.

    The topic may be named as in the root namespace (/pmu/frames), relative (pmu/frames) or in any namespace
    (/area1/pmu/frames): a name ending in a documented one has its QoS.
    """
    name = topic if topic.startswith('/') else f'/{topic}'
    known = [k for k in TOPIC_QOS if name.endswith(k)]
    return TOPIC_QOS[max(known, key=len)] if known else _qos(100)


def message_class(type_name: str) -> type:
    """Return the rclpy message class of a full ROS 2 type name such as 'std_msgs/msg/String'.

    Raises:
        NodeSetupError: The type name is malformed or its package is not installed.

    """
    parts = type_name.split('/')
    if len(parts) != 3:
        raise NodeSetupError(f'message type {type_name!r} is not of the form package/msg/Name')
    try:
        return getattr(importlib.import_module(f'{parts[0]}.{parts[1]}'), parts[2])
    except (ImportError, AttributeError) as exc:
        raise NodeSetupError(f'message type {type_name!r} is not installed: {exc}') from exc


class LossCounter:
    """Counts the messages one reader lost, from the writers' publication sequence numbers.

    Each writer numbers its samples 1, 2, 3, ...; a reliable reader gets them in order, so a jump is what
    its keep-last history (or the writer's) dropped. rclpy's MessageInfo names no writer, so writers are
    told apart by continuity: a number continues the stream whose last number is the closest below it, and
    one below every stream starts a new stream (a new or restarted writer). Messages before the first one a
    reader sees are not counted (a volatile late joiner was never owed them).

    Args:
        max_writers: Streams remembered; the least recently continued is forgotten beyond.

    """

    def __init__(self, max_writers: int = 8) -> None:
        self.lost = 0
        self._last: list[int] = []  # last sequence number per stream, least recently continued first
        self._max_writers = max_writers

    def seen(self, sequence: int | None) -> int:
        """Take one message's publication sequence number (None: the middleware gives none); return new losses."""
        if sequence is None:
            return 0
        below = [s for s in self._last if s < sequence]
        gap = 0
        if below:
            previous = max(below)
            self._last.remove(previous)
            gap = sequence - previous - 1
        self._last.append(sequence)
        del self._last[:-self._max_writers]
        self.lost += gap
        return gap


class TopicStatus:
    """One input topic's status in diagnostic_updater's TopicDiagnostic form: frequency and time stamps.

    Frequency (FrequencyStatus): messages over the last `window` publishes (one a second) divided by how far
    the node clock moved meanwhile; OK within `tolerance` of the expected rate, WARN "Frequency too low." or
    "Frequency too high." outside, ERROR "No events recorded." with none. The node clock is sim time in a
    replay, so a replay at any speed is measured against bag time; while that clock stands (before the first
    /clock, after the bag) no rate can be measured and nothing can be late: OK, and the message says so.
    Time stamps (TimeStampStatus): the delay of header.stamp behind the node clock, since the last publish;
    ERROR "Timestamps too far in future seen." / "... past seen." outside `stamp_bounds_s` (the node's own
    acceptance bounds), WARN "No data since last update." when none came while the clock ran.

    Args:
        name: The status name, '<node>: <topic> topic status'.
        rate_hz: Expected rate, Hz.
        stamp_bounds_s: (earliest, latest) acceptable delay of a stamp behind the node clock, s.
        tolerance: Fraction of the rate either side that is still OK (diagnostic_updater's default 0.1).
        window: Publishes the rate is measured over (diagnostic_updater's default 5).

    """

    def __init__(self, name: str, rate_hz: float, stamp_bounds_s: tuple[float, float], tolerance: float = 0.1,
                 window: int = 5) -> None:
        self.name, self.rate_hz, self.stamp_bounds_s, self.tolerance = name, rate_hz, stamp_bounds_s, tolerance
        self.count = 0
        self._history: deque[tuple[float, int]] = deque(maxlen=window)  # (node clock s, count) per publish
        self._delays_s: list[float] = []
        self.level = DiagnosticStatus.OK
        self.message = 'No events recorded.'
        self.values: dict[str, str] = {}

    def arrived(self, clock_s: float, stamp_s: float | None) -> None:
        """Count one message; clock_s: the node clock at arrival (0: not running), stamp_s: its header stamp."""
        self.count += 1
        if clock_s > 0 and stamp_s is not None and stamp_s > 0:
            self._delays_s.append(clock_s - stamp_s)

    def update(self, clock_s: float) -> None:
        """Take one window step at the node clock's clock_s (0: not running); set level, message and values."""
        if self._history and clock_s < self._history[-1][0]:
            self._history.clear()  # the clock went back (a new replay): an old window means nothing
        oldest_s, oldest_count = self._history[0] if self._history else (clock_s, self.count)
        duration_s = clock_s - oldest_s
        events = self.count - oldest_count
        if clock_s > 0:
            self._history.append((clock_s, self.count))
        low, high = self.rate_hz * (1 - self.tolerance), self.rate_hz * (1 + self.tolerance)
        found: list[tuple[bytes, str]] = []  # (DiagnosticStatus level, a byte field; message)
        if clock_s <= 0 or duration_s <= 0:
            found.append((DiagnosticStatus.OK, 'Node clock not running: no rate to measure.'))
            freq = None
        else:
            freq = events / duration_s
            if events == 0:
                found.append((DiagnosticStatus.ERROR, 'No events recorded.'))
            elif freq < low:
                found.append((DiagnosticStatus.WARN, 'Frequency too low.'))
            elif freq > high:
                found.append((DiagnosticStatus.WARN, 'Frequency too high.'))
            else:
                found.append((DiagnosticStatus.OK, 'Desired frequency met'))
        earliest, latest = self.stamp_bounds_s
        delays = self._delays_s
        if delays and min(delays) < earliest:
            found.append((DiagnosticStatus.ERROR, 'Timestamps too far in future seen.'))
        if delays and max(delays) > latest:
            found.append((DiagnosticStatus.ERROR, 'Timestamps too far in past seen.'))
        if not delays and freq is not None:
            found.append((DiagnosticStatus.WARN, 'No data since last update.'))
        self.level = max(level for level, _ in found)
        self.message = '; '.join(text for level, text in found if level == self.level)
        self.values = {
            'Events in window': str(events), 'Events since startup': str(self.count),
            'Duration of window (s)': f'{max(duration_s, 0.0):.6f}',
            'Actual frequency (Hz)': f'{freq:.6f}' if freq is not None else 'n/a',
            'Target frequency (Hz)': f'{self.rate_hz:.6f}',
            'Minimum acceptable frequency (Hz)': f'{low:.6f}', 'Maximum acceptable frequency (Hz)': f'{high:.6f}',
            'Earliest timestamp delay:': f'{min(delays):.6f}' if delays else 'n/a',
            'Latest timestamp delay:': f'{max(delays):.6f}' if delays else 'n/a',
            'Earliest acceptable timestamp delay:': f'{earliest:.6f}',
            'Latest acceptable timestamp delay:': f'{latest:.6f}',
        }
        self._delays_s = []


_INFRASTRUCTURE_TOPICS = ('/rosout', '/parameter_events')


class Diagnostics:
    """Counts inputs, rejects, compute time and extra figures, and publishes them on /diagnostics.

    One DiagnosticStatus for the node (named by its fully qualified name), then one per input topic with an
    expected rate (`TopicStatus`). The node's level says what holds now:
    - ERROR while a `fault` is raised, and for `diagnostics_hold_s` after the last callback exception;
    - WARN while a `warn` condition is raised (e.g. a stale PMU), and for `diagnostics_hold_s` after the last
      rejected input;
    - OK otherwise. The hold (10 s by default) keeps a condition that recurs at least that often reading as
      one lasting condition, and lets one that ended read as over. Counters (`rejected.*`, `error.*`) are
      totals since the start and never go down.

    The publish timer runs on the steady clock, so an as-fast-as-possible replay with a racing /clock
    does not multiply the diagnostics traffic.
    """

    def __init__(self, node: Node, period_s: float = 1.0) -> None:
        self._node = node
        self._pub = node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, qos_for(topics.DIAGNOSTICS))
        self.hold_s = float(declare_bounded(
            node, 'diagnostics_hold_s', 10.0, 0.1, 86_400.0,
            'the diagnostics level stays WARN this long after the last rejected input, and ERROR this long after '
            'the last callback exception, then returns to OK if nothing else holds it, s', read_only=True))
        self._arrivals_s: deque[float] = deque(maxlen=4096)
        self.rejects: Counter[str] = Counter()
        self.received = 0
        self.compute_last_s = 0.0
        self.compute_max_s = 0.0
        self.values: dict[str, str] = {}
        self.errors: Counter[str] = Counter()
        self.faults: dict[str, str] = {}
        self.warnings: dict[str, str] = {}
        self.topics: list[TopicStatus] = []
        self._rejected_at_s: dict[str, float] = {}
        self._failed_at_s: dict[str, float] = {}
        self._last_log_s: dict[str, float] = {}
        self._last_publish_s = 0.0
        self._timer = node.create_timer(period_s, self._tick, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _clock_s(self) -> float:
        return self._node.get_clock().now().nanoseconds * 1e-9

    def subscribe(self, msg_type: type, topic: str, callback: Callable[[object], None],
                  rate_hz: float | None = None, stamp_bounds_s: tuple[float, float] = (-1.0, 5.0),
                  event_callbacks: object | None = None) -> object:
        """Subscribe (in the node's namespace) with the topic's documented QoS; count, guard, count losses.

        The losses are `lost.<topic>` in /diagnostics, present (0) from the start. With `rate_hz`, the topic
        also gets its own status (`TopicStatus`): expected rate, Hz, and acceptable stamp delays, s.
        `event_callbacks` (rclpy SubscriptionEventCallbacks) are passed on, e.g. for liveliness changes.
        """
        counter = LossCounter()
        key = f'lost.{topic}'
        self.values[key] = '0'
        guarded = self.guard(callback)
        status = None
        if rate_hz is not None:
            name = self._node.resolve_topic_name(topics.relative(topic))
            status = TopicStatus(f'{self._node.get_fully_qualified_name()}: {name} topic status', rate_hz,
                                 stamp_bounds_s)
            self.topics.append(status)

        def take(msg: object, info: dict) -> None:
            if counter.seen(info.get('publication_sequence_number')):
                self.values[key] = str(counter.lost)
            self.arrived()
            if status is not None:
                stamp = getattr(getattr(msg, 'header', None), 'stamp', None)
                status.arrived(self._clock_s(), stamp.sec + stamp.nanosec * 1e-9 if stamp is not None else None)
            guarded(msg)

        return self._node.create_subscription(msg_type, topics.relative(topic), take, qos_for(topic),
                                              event_callbacks=event_callbacks)

    def arrived(self) -> None:
        """Count one input message."""
        self.received += 1
        self._arrivals_s.append(time.monotonic())

    def reject(self, reason: str, detail: str) -> None:
        """Log a dropped input, count it under its reason, and publish the counts at once.

        Args:
            reason: Short stable key, e.g. 'nan_value'; the diagnostics key is 'rejected.<reason>'.
            detail: What exactly was wrong, for the log.

        """
        self.rejects[reason] += 1
        now = time.monotonic()
        self._rejected_at_s[reason] = now
        # At 60 frames/s one broken PMU would flood the log and the topic: at most one line per reason per
        # second (the count says how many), and at most ten early diagnostics per second.
        if now - self._last_log_s.get(reason, -1e9) >= 1.0:
            self._last_log_s[reason] = now
            self._node.get_logger().warning(f'dropped input ({reason}, {self.rejects[reason]} so far): {detail}')
        if now - self._last_publish_s >= 0.1:
            self.publish()

    def guard(self, callback: Callable[..., object]) -> Callable[..., object]:
        """Wrap a callback so that an unexpected exception is logged with its traceback and counted, never fatal.

        The count is `error.<callback name>` in /diagnostics, and the level is ERROR for `diagnostics_hold_s`
        after each: an exception escaping a callback is a bug or an input no validator foresaw, and the node
        must go on.
        """
        key = getattr(callback, '__name__', 'callback')

        @functools.wraps(callback)
        def guarded(*args: object, **kwargs: object) -> object:
            try:
                return callback(*args, **kwargs)
            except Exception:  # noqa: BLE001  the whole point: nothing from one input may end the process
                self.errors[key] += 1
                self._failed_at_s[key] = time.monotonic()
                self._node.get_logger().error(f'{key} failed ({self.errors[key]} so far):\n{traceback.format_exc()}')
                self.publish()
                return None

        return guarded

    def fault(self, key: str, detail: str | None) -> None:
        """Raise (detail given) or clear (None) a lasting condition that keeps the level at ERROR."""
        self._condition(self.faults, key, detail, self._node.get_logger().error)

    def warn(self, key: str, detail: str | None) -> None:
        """Raise (detail given) or clear (None) a lasting condition that keeps the level at least at WARN."""
        self._condition(self.warnings, key, detail, self._node.get_logger().warning)

    def _condition(self, held: dict[str, str], key: str, detail: str | None, log: Callable[[str], object]) -> None:
        if detail is None:
            if held.pop(key, None) is not None:
                self._node.get_logger().info(f'{key}: over')
                self.publish()
        elif held.get(key) != detail:
            held[key] = detail
            log(f'{key}: {detail}')
            self.publish()

    def computed(self, seconds: float) -> None:
        """Record one compute time in s."""
        self.compute_last_s = seconds
        self.compute_max_s = max(self.compute_max_s, seconds)

    def input_rate_hz(self) -> float:
        """Return the input rate over the last 2 s of wall time, Hz."""
        now = time.monotonic()
        return sum(1 for t in self._arrivals_s if now - t <= 2.0) / 2.0

    def _tick(self) -> None:
        clock_s = self._clock_s()
        for status in self.topics:
            status.update(clock_s)
        self.publish()

    def level(self) -> tuple[bytes, str]:
        """Return the node's level now and its message."""
        now = time.monotonic()
        failed = sorted(k for k, t in self._failed_at_s.items() if now - t < self.hold_s)
        rejected = sorted(k for k, t in self._rejected_at_s.items() if now - t < self.hold_s)
        errors = [f'{k}: {v}' for k, v in sorted(self.faults.items())]
        if failed:
            errors.append(f'callback errors in the last {self.hold_s:g} s: {", ".join(failed)}')
        warnings = [f'{k}: {v}' for k, v in sorted(self.warnings.items())]
        if rejected:
            warnings.append(f'inputs rejected in the last {self.hold_s:g} s: {", ".join(rejected)}')
        if errors:
            return DiagnosticStatus.ERROR, '; '.join(errors + warnings)
        if warnings:
            return DiagnosticStatus.WARN, '; '.join(warnings)
        return DiagnosticStatus.OK, 'ok'

    def publish(self) -> None:
        """Publish the node's DiagnosticStatus and its topics' ones."""
        self._last_publish_s = time.monotonic()
        level, message = self.level()
        pairs = {
            'input_rate_hz': f'{self.input_rate_hz():.1f}',
            'received': str(self.received),
            'rejected': str(sum(self.rejects.values())),
            'compute_time_last_ms': f'{self.compute_last_s * 1e3:.3f}',
            'compute_time_max_ms': f'{self.compute_max_s * 1e3:.3f}',
        }
        pairs.update({f'rejected.{k}': str(v) for k, v in sorted(self.rejects.items())})
        pairs.update({f'error.{k}': str(v) for k, v in sorted(self.errors.items())})
        pairs.update({f'fault.{k}': v for k, v in sorted(self.faults.items())})
        pairs.update({f'warn.{k}': v for k, v in sorted(self.warnings.items())})
        pairs.update(self.values)
        # How many readers each writer has matched: another process can tell from it that this node's output
        # reaches its readers (the graph it sees only says that both ends exist).
        pairs.update({f'matched.{p.topic_name}': str(p.get_subscription_count()) for p in self._node.publishers
                      if p is not self._pub and p.topic_name not in _INFRASTRUCTURE_TOPICS})
        statuses = [DiagnosticStatus(
            level=level, name=self._node.get_fully_qualified_name(), hardware_id='controlled_islanding',
            message=message, values=[KeyValue(key=k, value=v) for k, v in pairs.items()])]
        statuses += [DiagnosticStatus(level=t.level, name=t.name, hardware_id='controlled_islanding', message=t.message,
                                      values=[KeyValue(key=k, value=v) for k, v in t.values.items()])
                     for t in self.topics]
        array = DiagnosticArray(status=statuses)
        array.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(array)


class ClockGate:
    """Judges every stamped input against the node clock (timebounds.StampGate) for one node.

    An input is used at once, held until the node clock reaches it, or refused and counted as `future_stamp`.
    Held inputs are judged again, in arrival order, before every new input (so nothing overtakes a held value)
    and on a steady timer that runs only while something is held.

    Args:
        node: The node; its clock is the reference.
        diag: Its diagnostics: refusals, and `held_for_clock` / `dropped_before_clock`.
        future_tolerance_s: How far a stamp may lead the clock and be used at once, s.
        max_held: How many inputs may wait; the oldest is dropped beyond.
        use: Called with each input that may be used.
        period_s: Wall time between looks at held inputs, s.

    """

    def __init__(self, node: Node, diag: Diagnostics, future_tolerance_s: float, max_held: int,
                 use: Callable[[object], None], period_s: float = 0.05) -> None:
        self._node, self._diag, self._use = node, diag, use
        self.gate: StampGate = StampGate(future_tolerance_s, max_held)
        self._timer = node.create_timer(period_s, diag.guard(self.release),
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._timer.cancel()

    def _now_s(self) -> float:
        return self._node.get_clock().now().nanoseconds * 1e-9

    def _refuse(self, exc: StampError) -> None:
        self._diag.reject(exc.reason, str(exc))

    def admit(self, what: str, stamp_s: float, item: object) -> None:
        """Use an input now, hold it until the clock reaches it, or refuse it as future-stamped."""
        self.release()
        try:
            usable = self.gate.offer(what, stamp_s, self._now_s(), item)
        except StampError as exc:
            self._refuse(exc)
            return
        if usable:
            self._use(item)
            return
        self._timer.reset()
        self._diag.values['held_for_clock'] = str(self.gate.held)
        self._diag.values['dropped_before_clock'] = str(self.gate.dropped_while_held)

    def release(self) -> None:
        """Use, in arrival order, every held input the clock has reached."""
        if not self.gate.held:
            self._timer.cancel()
            return
        self.gate.release(self._now_s(), self._use, self._refuse)
        self._diag.values['held_for_clock'] = str(self.gate.held)
        if not self.gate.held:
            self._timer.cancel()


def writers_matched(values: dict[str, str], count_subscribers: Callable[[str], int]) -> bool:
    """Whether a node's /diagnostics values say each of its writers matches every reader seen on its topic.

    That both ends of a topic exist in another process's view does not mean that the writer has matched the
    reader: under load two nodes found each other seconds later, and pmu_ingestion's volatile rotor angles sent
    meanwhile never reached coherency. A node that has not reported its writers yet is not wired.

    Args:
        values: The node's latest /diagnostics key-value pairs.
        count_subscribers: Topic name -> readers on it, as the caller's node sees the graph.

    """
    found = [(k[len('matched.'):], int(v)) for k, v in values.items() if k.startswith('matched.')]
    return bool(found) and all(n >= count_subscribers(t) for t, n in found)


def declare_bounded(node: Node, name: str, default: float | int, low: float | int, high: float | int,
                    description: str, read_only: bool = False) -> float | int:
    """Declare a parameter with its range and meaning (read-only: never changed at run time); return its value.

    Raises:
        NodeSetupError: The configured value is outside [low, high].

    """
    if isinstance(default, int):
        bound = {'integer_range': [IntegerRange(from_value=int(low), to_value=int(high), step=1)]}
    else:
        bound = {'floating_point_range': [FloatingPointRange(from_value=float(low), to_value=float(high))]}
    try:
        node.declare_parameter(name, default,
                               ParameterDescriptor(description=description, read_only=read_only, **bound))
    except InvalidParameterValueException as exc:
        raise NodeSetupError(f'parameter {name}: {exc}; it must be in [{low}, {high}]') from exc
    return node.get_parameter(name).value


def declare_limits(node: Node) -> Limits:
    """Declare the snapshot size caps as parameters; return them as Limits."""
    default = Limits()
    return Limits(**{
        field: int(declare_bounded(node, field, getattr(default, field), 1, 10 * getattr(default, field),
                                   f'largest number of {field[4:]} accepted in one network snapshot; a '
                                   'larger one is refused (too_large) before any per-element work'))
        for field in ('max_buses', 'max_branches', 'max_generators', 'max_loads')})


def settle_heap() -> None:
    """Move everything alive now out of the garbage collector's view.

    The libraries a node imports (scipy, scikit-learn, pypower) leave hundreds of thousands of objects; a
    full collection that walks them all stalls the node for tens of ms, in the middle of a request.
    """
    gc.collect()
    gc.freeze()


_DDS_MEMORY_XML = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_reader profile_name="controlled_islanding_reader" is_default_profile="true">
    <historyMemoryPolicy>DYNAMIC</historyMemoryPolicy>
  </data_reader>
  <data_writer profile_name="controlled_islanding_writer" is_default_profile="true">
    <historyMemoryPolicy>DYNAMIC</historyMemoryPolicy>
    <times>
      <heartbeatPeriod><sec>0</sec><nanosec>100000000</nanosec></heartbeatPeriod>
    </times>
  </data_writer>
</profiles>
"""


def _dds_memory_profile() -> str | None:
    """Point Fast DDS at a profile with the DYNAMIC history memory policy; return the file to delete.

    rmw_fastrtps forces PREALLOCATED_WITH_REALLOC unless RMW_FASTRTPS_USE_QOS_FROM_XML is set, and takes the
    XML defaults only for what the ROS QoS does not set (history, depth, reliability and durability still
    come from TOPIC_QOS). A user who configured Fast DDS through either variable keeps their own setup.
    The file is private to this process and deleted once the node exists (Fast DDS reads it when the first
    participant is created).
    """
    if 'RMW_FASTRTPS_USE_QOS_FROM_XML' in os.environ or 'FASTRTPS_DEFAULT_PROFILES_FILE' in os.environ:
        return None
    fd, path = tempfile.mkstemp(prefix='controlled_islanding_fastdds_', suffix='.xml')
    with os.fdopen(fd, 'w') as handle:
        handle.write(_DDS_MEMORY_XML)
    os.environ['RMW_FASTRTPS_USE_QOS_FROM_XML'] = '1'
    os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = path
    return path


def spin_node(factory: Callable[[], Node], args: list[str] | None = None,
              run: Callable[[Node, SingleThreadedExecutor], None] | None = None) -> int:
    """Init rclpy, build the node, spin it single-threaded until Ctrl-C or shutdown, then clean up.

    Args:
        factory: Builds the node; called after rclpy.init.
        args: Command line arguments (for --ros-args).
        run: What to do with the node and its executor instead of spinning forever (a node with an end,
            like the bag player).

    Returns:
        Process exit status: 0 after a clean stop, 1 when the node failed to start.

    """
    profile = _dds_memory_profile()
    rclpy.init(args=args)
    node = None
    status = 0
    try:
        node = factory()
        if profile is not None:
            os.unlink(profile)
            profile = None
        settle_heap()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        if run is None:
            executor.spin()
        else:
            run(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # Seen once in ~300 graph runs: a message take in flight when SIGINT shut the context down failed in
        # rclpy's C layer ("Unable to convert call argument") after the node's work was done. Only then is it
        # quiet; on a live context it is a real failure.
        if rclpy.ok():
            raise
    except (NodeSetupError, ParameterException) as exc:
        print(f'error: {type(exc).__name__}: {exc}' if isinstance(exc, ParameterException) else f'error: {exc}',
              flush=True)
        status = 1
    finally:
        if profile is not None:
            os.unlink(profile)
        if node is not None:
            close = getattr(node, 'close', None)
            if close is not None:
                close()
            node.destroy_node()
        rclpy.try_shutdown()
    return status
