"""The stability predictors (core/stability.py, core/swing_forecast.py) on cases whose answer is known.

A machine against an infinite bus, its fault at the terminals (no electrical power) cleared back onto the same
line: the equal-area criterion gives the critical clearing angle in closed form, so clearing a little before it
must come back and a little after it must slip. Then the real pipeline on two IEEE 39 bags (ANDES runs): the
unstable G6-G7 run alarms before its first slip with the final groups; the paper's case 2 stays quiet.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from controlled_islanding.core.stability import (
    FrameHistory,
    MachineSet,
    SIMEPredictor,
    StabilityError,
    _margin,
    switching,
)
from controlled_islanding.core.swing_forecast import ForecastPredictor

BAGS = Path(__file__).resolve().parents[1] / 'bags'
F0_HZ = 60.0
M_S, P_MAX, P_M = 10.0, 2.0, 1.0  # the machine's inertia (s) and its line's Pmax and its power (pu)
DELTA_S = math.asin(P_M / P_MAX)  # 30 deg
# Equal areas with no electrical power while the fault is on: cos(delta_cr) = (pi - 2 delta_s) sin(delta_s) -
# cos(delta_s); the fault-on swing is delta = delta_s + (omega_base Pm / 2M) t^2.
DELTA_CR = math.acos((math.pi - 2 * DELTA_S) * math.sin(DELTA_S) - math.cos(DELTA_S))
T_CR_S = math.sqrt((DELTA_CR - DELTA_S) / (2 * math.pi * F0_HZ * P_M / (2 * M_S)))
FAULT_S = 1.0


def smib(clear_after_s: float, end_s: float = 3.0, rate_fps: int = 60, tve: float = 0.005, seed: int = 0):
    """Frames of the machine (column 0) and the infinite bus (column 1, M = 1e6 s): t, delta, omega, Pe, V."""
    omega_base = 2 * math.pi * F0_HZ
    dt = 1.0 / (rate_fps * 20)
    d, w = DELTA_S, 1.0
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(int(end_s * rate_fps) + 1):
        t = k / rate_fps
        faulted = FAULT_S <= t < FAULT_S + clear_after_s
        pe = 0.0 if faulted else P_MAX * math.sin(d)
        noise = 1.0 + rng.normal(0.0, tve / 3.0, 2)
        frames.append((t, [d, 0.0], [w, 1.0], [pe * noise[0], -pe * noise[1]],
                       [0.2 if faulted else 1.0, 1.0]))
        for _ in range(20):  # RK4 of the swing equation to the next frame
            def rates(x, y, tt):
                fault_on = FAULT_S <= tt < FAULT_S + clear_after_s
                return omega_base * (y - 1.0), (P_M - (0.0 if fault_on else P_MAX * math.sin(x))) / M_S
            tt = t + _ * dt
            k1 = rates(d, w, tt)
            k2 = rates(d + dt / 2 * k1[0], w + dt / 2 * k1[1], tt + dt / 2)
            k3 = rates(d + dt / 2 * k2[0], w + dt / 2 * k2[1], tt + dt / 2)
            k4 = rates(d + dt * k3[0], w + dt * k3[1], tt + dt)
            d += dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            w += dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
    return frames


def machines() -> MachineSet:
    return MachineSet(names=('G', 'bus'), m_s=np.array([M_S, 1e6]), d_pu=np.zeros(2), pm_pu=np.array([P_M, -P_M]),
                      freq_hz=F0_HZ)


def first_slip_s(frames) -> float | None:
    slips = [t for t, d, *_ in frames if d[0] - d[1] - DELTA_S > math.pi]
    return slips[0] if slips else None


def run(predictor, frames):
    """Feed every frame; return the first alarm's (time, groups, predicted slip) or None."""
    for t, d, w, pe, v in frames:
        predictor.update(t, np.array(d), np.array(w), np.array(pe), np.array(v))
        if predictor.separates_:
            return t, predictor.groups_.copy(), predictor.first_slip_s_
    return None


