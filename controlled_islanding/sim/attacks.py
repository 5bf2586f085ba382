"""Attacks on a bag's PMU channels, as a spoofer or a failing field device would make them (pure numpy).

Each transform takes PMU channel arrays (wire.bagdata.PmuChannels, or the BagData that is one) and returns a
copy in which the named stations' data, from `start_s` on, are altered; STAT is left "good", as a spoofer would
leave it. Rows are time tags (BagData's uniform grid), columns channels.

- ``ramp``: +2 rad/s on both angles (a spoofed speed of 0.32 Hz; the frequency channel left honest).
- ``replay``: each frame replaced by the station's frame of 1 s earlier, under its fresh time tag.
- ``frozen``: every value held at the station's last frame with data before `start_s` (where it has none, as after
  an initial gap, at its first frame from `start_s` on: a station frozen from its first frame; frozen at an empty
  frame it would be a silent station, not a frozen one).
- ``current``: current magnitude x1.5 (a CT ratio error).
- ``step``: +20 degrees on both angles (a GPS time shift of about 0.9 ms at 60 Hz).
- ``ramp2``: the ramp on two stations at once (the coordinated case; give two stations).
- ``ramp_back``: -2 rad/s on both angles: a spoofed speed against the way a machine at the fault accelerates.
- ``gap_step``: the station silent for ``GAP_S`` (0.6 s, longer than pmu_ingestion's rotor angle filter bridges:
  its ``dse_max_gap_s``, 0.5 s, after which it starts again from the returning data), then back with both angles
  +pi: a time offset of half a cycle, as a GPS receiver that locks again wrongly after an outage gives, or a spoofer
  who drops the stream first so that no test of the station's own past spans the change.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from controlled_islanding.core.coherency import frame_period_s

__all__ = ['ATTACKS', 'AttackError', 'attack', 'with_tve_noise']

ATTACKS = ('ramp', 'replay', 'frozen', 'current', 'step', 'ramp2', 'ramp_back', 'gap_step')
RAMP_RAD_PER_S = 2.0
REPLAY_LAG_S = 1.0
CURRENT_FACTOR = 1.5
STEP_RAD = np.deg2rad(20.0)
GAP_S = 0.6
_FIELDS = ('v_mag_pu', 'v_angle_rad', 'i_mag_pu', 'i_angle_rad', 'frequency_hz', 'rocof_hz_per_s', 'stat')


class AttackError(ValueError):
    """An attack that cannot be applied (unknown name or station, no frame before the start)."""


def attack(channels, name: str, stations: Sequence[str], start_s: float):
    """Return a copy of `channels` with attack `name` on `stations` from time tag `start_s`, s, on.

    Raises:
        AttackError: Unknown attack or station; ramp2 without two stations; nothing before `start_s` to replay
            or freeze.

    """
    if name not in ATTACKS:
        raise AttackError(f'unknown attack {name!r}; one of {ATTACKS}')
    if name == 'ramp2' and len(stations) != 2:
        raise AttackError(f'ramp2 attacks two stations, got {list(stations)}')
    cols = []
    for sid in stations:
        if sid not in channels.station_ids:
            raise AttackError(f'no PMU station {sid!r} in the bag')
        cols.append(channels.station_ids.index(sid))
    tags = np.asarray(channels.tag_s, dtype=float)
    rows = np.flatnonzero(tags >= start_s - 1e-9)
    out = {f: np.array(getattr(channels, f), copy=True) for f in _FIELDS}
    elapsed = (tags[rows] - start_s)[:, None]
    idx = np.ix_(rows, cols)
    if name in ('ramp', 'ramp2', 'ramp_back'):
        rate = -RAMP_RAD_PER_S if name == 'ramp_back' else RAMP_RAD_PER_S
        out['v_angle_rad'][idx] += rate * elapsed
        out['i_angle_rad'][idx] += rate * elapsed
    elif name == 'step':
        out['v_angle_rad'][idx] += STEP_RAD
        out['i_angle_rad'][idx] += STEP_RAD
    elif name == 'current':
        out['i_mag_pu'][idx] *= CURRENT_FACTOR
    elif name == 'gap_step':
        silent = rows[tags[rows] < start_s + GAP_S - 1e-9]
        back = np.ix_(rows[tags[rows] >= start_s + GAP_S - 1e-9], cols)
        for f in ('v_mag_pu', 'v_angle_rad', 'i_mag_pu', 'i_angle_rad', 'frequency_hz', 'rocof_hz_per_s'):
            out[f][np.ix_(silent, cols)] = np.nan
        out['v_angle_rad'][back] += np.pi
        out['i_angle_rad'][back] += np.pi
    else:
        if name == 'replay':
            period_s = frame_period_s(tags)
            source = rows - int(round(REPLAY_LAG_S / period_s)) if period_s > 0 else rows
            if len(rows) and source.min() < 0:
                raise AttackError(f'replay: no frame {REPLAY_LAG_S:g} s before {start_s:.3f} s to take')
            for f in _FIELDS:
                # Read from the unaltered channels: a replay of replayed frames would repeat the attack's own output.
                out[f][idx] = np.asarray(getattr(channels, f))[np.ix_(source, cols)]
        else:
            v = np.asarray(channels.v_mag_pu, dtype=float)
            for c in cols:
                has = np.flatnonzero(np.isfinite(v[:, c]))
                before, after = has[has < (rows[0] if len(rows) else len(tags))], has[np.isin(has, rows)]
                if not before.size and not after.size:
                    raise AttackError(f'frozen: station {channels.station_ids[c]!r} has no frame to hold')
                held = before[-1] if before.size else after[0]
                for f in _FIELDS:
                    out[f][rows, c] = np.asarray(getattr(channels, f))[held, c]
    return dataclasses.replace(channels, **out)


def with_tve_noise(channels, noise_tve: float, seed: int = 0, present_tve: float = 0.0):
    """Return a copy of `channels` whose phasors carry the scenario format's TVE noise (sim/pmu.py) of noise_tve.

    Each phasor is multiplied by (1 + e), e complex Gaussian, |e| clipped, as sim/pmu.py draws it; frequency and
    ROCOF are left as they are (they are derived from the noise-free angle there too). Phasors that already carry
    noise of present_tve (a bag's own scenario noise) get the independent part that brings the total standard
    deviation to noise_tve's: sqrt(noise_tve^2 - present_tve^2).
    """
    from controlled_islanding.sim.pmu import _noisy

    if not 0 <= present_tve <= noise_tve:
        raise AttackError(f'TVE noise of {noise_tve} cannot be reached from phasors that carry {present_tve} already')
    added = float(np.sqrt(noise_tve ** 2 - present_tve ** 2))
    rng = np.random.default_rng(seed)
    v_mag, v_ang = _noisy(rng, np.asarray(channels.v_mag_pu), np.asarray(channels.v_angle_rad), added)
    i_mag, i_ang = _noisy(rng, np.asarray(channels.i_mag_pu), np.asarray(channels.i_angle_rad), added)
    return dataclasses.replace(channels, v_mag_pu=v_mag, v_angle_rad=v_ang, i_mag_pu=i_mag, i_angle_rad=i_ang)
