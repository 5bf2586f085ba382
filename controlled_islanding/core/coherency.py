"""Coherent generator groups from rotor angle trajectories by DTW (Algorithm 1, steps 2 to 4).

Reference: generators p and q are coherent when delta_p(t) - delta_q(t) stays about constant, so a constant
offset between two machines must not count. Each series has its own mean (over its valid samples) taken
off before DTW. The mean, unlike the first sample, stays a fair reference when the first second of every
PMU is lost or single frames are dropped at random: it is computed over whatever the window holds.

Time alignment: the series are taken to start at the same time tag and to share one time grid, NaN
marking a lost sample anywhere; a shorter series lost its end (or its last frames are not delivered yet).
When the series cover different spans (a PMU that fell silent early, joined late or lags), each pair is
compared over the span both cover, with means taken over that span. DTW's boundary condition pins both
ends of a path, so a series that stops a second early would otherwise be compared, end against end, with
machines that kept moving for that second. Lost samples inside the span are dropped, so the two series
of a pair still have unequal lengths, which DTW handles.

Dissimilarity: DTW (eq. 3, rad^2) grows with the number of samples, so groups are formed on the RMS angle
difference along the optimal warping path, r_pq = sqrt(DTW_pq / max(n_p, n_q)) in rad, with n the valid
samples of each series. It is comparable across window lengths and PMU rates, and so with ``decimate``, which
runs DTW on block means (a low-pass filter that keeps the swings under 2 Hz) while the k rule reads every sample.

Choosing k, and whether to split at all: a rule from core/k_rules.py, named by ``k_rule``. The default,
``separation``, splits generators whose angle difference is heading for a pole slip (pi rad), by its trend
over the window or by its runaway from a rest state at the window's start; it needs no threshold measured on
one system, and forms its groups by complete linkage of r with the separating pairs kept apart, so k is what
the data need (max_groups only caps it). The former fixed 1.0 rad RMS threshold, calibrated on IEEE 39 bags, is
the ``threshold`` rule. docs/coherency_rules.md compares the rules on every scenario bag.

Grouping for a fixed k, and for the rules that choose k alone (threshold, eigengap, gap, silhouette): k-medoids
(PAM, BUILD initialisation, so deterministic) on the precomputed r matrix. k-means needs coordinates and a
mean, which a DTW matrix does not have; PAM is the paper's step-9 algorithm too. Groups are numbered in order
of their first generator.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from controlled_islanding.core.dtw import clean_series, dtw_distance, dtw_distance_matrix
from controlled_islanding.core.k_rules import DEFAULT_RULE, Evidence, KRuleError, canonical, make_rule, silhouette

__all__ = ['CoherencyError', 'DTWCoherency', 'block_means', 'decimation_factor', 'frame_period_s', 'silhouette',
           'warm_up']


class CoherencyError(ValueError):
    """Series or settings the coherency estimator cannot use."""


def block_means(grid: np.ndarray, size: int) -> np.ndarray:
    """Return the mean of each block of ``size`` samples along the last axis, lost (NaN) samples left out.

    A block with no valid sample is NaN; the last block may be shorter. A block mean is a moving average sampled
    once a block: its gain at frequency f is |sin(pi f T) / (pi f T)| for a block of T s, 0.94 at 2 Hz for the
    10 frames/s blocks of a 60 frames/s stream, where inter-area modes lie (0.1 to 2 Hz).
    """
    if size < 1:
        raise CoherencyError(f'decimate must be a whole number >= 1, got {size}')
    grid = np.asarray(grid, dtype=float)
    pad = -grid.shape[-1] % size
    padded = np.concatenate([grid, np.full((*grid.shape[:-1], pad), np.nan)], axis=-1)
    blocks = padded.reshape(*grid.shape[:-1], -1, size)
    valid = ~np.isnan(blocks)
    count = valid.sum(axis=-1)
    total = np.where(valid, blocks, 0.0).sum(axis=-1)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def decimation_factor(t_s: np.ndarray | Sequence[float], target_fps: float) -> int:
    """Return the block size that brings samples with time tags t_s (s) down to about target_fps (at least 1).

    The stream's own spacing (the median step between tags) decides, not a nominal rate: a 30 frames/s stream
    under a 60 frames/s setting gets half the factor.
    """
    period_s = frame_period_s(t_s)
    if not target_fps > 0 or period_s == 0.0:
        return 1
    return max(1, int(round(1.0 / (target_fps * period_s))))


def frame_period_s(t_s: np.ndarray | Sequence[float]) -> float:
    """Return a stream's frame period, s: the median step between increasing time tags t_s (0.0 with none).

    The median, so that a lost frame (a step of two periods) or a gap does not lengthen it.
    """
    steps = np.diff(np.asarray(t_s, dtype=float))
    steps = steps[steps > 0]
    return float(np.median(steps)) if steps.size else 0.0


def _on_one_grid(series: Sequence[np.ndarray]) -> np.ndarray:
    """Return the series start-aligned on one time grid, (n, longest length), NaN past a shorter one's end.

    Raises DTWError as clean_series does for the first series it would refuse; equal lengths (every window of
    the coherency node) are checked as one array.
    """
    arrays = [np.asarray(x, dtype=float) for x in series]
    length = max(len(x) if x.ndim == 1 else 0 for x in arrays)
    if all(x.ndim == 1 and len(x) == length for x in arrays):
        grid = np.array(arrays)
        bad = np.isinf(grid).any(axis=1) | np.isnan(grid).all(axis=1)
        if not bad.any():
            return grid
        arrays = arrays[:int(np.argmax(bad)) + 1]
    for i, x in enumerate(arrays):
        clean_series(x, f'series {i}')
    return np.array([np.concatenate([x, np.full(length - len(x), np.nan)]) for x in arrays])


class _PairDistances:
    """DTW (rad^2) and RMS (rad) matrices of mean-referenced series, computed pair by pair as asked (see module doc).

    ``grid`` holds the series on one time grid, (n, longest length), rad, NaN where lost or past a series' end:
    what the k rule reads. DTW runs on the same grid, or on its block means of ``decimate`` samples (the band
    divided alike, rounded up). The matrices hold NaN at pairs not computed yet.
    """

    def __init__(self, series: Sequence[np.ndarray], window: int | None, decimate: int = 1) -> None:
        self.grid = _on_one_grid(series)
        on = block_means(self.grid, decimate) if decimate > 1 else self.grid
        self.window = window if window is None or decimate == 1 else -(-window // decimate)
        self.on_grid = on
        self._clean: list[np.ndarray] | None = None
        n = len(series)
        valid = ~np.isnan(on)
        self.first = valid.argmax(axis=1)
        self.last = valid.shape[1] - 1 - valid[:, ::-1].argmax(axis=1)
        self.same_span = len(set(self.first.tolist())) == 1 and len(set(self.last.tolist())) == 1
        self.dtw = np.full((n, n), np.nan)
        self.rms = np.full((n, n), np.nan)
        np.fill_diagonal(self.dtw, 0.0)
        np.fill_diagonal(self.rms, 0.0)

    @property
    def clean(self) -> list[np.ndarray]:
        """Return each series' valid samples (of the block means with ``decimate``): what DTW aligns."""
        if self._clean is None:
            self._clean = [np.ascontiguousarray(row[~np.isnan(row)]) for row in self.on_grid]
        return self._clean

    def rms_rad(self, pairs: np.ndarray | None = None) -> np.ndarray:
        """Return the RMS matrix with at least the pairs of the boolean mask ``pairs`` (None: all) computed."""
        wanted = np.isnan(self.rms) if pairs is None else np.isnan(self.rms) & np.asarray(pairs, dtype=bool)
        wanted = np.triu(wanted | wanted.T, 1)
        if not wanted.any():
            return self.rms
        if self.same_span:
            centred = [c - c.mean() for c in self.clean]
            dtw = dtw_distance_matrix(centred, window=self.window, pairs=wanted)
            lengths = np.array([len(c) for c in self.clean], dtype=float)
            rms = np.sqrt(dtw / np.maximum.outer(lengths, lengths))
            done = wanted | wanted.T
            self.dtw[done], self.rms[done] = dtw[done], rms[done]
            return self.rms
        # Different spans: each pair over the span both cover.
        for p, q in zip(*np.nonzero(wanted), strict=True):
            lo, hi = max(self.first[p], self.first[q]), min(self.last[p], self.last[q])
            a, b = self.on_grid[p][lo:hi + 1], self.on_grid[q][lo:hi + 1]
            a, b = a[~np.isnan(a)], b[~np.isnan(b)]
            if min(len(a), len(b)) < 2:
                a, b = self.clean[p], self.clean[q]
            self.dtw[p, q] = self.dtw[q, p] = dtw_distance(a - a.mean(), b - b.mean(), self.window)
            self.rms[p, q] = self.rms[q, p] = np.sqrt(self.dtw[p, q] / max(len(a), len(b)))
        return self.rms


