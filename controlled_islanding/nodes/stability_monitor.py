"""stability_monitor: will this swing separate the grid, into which groups, and when? If so, ask for islanding.

It reads the network snapshot (each machine's inertia, damping and dispatch, and the grid's nominal frequency)
and /rotor_angles: pmu_ingestion's filter state per machine (angle, speed, mechanical torque) with the measured
Re(V I*) and terminal |V| of the machine's own PMU channel. It never reads /pmu/frames: what it reads has passed
the PMU defence, a suspect station's machine coming with `valid` false and its power unknown.

Every sample, in time-tag order, goes to core/final_grouping.py's SwingWatch, the chosen predictor (SIME,
docs/prediction.md) that the coherency node runs too. When the watch raises a swing's alarm, the node publishes
one IslandingRequest stamped at the time tag of the frame that raised it, with the predicted final groups and the
predicted first pole slip, signed with the 'monitor' key (safety/signing.py), so partitioning can tell it from a
forged one. Once per swing; nothing while the swing returns. A late sample (older than one already taken) still
counts as received, but the predictor needs time-tag order and skips it.

A machine's angle is taken where the sample is valid, or where the filter still has a speed for it (its
prediction, with no data taken); its power and voltage only where the sample is valid. A frame without an angle
and a speed for every machine of the snapshot is not judged (`skipped_frames`): an OMIB that silently left a
machine out could name the wrong groups. Without speeds (pmu_ingestion's steady-state estimator) or without the
grid's nominal frequency or a machine's inertia, nothing is judged and /diagnostics says why (ERROR): the monitor
fails quiet, never with a request it cannot stand behind.

Stamps are bounded by the node clock (sim time in replay, bounded against the wall clock by ros/sim_clock.py):
a sample stamped more than `future_tolerance_s` ahead of it is refused; until the clock starts, inputs are held
(at most `max_held_samples`).
"""

from __future__ import annotations

import bisect
import math
import sys
import time
from pathlib import Path

import numpy as np
from controlled_islanding_msgs.msg import BranchStatus, IslandingRequest, NetworkSnapshot, RotorAngles
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from controlled_islanding.core.final_grouping import Alarm, SwingWatch, warm_up
from controlled_islanding.core.grid import Grid
from controlled_islanding.core.stability import MachineSet, StabilityError
from controlled_islanding.ros.clock_gate import ClockGate
from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.intake import SnapshotIntake
from controlled_islanding.ros.params import NodeSetupError, declare_bounded
from controlled_islanding.ros.sim_clock import SimClockWatch
from controlled_islanding.ros.spin import spin_node
from controlled_islanding.safety import signing
from controlled_islanding.wire import topics
from controlled_islanding.wire.messages import MONITOR_FIELDS, element_count, sample_columns, split_stamp, stamp_s
from controlled_islanding.wire.timebounds import MAX_HELD_ELEMENTS, Backlog

_MAX_BRANCH_CHANGES = 10_000  # branch status stamps remembered (for branch_changes_before); oldest forgotten


def request_msg(alarm: Alarm, names: tuple[str, ...], request_id: str, changes_before: int,
                z_alarm: float) -> IslandingRequest:
    """Return the (unsigned) IslandingRequest of an alarm: stamped at its frame, its groups and predicted slip."""
    msg = IslandingRequest(request_id=request_id, branch_changes_before=changes_before,
                           generator_names=list(names), group=[int(g) for g in alarm.groups],
                           reason=f'stability monitor: SIME predicts a separation into {alarm.k} groups, the first '
                                  f'pole slip {alarm.first_slip_s - alarm.t_s:.3f} s after this frame (margin '
                                  f'{alarm.confidence * z_alarm:.1f} standard errors below zero)')
    msg.header.stamp.sec, msg.header.stamp.nanosec = split_stamp(alarm.t_s)
    msg.header.frame_id = 'stability_monitor'
    if math.isfinite(alarm.first_slip_s):
        msg.predicted_first_slip.sec, msg.predicted_first_slip.nanosec = split_stamp(alarm.first_slip_s)
    return msg


