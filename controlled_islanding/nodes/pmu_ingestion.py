"""pmu_ingestion: the PDC end of the graph. PMU frames in, one rotor-angle sample per time tag out.

Frames are published as soon as they arrive, stamped with their time tag, so a frame never waits for a late
one; the coherency node orders its window by time tag. A frame repeating a time tag already seen is a
duplicate; one older than the newest by more than `max_delay_s` is too late. A PMU whose STAT says "do not
use" or "PMU error, no information about data" (bits 15-14 other than 00), or whose time cannot be trusted, or
that is absent from the frame, gives `valid = false` for its generator. Time untrusted, counted in
`unsynced_measurements` (the angles then have no common reference): "not synchronised to UTC" (bit 13;
pdc_client also sets it where the frame's FRACSEC time quality claims more than its `max_time_error_s`), "sorted
by arrival" (bit 12: a PDC put the data under a time tag that is not its own), or the PMU's own time quality
(bits 8-6) or time since it lost lock (bits 5-4, 10 s or more) worse than `max_time_error_s` (read here too, so
that a stream from any PDC, not only pdc_client, is held to it). Rotor angles come from the core estimator
with the generator reactances of the latest /network/snapshot. A generator's PMU is the channel whose station id
ends in '/<generator name>' (where machines share a bus, each has its own current), else the one at its bus.

`estimator` chooses how: 'dse' (default), core.dse's Kalman filter on each machine's model from the snapshot's
machine data (core.dse.StreamingDSE: each frame answered on arrival, a frame ahead of a missing tag from a copy
of the filter, a late one interpolated; the filter itself waits `dse_reorder_s` for a missing tag before
stepping it as lost); or 'steady_state', the angle of V + (ra + j xq) I, which is off by tens of degrees while
the flux states move after a fault (docs/benchmarks.md). Machines without dynamic data fall back to the
steady-state estimate; /diagnostics names them (`dse_fallback`). With 'dse', `valid` still means "this frame
had usable data for the generator": where it is false the angle is the filter's prediction.

Bad data (core/bad_data.py): every station's usable data are judged frame by frame (reported frequency against
its angles' own rate, frozen and replayed content, the dispatch and the snapshot's bus angles while the grid is
at rest, the voltage against the other stations of the same bus (the snapshot's bus of each station's machine)
and, with 'dse', the filter's innovation: the phasors against the machine model's prediction). A suspect station
is excluded: its generator gets `valid = false` with the test in `suspect_reason`, the filter steps it as lost
(its data still compared with the prediction, never taken), /diagnostics warns naming it (`suspect_stations`,
counted in `suspect_flags`), and it returns after `bad_data_clean_s` of clean data (a station new to the stream, or
back from a silence longer than `dse_max_gap_s` alone, during an event: once the grid is at rest again, as its
offset can only be judged against the snapshot). The filter takes a frame up to
`dse_reorder_s` after it came, so a station flagged by its innovation is marked from the frame in which the filter
took the offending one.

Time tags are bounded by the node's own clock (sim time in replay): a frame or snapshot stamped more than
`future_tolerance_s` ahead of it is refused, so it never becomes "the newest" that every honest frame would
then be judged too old against. Until that clock starts (sim time before the first /clock), inputs are held,
at most `max_held_frames`, and judged once it runs. Everything remembered per PMU is bounded: only stations
on a bus of the snapshot are remembered, at most `max_stations_remembered` of them (least recently heard
forgotten first).
"""

from __future__ import annotations

import math
import sys
import time
from collections import OrderedDict, deque

import numpy as np
from controlled_islanding_msgs.msg import NetworkSnapshot, PmuFrame, PmuMeasurement, RotorAngles
from rclpy.node import Node

