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

Engine: banded dynamic programs compiled by numba, two rows of the band at a time, the same recursion as
eq. 3 (no pruning, no lower bound, no early abandoning), so its values are eq. 3's to rounding; the tests
check it against an independent dynamic program and against dtaidistance's C engine, which stays the peer
in `controlled-islanding bench`. dtaidistance's conventions differ from ours in two places: it returns
sqrt of our value, and its ``window`` counts the diagonal, so our ``window`` is its ``window - 1``.

The matrix runs _LANES pairs of equal lengths side by side, one pair per lane of the same band cell: a
single pair is bound by the latency of its chain of min and add (each cell waits for its left neighbour),
while independent lanes fill the vector units (4 to 4.3x the single-pair kernel on the 2-core AVX2 machine).
Each lane performs the single-pair kernel's operations in the same order, so the values are bit for bit those
of `dtw_distance`. The matrix is spread over the cores by blocks of pairs when it is large enough to pay for
waking the thread pool (``parallel=None``), or as asked.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
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


def _check_window(window: int | None) -> int | None:
    if window is None:
        return None
    if int(window) != window or window < 0:
        raise DTWError(f'window must be a whole number of samples >= 0 or None, got {window!r}')
    return int(window)


@numba.njit(cache=True)
def _banded(a, b, window, prev, cur):
    """Eq. 3 for a and b within the band; prev and cur are scratch rows of len(b) + 1."""
    n, m = a.shape[0], b.shape[0]
    below = window + max(0, n - m)  # j - i >= -below
    above = window + max(0, m - n)  # j - i <= above
    prev[:] = np.inf
    prev[0] = 0.0  # the virtual cell before (0, 0)
    for i in range(n):
        lo, hi = max(0, i - below), min(m - 1, i + above)
        # cur[j + 1] is cell (i, j); cur[lo] is the cell left of the band and cur[hi + 2] the one right of it:
        # both inf, so that this row and the next see no stale value from two rows back.
        cur[lo] = np.inf
        ai, diag, left = a[i], prev[lo], np.inf
        for j in range(lo, hi + 1):
            up = prev[j + 1]
            diff = ai - b[j]
            left = diff * diff + min(diag, up, left)  # the three predecessors of (i, j), kept in registers
            cur[j + 1] = left
            diag = up
        if hi + 2 <= m:
            cur[hi + 2] = np.inf
        prev, cur = cur, prev
    return prev[m]


# Pairs per block of the matrix kernel. The lane loop is vectorised by LLVM only from 16 lanes (4-wide vectors,
# interleaved 4 times); 32 measured fastest (4.3x), 64 slower again (the band rows leave the L1 cache).
_LANES = 32
# Below this many band cells (pairs x rows x band width) a matrix takes about 10 ms on one core, less than waking
# the thread pool costs on a loaded machine.
_PARALLEL_FROM_CELLS = 20_000_000


@numba.njit(cache=True)
def _banded_lanes(a, b, n, m, window, prev, cur, diag, left, out):
    """Eq. 3 for _LANES pairs whose series have lengths n and m, the recursion of _banded lane by lane.

    a and b hold the series lane-interleaved (a[i * _LANES + l] is sample i of lane l's first series); prev and
    cur are scratch of (m + 1) * _LANES, diag and left of _LANES; out receives the _LANES distances.
    """
    lanes = _LANES
    # Unsigned lane indices: numba checks signed indices for negative values, which keeps LLVM from vectorising.
    ul = np.uint64(lanes)
    below = window + max(0, n - m)
    above = window + max(0, m - n)
    for t in range(lanes * (m + 1)):
        prev[t] = np.inf
    for lane in range(lanes):
        prev[lane] = 0.0
    for i in range(n):
        lo, hi = max(0, i - below), min(m - 1, i + above)
        for lane in range(lanes):
            cur[lo * lanes + lane] = np.inf
            diag[lane] = prev[lo * lanes + lane]
            left[lane] = np.inf
        row = np.uint64(i * lanes)
        for j in range(lo, hi + 1):
            up_at, b_at = np.uint64((j + 1) * lanes), np.uint64(j * lanes)
            for lane in range(ul):
                up = prev[up_at + lane]
                diff = a[row + lane] - b[b_at + lane]
                d, lf = diag[lane], left[lane]
                best = d if d < up else up
                value = diff * diff + (best if best < lf else lf)
                cur[up_at + lane] = value
                left[lane] = value
                diag[lane] = up
        if hi + 2 <= m:
            for lane in range(lanes):
                cur[(hi + 2) * lanes + lane] = np.inf
        prev, cur = cur, prev
    for lane in range(lanes):
        out[lane] = prev[m * lanes + lane]