class DTWCoherency:
    """Group generators whose rotor angles swing together, by DTW.

    Args:
        n_groups: Fixed number of groups, or None to let ``k_rule`` choose it.
        max_groups: Largest k a rule may choose (the default rule finds k itself; this only caps it).
        window: Sakoe-Chiba half-width in samples for DTW, or None for none.
        k_rule: Name of a rule in core.k_rules.RULES, or a rule instance (its settings in its constructor).
        random_state: Passed to k-medoids (BUILD initialisation makes it irrelevant; kept for the API).
        decimate: DTW on block means of this many samples (1: every sample), the band divided alike; the k rule
            still reads every sample. Inter-area swings lie under 2 Hz, so 10 frames/s keeps them (block_means);
            DTW's cost falls with the square of the factor. docs/benchmarks.md measures what it changes.
        all_pairs: Compute DTW for every pair. By default only the pairs the grouping reads are computed: none
            when the rule finds no split (the separation rule decides that from the angles alone), and not the
            separating pairs, which it keeps apart whatever their distance. The groups are the same either way.

    Attributes:
        labels_: Group of each generator, 0-based, numbered in order of first member.
        n_groups_: Number of groups chosen.
        distance_matrix_: DTW distances, eq. 3, rad^2; NaN at pairs not computed (see ``all_pairs``).
        rms_distance_rad_: The r matrix groups are formed on, rad; NaN where distance_matrix_ is.
        rule_: The rule instance used (its scores_ say what it measured); None when n_groups is fixed.
        silhouette_: Mean silhouette per k the rule scored (k -> score); empty when it scored none.

    """

    def __init__(self, n_groups: int | None = None, max_groups: int = 8, window: int | None = None,
                 k_rule=DEFAULT_RULE, random_state: int = 0, decimate: int = 1, all_pairs: bool = False) -> None:
        self.n_groups = n_groups
        self.max_groups = max_groups
        self.window = window
        self.k_rule = k_rule
        self.random_state = random_state
        self.decimate = decimate
        self.all_pairs = all_pairs

    def fit(self, series: Sequence[np.ndarray]) -> DTWCoherency:
        """Find the coherent groups.

        Args:
            series: One 1-D rotor angle array (rad) per generator; NaN = lost sample; lengths may differ.

        Returns:
            self.

        Raises:
            CoherencyError: No series, a bad setting (unknown rule included), or n_groups larger than the number
                of generators.
            DTWError: A series with no valid sample.

        """
        n = len(series)
        if n == 0:
            raise CoherencyError('no rotor angle series given')
        if self.n_groups is not None and not 1 <= self.n_groups <= n:
            raise CoherencyError(f'n_groups must be in 1 .. {n} (the number of generators), got {self.n_groups}')
        if self.max_groups < 2:
            raise CoherencyError(f'max_groups must be >= 2, got {self.max_groups}')
        try:
            rule = None if self.n_groups is not None else make_rule(self.k_rule)
        except KRuleError as exc:
            raise CoherencyError(str(exc)) from exc
        if int(self.decimate) != self.decimate or self.decimate < 1:
            raise CoherencyError(f'decimate must be a whole number >= 1, got {self.decimate!r}')
        pairs = _PairDistances(series, self.window, int(self.decimate))
        if self.all_pairs:
            pairs.rms_rad()
        cache: dict[int, np.ndarray] = {}

        def cluster(k: int) -> np.ndarray:
            if k not in cache:
                cache[k] = self._cluster(pairs.rms_rad, n, k)
            return cache[k]

        if rule is None:
            labels = cluster(self.n_groups)
        else:
            try:
                labels = rule.choose(Evidence(pairs.rms_rad, pairs.grid, self.max_groups, cluster))
            except KRuleError as exc:
                raise CoherencyError(str(exc)) from exc
        self.distance_matrix_, self.rms_distance_rad_ = pairs.dtw, pairs.rms
        self.rule_ = rule
        self.silhouette_: dict[int, float] = dict(getattr(rule, 'scores_', {}).get('silhouette', {}))
        self.labels_ = canonical(labels)
        self.n_groups_ = int(self.labels_.max()) + 1
        return self

    def _cluster(self, rms_rad, n: int, k: int) -> np.ndarray:
        if k == 1:
            return np.zeros(n, dtype=int)
        if k == n:
            return np.arange(n)
        # Imported here: kmedoids imports scikit-learn, 2 s of CPU at every node start, and the default rule never
        # clusters by PAM.
        import kmedoids

        result = kmedoids.pam(rms_rad(), k, init='build', random_state=self.random_state)
        return canonical(np.asarray(result.labels, dtype=int))


def warm_up(max_groups: int = 8, window: int | None = None, k_rule: str = DEFAULT_RULE, samples: int = 30) -> None:
    """Group a made-up window once and compute its DTW matrix, so that every engine a real window runs is loaded.

    numba loads a compiled engine on its first call (1-5 s on the shared 2-core machine; compiling it, where the
    cache is cold, longer). The made-up split, two groups one slipping a pole, is decided by the k rule's drift
    alone, before any distance: the fit loads the rule's engine but not the DTW one, which the first real window
    then loaded while a request waited (the chaos sweep's first run, from a checkout with a cold cache: its
    decision came 0.45 s late, where the others took 0.07 s).
    """
    ramp = np.linspace(0.0, 2.0 * np.pi, samples)
    series = [ramp * (i % 2) for i in range(max_groups + 2)]
    DTWCoherency(max_groups=max_groups, window=window, k_rule=k_rule).fit(series)
    dtw_distance_matrix(series, window=window)
