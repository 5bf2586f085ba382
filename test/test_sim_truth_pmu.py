"""Truth rule and PMU measurement model on synthetic simulations (no ANDES)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from controlled_islanding.core.grid import Branch, Generator, Grid, Load
from controlled_islanding.sim.andes_sim import Simulation, branch_ids
from controlled_islanding.sim.pmu import STAT_DATA_INVALID, measure, time_tags
from controlled_islanding.sim.scenario import Impairments, Scenario
from controlled_islanding.sim.truth import first_pole_slip_s, pole_slip_groups, truth_groups


def _angles(t: np.ndarray, amplitudes_rad: list[float], slip_rad_per_s: list[float]) -> np.ndarray:
    swing = np.sin(2 * np.pi * 1.0 * t)[:, None] * np.array(amplitudes_rad)[None, :]
    return 0.3 + swing + np.clip(t - 1.0, 0, None)[:, None] * np.array(slip_rad_per_s)[None, :]


def test_truth_one_group_when_swings_stay_within_pi() -> None:
    t = np.linspace(0, 5, 301)
    delta = _angles(t, [0.0, 0.5, 1.2, -1.0], [0.0, 0.0, 0.0, 0.0])  # largest pair difference 2.2 rad < pi
    assert truth_groups(t, delta).tolist() == [0, 0, 0, 0]
    assert first_pole_slip_s(t, delta) is None


def test_truth_separates_slipping_generators_and_numbers_groups_by_first_member() -> None:
    t = np.linspace(0, 5, 301)
    delta = _angles(t, [0.1, 0.1, 0.2, 0.1, 0.1], [4.0, 0.0, 4.0, 0.0, -6.0])
    assert truth_groups(t, delta).tolist() == [0, 1, 0, 1, 2]


def test_truth_is_the_final_grouping_even_when_the_slip_comes_after_the_request() -> None:
    t = np.linspace(0, 5, 301)
    delta = _angles(t, [0.1, 0.1], [0.0, 2.0])  # separates by pi only after t = 1 + pi/2 s
    assert truth_groups(t, delta).tolist() == [0, 1]
    # The former rule, kept as a diagnostic, only sees the slip once it has happened.
    assert pole_slip_groups(t, delta, 2.0).tolist() == [0, 0]
    assert pole_slip_groups(t, delta, 4.0).tolist() == [0, 1]
    slip = first_pole_slip_s(t, delta)
    assert slip == pytest.approx(1.0 + np.pi / 2.0, abs=t[1] - t[0] + 1e-9)


def test_truth_forgives_a_swing_past_pi_that_comes_back() -> None:
    t = np.linspace(0, 5, 501)
    swing = 3.6 * np.sin(np.pi * t / 5.0) ** 2  # the pair is 3.6 rad apart at 2.5 s, back together at 5 s
    delta = np.column_stack([np.zeros_like(t), swing])
    assert pole_slip_groups(t, delta, 5.0).tolist() == [0, 1]
    assert truth_groups(t, delta).tolist() == [0, 0]
    assert first_pole_slip_s(t, delta) is not None


def test_truth_keeps_machines_that_slip_together_in_one_group() -> None:
    t = np.linspace(0, 5, 301)
    # Machines 1 and 2 slip together (their difference swings by 1 rad); machine 0 stays.
    delta = _angles(t, [0.0, 0.5, -0.5], [0.0, 5.0, 5.0])
    assert truth_groups(t, delta).tolist() == [0, 1, 1]


def _simulation() -> Simulation:
    t = np.unique(np.concatenate([np.linspace(0, 4, 487), [1.0, 1.0 + 1e-6]]))
    n = len(t)
    buses = (1, 2, 3)
    bus_a = np.column_stack([0.1 * np.sin(t), 0.2 + 3.0 * t, -0.1 + 0.0 * t])  # bus 2 slips: angle passes 2 pi
    grid = Grid(name='toy', base_mva=100.0, buses=buses,
                branches=(Branch('1-2', 1, 2), Branch('2-3', 2, 3)),
                generators=(Generator('A', 1, 50.0, 100.0, 0.5), Generator('B', 2, 50.0, 100.0, 0.5)),
                loads=(Load(3, 100.0),))
    return Simulation(
        t_s=t, freq_hz=60.0, bus_numbers=buses, bus_v_pu=np.ones((n, 3)), bus_angle_rad=bus_a,
        generator_names=('A', 'B'), generator_buses=(1, 2), delta_rad=bus_a[:, :2] + 0.3,
        p_pu=np.full((n, 2), 0.5), q_pu=np.full((n, 2), 0.1), grid=grid, branch_ends={'1-2': (1, 2), '2-3': (2, 3)},
        trip_branch_ids=(), wall_s=0.0)


def _scenario(**impairments: float) -> Scenario:
    return Scenario(name='toy', description='', path=Path('toy.yaml'), case=Path('toy'), case_ref='toy', dispatch=None,
                    load_scale=1.0, step_s=0.01, end_s=4.0, faults=(), trips=(), rate_fps=60, pmu_buses=None,
                    noise_tve=0.01, seed=5, impairments=Impairments(**impairments), request_s=3.0)


def test_measurement_noise_stays_within_tve_and_angles_are_continuous() -> None:
    sim = _simulation()
    pmu = measure(sim, _scenario())
    assert pmu.buses == (1, 2)
    assert np.allclose(pmu.tag_s, np.arange(241) / 60)
    true_v = np.interp(pmu.tag_s, sim.t_s, sim.bus_angle_rad[:, 1])
    measured = pmu.v_mag_pu[:, 1] * np.exp(1j * pmu.v_angle_rad[:, 1])
    tve = np.abs(measured - np.exp(1j * true_v))
    assert tve.max() <= 0.01 + 1e-12
    assert tve.mean() > 0.001  # noise is really there
    assert pmu.v_angle_rad[-1, 1] > 2 * np.pi  # unwrapped, not folded into (-pi, pi]
    assert np.max(np.abs(np.diff(pmu.i_angle_rad[:, 1]))) < 0.5
    # I = conj(S / V) with S = 0.5 + 0.1j and |V| = 1: |I| = |S|
    assert np.allclose(np.median(pmu.i_mag_pu[:, 0]), abs(0.5 + 0.1j), rtol=0.01)
    # f = 60 + (d angle / dt) / 2 pi: bus 2 runs 3 rad/s fast
    assert np.median(pmu.frequency_hz[:, 1]) == pytest.approx(60 + 3 / (2 * np.pi), abs=0.01)
    assert (pmu.stat == 0).all() and pmu.frame_present.all()
    assert np.array_equal(pmu.delivery_s, pmu.tag_s)


def test_same_seed_same_measurements_and_impairments_leave_the_rest_alone() -> None:
    sim = _simulation()
    a, b = measure(sim, _scenario()), measure(sim, _scenario())
    assert np.array_equal(a.v_angle_rad, b.v_angle_rad)
    other = measure(sim, replace(_scenario(), seed=6))
    assert not np.array_equal(a.v_angle_rad, other.v_angle_rad)
    lossy = measure(sim, _scenario(frame_loss_rate=0.2))
    kept = lossy.stat == 0
    assert np.array_equal(lossy.v_angle_rad[kept], a.v_angle_rad[kept])


def test_impairments_frame_loss_gap_silence_and_delay() -> None:
    sim = _simulation()
    pmu = measure(sim, _scenario(frame_loss_rate=0.2))
    lost = pmu.stat == STAT_DATA_INVALID
    assert 0.15 < lost.mean() < 0.25
    assert np.isnan(pmu.v_mag_pu[lost]).all() and not np.isnan(pmu.v_mag_pu[~lost]).any()
    assert np.array_equal(pmu.frame_present, ~lost.all(axis=1))

    gap = measure(sim, _scenario(initial_gap_s=1.5))
    assert not gap.frame_present[gap.tag_s < 1.5].any() and gap.frame_present[gap.tag_s >= 1.5].all()

    silent = measure(sim, _scenario(silent_pmu_bus=2, silent_from_s=2.0))
    after = silent.tag_s >= 2.0
    assert (silent.stat[after, 1] == STAT_DATA_INVALID).all() and (silent.stat[:, 0] == 0).all()
    assert (silent.stat[~after, 1] == 0).all() and silent.frame_present.all()

    late = measure(sim, _scenario(delay_mean_s=0.1, delay_jitter_s=0.03))
    assert (late.delivery_s >= late.tag_s).all()
    assert np.mean(late.delivery_s - late.tag_s) == pytest.approx(0.1, abs=0.01)
    order = np.argsort(late.delivery_s, kind='stable')
    assert (np.diff(late.tag_s[order]) < 0).any()  # some frames arrive out of order


def test_time_tags_and_branch_ids() -> None:
    assert time_tags(1.0, 30).tolist() == [k / 30 for k in range(31)]
    assert len(time_tags(0.99, 60)) == math.floor(0.99 * 60) + 1
    assert branch_ids([(1, 2), (2, 3), (2, 1), (1, 2)]) == ['1-2', '2-3', '2-1#2', '1-2#3']


def test_a_negative_andes_voltage_is_reported_as_a_pmu_reports_it_in_the_bag_and_the_live_stream() -> None:
    """ANDES may carry a bus at V < 0 (the phasor turned by pi): a PMU reports |V| and the turned angle."""
    from controlled_islanding.sim.closed_loop import Sample
    from controlled_islanding.sim.pmu import PmuStream

    sim = _simulation()
    flip = sim.t_s >= 2.0
    v = np.where(flip[:, None] & (np.arange(3) == 1), -1.5, 1.0)  # bus 2 at -1.5 pu from 2 s, as IEEE 39's bus 32
    sim = replace(sim, bus_v_pu=v)
    scenario = replace(_scenario(), noise_tve=0.0)
    pmu = measure(sim, scenario)
    truth = np.interp(pmu.tag_s, sim.t_s, v[:, 1]) * np.exp(1j * np.interp(pmu.tag_s, sim.t_s, sim.bus_angle_rad[:, 1]))
    late = pmu.tag_s >= 2.0 + 1 / 60
    assert (pmu.v_mag_pu >= 0).all()
    assert np.allclose(pmu.v_mag_pu[late, 1], 1.5)
    assert np.allclose(pmu.v_mag_pu[:, 1] * np.exp(1j * pmu.v_angle_rad[:, 1]), truth)

    stream = PmuStream(scenario, sim.generator_names, sim.generator_buses, sim.bus_numbers, 60.0)
    frames = [f for k in range(len(sim.t_s)) for f in stream.feed(Sample(
        t_s=float(sim.t_s[k]), bus_v_pu=v[k], bus_angle_rad=sim.bus_angle_rad[k], delta_rad=sim.delta_rad[k],
        omega_pu=np.ones(2), p_pu=sim.p_pu[k], q_pu=sim.q_pu[k]))]
    live = np.array([f.v_mag_pu[1] * np.exp(1j * f.v_angle_rad[1]) for f in frames])
    assert min(f.v_mag_pu.min() for f in frames) >= 0
    assert np.allclose(live, truth[:len(live)])
