"""Bad-data detection per PMU station, from evidence the measurements already carry (no rclpy).

Why: C37.118.2 carries no authentication and a spoofer leaves STAT "good". A station whose data contradict
themselves, or repeat, is excluded before its angles can steer a cut; it comes back only after `clean_s` of
frames that pass every test.

The tests, each judged on one station's own channel, frame by frame:

- ``frequency_mismatch``: a PMU reports the frequency it measures, f = f0 + (d theta / dt) / (2 pi), theta the
  voltage angle against the nominal-frequency reference. Over a window of ``window_s`` of consecutive frames the
  angle's change must equal 2 pi times the integral of f - f0. An angle ramp (a spoofed speed), or a step of the
  angle (a GPS time shift), breaks it while the reported frequency stays honest; so does a frequency channel that
  no longer follows the angles. The bound is derived, not tuned: ``z`` standard deviations of the angle noise (two
  angle samples of TVE/3 each: C37.118.1's total vector error bound ``noise_tve``, taken as 3 sigma, as sim/pmu.py
  draws it), plus C37.118.1's frequency error bound ``frequency_error_hz`` integrated over the window, plus the
  discretisation of the PMU's own frequency estimate: a central or backward difference (or a group delay of one
  frame) leaves at most one frame's period times the spread of the reported frequency over the window, counted
  twice, plus the second largest one-frame residual in the window: a central difference spreads an honest angle
  jump (a fault) over two frames as two equal and opposite one-frame residuals, and an oscillation the frequency
  estimate averages out (one faster than half the frame rate) gives many, while a time shift of the angles gives
  one. z is the normal quantile of the per-test false-alarm rate ``false_alarm`` (1e-9: about one false test in a
  year of 30 frames/s per station). f0 is the standard nominal frequency (50 or 60 Hz) nearest the station's first
  reported frequency: no grid at rest strays 5 Hz from its nominal. The angle is unwrapped along the reported
  frequency (a machine slipping poles moves more than pi between frames), so the test sees a lie of up to pi per
  frame.
- ``frozen``: the station's six values (phasors, frequency, ROCOF) repeat exactly for ``frozen_frames``
  frames while another station's values changed. Float phasors carrying TVE noise, or a grid in motion,
  never repeat bit for bit; a network at rest repeats everywhere at once, which is not a frozen station.
- ``replayed``: the station's values equal, bit for bit, those of an earlier time tag within ``history_s``
  (other than the previous frame, which is the frozen test), while another station's values changed: frames
  recorded and played back under fresh time tags.

The tests see only frames the caller found usable (STAT bits 15 and 13 already make a station's data unusable
in pmu_ingestion, and absent frames are not stepped). The Kalman filter's innovations and the machine model's
bound on jumps are the next evidence to add (core/dse.py does not yet expose its innovation covariance).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import norm

__all__ = ['BadDataDetector', 'BadDataError', 'REASONS', 'StationVerdict']

REASONS = ('frequency_mismatch', 'frozen', 'replayed')
_NOMINALS_HZ = (50.0, 60.0)


class BadDataError(ValueError):
    """Settings the detector cannot use."""


@dataclass
class _Station:
    rows: deque = field(default_factory=deque)  # (t_s, unwrapped voltage angle rad, frequency Hz), consecutive
    last_content: tuple | None = None
    repeats: int = 0
    seen: dict = field(default_factory=dict)  # content -> newest time tag, s
    order: deque = field(default_factory=deque)  # (t_s, content), oldest first
    suspect_reason: str = ''
    flagged_at_s: float = math.nan  # the first time tag of the current suspicion
    clean_since_s: float = math.nan
    last_t_s: float = -math.inf
    f0_hz: float = math.nan  # nominal frequency, from the station's first frame


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

    Args:
        noise_tve: Total vector error bound of the phasors, as a 3-sigma bound (C37.118.1: 0.01).
        frequency_error_hz: Frequency error bound of the PMU (C37.118.1, class P steady state: 0.005 Hz).
        window_s: Window of the frequency test, s: long enough that a spoofed speed of 1 rad/s (0.16 Hz) leaves
            a residual of 0.5 rad, far above the bound; short enough to flag it within that time.
        false_alarm: Probability that one frequency test of an honest station exceeds the bound (sets z).
        frozen_frames: Consecutive exact repeats that make a station frozen.
        history_s: How far back replayed content is looked for, s.
        clean_s: Clean data a suspect station needs before it returns, s: twice the frequency window, so that
            the evidence that flagged it has left every window, and longer than the replay history's usual lag.

    """

    def __init__(self, noise_tve: float = 0.01, frequency_error_hz: float = 0.005, window_s: float = 0.5,
                 false_alarm: float = 1e-9, frozen_frames: int = 3, history_s: float = 2.0,
                 clean_s: float = 1.0) -> None:
        if not (0 < noise_tve < 1 and frequency_error_hz >= 0 and window_s > 0 and 0 < false_alarm < 0.5
                and frozen_frames >= 1 and history_s >= 0 and clean_s >= 0):
            raise BadDataError(f'bad settings: noise_tve={noise_tve}, frequency_error_hz={frequency_error_hz}, '
                               f'window_s={window_s}, false_alarm={false_alarm}, frozen_frames={frozen_frames}, '
                               f'history_s={history_s}, clean_s={clean_s}')
        self.noise_tve, self.frequency_error_hz, self.window_s = noise_tve, frequency_error_hz, window_s
        self.z = float(norm.isf(false_alarm / 2))
        self.frozen_frames, self.history_s, self.clean_s = frozen_frames, history_s, clean_s
        self.stations: dict[str, _Station] = {}
        self.period_s = math.inf  # the smallest spacing of time tags seen, s
        self.flags = 0  # suspicions raised

    def forget(self, keep: set[str]) -> None:
        """Forget every station not in keep (memory follows the network)."""
        for sid in [s for s in self.stations if s not in keep]:
            del self.stations[sid]

    def suspects(self) -> dict[str, str]:
        """Return station id -> reason for every station now suspect."""
        return {sid: st.suspect_reason for sid, st in self.stations.items() if st.suspect_reason}

    def verdict(self, station_id: str) -> StationVerdict:
        """Return one station's current state (trusted when never seen)."""
        st = self.stations.get(station_id)
        if st is None or not st.suspect_reason:
            return StationVerdict(station_id, '', math.nan)
        return StationVerdict(station_id, st.suspect_reason, st.flagged_at_s)

    def judge(self, t_s: float, station_ids, v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad, frequency_hz,
              rocof_hz_per_s) -> dict[str, str]:
        """Take one frame's usable measurements (one value per station) and return the suspects after it.

        Frames must come in time-tag order per station; an older or repeated tag is ignored for that station.

        Returns:
            Station id -> reason, for every station suspect after this frame.

        """
        t = float(t_s)
        values = [np.asarray(a, dtype=float).reshape(-1) for a in
                  (v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad, frequency_hz, rocof_hz_per_s)]
        ids = [str(s) for s in station_ids]
        contents = [tuple(float(a[j]) for a in values) for j in range(len(ids))]
        fresh = [sid for sid in ids if t > self.stations.get(sid, _Station()).last_t_s]
        changed = {sid for sid, c in zip(ids, contents, strict=True)
                   if sid in fresh and self.stations.get(sid, _Station()).last_content not in (None, c)}
        for sid, content in zip(ids, contents, strict=True):
            if sid not in fresh:
                continue
            st = self.stations.setdefault(sid, _Station())
            if st.last_t_s > -math.inf:
                self.period_s = min(self.period_s, t - st.last_t_s)
            others_moved = bool(changed - {sid})
            reason = self._content_test(st, t, content, others_moved) or self._frequency_test(st, t, content)
            self._settle(st, t, reason)
        return self.suspects()

    # ------------------------------------------------------------------------------------------------ the tests
    def _content_test(self, st: _Station, t: float, content: tuple, others_moved: bool) -> str:
        same = content == st.last_content
        st.repeats = st.repeats + 1 if same else 0
        earlier = st.seen.get(content)
        st.last_content = content
        st.seen[content] = t
        st.order.append((t, content))
        while st.order and st.order[0][0] < t - self.history_s:
            old_t, old = st.order.popleft()
            if st.seen.get(old) == old_t:
                del st.seen[old]
        if same and others_moved and st.repeats >= self.frozen_frames:
            return 'frozen'
        if not same and earlier is not None and others_moved:
            return 'replayed'
        return ''

    def _frequency_test(self, st: _Station, t: float, content: tuple) -> str:
        angle, freq = content[1], content[4]
        if not (math.isfinite(angle) and math.isfinite(freq)):
            st.rows.clear()
            return ''
        # Consecutive frames only: across a lost frame the frequency between the two tags is unknown.
        if st.rows and not (t - st.rows[-1][0] <= 1.5 * self.period_s):
            st.rows.clear()
        if math.isnan(st.f0_hz):
            st.f0_hz = min(_NOMINALS_HZ, key=lambda f: abs(f - freq))
        if st.rows:
            # Unwrapped along the reported frequency: a machine slipping poles moves more than pi in a frame.
            t_prev, prev, f_prev = st.rows[-1]
            step = 2 * math.pi * (0.5 * (freq + f_prev) - st.f0_hz) * (t - t_prev)
            angle = prev + step + math.remainder(angle - prev - step, 2 * math.pi)
        st.rows.append((t, angle, freq))
        while st.rows and st.rows[0][0] < t - self.window_s - 1e-9:
            st.rows.popleft()
        if len(st.rows) < 3 or st.rows[-1][0] - st.rows[0][0] < self.window_s - 1.5 * self.period_s:
            return ''
        rows = np.array(st.rows)
        f0 = st.f0_hz
        span_s = rows[-1, 0] - rows[0, 0]
        # Each frame's frequency covers the period that ends at it (backward) or surrounds it (central): the
        # difference between the two is the spread term of the bound.
        integral_rad = 2 * math.pi * float(np.sum((rows[1:, 2] - f0) * np.diff(rows[:, 0])))
        residual_rad = abs(rows[-1, 1] - rows[0, 1] - integral_rad)
        sigma_angle_rad = self.noise_tve / 3.0
        spread_hz = float(rows[:, 2].max() - rows[:, 2].min())
        per_frame_rad = np.abs(np.diff(rows[:, 1]) - 2 * math.pi * (rows[1:, 2] - f0) * np.diff(rows[:, 0]))
        second_rad = float(np.sort(per_frame_rad)[-2]) if len(per_frame_rad) > 1 else 0.0
        bound_rad = (self.z * math.sqrt(2.0) * sigma_angle_rad + 2 * math.pi * self.frequency_error_hz * span_s
                     + 2 * 2 * math.pi * self.period_s * spread_hz + second_rad)
        return 'frequency_mismatch' if residual_rad > bound_rad else ''

    def _settle(self, st: _Station, t: float, reason: str) -> None:
        st.last_t_s = t
        if reason:
            if not st.suspect_reason:
                st.suspect_reason, st.flagged_at_s = reason, t
                self.flags += 1
            st.clean_since_s = math.nan
            return
        if not st.suspect_reason:
            return
        if math.isnan(st.clean_since_s):
            st.clean_since_s = t
        elif t - st.clean_since_s >= self.clean_s:
            st.suspect_reason, st.flagged_at_s, st.clean_since_s = '', math.nan, math.nan
