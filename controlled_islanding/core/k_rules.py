"""Rules that choose the number of coherent groups k, and whether to split at all, from one window's evidence.

Every rule has one shape: ``rule.choose(evidence) -> labels`` (0-based group per generator; one group means
"no split"), with what it measured left in ``rule.scores_``. `DTWCoherency` (core/coherency.py) builds the
evidence once and hands it to the rule named by its ``k_rule``, so rules are swapped by name or by instance.
The groups themselves are always k-medoids (PAM) clusters of the DTW RMS matrix r; rules differ only in k.

Rules (docs/coherency_rules.md compares them on every scenario bag; `RULES` maps names to classes):

- ``separation`` (default): rate of separation against the pole-slip scale. For each generator pair the
  least-squares slope of the angle difference delta_p - delta_q over the window, times the span of the window,
  is the pair's drift, rad. pi rad is the angle at which one machine slips a pole on another: physics, not a
  number fitted to a system. A pair separates when
  - it drifted pi within the window (a pole slip's worth), or
  - at the window's mean rate it would drift pi within one more window (|drift| >= pi / 2 with the default
    horizon of one window) and it is not slowing down: over the latest half of the window it moves on, the
    same way, at least at the window's mean rate. This is the equal-area picture: a swing that will come back
    decelerates once past its stable equilibrium, a pair past the unstable one accelerates away.
  Stable swings go back and forth inside a window, so their drift is small whatever their amplitude, as long
  as the window holds about a swing period; a slow swing seen over less than that looks like a drift, which
  the slowing-down test is there to catch. No separating pair: one group. Otherwise the k in 2 .. max_groups
  whose PAM clustering never puts a separating pair in one group and whose groups all drift apart on average
  by the bar, with the best silhouette; failing that, complete-linkage clusters that keep separating pairs apart.
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


def pair_drift_rad(angles: np.ndarray) -> np.ndarray:
    """Return each pair's drift over the window: the least-squares slope of delta_p - delta_q times the span, rad.

    Each pair is fitted over the samples both have. The span is computed from the spread of those sample times
    (the first-to-last distance for evenly spaced samples), so it stays fair when some are lost.

    Args:
        angles: Rotor angles, rad, shape (n_generators, n_samples), on one time grid; NaN = lost.

    Returns:
        Antisymmetric (n, n) matrix: drift of delta_p - delta_q, rad (0 where a pair shares < 2 samples).

    """
    valid = np.isfinite(angles).astype(float)
    x = np.arange(angles.shape[1], dtype=float)
    values = np.where(valid > 0, angles, 0.0)
    n_common = valid @ valid.T
    sx = (valid * x) @ valid.T
    sxx = (valid * x * x) @ valid.T
    sd = values @ valid.T - valid @ values.T
    sxd = (values * x) @ valid.T - valid @ (values * x).T
    with np.errstate(invalid='ignore', divide='ignore'):
        var_x = sxx - sx * sx / n_common
        slope = (sxd - sx * sd / n_common) / var_x
        # First-to-last distance of n evenly spaced samples, from their spread, so lost samples leave it fair.
        drift = slope * np.sqrt(12.0 * var_x / n_common * (n_common - 1) / (n_common + 1))
    return np.where(np.isfinite(drift), drift, 0.0)


@dataclass
class Evidence:
    """What a rule may look at, computed once per window by DTWCoherency.

    Attributes:
        rms_rad: RMS angle difference along the optimal warping path, rad, (n, n).
        angles_rad: The window's rotor angles on one time grid, rad, (n, n_samples), NaN = lost.
        max_groups: Largest k a rule may choose (it is also capped at the number of generators).
        cluster: k -> PAM labels on rms_rad (cached by the caller).

    """

    rms_rad: np.ndarray
    angles_rad: np.ndarray
    max_groups: int
    cluster: Callable[[int], np.ndarray]
    _drift: np.ndarray | None = field(default=None, repr=False)

    @property
    def n(self) -> int:
        """Return the number of generators."""
        return len(self.rms_rad)

    @property
    def candidates(self) -> range:
        """Return the k > 1 a rule may pick: 2 .. min(max_groups, n)."""
        return range(2, min(self.max_groups, self.n) + 1)

    @property
    def drift_rad(self) -> np.ndarray:
        """Return pair_drift_rad of the window (computed on first use)."""
        if self._drift is None:
            self._drift = pair_drift_rad(self.angles_rad)
        return self._drift


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


class SeparationRule:
    """Split generators whose angle difference trends towards a pole slip (see the module docstring).

    Args:
        horizon_windows: How far ahead the window's mean rate is projected, in windows. A pair separates when
            |drift| * (1 + horizon_windows) >= pi rad.

    Attributes:
        scores_: 'bar_rad' (the |drift| bar), 'max_drift_rad', 'separating_pairs', 'silhouette' per k tried.

    """

    name = 'separation'

    def __init__(self, horizon_windows: float = 1.0) -> None:
        self.horizon_windows = horizon_windows

    def choose(self, ev: Evidence) -> np.ndarray:
        """Return the groups (see the module docstring)."""
        if not self.horizon_windows >= 0:
            raise KRuleError(f'horizon_windows must be >= 0, got {self.horizon_windows}')
        bar = np.pi / (1.0 + self.horizon_windows)
        drift = np.abs(ev.drift_rad)
        latest = pair_drift_rad(ev.angles_rad[:, ev.angles_rad.shape[1] // 2:])
        # Not slowing down: over the latest half of the window the pair moves on, the same way, at least at the
        # window's mean rate (a drift over half the window, doubled, is a rate per window).
        steady = (np.sign(latest) == np.sign(ev.drift_rad)) & (2.0 * np.abs(latest) >= drift)
        separating = (drift >= np.pi) | ((drift >= bar) & steady)
        self.scores_: dict = {'bar_rad': bar, 'max_drift_rad': float(drift.max()) if drift.size else 0.0,
                              'separating_pairs': int(np.triu(separating, 1).sum())}
        if ev.n < 2 or not separating.any():
            return _one_group(ev.n)
        admissible = []
        for k in ev.candidates:
            labels = ev.cluster(k)
            same = labels[:, None] == labels[None, :]
            if (separating & same).any():
                continue
            # Every two groups must separate as wholes, or a stable sub-group would be split off as well.
            means = [drift[np.ix_(labels == g, labels == h)].mean() for g in range(k) for h in range(g + 1, k)]
            if min(means) >= bar:
                admissible.append(k)
        best = _best_silhouette(ev, admissible, self.scores_)
        if best is not None:
            return ev.cluster(best)
        # Separating pairs at distance 2, the rest by drift scaled into [0, 1): complete linkage cut at 1.5 never
        # puts a separating pair in one group and merges the others by how little they drift apart.
        scaled = np.where(separating, 2.0, drift / (2.0 * drift.max()))
        np.fill_diagonal(scaled, 0.0)
        tree = linkage(squareform(scaled, checks=False), method='complete')
        return canonical(fcluster(tree, t=1.5, criterion='distance'))


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
