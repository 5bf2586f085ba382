"""Rotor angles by dynamic state estimation (core/dse.py) against ANDES' own rotor angles on short runs.

Two ANDES runs of 1.5 simulated seconds each, shared by the tests: IEEE 14 (GENROU, a bus fault cleared
by a line trip) and the PJM 5-bus system (GENCLS, a line trip). The PMU phasors come from sim/pmu.py with
its noise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controlled_islanding.core.dse import DSEError, MachineData, RotorAngleDSE, saturation_coefficients
from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad

_IEEE14 = """\
name: dse_ieee14
case: ieee14/ieee14_full.xlsx
step_s: 0.008333333333333333
end_s: 1.5
events:
  - {type: fault, bus: 4, start_s: 0.3, clear_s: 0.4}
  - {type: trip, branch: 4-5, t_s: 0.4}
pmu: {rate_fps: 60, noise_tve: 0.005}
seed: 3
islanding_request_s: 1.4
"""

_PJM5 = """\
name: dse_pjm5
case: 5bus/pjm5bus.xlsx
case_events: disable
step_s: 0.008333333333333333
end_s: 1.5
events:
  - {type: trip, branch: 0-4, t_s: 0.3}
pmu: {rate_fps: 60, noise_tve: 0.005}
seed: 4
islanding_request_s: 1.4
"""


class Run:
    """One short ANDES run as the estimator sees it: times, per-machine phasors, truth and machine data."""

    def __init__(self, tmp: Path, text: str) -> None:
        from controlled_islanding.sim.andes_sim import simulate
        from controlled_islanding.sim.pmu import measure
        from controlled_islanding.sim.scenario import load_scenario

        path = tmp / 'scenario.yaml'
        path.write_text(text)
        scenario = load_scenario(path)
        sim = simulate(scenario, progress=False)
        pmu = measure(sim, scenario)
        assert pmu.station_ids == tuple(f'PMU_{b}' for b in sim.generator_buses)  # one machine per bus
        self.t_s = pmu.tag_s
        self.phasors = [pmu.v_mag_pu, pmu.v_angle_rad, pmu.i_mag_pu, pmu.i_angle_rad]
        self.truth_rad = pmu.truth_delta_rad
        # The machine data the run's snapshot carries (sim/andes_sim.py), as pmu_ingestion gets them.
        generators = {g.name: g for g in sim.grid.generators}
        self.machines = MachineData.of_generators([generators[n] for n in sim.generator_names])
        self.event_s = min([f.start_s for f in scenario.faults] + [t.t_s for t in scenario.trips])

    def error_deg(self, angle_rad: np.ndarray) -> np.ndarray:
        return np.degrees(np.abs(np.angle(np.exp(1j * (angle_rad - self.truth_rad)))))


@pytest.fixture(scope='module')
def ieee14(tmp_path_factory) -> Run:
    return Run(tmp_path_factory.mktemp('ieee14'), _IEEE14)


@pytest.fixture(scope='module')
def pjm5(tmp_path_factory) -> Run:
    return Run(tmp_path_factory.mktemp('pjm5'), _PJM5)


def test_genrou_dse_follows_andes_through_a_fault_where_the_steady_state_estimate_does_not(ieee14: Run) -> None:
    dse = RotorAngleDSE().fit(ieee14.machines)
    assert set(dse.models_) == {'genrou'}
    est = dse.track(ieee14.t_s, *ieee14.phasors)
    steady = estimate_rotor_angle_rad(*ieee14.phasors, ieee14.machines.xq_pu, ieee14.machines.ra_pu)
    after = ieee14.t_s >= ieee14.event_s
    err, err_steady = ieee14.error_deg(est), ieee14.error_deg(steady)
    assert np.isfinite(est).all()
    # Before the event both see a machine at rest; saturation (S(1.0) = 0.09) already costs the steady state
    # degrees there, as the bag tests record.
    assert np.percentile(err[~after], 99) < 0.5
    assert np.percentile(err[after], 99) < 3.0
    assert np.percentile(err[after], 99) < 0.25 * np.percentile(err_steady[after], 99)
    assert np.median(err[after]) < 0.3


def test_classical_dse_tracks_a_gencls_machine(pjm5: Run) -> None:
    dse = RotorAngleDSE().fit(pjm5.machines)
    assert set(dse.models_) == {'classical'}
    est = dse.track(pjm5.t_s, *pjm5.phasors)
    swing = np.ptp(pjm5.truth_rad[pjm5.t_s >= pjm5.event_s] - pjm5.truth_rad[0], axis=0)
    assert np.degrees(swing.max()) > 5.0  # the trip really moves the machines
    assert np.percentile(pjm5.error_deg(est), 99) < 0.5


def test_a_gap_is_bridged_by_prediction_and_a_longer_one_reinitialises(ieee14: Run) -> None:
    gap = (ieee14.t_s >= 0.5) & (ieee14.t_s < 1.0)  # 0.5 s of lost frames during the swing after clearing
    lost = [np.where(gap[:, None], np.nan, x) for x in ieee14.phasors]
    bridged = RotorAngleDSE(max_gap_s=1.0).fit(ieee14.machines)
    est = bridged.track(ieee14.t_s, *lost)
    assert np.isfinite(est).all()
    assert (bridged.n_initialisations_ == 1).all()
    err = ieee14.error_deg(est)
    # Blind for 0.5 s, the prediction drifts (mostly with the system's frequency); the data bring it back.
    settled = ieee14.t_s >= 1.3
    assert np.percentile(err[settled], 99) < 2.5
    assert err[settled].max() < err[gap].max()

    limited = RotorAngleDSE(max_gap_s=0.2).fit(ieee14.machines)
    est = limited.track(ieee14.t_s, *lost)
    last_valid_s = ieee14.t_s[ieee14.t_s < 0.5][-1]
    late = gap & (ieee14.t_s - last_valid_s > 0.2)
    assert np.isnan(est[late]).all()
    assert np.isfinite(est[gap & ~late]).all() and (gap & ~late).sum() >= 10
    assert (limited.n_initialisations_ == 2).all()
    assert np.isfinite(est[~late]).all()
    # Re-initialised on the 2 pi branch nearest the last angle, and converging again.
    assert np.abs(est[settled] - ieee14.truth_rad[settled]).max() < np.pi
    assert np.percentile(ieee14.error_deg(est)[settled], 99) < 5.0


def test_a_stat_flagged_frame_counts_as_lost(ieee14: Run) -> None:
    k = int(np.searchsorted(ieee14.t_s, 0.5))
    t = ieee14.t_s[:k + 3]  # a few frames past the flagged one are enough
    garbage = [x[:k + 3].copy() for x in ieee14.phasors]
    for x in garbage:
        x[k] = 5.0  # what a PMU might send with STAT flagging its data invalid
    valid = np.ones_like(garbage[0], dtype=bool)
    valid[k] = False
    lost = [x[:k + 3].copy() for x in ieee14.phasors]
    for x in lost:
        x[k] = np.nan
    flagged = RotorAngleDSE().fit(ieee14.machines).track(t, *garbage, valid=valid)
    dropped = RotorAngleDSE().fit(ieee14.machines).track(t, *lost)
    assert flagged == pytest.approx(dropped, abs=1e-12)
    unflagged = RotorAngleDSE().fit(ieee14.machines).track(t, *garbage)
    assert np.abs(unflagged[k] - flagged[k]).max() > 1e-3  # the garbage would have mattered


@pytest.mark.parametrize('run_name', ['ieee14', 'pjm5'])
def test_the_innovation_of_a_time_shift_is_far_beyond_the_gate_and_the_gate_keeps_it_out(run_name, request) -> None:
    """A +20 degree step on both phasors of one machine (a GPS time shift): its NIS, and the gate's effect."""
    run: Run = request.getfixturevalue(run_name)
    k = int(np.searchsorted(run.t_s, 0.8))
    t = run.t_s[:k + 1]
    honest = RotorAngleDSE(innovation_gate=55.0).fit(run.machines)
    honest.track(t, *(x[:k + 1] for x in run.phasors))
    assert np.nanmax(honest.nis_) < 55.0 and np.isfinite(honest.nis_).all()
    shifted = [x[:k + 1].copy() for x in run.phasors]
    for x in (shifted[1], shifted[3]):
        x[k, 0] += np.deg2rad(20.0)
    gated = RotorAngleDSE(innovation_gate=55.0).fit(run.machines)
    angles = gated.track(t, *shifted)
    assert gated.nis_[0] > 10 * 55.0 and np.nanmax(gated.nis_[1:]) < 55.0
    ungated = RotorAngleDSE().fit(run.machines)
    taken = ungated.track(t, *shifted)
    assert ungated.nis_[0] == pytest.approx(gated.nis_[0])
    # Gated, the machine's angle is the filter's prediction; taken, the step pulls it.
    assert abs(angles[k, 0] - run.truth_rad[k, 0]) < 0.01 < abs(taken[k, 0] - run.truth_rad[k, 0])