class StabilityMonitorNode(Node):
    """Predicts the separation swing by swing; raises one signed IslandingRequest per swing that separates."""

    def __init__(self, **node_options) -> None:
        super().__init__('stability_monitor', **node_options)
        self.settings = {
            'noise_tve': float(declare_bounded(
                self, 'predictor_noise_tve', 0.01, 1e-6, 0.49,
                "the PMUs' total vector error bound (3 sigma; C37.118.1: 0.01): the switching test and the least "
                "error of Pe; must equal coherency's", True)),
            'z_alarm': float(declare_bounded(
                self, 'predictor_z_alarm', 3.0, 0.1, 100.0,
                "standard errors the equal-area margin must be below zero by for an alarm; must equal coherency's",
                True)),
            'history_s': float(declare_bounded(
                self, 'predictor_history_s', 2.0, 0.1, 60.0,
                "frames the predictor keeps, s of time tags (longer than a first swing); must equal coherency's",
                True)),
            'time_to_act_s': float(declare_bounded(
                self, 'predictor_time_to_act_s', 0.1, 0.0, 10.0,
                'how long before the predicted first pole slip islanding must be asked for: the alarm waits for a '
                "group's own split only while the slip is further away, s; must equal coherency's", True)),
            'max_groups': int(declare_bounded(
                self, 'max_groups', 8, 2, 1000, "most groups a request names; must equal coherency's", True)),
        }
        self.future_tolerance_s = float(declare_bounded(
            self, 'future_tolerance_s', 1.0, 0.0, 3600.0,
            'how far, s, a sample or snapshot stamp may lead this node clock (sim time in replay); further ahead it '
            'is refused (future_stamp)', True))
        self.max_held = int(declare_bounded(
            self, 'max_held_samples', 1000, 1, 100_000,
            'samples held while the node clock has not started or no snapshot has come; the oldest is dropped', True))
        self.keep_s = float(declare_bounded(
            self, 'keep_s', 6.0, 0.1, 3600.0, 'how long the predictions after each frame are remembered, s', True))
        rate_fps = float(declare_bounded(self, 'rate_fps', 60.0, 0.1, 10_000.0,
                                         'expected /rotor_angles samples per second (the PMU rate), for its '
                                         'frequency status in /diagnostics', True))
        self.declare_parameter('key_dir', '', ParameterDescriptor(
            description='directory with monitor.key, the request signing key; empty = $CONTROLLED_ISLANDING_KEYS or '
                        '~/.config/controlled_islanding/keys', read_only=True))
        key_dir = self.get_parameter('key_dir').value
        key_path = signing.key_paths(Path(key_dir) if key_dir else signing.default_key_dir(), 'monitor').private
        try:
            self.key = signing.load_private_key(key_path)
        except signing.SigningError as exc:
            raise NodeSetupError(f'{exc} (make keys with: controlled-islanding keys init {key_path.parent})') from exc
        self.diag = Diagnostics(self)
        self.intake = SnapshotIntake(self, self.diag)
        self.limits = self.intake.limits
        self.clock = SimClockWatch(self, self.diag)
        self.inputs = ClockGate(self, self.diag, self.future_tolerance_s, self.max_held, self._use, clock=self.clock)
        self.machines: MachineSet | None = None
        self.names: tuple[str, ...] = ()
        self.column: dict[str, int] = {}
        self.watch: SwingWatch | None = None
        self.early: Backlog[RotorAngles] = Backlog(self.max_held)
        self.changes: list[tuple[float, str]] = []  # (stamp s, branch id) of status changes, sorted
        self.requests = 0
        for key in ('swings_alarmed', 'skipped_frames', 'requests'):
            self.diag.counts[key] = 0
        self.pub = self.create_publisher(IslandingRequest, topics.relative(topics.ISLANDING_REQUEST),
                                         qos_for(topics.ISLANDING_REQUEST))
        self.diag.subscribe(NetworkSnapshot, topics.NETWORK_SNAPSHOT, self.on_snapshot)
        self.diag.subscribe(BranchStatus, topics.BRANCH_STATUS, self.on_branch_status)
        self.diag.subscribe(RotorAngles, topics.ROTOR_ANGLES, self.on_angles, rate_fps,
                            (-self.future_tolerance_s, 10.0))
        t0 = time.perf_counter()
        warm_up(self.settings['z_alarm'])
        self.diag.values['warm_up_ms'] = f'{(time.perf_counter() - t0) * 1e3:.1f}'
        self.get_logger().info(f'signing requests with key {signing.fingerprint(self.key)}')

    def _use(self, item: tuple[str, object]) -> None:
        kind, msg = item
        if kind == 'snapshot':
            self._take_snapshot(msg)
        elif kind == 'status':
            self._take_status(msg)
        else:
            self._take_angles(msg)

    # --- inputs -------------------------------------------------------------------------------------------------
    def on_snapshot(self, msg: NetworkSnapshot) -> None:
        """Take the machines from a snapshot, once its stamp is within bounds."""
        self.inputs.admit('network snapshot', stamp_s(msg.header.stamp), ('snapshot', msg), msg)

    def on_branch_status(self, msg: BranchStatus) -> None:
        """Remember a branch status change's stamp: a request says how many it knows of."""
        self.inputs.admit(f'branch {msg.branch_id[:64]} status', stamp_s(msg.header.stamp), ('status', msg))

    def on_angles(self, msg: RotorAngles) -> None:
        """Check one sample's shape and stamp; use it, hold it, or refuse it."""
        n = len(msg.generator_names)
        if n == 0:
            self.diag.reject('empty_message', 'rotor angles name no generator')
            return
        if n > self.limits.max_generators:
            self.diag.reject('too_large', f'rotor angles name {n} generators, more than '
                                          f'max_generators={self.limits.max_generators}')
            return
        lengths = {f: len(getattr(msg, f)) for f in ('generator_buses', 'angle_rad', 'valid')}
        optional = {f: len(getattr(msg, f)) for f in (*MONITOR_FIELDS, 'suspect_reason')}
        if any(x != n for x in lengths.values()) or any(x not in (0, n) for x in optional.values()):
            self.diag.reject('array_length', f'rotor angles: {n} names but {lengths | optional} values')
            return
        t = stamp_s(msg.header.stamp)
        if t <= 0:
            self.diag.reject('missing_stamp', 'rotor angles header.stamp is zero')
            return
        self.inputs.admit('rotor angles', t, ('angles', msg), msg)

    def _take_snapshot(self, msg: NetworkSnapshot) -> None:
        grid = self.intake.newer(msg)
        if grid is None:
            return
        machines = self._machines(grid)
        if machines is None:
            return
        if self.machines is None or not machines.same_as(self.machines):
            if self.watch is not None:
                self.get_logger().info('machines changed with the snapshot; the predictor starts again')
                self.diag.counts['predictor_resets'] += 1
            self.machines = machines
            self.names = machines.names
            self.column = {name: i for i, name in enumerate(self.names)}
            self.watch = SwingWatch(machines, keep_s=self.keep_s, **self.settings)
        while self.early:
            self._take_angles(self.early.popleft())

    def _machines(self, grid: Grid) -> MachineSet | None:
        """Return the snapshot's machines, or None (fault in /diagnostics) when the predictor cannot judge them."""
        if not math.isfinite(grid.freq_hz):
            why = ('the network snapshot gives no nominal frequency: kinetic energies and speeds in pu cannot be '
                   'read; nothing is judged')
        else:
            try:
                machines = MachineSet.of_grid(grid, grid.freq_hz)
            except StabilityError as exc:
                why = f'the network snapshot lacks machine data the predictor needs: {exc}; nothing is judged'
            else:
                self.diag.fault('cannot_judge', None)
                return machines
        self.machines, self.watch = None, None
        self.diag.fault('cannot_judge', why)
        return None

    def _take_status(self, msg: BranchStatus) -> None:
        item = (stamp_s(msg.header.stamp), str(msg.branch_id))
        i = bisect.bisect_left(self.changes, item)
        if i == len(self.changes) or self.changes[i] != item:
            self.changes.insert(i, item)
            del self.changes[:-_MAX_BRANCH_CHANGES]

    def _take_angles(self, msg: RotorAngles) -> None:
        if self.watch is None:
            self.diag.counts['unjudged_frames'] += 1
            if 'cannot_judge' not in self.diag.faults:
                if self.early.append(msg, element_count(msg)):
                    self.diag.reject('no_data', f'more than max_held_samples={self.max_held} rotor-angle samples '
                                                f'(or {MAX_HELD_ELEMENTS} elements) before any network snapshot: '
                                                'machines unknown')
            return
        t0 = time.perf_counter()
        row = sample_columns(msg, self.column)
        if row is None:
            self.diag.reject('unknown_id', f'rotor angles name generators {list(msg.generator_names)[:5]}...: not '
                                           'those of the network snapshot (unknown, missing or named twice)')
            return
        if not len(msg.omega_pu):
            self.diag.fault('no_speeds', 'rotor angles carry no speeds (pmu_ingestion must run the dse '
                                         'estimator): nothing is judged')
            return
        self.diag.fault('no_speeds', None)
        if not np.all(np.isfinite(row['delta_rad'][row['valid']])):
            self.diag.reject('nan_value', 'rotor angles marked valid hold NaN or inf')
            return
        t = stamp_s(msg.header.stamp)
        before = self.watch.skipped_
        alarm = self.watch.update(t, row['delta_rad'], row['omega_pu'], row['pe_pu'], row['v_pu'], row['valid'],
                                  row['pm_pu'])
        self.diag.counts['skipped_frames'] += self.watch.skipped_ - before
        p = self.watch.predictor
        self.diag.values['confidence'] = f'{p.confidence_:.2f}'
        self.diag.values['swing_start_s'] = f'{p.swing_start_s_:.3f}'
        if alarm is not None:
            self._request(alarm)
        self.diag.computed(time.perf_counter() - t0)

    # --- output -------------------------------------------------------------------------------------------------
    def _request(self, alarm: Alarm) -> None:
        self.requests += 1
        since = bisect.bisect_right(self.changes, (self.intake.stamp_s, '\uffff'))
        upto = bisect.bisect_right(self.changes, (alarm.t_s, '\uffff'))
        msg = request_msg(alarm, self.names, f'{self.get_fully_qualified_name()}/{alarm.t_s:.6f}',
                          max(0, upto - since), self.settings['z_alarm'])
        signing.sign_request(msg, self.key)
        self.pub.publish(msg)
        self.diag.counts['swings_alarmed'] += 1
        self.diag.counts['requests'] = self.requests
        lead = alarm.first_slip_s - alarm.t_s
        self.diag.values['last_request'] = f'{alarm.t_s:.3f} s, k={alarm.k}, slip {lead:.3f} s later'
        self.get_logger().info(f'request {msg.request_id}: separation into {alarm.k} groups predicted at '
                               f'{alarm.t_s:.3f} s, the first pole slip {lead:.3f} s later')


def main(args: list[str] | None = None) -> int:
    """Run the stability_monitor node."""
    return spin_node(StabilityMonitorNode, args)


if __name__ == '__main__':
    sys.exit(main())
