"""The separation rule without DTW where the separating pairs alone decide the groups: the same groups as the linkage.

SeparationRule._forced_groups skips DTW when "not separating" is an equivalence relation. Each window here is
grouped twice, by the default and by the rule with that shortcut turned off and every pair's DTW computed (the
direct computation), on random swings and on PMU-estimated angles of bags of four systems; labels and scores
must be equal, and both branches (shortcut taken, linkage needed) must occur.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controlled_islanding.core.coherency import DTWCoherency
from controlled_islanding.core.k_rules import SeparationRule

BAGS = Path(__file__).resolve().parents[1] / 'bags'
RATE_FPS = 60.0


class LinkageOnly(SeparationRule):
    """The rule as it was: the groups always from the constrained complete linkage of r."""

    @staticmethod
    def _forced_groups(ev, separating):
        return None


def both_ways(series, **kwargs) -> tuple[DTWCoherency, DTWCoherency]:
    fast = DTWCoherency(window=30, **kwargs).fit(series)
    direct = DTWCoherency(window=30, k_rule=LinkageOnly(), all_pairs=True, **kwargs).fit(series)
    assert np.array_equal(fast.labels_, direct.labels_)
    assert fast.rule_.scores_ == direct.rule_.scores_
    return fast, direct


def skipped_dtw(model: DTWCoherency) -> bool:
    """Whether a split was found with no pair's DTW computed (the shortcut)."""
    return model.n_groups_ > 1 and np.isnan(model.distance_matrix_[~np.eye(len(model.labels_), dtype=bool)]).all()


def random_window(rng: np.random.Generator) -> list[np.ndarray]:
    """Rotor angles, rad: 3 to 40 machines in 1 to 5 areas; each area at rest, drifting or running away.

    Areas drifting at neighbouring rates give chains (A apart from C, B from neither), where the linkage is needed.
    """
    n_areas = int(rng.integers(1, 6))
    n = int(rng.integers(max(3, n_areas), 41))
    area = np.concatenate([np.arange(n_areas), rng.integers(0, n_areas, n - n_areas)])
    t = np.arange(0.0, rng.uniform(1.0, 4.0), 1.0 / RATE_FPS)
    onset = rng.uniform(0.0, t[-1] * 0.6)
    # rad/s^2 per area: from 0 (at rest) through slow drifts to pole slips within the window.
    accel = rng.choice([0.0, 0.3, 0.8, 1.5, 3.0, 6.0, -2.0, -5.0], n_areas)
    out = []
    for g in area:
        swing = rng.uniform(0.02, 0.3) * np.sin(2 * np.pi * rng.uniform(0.3, 2.0) * t + rng.uniform(0, 6))
        x = rng.uniform(-1, 1) + swing + accel[g] * np.maximum(t - onset, 0.0) ** 2 / 2
        x += rng.normal(0, 0.003, len(t))
        kind = rng.integers(0, 4)
        if kind == 1:
            x[rng.random(len(t)) < 0.2] = np.nan
        elif kind == 2:
            x = x[:len(t) - int(rng.integers(0, len(t) // 4))]
        elif kind == 3:
            x[:int(rng.integers(1, len(t) // 4))] = np.nan
        out.append(x)
    return out


def test_random_windows_group_alike_with_and_without_dtw() -> None:
    rng = np.random.default_rng(32)
    taken = needed = 0
    for _ in range(300):
        fast, direct = both_ways(random_window(rng), max_groups=int(rng.integers(2, 6)))
        if fast.n_groups_ > 1:
            taken += skipped_dtw(fast)
            needed += not skipped_dtw(fast)
    assert taken >= 30 and needed >= 10, (taken, needed)


def test_the_cap_on_groups_and_a_chain_take_the_linkage() -> None:
    t = np.arange(0.0, 3.0, 1.0 / RATE_FPS)
    rng = np.random.default_rng(5)

    def area(accel: float, count: int) -> list[np.ndarray]:
        return [rng.uniform(-1, 1) + accel * t ** 2 / 2 + 0.05 * np.sin(2 * np.pi * 1.3 * t + rng.uniform(0, 6))
                for _ in range(count)]

    five = [x for a in (0.0, 4.0, -4.0, 9.0, -9.0) for x in area(a, 3)]
    fast, _ = both_ways(five)
    assert fast.n_groups_ == 5 and skipped_dtw(fast)
    capped, _ = both_ways(five, max_groups=3)
    assert capped.n_groups_ == 3 and not skipped_dtw(capped)
    # B between A and C: apart from neither, while A and C separate; r decides where B's machines go.
    chain = area(0.0, 3) + area(0.25, 3) + area(0.5, 3)
    fast, _ = both_ways(chain)
    separating = fast.rule_.scores_['separating_pairs']
    assert fast.n_groups_ >= 2 and 0 < separating < 27 and not skipped_dtw(fast)
    assert np.triu(~np.isnan(fast.distance_matrix_), 1).sum() == 9 * 8 // 2 - separating  # the others' DTW


def bag_windows(name: str, ends: int) -> list[list[np.ndarray]]:
    from controlled_islanding.evaluation.bag_angles import generator_series
    from controlled_islanding.wire.bagdata import load_bag

    bag = load_bag(BAGS / name)
    t_s, _, angles = generator_series(bag, float(bag.tag_s[0]), float(bag.tag_s[-1]))
    step = float(np.median(np.diff(t_s)))
    windows = []
    for end in np.linspace(t_s[0] + 30 * step, t_s[-1], ends):
        rows = (t_s >= end - 3.0 - 1e-9) & (t_s <= end + 1e-9)
        windows.append(list(angles[:, rows]))
    return windows


@pytest.mark.parametrize(('name', 'ends'), [('ieee39_g6g7_unstable', 40), ('kundur_bus9_unstable', 20),
                                            ('ei33_bus101048_pair_unstable', 12), ('gbnetwork_bus73_unstable', 4)])
def test_bag_windows_group_alike_with_and_without_dtw(name: str, ends: int) -> None:
    if not (BAGS / name).exists():
        pytest.skip(f'bag {name} not built')
    splits = 0
    for series in bag_windows(name, ends):
        fast, _ = both_ways(series)
        splits += fast.n_groups_ > 1
        # A lost sample here and there leaves the relation, and so the answer, to the same test.
        lossy = [np.where(np.random.default_rng(len(x)).random(len(x)) < 0.1, np.nan, x) for x in series]
        both_ways(lossy)
    assert splits >= 1, f'no window of {name} split: nothing compared where it matters'
