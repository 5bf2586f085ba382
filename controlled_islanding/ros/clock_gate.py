"""Every stamped input judged against the node clock before it is used (wire.timebounds.StampGate, per node).

With a SimClockWatch (partitioning, breaker_command), the node clock itself is bounded first: while it is
inconsistent, every input is held as before the clock started, so a forged /clock makes no stamp look due.
"""

from __future__ import annotations

from collections.abc import Callable

from controlled_islanding_msgs.msg import NetworkSnapshot
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.sim_clock import SimClockWatch
from controlled_islanding.wire.messages import element_count
from controlled_islanding.wire.timebounds import SNAPSHOT, StampError, StampGate


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
        clock: The node's sim clock bound (SimClockWatch), if it keeps one.

    """

    def __init__(self, node: Node, diag: Diagnostics, future_tolerance_s: float, max_held: int,
                 use: Callable[[object], None], period_s: float = 0.05, clock: SimClockWatch | None = None) -> None:
        self._node, self._diag, self._use = node, diag, use
        self._clock = clock
        self.gate: StampGate = StampGate(future_tolerance_s, max_held)
        self._timer = node.create_timer(period_s, diag.guard(self.release),
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._timer.cancel()

    def _now_s(self) -> float:
        if self._clock is not None and self._clock.inconsistency() is not None:
            return 0.0  # held as before the clock started
        return self._node.get_clock().now().nanoseconds * 1e-9

    def _refuse(self, exc: StampError) -> None:
        self._diag.reject(exc.reason, str(exc))

    def admit(self, what: str, stamp_s: float, item: object, msg: object = None) -> None:
        """Use an input now, hold it until the clock reaches it, or refuse it as future-stamped.

        `msg`, the message the input came from, sizes it for the hold (wire.messages.element_count); a network
        snapshot is known by its type.
        """
        self.release()
        kind = SNAPSHOT if isinstance(msg, NetworkSnapshot) else ''
        try:
            usable = self.gate.offer(what, stamp_s, self._now_s(), item, element_count(msg), kind)
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
