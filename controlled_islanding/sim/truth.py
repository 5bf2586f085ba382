"""Ground-truth coherent groups from the simulator's own rotor angles.

The truth is the grouping the system ends in (shared with CORE and NODES):
1. Take the simulated rotor angles at the PMU time tags and their deviations d_p(t) = delta_p(t) - delta_p(0)
   (t = 0 is the pre-fault steady state), rad, continuous (never wrapped: a pole slip adds 2 pi for good).
2. Final deviations: d_p(T) at the last time tag T, the end of the run.
3. Groups: complete-linkage clusters of |d_p(T) - d_q(T)| cut at pi rad, the angle at which one machine slips
   a pole against another. Machines that keep slipping together stay together (their deviations grow alike);
   machines that slip against each other end many times pi apart; a swing that came back ends close. A system
   that stays synchronous is one group. The rule has no scale of its own beyond pi, which is physical.
4. Groups are numbered 0, 1, ... in the order of their first generator in the case.

"Final" assumes the run lasts long enough after the last disturbance for a separating pair to pass pi and a
surviving swing to come back under it; `first_pole_slip_s` and the end time, both in the manifest, show the
margin.

Diagnostics kept beside the truth:
- `pole_slip_groups(t_s, delta_rad, until_s)`: the former rule, complete-linkage clusters of the largest
  separation max |d_p - d_q| over [0, until_s] cut at pi rad, i.e. who had already slipped by the request.
- `first_pole_slip_s`: the first time tag at which any two machines are more than pi rad apart.
- `separation_visible_s`: the request-time rule of the scenarios made for other systems (bags/README.md): the
  first time tag, outside every fault, at which two machines of different final groups are more than 90 deg
  apart, i.e. the earliest moment an operator can see the separation coming.
"""

from __future__ import annotations

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

POLE_SLIP_RAD = np.pi
# Two groups whose angle has moved 90 deg apart are past the crest of the power-angle curve P = Pmax sin(delta)
# that ties them for any pre-fault angle between them in [0, 90) deg: further separation lowers the power that
# pulls them back. It is also the lower bound of the "borderline" (90 to 180 deg at the request).
SEPARATION_VISIBLE_RAD = np.pi / 2


class TruthError(ValueError):
    """Rotor angles unusable for the truth rule."""


def _deviations(t_s: np.ndarray, delta_rad: np.ndarray) -> np.ndarray:
    delta_rad = np.asarray(delta_rad, dtype=float)
    if delta_rad.ndim != 2 or delta_rad.shape[0] != len(t_s) or len(t_s) == 0:
        raise TruthError(f'delta_rad has shape {delta_rad.shape}, expected ({len(t_s)} > 0, n_gen)')
    return delta_rad - delta_rad[0]


def _clusters(separation_rad: np.ndarray) -> np.ndarray:
    n = separation_rad.shape[0]
    if n == 1:
        return np.zeros(1, dtype=int)
    raw = fcluster(linkage(squareform(separation_rad, checks=False), method='complete'), POLE_SLIP_RAD,
                   criterion='distance')
    order: dict[int, int] = {}
    return np.array([order.setdefault(int(label), len(order)) for label in raw], dtype=int)


def final_separation(t_s: np.ndarray, delta_rad: np.ndarray) -> np.ndarray:
    """Return |d_p(T) - d_q(T)| at the last time tag T, rad (see the module docstring).

    Args:
        t_s: Time tags, s, ascending, starting at the pre-fault steady state.
        delta_rad: Rotor angles, rad, shape (len(t_s), n_gen).

    Returns:
        Symmetric (n_gen, n_gen) matrix, rad.

    Raises:
        TruthError: No samples, or shapes disagree.

    """
    d = _deviations(t_s, delta_rad)[-1]
    return np.abs(d[:, None] - d[None, :])