def test_model_cap_and_fallbacks(ieee14: Run) -> None:
    m = ieee14.machines
    assert RotorAngleDSE(model='two_axis').fit(m).models_ == ('two_axis',) * len(m.names)
    partial = MachineData(names=('a', 'b', 'c'), m_s=[8.0, np.nan, np.nan], d_pu=[0.0, 0.0, 0.0],
                          xd1_pu=[0.3, 0.3, np.nan], xq_pu=[np.nan, 0.7, np.nan])
    dse = RotorAngleDSE().fit(partial)
    assert dse.models_ == ('classical', 'steady_state', '')
    v = np.ones(3)
    i = np.full(3, 0.5)
    out = dse.update(0.0, v, np.zeros(3), i, np.full(3, -0.1))
    assert np.isfinite(out[:2]).all() and np.isnan(out[2])
    assert out[1] == pytest.approx(np.angle(1 + 0.7j * 0.5 * np.exp(-0.1j)))


def test_bad_settings_and_frames_are_named() -> None:
    m = MachineData(names=('a',), m_s=[8.0], d_pu=[0.0], xd1_pu=[0.3])
    with pytest.raises(DSEError, match='model'):
        RotorAngleDSE(model='sixth').fit(m)
    with pytest.raises(DSEError, match='max_gap_s'):
        RotorAngleDSE(max_gap_s=0).fit(m)
    with pytest.raises(DSEError, match='one value per machine'):
        MachineData(names=('a', 'b'), m_s=[8.0])
    dse = RotorAngleDSE().fit(m)
    dse.update(1.0, [1.0], [0.0], [0.5], [0.0])
    with pytest.raises(DSEError, match='not after'):
        dse.update(1.0, [1.0], [0.0], [0.5], [0.0])
    with pytest.raises(DSEError, match='one value per machine'):
        dse.update(2.0, [1.0, 1.0], [0.0], [0.5], [0.0])