def test_the_smib_case_is_what_the_equal_area_criterion_says() -> None:
    assert math.degrees(DELTA_CR) == pytest.approx(79.56, abs=0.01)
    assert first_slip_s(smib(0.9 * T_CR_S)) is None
    assert first_slip_s(smib(1.1 * T_CR_S)) is not None


@pytest.mark.parametrize('make', [lambda: SIMEPredictor(machines()), lambda: ForecastPredictor(machines())],
                         ids=['sime', 'forecast'])
def test_a_swing_cleared_before_the_critical_angle_raises_no_alarm(make) -> None:
    assert run(make(), smib(0.9 * T_CR_S)) is None


@pytest.mark.parametrize('make', [lambda: SIMEPredictor(machines()), lambda: ForecastPredictor(machines())],
                         ids=['sime', 'forecast'])
def test_a_swing_cleared_after_the_critical_angle_alarms_before_the_slip_with_its_groups(make) -> None:
    frames = smib(1.1 * T_CR_S)
    slip = first_slip_s(frames)
    alarm = run(make(), frames)
    assert alarm is not None
    t, groups, predicted = alarm
    assert FAULT_S + 1.1 * T_CR_S < t < slip
    assert groups.tolist() == [0, 1]
    assert predicted == pytest.approx(slip, abs=0.1)


def test_the_margin_is_the_kinetic_energy_left_at_the_unstable_equilibrium() -> None:
    # Pa(x) = x - 1 moving forward: decelerating until delta_u one radian ahead, an area of 1/2 pu rad.
    assert _margin(np.array([0.0, 1.0, -1.0]), 1.0, 0.3, 0.5) == pytest.approx((0.2, 1.0))
    assert _margin(np.array([0.0, 1.0, -1.0]), 1.0, 0.8, 0.5)[0] == pytest.approx(-0.3)
    # The same curve mirrored, moving backward.
    assert _margin(np.array([0.0, 1.0, 1.0]), -1.0, 0.8, 0.5)[0] == pytest.approx(-0.3)
    # Decelerating with no rising crossing ahead: the swing returns.
    assert _margin(np.array([-1.0, 0.0, -1.0]), 1.0, 5.0, 0.5)[0] == math.inf
    # Accelerating again past delta_u half a radian behind: the energy gained since is taken back.
    eta, y_u = _margin(np.array([0.0, 1.0, 0.5]), 1.0, 0.3, 1.0)
    assert y_u == pytest.approx(-0.5) and eta == pytest.approx(-(0.3 - 0.125))


def test_switching_is_a_voltage_jump_no_measurement_error_explains() -> None:
    tve = 0.01
    worst = 0.9 * tve  # each magnitude within TVE, the errors alternating: a second difference of 3.6 TVE
    smooth = np.array([[1.0 + worst, 1.0], [1.0 - worst, 1.0], [1.0 + worst, 1.0]])
    assert not switching(smooth, tve)
    assert switching(np.array([[1.0, 1.0], [1.0, 1.0], [0.7, 1.0]]), tve)
    assert not switching(np.array([[np.nan, 1.0], [1.0, 1.0], [0.7, 1.0]]), tve)


def test_the_swing_starts_at_the_frame_before_the_last_flagged_one() -> None:
    history = FrameHistory(machines(), 0.01, 2.0)
    volts = [1.0, 1.0, 1.0, 0.3, 0.3, 0.3, 0.3, 1.0, 1.0, 1.0, 1.0]
    starts = []
    for k, v in enumerate(volts):
        history.take(k * 0.1, [0.5, 0.0], [1.0, 1.0], [1.0, -1.0], [v, 1.0], None, None)
        starts.append(history.swing_start_s)
    assert starts[2] == -math.inf  # nothing yet
    assert starts[3] == math.inf and starts[4] == math.inf  # the fault's jump flags frames 3 and 4
    assert starts[5] == pytest.approx(0.3)  # the faulted network holds from frame 3
    assert starts[8] == math.inf and starts[9] == pytest.approx(0.7)  # cleared at frame 7
    assert history.recovered  # the voltages rose


