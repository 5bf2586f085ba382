"""A short-horizon forward simulation of every machine's swing equation: the second predictor of core/stability.py.

The same inputs and interface as core/stability.py's SIMEPredictor (``separates_``, ``groups_``,
``first_slip_s_``, ``confidence_``). Where SIME reduces the machines to one OMIB, this keeps them all:

1. Swings, as SIME: nothing is judged before a network switching, and the present swing's samples start after
   the latest one (core/stability.py's FrameHistory). Only the swing after a switching that raised the terminal
   voltages (a fault cleared) is judged: after one that lowered them the faulted network may still be there,
   and a forecast from it would carry the fault on. And only its first swing: once the two machines farthest
   apart close in again (``first_swing_over``) the swing is survived; each machine's curve of a later swing is
   a loop, no function of its angle.
2. Each machine's accelerating power Pa_i = Pm_i - Pe_i - D_i (omega_i - 1) (Pm_i the filter's torque) as a
   function of its angle against the centre of inertia of all machines, theta_i = delta_i - delta_COI: a
   polynomial fitted to the present swing (least squares). The network is not modelled: the snapshot carries
   no impedances, and each machine's own measured trajectory says how its electrical power answers its angle.
3. From the filter's present angles and speeds, the swing equations M_i d(omega_i)/dt = Pa_i(theta_i),
   d(delta_i)/dt = omega_base (omega_i - 1) are integrated ``horizon_s`` ahead (RK4, compiled as the DSE's
   kernel, core/dse_kernel.py). The first pole slip is the first time two machines' deviations from rest are
   more than pi rad apart; the groups are those of sim/truth.py's rule on the deviations at the end: complete
   linkage of the pair separations cut at pi.
4. A forecast is trusted only while every machine stays within its curve's reach: no further from its samples'
   range than that range is wide (the polynomial is a Taylor expansion about the samples). A pole slip found
   after a machine left its reach is no verdict.
5. Confidence: the forecast is made twice, with quadratic and with cubic curves (the expansion's next term);
   it separates when both find a pole slip within their reach, with the same groups. ``confidence_`` is 1 then
   (and 0 when they disagree): the forecast has no standard error of its own.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

from controlled_islanding.core.stability import POLE_SLIP_RAD, FrameHistory, MachineSet, StabilityError

__all__ = ['ForecastPredictor']


@numba.njit(cache=True)
def _integrate(delta0, omega0, coef, centre, m_s, omega_base, rest, step_s, steps, low, high):
    """RK4 of the swing equations with Pa_i a polynomial in theta_i - centre_i (coef rows, highest power first).

    Returns (slip_step, left_step, delta at the end): the first step at which two machines' deviations from rest
    are pi apart (-1: none), the first at which a machine's theta left [low_i, high_i] (-1: none).
    """
    n = delta0.shape[0]
    degree = coef.shape[1] - 1
    total = 0.0
    for i in range(n):
        total += m_s[i]
    d = delta0.copy()
    w = omega0.copy()
    kd = np.zeros((4, n))
    kw = np.zeros((4, n))
    slip_step, left_step = -1, -1
    for step in range(steps):
        for stage in range(4):
            h = 0.0 if stage == 0 else (0.5 if stage < 3 else 1.0) * step_s
            coi = 0.0
            for i in range(n):
                di = d[i] + (h * kd[stage - 1, i] if stage > 0 else 0.0)
                coi += m_s[i] * di
            coi /= total
            for i in range(n):
                di = d[i] + (h * kd[stage - 1, i] if stage > 0 else 0.0)
                wi = w[i] + (h * kw[stage - 1, i] if stage > 0 else 0.0)
                x = di - coi - centre[i]
                pa = 0.0
                for k in range(degree + 1):
                    pa = pa * x + coef[i, k]
                kd[stage, i] = omega_base * (wi - 1.0)
                kw[stage, i] = pa / m_s[i]
        for i in range(n):
            d[i] += step_s * (kd[0, i] + 2.0 * kd[1, i] + 2.0 * kd[2, i] + kd[3, i]) / 6.0
            w[i] += step_s * (kw[0, i] + 2.0 * kw[1, i] + 2.0 * kw[2, i] + kw[3, i]) / 6.0
        coi = 0.0
        for i in range(n):
            coi += m_s[i] * d[i]
        coi /= total
        lo, hi = np.inf, -np.inf
        for i in range(n):
            dev = d[i] - rest[i]
            lo = min(lo, dev)
            hi = max(hi, dev)
            theta = d[i] - coi
            if left_step < 0 and (theta < low[i] or theta > high[i]):
                left_step = step
        if slip_step < 0 and hi - lo > np.pi:
            slip_step = step
        if slip_step >= 0 and left_step >= 0:
            break
    return slip_step, left_step, d


def _fit_all(theta: np.ndarray, pa: np.ndarray, degree: int) -> np.ndarray | None:
    """Return per machine Pa_i as a polynomial in theta_i - theta_i(now), least squares, highest power first.

    None when a machine has too few measured samples for the degree.
    """
    k, n = theta.shape
    out = np.zeros((n, degree + 1))
    for i in range(n):
        ok = np.isfinite(pa[:, i])
        if ok.sum() < degree + 2:
            return None
        x = theta[ok, i] - theta[-1, i]
        design = np.column_stack([x ** p for p in range(degree, -1, -1)])
        out[i], *_ = np.linalg.lstsq(design, pa[ok, i], rcond=None)
    return out


def first_swing_over(delta: np.ndarray, omega: np.ndarray, rest: np.ndarray) -> bool:
    """Return whether the largest separation of the present swing has turned back.

    At some sample the two machines farthest apart (deviations from rest) were closing in (their speeds). A grid
    that loses synchronism on its first swing separates ever wider until the slip; once the widest pair turns
    back that swing is survived.
    """
    dev = delta - rest
    top, bottom = dev.argmax(axis=1), dev.argmin(axis=1)
    rows = np.arange(len(dev))
    return bool(np.any(omega[rows, top] < omega[rows, bottom]))


def _groups(deviation: np.ndarray) -> np.ndarray:
    """sim/truth.py's rule: complete-linkage clusters of |d_p - d_q| cut at pi, numbered by first member."""
    if len(deviation) < 2:
        return np.zeros(len(deviation), dtype=int)
    sep = np.abs(deviation[:, None] - deviation[None, :])
    raw = fcluster(linkage(squareform(sep, checks=False), method='complete'), POLE_SLIP_RAD, criterion='distance')
    order: dict[int, int] = {}
    return np.array([order.setdefault(int(x), len(order)) for x in raw], dtype=int)