def test_saturation_coefficients_as_andes() -> None:
    # The quadratic curve must pass through its two data points (ieee14_full.xlsx GENROU: 0.09, 0.38).
    a, b = saturation_coefficients(np.array([0.09, 0.0]), np.array([0.38, 0.0]))
    s = np.array([0.09, 0.38])
    assert b[0] * (np.array([1.0, 1.2]) - a[0]) ** 2 / np.array([1.0, 1.2]) == pytest.approx(s)
    assert b[1] == 0.0


@pytest.mark.parametrize('diagonal', [[4e-4, 1e-4, 9e-6], [4e-4, 1e-4, -1e-18]])
def test_sigma_points_carry_the_covariance_and_survive_an_indefinite_one(diagonal) -> None:
    # Rounding can leave a covariance a hair from positive definite: the kernel then takes its eigen square root
    # (negative eigenvalues as 0) instead of Cholesky's; both give 2n points with the covariance's mean and spread.
    from controlled_islanding.core import dse_kernel

    rng = np.random.default_rng(5)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    cov = q @ np.diag(diagonal) @ q.T
    x = np.array([0.3, 1.0, 0.8])
    pts = np.empty((6, 3))
    dse_kernel._sigma_points(x, cov, np.empty((3, 3)), pts)
    dev = pts - x
    assert pts.mean(axis=0) == pytest.approx(x, abs=1e-15)
    assert dev.T @ dev / len(pts) == pytest.approx(q @ np.diag(np.maximum(diagonal, 0.0)) @ q.T, abs=1e-15)


