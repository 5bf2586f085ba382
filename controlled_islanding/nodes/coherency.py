"""coherency: group generators by DTW over a sliding window of rotor angles, periodically and on every request.

Samples are kept ordered by time tag (late ones are inserted, not appended), so the window is the last
`window_s` of time tags, whatever order frames arrived in. Periodic recomputation runs on the wall (steady)
clock every `period_s` when new samples came in: its cost stays bounded in an as-fast-as-possible replay, and
the groups stay warm for the next request. On a request stamped T the node waits (at most `request_wait_s`
wall) for a sample at T or later, then groups the window ending at T and publishes at once, with the request's
id, so partitioning can tell that answer from a periodic grouping that reaches it later; the groups are latched
(transient local) for late joiners.

The groups are the predicted final grouping (core/final_grouping.py), the one rule the stability monitor shares:
every sample also goes, in time-tag order, to a SwingWatch (the chosen predictor, SIME, on the filter's angles,
speeds and torques and the measured power and voltage /rotor_angles carries); for a window ending at T, the
groups are the predicted ones when a separation was predicted with confidence by T in the present swing (so the
monitor's request and this node's answer agree on k), else the DTW rule's, less the splits the predictor says
come back (a pair drifting apart but slowing down and predicted to return, or already heading back). Without the
grid's nominal frequency or the machines' inertia in the snapshot, or without speeds in the samples, there is no
prediction and the DTW rule's groups stand (`grouping` in /diagnostics says which).

The generators are those of the latched /network/snapshot: a sample naming any other generator is refused
(unknown_id), and a snapshot with a different generator set starts a new window. Stamps are bounded by the
node's own clock (sim time in replay): a sample or request stamped more than `future_tolerance_s` ahead of
it is refused, so it can never become the newest sample that makes every honest one look too old. Until that
clock starts, inputs are held (at most `max_held_samples`) and judged once it runs.
"""

from __future__ import annotations

import bisect
import math
import sys
import time

import numpy as np
from controlled_islanding_msgs.msg import CoherentGroups, IslandingRequest, NetworkSnapshot, RotorAngles
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from controlled_islanding.core.coherency import DTWCoherency, decimation_factor, frame_period_s
from controlled_islanding.core.coherency import warm_up as warm_up_dtw
from controlled_islanding.core.final_grouping import STAMP_ROUNDING_S, SwingWatch, final_groups, warm_up
from controlled_islanding.core.k_rules import DEFAULT_RULE, RULES
from controlled_islanding.core.stability import MachineSet, StabilityError
from controlled_islanding.ros.clock_gate import ClockGate
from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.intake import SnapshotIntake
from controlled_islanding.ros.params import NodeSetupError, declare_bounded
from controlled_islanding.ros.pending import PendingRequests
from controlled_islanding.ros.spin import spin_node
from controlled_islanding.wire import topics
from controlled_islanding.wire.messages import (
    MAX_REQUEST_ID,
    MONITOR_FIELDS,
    element_count,
    sample_columns,
    split_stamp,
    stamp_s,
)
from controlled_islanding.wire.timebounds import MAX_HELD_ELEMENTS, Backlog

# A frame period is the median spacing of the newest samples; C37.118.1's slowest reporting rate is 10 frames/s,
# so no frame period is longer than 0.1 s (a gap in the data is not a period).
_PERIOD_SAMPLES = 9
_MAX_FRAME_WAIT_S = 0.1


