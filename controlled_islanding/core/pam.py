"""PAM k-medoids (BUILD, then SWAP) on Euclidean distances between points, without an n x n distance matrix.

The algorithm and its tie-breaking are those of the kmedoids package's ``pam(diss, k, init='build')``
(Schubert and Rousseeuw's implementation of Kaufman and Rousseeuw's PAM): BUILD picks the point with the
least total distance, then k-1 times the point that lowers the loss most; SWAP then makes the single best
(medoid, non-medoid) swap per iteration until none lowers the loss, at most ``max_iter`` times; on equal
gains the lowest index wins. Two things differ. Distances are computed when needed, in the points' own space,
instead of being read from an n x n matrix (at 9241 buses that matrix alone is 0.68 GB, and its n x n x p
difference array several times that). And SWAP evaluates a candidate against all k medoids in one pass
(FastPAM1's shared sum), so its sums are added in another order than kmedoids': equal to the last bits,
the same swaps unless two candidates' gains tie to the last bits (in one dimension exact ties are common,
and either choice is then a PAM result of equal loss). The tests compare with kmedoids.pam.

Cost: n^2 distances per BUILD step and per SWAP iteration, _LANES candidates at a time through the points (each
lane doing one candidate's scalar sums in their order, so the gains are those of one candidate at a time), spread
over the cores from _PARALLEL_FROM points.
"""

from __future__ import annotations

import numba
import numpy as np

_NONE = -1  # no second-nearest medoid yet
# Below this many points a SWAP pass takes under a few ms on one core, less than waking a thread pool costs on
# a loaded machine (measured: 33 ms per pass at 39 points with load 7 on 2 cores).
_PARALLEL_FROM = 1000
# Candidates per pass over the points. One candidate's loop is bound by the latency of its sums; _LANES of them
# side by side fill the vector units. The lane loops run to an array's length, not to this constant, since LLVM
# unrolls a short constant loop completely and then leaves it unvectorised.
_LANES = 32


@numba.njit(cache=True, inline='always')
def _dist(x: np.ndarray, i: int, j: int) -> float:
    """Euclidean distance between rows i and j, summing squared differences in column order (as numpy does)."""
    acc = 0.0
    for c in range(x.shape[1]):
        diff = x[i, c] - x[j, c]
        acc += diff * diff
    return np.sqrt(acc)


@numba.njit(cache=True)
def _load_lanes(x, first, count, xl):
    """Copy points first .. first+count-1 into xl lane-interleaved (xl[c * _LANES + l]); spare lanes repeat the last."""
    for c in range(x.shape[1]):
        for lane in range(_LANES):
            xl[c * _LANES + lane] = x[first + min(lane, count - 1), c]


@numba.njit(cache=True)
def _lane_distances(x, o, xl, d):
    """d[l] = _dist between lane l's point and point o, with _dist's operations in _dist's order."""
    ul = np.uint64(d.shape[0])
    for lane in range(ul):
        d[lane] = 0.0
    for c in range(x.shape[1]):
        xo, at = x[o, c], np.uint64(c * _LANES)
        for lane in range(ul):
            diff = xl[at + lane] - xo
            d[lane] += diff * diff
    for lane in range(ul):
        d[lane] = np.sqrt(d[lane])


@numba.njit(cache=True)
def _build_gains(x, near_d, gain, lo, hi, first):
    """Store in gain[i] the loss change of making point i (lo .. hi-1) a medoid; first: its total distance."""
    n = x.shape[0]
    xl, d, total = np.empty(x.shape[1] * _LANES), np.empty(_LANES), np.empty(_LANES)
    ul = np.uint64(d.shape[0])
    for block in range(lo, hi, _LANES):
        count = min(_LANES, hi - block)
        _load_lanes(x, block, count, xl)
        total[:] = 0.0
        for j in range(n):  # j == i counts too: a new medoid saves its own distance
            _lane_distances(x, j, xl, d)
            nj = near_d[j]
            for lane in range(ul):
                dl = d[lane]
                total[lane] += dl if first else (dl - nj if dl < nj else 0.0)
        for lane in range(count):
            gain[block + lane] = total[lane]


