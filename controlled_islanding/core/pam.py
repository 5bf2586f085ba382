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
over the cores from _PARALLEL_FROM points. In one dimension (the spectral embedding of a 2-way split) every gain is
a sum of |t - x| and of tents max(r - |t - x|, 0), which sorting and prefix sums give for all candidates in
O(n log n); those sums differ from the kernel's sequential ones by less than a rounding bound, so only the
candidates within twice that bound of the least can be chosen, and the kernel decides among them (the same
choice, bit for bit, with a handful of candidates instead of n).
"""

from __future__ import annotations

import numba
import numpy as np

_NONE = -1  # no second-nearest medoid yet
# Below this many points a SWAP pass takes under a few ms on one core, less than waking a thread pool costs on
# a loaded machine (measured: 33 ms per pass at 39 points with load 7 on 2 cores).
_PARALLEL_FROM = 1000
# From this many points of one dimension (k = 2 in the spectral embedding), each BUILD step and SWAP pass first
# computes every candidate's gain by sorting and prefix sums (O(n log n)), with a bound on how far that is from the
# kernel's sequential sum, and runs the kernel only on the candidates within twice the bound of the least: the same
# choice, bit for bit, at a fraction of the n^2 distances.
_SHORTLIST_FROM = 256
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
def _load_lanes(x, cands, first, count, xl):
    """Copy points cands[first .. first+count-1] into xl lane-interleaved (xl[c * _LANES + l]), spares the last."""
    for c in range(x.shape[1]):
        for lane in range(_LANES):
            xl[c * _LANES + lane] = x[cands[first + min(lane, count - 1)], c]


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
def _build_gains(x, near_d, gain, cands, lo, hi, first):
    """Store in gain[i] the loss change of making point i = cands[lo .. hi-1] a medoid; first: its total distance."""
    n = x.shape[0]
    xl, d, total = np.empty(x.shape[1] * _LANES), np.empty(_LANES), np.empty(_LANES)
    ul = np.uint64(d.shape[0])
    for block in range(lo, hi, _LANES):
        count = min(_LANES, hi - block)
        _load_lanes(x, cands, block, count, xl)
        total[:] = 0.0
        for j in range(n):  # j == i counts too: a new medoid saves its own distance
            _lane_distances(x, j, xl, d)
            nj = near_d[j]
            for lane in range(ul):
                dl = d[lane]
                total[lane] += dl if first else (dl - nj if dl < nj else 0.0)
        for lane in range(count):
            gain[cands[block + lane]] = total[lane]


@numba.njit(cache=True, parallel=True)
def _build_gains_parallel(x, near_d, gain, cands, first, chunks):
    n = cands.shape[0]
    for c in numba.prange(chunks):
        _build_gains(x, near_d, gain, cands, c * n // chunks, (c + 1) * n // chunks, first)


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
def _swap_gains(x, meds, near_i, near_d, seco_d, change, medoid, cands, lo, hi):
    """For every non-medoid j in cands[lo .. hi-1]: the best loss change of swapping it in, and for which medoid.

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
        _load_lanes(x, cands, block, count, xl)
        for lane in range(_LANES):
            cand[lane] = cands[block + min(lane, count - 1)]
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
            j = cands[block + lane]
            change[j], medoid[j] = 0.0, k
            if j == meds[near_i[j]]:
                continue
            for m in range(k):
                if shared[lane] + own[m * _LANES + lane] < change[j]:
                    change[j], medoid[j] = shared[lane] + own[m * _LANES + lane], m