def test_bad_machine_data_and_frames_are_refused_naming_the_fault() -> None:
    with pytest.raises(StabilityError, match='inertia'):
        MachineSet(names=('a', 'b'), m_s=np.array([1.0, np.nan]), d_pu=np.zeros(2), pm_pu=np.zeros(2))
    with pytest.raises(StabilityError, match='scheduled power'):
        MachineSet(names=('a', 'b'), m_s=np.ones(2), d_pu=np.zeros(2), pm_pu=np.array([1.0, np.nan]))
    predictor = SIMEPredictor(machines())
    predictor.update(1.0, [0.5, 0.0], [1.0, 1.0], [1.0, -1.0])
    with pytest.raises(StabilityError, match='not after'):
        predictor.update(1.0, [0.5, 0.0], [1.0, 1.0], [1.0, -1.0])
    with pytest.raises(StabilityError, match='one value per machine'):
        predictor.update(2.0, [0.5], [1.0, 1.0], [1.0, -1.0])


def test_the_pipeline_on_ieee39_bags_alarms_before_the_slip_and_stays_quiet_on_a_stable_run() -> None:
    from controlled_islanding.evaluation.predictors import report, run_from_bag, study

    names = ('sime', 'forecast')
    unstable = study(run_from_bag(BAGS / 'ieee39_g6g7_unstable'), names=names)
    for name in names:
        assert unstable.lead_s(name) > 0.1, name
        assert unstable.groups_right(name), name
    stable = study(run_from_bag(BAGS / 'ieee39_paper_case2'), names=names)
    assert all(o.alarm_s is None for o in stable.outcomes.values())
    lines = report([unstable, stable], names)
    assert '| sime | 1 / 1 | 1 / 1 | 1 / 1 | 1 / 1 |' in '\n'.join(lines)
    assert any(line.startswith('| ieee39_paper_case2 |') and line.count('quiet') == 2 for line in lines)


def test_a_machine_past_its_unstable_equilibrium_at_the_clearing_alarms_on_the_first_frame_after_it() -> None:
    # Cleared at 1.6 critical clearing times, 30 frames/s: the machine leaves the fault past delta_u and slips
    # three frames later, before the four samples a curve needs (GB network, bus 73).
    frames = smib(1.6 * T_CR_S, rate_fps=30)
    slip = first_slip_s(frames)
    alarm = run(SIMEPredictor(machines()), frames)
    assert alarm is not None
    t, groups, predicted = alarm
    assert t == min(f[0] for f in frames if f[0] > FAULT_S + 1.6 * T_CR_S), 'the first frame after the clearing'
    assert t < slip and groups.tolist() == [0, 1]
    assert t < predicted <= slip + 1 / 30
    # Cleared past the crest but before delta_u: it decelerates after the clearing, so no alarm on that frame.
    frames = smib(1.4 * T_CR_S, rate_fps=30)
    first = min(f[0] for f in frames if f[0] > FAULT_S + 1.4 * T_CR_S)
    alarm = run(SIMEPredictor(machines()), frames)
    assert alarm is None or alarm[0] > first
    # A fault that is never cleared: the voltages never rise, nothing is judged on one frame.
    assert run(SIMEPredictor(machines()), smib(10.0, rate_fps=30)) is None


def test_a_magnitude_a_hair_below_zero_is_no_switching_forever() -> None:
    tve = 0.01
    dead = np.array([[-1.21496e-11, 1.0], [-1.21703e-11, 1.0], [-1.21765e-11, 1.0]])  # as ANDES reported a dead bus
    assert not switching(dead, tve)


def test_the_kth_verdict_of_a_swing_clears_the_bar_that_keeps_one_verdicts_false_alarm_rate() -> None:
    from scipy.stats import norm

    from controlled_islanding.core.stability import _bonferroni

    assert _bonferroni(3.0, 1) == pytest.approx(3.0)
    for k in (2, 16, 120):
        assert k * norm.sf(_bonferroni(3.0, k)) == pytest.approx(norm.sf(3.0))
    assert _bonferroni(3.0, 16) > 3.03 * 1.01, 'the 16th verdict at 1.01 of the bar (IEEE 39 G6-G7 200 ms) is no alarm'
