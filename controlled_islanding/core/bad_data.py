"""Bad-data detection per PMU station, from evidence the measurements already carry (no rclpy).

Why: C37.118.2 carries no authentication and a spoofer leaves STAT "good". A station whose data contradict
themselves, or repeat, is excluded before its angles can steer a cut; it comes back only after `clean_s` of
frames that pass every test.

The tests, frame by frame (each on one station's own channel, but the last two, which set stations side by side):

- ``frequency_mismatch``: a PMU reports the frequency it measures, f = f0 + (d theta / dt) / (2 pi), theta the
  voltage angle against the nominal-frequency reference. Over a window of ``window_s`` worth of frames in a chain
  (consecutive, or at most ``max_step_s`` apart where the voltage magnitude did not jump between them) the
  angle's change must equal 2 pi times the integral of f - f0. An angle ramp (a spoofed speed), or a step of the
  angle (a GPS time shift), breaks it while the reported frequency stays honest; so does a frequency channel that
  no longer follows the angles. The bound is derived, not tuned: ``z`` standard deviations of the angle noise (two
  angle samples of TVE/3 each: C37.118.1's total vector error bound ``noise_tve``, taken as 3 sigma, as sim/pmu.py
  draws it), plus C37.118.1's frequency error bound ``frequency_error_hz`` integrated over the window, plus the
  discretisation of the PMU's own frequency estimate: a central or backward difference (or a group delay of one
  frame) leaves at most one step (the window's longest) times the spread of the reported frequency over it, counted
  twice, plus the second largest one-frame residual in the window: a central difference spreads an honest angle
  jump (a fault) over two frames as two equal and opposite one-frame residuals, and an oscillation the frequency
  estimate averages out (one faster than half the frame rate) gives many, while a time shift of the angles gives
  one. z is the normal quantile of the per-test false-alarm rate ``false_alarm`` (1e-9: about one false test in a
  year of 30 frames/s per station). Until a chain fills the window (at the stream's start, after a gap the chain
  does not span, after the voltage comes back above the floor) the same bound is applied to the frames at hand,
  from the second on, with their own span: a fault cleared shortly before the request leaves only a few frames
  between the voltage's recovery and the request (EI 33's bus 101048: 5), and a spoofed speed on them was never
  judged. That adds at most one test per frame to a chain's first window, so the false-alarm rate per frame stays
  ``false_alarm``. f0 is the grid's nominal frequency: the network snapshot's where the caller gives it, else,
  once, the standard nominal (50 or 60 Hz) the first frame's stations report around (their median within 5 Hz of
  one, C37.118.1's frequency measuring range: no grid strays further). One for the grid, never a station's own:
  learnt from each station's first frame, one frame of garbage (-60 Hz, as the fuzz sends it) made that station's
  honest 60 Hz data read as a 50 Hz grid's, flagged on every frame after. The angle is unwrapped along the reported
  frequency (a machine slipping poles moves more than pi between frames), so the test sees a lie of up to pi per
  frame. A frame whose voltage is below ``angle_floor_pu`` breaks the chain as a lost frame does: near the
  electrical centre of a pole slip the terminal voltage passes through zero, its phasor turns by pi between two
  frames and no frequency estimate follows it (a PMU's magnitude is never negative: the phasor turns; without the
  floor the default bag's honest PMU_32 at 6.63 s was flagged).
- ``frozen``: the station's six values (phasors, frequency, ROCOF) repeat exactly for ``frozen_frames``
  frames while another station's values changed. Float phasors carrying TVE noise, or a grid in motion,
  never repeat bit for bit; a network at rest repeats everywhere at once, which is not a frozen station.
- ``replayed``: the station's values equal, bit for bit, those of an earlier time tag within ``history_s``
  (other than the previous frame, which is the frozen test), while another station's values changed: frames
  recorded and played back under fresh time tags.

- ``innovation``: the station's phasors against its machine's model. core/dse.py's Kalman filter predicts the
  voltage behind the machine's stator reactance, z = V + (ra + j x_s) I, from its states (the rotor angle and
  speed, the fluxes, the swing under the measured electrical power Re(V I*) with the snapshot's inertia and
  damping), and weighs the measured z against it by their covariance: the normalised innovation squared (NIS),
  chi-square with 2 degrees of freedom while the model and the C37.118.1 noise hold. A frame whose NIS exceeds
  the chi-square quantile of ``innovation_false_alarm`` (1e-12 per frame: about one false test in a thousand
  years of 30 frames/s per station) flags the station, and the filter does not take it (core.dse's
  innovation_gate). This is the machine model's bound on jumps: z is a machine state, which no fault or switching
  makes jump between frames, so a GPS time shift of the angles (the step), the frames of another time, or a CT
  ratio that moves x_s I, stand out at once; a bolted fault or a line trip moves V and I, not z. The filter's
  model is approximate (its exciter and governor are random walks; inputs are taken linear between frames): over
  the 17 manifest bags (about 100 000 judged frames) the largest honest NIS is 31, 33 with 1 % TVE noise, at
  fault inceptions, under the bound of 55.3; on the 44 judged frames whose voltage is below 0.1 pu (all inside
  bolted faults) it is 12, 15 with the noise. Judged only where the frame is within that noise model (core.dse's
  nis_: z at least 0.1 pu, the current not slipping against the voltage faster than the frame rate follows, not
  just after the filter's (re)initialisation); a station whose machine has no dynamic data is not judged. Inside
  a bolted fault at its own terminal a station's voltage carries no angle, so the frequency test cannot judge it,
  but z, carried by the fault current, still can: a spoofed speed from the fault's inception (GB's bus 73, 30
  frames/s) stands out on its first frame. On PJM 5-bus's bus 3 (60 frames/s) and Nordic's bus 6000 the filter
  takes a +2 rad/s ramp as a speed within its torque's random walk, no frame's NIS above 24: where the attack's
  frames before the request all lie inside the fault, no test of one station's own data here sees it.

- ``bus_disagreement``: stations that measure one bus (several machines on a bus, each with its own channel, as
  the snapshot maps them) report one voltage. Two C37.118.1-compliant phasors of the same voltage V differ by at
  most noise_tve (|V_a| + |V_b|) / (1 - noise_tve) (each within TVE noise_tve of V, |V| at most |V_k| / (1 -
  noise_tve)): a hard bound, no false-alarm rate to choose. A station that breaks it with more than half of the
  others at its bus is flagged; of two that disagree neither can be told right, and both are. Judged where both
  voltages are at least ``MEASURING_RANGE_FLOOR_PU``, the bottom of the standard's range. Unlike every test of a
  station's own past, it sees a lie present from the station's first frame (a GPS time offset, a recording of
  another time) and a drag too slow for the frequency test, on every frame in range.

- ``angle_mismatch``: while the grid is at rest (as the schedule test: no event yet, or, after one, settled again
  under a newer network snapshot; the caller gives each snapshot's stamp to ``reference``), the stations' voltage angles
  against the network snapshot's angles of their buses. The PMUs' reference and the snapshot's differ by one angle
  for all, so two stations' differences agree within ``angle_tolerance_rad`` plus both phasors' TVE angle (2
  asin(noise_tve)); a station that breaks it with more than half of the others is flagged (of two, both): a GPS
  time offset in place before the event, which shows in no station's own past (the step attack on a stream whose
  first frame is the fault's). Judged where the voltage is in the measuring range.

- ``new_station`` and ``gap_in_event``: a station with no past its frames can be tested against, one that joins a
  running stream or comes back from a silence longer than the filter bridges while the others reported (a time
  offset put in place while it was silent passes every test of its own). At rest the tests against the snapshot
  judge it at once (one that joins more than ``clean_s`` into the stream is ``new_station`` for ``clean_s`` as
  well); during an event it is held until the grid is at rest again, as ``gap_in_event`` (a late joiner keeps
  ``new_station``; see _unlinked).

The tests see only frames the caller found usable (pmu_ingestion drops data whose STAT says "do not use" or "PMU
error" (bits 15-14), "not synchronised" (bit 13), "sorted by arrival" (bit 12: the tag is not the data's own) or
a time quality worse than its `max_time_error_s` (bits 8-6 and 5-4), and absent frames are not stepped).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

__all__ = ['BadDataDetector', 'BadDataError', 'MEASURING_RANGE_FLOOR_PU', 'NOMINALS_HZ', 'REASONS', 'StationVerdict',
           'nominal_of']

MEASURING_RANGE_FLOOR_PU = 0.1  # C37.118.1 (class M) specifies accuracy from 10 % of rated voltage up

_MAX_PERIOD_S = 1.0  # C37.118.2's slowest reporting rate is one frame a second
_PERIOD_SAMPLES = 512  # spacings the period is judged on: a few frames of a few hundred stations

REASONS = ('frequency_mismatch', 'frozen', 'replayed', 'innovation', 'schedule_mismatch', 'angle_mismatch',
           'bus_disagreement', 'new_station', 'gap_in_event')
NOMINALS_HZ = (50.0, 60.0)  # the two nominal frequencies of AC grids (C37.118.2's FNOM allows no other)
_RANGE_HZ = 5.0  # C37.118.1 (class M): frequency is measured within +-5 Hz of the nominal


def nominal_of(frequency_hz) -> float:
    """Return the nominal frequency (50 or 60 Hz) nearest the PMUs' median reported frequency, Hz; NaN if none.

    A grid runs within a few percent of its nominal frequency even through a fault, so the median of what its PMUs
    report names it. Only frequencies within C37.118.1's measuring range of a nominal count: a garbage -60 Hz is no
    grid's.
    """
    f = np.asarray(frequency_hz, dtype=float).reshape(-1)
    f = f[np.isfinite(f)]
    f = f[np.min(np.abs(f[:, None] - np.array(NOMINALS_HZ)[None, :]), axis=1) <= _RANGE_HZ]
    if not f.size:
        return math.nan
    median = float(np.median(f))
    return min(NOMINALS_HZ, key=lambda f0: abs(f0 - median))


class BadDataError(ValueError):
    """Settings the detector cannot use."""


@dataclass(frozen=True)
class StationVerdict:
    """One station's state after a frame.

    Attributes:
        station_id: The station.
        reason: '' when trusted; else the test (a name in REASONS) that made it suspect, kept until it returns.
        flagged_at_s: Time tag at which the current suspicion began, s (NaN when trusted).

    """

    station_id: str
    reason: str
    flagged_at_s: float


class BadDataDetector:
    """Judges each PMU station from its own frames; a suspect station returns after ``clean_s`` of clean data.

    The stations of a frame are judged together, in arrays (a frame of 394 stations costs about a millisecond).

    Args:
        noise_tve: Total vector error bound of the phasors, as a 3-sigma bound (C37.118.1: 0.01).
        frequency_error_hz: Frequency error bound of the PMU (C37.118.1, class P steady state: 0.005 Hz).
        window_s: Window of the frequency test, s: long enough that a spoofed speed of 1 rad/s (0.16 Hz) leaves
            a residual of 0.5 rad, far above the bound; short enough to flag it within that time.
        false_alarm: Probability that one frequency test of an honest station exceeds the bound (sets z).
        frozen_frames: Consecutive exact repeats that make a station frozen.
        history_s: How far back replayed content is looked for, s.
        clean_s: Clean data a suspect station needs before it returns, s: twice the frequency window, so that
            the evidence that flagged it has left every window.
        angle_floor_pu: Voltage magnitude below which a frame's angle is not compared with its frequency, pu. A
            pass through zero between two frames leaves both at most the magnitude's one-frame change apart from
            zero: 0.2 pu covers a change of 0.4 pu per frame, where the simulated pole slips change 0.1-0.2.
        innovation_false_alarm: Probability that one frame's innovation test of an honest station exceeds its
            bound, under the filter's model (sets ``nis_bound``, the chi-square quantile with 2 degrees of
            freedom).
        schedule_tolerance: How far, as a share of its scheduled power, a machine's output may stand from the
            network snapshot's dispatch while the grid is at rest (regulation between snapshots, the snapshot's
            own error): the deployment's figure, from its EMS; the bags' machines stand on it exactly.
        angle_tolerance_rad: How far the angle between two buses may stand from the snapshot's while the grid is
            at rest (the snapshot's state-estimate error and the drift since it): the deployment's figure, from its
            EMS; the bags' buses stand on it exactly. 0.1 rad is 5.7 deg, a time error of 0.26 ms at 60 Hz; a GPS
            shift of 0.9 ms moves an angle 20 deg.
        rest_s: How long every station's P and |V| must stay within twice their TVE error of one value before the
            tests at rest judge again after an event, s (with a snapshot stamped since): half the period of the
            slowest electromechanical swing, an inter-area mode of 0.1 Hz, so a swing still under way shows.
        max_step_s: The longest step between a station's frames the frequency test spans, s (at least 1.5 frame
            periods): a tenth of a second, over which a 1 Hz swing's frequency departs from its chord by at most
            (pi f T)^2 / 2, 5 %, of its excursion, so the discretisation term, taken on the window's longest step,
            holds.
        max_gap_s: The longest silence the filter bridges by prediction, s (core.dse's max_gap_s; pmu_ingestion's
            dse_max_gap_s): a station silent for longer, while the others reported, has no past its returning
            frames are tested against (see _unlinked).

    Attributes:
        nis_bound: The largest normalised innovation squared an honest frame is allowed (give it to
            core.dse.RotorAngleDSE as innovation_gate).

    """

    def __init__(self, noise_tve: float = 0.01, frequency_error_hz: float = 0.005, window_s: float = 0.5,
                 false_alarm: float = 1e-9, frozen_frames: int = 3, history_s: float = 2.0,
                 clean_s: float = 1.0, angle_floor_pu: float = 0.2, innovation_false_alarm: float = 1e-12,
                 schedule_tolerance: float = 0.1, angle_tolerance_rad: float = 0.1, rest_s: float = 5.0,
                 max_step_s: float = 0.1, max_gap_s: float = 0.5) -> None:
        if not (0 < noise_tve < 1 and frequency_error_hz >= 0 and window_s > 0 and 0 < false_alarm < 0.5
                and frozen_frames >= 1 and history_s >= 0 and clean_s >= 0 and 0 <= angle_floor_pu < 1
                and 0 < innovation_false_alarm < 0.5 and schedule_tolerance >= 0 and angle_tolerance_rad >= 0
                and rest_s >= 0 and max_step_s > 0 and max_gap_s > 0):
            raise BadDataError(f'bad settings: noise_tve={noise_tve}, frequency_error_hz={frequency_error_hz}, '
                               f'window_s={window_s}, false_alarm={false_alarm}, frozen_frames={frozen_frames}, '
                               f'history_s={history_s}, clean_s={clean_s}, angle_floor_pu={angle_floor_pu}, '
                               f'innovation_false_alarm={innovation_false_alarm}, '
                               f'schedule_tolerance={schedule_tolerance}, angle_tolerance_rad={angle_tolerance_rad}, '
                               f'rest_s={rest_s}, max_step_s={max_step_s}, max_gap_s={max_gap_s}')
        self.nis_bound = -2.0 * math.log(innovation_false_alarm)  # chi-square(2) is exponential of mean 2
        self.schedule_tolerance, self.angle_tolerance_rad = schedule_tolerance, angle_tolerance_rad
        self.t_first = math.nan  # the first frame judged, s
        self.at_rest = True  # no event since the first frame, or the grid settled since (see _schedule_test)
        self.rest_s, self.max_step_s, self.max_gap_s = rest_s, max_step_s, max_gap_s
        self.last_jump_s = -math.inf  # time tag of the newest frame that showed an event, s
        self.reference_s = -math.inf  # stamp of the newest network snapshot (reference), s
        self.noise_tve, self.frequency_error_hz, self.window_s = noise_tve, frequency_error_hz, window_s
        self.z = -NormalDist().inv_cdf(false_alarm / 2)
        self.frozen_frames, self.history_s, self.clean_s = frozen_frames, history_s, clean_s
        self.angle_floor_pu = angle_floor_pu
        self.f0_hz = math.nan  # the grid's nominal frequency, Hz (NaN until known: no frequency test)
        self.period_s = math.inf  # the commonest spacing of the stations' recent time tags, s
        self._gaps: deque[int] = deque(maxlen=_PERIOD_SAMPLES)  # recent spacings, us
        self._gap_counts: dict[int, int] = {}
        self.flags = 0  # suspicions raised
        self.row: dict[str, int] = {}
        self.ids: list[str] = []
        self._m = 0  # frames in the frequency window (its ring length); 0 until the period is known
        self._alloc(0)
        self._seen: dict[tuple[int, bytes], float] = {}  # (row, content) -> newest time tag, s
        self._order: deque[tuple[float, tuple[int, bytes]]] = deque()

    def _alloc(self, n: int) -> None:
        self.last_t = np.full(n, -np.inf)
        self.last_angle = np.full(n, np.nan)
        self.last_freq = np.full(n, np.nan)
        self.count = np.zeros(n, dtype=int)  # consecutive frames, for the frequency window
        self.ptr = np.zeros(n, dtype=int)
        self.ring_e = np.zeros((n, self._m))  # one-frame residuals, rad
        self.ring_f = np.full((n, self._m), np.nan)  # reported frequencies, Hz (NaN: none in this chain)
        self.ring_g = np.zeros((n, self._m))  # the steps the residuals span, s (0: none in this chain)
        self.content = np.full((n, 6), np.nan)
        self.last_v = np.full(n, np.nan)  # voltage magnitude of the station's previous frame, pu
        self.steady_since = np.full(n, np.nan)  # time tag since which P and |V| stayed steady, s
        self.p_lo, self.p_hi = np.full(n, np.nan), np.full(n, np.nan)  # P's range since then, pu
        self.v_lo, self.v_hi = np.full(n, np.nan), np.full(n, np.nan)  # |V|'s range since then, pu
        self.repeats = np.zeros(n, dtype=int)
        self.reason = np.full(n, '', dtype=object)
        self.flagged_at = np.full(n, np.nan)
        self.clean_since = np.full(n, np.nan)
        self.unlinked = np.zeros(n, dtype=bool)  # no past to test against, held until the grid is at rest again

    def _grow(self, n: int) -> None:
        old = {k: v for k, v in vars(self).items() if isinstance(v, np.ndarray)}
        self._alloc(n)
        for k, v in old.items():
            getattr(self, k)[:len(v)] = v

    def forget(self, keep: set[str]) -> None:
        """Forget every station not in keep (memory follows the network)."""
        if set(self.ids) <= keep:
            return
        kept = [sid for sid in self.ids if sid in keep]
        rows = np.array([self.row[sid] for sid in kept], dtype=int)
        for k, v in list(vars(self).items()):
            if isinstance(v, np.ndarray):
                setattr(self, k, v[rows])
        self.ids, self.row = kept, {sid: j for j, sid in enumerate(kept)}
        self._seen.clear()
        self._order.clear()

    def suspects(self) -> dict[str, str]:
        """Return station id -> reason for every station now suspect."""
        return {self.ids[j]: str(self.reason[j]) for j in np.flatnonzero(self.reason != '')}

    def verdict(self, station_id: str) -> StationVerdict:
        """Return one station's current state (trusted when never seen)."""
        j = self.row.get(station_id)
        if j is None or not self.reason[j]:
            return StationVerdict(station_id, '', math.nan)
        return StationVerdict(station_id, str(self.reason[j]), float(self.flagged_at[j]))

    def innovations(self, t_s: float, station_ids, nis) -> dict[str, str]:
        """Take the filter's normalised innovations squared of one frame (NaN: not judged) and return the suspects.

        Call it after judge() for the same frame: a station whose NIS exceeds nis_bound becomes suspect (or stays
        suspect, its clean time starting again), flagged at t_s. The frame may be older than the newest judged
        one (the filter takes a frame up to its reorder wait after it came). Stations judge() never saw are
        ignored.
        """
        nis = np.asarray(nis, dtype=float).reshape(-1)
        ids = [str(x) for x in station_ids]
        with np.errstate(invalid='ignore'):
            over = nis > self.nis_bound
        for j in np.flatnonzero(over):
            r = self.row.get(ids[j])
            if r is None:  # never judged: its data came to the filter without passing judge()
                continue
            if not self.reason[r]:
                self.flags += 1
                self.reason[r] = 'innovation'
                self.flagged_at[r] = float(t_s)
            self.clean_since[r] = np.nan
        return self.suspects()

    def _add(self, new: list[str]) -> None:
        if new:
            self.row.update((sid, len(self.ids) + j) for j, sid in enumerate(new))
            self.ids.extend(new)
            self._grow(len(self.ids))

    def judge(self, t_s: float, station_ids, v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad, frequency_hz,
              rocof_hz_per_s, scheduled_p_pu=None, buses=None, bus_angle_rad=None,
              nominal_hz: float | None = None) -> dict[str, str]:
        """Take one frame's usable measurements (one value per station) and return the suspects after it.

        Frames must come in time-tag order per station; an older or repeated tag is ignored for that station.

        Args:
            scheduled_p_pu: Per station, the network snapshot's dispatch of the machine(s) whose current it
                measures, pu on the system base (NaN: none); None: no schedule test.
            buses: Per station, the bus whose voltage it measures, as the network snapshot maps it (negative: not
                known); None: no bus test.
            bus_angle_rad: Per station, the network snapshot's voltage angle of that bus, rad (NaN: not known);
                None: no angle test.
            nominal_hz: The grid's nominal frequency f0, Hz, as the network snapshot gives it; None or NaN: not
                known, learnt once from the frames (see the module docstring).

        Returns:
            Station id -> reason, for every station suspect after this frame.

        """
        t = float(t_s)
        ids = [str(x) for x in station_ids]
        new = [sid for sid in dict.fromkeys(ids) if sid not in self.row]
        self._add(new)
        if math.isnan(self.t_first):
            self.t_first = t
        late = {self.row[sid] for sid in new} if t - self.t_first >= self.clean_s - 1e-9 else set()
        sched = (np.full(len(ids), np.nan) if scheduled_p_pu is None
                 else np.asarray(scheduled_p_pu, dtype=float).reshape(-1))
        bus = np.full(len(ids), -1) if buses is None else np.asarray(buses, dtype=np.int64).reshape(-1)
        snap = (np.full(len(ids), np.nan) if bus_angle_rad is None
                else np.asarray(bus_angle_rad, dtype=float).reshape(-1))
        values = np.column_stack([np.asarray(a, dtype=float).reshape(-1) for a in
                                  (v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad, frequency_hz, rocof_hz_per_s)])
        rows = np.array([self.row[sid] for sid in ids], dtype=int)
        fresh = t > self.last_t[rows]
        _, first = np.unique(rows, return_index=True)
        once = np.zeros(len(rows), dtype=bool)
        once[first] = True
        keep = fresh & once
        rows, values, sched, bus, snap = rows[keep], values[keep], sched[keep], bus[keep], snap[keep]
        if not len(rows):
            return self.suspects()
        if nominal_hz is not None and math.isfinite(nominal_hz) and nominal_hz > 0:
            self.f0_hz = float(nominal_hz)
        elif math.isnan(self.f0_hz):
            self.f0_hz = nominal_of(values[:, 4])
        gaps = t - self.last_t[rows]
        self._learn_period(gaps)
        reason = self._content_test(t, rows, values)
        with np.errstate(invalid='ignore'):  # a station's |V| against its previous frame's, by more than the TVE
            jumped = np.abs(np.abs(values[:, 0]) - self.last_v[rows]) > 2 * self.noise_tve * self.last_v[rows]
        freq_bad = self._frequency_test(t, rows, values, gaps, jumped)
        reason = np.where((reason == '') & freq_bad, 'frequency_mismatch', reason)
        reason = np.where((reason == '') & self._schedule_test(t, rows, values, sched, gaps, jumped),
                          'schedule_mismatch', reason)
        reason = np.where((reason == '') & self._angle_test(values, snap), 'angle_mismatch', reason)
        reason = np.where((reason == '') & self._bus_test(values, bus), 'bus_disagreement', reason)
        reason = np.where((reason == '') & np.isin(rows, list(late)), 'new_station', reason)
        joined = np.isin(rows, [self.row[sid] for sid in new]) & (t - self.t_first > self.max_gap_s)
        reason = np.where((reason == '') & self._unlinked(t, rows, gaps, joined), 'gap_in_event', reason)
        self._settle(t, rows, reason)
        self.last_t[rows] = t
        return self.suspects()

    def _unlinked(self, t: float, rows: np.ndarray, gaps: np.ndarray, joined: np.ndarray) -> np.ndarray:
        """Stations with no past to test their frames against while the grid is not at rest: held until it is.

        A station silent for longer than the filter bridges (max_gap_s) while the others reported, from the stream's
        first frame or since its own last one: the filter starts again from its frames and the frequency window
        starts a new chain, so a time offset put in place while it was silent (half a cycle: docs/attacks.md,
        gap_step) passes every test of its own. At rest the tests against the snapshot judge it at once; during an
        event nothing can, and its machine stays unobserved until the grid is at rest again. A silence of the whole
        stream (a stalled collector, a restarted node) is no one station's act and holds none.
        """
        stream_t = float(np.max(self.last_t, initial=-np.inf))  # the newest frame before this one, any station's
        with np.errstate(invalid='ignore'):
            back = np.isfinite(self.last_t[rows]) & (gaps > self.max_gap_s) & (t - stream_t <= self.max_gap_s)
        held = (self.unlinked[rows] | back | joined) & (not self.at_rest)
        self.unlinked[rows] = held
        return held

    def _learn_period(self, gaps: np.ndarray) -> None:
        """Take the frame period as the commonest spacing of the recent time tags, never the smallest.

        A stream tags its frames at multiples of its period (C37.118.2 FRACSEC), so honest spacings repeat
        exactly; forged or stray tags, at any spacing, do not. The smallest spacing ever seen was a wire value
        any two frames could set: a fuzz's frames 1 ms apart switched the frequency test off for good, and
        ones that set a two-frame window made the honest replay after them flag seven stations.
        """
        for gap in gaps[np.isfinite(gaps) & (gaps > 0) & (gaps <= _MAX_PERIOD_S)]:
            key = int(round(float(gap) * 1e6))
            if len(self._gaps) == self._gaps.maxlen:
                old = self._gaps[0]
                self._gap_counts[old] -= 1
                if not self._gap_counts[old]:
                    del self._gap_counts[old]
            self._gaps.append(key)
            self._gap_counts[key] = self._gap_counts.get(key, 0) + 1
        if not self._gap_counts:
            return
        period_s = min(self._gap_counts, key=lambda k: (-self._gap_counts[k], k)) * 1e-6
        if period_s != self.period_s:
            self.period_s = period_s
            m = max(2, int(round(self.window_s / period_s)))
            if m != self._m:
                self._m = m
                self._alloc_rings()

    def _alloc_rings(self) -> None:
        n = len(self.ids)
        self.ring_e, self.ring_f = np.zeros((n, self._m)), np.full((n, self._m), np.nan)
        self.ring_g = np.zeros((n, self._m))
        self.count[:] = 0
        self.ptr[:] = 0

    # ------------------------------------------------------------------------------------------------ the tests
    def _content_test(self, t: float, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
        prev = self.content[rows]
        had = np.isfinite(self.last_t[rows])
        same = had & np.all(values == prev, axis=1)
        changed = had & ~same
        others_moved = (changed.sum() - changed) > 0
        self.repeats[rows] = np.where(same, self.repeats[rows] + 1, 0)
        self.content[rows] = values
        out = np.full(len(rows), '', dtype=object)
        out[same & others_moved & (self.repeats[rows] >= self.frozen_frames)] = 'frozen'
        for j in np.flatnonzero(~same):
            key = (int(rows[j]), values[j].tobytes())
            if others_moved[j] and key in self._seen:
                out[j] = 'replayed'
            self._seen[key] = t
            self._order.append((t, key))
        while self._order and self._order[0][0] < t - self.history_s:
            old_t, key = self._order.popleft()
            if self._seen.get(key) == old_t:
                del self._seen[key]
        return out

    def _schedule_test(self, t: float, rows: np.ndarray, values: np.ndarray, sched: np.ndarray,
                       gaps: np.ndarray, jumped: np.ndarray) -> np.ndarray:
        """While the grid is at rest, each station's active power Re(V I*) against the snapshot's dispatch.

        At rest means no frame since the first has moved any station's voltage magnitude by more than the TVE
        allows (2 noise_tve of it: a bolted fault, a trip or a switching does, and ends the rest), or, after such a
        jump, that the grid has settled again under a newer snapshot (_settled). A jump counts from a station's
        previous frame one period before, or where another station jumps in the same frame (a stream that lost
        frames across an event): one station back from an outage at another voltage is no event; counted as one, it
        would end these tests for every station, and its own time offset would be judged by none. The bound: the
        power's own TVE error, (2 noise_tve + noise_tve^2) |V| |I|, plus schedule_tolerance of the dispatch. A
        current transformer's ratio error, or spoofed magnitudes, fail it from the first frame at rest.
        """
        v = np.abs(values[:, 0])
        self.last_v[rows] = v
        p = values[:, 0] * values[:, 2] * np.cos(values[:, 1] - values[:, 3])
        p_error = (2 * self.noise_tve + self.noise_tve ** 2) * np.abs(values[:, 0] * values[:, 2])
        with np.errstate(invalid='ignore'):
            self._track_steadiness(t, rows, p, v, p_error)
            if np.any(jumped & (gaps <= 1.5 * self.period_s)) or np.count_nonzero(jumped) >= 2:
                self.at_rest = False
                self.last_jump_s = t
            elif not self.at_rest:
                self.at_rest = self._settled(t, rows)
            if not self.at_rest:
                return np.zeros(len(rows), dtype=bool)
            return np.abs(p - sched) > p_error + self.schedule_tolerance * np.abs(sched)

    def _track_steadiness(self, t: float, rows: np.ndarray, p: np.ndarray, v: np.ndarray,
                          p_error: np.ndarray) -> None:
        """Keep, per station, since when its P and |V| have stayed within twice their TVE error of one value."""
        lo_p, hi_p = np.fmin(self.p_lo[rows], p), np.fmax(self.p_hi[rows], p)
        lo_v, hi_v = np.fmin(self.v_lo[rows], v), np.fmax(self.v_hi[rows], v)
        moved = ((hi_p - lo_p > 2 * p_error) | (hi_v - lo_v > 2 * self.noise_tve * v)
                 | np.isnan(self.steady_since[rows]))
        self.p_lo[rows], self.p_hi[rows] = np.where(moved, p, lo_p), np.where(moved, p, hi_p)
        self.v_lo[rows], self.v_hi[rows] = np.where(moved, v, lo_v), np.where(moved, v, hi_v)
        self.steady_since[rows] = np.where(moved, t, self.steady_since[rows])

    def _settled(self, t: float, rows: np.ndarray) -> bool:
        """Whether the tests at rest may judge again after an event: the grid settled under a newer snapshot.

        Every station of this frame steady (_track_steadiness) for rest_s, and the newest snapshot stamped after
        all of them settled: a snapshot of the grid as it now stands, whose dispatch and angles are again what the
        stations must agree with. A snapshot stamped within the swing, or before the event, is not.
        """
        since = max(float(np.max(self.steady_since[rows])), self.last_jump_s)
        return self.reference_s >= since and t - since >= self.rest_s - 1e-9

    def reference(self, stamp_s: float) -> None:
        """Take the stamp of a network snapshot the caller now passes the dispatch and angles of, s.

        After an event, the tests at rest judge again once the grid has settled under a snapshot stamped since it
        did (see _settled); without one they stay off, as a grid that moved no longer stands where the older
        snapshot says.
        """
        self.reference_s = max(self.reference_s, float(stamp_s))

    def _angle_test(self, values: np.ndarray, snap: np.ndarray) -> np.ndarray:
        """While at rest (set by _schedule_test on this frame), each voltage angle against the snapshot's."""
        bad = np.zeros(len(snap), dtype=bool)
        if not self.at_rest:
            return bad
        with np.errstate(invalid='ignore'):
            ok = np.isfinite(snap) & np.isfinite(values[:, 1]) & (np.abs(values[:, 0]) >= MEASURING_RANGE_FLOOR_PU)
        if ok.sum() < 2:
            return bad
        d = values[ok, 1] - snap[ok]
        apart = np.abs(np.angle(np.exp(1j * (d[:, None] - d[None, :]))))
        bad[ok] = 2 * (apart > self.angle_tolerance_rad + 2 * math.asin(self.noise_tve)).sum(axis=1) > ok.sum() - 1
        return bad

    def _bus_test(self, values: np.ndarray, bus: np.ndarray) -> np.ndarray:
        bad = np.zeros(len(bus), dtype=bool)
        mag = np.abs(values[:, 0])
        with np.errstate(invalid='ignore'):
            ok = (bus >= 0) & np.isfinite(values[:, 1]) & (mag >= MEASURING_RANGE_FLOOR_PU)
        shared, counts = np.unique(bus[ok], return_counts=True)
        for b in shared[counts >= 2]:
            at = np.flatnonzero(ok & (bus == b))
            v = values[at, 0] * np.exp(1j * values[at, 1])
            gap = np.abs(v[:, None] - v[None, :])
            allowed = self.noise_tve / (1.0 - self.noise_tve) * (mag[at][:, None] + mag[at][None, :])
            bad[at] = 2 * (gap > allowed).sum(axis=1) > len(at) - 1
        return bad

    def _frequency_test(self, t: float, rows: np.ndarray, values: np.ndarray, gaps: np.ndarray,
                        jumped: np.ndarray) -> np.ndarray:
        angle, freq = values[:, 1], values[:, 4]
        f0 = self.f0_hz
        ok = (np.isfinite(angle) & np.isfinite(freq) & (np.abs(values[:, 0]) >= self.angle_floor_pu)
              & math.isfinite(f0))
        # Consecutive frames, or frames at most max_step_s apart (a lost frame, a station at a slower rate than the
        # stream's: one that sent every other frame was judged by no frequency test, and a spoofed speed on it
        # steered the cut) whose voltage magnitude did not jump between them: a switching inside the gap turns the
        # voltage's phase where no frame shows it, one residual without the opposite one a PMU's estimate spreads
        # it into (the second largest's allowance), and an honest frame lost at a clearing was flagged.
        follows = (ok & np.isfinite(self.last_angle[rows])
                   & ((gaps <= 1.5 * self.period_s) | ((gaps <= self.max_step_s) & ~jumped)))
        prev, f_prev = self.last_angle[rows], self.last_freq[rows]
        with np.errstate(invalid='ignore'):
            # Unwrapped along the reported frequency: a machine slipping poles moves more than pi in a frame.
            step = 2 * np.pi * (0.5 * (freq + f_prev) - f0) * gaps
            unwrapped = prev + step + np.remainder(angle - prev - step + np.pi, 2 * np.pi) - np.pi
            e = unwrapped - prev - 2 * np.pi * (freq - f0) * gaps
        self.last_angle[rows] = np.where(ok, np.where(follows, unwrapped, angle), np.nan)
        self.last_freq[rows] = np.where(ok, freq, np.nan)
        bad = np.zeros(len(rows), dtype=bool)
        if not self._m:
            return bad
        # A chain broken (a gap it does not span, a voltage below the floor) starts a new window: what it held is
        # not summed with what follows.
        broken = rows[~follows & (self.count[rows] > 0)]
        self.ring_e[broken] = 0.0
        self.ring_f[broken] = np.nan
        self.ring_g[broken] = 0.0
        self.count[rows] = np.where(follows, self.count[rows] + 1, 0)
        live = follows
        r, p = rows[live], self.ptr[rows[live]]
        self.ring_e[r, p] = e[live]
        self.ring_f[r, p] = freq[live]
        self.ring_g[r, p] = gaps[live]
        self.ptr[r] = (p + 1) % self._m
        # Judged from the second consecutive frame on, over the frames at hand (at most the window): the bound is
        # derived for a window of any length, and a chain that starts again after a fault (the voltage back above
        # the floor) may have only a few frames before the request.
        judged = live & (self.count[rows] >= 2)
        if not judged.any():
            return bad
        fr = rows[judged]
        residual = np.abs(self.ring_e[fr].sum(axis=1))
        second = np.partition(np.abs(self.ring_e[fr]), -2, axis=1)[:, -2]
        spread = np.nanmax(self.ring_f[fr], axis=1) - np.nanmin(self.ring_f[fr], axis=1)
        span_s = self.ring_g[fr].sum(axis=1)
        step_s = np.maximum(self.ring_g[fr].max(axis=1), self.period_s)
        bound = (self.z * math.sqrt(2.0) * self.noise_tve / 3.0 + 2 * np.pi * self.frequency_error_hz * span_s
                 + 2 * 2 * np.pi * step_s * spread + second)
        bad[judged] = residual > bound
        return bad

    def _settle(self, t: float, rows: np.ndarray, reason: np.ndarray) -> None:
        flagged = reason != ''
        raised = flagged & (self.reason[rows] == '')
        self.flags += int(raised.sum())
        self.reason[rows[raised]] = reason[raised]
        self.flagged_at[rows[raised]] = t
        self.clean_since[rows[flagged]] = np.nan
        calm = rows[~flagged & (self.reason[rows] != '')]
        start = calm[np.isnan(self.clean_since[calm])]
        self.clean_since[start] = t
        back = calm[t - self.clean_since[calm] >= self.clean_s]
        self.reason[back] = ''
        self.flagged_at[back] = np.nan
        self.clean_since[back] = np.nan