@numba.njit(cache=True, parallel=True)
def _build_gains_parallel(x, near_d, gain, first, chunks):
    n = x.shape[0]
    for c in numba.prange(chunks):
        _build_gains(x, near_d, gain, c * n // chunks, (c + 1) * n // chunks, first)


@numba.njit(cache=True)
def _assign(x: np.ndarray, meds: np.ndarray, near_i, near_d, seco_i, seco_d) -> float:
    """Nearest and second-nearest medoid of every point (the reference's initial assignment); return the loss."""
    loss = 0.0
    for i in range(x.shape[0]):
        near_i[i], near_d[i], seco_i[i], seco_d[i] = 0, _dist(x, i, meds[0]), _NONE, 0.0
        for m in range(1, meds.shape[0]):
            d = _dist(x, i, meds[m])
            if d < near_d[i] or i == meds[m]:
                seco_i[i], seco_d[i] = near_i[i], near_d[i]
                near_i[i], near_d[i] = m, d
            elif seco_i[i] == _NONE or d < seco_d[i]:
                seco_i[i], seco_d[i] = m, d
        loss += near_d[i]
    return loss


@numba.njit(cache=True)
def _swap_gains(x, meds, near_i, near_d, seco_d, change, medoid, lo, hi):
    """For every non-medoid j in lo .. hi-1: the best loss change of swapping it in, and for which medoid.

    PAM's change for removing medoid m is the sum over points o of min(d_jo - near_o, 0) when o's nearest
    medoid is not m, else min(d_jo, second_o) - near_o. One pass gives it for every m at once (FastPAM1's
    shared sum plus a correction per medoid): n distances per candidate instead of k n. _LANES candidates go
    through the points together, each summing in the scalar order; o == j adds 0.0 instead of nothing, which
    leaves every comparison as it was (the sums only differ, if ever, in the sign of a zero).
    """
    n, k = x.shape[0], meds.shape[0]
    xl, d = np.empty(x.shape[1] * _LANES), np.empty(_LANES)
    ul = np.uint64(d.shape[0])
    shared, own, cand = np.empty(_LANES), np.empty(k * _LANES), np.empty(_LANES, dtype=np.int64)
    for block in range(lo, hi, _LANES):
        count = min(_LANES, hi - block)
        _load_lanes(x, block, count, xl)
        for lane in range(_LANES):
            cand[lane] = block + min(lane, count - 1)
            shared[lane] = -near_d[cand[lane]]  # j itself stops paying its distance
        own[:] = 0.0
        for o in range(n):
            _lane_distances(x, o, xl, d)
            no, so, at = near_d[o], seco_d[o], np.uint64(near_i[o] * _LANES)
            for lane in range(ul):
                djo = d[lane]
                gain = djo - no if djo < no else 0.0
                term = (djo if djo < so else so) - no - gain
                other = cand[lane] != o
                shared[lane] += gain if other else 0.0
                own[at + lane] += term if other else 0.0
        for lane in range(count):
            j = block + lane
            change[j], medoid[j] = 0.0, k
            if j == meds[near_i[j]]:
                continue
            for m in range(k):
                if shared[lane] + own[m * _LANES + lane] < change[j]:
                    change[j], medoid[j] = shared[lane] + own[m * _LANES + lane], m


@numba.njit(cache=True, parallel=True)
def _swap_gains_parallel(x, meds, near_i, near_d, seco_d, change, medoid, chunks):
    """_swap_gains over all points, chunks of candidates on all cores (each j's sums stay sequential)."""
    n = x.shape[0]
    for c in numba.prange(chunks):
        _swap_gains(x, meds, near_i, near_d, seco_d, change, medoid, c * n // chunks, (c + 1) * n // chunks)


@numba.njit(cache=True)
def _second(x, meds, o, nearest, b, d_ob):
    s_i, s_d = b, d_ob
    for m in range(meds.shape[0]):
        if m == nearest or m == b:
            continue
        d = _dist(x, o, meds[m])
        if d < s_d:
            s_i, s_d = m, d
    return s_i, s_d


@numba.njit(cache=True)
def _do_swap(x, meds, near_i, near_d, seco_i, seco_d, b, j) -> float:
    meds[b] = j
    loss = 0.0
    for o in range(x.shape[0]):
        if o == j:
            if near_i[o] != b:
                seco_i[o], seco_d[o] = near_i[o], near_d[o]
            near_i[o], near_d[o] = b, 0.0
            continue
        doj = _dist(x, o, j)
        if near_i[o] == b:
            if doj < seco_d[o]:
                near_d[o] = doj
            else:
                near_i[o], near_d[o] = seco_i[o], seco_d[o]
                seco_i[o], seco_d[o] = _second(x, meds, o, near_i[o], b, doj)
        elif doj < near_d[o]:
            seco_i[o], seco_d[o] = near_i[o], near_d[o]
            near_i[o], near_d[o] = b, doj
        elif doj < seco_d[o]:
            seco_i[o], seco_d[o] = b, doj
        elif seco_i[o] == b:
            seco_i[o], seco_d[o] = _second(x, meds, o, near_i[o], b, doj)
        loss += near_d[o]
    return loss


def _build(x: np.ndarray, k: int) -> np.ndarray:
    """PAM BUILD: the point of least total distance, then k-1 times the point that lowers the loss most."""
    n = x.shape[0]
    near_d, gain = np.full(n, np.inf), np.empty(n)
    meds = np.empty(k, dtype=np.int64)
    for m in range(k):
        if n < _PARALLEL_FROM:
            _build_gains(x, near_d, gain, 0, n, m == 0)
        else:
            _build_gains_parallel(x, near_d, gain, m == 0, 8 * numba.get_num_threads())
        meds[m] = int(np.argmin(gain))  # the first of equal gains, as the reference's strict '<' scan
        near_d = np.minimum(near_d, np.sqrt(((x - x[meds[m]]) ** 2).sum(axis=1)))
    return meds


def pam(points: np.ndarray, k: int, max_iter: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Cluster points by PAM (BUILD and SWAP) on their Euclidean distances.

    Args:
        points: n x p coordinates (any unit; distances are in the same unit).
        k: Number of clusters, 1 <= k <= n.
        max_iter: Most SWAP iterations.

    Returns:
        (labels, medoids): the cluster of each point (0 .. k-1, cluster c around medoid c), and the
        medoids' row indices.

    Raises:
        ValueError: k out of range or points not a finite 2-D array.

    """
    x = np.ascontiguousarray(points, dtype=np.float64)
    if x.ndim != 2 or not np.isfinite(x).all():
        raise ValueError(f'points must be a finite 2-D array, got shape {x.shape}')
    n = x.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f'k must be in 1 .. {n}, got {k}')
    meds = _build(x, k)
    near_i, seco_i = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    near_d, seco_d = np.empty(n), np.empty(n)
    loss = _assign(x, meds, near_i, near_d, seco_i, seco_d)
    change, medoid = np.empty(n), np.empty(n, dtype=np.int64)
    for _ in range(max_iter if k > 1 else 0):
        if n < _PARALLEL_FROM:
            _swap_gains(x, meds, near_i, near_d, seco_d, change, medoid, 0, n)
        else:
            _swap_gains_parallel(x, meds, near_i, near_d, seco_d, change, medoid, 8 * numba.get_num_threads())
        j = int(np.argmin(change))  # the first of equal gains, as the reference's strict '<' scan
        if not change[j] < 0.0:
            break
        new_loss = _do_swap(x, meds, near_i, near_d, seco_i, seco_d, int(medoid[j]), j)
        if new_loss >= loss:  # the reference stops here too (rounding)
            break
        loss = new_loss
    return near_i.copy(), meds.copy()


# Compile (or load from numba's cache) the serial kernels now, at import: the partitioning node imports this at
# start-up so that its first request does not pay for it. The parallel ones compile on the first large grid.
pam(np.arange(4.0).reshape(4, 1), 2)