from controlled_islanding.core.bad_data import BadDataDetector, BadDataError
from controlled_islanding.core.dse import DSEError, MachineData, StreamingDSE, TagGrid, nominal_hz
from controlled_islanding.core.grid import Grid
from controlled_islanding.core.rotor_angle import RotorAngleError, estimate_rotor_angle_rad
from controlled_islanding.ros.clock_gate import ClockGate
from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.intake import SnapshotIntake
from controlled_islanding.ros.params import NodeSetupError, declare_bounded
from controlled_islanding.ros.spin import spin_node
from controlled_islanding.wire import topics
from controlled_islanding.wire.messages import element_count, stamp_s
from controlled_islanding.wire.timebounds import MAX_HELD_ELEMENTS, Backlog

_UNUSABLE = 0xC000  # STAT bits 15-14: 01 = PMU error, no information about data; 10 = data invalid; 11 = PMU error
_SORT_BY_ARRIVAL = PmuMeasurement.STAT_SORT_BY_ARRIVAL  # bit 12
_TIME_QUALITY_SHIFT, _UNLOCKED_SHIFT = 6, 4  # STAT bits 8-6 and 5-4 (C37.118.2-2011, table 7)
# Worst time error, s, of each PMU time quality code (bits 8-6): 0 = not used (a 2005 device: no information),
# 1 = < 100 ns ... 6 = < 10 ms, 7 = > 10 ms or unknown.
_PMU_TIME_ERROR_S = (None, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, math.inf)
_FIELDS = ('voltage_magnitude_pu', 'voltage_angle_rad', 'current_magnitude_pu', 'current_angle_rad')
_MAX_STATION_ID_CHARS = 256  # a remembered key longer than any real PMU name only costs memory
_MAX_STALE_NAMED = 50  # stale station ids listed in /diagnostics
_RELEASE_PERIOD_S = 0.05  # wall time between looks at held inputs while any wait for the node clock
_ESTIMATORS = ('steady_state', 'dse')


