"""Coherent generator groups from rotor angle trajectories by DTW (Algorithm 1, steps 2 to 4).

Reference: generators p and q are coherent when delta_p(t) - delta_q(t) stays about constant, so a constant
offset between two machines must not count. Each series has its own mean (over its valid samples) taken
off before DTW. The mean, unlike the first sample, stays a fair reference when the first second of every
PMU is lost or single frames are dropped at random: it is computed over whatever the window holds.

Dissimilarity: DTW (eq. 3, rad^2) grows with the number of samples, so groups are formed on the RMS angle
difference along the optimal warping path, r_pq = sqrt(DTW_pq / max(n_p, n_q)) in rad, with n the valid
samples of each series. It is comparable across window lengths and PMU rates.

Choosing k:
- k = 1 ("no split") when every pair is closer than ``coherence_threshold_rad`` (default 1.0 rad, 57 deg).
  A machine that slips a pole drifts by more than pi rad from the others and its r against them grows
  past 1 rad within about a second of the slip; stable post-fault swings of IEEE 39 (peak spread about
  85 deg, ANDES) stay well below. On SIM's unstable bag, coherent pairs measure at most 0.4 rad and
  incoherent ones over 4 rad.
- Otherwise k in 2 .. max_groups maximising the mean silhouette (Rousseeuw 1987) of the clustering on
  the precomputed r matrix. The paper's "minimising inter-coherent group distances" [23] alone always
  prefers more groups; the silhouette weighs each generator's distance to its own group against the
  nearest other group, works on any precomputed dissimilarity, and is the standard index for k-medoids.
  It is undefined for k = 1, hence the separate threshold.

Grouping: k-medoids (PAM, BUILD initialisation, so deterministic) on the precomputed r matrix. k-means
needs coordinates and a mean, which a DTW matrix does not have; PAM is the paper's step-9 algorithm too.
Groups are numbered in order of their first generator.
"""

from __future__ import annotations

from collections.abc import Sequence

import kmedoids
import numpy as np

from controlled_islanding.core.dtw import clean_series, dtw_distance_matrix


class CoherencyError(ValueError):
    """Series or settings the coherency estimator cannot use."""


def silhouette(r: np.ndarray, labels: np.ndarray) -> float:
    """Return the mean silhouette (Rousseeuw 1987) of a clustering on a precomputed dissimilarity matrix.

    Singleton clusters score 0, as in scikit-learn's silhouette_score (which this equals; it is written
    out here because scikit-learn's input checks cost a millisecond per call on the decision path).
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
        coherence_threshold_rad: All pairs closer than this (RMS along the warping path, rad) means k = 1.
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
        clean = [clean_series(s, f'series {i}') for i, s in enumerate(series)]
        centred = [c - c.mean() for c in clean]
        self.distance_matrix_ = dtw_distance_matrix(centred, window=self.window)
        lengths = np.array([len(c) for c in clean], dtype=float)
        self.rms_distance_rad_ = np.sqrt(self.distance_matrix_ / np.maximum.outer(lengths, lengths))
        self.silhouette_: dict[int, float] = {}
        r = self.rms_distance_rad_
        if self.n_groups is not None:
            k = self.n_groups
        elif n < 3 or r.max() < self.coherence_threshold_rad:
            k = 1 if r.max() < self.coherence_threshold_rad else n
        else:
            for cand in range(2, min(self.max_groups, n - 1) + 1):
                labels = self._cluster(r, cand)
                self.silhouette_[cand] = silhouette(r, labels)
            k = max(self.silhouette_, key=lambda c: (self.silhouette_[c], -c))
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