@numba.njit(cache=True)
def _blocks(flat, start, stop, pi, pj, block, window, out, first, last):
    """DTW of the pairs of blocks first .. last-1 (series pi[p] and pj[p], stored in flat[start[s]:stop[s]]).

    Block c holds pairs block[c] .. block[c + 1] - 1: at most _LANES, all with the same two series lengths. A
    block with fewer pairs repeats its last one in the spare lanes.
    """
    lanes = _LANES
    longest = 0
    for s in range(start.shape[0]):
        longest = max(longest, stop[s] - start[s])
    prev, cur = np.empty((longest + 1) * lanes), np.empty((longest + 1) * lanes)
    a, b = np.empty(longest * lanes), np.empty(longest * lanes)
    diag, left, res = np.empty(lanes), np.empty(lanes), np.empty(lanes)
    for c in range(first, last):
        lo, hi = block[c], block[c + 1]
        n, m = stop[pi[lo]] - start[pi[lo]], stop[pj[lo]] - start[pj[lo]]
        for lane in range(lanes):
            p = lo + min(lane, hi - lo - 1)
            for t in range(n):
                a[t * lanes + lane] = flat[start[pi[p]] + t]
            for t in range(m):
                b[t * lanes + lane] = flat[start[pj[p]] + t]
        _banded_lanes(a, b, n, m, window, prev, cur, diag, left, res)
        for lane in range(hi - lo):
            out[lo + lane] = res[lane]


@numba.njit(cache=True, parallel=True)
def _blocks_parallel(flat, start, stop, pi, pj, block, window, out, chunks):
    count = block.shape[0] - 1
    for c in numba.prange(chunks):
        _blocks(flat, start, stop, pi, pj, block, window, out, c * count // chunks, (c + 1) * count // chunks)


def _no_band(series: Sequence[np.ndarray]) -> int:
    """Return a half-width that no path can leave (the longest series' length)."""
    return max(len(s) for s in series)


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
    w = _check_window(window)
    a_c, b_c = clean_series(a, 'a'), clean_series(b, 'b')
    band = _no_band([a_c, b_c]) if w is None else w
    scratch = max(len(a_c), len(b_c)) + 1
    return float(_banded(a_c, b_c, band, np.empty(scratch), np.empty(scratch)))


def dtw_distance_matrix(series: Sequence[np.ndarray | Sequence[float]], window: int | None = None,
                        parallel: bool | None = None, pairs: np.ndarray | None = None) -> np.ndarray:
    """Return the symmetric matrix of DTW distances (eq. 3) between every pair of series, or the pairs asked.

    Args:
        series: One 1-D series per item (NaN = lost sample, dropped); lengths may differ.
        window: Sakoe-Chiba half-width in samples, or None.
        parallel: Spread pairs over all cores; None (default) does so only for matrices of at least
            _PARALLEL_FROM_CELLS band cells (a decision on hundreds of machines), since for tens of machines
            waking the threads costs more than it saves on a machine shared with the ROS nodes.
        pairs: Boolean (n, n) mask of the pairs to compute (its upper triangle is read), or None for all. Each
            value asked is the one the whole matrix would hold, bit for bit.

    Returns:
        n x n array, zero diagonal, in the square of the series' unit; NaN at the pairs not asked.

    Raises:
        DTWError: A bad series, window or mask.

    """
    w = _check_window(window)
    clean = [clean_series(s, f'series {i}') for i, s in enumerate(series)]
    n = len(clean)
    out = np.zeros((n, n))
    pi, pj = np.triu_indices(n, k=1)
    if pairs is not None:
        mask = np.asarray(pairs, dtype=bool)
        if mask.shape != (n, n):
            raise DTWError(f'pairs must be a ({n}, {n}) mask for {n} series, got shape {mask.shape}')
        out[pi, pj] = out[pj, pi] = np.nan
        pi, pj = pi[mask[pi, pj]], pj[mask[pi, pj]]
    if len(pi) == 0:
        return out
    lengths = np.array([len(c) for c in clean], dtype=np.int64)
    stop = np.cumsum(lengths)
    start = stop - lengths
    # Pairs sorted by their two lengths (stable), so that each block of lanes shares one band geometry.
    order = np.lexsort((lengths[pj], lengths[pi]))
    pi, pj = pi[order].astype(np.int64), pj[order].astype(np.int64)
    new_run = np.flatnonzero((np.diff(lengths[pi]) != 0) | (np.diff(lengths[pj]) != 0)) + 1
    runs = np.concatenate([[0], new_run, [len(pi)]])
    block = np.concatenate([np.arange(lo, hi, _LANES) for lo, hi in zip(runs[:-1], runs[1:], strict=True)]
                           + [[len(pi)]]).astype(np.int64)
    values = np.empty(len(pi))
    band = _no_band(clean) if w is None else w
    flat = np.concatenate(clean)
    if parallel is None:
        longest = int(lengths.max())
        parallel = len(pi) * longest * min(2 * band + 1, longest) >= _PARALLEL_FROM_CELLS
    if parallel:
        _blocks_parallel(flat, start, stop, pi, pj, block, band, values,
                         min(len(block) - 1, 8 * numba.get_num_threads()))
    else:
        _blocks(flat, start, stop, pi, pj, block, band, values, 0, len(block) - 1)
    out[pi, pj] = values
    out[pj, pi] = values
    return out