@numba.njit(cache=True, parallel=True)
def _swap_gains_parallel(x, meds, near_i, near_d, seco_d, change, medoid, cands, chunks):
    """_swap_gains over cands, chunks of candidates on all cores (each j's sums stay sequential)."""
    n = cands.shape[0]
    for c in numba.prange(chunks):
        _swap_gains(x, meds, near_i, near_d, seco_d, change, medoid, cands, c * n // chunks, (c + 1) * n // chunks)


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


def _tent_sums(centres: np.ndarray, radii: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Sum over o of max(radii_o - |t - centres_o|, 0) for each t in at; 1-D, centres and at in ascending order.

    A tent is (x + r) - t on [x, x + r) and t - (x - r) on (x - r, x): counts and sums of the right ends of the
    tents whose centre is at or left of t, less those already over, and likewise for the left ends.
    """
    right, left = centres + radii, centres - radii

    def prefix(values: np.ndarray) -> np.ndarray:
        return np.concatenate([[0.0], np.cumsum(values)])

    ends, starts = np.sort(right), np.sort(left)
    n_c = np.searchsorted(centres, at, side='right')  # centre <= t
    n_r = np.searchsorted(ends, at, side='right')  # right end <= t: tent over
    n_l = np.searchsorted(starts, at, side='left')  # left end < t: tent begun
    rising = (at * n_l - prefix(starts)[n_l]) - (at * n_c - prefix(left)[n_c])
    falling = (prefix(right)[n_c] - at * n_c) - (prefix(ends)[n_r] - at * n_r)
    return rising + falling


def _distance_sums(line: np.ndarray) -> np.ndarray:
    """Sum over o of |t - line_o| for each t in line (1-D), by sorting and prefix sums."""
    ordered = np.sort(line)
    below = np.searchsorted(ordered, line, side='right')
    prefix = np.concatenate([[0.0], np.cumsum(ordered)])
    return (line * below - prefix[below]) + ((prefix[-1] - prefix[below]) - line * (len(line) - below))


def _shortlist(values: np.ndarray, bound: float, allowed: np.ndarray | None = None) -> np.ndarray:
    """Return the indices whose exact value may be the least, given values within bound of the exact ones."""
    if allowed is not None:
        values = np.where(allowed, values, np.inf)
    return np.flatnonzero(values <= values.min() + 2.0 * bound).astype(np.int64)


def _error_bound(x: np.ndarray, *radii: np.ndarray) -> float:
    """Return a bound on |prefix-sum value - kernel value| of one gain over n points of 1-D data.

    Both are sums of n terms, each a few operations on numbers up to scale; a recursive sum of n terms errs by
    at most n eps times the sum of their magnitudes, so n^2 eps scale bounds either, with a wide margin.
    """
    scale = 4.0 * (float(np.abs(x).max()) + sum(float(r.max()) for r in radii))
    return 256.0 * x.shape[0] ** 2 * np.finfo(float).eps * scale


def _swap_shortlist(line: np.ndarray, meds: np.ndarray, near_i: np.ndarray, near_d: np.ndarray,
                    seco_d: np.ndarray) -> np.ndarray:
    """Return the SWAP candidates (1-D) whose exact best change may be negative and least; none: no swap helps.

    _swap_gains' change for candidate t and medoid m is a sum of tents: its shared part is minus the tents of
    radius near_o, and a point o of medoid m adds min(d, seco_o) - near_o - min(d - near_o, 0)
    = (seco_o - near_o) - tent(seco_o) + tent(near_o).
    """
    order = np.argsort(line, kind='stable')
    at, near, seco, owner = line[order], near_d[order], seco_d[order], near_i[order]
    shared = -_tent_sums(at, near, at)
    in_order = np.full(len(line), np.inf)
    for m in range(len(meds)):
        own = owner == m
        change = shared + float((seco[own] - near[own]).sum()) - _tent_sums(at[own], seco[own], at) \
            + _tent_sums(at[own], near[own], at)
        in_order = np.minimum(in_order, change)
    best = np.empty(len(line))
    best[order] = in_order
    bound = _error_bound(line, near_d, seco_d)
    allowed = (meds[near_i] != np.arange(len(line))) & (best - bound < 0.0)  # medoids are no candidates
    if not allowed.any():
        return np.empty(0, dtype=np.int64)
    return _shortlist(best, bound, allowed)


def _build(x: np.ndarray, k: int) -> np.ndarray:
    """PAM BUILD: the point of least total distance, then k-1 times the point that lowers the loss most."""
    n = x.shape[0]
    near_d, gain = np.full(n, np.inf), np.empty(n)
    meds = np.empty(k, dtype=np.int64)
    everyone = np.arange(n, dtype=np.int64)
    for m in range(k):
        cands = everyone
        if x.shape[1] == 1 and n >= _SHORTLIST_FROM:
            line = x[:, 0]
            if m == 0:
                approx, bound = _distance_sums(line), _error_bound(line)
            else:  # the kernel's sum of min(d - near, 0)
                order = np.argsort(line, kind='stable')
                approx, bound = np.empty(n), _error_bound(line, near_d)
                approx[order] = -_tent_sums(line[order], near_d[order], line[order])
            cands = _shortlist(approx, bound)
            if 4 * len(cands) > n:
                cands = everyone
            gain[:] = np.inf
        if len(cands) < _PARALLEL_FROM:
            _build_gains(x, near_d, gain, cands, 0, len(cands), m == 0)
        else:
            _build_gains_parallel(x, near_d, gain, cands, m == 0, 8 * numba.get_num_threads())
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
    everyone = np.arange(n, dtype=np.int64)
    for _ in range(max_iter if k > 1 else 0):
        cands = everyone
        if x.shape[1] == 1 and n >= _SHORTLIST_FROM:
            cands = _swap_shortlist(x[:, 0], meds, near_i, near_d, seco_d)
            if not len(cands):
                break  # no swap can lower the loss
            if 4 * len(cands) > n:
                cands = everyone
            change[:] = 0.0  # what the kernel gives a candidate whose swaps all fail to lower the loss
        if len(cands) < _PARALLEL_FROM:
            _swap_gains(x, meds, near_i, near_d, seco_d, change, medoid, cands, 0, len(cands))
        else:
            _swap_gains_parallel(x, meds, near_i, near_d, seco_d, change, medoid, cands,
                                 8 * numba.get_num_threads())
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
