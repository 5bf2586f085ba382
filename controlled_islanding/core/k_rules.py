"""Rules that choose the number of coherent groups k, and whether to split at all, from one window's evidence.

Every rule has one shape: ``rule.choose(evidence) -> labels`` (0-based group per generator; one group means
"no split"), with what it measured left in ``rule.scores_``. `DTWCoherency` (core/coherency.py) builds the
evidence once and hands it to the rule named by its ``k_rule``, so rules are swapped by name or by instance.
Every rule forms its groups from the DTW RMS matrix r: the default by constrained complete linkage, the others
by k-medoids (PAM) once they have chosen k.

Rules (docs/coherency_rules.md compares them on every scenario bag; `RULES` maps names to classes):

- ``separation`` (default): pairs heading for a pole slip, against the pole-slip scale pi rad (the angle at which
  one machine slips a pole on another: physics, not a number fitted to a system). A pair separates when
  - trend over the window: the least-squares slope of delta_p - delta_q times the span of the window (the
    pair's drift) reaches pi, or at that rate the pair would drift pi within one more window (|drift| >= pi / 2
    with the default horizon of one window) and it is not slowing down: over the latest half of the window it
    moves on, the same way, at least at the window's mean rate (least-squares slopes compared). Stable swings go
    back and forth inside a window, so their drift is small whatever their amplitude, as long as the window holds
    about a swing period; or
  - runaway from rest (pair_runaway): the window starts before the disturbance (the pair at rest over its first
    quarter), and the pair is now pi from where it rested, or pi / 2 and still moving away without slowing
    down. This sees a runaway a fraction of a second after the fault is cleared, which the trend over a window
    that is mostly pre-disturbance data cannot (the trend is diluted by the flat part).
  Equal-area: after clearing, a swing that will come back decelerates as it moves away from its equilibrium;
  a pair past its unstable equilibrium accelerates away. No separating pair: one group ("no split").
  Otherwise the groups are the complete-linkage clusters of r in which no group holds a separating pair and no
  two groups could merge without one: separating pairs are cannot-links, r (the paper's DTW coherency) decides
  where every other machine goes. k is what the data need, a single runaway machine is a group of its own, and
  max_groups is only a cap (beyond it the groups that drift apart least are merged, and scores_ says so). When
  the separating pairs are exactly the pairs between some classes (groups slipping apart as wholes), those
  classes are the linkage's groups whatever r is, so r is not computed at all (SeparationRule._forced_groups
  proves it; test_core_forced_groups.py checks it against the linkage on every pair).
- ``threshold``: the former rule, RMS warped distance r against a fixed ``coherence_threshold_rad`` (1.0 rad,
  measured on IEEE 39 bags). Kept for comparison.
- ``eigengap``: largest gap in the spectrum of the normalised Laplacian of a self-tuning Gaussian affinity of r
  (Zelnik-Manor and Perona 2004: each generator's scale is its distance to its 7th nearest neighbour).
- ``gap``: gap statistic (Tibshirani, Walther and Hastie 2001) on a classical-MDS embedding of r, reference
  sets uniform in the embedding's bounding box, smallest k with Gap(k) >= Gap(k+1) - s(k+1).
- ``silhouette``: the k with the best mean silhouette, "no split" unless that silhouette reaches 0.5, the
  lower bound of "a reasonable structure" (Kaufman and Rousseeuw 1990).

The last three are relative: they read structure from the data's own scale and so also split a stable system
whose machines swing in distinct modes; the table shows it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numba
import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform


class KRuleError(ValueError):
    """An unknown rule name or a bad rule setting."""


def silhouette(r: np.ndarray, labels: np.ndarray) -> float:
    """Return the mean silhouette (Rousseeuw 1987) of a clustering on a precomputed dissimilarity matrix.

    Singleton clusters score 0, as in scikit-learn's silhouette_score (which this equals; it is written
    out here because scikit-learn's input checks cost a millisecond per call on the decision path).

    Args:
        r: Symmetric dissimilarities, zero diagonal.
        labels: Cluster of each item; at least two clusters.

    Returns:
        The mean silhouette, in [-1, 1].

    """
    ks = np.unique(labels)
    member = labels[None, :] == ks[:, None]
    sizes = member.sum(axis=1)
    mean_to = (r @ member.T.astype(float)) / sizes[None, :]
    own = np.searchsorted(ks, labels)
    n = len(labels)
    own_size = sizes[own]
    a = mean_to[np.arange(n), own] * own_size / np.maximum(own_size - 1, 1)
    mean_to[np.arange(n), own] = np.inf
    b = mean_to.min(axis=1)
    s = np.where(own_size > 1, (b - a) / np.maximum(np.maximum(a, b), 1e-300), 0.0)
    return float(s.mean())


def canonical(labels: np.ndarray) -> np.ndarray:
    """Renumber groups in order of their first member."""
    order: dict[int, int] = {}
    return np.array([order.setdefault(int(lab), len(order)) for lab in np.asarray(labels).tolist()], dtype=int)


def pair_drift_rad(angles: np.ndarray, per_sample: bool = False) -> np.ndarray:
    """Return each pair's drift over the window: the least-squares slope of delta_p - delta_q times the span, rad.

    Each pair is fitted over the samples both have. The span is computed from the spread of those sample times
    (the first-to-last distance for evenly spaced samples), so it stays fair when some are lost.

    The sums run in a compiled loop per pair (_drift_rows), not as BLAS products: on 2 cores shared with other work,
    OpenBLAS's threads made the six 394 x 240 x 394 products of GBnetwork take 0.25 s instead of 0.05 s.

    Args:
        angles: Rotor angles, rad, shape (n_generators, n_samples), on one time grid; NaN = lost.
        per_sample: Return the slope itself, rad per sample: a rate, which unlike the drift does not grow with
            the span, so two stretches of one window compare fairly whatever their sample counts.

    Returns:
        Antisymmetric (n, n) matrix: drift of delta_p - delta_q, rad, or its rate, rad per sample (0 where a pair
        shares < 2 samples).

    """
    drift, rate, _ = _drift_and_rate(angles)
    return rate if per_sample else drift


def _drift_and_rate(angles: np.ndarray, half: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return pair_drift_rad's drift and rate matrices, and the rate over samples half .. end, from one pass.

    The latest rate is bit for bit pair_drift_rad(angles[:, half:], per_sample=True): its sums run over the same
    samples in the same order, time counted from the half. half=None leaves it zero.
    """
    angles = np.ascontiguousarray(angles, dtype=np.float64)
    drift = np.zeros((angles.shape[0], angles.shape[0]))
    rate, latest = np.zeros_like(drift), np.zeros_like(drift)
    _drift_rows(angles, angles.shape[1] if half is None else half, drift, rate, latest)
    return drift, rate, latest


