"""coherency: group generators by DTW over a sliding window of rotor angles, periodically and on every request.

Samples are kept ordered by time tag (late ones are inserted, not appended), so the window is the last
`window_s` of time tags, whatever order frames arrived in. Periodic recomputation runs on the wall (steady)
clock every `period_s` when new samples came in: its cost stays bounded in an as-fast-as-possible replay, and
the groups stay warm for the next request. On a request stamped T the node waits (at most `request_wait_s`
wall) for a sample at T or later, then groups the window ending at T and publishes at once; the groups are
latched (transient local) for late joiners.
"""

from __future__ import annotations

import bisect
import sys
import time

import numpy as np
from controlled_islanding_msgs.msg import CoherentGroups, IslandingRequest, RotorAngles
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from controlled_islanding import topics
from controlled_islanding.core.coherency import DTWCoherency
from controlled_islanding.messages import split_stamp, stamp_s
from controlled_islanding.node_common import Diagnostics, NodeSetupError, qos_for, spin_node


class CoherencyNode(Node):
    """Sliding-window DTW coherency."""

    def __init__(self) -> None:
        super().__init__('coherency')
        self.declare_parameter('window_s', 3.0)
        self.declare_parameter('period_s', 0.5)
        self.declare_parameter('min_samples', 30)
        self.declare_parameter('request_wait_s', 0.5)
        self.declare_parameter('sample_tolerance_s', 0.02)
        self.declare_parameter('max_groups', 4)
        self.declare_parameter('max_sample_age_s', 10.0)
        self.declare_parameter('dtw_band_samples', 30)
        self.window_s = float(self.get_parameter('window_s').value)
        self.min_samples = int(self.get_parameter('min_samples').value)
        self.request_wait_s = float(self.get_parameter('request_wait_s').value)
        self.tolerance_s = float(self.get_parameter('sample_tolerance_s').value)
        self.max_groups = int(self.get_parameter('max_groups').value)
        self.max_sample_age_s = float(self.get_parameter('max_sample_age_s').value)
        band = int(self.get_parameter('dtw_band_samples').value)
        self.band = band if band > 0 else None
        if self.window_s <= 0 or self.min_samples < 2:
            raise NodeSetupError(f'window_s={self.window_s} must be positive and min_samples={self.min_samples} >= 2')
        self.names: tuple[str, ...] | None = None
        self.buses: list[int] = []
        self.t_s: list[float] = []
        self.angles: list[np.ndarray] = []  # NaN where invalid
        self.dirty = False
        self.computed_end_s = -1.0  # newest sample time of the last published groups, s
        self.late_inserts_before_s = -1.0  # newest time tag of a sample inserted behind that, s
        self.pending: list[tuple[IslandingRequest, float]] = []
        self.diag = Diagnostics(self)
        self.pub = self.create_publisher(CoherentGroups, topics.COHERENT_GROUPS, qos_for(topics.COHERENT_GROUPS))
        self.create_subscription(RotorAngles, topics.ROTOR_ANGLES, self.on_angles, qos_for(topics.ROTOR_ANGLES))
        self.create_subscription(IslandingRequest, topics.ISLANDING_REQUEST, self.on_request,
                                 qos_for(topics.ISLANDING_REQUEST))
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(float(self.get_parameter('period_s').value), self.on_period, clock=steady)
        # Polls for the wait deadlines only while a request waits (no 100 Hz wake-ups when idle).
        self.pending_timer = self.create_timer(0.01, self._serve_pending, clock=steady)

    def on_angles(self, msg: RotorAngles) -> None:
        """Insert one sample into the window, after checking it."""
        self.diag.arrived()
        n = len(msg.generator_names)
        lengths = (len(msg.generator_buses), len(msg.angle_rad), len(msg.valid))
        if n == 0:
            self.diag.reject('empty_message', 'rotor angles name no generator')
            return
        if any(x != n for x in lengths):
            self.diag.reject('array_length', f'rotor angles: {n} names but buses/angles/valid have {lengths}')
            return
        names = tuple(msg.generator_names)
        if self.names is not None and names != self.names:
            self.diag.reject('unknown_id', f'rotor angles for generators {names}, expected {self.names}')
            return
        angles = np.asarray(msg.angle_rad, dtype=float)
        valid = np.asarray(msg.valid, dtype=bool)
        if not np.all(np.isfinite(angles[valid])):
            self.diag.reject('nan_value', 'rotor angles marked valid hold NaN or inf')
            return
        t = stamp_s(msg.header.stamp)
        if t <= 0:
            self.diag.reject('missing_stamp', 'rotor angles header.stamp is zero')
            return
        if self.t_s and t < self.t_s[-1] - self.max_sample_age_s:
            self.diag.reject('time_backwards', f'sample at {t:.3f} s is {self.t_s[-1] - t:.3f} s older than '
                                               f'the newest; more than max_sample_age_s={self.max_sample_age_s}')
            return
        i = bisect.bisect_left(self.t_s, t)
        if i < len(self.t_s) and self.t_s[i] == t:
            self.diag.reject('duplicate', f'a sample at {t:.6f} s is already held')
            return
        if self.names is None:
            self.names, self.buses = names, [int(b) for b in msg.generator_buses]
        if t <= self.computed_end_s:
            self.late_inserts_before_s = max(self.late_inserts_before_s, t)
        self.t_s.insert(i, t)
        self.angles.insert(i, np.where(valid, angles, np.nan))
        # Keep twice the window: a request stamped a little in the past still finds its whole window.
        cut = bisect.bisect_left(self.t_s, self.t_s[-1] - 2 * self.window_s)
        if cut:
            del self.t_s[:cut], self.angles[:cut]
        self.dirty = True
        if self.pending:
            self._serve_pending()

    def on_request(self, msg: IslandingRequest) -> None:
        """Queue a request; it is served once data up to its stamp is in (or the wait ends)."""
        t = stamp_s(msg.header.stamp)
        if not msg.request_id or t <= 0:
            self.diag.reject('empty_message', 'islanding request without request_id or stamp')
            return
        self.pending.append((msg, time.monotonic() + self.request_wait_s))
        self.pending_timer.reset()
        self._serve_pending()

    def _serve_pending(self) -> None:
        if not self.pending:
            self.pending_timer.cancel()
            return
        now = time.monotonic()
        for item in list(self.pending):
            request, deadline = item
            t = stamp_s(request.header.stamp)
            if (not self.t_s or self.t_s[-1] < t - self.tolerance_s) and now < deadline:
                continue
            self.pending.remove(item)
            if not self.t_s or self.t_s[0] > t:
                self.diag.reject('no_data', f'request {request.request_id}: no rotor angles before its stamp')
                continue
            if self.computed_end_s >= t - self.tolerance_s and not self._changed_before(t):
                continue  # the latched groups already cover this request: nothing new to compute
            self._compute(t)

    def _changed_before(self, t: float) -> bool:
        return self.late_inserts_before_s >= 0 and self.late_inserts_before_s <= t

    def on_period(self) -> None:
        """Recompute on new data, so the groups are warm when a request comes."""
        if self.dirty and not self.pending:
            self._compute(self.t_s[-1])

    def _compute(self, end_s: float) -> None:
        hi = bisect.bisect_right(self.t_s, end_s)
        lo = bisect.bisect_left(self.t_s, end_s - self.window_s)
        if hi - lo < self.min_samples:
            self.diag.values['skipped_short_window'] = str(int(self.diag.values.get('skipped_short_window', 0)) + 1)
            return
        t0 = time.perf_counter()
        block = np.vstack(self.angles[lo:hi])
        try:
            model = DTWCoherency(max_groups=self.max_groups, window=self.band).fit(list(block.T))
        except Exception as exc:  # the core names what was wrong; the node keeps running
            self.diag.reject('compute_failed', f'coherency over {hi - lo} samples: {exc}')
            return
        assert self.names is not None
        msg = CoherentGroups(generator_names=list(self.names), generator_buses=self.buses,
                             group=[int(g) for g in model.labels_], k=int(model.n_groups_), method='dtw',
                             distance=[float(x) for x in np.asarray(model.distance_matrix_, dtype=float).ravel()],
                             window_s=float(self.t_s[hi - 1] - self.t_s[lo]))
        newest = self.t_s[hi - 1]
        self.computed_end_s, self.late_inserts_before_s = newest, -1.0
        msg.header.stamp.sec, msg.header.stamp.nanosec = split_stamp(newest)
        self.pub.publish(msg)
        self.dirty = self.dirty and hi < len(self.t_s)
        self.diag.computed(time.perf_counter() - t0)
        self.diag.values['k'] = str(msg.k)
        self.diag.values['window_samples'] = str(hi - lo)


def main(args: list[str] | None = None) -> int:
    """Run the coherency node."""
    return spin_node(CoherencyNode, args)


if __name__ == '__main__':
    sys.exit(main())
