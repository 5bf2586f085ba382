"""DTW (eqs. 1-3) against an independent dynamic program written from the paper's definition."""

from __future__ import annotations

import numpy as np
import pytest
from dtaidistance import dtw as dtaidistance_dtw

from controlled_islanding.core.dtw import DTWError, dtw_distance, dtw_distance_matrix


def reference_dtw(a: np.ndarray, b: np.ndarray, window: int | None = None) -> float:
    """Eq. 3 by the textbook recurrence over the full i x k cost matrix, with the module's band definition."""
    a = a[~np.isnan(a)]
    b = b[~np.isnan(b)]
    n, m = len(a), len(b)
    acc = np.full((n + 1, m + 1), np.inf)
    acc[0, 0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            shift = (j - 1) - (i - 1)
            if window is not None and not (-window - max(0, n - m) <= shift <= window + max(0, m - n)):
                continue
            acc[i, j] = (a[i - 1] - b[j - 1]) ** 2 + min(acc[i - 1, j - 1], acc[i - 1, j], acc[i, j - 1])
    return float(acc[n, m])


def brute_force_dtw(a: np.ndarray, b: np.ndarray) -> float:
    """Eq. 2 minimised over every warping path (tiny series only)."""
    best = np.inf

    def walk(i: int, j: int, total: float) -> None:
        nonlocal best
        total += (a[i] - b[j]) ** 2
        if i == len(a) - 1 and j == len(b) - 1:
            best = min(best, total)
            return
        for di, dj in ((1, 0), (0, 1), (1, 1)):
            if i + di < len(a) and j + dj < len(b):
                walk(i + di, j + dj, total)

    walk(0, 0, 0.0)
    return best


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def test_definition_by_brute_force(rng: np.random.Generator) -> None:
    for _ in range(20):
        a, b = rng.normal(size=rng.integers(1, 6)), rng.normal(size=rng.integers(1, 6))
        assert dtw_distance(a, b) == pytest.approx(brute_force_dtw(a, b), rel=1e-12, abs=1e-15)
        assert reference_dtw(a, b) == pytest.approx(brute_force_dtw(a, b), rel=1e-12, abs=1e-15)


@pytest.mark.parametrize('window', [None, 0, 1, 3, 10])
def test_matches_reference_with_unequal_lengths_and_window(rng: np.random.Generator, window: int | None) -> None:
    for _ in range(10):
        a = np.cumsum(rng.normal(size=rng.integers(20, 60)))
        b = np.cumsum(rng.normal(size=rng.integers(20, 60)))
        ref = reference_dtw(a, b, window)
        assert dtw_distance(a, b, window) == pytest.approx(ref, rel=1e-9)
        assert dtw_distance(b, a, window) == pytest.approx(ref, rel=1e-9)


def test_matches_dtaidistance_pure_python_path(rng: np.random.Generator) -> None:
    a, b = np.sin(np.linspace(0, 6, 120)), np.sin(np.linspace(0.3, 6.5, 97)) + rng.normal(0, 0.05, 97)
    assert dtw_distance(a, b) == pytest.approx(dtaidistance_dtw.distance(a, b, use_c=False) ** 2, rel=1e-9)


def test_zero_window_on_equal_lengths_is_squared_euclidean(rng: np.random.Generator) -> None:
    a, b = rng.normal(size=50), rng.normal(size=50)
    assert dtw_distance(a, b, window=0) == pytest.approx(float(((a - b) ** 2).sum()), rel=1e-12)
    assert dtw_distance(a, b) < dtw_distance(a, b, window=0)


def test_lost_samples_are_dropped_not_interpolated(rng: np.random.Generator) -> None:
    a, b = rng.normal(size=40), rng.normal(size=40)
    lost = a.copy()
    lost[[0, 5, 6, 20]] = np.nan
    assert dtw_distance(lost, b) == pytest.approx(reference_dtw(np.delete(a, [0, 5, 6, 20]), b), rel=1e-9)
    assert dtw_distance(a[:1], a[:1]) == 0.0


def test_matrix_matches_pairwise_and_is_symmetric(rng: np.random.Generator) -> None:
    series = [np.cumsum(rng.normal(size=rng.integers(30, 50))) for _ in range(6)]
    series[2][[3, 4]] = np.nan
    for window in (None, 4):
        d = dtw_distance_matrix(series, window)
        assert d.shape == (6, 6) and np.all(np.diag(d) == 0.0)
        assert np.array_equal(d, d.T)
        for i in range(6):
            for j in range(i + 1, 6):
                assert d[i, j] == pytest.approx(reference_dtw(series[i], series[j], window), rel=1e-9)
    equal = [s[:30] for s in series if not np.isnan(s[:30]).any()]
    d = dtw_distance_matrix(equal)
    assert d[0, 1] == pytest.approx(reference_dtw(equal[0], equal[1]), rel=1e-9)
    ramp = np.arange(30.0)
    assert dtw_distance_matrix([ramp, ramp[::-1].copy()])[0, 1] == pytest.approx(((ramp - ramp[::-1]) ** 2).sum())
    assert np.array_equal(dtw_distance_matrix(equal, parallel=True), d)


def test_pairs_asked_are_the_whole_matrix_bit_for_bit(rng: np.random.Generator) -> None:
    # 40 series of two lengths: blocks of lanes hold different pairs when some are left out.
    series = [np.cumsum(rng.normal(size=60 if i % 3 else 55)) for i in range(40)]
    whole = dtw_distance_matrix(series, 5)
    mask = rng.random((40, 40)) < 0.3
    part = dtw_distance_matrix(series, 5, pairs=mask)
    asked = np.triu(mask, 1) | np.triu(mask, 1).T
    assert np.array_equal(part[asked], whole[asked]) and np.all(np.diag(part) == 0.0)
    assert np.isnan(part[~asked & ~np.eye(40, dtype=bool)]).all()
    none = dtw_distance_matrix(series, pairs=np.zeros((40, 40), bool))
    assert np.array_equal(np.isnan(none), ~np.eye(40, dtype=bool))
    with pytest.raises(DTWError, match=r'pairs must be a \(40, 40\) mask'):
        dtw_distance_matrix(series, pairs=np.ones((3, 3), bool))


@pytest.mark.parametrize(('bad', 'message'), [
    (np.zeros((3, 2)), '1-D'),
    (np.array([1.0, np.inf]), 'infinite'),
    (np.array([np.nan, np.nan]), 'no valid sample'),
])
def test_bad_series_are_named(bad: np.ndarray, message: str) -> None:
    with pytest.raises(DTWError, match=message):
        dtw_distance_matrix([np.zeros(3), bad])


@pytest.mark.parametrize('window', [-1, 1.5])
def test_bad_window(window: float) -> None:
    with pytest.raises(DTWError, match='window'):
        dtw_distance(np.zeros(3), np.zeros(3), window)  # type: ignore[arg-type]


@pytest.mark.parametrize('window', [None, 0, 1, 5, 30])
def test_engine_equals_dtaidistance_to_1e_12(rng: np.random.Generator, window: int | None) -> None:
    # Our compiled kernel against dtaidistance's C engine (its window counts the diagonal; it returns sqrt).
    series = [np.cumsum(rng.normal(size=rng.integers(20, 160))) for _ in range(12)]
    series += [s[:100].copy() for s in series[:4] if len(s) >= 100]  # equal lengths too
    ours = dtw_distance_matrix(series, window)
    theirs = np.asarray(dtaidistance_dtw.distance_matrix_fast(
        series, window=None if window is None else window + 1, use_pruning=False), dtype=float) ** 2
    off = ~np.eye(len(series), dtype=bool)
    np.testing.assert_allclose(ours[off], theirs[off], rtol=1e-12, atol=0)
    assert np.array_equal(dtw_distance_matrix(series, window, parallel=True), ours)
    assert dtw_distance(series[0], series[1], window) == ours[0, 1]
