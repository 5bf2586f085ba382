"""Bad-input accounting and /diagnostics, in diagnostic_updater's conventions: what every node counts, and how."""

from __future__ import annotations

import functools
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.params import declare_bounded
from controlled_islanding.wire import topics


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
# breaker_command's count of decisions handled, published at once after each (Diagnostics.subscribe handled_key).
DECISIONS_HANDLED = 'decisions_handled'


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
        self.counts: Counter[str] = Counter()  # the node's own counters, published beside the values
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
                  event_callbacks: object | None = None, handled_key: str | None = None,
                  with_info: bool = False) -> object:
        """Subscribe (in the node's namespace) with the topic's documented QoS; count, guard, count losses.

        The losses are `lost.<topic>` in /diagnostics, present (0) from the start. With `rate_hz`, the topic
        also gets its own status (`TopicStatus`): expected rate, Hz, and acceptable stamp delays, s.
        `event_callbacks` (rclpy SubscriptionEventCallbacks) are passed on, e.g. for liveliness changes.
        With `handled_key`, the number of messages the callback has finished with is that counter, and the
        diagnostics go out at once after each: another process can then tell exactly when a message was
        handled (a replay's player holds its clock until breaker_command has handled a decision). With
        `with_info`, the callback gets the message info too (rclpy's dict: `source_timestamp`, ns, ...).
        """
        counter = LossCounter()
        key = f'lost.{topic}'
        self.counts[key] = 0
        if handled_key is not None:
            self.counts[handled_key] = 0
        guarded = self.guard(callback)
        status = None
        if rate_hz is not None:
            name = self._node.resolve_topic_name(topics.relative(topic))
            status = TopicStatus(f'{self._node.get_fully_qualified_name()}: {name} topic status', rate_hz,
                                 stamp_bounds_s)
            self.topics.append(status)

        def take(msg: object, info: dict) -> None:
            if counter.seen(info.get('publication_sequence_number')):
                self.counts[key] = counter.lost
            self.arrived()
            if status is not None:
                stamp = getattr(getattr(msg, 'header', None), 'stamp', None)
                status.arrived(self._clock_s(), stamp.sec + stamp.nanosec * 1e-9 if stamp is not None else None)
            if with_info:
                guarded(msg, info)
            else:
                guarded(msg)
            if handled_key is not None:
                self.counts[handled_key] += 1
                self.publish()

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
        if self._condition(self.faults, key, detail):
            self._node.get_logger().error(f'{key}: {detail}')
            self.publish()

    def warn(self, key: str, detail: str | None) -> None:
        """Raise (detail given) or clear (None) a lasting condition that keeps the level at least at WARN."""
        # Logged here, not in _condition: rclpy raises when one call site logs at two severities (a breaker
        # node with a fault raised lost its control_centre_silent warning to that).
        if self._condition(self.warnings, key, detail):
            self._node.get_logger().warning(f'{key}: {detail}')
            self.publish()

    def _condition(self, held: dict[str, str], key: str, detail: str | None) -> bool:
        """Update a condition; return True when it is raised anew or its detail changed (the caller logs it)."""
        if detail is None:
            if held.pop(key, None) is not None:
                self._node.get_logger().info(f'{key}: over')
                self.publish()
            return False
        if held.get(key) == detail:
            return False
        held[key] = detail
        return True

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
        array = DiagnosticArray(status=self.statuses())
        array.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(array)

    def statuses(self) -> list[DiagnosticStatus]:
        """Return the node's DiagnosticStatus and its topics' ones, as publish() sends them now."""
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
        pairs.update({k: str(v) for k, v in self.counts.items()})
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
        return statuses


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