class ForecastPredictor:
    """Forward simulation of every machine's swing from the filter's state (see the module docstring).

    Args:
        machines: The machines (MachineSet), in the frames' column order.
        noise_tve: The PMUs' total vector error bound (the switching test, as SIME's).
        horizon_s: How far ahead the swing equations run, s: 1 s, the first swing of the slowest inter-area
            modes (0.5 to 1 Hz) from its start to its far end.
        step_s: The integration step, s (RK4 on a swing of a few rad/s is exact to 1e-6 rad at 1/120 s).
        history_s: Frames kept, s (as SIME's).

    Attributes (after update):
        separates_, groups_, first_slip_s_, confidence_: see core/stability.py's module docstring.

    """

    def __init__(self, machines: MachineSet, noise_tve: float = 0.01, horizon_s: float = 1.0,
                 step_s: float = 1.0 / 120.0, history_s: float = 2.0) -> None:
        if not (horizon_s > 0 and 0 < step_s <= horizon_s):
            raise StabilityError(f'horizon_s > 0 and 0 < step_s <= horizon_s needed, got {horizon_s}, {step_s}')
        self.machines, self.noise_tve, self.horizon_s, self.step_s = machines, noise_tve, horizon_s, step_s
        self._history = FrameHistory(machines, noise_tve, history_s)
        self.reset()

    def reset(self) -> ForecastPredictor:
        """Forget every frame."""
        self._history.reset()
        n = len(self.machines.names)
        self.separates_, self.groups_, self.first_slip_s_, self.confidence_ = False, np.zeros(n, dtype=int), \
            math.nan, math.nan
        return self

    def fit(self, t_s, delta_rad, omega_pu, pe_pu, v_pu=None, valid=None, pm_pu=None) -> ForecastPredictor:
        """Reset, then take a window frame by frame (as SIMEPredictor.fit)."""
        self.reset()
        for k in range(len(t_s)):
            self.update(t_s[k], delta_rad[k], omega_pu[k], pe_pu[k], None if v_pu is None else v_pu[k],
                        None if valid is None else valid[k], None if pm_pu is None else pm_pu[k])
        return self

    def update(self, t_s: float, delta_rad, omega_pu, pe_pu, v_pu=None, valid=None,
               pm_pu=None) -> ForecastPredictor:
        """Take one frame and forecast (arguments as SIMEPredictor.update)."""
        if not self._history.take(t_s, delta_rad, omega_pu, pe_pu, v_pu, valid, pm_pu):
            return self
        n = len(self.machines.names)
        self.separates_, self.groups_, self.first_slip_s_, self.confidence_ = False, np.zeros(n, dtype=int), \
            math.nan, math.nan
        t, delta, omega, pa = self._history.swing()
        if len(t) < 5 or n < 2 or not self._history.recovered or first_swing_over(delta, omega,
                                                                                   self._history.rest_rad):
            return self
        m = self.machines.m_s
        theta = delta - (delta @ m / m.sum())[:, None]
        low = theta.min(axis=0)
        high = theta.max(axis=0)
        span = high - low
        reach_low, reach_high = low - span, high + span
        answers = []
        for degree in (2, 3):
            coef = _fit_all(theta, pa, degree)
            if coef is None:
                return self
            steps = int(math.ceil(self.horizon_s / self.step_s))
            slip, left, end = _integrate(delta[-1].astype(float), omega[-1].astype(float), coef,
                                         theta[-1].astype(float), m, self.machines.omega_base,
                                         self._history.rest_rad.astype(float), self.step_s, steps,
                                         reach_low, reach_high)
            trusted = slip >= 0 and (left < 0 or slip <= left)
            answers.append((trusted, slip, _groups(end - self._history.rest_rad) if trusted else None))
        (ok2, slip2, g2), (ok3, _, g3) = answers
        agree = ok2 and ok3 and np.array_equal(g2, g3) and g2.max() > 0
        self.confidence_ = 1.0 if agree else 0.0
        if agree:
            self.separates_, self.groups_ = True, g2
            self.first_slip_s_ = float(t[-1]) + (slip2 + 1) * self.step_s
        return self
