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

Coherence threshold: two generators farther apart than ``coherence_threshold_rad`` (default 1.0 rad,
57 deg) are not coherent and never share a group; closer ones may. It mirrors the truth rule (a pole slip,
relative drift past pi rad, separates two machines) with a margin for the stable swings. Measured on SIM's
bags with 3 s windows and a 30-sample band: coherent pairs reach at most 0.56 rad (the paper's case 1,
stable, peak spread about 85 deg); a slipping machine's r against the rest passes 1 rad once its drift in
the window reaches about 250 to 330 deg, i.e. 0.25 to 0.5 s after the truth rule's pi crossing, and is
over 4 rad a second later. A lower threshold detects earlier at the cost of that margin.

Choosing k:
- k = 1 ("no split") when every pair is within the threshold.
- Otherwise the k in 2 .. max_groups whose k-medoids clustering keeps every group within the threshold
  and has the highest mean silhouette (Rousseeuw 1987) on the precomputed r matrix. The paper's
  "minimising inter-coherent group distances" [23] alone always prefers more groups; the silhouette weighs
  each generator's distance to its own group against the nearest other group, works on any precomputed
  dissimilarity, and is the standard index for k-medoids. It is undefined for k = 1, hence the threshold.
- If no such k exists, complete-linkage clusters cut at the threshold (every group within it, as few
  groups as the linkage finds; may exceed max_groups).

Grouping: k-medoids (PAM, BUILD initialisation, so deterministic) on the precomputed r matrix. k-means
needs coordinates and a mean, which a DTW matrix does not have; PAM is the paper's step-9 algorithm too.
Groups are numbered in order of their first generator.
"""

from __future__ import annotations

from collections.abc import Sequence

import kmedoids
import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

from controlled_islanding.core.dtw import clean_series, dtw_distance, dtw_distance_matrix


class CoherencyError(ValueError):
    """Series or settings the coherency estimator cannot use."""


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


def _diameter(r: np.ndarray, labels: np.ndarray) -> float:
    """Return the largest distance between two members of one group."""
    same = labels[:, None] == labels[None, :]
    return float(np.max(np.where(same, r, 0.0)))


def _distances(series: Sequence[np.ndarray], window: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Return the DTW matrix (rad^2) of mean-referenced series and the RMS matrix r (rad); see the module doc."""
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
        return dtw, np.sqrt(dtw / np.maximum.outer(lengths, lengths))
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
    return dtw, rms


def _canonical(labels: np.ndarray) -> np.ndarray:
    """Renumber groups in order of their first member."""
    order: dict[int, int] = {}
    for lab in labels.tolist():
        order.setdefault(lab, len(order))
    return np.array([order[lab] for lab in labels.tolist()], dtype=int)


class DTWCoherency:
    """Group generators whose rotor angles swing together, by DTW.

    Args:
        n_groups: Fixed number of groups, or None to choose it (see the module docstring).
        max_groups: Largest k tried when choosing.
        window: Sakoe-Chiba half-width in samples for DTW, or None for none.
        coherence_threshold_rad: Generators farther apart than this (RMS along the warping path, rad) never share
            a group; all pairs closer means k = 1.
        random_state: Passed to k-medoids (BUILD initialisation makes it irrelevant; kept for the API).

    Attributes:
        labels_: Group of each generator, 0-based, numbered in order of first member.
        n_groups_: Number of groups chosen.
        distance_matrix_: DTW distances, eq. 3, rad^2.
        rms_distance_rad_: The r matrix groups were formed on, rad.
        silhouette_: Mean silhouette per k tried (k -> score), empty when k = 1 by threshold.

    """

    def __init__(self, n_groups: int | None = None, max_groups: int = 4, window: int | None = None,
                 coherence_threshold_rad: float = 1.0, random_state: int = 0) -> None:
        self.n_groups = n_groups
        self.max_groups = max_groups
        self.window = window
        self.coherence_threshold_rad = coherence_threshold_rad
        self.random_state = random_state

    def fit(self, series: Sequence[np.ndarray]) -> DTWCoherency:
        """Find the coherent groups.

        Args:
            series: One 1-D rotor angle array (rad) per generator; NaN = lost sample; lengths may differ.

        Returns:
            self.

        Raises:
            CoherencyError: No series, a bad setting, or n_groups larger than the number of generators.
            DTWError: A series with no valid sample.

        """
        n = len(series)
        if n == 0:
            raise CoherencyError('no rotor angle series given')
        if self.n_groups is not None and not 1 <= self.n_groups <= n:
            raise CoherencyError(f'n_groups must be in 1 .. {n} (the number of generators), got {self.n_groups}')
        if self.max_groups < 2:
            raise CoherencyError(f'max_groups must be >= 2, got {self.max_groups}')
        if not self.coherence_threshold_rad > 0:
            raise CoherencyError(f'coherence_threshold_rad must be > 0, got {self.coherence_threshold_rad}')
        self.distance_matrix_, self.rms_distance_rad_ = _distances(series, self.window)
        self.silhouette_: dict[int, float] = {}
        r = self.rms_distance_rad_
        if self.n_groups is not None:
            k = self.n_groups
        elif r.max() < self.coherence_threshold_rad:
            k = 1
        else:
            admissible: list[int] = []
            for cand in range(2, min(self.max_groups, n - 1) + 1):
                labels = self._cluster(r, cand)
                self.silhouette_[cand] = silhouette(r, labels)
                if _diameter(r, labels) < self.coherence_threshold_rad:
                    admissible.append(cand)
            if admissible:
                k = max(admissible, key=lambda c: (self.silhouette_[c], -c))
            else:
                tree = linkage(squareform(r, checks=False), method='complete')
                self.labels_ = _canonical(fcluster(tree, t=self.coherence_threshold_rad, criterion='distance'))
                self.n_groups_ = int(self.labels_.max()) + 1
                return self
        self.labels_ = self._cluster(r, k)
        self.n_groups_ = int(self.labels_.max()) + 1
        return self

    def _cluster(self, r: np.ndarray, k: int) -> np.ndarray:
        if k == 1:
            return np.zeros(len(r), dtype=int)
        if k == len(r):
            return np.arange(len(r))
        result = kmedoids.pam(r, k, init='build', random_state=self.random_state)
        return _canonical(np.asarray(result.labels, dtype=int))