@numba.njit(cache=True)
def _slope(count, sx, sxx, sd, sxd):
    """Least-squares slope and its first-to-last drift from the sums (0, 0 below two samples or no spread)."""
    if count < 2.0:
        return 0.0, 0.0, False
    var_x = sxx - sx * sx / count
    if not var_x > 0.0:
        return 0.0, 0.0, False
    slope = (sxd - sx * sd / count) / var_x
    # First-to-last distance of count evenly spaced samples, from their spread, so lost samples leave it fair.
    return slope, slope * np.sqrt(12.0 * var_x / count * (count - 1.0) / (count + 1.0)), True


@numba.njit(cache=True)
def _drift_rows(angles, half, drift, rate, latest):
    """pair_drift_rad's drift and rate of every pair p < q into [p, q], and 0 - them into [q, p] (time in samples).

    latest receives the rate over samples half .. m - 1, time counted from half. [q, p] is what subtracting the
    transpose of a strict upper triangle gave, the former way, 0.0 - x.
    """
    n, m = angles.shape
    finite = np.empty((n, m), dtype=np.bool_)
    for p in range(n):
        for t in range(m):
            finite[p, t] = np.isfinite(angles[p, t])
    for p in range(n):
        for q in range(p + 1, n):
            count, sx, sxx, sd, sxd = 0.0, 0.0, 0.0, 0.0, 0.0
            count2, sx2, sxx2, sd2, sxd2 = 0.0, 0.0, 0.0, 0.0, 0.0
            for t in range(m):
                if finite[p, t] and finite[q, t]:
                    d = angles[p, t] - angles[q, t]
                    count += 1.0
                    sx += t
                    sxx += t * t
                    sd += d
                    sxd += t * d
                    if t >= half:
                        u = t - half
                        count2 += 1.0
                        sx2 += u
                        sxx2 += u * u
                        sd2 += d
                        sxd2 += u * d
            slope, span, ok = _slope(count, sx, sxx, sd, sxd)
            if ok:
                rate[p, q], drift[p, q] = slope, span
                rate[q, p], drift[q, p] = 0.0 - slope, 0.0 - span
            slope, span, ok = _slope(count2, sx2, sxx2, sd2, sxd2)
            if ok:
                latest[p, q], latest[q, p] = slope, 0.0 - slope


