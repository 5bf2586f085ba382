"""A node's sim clock bounded against the wall clock (wire.timebounds.SimClockGuard), under use_sim_time only.

Every change of the node clock (every /clock value rclpy's time source applies, through a jump callback) is
one reading, on the steady clock, and so is every look the node takes before trusting its clock. On the wall
clock (use_sim_time false, a deployment) the parameters are declared but nothing is judged.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

from rclpy.clock import JumpThreshold
from rclpy.duration import Duration
from rclpy.node import Node

from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.params import declare_bounded
from controlled_islanding.wire.timebounds import ClockJump, SimClockGuard

_REPORT_PERIOD_S = 1.0


class SimClockWatch:
    """Judges every reading of a node's sim clock; `inconsistency()` says why it cannot be trusted now.

    Each jump is counted as `rejected.clock_jump`; `fault.clock_inconsistent` (ERROR) names it until the clock is
    consistent again. `on_jump` (the breaker's audit) gets a jump and the number so far: the first one back and
    the first ahead, then at most one of each a second, since a forger can publish /clock at any rate.

    Args:
        node: The node; its clock is judged.
        diag: Its diagnostics.
        on_jump: Called with a jump and the number of jumps so far.

    """

    def __init__(self, node: Node, diag: Diagnostics,
                 on_jump: Callable[[ClockJump, int], None] | None = None) -> None:
        self._node, self._diag, self._on_jump = node, diag, on_jump
        self._reported_wall_s: dict[str, float] = {}  # jump kind -> last reported, wall s
        guard = SimClockGuard(
            max_rate=float(declare_bounded(
                node, 'sim_clock_max_rate', 1000.0, 1.0, 1e6,
                'under use_sim_time: sim time may advance at most this many seconds per second of wall time '
                '(besides sim_clock_max_jump_s at once); a faster /clock is a jump', True)),
            max_jump_s=float(declare_bounded(
                node, 'sim_clock_max_jump_s', 10.0, 0.1, 3600.0,
                'under use_sim_time: sim time may advance at most this far at once, s', True)),
            recovery_s=float(declare_bounded(
                node, 'sim_clock_recovery_s', 5.0, 0.0, 3600.0,
                'under use_sim_time: after a clock jump, the clock is trusted again once it followed the trusted '
                'time for this long (wall), s', True)))
        self.guard: SimClockGuard | None = None
        if not node.get_parameter('use_sim_time').value:
            return
        self.guard = guard
        diag.values['sim_clock_jumps'] = '0'
        # Every change of at least 1 ns either way: each /clock value the time source applies is a reading.
        threshold = JumpThreshold(min_forward=Duration(nanoseconds=1), min_backward=Duration(nanoseconds=-1),
                                  on_clock_change=True)
        self._handle = node.get_clock().create_jump_callback(threshold, post_callback=diag.guard(self._changed))

    def _read(self) -> tuple[float, float]:
        return time.monotonic(), self._node.get_clock().now().nanoseconds * 1e-9

    def _changed(self, _jump: object) -> None:
        self._judge(*self._read())

    def _judge(self, wall_s: float, sim_s: float) -> None:
        assert self.guard is not None
        jump = self.guard.observe(wall_s, sim_s)
        if jump is None:
            return
        self._diag.values['sim_clock_jumps'] = str(self.guard.jumps)
        self._diag.reject('clock_jump', jump.describe())
        if wall_s - self._reported_wall_s.get(jump.kind, -math.inf) < _REPORT_PERIOD_S:
            return
        self._reported_wall_s[jump.kind] = wall_s
        self._diag.fault('clock_inconsistent', f'{jump.describe()} ({self.guard.jumps} jumps so far)')
        if self._on_jump is not None:
            self._on_jump(jump, self.guard.jumps)

    def inconsistency(self) -> str | None:
        """Why the clock cannot be trusted now, or None when it can (always on the wall clock).

        Reads the clock first: a forged value the node clock still shows is a jump of its own.
        """
        if self.guard is None:
            return None
        wall_s, sim_s = self._read()
        self._judge(wall_s, sim_s)
        why = self.guard.inconsistency(wall_s)
        if why is None:
            self._diag.fault('clock_inconsistent', None)
        return why
