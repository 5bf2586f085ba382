"""Rotor angle from a generator's terminal voltage and current phasors (Algorithm 1, step 1).

The internal voltage behind the q-axis reactance, E = V + (ra + j xq) I, lies on the q axis, so its
angle is the rotor angle in the frame of the phasors (the PMU's, i.e. against the nominal-frequency
reference). I is the current leaving the machine into the network, I = conj((P + jQ) / V) with P, Q the
machine's output. All quantities in pu on one base (the system base for xq and ra, as in NetworkSnapshot).
"""

from __future__ import annotations

import numpy as np


class RotorAngleError(ValueError):
    """Phasor arrays or machine data that do not fit together."""


def unwrap_nan(angle_rad: np.ndarray, axis: int = 0) -> np.ndarray:
    """Unwrap angles along an axis, skipping NaN (lost) samples instead of spreading NaN.

    Args:
        angle_rad: Angles, rad; NaN where lost.
        axis: Time axis.

    Returns:
        Unwrapped angles, rad, NaN where the input is NaN.

    """
    a = np.moveaxis(np.asarray(angle_rad, dtype=float), axis, 0)
    if not np.isnan(a).any():  # the common case, and the per-frame hot path of pmu_ingestion
        return np.moveaxis(np.unwrap(a, axis=0), 0, axis)
    out = np.full_like(a, np.nan)
    flat_in = a.reshape(a.shape[0], -1)
    flat_out = out.reshape(a.shape[0], -1)
    for col in range(flat_in.shape[1]):
        ok = ~np.isnan(flat_in[:, col])
        flat_out[ok, col] = np.unwrap(flat_in[ok, col])
    return np.moveaxis(out, 0, axis)


def estimate_rotor_angle_rad(v_mag_pu: np.ndarray, v_angle_rad: np.ndarray, i_mag_pu: np.ndarray,
                             i_angle_rad: np.ndarray, xq_pu: float | np.ndarray,
                             ra_pu: float | np.ndarray = 0.0) -> np.ndarray:
    """Estimate rotor angles as the angle of E = V + (ra + j xq) I, unwrapped along time.

    Args:
        v_mag_pu: Terminal voltage magnitude, pu; shape (n_frames,) or (n_frames, n_gen); NaN = lost.
        v_angle_rad: Terminal voltage angle, rad; same shape.
        i_mag_pu: Current magnitude out of the machine, pu on the system base; same shape.
        i_angle_rad: Current angle, rad; same shape.
        xq_pu: q-axis synchronous reactance, pu on the system base; scalar or one per generator.
        ra_pu: Armature resistance, pu on the system base; scalar or one per generator.

    Returns:
        Rotor angles, rad, unwrapped along axis 0 over the valid samples; NaN where any input is lost.

    Raises:
        RotorAngleError: Shapes that do not broadcast, or a reactance that is missing or negative.

    """
    arrays = [np.asarray(x, dtype=float) for x in (v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad)]
    if len({a.shape for a in arrays}) != 1 or arrays[0].ndim not in (1, 2):
        raise RotorAngleError(f'phasor arrays must share one shape (n_frames,) or (n_frames, n_gen), '
                              f'got {[a.shape for a in arrays]}')
    xq = np.asarray(xq_pu, dtype=float)
    ra = np.asarray(ra_pu, dtype=float)
    n_gen = 1 if arrays[0].ndim == 1 else arrays[0].shape[1]
    for name, val in (('xq_pu', xq), ('ra_pu', ra)):
        if val.ndim > 1 or (val.ndim == 1 and (arrays[0].ndim == 1 or len(val) != n_gen)):
            raise RotorAngleError(f'{name} must be a scalar or one value per generator ({n_gen}), '
                                  f'got shape {val.shape}')
        if np.isnan(val).any() or (val < 0).any():
            raise RotorAngleError(f'{name} must be known and >= 0, got {val}')
    v = arrays[0] * np.exp(1j * arrays[1])
    i = arrays[2] * np.exp(1j * arrays[3])
    return unwrap_nan(np.angle(v + (ra + 1j * xq) * i), axis=0)