@dataclass
class Evidence:
    """What a rule may look at, computed once per window by DTWCoherency.

    Attributes:
        rms_of: mask -> RMS angle difference along the optimal warping path, rad, (n, n), computed at least for
            the pairs of the boolean mask (None: all) and NaN where not computed. DTW is most of a window's cost,
            so a rule asks only for the pairs its answer depends on.
        angles_rad: The window's rotor angles on one time grid, rad, (n, n_samples), NaN = lost.
        max_groups: Largest k a rule may choose (it is also capped at the number of generators).
        cluster: k -> PAM labels on rms_rad (cached by the caller).

    """

    rms_of: Callable[[np.ndarray | None], np.ndarray]
    angles_rad: np.ndarray
    max_groups: int
    cluster: Callable[[int], np.ndarray]
    _drift: np.ndarray | None = field(default=None, repr=False)
    _rate: np.ndarray | None = field(default=None, repr=False)
    _latest: np.ndarray | None = field(default=None, repr=False)

    @property
    def n(self) -> int:
        """Return the number of generators."""
        return len(self.angles_rad)

    @property
    def rms_rad(self) -> np.ndarray:
        """Return the RMS matrix of every pair, rad, (n, n)."""
        return self.rms_of(None)

    @property
    def candidates(self) -> range:
        """Return the k > 1 a rule may pick: 2 .. min(max_groups, n)."""
        return range(2, min(self.max_groups, self.n) + 1)

    @property
    def drift_rad(self) -> np.ndarray:
        """Return pair_drift_rad of the window (computed on first use)."""
        self._measure_drift()
        return self._drift

    @property
    def rate_rad_per_sample(self) -> np.ndarray:
        """Return pair_drift_rad(per_sample=True) of the window (computed with drift_rad)."""
        self._measure_drift()
        return self._rate

    @property
    def latest_rate_rad_per_sample(self) -> np.ndarray:
        """Return pair_drift_rad(per_sample=True) of the latest half of the window (samples m // 2 on)."""
        self._measure_drift()
        return self._latest

    def _measure_drift(self) -> None:
        if self._drift is None:
            self._drift, self._rate, self._latest = _drift_and_rate(self.angles_rad, self.angles_rad.shape[1] // 2)


def _one_group(n: int) -> np.ndarray:
    return np.zeros(n, dtype=int)


def _best_silhouette(ev: Evidence, ks, scores: dict) -> int | None:
    """Return the k among ks with the best silhouette (ties to fewer groups), recording scores."""
    best = None
    for k in ks:
        scores.setdefault('silhouette', {})[k] = s = silhouette(ev.rms_rad, ev.cluster(k))
        if best is None or s > scores['silhouette'][best]:
            best = k
    return best


def pair_runaway(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return which pairs run away from a rest state at the window's start, and how far they have moved, rad.

    Each pair is taken over the samples both have. Its reference is the mean of delta_p - delta_q over the
    first quarter of those samples, and the pair counts as starting at rest when it moves less than an eighth
    of its deviation at the end within that quarter (a window that begins before the disturbance). A pair at rest
    to begin with runs away when its deviation from the reference at the end is
    - at least pi rad: it has slipped a pole against its pre-disturbance angle, the truth's own test, or
    - at least pi / 2 rad and it is still moving away without slowing down: over the latest quarter of that
      deviation it is not decelerating (the least-squares parabola through those samples curves away from the
      reference, or is straight), and it never went past its present deviation since the half-way mark (a swing
      that turned back and returned is not running away). With fewer than three samples in that quarter (crossed
      within a frame or two), it must have covered it at least as fast as the quarter before it.
      The test looks at the latest quarter alone because the quarter before can hold the fault-on motion and the
      clearing frame's step in the estimated angle, both faster than any motion after clearing: compared with
      them, a pair accelerating after clearing read as slowing down (PSS/E IEEE 14, G1 against G2 at the request:
      107 deg from rest, its speed growing from 0.04 to 0.105 rad per frame since clearing, one frame of 0.30 rad
      at clearing in the quarter before).
    Equal-area: after a disturbance is cleared a pair that will come back decelerates as it moves away from its
    equilibrium; one past its unstable equilibrium accelerates away. A stable swing moves less than pi / 2 from
    where it started on its accelerating side. The timing test compares sample counts, so it needs no time unit.

    Each pair's test is a loop over its samples, compiled by numba (_runaway_rows): 0.15 s on GBnetwork's 394
    machines, where the former numpy version, a pass over all pairs per generator, took 1 to 2 s (threads would
    save another 0.07 s idle, nothing on a loaded machine, and cost seconds of compilation). The reference is
    summed in numpy's pairwise order, so every figure is bit for bit the former version's.

    Args:
        angles: Rotor angles, rad, shape (n_generators, n_samples), on one time grid; NaN = lost.

    Returns:
        (runaway, deviation): symmetric (n, n) bool and float matrices; deviation is |delta_pq(end) - reference|,
        rad, for pairs at rest at the start, else 0.

    """
    angles = np.ascontiguousarray(angles, dtype=np.float64)
    n, m = angles.shape
    runaway = np.zeros((n, n), dtype=bool)
    deviation = np.zeros((n, n))
    _runaway_rows(angles, runaway, deviation)
    # delta_q - delta_p is -(delta_p - delta_q) sample by sample, so the test of (q, p) is that of (p, q) exactly.
    runaway |= runaway.T
    deviation += deviation.T
    return runaway, deviation


@numba.njit(cache=True)
def _block_sum(x, lo, count):
    """Sum of up to 128 values as numpy adds them: 8 accumulators, then the rest in order."""
    if count < 8:
        res = -0.0
        for i in range(lo, lo + count):
            res += x[i]
        return res
    r0, r1, r2, r3, r4, r5, r6, r7 = x[lo], x[lo + 1], x[lo + 2], x[lo + 3], x[lo + 4], x[lo + 5], x[lo + 6], x[lo + 7]
    i = lo + 8
    while i < lo + count - count % 8:
        r0, r1, r2, r3 = r0 + x[i], r1 + x[i + 1], r2 + x[i + 2], r3 + x[i + 3]
        r4, r5, r6, r7 = r4 + x[i + 4], r5 + x[i + 5], r6 + x[i + 6], r7 + x[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < lo + count:
        res += x[i]
        i += 1
    return res


@numba.njit(cache=True)
def _pairwise_sum(x):
    """Sum x in numpy's order (halves split at a multiple of 8, blocks of up to 128), bit for bit.

    numpy recurses; numba's cache mishandles a recursive function called from a parallel one, so the halves are
    walked with a stack instead (post-order: left half, right half, then their sum).
    """
    los, counts, states = np.zeros(64, np.int64), np.zeros(64, np.int64), np.zeros(64, np.int64)
    values = np.zeros(64)
    top, held = 0, 0
    los[0], counts[0] = 0, x.shape[0]
    while top >= 0:
        lo, count, state = los[top], counts[top], states[top]
        if count <= 128 or state == 2:
            if count <= 128:
                values[held] = _block_sum(x, lo, count)
                held += 1
            else:
                held -= 1
                values[held - 1] = values[held - 1] + values[held]
            top -= 1
            continue
        half = count // 2
        half -= half % 8
        states[top] = state + 1
        top += 1
        los[top], counts[top], states[top] = (lo, half, 0) if state == 0 else (lo + half, count - half, 0)
    return values[0]


@numba.njit(cache=True)
def _runaway_rows(angles, runaway, deviation):
    """pair_runaway's test of every pair (p, q > p), into the upper triangles."""
    n, m = angles.shape
    diff, quarter_diff = np.empty(m), np.empty(m)
    both = np.empty(m, dtype=np.bool_)
    finite = np.empty((n, m), dtype=np.bool_)
    for p in range(n):
        for t in range(m):
            finite[p, t] = np.isfinite(angles[p, t])
    for p in range(n):
        for q in range(p + 1, n):
            count, first, last = 0, -1, -1
            for t in range(m):
                ok = finite[p, t] and finite[q, t]
                both[t] = ok
                diff[t] = angles[p, t] - angles[q, t] if ok else 0.0
                if ok:
                    count += 1
                    last = t
                    if first < 0:
                        first = t
            if count < 4:
                continue
            end_quarter = first + (last - first) // 4
            in_quarter, high, low = 0, -np.inf, np.inf
            for t in range(m):
                inside = both[t] and t <= end_quarter
                quarter_diff[t] = diff[t] if inside else 0.0
                if inside:
                    in_quarter += 1
                    high = max(high, diff[t])
                    low = min(low, diff[t])
            ref = _pairwise_sum(quarter_diff) / in_quarter
            end = diff[last]
            dev = abs(end - ref)
            if not high - low <= dev / 8:  # not at rest over the first quarter
                continue
            deviation[p, q] = dev
            if dev >= np.pi:
                runaway[p, q] = True
                continue
            if not dev >= np.pi / 2:
                continue
            # Progress from the reference towards the end value, rad: the last samples at a half and at three
            # quarters of the deviation, and whether it went past the end's deviation after the half-way mark.
            way = np.sign(end - ref)
            half, three_q = -1, -1
            for t in range(m):
                if both[t]:
                    progress = way * (diff[t] - ref)
                    if progress <= dev / 2:
                        half = t
                    if progress <= 0.75 * dev:
                        three_q = t
            overshot = False
            for t in range(max(half, 0), m):
                if both[t] and way * (diff[t] - ref) > dev:
                    overshot = True
            runaway[p, q] = not overshot and _not_slowing(diff, both, way, half, three_q, last)


@numba.njit(cache=True)
def _not_slowing(diff, both, way, half, three_q, last):
    """Whether a pair is not decelerating over the latest quarter of its deviation (samples three_q .. last).

    The sign of the least-squares parabola's curvature through those samples (time centred on their mean, so the
    normal equations stay well conditioned); by Cramer's rule it is the sign of one determinant, the Gram matrix's
    own being positive. Fewer than three samples: that quarter took no longer than the quarter before it.
    """
    count, mean = 0, 0.0
    for t in range(three_q, last + 1):
        if both[t]:
            count += 1
            mean += t
    if count < 3:
        return last - three_q <= three_q - half
    mean /= count
    s0, s2, s3, s4, y0, y1, y2 = float(count), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for t in range(three_q, last + 1):
        if both[t]:
            x = t - mean
            y = way * diff[t]
            s2 += x * x
            s3 += x * x * x
            s4 += x * x * x * x
            y0 += y
            y1 += x * y
            y2 += x * x * y
    # Normal equations [[s4, s3, s2], [s3, s2, 0], [s2, 0, s0]] (a, b, c) = (y2, y1, y0): a's numerator.
    numerator = y2 * (s2 * s0) - s3 * (y1 * s0) + s2 * (-y0 * s2)
    return numerator >= 0.0


class SeparationRule:
    """Split generators whose angle difference is heading for a pole slip (see the module docstring).

    Args:
        horizon_windows: How far ahead the window's mean rate is projected, in windows. A pair separates when
            |drift| * (1 + horizon_windows) >= pi rad.

    Attributes:
        scores_: 'bar_rad' (the |drift| bar), 'max_drift_rad', 'max_deviation_rad' (from rest, pair_runaway),
            'separating_pairs', and 'merged_beyond_max_groups' when the groups needed outnumber max_groups.

    """

    name = 'separation'

    def __init__(self, horizon_windows: float = 1.0) -> None:
        self.horizon_windows = horizon_windows

    def separating(self, ev: Evidence) -> np.ndarray:
        """Return the symmetric (n, n) matrix of separating pairs, recording what was measured in scores_."""
        if not self.horizon_windows >= 0:
            raise KRuleError(f'horizon_windows must be >= 0, got {self.horizon_windows}')
        bar = np.pi / (1.0 + self.horizon_windows)
        drift = np.abs(ev.drift_rad)
        rate = ev.rate_rad_per_sample
        latest = ev.latest_rate_rad_per_sample
        # Not slowing down: over the latest half of the window the pair moves on, the same way, at least at the
        # window's mean rate. Rates, not drifts: the latest half spans (n - 1) // 2 of an even count's n - 1 sample
        # steps, and a pair whose first samples are lost spans less than the window, so a doubled drift over the
        # half read a steady pair as slowing down in the one case and a slowing one as steady in the other.
        steady = (np.sign(latest) == np.sign(rate)) & (np.abs(latest) >= np.abs(rate))
        runaway, deviation = pair_runaway(ev.angles_rad)
        separating = (drift >= np.pi) | ((drift >= bar) & steady) | runaway
        np.fill_diagonal(separating, False)
        self.scores_: dict = {'bar_rad': bar, 'max_drift_rad': float(drift.max()) if drift.size else 0.0,
                              'max_deviation_rad': float(deviation.max()) if deviation.size else 0.0,
                              'separating_pairs': int(np.triu(separating, 1).sum())}
        return separating

    def choose(self, ev: Evidence) -> np.ndarray:
        """Return the groups (see the module docstring)."""
        separating = self.separating(ev)
        if ev.n < 2 or not separating.any():
            return _one_group(ev.n)
        forced = self._forced_groups(ev, separating)
        if forced is not None:
            return forced
        # A separating pair's r is never read: its distance below is set apart whatever r is.
        r = ev.rms_of(~separating)
        # Complete linkage of r in which a separating pair is farther apart than any other: cut below that
        # distance, every group is free of separating pairs and no two groups could merge without one.
        apart = 2.0 * float(np.max(r, where=~separating, initial=0.0)) + 1.0
        distance = np.where(separating, apart + np.abs(ev.drift_rad), r)
        np.fill_diagonal(distance, 0.0)
        tree = linkage(squareform(distance, checks=False), method='complete')
        labels = fcluster(tree, t=apart, criterion='distance')
        if labels.max() > ev.max_groups:
            # More groups than the caller takes: merge the groups that drift apart least first.
            self.scores_['merged_beyond_max_groups'] = int(labels.max())
            labels = fcluster(tree, t=ev.max_groups, criterion='maxclust')
        return canonical(labels)

    @staticmethod
    def _forced_groups(ev: Evidence, separating: np.ndarray) -> np.ndarray | None:
        """Return the groups the linkage in choose() forms whatever r is, or None when r decides them.

        When "not separating" is an equivalence relation (every machine is compatible with exactly the members of
        its own class, i.e. the separating pairs are all the pairs between classes: the usual shape of groups
        slipping apart), the constrained complete linkage forms exactly those classes, so no DTW is needed. Proof:
        a compatible pair's distance is r <= max r < apart and a separating pair's is apart + |drift| > apart.
        While a class is in two clusters of the linkage, those two are closer than apart, and every two clusters
        of different classes are farther, so the linkage completes each class (at heights below apart) before
        any merge across classes (above apart), and the cut at apart returns the classes. Ties among r move
        merges within a class only.

        Two guards keep it to where that holds in floating point, the linkage being taken otherwise:
        - as many classes as max_groups at most (beyond, the cap's merges are read off the tree);
        - apart + |drift| > apart for every separating pair. apart = 2 max r + 1 is not known without the DTW,
          but r <= 2 sqrt(2) R, R the widest range of one series in the window (after taking off a mean, two
          samples differ by at most range_p + range_q, and a warping path has fewer than 2 max(n_p, n_q) cells;
          block means stay within the range), so apart < 4 sqrt(2) R + 1, and |drift| above the spacing of floats
          at 8 R + 2 (rounding of r and apart included) suffices.
        """
        compatible = ~separating  # the diagonal is compatible: separating() clears it
        # Each machine's first compatible machine names its class if compatibility is an equivalence relation;
        # conversely, when "same first" is exactly "compatible", compatibility is the kernel of that map.
        first = compatible.argmax(axis=1)
        if not np.array_equal(first[:, None] == first[None, :], compatible):
            return None
        if len(np.unique(first)) > ev.max_groups:
            return None
        angles = ev.angles_rad
        widest = float(np.max(np.nanmax(angles, axis=1) - np.nanmin(angles, axis=1)))
        upper = np.spacing(8.0 * widest + 2.0)
        if not float(np.min(np.abs(ev.drift_rad)[separating])) > upper:
            return None
        return canonical(first)


class ThresholdRule:
    """The former rule: a fixed RMS coherence threshold (measured on IEEE 39 bags).

    k = 1 if every pair's r is below the threshold; else the k whose PAM clustering keeps every group within it,
    with the best silhouette; else complete-linkage clusters of r cut at it.

    Args:
        coherence_threshold_rad: Generators farther apart than this (RMS along the warping path, rad) never share
            a group.

    """

    name = 'threshold'

    def __init__(self, coherence_threshold_rad: float = 1.0) -> None:
        self.coherence_threshold_rad = coherence_threshold_rad

    def choose(self, ev: Evidence) -> np.ndarray:
        """Return the groups."""
        limit = self.coherence_threshold_rad
        if not limit > 0:
            raise KRuleError(f'coherence_threshold_rad must be > 0, got {limit}')
        r = ev.rms_rad
        self.scores_: dict = {'max_rms_rad': float(r.max()) if r.size else 0.0}
        if ev.n < 2 or r.max() < limit:
            return _one_group(ev.n)
        admissible = []
        for k in range(2, min(ev.max_groups, ev.n - 1) + 1):
            labels = ev.cluster(k)
            same = labels[:, None] == labels[None, :]
            if float(np.max(np.where(same, r, 0.0))) < limit:
                admissible.append(k)
        best = _best_silhouette(ev, admissible, self.scores_)
        if best is not None:
            return ev.cluster(best)
        return canonical(fcluster(linkage(squareform(r, checks=False), method='complete'), t=limit,
                                  criterion='distance'))


class EigengapRule:
    """k at the largest eigengap of a self-tuning affinity's normalised Laplacian (k = 1 allowed).

    Args:
        neighbour: Which nearest neighbour's distance sets each generator's scale (7 in the paper cited).

    """

    name = 'eigengap'

    def __init__(self, neighbour: int = 7) -> None:
        self.neighbour = neighbour

    def choose(self, ev: Evidence) -> np.ndarray:
        """Return the groups."""
        r, n = ev.rms_rad, ev.n
        self.scores_: dict = {}
        if n < 2 or r.max() <= 0.0:
            return _one_group(n)
        scale = np.sort(r, axis=1)[:, min(self.neighbour, n - 1)]
        # A generator identical to its neighbours gets the smallest non-zero scale, not a zero that divides.
        scale = np.maximum(scale, r[r > 0].min())
        affinity = np.exp(-r ** 2 / np.outer(scale, scale))
        np.fill_diagonal(affinity, 0.0)
        d = affinity.sum(axis=1)
        inv = 1.0 / np.sqrt(np.maximum(d, 1e-300))
        eig = np.sort(np.linalg.eigvalsh(np.eye(n) - inv[:, None] * affinity * inv[None, :]))
        top = min(ev.max_groups, n - 1)
        gaps = np.diff(eig[:top + 1])       # gaps[k - 1] = lambda_{k+1} - lambda_k
        self.scores_['eigengap'] = {k + 1: float(g) for k, g in enumerate(gaps)}
        k = int(np.argmax(gaps)) + 1
        return ev.cluster(k) if k > 1 else _one_group(n)


class GapStatisticRule:
    """Gap statistic on a classical-MDS embedding of r (k = 1 allowed).

    Args:
        n_references: Uniform reference sets drawn.
        random_state: Seed of the reference sets (the rule is deterministic for a given seed).

    """

    name = 'gap'

    def __init__(self, n_references: int = 20, random_state: int = 0) -> None:
        self.n_references = n_references
        self.random_state = random_state

    def choose(self, ev: Evidence) -> np.ndarray:
        """Return the groups."""
        import kmedoids

        r, n = ev.rms_rad, ev.n
        self.scores_: dict = {}
        if n < 3 or r.max() <= 0.0:
            return _one_group(n)
        centre = np.eye(n) - 1.0 / n
        vals, vecs = np.linalg.eigh(-0.5 * centre @ (r ** 2) @ centre)
        keep = vals > 1e-12 * vals.max()
        coords = vecs[:, keep] * np.sqrt(vals[keep])
        top = min(ev.max_groups, n - 1)

        def log_w(points: np.ndarray, labels_of: Callable[[int], np.ndarray]) -> np.ndarray:
            out = []
            for k in range(1, top + 2):
                labels = labels_of(k)
                w = sum(((points[labels == g] - points[labels == g].mean(axis=0)) ** 2).sum() for g in range(k))
                out.append(np.log(max(w, 1e-300)))
            return np.array(out)

        def pam(points: np.ndarray) -> Callable[[int], np.ndarray]:
            dist = np.sqrt(((points[:, None, :] - points[None, :, :]) ** 2).sum(axis=2))
            return lambda k: (np.zeros(n, dtype=int) if k == 1 else np.arange(n) if k == n else
                              np.asarray(kmedoids.pam(dist, k, init='build').labels, dtype=int))

        data = log_w(coords, lambda k: _one_group(n) if k == 1 else ev.cluster(k))
        rng = np.random.default_rng(self.random_state)
        lo, hi = coords.min(axis=0), coords.max(axis=0)
        refs = np.array([log_w(ref, pam(ref)) for ref in
                         (rng.uniform(lo, hi, size=coords.shape) for _ in range(self.n_references))])
        gap = refs.mean(axis=0) - data
        s = refs.std(axis=0) * np.sqrt(1.0 + 1.0 / self.n_references)
        self.scores_['gap'] = {k + 1: float(g) for k, g in enumerate(gap)}
        k = next((k for k in range(1, top + 1) if gap[k - 1] >= gap[k] - s[k]), top)
        return ev.cluster(k) if k > 1 else _one_group(n)


class SilhouetteRule:
    """The best-silhouette k, or "no split" when even that silhouette shows no reasonable structure.

    Args:
        min_silhouette: Least mean silhouette that counts as structure (0.5: Kaufman and Rousseeuw).

    """

    name = 'silhouette'

    def __init__(self, min_silhouette: float = 0.5) -> None:
        self.min_silhouette = min_silhouette

    def choose(self, ev: Evidence) -> np.ndarray:
        """Return the groups."""
        self.scores_: dict = {}
        if ev.n < 3 or ev.rms_rad.max() <= 0.0:
            return _one_group(ev.n)
        best = _best_silhouette(ev, range(2, min(ev.max_groups, ev.n - 1) + 1), self.scores_)
        if best is None or self.scores_['silhouette'][best] < self.min_silhouette:
            return _one_group(ev.n)
        return ev.cluster(best)


RULES = {rule.name: rule for rule in (SeparationRule, ThresholdRule, EigengapRule, GapStatisticRule,
                                      SilhouetteRule)}
DEFAULT_RULE = SeparationRule.name


def make_rule(rule):
    """Return a rule instance: a rule object as given, or a new one of the named class with its defaults.

    Raises:
        KRuleError: An unknown name, or an object without choose().

    """
    if isinstance(rule, str):
        if rule not in RULES:
            raise KRuleError(f'unknown k rule {rule!r}; known: {sorted(RULES)}')
        return RULES[rule]()
    if not callable(getattr(rule, 'choose', None)):
        raise KRuleError(f'a k rule needs a choose(evidence) method, got {rule!r}')
    return rule


# Compile (or load from numba's cache) the kernels now, at import: the coherency node imports this at start-up, so
# that its first request does not pay for it, and tools/setup.sh compiles them once for every later process.
pair_runaway(np.zeros((2, 4)))
pair_drift_rad(np.zeros((2, 4)))
