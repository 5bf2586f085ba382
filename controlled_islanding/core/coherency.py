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
samples of each series. It is comparable across window lengths and PMU rates.

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

import kmedoids
import numpy as np

from controlled_islanding.core.dtw import clean_series, dtw_distance, dtw_distance_matrix
from controlled_islanding.core.k_rules import DEFAULT_RULE, Evidence, KRuleError, canonical, make_rule, silhouette

__all__ = ['CoherencyError', 'DTWCoherency', 'silhouette']


class CoherencyError(ValueError):
    """Series or settings the coherency estimator cannot use."""


def _distances(series: Sequence[np.ndarray], window: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the DTW matrix (rad^2) of mean-referenced series, the RMS matrix r (rad), and the series on one grid.

    The third is (n, longest length), rad, NaN where lost or past a series' end; see the module doc.
    """
    clean = [clean_series(x, f'series {i}') for i, x in enumerate(series)]
    n = len(clean)
    # Start-aligned on one time grid: a shorter series lost its end (or it is not delivered yet).
    length = max(len(x) for x in series)
    arrays = [np.concatenate([np.asarray(x, dtype=float), np.full(length - len(x), np.nan)]) for x in series]
    valid = ~np.isnan(np.array(arrays))
    first = valid.argmax(axis=1)
    last = valid.shape[1] - 1 - valid[:, ::-1].argmax(axis=1)
    if len(set(first.tolist())) == 1 and len(set(last.tolist())) == 1:
        centred = [c - c.mean() for c in clean]
        dtw = dtw_distance_matrix(centred, window=window)
        lengths = np.array([len(c) for c in clean], dtype=float)
        return dtw, np.sqrt(dtw / np.maximum.outer(lengths, lengths)), np.array(arrays)
    # Different spans: each pair over the span both cover.
    dtw, rms = np.zeros((n, n)), np.zeros((n, n))
    for p in range(n):
        for q in range(p + 1, n):
            lo, hi = max(first[p], first[q]), min(last[p], last[q])
            a, b = arrays[p][lo:hi + 1], arrays[q][lo:hi + 1]
            a, b = a[~np.isnan(a)], b[~np.isnan(b)]
            if min(len(a), len(b)) < 2:
                a, b = clean[p], clean[q]
            dtw[p, q] = dtw[q, p] = dtw_distance(a - a.mean(), b - b.mean(), window)
            rms[p, q] = rms[q, p] = np.sqrt(dtw[p, q] / max(len(a), len(b)))
    return dtw, rms, np.array(arrays)


class DTWCoherency:
    """Group generators whose rotor angles swing together, by DTW.

    Args:
        n_groups: Fixed number of groups, or None to let ``k_rule`` choose it.
        max_groups: Largest k a rule may choose (the default rule finds k itself; this only caps it).
        window: Sakoe-Chiba half-width in samples for DTW, or None for none.
        k_rule: Name of a rule in core.k_rules.RULES, or a rule instance (its settings in its constructor).
        random_state: Passed to k-medoids (BUILD initialisation makes it irrelevant; kept for the API).

    Attributes:
        labels_: Group of each generator, 0-based, numbered in order of first member.
        n_groups_: Number of groups chosen.
        distance_matrix_: DTW distances, eq. 3, rad^2.
        rms_distance_rad_: The r matrix groups are formed on, rad.
        rule_: The rule instance used (its scores_ say what it measured); None when n_groups is fixed.
        silhouette_: Mean silhouette per k the rule scored (k -> score); empty when it scored none.

    """

    def __init__(self, n_groups: int | None = None, max_groups: int = 8, window: int | None = None,
                 k_rule=DEFAULT_RULE, random_state: int = 0) -> None:
        self.n_groups = n_groups
        self.max_groups = max_groups
        self.window = window
        self.k_rule = k_rule
        self.random_state = random_state

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
        self.distance_matrix_, self.rms_distance_rad_, angles = _distances(series, self.window)
        cache: dict[int, np.ndarray] = {}

        def cluster(k: int) -> np.ndarray:
            if k not in cache:
                cache[k] = self._cluster(self.rms_distance_rad_, k)
            return cache[k]

        if rule is None:
            labels = cluster(self.n_groups)
        else:
            try:
                labels = rule.choose(Evidence(self.rms_distance_rad_, angles, self.max_groups, cluster))
            except KRuleError as exc:
                raise CoherencyError(str(exc)) from exc
        self.rule_ = rule
        self.silhouette_: dict[int, float] = dict(getattr(rule, 'scores_', {}).get('silhouette', {}))
        self.labels_ = canonical(labels)
        self.n_groups_ = int(self.labels_.max()) + 1
        return self

    def _cluster(self, r: np.ndarray, k: int) -> np.ndarray:
        if k == 1:
            return np.zeros(len(r), dtype=int)
        if k == len(r):
            return np.arange(len(r))
        result = kmedoids.pam(r, k, init='build', random_state=self.random_state)
        return canonical(np.asarray(result.labels, dtype=int))
