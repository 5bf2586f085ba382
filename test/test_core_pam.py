"""PAM k-medoids without a distance matrix (core/pam.py), against the kmedoids package on the same points."""

from __future__ import annotations

import kmedoids
import numpy as np
import pytest

from controlled_islanding.core.pam import pam


def distances(x: np.ndarray) -> np.ndarray:
    return np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(axis=2))


@pytest.mark.parametrize('seed', range(40))
def test_same_medoids_and_labels_as_kmedoids_pam(seed: int) -> None:
    # Points in general position (2 or 3 dimensions, continuous): no gains tie, so the swaps are the same.
    rng = np.random.default_rng(seed)
    n, p, k = int(rng.integers(5, 200)), int(rng.integers(2, 4)), int(rng.integers(2, 6))
    x = rng.normal(size=(n, p)) + rng.integers(0, 3, size=(n, 1))  # a little cluster structure
    ref = kmedoids.pam(distances(x), k, init='build', random_state=0)
    labels, medoids = pam(x, k)
    assert medoids.tolist() == np.asarray(ref.medoids).tolist()
    assert labels.tolist() == np.asarray(ref.labels).tolist()


@pytest.mark.parametrize('seed', range(20))
def test_result_is_a_swap_local_optimum_with_ties(seed: int) -> None:
    # One dimension with rounded values: gains tie exactly, so only the PAM property itself is checked.
    rng = np.random.default_rng(seed)
    n, k = int(rng.integers(5, 80)), int(rng.integers(2, 5))
    x = np.round(rng.normal(size=(n, 1)), 1)
    d = distances(x)
    labels, medoids = pam(x, k)
    loss = d[:, medoids].min(axis=1).sum()
    assert labels.tolist() == np.argmin(d[:, medoids], axis=1).tolist() or \
        np.allclose(d[np.arange(n), medoids[labels]], d[:, medoids].min(axis=1))
    for m in range(k):
        for j in set(range(n)) - set(medoids.tolist()):
            trial = medoids.copy()
            trial[m] = j
            assert d[:, trial].min(axis=1).sum() >= loss - 1e-12


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match='k must be'):
        pam(np.zeros((3, 1)), 4)
    with pytest.raises(ValueError, match='finite 2-D'):
        pam(np.array([[np.nan]]), 1)


@pytest.mark.parametrize('seed', range(12))
def test_one_dimension_shortlist_chooses_as_the_full_passes(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    # From _SHORTLIST_FROM points in one dimension, BUILD and SWAP run the kernel only on the candidates that prefix
    # sums leave within their error bound of the best: the same medoids and labels as every candidate's full pass,
    # with rounded values (exact ties), duplicates, and clusters of very unequal size and spread.
    from controlled_islanding.core import pam as pam_module

    rng = np.random.default_rng(seed)
    n, k = int(rng.integers(pam_module._SHORTLIST_FROM, 1500)), int(rng.integers(2, 5))
    x = rng.normal(size=(n, 1)) * rng.choice([1e-3, 1.0, 30.0], size=(n, 1)) + rng.integers(0, 4, size=(n, 1))
    if seed % 3 == 0:
        x = np.round(x, 1)
    if seed % 3 == 1:
        x[: n // 4] = x[n // 4: 2 * (n // 4)]
    got = pam(x, k)
    monkeypatch.setattr(pam_module, '_SHORTLIST_FROM', n + 1)
    full = pam(x, k)
    assert got[1].tolist() == full[1].tolist()
    assert got[0].tolist() == full[0].tolist()