@pytest.mark.parametrize('kind, n', [(0, 3), (1, 6), (2, 8)])
def test_points_stepped_together_equal_each_stepped_alone(kind, n) -> None:
    # The kernel takes a machine's points through RK4 stage by stage across points (the rates vectorised, GENROU's
    # padded with copies, the trigonometry shared with the mean's where the angles are equal); every point must
    # come out bit for bit as RK4 on that point alone, through the same rates.
    from controlled_islanding.core import dse_kernel as kern

    rng = np.random.default_rng(kind)
    par = np.array([8.0, 0.5, 0.0, 0.3, 1.8, 1.7, 0.5, 6.0, 0.5, 0.2, 0.2, 0.1, 0.03, 0.05, 0.8, 0.1, 0.5, 0.5, 2.0,
                    2.0, 1.0])
    prm = kern._machine_values(kind, par)
    mean = np.array({3: [0.4, 1.002, 0.8], 6: [0.4, 1.002, 1.0, 0.3, 0.8, 1.6],
                     8: [0.4, 1.002, 1.0, 0.3, 0.9, 0.4, 0.8, 1.6]}[n])
    cov = np.diag(rng.uniform(1e-6, 1e-3, n))
    pts = np.empty((2 * n, n))
    kern._sigma_points(mean, cov, np.empty((n, n)), pts)
    steps, h, omega = 2, 1.0 / 120.0, 2 * np.pi * 60.0
    inp = rng.uniform(0.5, 1.0, (steps, 3, 3))
    memo1 = kern._memo(kind, mean[0])
    memo2 = kern._memo(kind, mean[0] + 0.5 * h * (omega * (mean[1] - 1.0)))
    alone = pts.copy()
    no_memo = kern._memo(kind, np.nan)
    for x in alone:
        for q in range(steps):
            ks = []
            for f, at in ((0.0, 0), (0.5 * h, 1), (0.5 * h, 1), (h, 2)):
                stage = x if not ks else x + f * ks[-1]
                out = np.empty(n)
                kern._derivative(kind, stage, *inp[q, at], False, prm, omega, no_memo, out)
                ks.append(out)
            x += (h / 6.0) * (ks[0] + 2 * ks[1] + 2 * ks[2] + ks[3])
    ncol = 32 if kind == 2 else 2 * n
    together = pts.copy()
    kern._propagate(kind, together, steps, h, inp, memo1, memo2, False, prm, omega, np.empty((6, 2 * n)),
                    np.empty((10, ncol)), np.empty((6, ncol)), np.empty((6, 2 * n)))
    assert np.array_equal(together, alone)
    assert not np.array_equal(together, pts)


def test_time_constants_a_model_does_not_use_may_be_zero() -> None:
    # The kernel takes reciprocals of the time constants once per frame: only those of each machine's model.
    machines = MachineData(names=('A', 'B'), m_s=[8.0, 8.0], d_pu=[0.0, 0.0], xd1_pu=[0.3, 0.3],
                           xd_pu=[np.nan, 1.8], xq_pu=[1.7, 1.7], xq1_pu=[np.nan, 0.5], td10_s=[0.0, 6.0],
                           tq10_s=[0.0, 0.5], td20_s=[0.0, 0.0], tq20_s=[0.0, 0.0])
    dse = RotorAngleDSE().fit(machines)
    assert dse.models_ == ('classical', 'two_axis')
    for k in range(3):
        angles = dse.update(k / 60.0, [1.0, 1.0], [0.1, 0.1], [0.8, 0.8], [-0.1, -0.1])
    assert np.isfinite(angles).all()
