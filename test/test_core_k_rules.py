"""k rules: each rule behind DTWCoherency, the drift and runaway measures, the separation rule's physics and groups."""

from __future__ import annotations

import numpy as np
import pytest

from controlled_islanding.core.coherency import CoherencyError, DTWCoherency
from controlled_islanding.core.k_rules import RULES, SeparationRule, ThresholdRule, pair_drift_rad, pair_runaway

RATE_FPS = 60.0
WINDOW_S = 3.0


def partition(labels) -> set[frozenset[int]]:
    groups: dict[int, set[int]] = {}
    for i, g in enumerate(labels):
        groups.setdefault(int(g), set()).add(i)
    return {frozenset(s) for s in groups.values()}


def two_areas(difference_rad, seed: int = 0, n_a: int = 4, n_b: int = 3) -> list[np.ndarray]:
    """Rotor angles, rad: area B leads area A by difference_rad(t); every machine has an offset and a local swing."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, WINDOW_S, 1.0 / RATE_FPS)
    common = 0.3 * np.sin(2 * np.pi * 0.6 * t)
    out = []
    for i in range(n_a + n_b):
        local = rng.uniform(0.02, 0.05) * np.sin(2 * np.pi * rng.uniform(1.2, 2.0) * t + rng.uniform(0, 6))
        shift = difference_rad(t) if i >= n_a else 0.0
        out.append(rng.uniform(-1, 1) + common + local + shift + rng.normal(0, 0.003, len(t)))
    return out


AREAS = [0, 0, 0, 0, 1, 1, 1]


def test_drift_is_the_change_of_a_steady_trend_and_ignores_offsets_and_lost_samples() -> None:
    t = np.arange(0.0, WINDOW_S, 1.0 / RATE_FPS)
    a = 0.7 * t / t[-1] + 5.0
    b = np.zeros_like(t)
    b_lossy = b.copy()
    b_lossy[::5] = np.nan
    drift = pair_drift_rad(np.array([a, b, b_lossy]))
    assert drift[0, 1] == pytest.approx(0.7, rel=2e-3) and drift[1, 0] == pytest.approx(-0.7, rel=2e-3)
    assert drift[0, 2] == pytest.approx(0.7, rel=1e-2)
    assert drift[1, 2] == pytest.approx(0.0, abs=1e-12)


def test_the_issues_case_152_deg_apart_and_drifting_is_split_where_the_fixed_threshold_saw_one_group() -> None:
    # Area B falls behind, accelerating, from the middle of the window: 152 deg apart at its end, not yet pi.
    end_rad = np.radians(152.0)
    series = two_areas(lambda t: end_rad * np.clip((t - 1.5) / 1.5, 0.0, None) ** 2)
    separation = DTWCoherency(k_rule='separation').fit(series)
    assert partition(separation.labels_) == partition(AREAS)
    assert DTWCoherency(k_rule='threshold').fit(series).n_groups_ == 1


def test_a_large_first_swing_that_comes_back_is_not_a_separation() -> None:
    # The areas swing 80 deg apart right after a fault at the start of the window and come back, damped.
    series = two_areas(lambda t: np.radians(80.0) * np.exp(-0.3 * t) * np.sin(2 * np.pi * 0.8 * t))
    est = DTWCoherency(k_rule='separation').fit(series)
    assert est.n_groups_ == 1
    assert est.rule_.scores_['max_drift_rad'] < np.pi / 2


def test_a_slow_swing_decelerating_at_the_end_of_the_window_is_not_a_separation() -> None:
    # A quarter of a 12 s period: the areas move 130 deg apart over the window, slowing to a stop at its end.
    series = two_areas(lambda t: np.radians(130.0) * np.sin(np.pi * t / (2 * WINDOW_S)))
    drift = np.abs(pair_drift_rad(np.array(series)))
    assert drift.max() >= np.pi / 2  # fast enough to pass the rate bar on its own
    assert DTWCoherency(k_rule='separation').fit(series).n_groups_ == 1


def test_a_pole_slip_inside_the_window_separates_even_at_a_steady_rate() -> None:
    series = two_areas(lambda t: 2 * np.pi * 0.5 * t)  # 0.5 Hz slip: 3 pi rad over the window
    assert partition(DTWCoherency(k_rule='separation').fit(series).labels_) == partition(AREAS)


@pytest.mark.parametrize('samples', [90, 91])
def test_a_pair_speeding_up_is_not_slowing_down_whatever_the_parity_of_the_window(samples: int) -> None:
    # 3 s at 30 frames/s holds 90 or 91 tags, as the window's start edge falls. 121 deg over the window, its rate
    # 0.7 % higher over the latest half: at that rate pi within one more window, and not slowing. Doubling the
    # half's drift read it as slowing with 90 samples (the half spans 44 of 89 steps).
    t = np.arange(samples) / 30.0
    series = [0.7 * (t + 0.005 * t ** 2), np.zeros_like(t)]
    assert np.pi / 2 <= abs(pair_drift_rad(np.array(series))[0, 1]) < np.pi
    assert DTWCoherency(k_rule='separation').fit(series).n_groups_ == 2


def test_a_pair_slowing_down_with_its_first_samples_lost_is_not_a_trend_separation() -> None:
    # 118 deg over the 54 samples the pair shares, the latest half 5 % slower than their mean rate: slowing down.
    # Its drift spans 0.6 of the window, so a doubled drift over the latest half had read it as steady.
    t = np.arange(90) / 30.0
    lost_start = np.zeros_like(t)
    lost_start[:36] = np.nan
    series = [2.0 * t - 0.2 * t ** 2, lost_start]
    assert np.pi / 2 <= abs(pair_drift_rad(np.array(series))[0, 1]) < np.pi
    assert DTWCoherency(k_rule='separation').fit(series).n_groups_ == 1


def test_three_areas_two_of_them_slipping_apart() -> None:
    rng = np.random.default_rng(3)
    t = np.arange(0.0, WINDOW_S, 1.0 / RATE_FPS)
    drifts = [0.0 * t, 1.5 * t ** 2, -1.2 * t ** 2]
    group_of = [0, 0, 0, 1, 1, 2, 2, 0]
    series = [rng.uniform(-1, 1) + drifts[g] + 0.05 * np.sin(2 * np.pi * 1.4 * t + rng.uniform(0, 6)) for g in group_of]
    assert partition(DTWCoherency(k_rule='separation').fit(series).labels_) == partition(group_of)


def test_a_runaway_from_rest_is_split_while_its_trend_over_the_window_is_still_small() -> None:
    # At rest for 2.6 s, then area B accelerates away: 130 deg from where it rested at the end of the window.
    # The trend over the window, mostly at rest, is below the pi / 2 bar; the runaway from rest is not.
    end_rad = np.radians(130.0)
    series = two_areas(lambda t: end_rad * np.clip((t - 2.6) / (WINDOW_S - 2.6), 0.0, None) ** 2)
    est = DTWCoherency(k_rule='separation').fit(series)
    assert est.rule_.scores_['max_drift_rad'] < np.pi / 2
    assert partition(est.labels_) == partition(AREAS)


def test_a_swing_from_rest_that_slows_down_is_not_a_runaway_however_far_it_goes() -> None:
    t = np.arange(0.0, WINDOW_S, 1.0 / RATE_FPS)
    rest = np.zeros_like(t)
    # 150 deg out by the end of the window, but decelerating to a stop there: a swing that will come back.
    slowing = np.radians(150.0) * np.sin(np.pi / 2 * np.clip((t - 1.0) / 2.0, 0.0, None))
    # The same distance, still accelerating at the end.
    speeding = np.radians(150.0) * np.clip((t - 1.0) / 2.0, 0.0, None) ** 2
    runaway, deviation = pair_runaway(np.array([rest, slowing, speeding]))
    assert np.degrees(deviation[0, 1]) == pytest.approx(150.0, abs=1.0)
    assert not runaway[0, 1] and runaway[0, 2] and runaway[2, 0]
    # Without a rest state at the window's start there is no reference to run away from.
    moving = np.array([rest, np.radians(150.0) * t / t[-1]])
    assert not pair_runaway(moving)[0].any()


def not_slowing(diff, both, way, half: int, three_q: int, last: int) -> bool:
    """Return whether a parabola fitted to the latest quarter of the deviation curves away (numpy's polyfit)."""
    t = np.flatnonzero(both[three_q:last + 1]) + three_q
    if len(t) < 3:
        return bool(last - three_q <= three_q - half)
    return bool(np.polyfit(t - t.mean(), way * diff[t], 2)[0] >= 0.0)


def test_a_pair_accelerating_after_clearing_runs_away_though_the_fault_moved_it_faster() -> None:
    # Measured on the PSS/E IEEE 14 bag (G1 against G2 at its request, 60 frames/s): at rest, then 0.25 s of fault
    # pushing the pair apart at a growing rate, a 0.30 rad step in the estimated angle at the clearing frame, and
    # 0.15 s after clearing in which the pair speeds up from 0.04 to 0.105 rad per frame, 107 deg from rest. The
    # quarter of the deviation before the latest one holds the fault and the step, faster than anything after
    # clearing; the latest quarter alone shows the acceleration that equal-area reads as past the unstable point.
    rest = np.zeros(150)
    fault = np.cumsum(np.linspace(0.01, 0.08, 15))
    after = fault[-1] + 0.30 + np.cumsum(np.linspace(0.04, 0.105, 9))
    runaway_pair = np.concatenate([rest, fault, after])
    # The same fault and step, then 0.15 s slowing down to a stop: a swing that will come back.
    swing = np.concatenate([rest, fault, fault[-1] + 0.30 + np.cumsum(np.linspace(0.16, 0.0, 9))])
    flat = np.zeros_like(runaway_pair)
    runaway, deviation = pair_runaway(np.array([flat, runaway_pair, swing]))
    assert np.degrees(deviation[0, 1]) > 90.0 and np.degrees(deviation[0, 2]) > 90.0
    assert runaway[0, 1] and not runaway[0, 2]


def numpy_pair_runaway(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return pair_runaway by its former numpy formulation (a pass over every pair per generator): the reference.

    The curvature of the latest quarter comes from numpy's polyfit, not the compiled normal equations.
    """
    n, m = angles.shape
    valid = np.isfinite(angles)
    idx, rows = np.arange(m), np.arange(n)
    runaway, deviation = np.zeros((n, n), dtype=bool), np.zeros((n, n))
    for p in range(n):
        both = valid[p] & valid
        has = both.sum(axis=1) >= 4
        diff = np.where(both, angles[p] - np.where(valid, angles, 0.0), 0.0)
        first = np.argmax(both, axis=1)
        last = m - 1 - np.argmax(both[:, ::-1], axis=1)
        quarter = both & (idx[None, :] <= (first + (last - first) // 4)[:, None])
        ref = np.where(quarter, diff, 0.0).sum(axis=1) / np.maximum(quarter.sum(axis=1), 1)
        moved = np.where(quarter, diff, -np.inf).max(axis=1) - np.where(quarter, diff, np.inf).min(axis=1)
        end = diff[rows, last]
        dev = np.where(has, np.abs(end - ref), 0.0)
        progress = np.sign(end - ref)[:, None] * (diff - ref[:, None])
        half = np.where(both & (progress <= dev[:, None] / 2), idx, -1).max(axis=1)
        three_q = np.where(both & (progress <= 0.75 * dev[:, None]), idx, -1).max(axis=1)
        overshot = np.where(both & (idx[None, :] >= half[:, None]), progress, -np.inf).max(axis=1) > dev
        at_rest = has & (moved <= dev / 8)
        keeps_going = np.array([not_slowing(diff[q], both[q], np.sign(end[q] - ref[q]), half[q], three_q[q], last[q])
                                if at_rest[q] and np.pi / 2 <= dev[q] < np.pi else False for q in rows]) & ~overshot
        runaway[p] = at_rest & ((dev >= np.pi) | ((dev >= np.pi / 2) & keeps_going))
        deviation[p] = np.where(at_rest, dev, 0.0)
    runaway |= runaway.T
    np.fill_diagonal(runaway, False)
    return runaway, deviation


def test_compiled_runaway_is_the_numpy_formulation_bit_for_bit_on_bags_of_three_systems() -> None:
    from pathlib import Path

    from controlled_islanding.evaluation.bag_angles import generator_series
    from controlled_islanding.wire.bagdata import load_bag

    bags = Path(__file__).resolve().parents[1] / 'bags'
    rng = np.random.default_rng(3)
    windows = []
    for name in ('pjm5bus_bus3_unstable', 'nordic44_bus6000_three_groups', 'ei33_bus101048_pair_unstable'):
        if not (bags / name).exists():
            continue
        bag = load_bag(bags / name)
        t_s, _, angles_rad = generator_series(bag, float(bag.tag_s[0]), float(bag.tag_s[-1]))
        for end in t_s[-1] - np.arange(2) * 0.5:
            window = np.array([a[(t_s >= end - WINDOW_S - 1e-9) & (t_s <= end + 1e-9)] for a in angles_rad])
            lost = np.where(rng.random(window.shape) < 0.2, np.nan, window)
            lost[0, -20:] = lost[-1, :15] = np.nan  # spans that differ
            windows += [window, lost]
    expected = [numpy_pair_runaway(angles) for angles in windows]
    assert sum(e[0].any() for e in expected) >= 4, 'too few runaways among the windows compared'
    for angles, (runaway, deviation) in zip(windows, expected, strict=True):
        got = pair_runaway(angles)
        assert np.array_equal(got[0], runaway) and np.array_equal(got[1], deviation)


def test_as_many_groups_as_slip_apart_and_a_cap_merges_the_closest() -> None:
    # Five groups each slipping at its own rate: more than the four the former k-medoids search allowed.
    rng = np.random.default_rng(4)
    t = np.arange(0.0, WINDOW_S, 1.0 / RATE_FPS)
    rates = [0.0, 4.0, -4.0, 9.0, -9.0]  # rad/s^2
    group_of = [0, 0, 0, 0, 1, 1, 2, 3, 4, 4, 0, 0]
    series = [rng.uniform(-1, 1) + rates[g] * t ** 2 / 2 + 0.05 * np.sin(2 * np.pi * 1.3 * t + rng.uniform(0, 6))
              for g in group_of]
    est = DTWCoherency(k_rule='separation').fit(series)
    assert partition(est.labels_) == partition(group_of)
    capped = DTWCoherency(k_rule='separation', max_groups=3).fit(series)
    assert capped.n_groups_ == 3 and capped.rule_.scores_['merged_beyond_max_groups'] == 5


@pytest.mark.parametrize('rule', sorted(RULES))
def test_every_rule_runs_behind_dtw_coherency_and_finds_a_fast_separation(rule: str) -> None:
    # Areas larger than the eigengap rule's 7th neighbour, so its self-tuned scale stays inside an area.
    series = two_areas(lambda t: 2.0 * t ** 2, seed=1, n_a=9, n_b=8)
    est = DTWCoherency(k_rule=rule).fit(series)
    assert partition(est.labels_) == partition([0] * 9 + [1] * 8), est.rule_.scores_
    assert est.rule_.name == rule


def test_a_rule_instance_with_its_own_settings_is_used() -> None:
    series = two_areas(lambda t: 0.5 * t, seed=2)  # 1.5 rad over the window: RMS about 0.45 rad
    assert DTWCoherency(k_rule=ThresholdRule(coherence_threshold_rad=0.2)).fit(series).n_groups_ == 2
    assert DTWCoherency(k_rule=ThresholdRule(coherence_threshold_rad=1.0)).fit(series).n_groups_ == 1
    # No horizon: only a full pi of drift inside the window separates.
    assert DTWCoherency(k_rule=SeparationRule(horizon_windows=0.0)).fit(series).n_groups_ == 1


@pytest.mark.parametrize(('rule', 'message'), [('nope', 'unknown k rule'), (object(), 'choose'),
                                               (SeparationRule(horizon_windows=-1.0), 'horizon_windows'),
                                               (ThresholdRule(coherence_threshold_rad=0.0), 'coherence_threshold')])
def test_bad_rules_are_refused(rule, message: str) -> None:
    with pytest.raises(CoherencyError, match=message):
        DTWCoherency(k_rule=rule).fit(two_areas(lambda t: 2.0 * t ** 2))


def test_one_pass_gives_the_latest_halfs_rate_bit_for_bit() -> None:
    from controlled_islanding.core.k_rules import _drift_and_rate

    rng = np.random.default_rng(9)
    for m in (4, 37, 91, 180):
        angles = np.cumsum(rng.normal(0, 0.05, (12, m)), axis=1) + rng.uniform(-1, 1, (12, 1))
        angles[rng.random(angles.shape) < 0.15] = np.nan
        angles[0, m // 2:-1] = np.nan  # one sample left in the latest half: no rate there
        drift, rate, latest = _drift_and_rate(angles, m // 2)
        assert np.array_equal(drift, pair_drift_rad(angles)) and np.array_equal(rate, pair_drift_rad(angles, True))
        expected = pair_drift_rad(angles[:, m // 2:], per_sample=True)
        assert np.array_equal(latest, expected) and np.array_equal(np.signbit(latest), np.signbit(expected))
        assert np.array_equal(drift, -drift.T) and not latest[0].any() and rate[0].any()