class CoherencyNode(Node):
    """Sliding-window DTW coherency."""

    def __init__(self, **node_options) -> None:
        super().__init__('coherency', **node_options)
        self.declare_parameter('window_s', 3.0)
        self.declare_parameter('period_s', 0.5)
        self.declare_parameter('min_samples', 30)
        self.declare_parameter('request_wait_s', 0.5)
        self.declare_parameter('sample_tolerance_s', 0.02)
        self.declare_parameter('max_groups', 8)
        self.declare_parameter('max_sample_age_s', 10.0)
        self.declare_parameter('dtw_band_samples', 30)
        self.declare_parameter('dtw_all_pairs', False)
        self.declare_parameter('dtw_decimate_to_fps', 0.0)
        self.declare_parameter('k_rule', DEFAULT_RULE)
        self.k_rule = str(self.get_parameter('k_rule').value)
        if self.k_rule not in RULES:
            raise NodeSetupError(f'k_rule={self.k_rule!r} is not one of {sorted(RULES)}')
        self.window_s = float(self.get_parameter('window_s').value)
        self.min_samples = int(self.get_parameter('min_samples').value)
        self.request_wait_s = float(self.get_parameter('request_wait_s').value)
        self.tolerance_s = float(self.get_parameter('sample_tolerance_s').value)
        self.max_groups = int(self.get_parameter('max_groups').value)
        self.max_sample_age_s = float(self.get_parameter('max_sample_age_s').value)
        band = int(self.get_parameter('dtw_band_samples').value)
        self.all_pairs = bool(self.get_parameter('dtw_all_pairs').value)
        self.decimate_to_fps = float(self.get_parameter('dtw_decimate_to_fps').value)
        if not (self.decimate_to_fps >= 0 and math.isfinite(self.decimate_to_fps)):
            raise NodeSetupError(f'dtw_decimate_to_fps={self.decimate_to_fps} must be 0 (off) or a rate in frames/s')
        self.band = band if band > 0 else None
        if self.window_s <= 0 or self.min_samples < 2:
            raise NodeSetupError(f'window_s={self.window_s} must be positive and min_samples={self.min_samples} >= 2')
        future_tolerance_s = float(declare_bounded(
            self, 'future_tolerance_s', 1.0, 0.0, 3600.0,
            'how far, s, a rotor-angle sample, request or snapshot stamp may lead this node clock (sim time in '
            'replay); further ahead it is refused (future_stamp)'))
        self.max_held = int(declare_bounded(
            self, 'max_held_samples', 1000, 1, 100_000,
            'samples held while the node clock has not started or no snapshot has come; the oldest is dropped'))
        self.max_window_samples = int(declare_bounded(
            self, 'max_window_samples', 10_000, 2, 1_000_000,
            'samples kept in the window (twice window_s of time tags); beyond it the oldest are dropped'))
        # The predictor's settings: the stability monitor's own (config/stability_monitor.yaml), so both predict alike.
        self.predictor_settings = {
            'noise_tve': float(declare_bounded(self, 'predictor_noise_tve', 0.01, 1e-6, 0.49,
                                               "as stability_monitor's: the PMUs' TVE bound", True)),
            'z_alarm': float(declare_bounded(self, 'predictor_z_alarm', 3.0, 0.1, 100.0,
                                             "as stability_monitor's: the alarm's standard errors", True)),
            'history_s': float(declare_bounded(self, 'predictor_history_s', 2.0, 0.1, 60.0,
                                               "as stability_monitor's: frames the predictor keeps, s", True)),
            'time_to_act_s': float(declare_bounded(self, 'predictor_time_to_act_s', 0.1, 0.0, 10.0,
                                                   "as stability_monitor's: time to act before the slip, s", True)),
            'max_groups': self.max_groups}
        self.watch: SwingWatch | None = None
        if self.max_window_samples < self.min_samples:
            raise NodeSetupError(f'max_window_samples={self.max_window_samples} < min_samples={self.min_samples}: '
                                 'no window could ever be grouped')
        self.early: Backlog[RotorAngles] = Backlog(self.max_held)  # samples that overtook the snapshot
        self.names: tuple[str, ...] | None = None  # the snapshot's generators, in window column order
        self.column: dict[str, int] = {}
        self.buses: list[int] = []
        self.t_s: list[float] = []
        self.angles: list[np.ndarray] = []  # NaN where invalid
        self.suspect: list[dict[int, str]] = []  # per sample: column -> why its PMU data were suspect
        self.dirty = False
        self.computed_end_s = -1.0  # newest sample time of the last published groups, s
        self.late_inserts_before_s = -1.0  # newest time tag of a sample inserted behind that, s
        self.diag = Diagnostics(self)
        self.intake = SnapshotIntake(self, self.diag)
        self.limits = self.intake.limits
        self.inputs = ClockGate(self, self.diag, future_tolerance_s, self.max_held, self._use)
        self.pub = self.create_publisher(CoherentGroups, topics.relative(topics.COHERENT_GROUPS),
                                         qos_for(topics.COHERENT_GROUPS))
        self.diag.subscribe(NetworkSnapshot, topics.NETWORK_SNAPSHOT, self.on_snapshot)
        rate_fps = float(declare_bounded(self, 'rate_fps', 60.0, 0.1, 10_000.0,
                                         'expected rotor-angle samples per second (the PMU rate), for the '
                                         '/rotor_angles frequency status in /diagnostics', read_only=True))
        self.diag.subscribe(RotorAngles, topics.ROTOR_ANGLES, self.on_angles, rate_fps,
                            (-future_tolerance_s, self.max_sample_age_s))
        self.diag.subscribe(IslandingRequest, topics.ISLANDING_REQUEST, self.on_request)
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(float(self.get_parameter('period_s').value), self.diag.guard(self.on_period), clock=steady)
        self.pending = PendingRequests(self, self.diag.guard, self.request_wait_s, self._has_data_for, self._serve)
        self._warm_up_engine()

    def _use(self, item: tuple[str, object]) -> None:
        kind, msg = item
        if kind == 'snapshot':
            self._take_snapshot(msg)
        elif kind == 'angles':
            self._take_angles(msg)
        else:
            self._take_request(msg)

    def on_snapshot(self, msg: NetworkSnapshot) -> None:
        """Take the generator set from a snapshot, once its stamp is within bounds."""
        self.inputs.admit('network snapshot', stamp_s(msg.header.stamp), ('snapshot', msg), msg)

    def _take_snapshot(self, msg: NetworkSnapshot) -> None:
        grid = self.intake.newer(msg)
        if grid is None:
            return
        bus_of = {g.name: g.bus for g in grid.generators}
        if self.names is None or set(self.names) != set(bus_of):
            if self.names is not None:
                # Samples of another generator set cannot share a DTW window with the new one.
                self.get_logger().info(f'generator set changed ({len(self.names)} -> {len(bus_of)}); window reset')
                self.diag.counts['window_resets'] += 1
            self.names = tuple(g.name for g in grid.generators)
            self.column = {n: i for i, n in enumerate(self.names)}
            self.t_s, self.angles, self.suspect, self.dirty = [], [], [], False
            self.computed_end_s, self.late_inserts_before_s = -1.0, -1.0
        self.buses = [bus_of[n] for n in self.names]
        self._start_watch(grid)
        while self.early:
            self._take_angles(self.early.popleft())

    def _start_watch(self, grid) -> None:
        """(Re)start the predictor for a snapshot's machines (kept when they are the same), or say why there is none."""
        try:
            if not np.isfinite(grid.freq_hz):
                raise StabilityError('the snapshot gives no nominal frequency')
            machines = MachineSet.of_grid(grid, grid.freq_hz).reordered(self.names)
        except StabilityError as exc:
            self.watch = None
            self.diag.values['grouping'] = f'DTW rule only: no prediction ({exc})'[:200]
            return
        if self.watch is None or not machines.same_as(self.watch.machines):
            self.watch = SwingWatch(machines, keep_s=2 * self.window_s, **self.predictor_settings)

    def _warm_up_engine(self) -> None:
        """Load the DTW and k-rule engines before spinning (core.coherency.warm_up), not at the first real window.

        numba loads a compiled engine on its first call: about 45 MB and 1-5 s on the shared 2-core machine.
        Paid at start-up (within the supervisor's start-up grace), it is neither the first request's latency, nor
        a callback long enough to look hung, nor a step in the memory of a node that has been running (the fuzz
        soak measured it as growth; docs/nodes.md, "Fuzz soak").
        """
        t0 = time.perf_counter()
        try:
            warm_up_dtw(self.max_groups, self.band, self.k_rule, self.min_samples)
        except Exception as exc:  # noqa: BLE001  a made-up window only loads the engines; its answer is unused
            self.get_logger().info(f'DTW warm-up grouping failed ({exc}); continuing')
        warm_up(self.predictor_settings['z_alarm'])
        self.diag.values['warm_up_ms'] = f'{(time.perf_counter() - t0) * 1e3:.1f}'

    def on_angles(self, msg: RotorAngles) -> None:
        """Check one sample's shape and stamp; use it, hold it, or refuse it."""
        n = len(msg.generator_names)
        lengths = (len(msg.generator_buses), len(msg.angle_rad), len(msg.valid))
        if n == 0:
            self.diag.reject('empty_message', 'rotor angles name no generator')
            return
        if n > self.limits.max_generators:
            self.diag.reject('too_large', f'rotor angles name {n} generators, more than '
                                          f'max_generators={self.limits.max_generators}')
            return
        if any(x != n for x in lengths) or any(len(getattr(msg, f)) not in (0, n)
                                               for f in ('suspect_reason', *MONITOR_FIELDS)):
            self.diag.reject('array_length', f'rotor angles: {n} names but buses/angles/valid have {lengths}')
            return
        t = stamp_s(msg.header.stamp)
        if t <= 0:
            self.diag.reject('missing_stamp', 'rotor angles header.stamp is zero')
            return
        self.inputs.admit('rotor angles', t, ('angles', msg), msg)

    def _take_angles(self, msg: RotorAngles) -> None:
        """Insert one sample, within time bounds, into the window, after checking its generators and values."""
        if self.names is None:
            if self.early.append(msg, element_count(msg)):
                self.diag.reject('no_data', f'more than max_held_samples={self.max_held} rotor-angle samples '
                                            f'(or {MAX_HELD_ELEMENTS} elements) before any network snapshot: '
                                            'generator set unknown')
            return
        names = [str(x) for x in msg.generator_names]
        cols = [self.column.get(x, -1) for x in names]
        if -1 in cols or len(set(cols)) != len(cols) or len(cols) != len(self.names):
            unknown = sorted(set(names) - set(self.column))[:5]
            missing = sorted(set(self.column) - set(names))[:5]
            self.diag.reject('unknown_id', f'rotor angles name generators {names[:5]}...: not those of the network '
                                           f'snapshot (unknown {unknown}, missing {missing}, or named twice)')
            return
        angles = np.asarray(msg.angle_rad, dtype=float)
        valid = np.asarray(msg.valid, dtype=bool)
        if not np.all(np.isfinite(angles[valid])):
            self.diag.reject('nan_value', 'rotor angles marked valid hold NaN or inf')
            return
        row = np.full(len(self.names), np.nan)
        row[cols] = np.where(valid, angles, np.nan)
        self._watch(msg)
        suspect = {cols[j]: str(why) for j, why in enumerate(msg.suspect_reason) if why}
        t = stamp_s(msg.header.stamp)
        if self.t_s and t < self.t_s[-1] - self.max_sample_age_s:
            self.diag.reject('time_backwards', f'sample at {t:.3f} s is {self.t_s[-1] - t:.3f} s older than '
                                               f'the newest; more than max_sample_age_s={self.max_sample_age_s}')
            return
        i = bisect.bisect_left(self.t_s, t)
        if i < len(self.t_s) and self.t_s[i] == t:
            self.diag.reject('duplicate', f'a sample at {t:.6f} s is already held')
            return
        if t <= self.computed_end_s:
            self.late_inserts_before_s = max(self.late_inserts_before_s, t)
        self.t_s.insert(i, t)
        self.angles.insert(i, row)
        self.suspect.insert(i, suspect)
        # Keep twice the window: a request stamped a little in the past still finds its whole window.
        cut = bisect.bisect_left(self.t_s, self.t_s[-1] - 2 * self.window_s)
        cut = max(cut, len(self.t_s) - self.max_window_samples)
        if cut:
            del self.t_s[:cut], self.angles[:cut], self.suspect[:cut]
        self.dirty = True
        if self.pending:
            self.pending.serve()

    def _watch(self, msg: RotorAngles) -> None:
        """Feed a sample to the predictor (SwingWatch skips one older than the newest it took)."""
        if self.watch is None:
            return
        if not len(msg.omega_pu):
            self.diag.values['grouping'] = 'DTW rule only: the rotor angles carry no speeds (no dse estimator)'
            return
        row = sample_columns(msg, self.column)
        if row is not None:
            self.watch.update(stamp_s(msg.header.stamp), row['delta_rad'], row['omega_pu'], row['pe_pu'], row['v_pu'],
                              row['valid'], row['pm_pu'])

    def on_request(self, msg: IslandingRequest) -> None:
        """Check a request's stamp; queue it, hold it, or refuse it."""
        t = stamp_s(msg.header.stamp)
        # An id partitioning refuses would put it on groups partitioning's decoder drops, and those groups would
        # still count as computed here for the next, honest request of that time.
        if not 0 < len(msg.request_id) <= MAX_REQUEST_ID or t <= 0:
            self.diag.reject('empty_message', f'islanding request without request_id (or longer than '
                                              f'{MAX_REQUEST_ID} characters) or stamp')
            return
        self.inputs.admit('islanding request', t, ('request', msg), msg)

    def _take_request(self, msg: IslandingRequest) -> None:
        """Queue a request; it is served once data up to its stamp is in (or the wait ends)."""
        self.pending.add(msg)

    def _has_data_for(self, request: IslandingRequest) -> bool:
        t = stamp_s(request.header.stamp)
        if not (self.t_s and self.t_s[-1] >= t - self.tolerance_s):
            return False
        # The prediction standing at T is known once the watch has taken a frame at or after T: the monitor
        # raises its request at a frame's own time tag, and the frame before (within sample_tolerance_s at 60
        # frames/s) has no alarm yet. A request stamped between frames (the scenario's 1.5667 s at 30 frames/s)
        # has no frame at T, and in lockstep none comes until it is answered: the frame at T, if any, follows
        # its predecessor within a frame period, so the wait for it is one frame period of wall time.
        if self.watch is None or self.watch.frames_ == 0 or self.watch.last_t_s >= t - STAMP_ROUNDING_S:
            return True
        period_s = frame_period_s(self.t_s[-_PERIOD_SAMPLES:])
        return self.pending.waited_s(request) >= min(period_s, _MAX_FRAME_WAIT_S)

    def _serve(self, request: IslandingRequest) -> None:
        t = stamp_s(request.header.stamp)
        if not self.t_s or self.t_s[0] > t:
            self.diag.reject('no_data', f'request {request.request_id}: no rotor angles before its stamp')
            return
        # The latched groups answer only when they end at the request or just after it: groups of the frame
        # before it were computed before that frame's prediction (a monitor's request at 5.617 s was decided on the
        # periodic groups of 5.600 s, made before the alarm, and nothing was split).
        if -STAMP_ROUNDING_S <= self.computed_end_s - t <= self.tolerance_s and not self._changed_before(t):
            return  # the latched groups end at this request: nothing new to compute
        # Groups ending later than the request are no answer to it: partitioning takes only groups whose
        # samples end at the request, so that a grouping stamped ahead of it can never be the one used.
        self._compute(t, request.request_id)

    def _changed_before(self, t: float) -> bool:
        return self.late_inserts_before_s >= 0 and self.late_inserts_before_s <= t

    def on_period(self) -> None:
        """Recompute on new data, so the groups are warm when a request comes."""
        if self.dirty and not self.pending:
            self._compute(self.t_s[-1])

    def _final(self, end_s: float, seen: np.ndarray, rule_labels: np.ndarray) -> list[int]:
        """Return the predicted final grouping of the observed machines `seen` (core/final_grouping.py)."""
        if self.watch is None or self.watch.frames_ == 0:
            return [int(g) for g in rule_labels]
        alarm = self.watch.at(end_s)
        if alarm is not None:
            out = final_groups(alarm, [])[seen]
            order: dict[int, int] = {}
            self.diag.values['grouping'] = f'predicted at {alarm.t_s:.3f} s (k={alarm.k})'
            return [order.setdefault(int(g), len(order)) for g in out]
        full = np.full(len(self.names), -1)
        full[seen] = rule_labels
        returning = self.watch.returning(full)
        labels = final_groups(None, rule_labels, returning)
        merged = int(rule_labels.max()) - int(labels.max())
        self.diag.values['grouping'] = 'DTW rule' + (f', {merged} split(s) predicted to come back' if merged else '')
        return [int(g) for g in labels]

    def _compute(self, end_s: float, request_id: str = '') -> None:
        hi = bisect.bisect_right(self.t_s, end_s)
        lo = bisect.bisect_left(self.t_s, end_s - self.window_s)
        # The DTW rule needs min_samples to see a shape; the predicted groups of an alarm standing at end_s do
        # not (the predictor judged the swing since its switching). A request raised less than min_samples
        # frames after the data began (the PMUs' first 5 s missing, the first frame at the fault: the monitor's
        # request at 5.38 s found no groups and the grid was lost) is answered with them: a machine is then
        # observed if every sample of the short window has its angle.
        short = hi - lo < self.min_samples
        if short and (hi - lo < 1 or self.watch is None or not self.watch.frames_ or self.watch.at(end_s) is None):
            self.diag.counts['skipped_short_window'] += 1
            return
        t0 = time.perf_counter()
        block = np.vstack(self.angles[lo:hi])
        assert self.names is not None
        # A generator whose PMU gave fewer than min_samples usable angles in the window is unobserved: it joins
        # no group and constrains no island, rather than being grouped on a handful of points.
        # A generator whose PMU data were suspect anywhere in the window is excluded: its other samples there may
        # carry the same attack, not yet flagged.
        suspect: dict[int, str] = {}
        for marks in self.suspect[lo:hi]:
            suspect.update(marks)
        seen = np.flatnonzero(np.isfinite(block).sum(axis=0) >= min(self.min_samples, hi - lo))
        seen = np.array([j for j in seen if j not in suspect], dtype=int)
        observed = set(seen.tolist())
        unobserved = [name for j, name in enumerate(self.names) if j not in observed]
        if len(seen) == 0:
            self.diag.reject('no_data', f'no generator has {self.min_samples} usable samples in the window')
            return
        decimate = decimation_factor(self.t_s[lo:hi], self.decimate_to_fps)
        try:
            if len(seen) == 1:
                labels, k, distance = [0], 1, [0.0]
            elif short:
                labels = self._final(end_s, seen, np.zeros(len(seen), dtype=int))  # the alarm's groups
                k, distance = max(labels) + 1, []
            else:
                model = DTWCoherency(max_groups=self.max_groups, window=self.band, k_rule=self.k_rule,
                                     decimate=decimate, all_pairs=self.all_pairs).fit(list(block[:, seen].T))
                labels = self._final(end_s, seen, model.labels_)
                k = max(labels) + 1
                matrix = np.asarray(model.distance_matrix_, dtype=float)
                # The message's distance is all pairs or none: the pairs the rule did not need were not computed.
                distance = [float(x) for x in matrix.ravel()] if not np.isnan(matrix).any() else []
        except Exception as exc:  # the core names what was wrong; the node keeps running
            self.diag.reject('compute_failed', f'coherency over {hi - lo} samples: {exc}')
            return
        msg = CoherentGroups(generator_names=[self.names[j] for j in seen],
                             generator_buses=[self.buses[j] for j in seen], group=labels, k=k, method='dtw',
                             distance=distance, window_s=float(self.t_s[hi - 1] - self.t_s[lo]),
                             unobserved_generator_names=unobserved, request_id=request_id,
                             suspect_generator_names=[self.names[j] for j in sorted(suspect)],
                             suspect_reasons=[suspect[j] for j in sorted(suspect)])
        newest = self.t_s[hi - 1]
        self.computed_end_s, self.late_inserts_before_s = newest, -1.0
        msg.header.stamp.sec, msg.header.stamp.nanosec = split_stamp(newest)
        self.pub.publish(msg)
        self.dirty = self.dirty and hi < len(self.t_s)
        self.diag.computed(time.perf_counter() - t0)
        self.diag.values['k'] = str(msg.k)
        self.diag.values['window_samples'] = str(hi - lo)
        self.diag.values['dtw_decimate'] = str(decimate)
        self.diag.values['unobserved_generators'] = ','.join(unobserved)[:200]


def main(args: list[str] | None = None) -> int:
    """Run the coherency node."""
    return spin_node(CoherencyNode, args)


if __name__ == '__main__':
    sys.exit(main())