class PmuIngestionNode(Node):
    """Turns PMU frames into rotor angles."""

    def __init__(self, **node_options) -> None:
        super().__init__('pmu_ingestion', **node_options)
        self.declare_parameter('rate_fps', 60.0)
        self.declare_parameter('max_delay_s', 1.0)
        self.declare_parameter('stale_pmu_s', 0.5)
        self.rate_fps = float(self.get_parameter('rate_fps').value)
        self.max_delay_s = float(self.get_parameter('max_delay_s').value)
        self.stale_pmu_s = float(self.get_parameter('stale_pmu_s').value)
        if self.rate_fps <= 0:
            raise NodeSetupError(f'rate_fps={self.rate_fps} must be positive')
        future_tolerance_s = float(declare_bounded(
            self, 'future_tolerance_s', 1.0, 0.0, 3600.0,
            'how far, s, a frame time tag or snapshot stamp may lead this node clock (sim time in replay); '
            'further ahead it is refused (future_stamp)'))
        max_held = int(declare_bounded(
            self, 'max_held_frames', 1000, 1, 100_000,
            'frames held while the node clock has not started or no snapshot has come; the oldest is dropped'))
        self.max_pmus = int(declare_bounded(
            self, 'max_pmus_per_frame', 10_000, 1, 1_000_000,
            'largest number of PMU measurements in one frame; a larger frame is refused (too_large)'))
        self.max_stations = int(declare_bounded(
            self, 'max_stations_remembered', 10_000, 1, 1_000_000,
            'PMU stations remembered for staleness; beyond it the least recently heard is forgotten'))
        self.declare_parameter('estimator', 'dse')
        self.estimator = str(self.get_parameter('estimator').value)
        if self.estimator not in _ESTIMATORS:
            raise NodeSetupError(f'estimator={self.estimator!r} must be one of {_ESTIMATORS}')
        if self.estimator == 'dse':
            # Loaded at start, not by the first snapshot's filter: loading numba and the kernel takes seconds under
            # load, and the frames arriving meanwhile queued behind it (a real-time replay fell 4.8 s behind).
            from controlled_islanding.core import dse_kernel  # noqa: F401
        self.declare_parameter('dse_model', 'auto')
        self.dse_model = str(self.get_parameter('dse_model').value)
        self.dse_max_gap_s = float(declare_bounded(
            self, 'dse_max_gap_s', 0.5, 1e-3, 60.0,
            'longest run of missing frames the filter bridges by prediction; after a longer one it re-initialises'))
        self.dse_reorder_s = float(declare_bounded(
            self, 'dse_reorder_s', 0.1, 0.0, 10.0,
            'how long, s, the filter waits for a missing time tag once a newer frame has come (frames are still '
            'answered at once; a longer wait uses more late frames, at the cost of more work while it waits)'))
        self.stream: StreamingDSE | None = None
        self.frame_stations: OrderedDict[int, list[str]] = OrderedDict()  # time-tag key -> station per generator
        self.declare_parameter('bad_data', True)
        noise_tve = float(declare_bounded(
            self, 'bad_data_noise_tve', 0.01, 1e-6, 0.5,
            "the PMUs' total vector error bound (3 sigma; C37.118.1: 0.01), from which the bad-data bounds follow"))
        clean_s = float(declare_bounded(
            self, 'bad_data_clean_s', 1.0, 0.0, 3600.0,
            'clean data, s of time tags, a suspect PMU station needs before it is used again'))
        self.max_time_error_s = float(declare_bounded(
            self, 'max_time_error_s', 1e-4, 0.0, 10.0,
            'a PMU whose STAT time quality (bits 8-6) claims a worse time error, s, or that lost lock 10 s or more '
            'before (bits 5-4), is not synchronised; 1e-4 s is 2.2 degrees at 60 Hz (pdc_client holds FRACSEC to '
            'its own)'))
        try:
            self.detector = (BadDataDetector(noise_tve=noise_tve, clean_s=clean_s, max_gap_s=self.dse_max_gap_s)
                             if self.get_parameter('bad_data').value else None)
        except BadDataError as exc:
            raise NodeSetupError(str(exc)) from exc
        self.suspect_named = ''
        self.diag = Diagnostics(self)
        self.intake = SnapshotIntake(self, self.diag)
        self.diag.values['estimator'] = self.estimator
        self.grid: Grid | None = None
        self.buses: frozenset[int] = frozenset()
        # Topics are not ordered against each other: frames may overtake the snapshot. Hold them until it comes.
        self.early: Backlog[PmuFrame] = Backlog(max_held)
        self.max_early = max_held
        self.seen: deque[int] = deque(maxlen=4096)
        self.seen_set: set[int] = set()
        self.unique_frames = 0
        self.first_s = math.inf
        self.newest_s = -math.inf
        # A 30 frames/s stream under rate_fps 60 has every other tag of the rate_fps grid empty, not missing: missing
        # frames are counted on the stream's own grid, the one core.dse.StreamingDSE steps on.
        self.tag_grid = TagGrid()
        # station id -> (bus, last time tag with usable data, s), least recently heard first
        self.stations: OrderedDict[str, tuple[int, float]] = OrderedDict()
        self.stations_forgotten = 0
        self.unsynced = 0
        self.last_angle_rad: dict[str, float] = {}
        self.inputs = ClockGate(self, self.diag, future_tolerance_s, max_held, self._use, _RELEASE_PERIOD_S)
        self.pub = self.create_publisher(RotorAngles, topics.relative(topics.ROTOR_ANGLES),
                                         qos_for(topics.ROTOR_ANGLES))
        self.diag.subscribe(NetworkSnapshot, topics.NETWORK_SNAPSHOT, self.on_snapshot)
        self.diag.subscribe(PmuFrame, topics.PMU_FRAMES, self.on_frame, self.rate_fps,
                            (-future_tolerance_s, self.max_delay_s))

    def _use(self, item: tuple[str, object]) -> None:
        kind, msg = item
        if kind == 'snapshot':
            self._take_snapshot(msg)
        else:
            self._take_frame(msg)

    def on_snapshot(self, msg: NetworkSnapshot) -> None:
        """Take the generators (names, buses, reactances) from a snapshot, once its stamp is within bounds."""
        self.inputs.admit('network snapshot', stamp_s(msg.header.stamp), ('snapshot', msg), msg)

    def _take_snapshot(self, msg: NetworkSnapshot) -> None:
        grid = self.intake.newer(msg)
        if grid is None:
            return
        if self.estimator == 'dse' and not self._start_dse(grid, grid.freq_hz):
            return
        self.grid, self.buses = grid, frozenset(grid.buses)
        # Memory follows the network: nothing is kept for a generator or a bus the snapshot no longer has.
        names = {g.name for g in grid.generators}
        self.last_angle_rad = {n: a for n, a in self.last_angle_rad.items() if n in names}
        for station in [s for s, (bus, _) in self.stations.items() if bus not in self.buses]:
            del self.stations[station]
        if self.detector is not None:
            self.detector.forget(set(self.stations))
            self.detector.reference(stamp_s(msg.header.stamp))
        while self.early:
            self._take_frame(self.early.popleft())

    def _start_dse(self, grid: Grid, freq_hz: float) -> bool:
        """Fit the filter to a snapshot's machines (kept as is when their data and f0 did not change).

        The filter's speed is in pu of 2 pi f0: a 60 Hz filter on a 50 Hz grid scales every speed by 5/6. A snapshot
        that does not give f0 leaves the filter unmade until a frame's reported frequencies name it (_frame_f0).
        """
        machines = MachineData.of_generators(grid.generators)
        same = self.stream is not None and self.stream.dse.machines_.same_as(machines)
        if same and (self.stream.dse.freq_hz == freq_hz or not math.isfinite(freq_hz)):
            return True
        if not math.isfinite(freq_hz):
            self.stream = None
            return True
        try:
            self.stream = StreamingDSE(machines, self.rate_fps, self.dse_reorder_s, history_s=self.max_delay_s,
                                       model=self.dse_model, max_gap_s=self.dse_max_gap_s, freq_hz=freq_hz,
                                       innovation_gate=self.detector.nis_bound if self.detector else math.inf)
        except DSEError as exc:
            self.diag.reject('bad_value', f'network snapshot: no rotor angle filter from its machine data: {exc}')
            return False
        self.diag.values['nominal_frequency_hz'] = f'{freq_hz:g}'
        models = self.stream.dse.models_
        self.diag.values['dse_models'] = ','.join(f'{m or "none"}:{models.count(m)}' for m in sorted(set(models)))
        fallback = self.stream.fallback_names()
        more = ',...' if len(fallback) > _MAX_STALE_NAMED else ''
        self.diag.values['dse_fallback'] = ','.join(fallback[:_MAX_STALE_NAMED]) + more
        self.diag.values['dse_fallback_count'] = str(len(fallback))
        self.diag.warn('dse_fallback', f'{len(fallback)} generator(s) without dynamic data in the snapshot use the '
                                       f'steady-state estimate: {self.diag.values["dse_fallback"]}'
                       if fallback else None)
        return True

    def _judge(self, m: PmuMeasurement, stations: set[str]) -> str:
        """Return 'use', 'unusable' (a known PMU without usable data) or 'rejected' (not remembered)."""
        if len(m.station_id) > _MAX_STATION_ID_CHARS:
            self.diag.reject('too_large', f'PMU station id of {len(m.station_id)} characters, more than '
                                          f'{_MAX_STATION_ID_CHARS}')
            return 'rejected'
        if m.station_id in stations:
            self.diag.reject('duplicate', f'PMU {m.station_id} appears twice in one frame')
            return 'rejected'
        stations.add(m.station_id)
        if int(m.bus) not in self.buses:
            self.diag.reject('unknown_id', f'PMU {m.station_id} reports bus {m.bus}, not in the network')
            return 'rejected'
        if m.stat & _UNUSABLE:
            return 'unusable'
        if not self._synchronised(m.stat):
            self.unsynced += 1
            self.diag.values['unsynced_measurements'] = str(self.unsynced)
            return 'unusable'
        if not all(math.isfinite(getattr(m, f)) for f in _FIELDS):
            self.diag.reject('nan_value', f'PMU {m.station_id}: NaN or inf phasor with a good STAT')
            return 'unusable'
        if m.voltage_magnitude_pu < 0 or m.current_magnitude_pu < 0:
            # A phasor's magnitude is never negative (C37.118.2 polar; past zero the angle turns by pi instead).
            self.diag.reject('bad_value', f'PMU {m.station_id}: negative phasor magnitude with a good STAT')
            return 'unusable'
        return 'use'

    def _synchronised(self, stat: int) -> bool:
        """Whether a STAT word lets the data's angles be trusted against its time tag."""
        if stat & (PmuMeasurement.STAT_SYNC_ERROR | _SORT_BY_ARRIVAL) or (stat >> _UNLOCKED_SHIFT) & 0x3:
            return False
        error_s = _PMU_TIME_ERROR_S[(stat >> _TIME_QUALITY_SHIFT) & 0x7]
        return error_s is None or error_s <= self.max_time_error_s

    def _remember(self, station: str, bus: int, usable_at_s: float) -> None:
        bus_was, last_s = self.stations.pop(station, (bus, -math.inf))
        self.stations[station] = (bus, max(last_s, usable_at_s) if bus_was == bus else usable_at_s)
        if len(self.stations) > self.max_stations:
            self.stations.popitem(last=False)
            self.stations_forgotten += 1

    def on_frame(self, frame: PmuFrame) -> None:
        """Check a frame's shape and time tag; use it, hold it, or refuse it."""
        t = stamp_s(frame.header.stamp)
        if t <= 0:
            self.diag.reject('missing_stamp', 'PMU frame header.stamp (time tag) is zero')
            return
        if not frame.measurements:
            self.diag.reject('empty_message', f'PMU frame at {t:.3f} s has no measurements')
            return
        if len(frame.measurements) > self.max_pmus:
            self.diag.reject('too_large', f'PMU frame at {t:.3f} s has {len(frame.measurements)} measurements, '
                                          f'more than max_pmus_per_frame={self.max_pmus}')
            return
        self.inputs.admit('PMU frame', t, ('frame', frame), frame)

    def _take_frame(self, frame: PmuFrame) -> None:
        """Estimate each generator's rotor angle from a frame within bounds, publish."""
        t0 = time.perf_counter()
        t = stamp_s(frame.header.stamp)
        if self.grid is None:
            dropped = self.early.append(frame, element_count(frame))
            if len(self.early) > 1 and (stamp_s(self.early[-1].header.stamp) - stamp_s(self.early[0].header.stamp)
                                        > self.max_delay_s):
                self.early.popleft()
                dropped += 1
            if dropped:
                self.diag.reject('no_data', f'PMU frames for more than max_delay_s={self.max_delay_s} (or more than '
                                            f'max_held_frames={self.max_early}, or {MAX_HELD_ELEMENTS} elements) '
                                            'before any network snapshot: generator reactances unknown')
            return
        key = int(round(t * self.rate_fps))
        if key in self.seen_set:
            self.diag.reject('duplicate', f'PMU frame time tag {t:.6f} s already seen')
            return
        if t < self.newest_s - self.max_delay_s:
            self.diag.reject('time_backwards', f'PMU frame at {t:.3f} s is {self.newest_s - t:.3f} s older than '
                                               f'the newest; more than max_delay_s={self.max_delay_s}')
            return
        by_bus, by_generator = {}, {}
        stations: set[str] = set()
        for m in frame.measurements:
            verdict = self._judge(m, stations)
            if verdict == 'use':
                by_bus[int(m.bus)] = m
                by_generator[m.station_id.rpartition('/')[2]] = m
            if verdict != 'rejected':
                self._remember(m.station_id, int(m.bus), t if verdict == 'use' else -math.inf)
        sources = self._sources(by_bus, by_generator)
        suspect = self._screen(t, by_bus, by_generator)
        if self.estimator == 'dse' and self.stream is None and not self._frame_f0(by_bus, by_generator):
            return
        try:
            if self.stream is not None:
                angles = self._dse_angles(frame, t, sources, suspect)
                suspect = self._innovations(key, sources, suspect)
            else:
                angles = self._angles(frame, by_bus, by_generator)
            self._mark_suspect(angles, suspect)
        except (RotorAngleError, DSEError) as exc:  # the snapshot validator should make this impossible
            self.diag.reject('compute_failed', f'rotor angles of the frame at {t:.3f} s: {exc}')
            return
        if len(self.seen) == self.seen.maxlen:
            self.seen_set.discard(self.seen[0])
        self.seen.append(key)
        self.seen_set.add(key)
        self.unique_frames += 1
        self.first_s, self.newest_s = min(self.first_s, t), max(self.newest_s, t)
        self.tag_grid.add(key)
        self.pub.publish(angles)
        self._account(t0)

    def _frame_f0(self, by_bus: dict[int, PmuMeasurement], by_generator: dict[str, PmuMeasurement]) -> bool:
        """Make the filter at the nominal frequency this frame's usable stations report; False if none does."""
        assert self.grid is not None
        reported = [m.frequency_hz for m in [*by_bus.values(), *by_generator.values()]]
        try:
            f0 = nominal_hz(reported)
        except DSEError:
            self.diag.reject('no_data', 'the snapshot gives no nominal frequency and no usable PMU of the frame '
                                        'reports one: no rotor angle filter yet')
            return False
        return self._start_dse(self.grid, f0)

    def _screen(self, t: float, by_bus: dict[int, PmuMeasurement],
                by_generator: dict[str, PmuMeasurement]) -> dict[str, str]:
        """Judge the frame's usable stations; drop the suspect ones; return generator name -> reason."""
        if self.detector is None or self.grid is None:
            return {}
        used = {m.station_id: m for m in [*by_bus.values(), *by_generator.values()]}
        ms = list(used.values())
        scheduled: dict[str, float] = {}
        bus: dict[str, int] = {}  # the snapshot's bus of each station's machine, not the bus the wire claims
        for g in self.grid.generators:
            m = by_generator.get(g.name) or by_bus.get(g.bus)
            if m is not None:
                scheduled[m.station_id] = scheduled.get(m.station_id, 0.0) + g.p_mw / self.grid.base_mva
                bus[m.station_id] = g.bus
        suspects = self.detector.judge(t, [m.station_id for m in ms], *(
            [getattr(m, f) for m in ms] for f in (*_FIELDS, 'frequency_hz', 'rocof_hz_per_s')),
            [scheduled.get(m.station_id, math.nan) for m in ms], [bus.get(m.station_id, -1) for m in ms],
            self.grid.bus_angles_at(bus.get(m.station_id, -1) for m in ms),
            nominal_hz=self.stream.dse.freq_hz if self.stream is not None else self.grid.freq_hz)
        # Whether the tests against the snapshot judge: an operator who sees 'no' long after an event is missing a
        # newer snapshot (docs/deployment.md).
        self.diag.values['grid_at_rest'] = 'yes' if self.detector.at_rest else 'no'
        if math.isfinite(self.detector.last_jump_s):
            self.diag.values['last_event_s'] = f'{self.detector.last_jump_s:.3f}'
        out = {}
        for g in self.grid.generators:
            m = by_generator.get(g.name) or by_bus.get(g.bus)
            if m is not None and m.station_id in suspects:
                out[g.name] = f'{suspects[m.station_id]}: {m.station_id}'
        for table in (by_bus, by_generator):
            for key in [k for k, m in table.items() if m.station_id in suspects]:
                del table[key]
        self._name_suspects(suspects)
        return out

    def _name_suspects(self, suspects: dict[str, str]) -> None:
        assert self.detector is not None
        named = ','.join(f'{sid} ({why})' for sid, why in sorted(suspects.items())[:_MAX_STALE_NAMED])
        if named != self.suspect_named:
            self.suspect_named = named
            self.diag.values['suspect_stations'] = named
            self.diag.values['suspect_flags'] = str(self.detector.flags)
            self.diag.warn('suspect_data', f'{len(suspects)} PMU station(s) excluded as suspect data: {named}'
                           if suspects else None)

    def _sources(self, by_bus: dict[int, PmuMeasurement],
                 by_generator: dict[str, PmuMeasurement]) -> list[PmuMeasurement | None]:
        """Each generator's channel in this frame (its own, else its bus's), before any is found suspect."""
        assert self.grid is not None
        return [by_generator.get(g.name) or by_bus.get(g.bus) for g in self.grid.generators]

    def _innovations(self, key: int, sources: list[PmuMeasurement | None],
                     suspect: dict[str, str]) -> dict[str, str]:
        """Judge the innovations of the frames the filter took; return generator name -> reason for this frame."""
        assert self.grid is not None and self.stream is not None
        self.frame_stations[key] = [m.station_id if m is not None else '' for m in sources]
        while len(self.frame_stations) > self.max_early:
            self.frame_stations.popitem(last=False)
        if self.detector is None:
            self.stream.innovations.clear()
            return suspect
        suspects = self.detector.suspects()
        while self.stream.innovations:
            t_taken, nis = self.stream.innovations.popleft()
            ids = self.frame_stations.get(int(round(t_taken * self.rate_fps)))
            if ids is not None:
                suspects = self.detector.innovations(t_taken, ids, np.where([bool(x) for x in ids], nis, np.nan))
        out = dict(suspect)
        for g, m in zip(self.grid.generators, sources, strict=True):
            if m is not None and m.station_id in suspects and g.name not in out:
                out[g.name] = f'{suspects[m.station_id]}: {m.station_id}'
        self._name_suspects(suspects)
        return out

    def _mark_suspect(self, angles: RotorAngles, suspect: dict[str, str]) -> None:
        if suspect:
            angles.suspect_reason = [suspect.get(n, '') for n in angles.generator_names]
            angles.valid = [v and n not in suspect for v, n in zip(angles.valid, angles.generator_names, strict=True)]
            # A stability monitor reads only data that passed these tests: a suspect station's power and voltage
            # are not known.
            angles.pe_pu = [math.nan if n in suspect else x for n, x in zip(angles.generator_names, angles.pe_pu,
                                                                            strict=True)]
            angles.v_pu = [math.nan if n in suspect else x for n, x in zip(angles.generator_names, angles.v_pu,
                                                                          strict=True)]

    def _angles(self, frame: PmuFrame, by_bus: dict[int, PmuMeasurement],
                by_generator: dict[str, PmuMeasurement]) -> RotorAngles:
        assert self.grid is not None
        gens = self.grid.generators
        # A channel of the machine's own ('<station>/<generator name>', where machines share a bus) carries its
        # current; the rotor angle needs that current, never a bus total shared with another machine.
        source = [by_generator.get(g.name) or by_bus.get(g.bus) for g in gens]
        valid = np.array([m is not None for m in source])
        angles = np.zeros(len(gens))
        if valid.any():
            idx = np.flatnonzero(valid)
            cols = np.array([[getattr(source[i], f) for f in _FIELDS] for i in idx])
            # One row = one time tag: the estimator unwraps along rows, never across generators.
            raw = estimate_rotor_angle_rad(
                cols[None, :, 0], cols[None, :, 1], cols[None, :, 2], cols[None, :, 3],
                np.array([gens[i].xq_pu for i in idx]), np.array([gens[i].ra_pu for i in idx]))[0]
            # Unwrap along time, frame by frame, against the last angle of each generator: at 60 frames/s a
            # rotor moves far less than pi between frames, even slipping poles.
            ref = np.array([self.last_angle_rad.get(gens[i].name, raw[j]) for j, i in enumerate(idx)])
            angles[idx] = ref + np.angle(np.exp(1j * (raw - ref)))
        valid &= np.isfinite(angles)
        for i in np.flatnonzero(valid):
            self.last_angle_rad[gens[i].name] = float(angles[i])
        return RotorAngles(header=frame.header, generator_names=[g.name for g in gens],
                           generator_buses=[g.bus for g in gens], angle_rad=np.where(valid, angles, 0.0).tolist(),
                           valid=valid.tolist(), **_terminal_power(source))

    def _dse_angles(self, frame: PmuFrame, t: float, source: list[PmuMeasurement | None],
                    suspect: dict[str, str]) -> RotorAngles:
        assert self.grid is not None and self.stream is not None
        gens = self.grid.generators
        seen = np.array([m is not None for m in source])
        cols = np.full((len(gens), len(_FIELDS)), np.nan)
        for i in np.flatnonzero(seen):
            cols[i] = [getattr(source[i], f) for f in _FIELDS]
        # A suspect station's data go in as not valid: compared with the filter's prediction, never taken.
        valid = seen & np.array([g.name not in suspect for g in gens])
        angles = self.stream.offer(t, *cols.T, valid)
        for key in ('lost_frames', 'late_frames', 'ahead_frames'):
            self.diag.values[f'dse_{key}'] = str(getattr(self.stream, key))
        known = np.isfinite(angles)
        return RotorAngles(header=frame.header, generator_names=[g.name for g in gens],
                           generator_buses=[g.bus for g in gens], angle_rad=np.where(known, angles, 0.0).tolist(),
                           valid=(valid & known).tolist(), omega_pu=self.stream.omega_pu_.tolist(),
                           tm_pu=self.stream.tm_pu_.tolist(),
                           **_terminal_power([m if ok else None for m, ok in zip(source, valid, strict=True)]))

    def _account(self, t0: float) -> None:
        self.diag.computed(time.perf_counter() - t0)
        expected = int(round((self.newest_s - self.first_s) * self.rate_fps / self.tag_grid.period)) + 1
        self.diag.values['missing_frames'] = str(max(0, expected - self.unique_frames))
        if self.unique_frames % 30:
            return  # stale PMUs change slowly; refreshing them twice a second at 60 frames/s is plenty
        stale = sorted(s for s, (_, last) in self.stations.items() if self.newest_s - last > self.stale_pmu_s)
        self.diag.values['stale_pmus'] = str(len(stale))
        # Named up to a point: the count says how many, and a diagnostics message must stay small.
        more = ',...' if len(stale) > _MAX_STALE_NAMED else ''
        self.diag.values['stale_pmu_ids'] = ','.join(stale[:_MAX_STALE_NAMED]) + more
        self.diag.warn('stale_pmus', f'{len(stale)} PMU(s) without usable data for more than {self.stale_pmu_s:g} s: '
                                     f'{self.diag.values["stale_pmu_ids"]}' if stale else None)
        self.diag.values['stations_remembered'] = str(len(self.stations))
        self.diag.values['stations_forgotten'] = str(self.stations_forgotten)


def _terminal_power(source: list[PmuMeasurement | None]) -> dict[str, list[float]]:
    """Return RotorAngles' pe_pu (Re(V I*), pu system base) and v_pu (|V|, pu) of each channel; NaN: none."""
    pe, v = [], []
    for m in source:
        if m is None:
            pe.append(math.nan)
            v.append(math.nan)
            continue
        pe.append(m.voltage_magnitude_pu * m.current_magnitude_pu
                  * math.cos(m.voltage_angle_rad - m.current_angle_rad))
        v.append(float(m.voltage_magnitude_pu))
    return {'pe_pu': pe, 'v_pu': v}


def main(args: list[str] | None = None) -> int:
    """Run the pmu_ingestion node."""
    return spin_node(PmuIngestionNode, args)


if __name__ == '__main__':
    sys.exit(main())
