"""Dynamic time warping exactly as the paper's eqs. 1 to 3: squared local cost summed along the best path.

DTW(a, b) = min over warping paths w of sum_l (a[m_l] - b[n_l])^2, with the boundary, continuity and
monotonicity conditions (steps (1,0), (0,1), (1,1)). Units: the square of the series' unit (rad^2 for
rotor angles).

Lost samples (NaN) are dropped, not interpolated: DTW aligns what is left, which is why unequal lengths
are allowed at all.

Sakoe-Chiba window (``window``, in samples of the series after dropping lost samples): cell (i, j),
0-based, may be on the path iff -window <= j - i <= window + (len(b) - len(a)) when len(b) >= len(a)
(mirrored otherwise), i.e. a band of half-width ``window`` widened by the length difference so that the
far corner stays reachable. ``window=0`` on equal lengths is the squared Euclidean distance; ``None``
means no window.

Engine: dtaidistance's C implementation (the issue allows it). Its convention differs from ours in two
places, both handled here: it returns sqrt of our value, and its ``window`` counts the diagonal, so our
``window`` is its ``window - 1``. Its pruning is never used: dtaidistance 2.5.1 returns inf with pruning
on series of unequal length, and on equal lengths whenever the diagonal path is the optimum (the bound
it prunes with is then reached exactly).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


class DTWError(ValueError):
    """A series DTW cannot use (not 1-D, infinite values, nothing left after dropping lost samples)."""


def clean_series(series: np.ndarray | Sequence[float], name: str = 'series') -> np.ndarray:
    """Return a series as contiguous float64 with lost (NaN) samples dropped.

    Args:
        series: 1-D samples; NaN marks a lost sample.
        name: How to name the series in errors.

    Returns:
        The valid samples, in order.

    Raises:
        DTWError: Not 1-D, infinite samples, or no valid sample.

    """
    arr = np.asarray(series, dtype=float)
    if arr.ndim != 1:
        raise DTWError(f'{name} must be 1-D, got shape {arr.shape}')
    if np.isinf(arr).any():
        raise DTWError(f'{name} has infinite samples (use NaN for lost samples)')
    arr = np.ascontiguousarray(arr[~np.isnan(arr)])
    if arr.size == 0:
        raise DTWError(f'{name} has no valid sample')
    return arr


def _engine_window(window: int | None) -> int | None:
    if window is None:
        return None
    if int(window) != window or window < 0:
        raise DTWError(f'window must be a whole number of samples >= 0 or None, got {window!r}')
    return int(window) + 1


def dtw_distance(a: np.ndarray | Sequence[float], b: np.ndarray | Sequence[float], window: int | None = None) -> float:
    """Return DTW(a, b) of eq. 3: the least sum of squared differences along a warping path.

    Args:
        a: First series (NaN = lost sample, dropped).
        b: Second series (NaN = lost sample, dropped).
        window: Sakoe-Chiba half-width in samples (see the module docstring), or None.

    Returns:
        The distance, in the square of the series' unit.

    Raises:
        DTWError: A bad series or window.

    """
    from dtaidistance import dtw

    a_c, b_c = clean_series(a, 'a'), clean_series(b, 'b')
    d = dtw.distance_fast(a_c, b_c, window=_engine_window(window), use_pruning=False)
    return float(d) ** 2


def dtw_distance_matrix(series: Sequence[np.ndarray | Sequence[float]], window: int | None = None,
                        parallel: bool = False) -> np.ndarray:
    """Return the symmetric matrix of DTW distances (eq. 3) between every pair of series.

    Args:
        series: One 1-D series per item (NaN = lost sample, dropped); lengths may differ.
        window: Sakoe-Chiba half-width in samples, or None.
        parallel: Spread pairs over all cores (OpenMP); off by default because the decision path shares
            the machine with the ROS nodes.

    Returns:
        n x n array, zero diagonal, in the square of the series' unit.

    Raises:
        DTWError: A bad series or window.

    """
    from dtaidistance import dtw

    clean = [clean_series(s, f'series {i}') for i, s in enumerate(series)]
    n = len(clean)
    if n < 2:
        return np.zeros((n, n))
    d = dtw.distance_matrix_fast(clean, window=_engine_window(window), use_pruning=False, parallel=parallel)
    d = np.asarray(d, dtype=float) ** 2
    np.fill_diagonal(d, 0.0)
    return d
