"""Correlation-coefficient coherency, the paper's baseline after its reference [24].

Every generator pair is correlated (Pearson, over the samples both have), and the generators are split on the
average correlation: average-linkage clustering on the dissimilarity 1 - r, cut at 1 - r_mean, where r_mean is the
mean over all distinct pairs. Pairs correlated better than average end up together. The rule needs no tuning,
which is the method's appeal, and it always splits unless every pair is equally correlated (or all pairs reach
`coherent_above`), which is the weakness the paper points out: its number of groups follows the data's spread,
not a physical threshold.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform


class CorrelationError(ValueError):
    """Series that cannot be correlated: too few generators, unequal lengths, too few shared samples."""


class CorrelationCoherency:
    """Coherent generator groups from pairwise correlation coefficients (scikit-learn style).

    Args:
        coherent_above: If every pairwise correlation is at least this (unitless, in [-1, 1]), return one group.
            None (default) follows [24] and always splits on the average.
        min_samples: Fewest samples a pair must share to be correlated.

    Attributes:
        labels_: Group per generator, 0-based, numbered by first appearance.
        n_groups_: Number of groups.
        correlation_: n x n Pearson correlation matrix, unitless.
        distance_matrix_: 1 - correlation_, unitless.
        threshold_: Mean off-diagonal correlation the split is made at, unitless.

    """

    def __init__(self, coherent_above: float | None = None, min_samples: int = 3) -> None:
        self.coherent_above = coherent_above
        self.min_samples = min_samples

    def fit(self, series: Sequence[np.ndarray]) -> CorrelationCoherency:
        """Group generators by the correlation of their rotor-angle series.

        Args:
            series: One 1-D rotor-angle array (rad) per generator, all on the same time tags; NaN = lost sample.

        Returns:
            self.

        Raises:
            CorrelationError: Fewer than one series, unequal lengths, or a pair sharing fewer than
                `min_samples` valid samples.

        """
        arrays = [np.asarray(s, dtype=float).ravel() for s in series]
        if not arrays:
            raise CorrelationError('no generator series to correlate')
        lengths = {a.size for a in arrays}
        if len(lengths) != 1:
            raise CorrelationError(f'series must share time tags; got lengths {sorted(lengths)}')
        n = len(arrays)
        data = np.vstack(arrays)
        corr = np.eye(n)
        for p in range(n):
            for q in range(p + 1, n):
                corr[p, q] = corr[q, p] = self._pair(data[p], data[q], p, q)
        self.correlation_ = corr
        self.distance_matrix_ = 1.0 - corr
        if n == 1:
            self.threshold_ = 1.0
            self._set(np.zeros(1, dtype=int))
            return self
        off = corr[np.triu_indices(n, 1)]
        self.threshold_ = float(off.mean())
        if (self.coherent_above is not None and off.min() >= self.coherent_above) or np.ptp(off) <= 1e-12:
            self._set(np.zeros(n, dtype=int))
            return self
        tree = linkage(squareform(np.clip(self.distance_matrix_, 0.0, 2.0), checks=False), method='average')
        self._set(fcluster(tree, t=1.0 - self.threshold_, criterion='distance'))
        return self

    def _pair(self, a: np.ndarray, b: np.ndarray, p: int, q: int) -> float:
        ok = np.isfinite(a) & np.isfinite(b)
        if ok.sum() < self.min_samples:
            raise CorrelationError(f'generators {p} and {q} share {int(ok.sum())} valid samples; '
                                   f'need at least {self.min_samples}')
        a, b = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        if na == 0.0 or nb == 0.0:
            # A flat trace has no defined correlation; two flat traces move together, one alone does not.
            return 1.0 if na == nb else 0.0
        return float(np.clip(a @ b / (na * nb), -1.0, 1.0))

    def _set(self, raw: np.ndarray) -> None:
        order: dict[int, int] = {}
        self.labels_ = np.array([order.setdefault(int(v), len(order)) for v in raw], dtype=int)
        self.n_groups_ = len(order)