def truth_groups(t_s: np.ndarray, delta_rad: np.ndarray) -> np.ndarray:
    """Return the true (final) coherent group of every generator (see the module docstring).

    Args:
        t_s: Time tags, s, the whole run.
        delta_rad: Rotor angles, rad, shape (len(t_s), n_gen).

    Returns:
        0-based group per generator, numbered in order of first appearance.

    Raises:
        TruthError: As final_separation.

    """
    return _clusters(final_separation(t_s, delta_rad))


def separation_matrix(t_s: np.ndarray, delta_rad: np.ndarray, until_s: float) -> np.ndarray:
    """Return S_pq = max |d_p - d_q| over [0, until_s], rad.

    Args:
        t_s: Time tags, s, ascending, starting at the pre-fault steady state.
        delta_rad: Rotor angles, rad, shape (len(t_s), n_gen).
        until_s: End of the window (the islanding request time), s.

    Returns:
        Symmetric (n_gen, n_gen) matrix, rad.

    Raises:
        TruthError: No sample in the window, or shapes disagree.

    """
    d = _deviations(t_s, delta_rad)
    window = np.asarray(t_s) <= until_s + 1e-9
    if not window.any():
        raise TruthError(f'no rotor angle sample at or before {until_s} s')
    d = d[window]
    return np.max(np.abs(d[:, :, None] - d[:, None, :]), axis=0)


def pole_slip_groups(t_s: np.ndarray, delta_rad: np.ndarray, until_s: float) -> np.ndarray:
    """Return the groups of machines already a pole slip apart by until_s (a diagnostic, not the truth).

    Args:
        t_s: Time tags, s.
        delta_rad: Rotor angles, rad, shape (len(t_s), n_gen).
        until_s: The islanding request time, s.

    Returns:
        0-based group per generator, numbered in order of first appearance.

    Raises:
        TruthError: As separation_matrix.

    """
    return _clusters(separation_matrix(t_s, delta_rad, until_s))


def first_pole_slip_s(t_s: np.ndarray, delta_rad: np.ndarray) -> float | None:
    """Return the first time tag at which two machines are more than pi rad apart, s; None if never.

    Args:
        t_s: Time tags, s.
        delta_rad: Rotor angles, rad, shape (len(t_s), n_gen).

    Raises:
        TruthError: No samples, or shapes disagree.

    """
    d = _deviations(t_s, delta_rad)
    spread = d.max(axis=1) - d.min(axis=1)
    hits = np.flatnonzero(spread > POLE_SLIP_RAD)
    return float(np.asarray(t_s)[hits[0]]) if len(hits) else None


def separation_visible_s(t_s: np.ndarray, delta_rad: np.ndarray, groups: np.ndarray,
                         faults_s: list[tuple[float, float]] = (), angle_rad: float = SEPARATION_VISIBLE_RAD
                         ) -> float | None:
    """Return the first time tag, outside every fault, at which two final groups are more than angle_rad apart.

    Args:
        t_s: Time tags, s.
        delta_rad: Rotor angles, rad, shape (len(t_s), n_gen).
        groups: Final group of every generator (truth_groups).
        faults_s: (start, clear) of every fault, s; tags in [start, clear) are skipped (no request during a
            fault: the protection clears it first).
        angle_rad: Separation between deviations d = delta - delta(0) that counts as visible, rad.

    Returns:
        The time tag, s; None when the system stays one group or never separates that far.

    Raises:
        TruthError: No samples, or shapes disagree.

    """
    d = _deviations(t_s, delta_rad)
    groups = np.asarray(groups)
    across = groups[:, None] != groups[None, :]
    if not across.any():
        return None
    t = np.asarray(t_s, dtype=float)
    gap = np.array([np.abs(row[:, None] - row[None, :])[across].max() for row in d])
    outside = np.ones(len(t), dtype=bool)
    for start, clear in faults_s:
        outside &= ~((t >= start - 1e-9) & (t < clear - 1e-9))
    hits = np.flatnonzero((gap > angle_rad) & outside)
    return float(t[hits[0]]) if len(hits) else None
