"""Ground-truth coherent groups from the simulator's own rotor angles.

The rule (shared with CORE and NODES):
1. Take the simulated rotor angles at the PMU time tags from the simulation start up to and including
   the islanding request time, and their deviations d_p(t) = delta_p(t) - delta_p(0) (t = 0 is the
   pre-fault steady state).
2. Separation of generators p and q: S_pq = max over that window of |d_p(t) - d_q(t)|, rad.
3. Groups: complete-linkage clustering of S cut at pi rad, so every two generators in one group stayed
   within pi rad (no pole slip) of each other for the whole window, and generators in different groups
   separated by more than pi rad. A system that stays synchronous is one group.
4. Groups are numbered 0, 1, ... in the order of their first generator in the case.
"""

from __future__ import annotations

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

POLE_SLIP_RAD = np.pi


class TruthError(ValueError):
    """Rotor angles unusable for the truth rule."""


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
    delta_rad = np.asarray(delta_rad, dtype=float)
    if delta_rad.ndim != 2 or delta_rad.shape[0] != len(t_s):
        raise TruthError(f'delta_rad has shape {delta_rad.shape}, expected ({len(t_s)}, n_gen)')
    window = np.asarray(t_s) <= until_s + 1e-9
    if not window.any():
        raise TruthError(f'no rotor angle sample at or before {until_s} s')
    d = delta_rad[window] - delta_rad[0]
    return np.max(np.abs(d[:, :, None] - d[:, None, :]), axis=0)


def truth_groups(t_s: np.ndarray, delta_rad: np.ndarray, until_s: float) -> np.ndarray:
    """Return the true coherent group of every generator (see the module docstring).

    Args:
        t_s: Time tags, s.
        delta_rad: Rotor angles, rad, shape (len(t_s), n_gen).
        until_s: The islanding request time, s.

    Returns:
        0-based group per generator, numbered in order of first appearance.

    Raises:
        TruthError: As separation_matrix.

    """
    sep = separation_matrix(t_s, delta_rad, until_s)
    n = sep.shape[0]
    if n == 1:
        return np.zeros(1, dtype=int)
    raw = fcluster(linkage(squareform(sep, checks=False), method='complete'), POLE_SLIP_RAD, criterion='distance')
    order: dict[int, int] = {}
    return np.array([order.setdefault(int(label), len(order)) for label in raw], dtype=int)
