"""Rotor angles by dynamic state estimation: an unscented Kalman filter per machine (Algorithm 1, step 1, KF route).

Why: the steady-state estimate, the angle of E = V + (ra + j xq) I, holds only while the machine's flux states
stand still. After a fault they move for seconds (GENROU), and the estimate is off by tens of degrees just when
coherency is assessed. A filter on a machine model follows the flux states instead of assuming them.

Frame and conventions (those of ANDES, PSS/E and core/rotor_angle.py): phasors are against the nominal-frequency
reference; the machine's q axis leads its d axis; a network phasor X and its dq parts satisfy
X = (x_d + j x_q) e^(j(delta - pi/2)). All per unit on the system base (M = 2H in s on the system base, as
ANDES' ``M.v``); I is the current leaving the machine.

Models (``MODELS``, picked per machine by what its data allows, or capped by the ``model`` setting):
- ``classical``: delta, omega and the mechanical torque tm behind a constant E' and x'd (needs M, D, x'd).
- ``two_axis``: fourth-order, delta, omega, e'q, e'd, plus tm and the field voltage vf (needs also xd, xq, x'q,
  T'd0, T'q0).
- ``genrou``: sixth-order, the GENROU equations of PSS/E and ANDES with quadratic saturation: delta, omega, e'q,
  e'd, e''d, e''q, plus tm and vf (needs also x''d, x''q, xl, T''d0, T''q0, S(1.0), S(1.2)).
- ``steady_state``: no dynamic data; the angle of V + (ra + j xq) I, as core/rotor_angle.py.

Field voltage and mechanical torque are filter states following a random walk, not inputs: a PMU measures neither,
and the exciter and governor models and their data are the least reliable part of a dynamic data set (or absent).
Their effect on the angle passes through T'd0 (seconds) and the inertia, so the filter tracks them from the
currents as they drift; the random walk's intensity allows a field forcing to its ceiling within a fraction of a
second and a governor's change of several tenths of the output within a second.

Filter design: inputs are the measured terminal voltage V and current I (linearly interpolated between frames),
and the measurement is the voltage behind the model's stator impedance, z = V + (ra + j x_s) I, with x_s = x'd
(classical, two-axis) or x''d (genrou); the model predicts z from its states alone (plus a saliency term in the
measured current where x_s differs between the axes). This is the current measurement of the usual design
(V input, I measured) rearranged: solving the stator for I = (E - V) / (ra + j x_s) from the states makes the
flux equations stiff where x''d is small (ieee39's G1: x''d = 0.0008 pu on the system base gives a 0.8 ms time
constant, 20 times shorter than a 60 fps frame), while with the measured current they keep their open-circuit
time constants. The torque of the swing equation is the measured electrical torque Re(V conj I) + ra |I|^2.

The filter is the unscented transform with kappa = 0 (the cubature rule: 2n equally weighted points), which needs
no tuning and never has negative weights. Process noise is additive, scaled per machine by its initial output;
measurement noise follows the total vector error (C37.118 allows 1 %) of V and of I seen through x_s; below the
bottom of the measuring range (10 % of rated, where the standard sets no accuracy) V's error is taken as at that
magnitude, since a converter's error floor is in volts.

Between frames the inputs are taken to change linearly, but a fault or a switching makes them jump at an unknown
instant within the frame; the covariance is widened by that uncertainty (the change of the state derivative
between the frame's two inputs, times the step, uniform over the step), which is what keeps the filter from
trusting its prediction across a fault's inception or clearing.

Lost and flagged data: a machine whose phasors are NaN or flagged invalid in a frame gets a prediction-only step:
the voltage and current held, the electrical torque taken equal to the mechanical one (holding the last measured
one would keep accelerating the machine), and the speed's uncertainty growing by a random walk of the size of a
swing. The first frame after at most ``resume_span_s`` of lost ones is stepped again from the last valid frame, with
the inputs linear across the loss, as between any two frames (a fault's inception while the data were lost is then
an input that jumped at an unknown instant, which the covariance allows); after a longer loss it counts as blind too
(its held inputs are stale), and the covariance is first widened by what the unseen inputs may have done over the
span (core/dse_kernel.py's widen_span). When no machine's data came for longer than ``resume_span_s`` (the whole
stream silent), the innovations are judged again only ``judge_after_s`` after its return. After a gap longer than
``max_gap_s`` the estimate is withdrawn (NaN) and the machine is re-initialised at its next valid frame, from the
steady-state relations, on the 2 pi branch nearest its last angle. Frames must come in time order.
Each model class runs one bank of filters for all its machines: one call per frame of the compiled step in
core/dse_kernel.py (numpy call overhead made the batched numpy version cost 2 to 11 ms per frame).
"""

from __future__ import annotations

import copy
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from controlled_islanding.core.bad_data import MEASURING_RANGE_FLOOR_PU, nominal_of

__all__ = ['DSEError', 'MODELS', 'MachineData', 'RotorAngleDSE', 'StreamingDSE', 'nominal_hz',
           'saturation_coefficients']

MODELS = ('steady_state', 'classical', 'two_axis', 'genrou')
_HALF_PI = 0.5 * np.pi


class DSEError(ValueError):
    """Machine data, settings or frames the estimator cannot use."""


def nominal_hz(frequency_hz) -> float:
    """Return the nominal frequency (50 or 60 Hz) the PMUs report around (bad_data.nominal_of), Hz.

    For a filter (omega_base) whose snapshot does not say.

    Raises:
        DSEError: No finite frequency among them within 5 Hz of 50 or 60 Hz.

    """
    f0 = nominal_of(frequency_hz)
    if math.isnan(f0):
        raise DSEError('no PMU reported a frequency within 5 Hz of 50 or 60 Hz: the nominal frequency is unknown')
    return f0


def saturation_coefficients(s10: np.ndarray, s12: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quadratic saturation A, B of GENROU from S(1.0) and S(1.2), as PSS/E and ANDES define them.

    Se(psi) = B (psi - A)^2 / psi for psi > A, else 0. S(1.2) = 0 is read as 1; S(1.0) = 0 means no saturation.

    Args:
        s10: Saturation factor at 1.0 pu air-gap flux.
        s12: Saturation factor at 1.2 pu.

    Returns:
        (A in pu, B in 1/pu), B = 0 where there is no saturation.

    """
    s10 = np.asarray(s10, dtype=float)
    s12 = np.where(np.asarray(s12, dtype=float) == 0.0, 1.0, s12)
    with np.errstate(divide='ignore', invalid='ignore'):
        a = np.sqrt(s10 * 1.0 / (s12 * 1.2))
        sat_a = 1.2 - (1.0 - 1.2) / (a - 1.0)
        sat_b = s12 * 1.2 * (a - 1.0) ** 2 / (1.0 - 1.2) ** 2
    none = (a == 0) | ~np.isfinite(sat_a) | ~np.isfinite(sat_b)
    return np.where(none, 1.0, sat_a), np.where(none, 0.0, sat_b)


_COLUMNS = ('m_s', 'd_pu', 'ra_pu', 'xd1_pu', 'xd_pu', 'xq_pu', 'xq1_pu', 'td10_s', 'tq10_s', 'xd2_pu',
            'xq2_pu', 'xl_pu', 'td20_s', 'tq20_s', 's10', 's12')
_NEEDS = {'steady_state': ('xq_pu',), 'classical': ('m_s', 'd_pu', 'xd1_pu'),
          'two_axis': ('m_s', 'd_pu', 'xd1_pu', 'xd_pu', 'xq_pu', 'xq1_pu', 'td10_s', 'tq10_s'),
          'genrou': ('m_s', 'd_pu', 'xd1_pu', 'xd_pu', 'xq_pu', 'xq1_pu', 'td10_s', 'tq10_s', 'xd2_pu', 'xq2_pu',
                     'xl_pu', 'td20_s', 'tq20_s', 's10', 's12')}


@dataclass(frozen=True)
class MachineData:
    """Dynamic data of n machines, per unit on the system base; NaN (or None for a whole column) = unknown.

    Attributes:
        names: Machine names.
        m_s: Inertia M = 2H, s, on the system base (ANDES ``M.v``).
        d_pu: Damping, pu torque per pu speed, system base.
        ra_pu: Armature resistance (0 when unknown).
        xd1_pu, xq1_pu: Transient reactances x'd, x'q.
        xd_pu, xq_pu: Synchronous reactances.
        td10_s, tq10_s: Open-circuit transient time constants T'd0, T'q0, s.
        xd2_pu, xq2_pu, xl_pu: Sub-transient reactances x''d, x''q and the leakage reactance.
        td20_s, tq20_s: Open-circuit sub-transient time constants T''d0, T''q0, s.
        s10, s12: Saturation factors S(1.0), S(1.2) (0, 0: none).
        model: Each machine's own model name in the source data (for example ANDES' GENROU, GENCLS); informative.

    """

    names: tuple[str, ...]
    m_s: np.ndarray | None = None
    d_pu: np.ndarray | None = None
    ra_pu: np.ndarray | None = None
    xd1_pu: np.ndarray | None = None
    xd_pu: np.ndarray | None = None
    xq_pu: np.ndarray | None = None
    xq1_pu: np.ndarray | None = None
    td10_s: np.ndarray | None = None
    tq10_s: np.ndarray | None = None
    xd2_pu: np.ndarray | None = None
    xq2_pu: np.ndarray | None = None
    xl_pu: np.ndarray | None = None
    td20_s: np.ndarray | None = None
    tq20_s: np.ndarray | None = None
    s10: np.ndarray | None = None
    s12: np.ndarray | None = None
    model: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        n = len(self.names)
        object.__setattr__(self, 'names', tuple(str(x) for x in self.names))
        for name in _COLUMNS:
            value = getattr(self, name)
            default = 0.0 if name == 'ra_pu' else np.nan
            arr = np.full(n, default) if value is None else np.array(value, dtype=float).reshape(-1)
            if arr.shape != (n,):
                raise DSEError(f'MachineData.{name}: one value per machine ({n}) needed, got shape {arr.shape}')
            if name == 'ra_pu':
                arr = np.where(np.isnan(arr), 0.0, arr)
            object.__setattr__(self, name, arr)
        if self.model and len(self.model) != n:
            raise DSEError(f'MachineData.model: one name per machine ({n}) needed, got {len(self.model)}')

    @classmethod
    def of_generators(cls, generators) -> MachineData:
        """Return the data core.grid.Generator objects carry (their xq, ra and dynamic data), in their order."""
        return cls(names=tuple(g.name for g in generators), model=tuple(str(g.model) for g in generators),
                   **{name: np.array([getattr(g, name) for g in generators], dtype=float) for name in _COLUMNS})

    def same_as(self, other: MachineData) -> bool:
        """Whether two data sets name the same machines, in the same order, with the same data (NaN equal NaN)."""
        return self.names == other.names and tuple(self.model) == tuple(other.model) and all(
            np.array_equal(getattr(self, c), getattr(other, c), equal_nan=True) for c in _COLUMNS)

    def richest_model(self) -> np.ndarray:
        """Return, per machine, the richest model of MODELS its data allows ('' when not even steady_state)."""
        out = np.full(len(self.names), '', dtype=object)
        for model in MODELS:
            ok = np.ones(len(self.names), dtype=bool)
            for col in _NEEDS[model]:
                value = getattr(self, col)
                ok &= np.isfinite(value) & (value >= 0)
            if model != 'steady_state':
                ok &= self.m_s > 0
            if model in ('two_axis', 'genrou'):
                ok &= (self.td10_s > 0) & (self.tq10_s > 0) & (self.xd_pu > self.xd1_pu) & (self.xq1_pu > 0)
            if model == 'genrou':
                ok &= (self.td20_s > 0) & (self.tq20_s > 0) & (self.xd2_pu > 0) & (self.xd1_pu != self.xl_pu) \
                    & (self.xq1_pu != self.xl_pu) & (self.xd_pu != self.xl_pu)
            out[ok] = model
        return out

    def take(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """Return the numeric columns of the given machines."""
        return {name: getattr(self, name)[rows] for name in _COLUMNS}


def _to_dq(x: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Network phasor -> (d, q) parts in the rotor frame at angle delta."""
    y = x * np.exp(-1j * delta)
    return -y.imag, y.real


class _Model:
    """One machine model: state layout and steady-state initialisation, batched over machines (numpy).

    Its dynamics and measurement are in core/dse_kernel.py (_rates, _internal_voltage), under its name in
    _MODEL_CLASSES. Parameters arrive as a dict of arrays, one value per machine.
    """

    states: tuple[str, ...] = ()
    tm_index: int = -1

    def stator_x(self, p: dict) -> np.ndarray:
        return p['xd1_pu']

    def time_constants(self, p: dict) -> list[np.ndarray]:
        return []

    def init(self, v: np.ndarray, i: np.ndarray, p: dict) -> tuple[np.ndarray, np.ndarray]:
        """Steady-state states (g, n) and fixed per-machine values (g,) from one frame's V and I."""
        raise NotImplementedError


class _Classical(_Model):
    states = ('delta_rad', 'omega_pu', 'tm_pu')
    tm_index = 2

    def init(self, v, i, p):
        e = v + (p['ra_pu'] + 1j * p['xd1_pu']) * i
        te = (v * np.conj(i)).real + p['ra_pu'] * np.abs(i) ** 2
        return np.stack([np.angle(e), np.ones_like(te), te], axis=-1), np.abs(e)


class _TwoAxis(_Model):
    states = ('delta_rad', 'omega_pu', 'e1q_pu', 'e1d_pu', 'tm_pu', 'vf_pu')
    tm_index = 4

    def time_constants(self, p):
        return [p['td10_s'], p['tq10_s']]

    def init(self, v, i, p):
        delta = np.angle(v + (p['ra_pu'] + 1j * p['xq_pu']) * i)
        vd, vq = _to_dq(v, delta)
        i_d, i_q = _to_dq(i, delta)
        e1q = vq + p['ra_pu'] * i_q + p['xd1_pu'] * i_d
        e1d = vd + p['ra_pu'] * i_d - p['xq1_pu'] * i_q
        vf = e1q + (p['xd_pu'] - p['xd1_pu']) * i_d
        te = vd * i_d + vq * i_q + p['ra_pu'] * (i_d ** 2 + i_q ** 2)
        return np.stack([delta, np.ones_like(te), e1q, e1d, te, vf], axis=-1), np.zeros_like(te)


class _Genrou(_Model):
    states = ('delta_rad', 'omega_pu', 'e1q_pu', 'e1d_pu', 'e2d_pu', 'e2q_pu', 'tm_pu', 'vf_pu')
    tm_index = 6

    def stator_x(self, p):
        return p['xd2_pu']

    def time_constants(self, p):
        return [p['td10_s'], p['tq10_s'], p['td20_s'], p['tq20_s']]

    @staticmethod
    def gains(p):
        """Return GENROU's gamma_d1, gamma_q1, gamma_d2, gamma_q2, gamma_qd (ANDES' names) from the reactances."""
        xl = p['xl_pu']
        gd1 = (p['xd2_pu'] - xl) / (p['xd1_pu'] - xl)
        gq1 = (p['xq2_pu'] - xl) / (p['xq1_pu'] - xl)
        gd2 = (p['xd1_pu'] - p['xd2_pu']) / (p['xd1_pu'] - xl) ** 2
        gq2 = (p['xq1_pu'] - p['xq2_pu']) / (p['xq1_pu'] - xl) ** 2
        gqd = (p['xq_pu'] - xl) / (p['xd_pu'] - xl)
        return gd1, gq1, gd2, gq2, gqd

    def init(self, v, i, p):
        # ANDES' GENROU initialisation (after OpenIPSL's), which assumes x''d = x''q.
        zs = p['ra_pu'] + 1j * p['xd2_pu']
        psi20 = v + zs * i
        psi_abs, psi_arg = np.abs(psi20), np.angle(psi20)
        gqd = p['gqd']
        se0 = np.where(psi_abs >= p['sat_a'], (psi_abs - p['sat_a']) ** 2 * p['sat_b'] / np.maximum(psi_abs, 1e-9),
                       0.0)
        a = psi_abs * (1 + se0 * gqd)
        b = np.abs(i) * (p['xq2_pu'] - p['xq_pu'])
        rel = psi_arg - np.angle(i)
        delta = np.arctan(b * np.cos(rel) / (b * np.sin(rel) - a)) + psi_arg
        psi2q0, psi2d0 = _to_dq(psi20, delta)
        i_d, i_q = _to_dq(i, delta)
        vd, vq = _to_dq(v, delta)
        te = vd * i_d + vq * i_q + p['ra_pu'] * (i_d ** 2 + i_q ** 2)
        vf = (se0 + 1) * psi2d0 + (p['xd_pu'] - p['xd2_pu']) * i_d
        e1q = i_d * (p['xd1_pu'] - p['xd_pu']) - se0 * psi2d0 + vf
        e1d = i_q * (p['xq_pu'] - p['xq1_pu']) - se0 * gqd * psi2q0
        e2d = i_d * (p['xl_pu'] - p['xd_pu']) - se0 * psi2d0 + vf
        e2q = -i_q * (p['xl_pu'] - p['xq_pu']) - se0 * gqd * psi2q0
        return np.stack([delta, np.ones_like(te), e1q, e1d, e2d, e2q, te, vf], axis=-1), np.zeros_like(te)


_MODEL_CLASSES = {'classical': _Classical, 'two_axis': _TwoAxis, 'genrou': _Genrou}


class _Bank:
    """The batched filter of the machines that share one model."""

    def __init__(self, name: str, model: _Model, rows: np.ndarray, params: dict[str, np.ndarray]) -> None:
        from controlled_islanding.core import dse_kernel

        self.model = model
        self.kind = dse_kernel.KINDS[name]
        self.filter_frame = dse_kernel.filter_frame
        self.widen_span = dse_kernel.widen_span
        self.rows = rows
        self.p = params                                  # (g,) arrays
        # (g, len(PARAMS)), one row per machine, as the kernel reads them; NaN = a value its model does not use
        self.par = np.stack([params.get(k, np.full(len(rows), np.nan)) for k in dse_kernel.PARAMS], axis=-1)
        g, n = len(rows), len(model.states)
        self.x = np.full((g, n), np.nan)
        self.cov = np.zeros((g, n, n))
        self.aux = np.zeros(g)
        self.q_rate = np.zeros((g, n))                   # process noise intensity per state, (unit)^2 / s
        self.step_s = 1.0 / 60.0                         # longest integration step, s
        self.live = np.zeros(g, dtype=bool)              # initialised and within the gap limit
        self.last_t = np.full(g, -np.inf)                # time of the last valid frame, s
        self.v_last = np.zeros(g, dtype=complex)
        self.i_last = np.zeros(g, dtype=complex)
        self.nis = np.full(g, np.nan)                    # normalised innovation squared of the last frame
        self.learn_t = np.full(g, -np.inf)               # since when the filter learns again, s (see nis_)
        self.x_seen = np.full((g, n), np.nan)            # state and covariance after the last valid frame
        self.cov_seen = np.zeros((g, n, n))
        self.turned_slowly = np.ones(g, dtype=bool)      # the last valid frame's phasors turned within the TVE


class RotorAngleDSE:
    """Rotor angles of many machines from their terminal phasors by an unscented Kalman filter per machine.

    Args:
        model: 'auto' (each machine's richest model its data allows) or a name in MODELS: the richest model used;
            machines whose data allow less get less.
        freq_hz: System nominal frequency, Hz.
        max_gap_s: Longest run of missing frames bridged by prediction alone; after a longer one the estimate is
            withdrawn (NaN) and the machine re-initialised at its next valid frame.
        measurement_tve: Total vector error of the phasors, taken as a 3-sigma bound (C37.118: at most 0.01).
        max_step_s: Longest integration (RK4) step, s; None: 0.6 times the machine's shortest time constant,
            capped at 1/60 s, and one step per frame for the classical model (see _step_seconds).
        torque_walk_per_sqrt_s: Random-walk intensity of the mechanical torque, in units of the machine's output
            at initialisation (its apparent power, at least 0.1 pu) per square root of a second.
        field_walk_per_sqrt_s: The same for the field voltage, in units of its value at initialisation (at least 1):
            a high initial response exciter (IEEE 421.2) forces the field to its ceiling, about twice its rated
            value, within 0.1 s: 2 / sqrt(0.1 s) moves it by 2 in 0.1 s at one sigma. At 1, the filter lagged
            IEEE 14's field forcing through its fault by innovations of up to 7.4 sigma.
        flux_noise_per_sqrt_s: Model-error noise of the flux states, in units of the internal voltage.
        init_delta_std_rad: Standard deviation of the initial angle: the steady-state relations the filter starts
            from are exact at rest but not during a swing (after a gap).
        blind_speed_walk_pu_per_sqrt_s: Random walk of the speed while a machine's data are lost (its electrical
            torque is then unknown): after a fault speeds stay within about 1 % of nominal, so 0.005 pu over 1 s.
        innovation_gate: A judged frame (see nis_) whose normalised innovation squared exceeds it does not correct
            its machine's filter: data that contradict the model this far are not let in (core/bad_data.py
            excludes the station from then on). inf: no gate.
        judge_after_s: A machine's innovations are judged only this long after its (re)initialisation, s: the
            steady-state relations the filter starts from hold at rest, and a machine that joins during a swing
            takes a few tenths of a second to be learnt (a Kundur machine at 10 % overspeed: 0.35 s above the
            bound of core/bad_data.py).
        resume_span_s: Longest loss of a machine's data after which the filter steps again from its last valid
            frame, the inputs linear across the loss, rather than on from the blind steps, s: a tenth of a second,
            over which a 1 Hz swing's electrical power stays within (pi f T)^2 / 2, 5 %, of its chord.
        widen_span_s: Longest loss of a machine's data after which its covariance is widened by what the unseen
            inputs may have done (dse_kernel.widen_span), s: a quarter of a 1 Hz swing's period, over which its
            accelerating power runs one way, between its values at the two ends. Past it the blind walk alone
            (widened so over 0.5 s through a swing, IEEE 14's G1 came back on the wrong branch of its angle).

    Attributes (after fit):
        models_: Model used for each machine (a name in MODELS, or '' when the machine has no usable data: NaN).
        delta_rad_: Latest rotor angle per machine, rad, NaN where none (after update).
        omega_pu_: Latest rotor speed per machine, pu (NaN for steady_state machines).
        nis_: Normalised innovation squared of the latest frame per machine: the measured z = V + (ra + j x_s) I
            against the filter's prediction, weighed by their covariance (chi-square with 2 degrees of freedom
            where the model and the noise hold). Judged also where ``valid`` is False but the data are present
            (a suspect station: compared, never corrected), and only where the frame is within the noise model:
            z at least 0.1 pu (the bottom of C37.118.1's measuring range; inside a bolted fault at the terminal V
            is below it but z, carried by the fault current, is not, and a spoofed speed there shows at once: the
            machine accelerates at Pm / M with no electrical output, which the model knows; a dead bus, V and I both
            near zero, is not judged), and the current
            turned against the voltage since the last frame by at most 2 acos(1 - measurement_tve) rad (half-way
            along the chord the filter takes between frames, a phasor turning by phi falls short by
            1 - cos(phi / 2): within the TVE only up to that turn; a machine slipping poles turns further), and
            not within judge_after_s of the machine's (re)initialisation or of the stream's return from a silence of
            every machine longer than resume_span_s, and, the first frame after lost ones, only where the
            phasors turned within that bound at the machine's last valid frame too (where they turned faster, a
            machine slipping poles, the span's unseen path is no chord: Nordic 44's slipping machines were flagged
            on the frame after one or two lost ones). NaN elsewhere, and for steady_state machines.
        tm_pu_: Latest mechanical torque per machine, pu on the system base: the filter's random-walk state, which
            follows a governor's action from the measured swing (NaN for steady_state machines).
        n_initialisations_: Times each machine was (re-)initialised.

    """

    def __init__(self, model: str = 'auto', freq_hz: float = 60.0, max_gap_s: float = 0.5,
                 measurement_tve: float = 0.01, max_step_s: float | None = None, torque_walk_per_sqrt_s: float = 0.3,
                 field_walk_per_sqrt_s: float = 2.0 / math.sqrt(0.1), flux_noise_per_sqrt_s: float = 0.01,
                 init_delta_std_rad: float = 0.1, blind_speed_walk_pu_per_sqrt_s: float = 0.005,
                 innovation_gate: float = math.inf, judge_after_s: float = 0.5, resume_span_s: float = 0.1,
                 widen_span_s: float = 0.25) -> None:
        self.model = model
        self.freq_hz = freq_hz
        self.max_gap_s = max_gap_s
        self.measurement_tve = measurement_tve
        self.max_step_s = max_step_s
        self.torque_walk_per_sqrt_s = torque_walk_per_sqrt_s
        self.field_walk_per_sqrt_s = field_walk_per_sqrt_s
        self.flux_noise_per_sqrt_s = flux_noise_per_sqrt_s
        self.init_delta_std_rad = init_delta_std_rad
        self.blind_speed_walk_pu_per_sqrt_s = blind_speed_walk_pu_per_sqrt_s
        self.innovation_gate = innovation_gate
        self.judge_after_s = judge_after_s
        self.resume_span_s = resume_span_s
        self.widen_span_s = widen_span_s

    # ----------------------------------------------------------------------------------------------------- set-up
    def fit(self, machines: MachineData) -> RotorAngleDSE:
        """Bind the machines' data, choose each machine's model and reset every filter.

        Args:
            machines: Dynamic data of the machines, in the column order of later frames.

        Returns:
            self.

        Raises:
            DSEError: A bad setting.

        """
        if self.model != 'auto' and self.model not in MODELS:
            raise DSEError(f"model must be 'auto' or one of {MODELS}, got {self.model!r}")
        for name in ('freq_hz', 'max_gap_s', 'measurement_tve'):
            if not getattr(self, name) > 0:
                raise DSEError(f'{name} must be > 0, got {getattr(self, name)}')
        if self.max_step_s is not None and not self.max_step_s > 0:
            raise DSEError(f'max_step_s must be > 0 or None, got {self.max_step_s}')
        richest = machines.richest_model()
        cap = len(MODELS) - 1 if self.model == 'auto' else MODELS.index(self.model)
        chosen = np.array([MODELS[min(MODELS.index(m), cap)] if m else '' for m in richest], dtype=object)
        self.machines_ = machines
        self.models_ = tuple(str(m) for m in chosen)
        self._banks: list[_Bank] = []
        for name, cls in _MODEL_CLASSES.items():
            rows = np.flatnonzero(chosen == name)
            if rows.size:
                params = machines.take(rows)
                params['sat_a'], params['sat_b'] = saturation_coefficients(params['s10'], params['s12'])
                if name == 'genrou':
                    params.update(zip(('gd1', 'gq1', 'gd2', 'gq2', 'gqd'), _Genrou.gains(params), strict=True))
                bank = _Bank(name, cls(), rows, params)
                bank.step_s = self._step_seconds(bank)
                self._banks.append(bank)
        self._steady_rows = np.flatnonzero(chosen == 'steady_state')
        self.reset()
        return self

    def fork(self) -> RotorAngleDSE:
        """Return a copy of the filter whose frames leave this one as it is (data and settings shared)."""
        twin = copy.copy(self)
        twin._banks = [copy.copy(bank) for bank in self._banks]
        for bank in twin._banks:
            for name in ('x', 'cov', 'aux', 'q_rate', 'live', 'last_t', 'v_last', 'i_last', 'nis', 'learn_t', 'x_seen',
                         'cov_seen', 'turned_slowly'):
                setattr(bank, name, getattr(bank, name).copy())
        for name in ('delta_rad_', 'omega_pu_', 'tm_pu_', 'nis_', '_steady_last_t', 'n_initialisations_'):
            setattr(twin, name, getattr(self, name).copy())
        return twin

    def reset(self) -> RotorAngleDSE:
        """Forget every filter's state (the next valid frame initialises each machine)."""
        n = len(self.machines_.names)
        for bank in self._banks:
            bank.live[:] = False
            bank.last_t[:] = -np.inf
            bank.learn_t[:] = -np.inf
            bank.x[:] = np.nan
        self._t_s: float | None = None
        self._t_seen: float | None = None  # the newest frame with any machine's data, s
        self.delta_rad_ = np.full(n, np.nan)
        self.omega_pu_ = np.full(n, np.nan)
        self.nis_ = np.full(n, np.nan)
        self.tm_pu_ = np.full(n, np.nan)
        self._steady_last_t = np.full(n, -np.inf)
        self.n_initialisations_ = np.zeros(n, dtype=int)
        return self

    # ----------------------------------------------------------------------------------------------------- frames
    def update(self, t_s: float, v_mag_pu: np.ndarray, v_angle_rad: np.ndarray, i_mag_pu: np.ndarray,
               i_angle_rad: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Take one frame (one value per machine) and return every machine's rotor angle.

        Args:
            t_s: Time tag, s; later than the previous frame's.
            v_mag_pu, v_angle_rad: Terminal voltage phasor per machine, pu, rad; NaN = lost.
            i_mag_pu, i_angle_rad: Current out of the machine per machine, pu on the system base, rad; NaN = lost.
            valid: False where the frame's STAT flags the machine's data invalid (treated as lost); None: all.

        Returns:
            Rotor angle per machine, rad, continuous across frames; NaN before a machine's first valid frame,
            after a gap longer than max_gap_s until its next one, and for machines with no usable data.

        Raises:
            DSEError: Not fitted, arrays of the wrong length, or a time tag not after the previous one.

        """
        if not hasattr(self, 'models_'):
            raise DSEError('fit(machines) first')
        n = len(self.models_)
        arrays = [np.asarray(a, dtype=float).reshape(-1) for a in (v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad)]
        if any(a.shape != (n,) for a in arrays):
            raise DSEError(f'one value per machine ({n}) needed, got shapes {[a.shape for a in arrays]}')
        v = arrays[0] * np.exp(1j * arrays[1])
        i = arrays[2] * np.exp(1j * arrays[3])
        seen = np.isfinite(v) & np.isfinite(i)
        ok = seen.copy()
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool).reshape(-1)
        self.nis_ = np.full(n, np.nan)
        t = float(t_s)
        if self._t_s is not None and not t > self._t_s:
            raise DSEError(f'frame at {t} s is not after the previous one at {self._t_s} s')
        dt = None if self._t_s is None else t - self._t_s
        self._t_s = t
        # Back from a silence of the whole stream longer than a resumed span (a PDC or network outage: no station's
        # act, as core/bad_data.py's hold): a fault's inception within it leaves every filter of its area as uncertain
        # as a (re)initialisation does (a 0.15 s outage at a fault's inception flagged honest stations on every
        # manifest system), so their innovations are judged judge_after_s after the return.
        if seen.any():
            if self._t_seen is not None and t - self._t_seen > self.resume_span_s + 1e-9:
                for bank in self._banks:
                    bank.learn_t = np.where(seen[bank.rows], t, bank.learn_t)
            self._t_seen = t
        for bank in self._banks:
            self._step_bank(bank, t, dt, v[bank.rows], i[bank.rows], ok[bank.rows], seen[bank.rows])
        self._steady_state(t, v, i, ok)
        return self.delta_rad_.copy()

    def track(self, t_s: np.ndarray, v_mag_pu: np.ndarray, v_angle_rad: np.ndarray, i_mag_pu: np.ndarray,
              i_angle_rad: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Reset, then update frame by frame; return the angles of every frame.

        Args:
            t_s: Time tags, s, increasing, shape (n_frames,).
            v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad: Shape (n_frames, n_machines); NaN = lost.
            valid: Same shape, False where STAT flags the data invalid; None: all valid.

        Returns:
            Rotor angles, rad, shape (n_frames, n_machines); see update.

        """
        self.reset()
        t = np.asarray(t_s, dtype=float)
        out = np.full((len(t), len(self.models_)), np.nan)
        for k in range(len(t)):
            out[k] = self.update(t[k], v_mag_pu[k], v_angle_rad[k], i_mag_pu[k], i_angle_rad[k],
                                 None if valid is None else valid[k])
        return out

    # ------------------------------------------------------------------------------------------------- internals
    def _steady_state(self, t: float, v: np.ndarray, i: np.ndarray, ok: np.ndarray) -> None:
        rows = self._steady_rows
        if not rows.size:
            return
        m = self.machines_
        angle = np.angle(v[rows] + (m.ra_pu[rows] + 1j * m.xq_pu[rows]) * i[rows])
        prev = self.delta_rad_[rows]
        near = np.where(np.isfinite(prev), prev + np.angle(np.exp(1j * (angle - prev))), angle)
        gone = t - self._steady_last_t[rows] > self.max_gap_s
        new = np.where(ok[rows], near, np.where(gone, np.nan, prev))
        self._steady_last_t[rows[ok[rows]]] = t
        self.delta_rad_[rows] = new

    def _step_seconds(self, bank: _Bank) -> float:
        if self.max_step_s is not None:
            return self.max_step_s
        # RK4 is stable up to h / T = 2.8 and accurate to about 1e-4 of a step's change at h / T = 0.6.
        constants = [np.min(c) for c in bank.model.time_constants(bank.p)]
        if not constants:
            # The classical model has no time constant: its torque comes from the measured inputs, linear in time
            # over a step, so the speed is a quadratic and the angle a cubic in time (damping aside, whose time
            # constant M/D is seconds), which RK4 integrates exactly in one step of any length.
            return np.inf
        return min([1.0 / 60.0] + [0.6 * c for c in constants])

    def _step_bank(self, bank: _Bank, t: float, dt: float | None, v: np.ndarray, i: np.ndarray,
                   ok: np.ndarray, seen: np.ndarray) -> None:
        gap = t - bank.last_t
        stale = bank.live & ~ok & (gap > self.max_gap_s)
        bank.live &= ~stale
        start = ok & (~bank.live | (gap > self.max_gap_s))
        run = bank.live & ~start
        with np.errstate(invalid='ignore'):
            turn = np.abs(np.angle(v * np.conj(i) * np.conj(bank.v_last * np.conj(bank.i_last))))
            z = v + (bank.p['ra_pu'] + 1j * bank.model.stator_x(bank.p)) * i
            slowly = turn <= 2 * np.arccos(1 - self.measurement_tve)
            # Frames lost before this one: the machine's last valid frame is not the stream's previous one.
            spanned = bank.last_t < t - (np.inf if dt is None else dt) - 1e-9
            judged = ((np.abs(z) >= MEASURING_RANGE_FLOOR_PU) & slowly & (~spanned | bank.turned_slowly)
                      & (t - bank.learn_t >= self.judge_after_s - 1e-9))
        if dt is not None and run.any():
            # Lost data: the last inputs are held (the blind steps give the answers while they last). On the first
            # frame after at most resume_span_s of lost ones the filter starts again from its state after the last
            # valid frame and steps the span with the inputs linear between the two frames, as between any two: a
            # fault's inception or clearing while the data were lost is then within its rule for an input that
            # jumped at an unknown instant, where the blind steps, with no acceleration, had left the machine
            # behind (one frame lost at a fault's inception made honest stations' innovations exceed the bad-data
            # bound on every manifest bag). After a longer loss the swing bends the inputs away from that line: the
            # frame's inputs stand for its whole step, blind.
            # The state after a machine's last valid frame is kept when its data stop, for its return.
            stops = run & ~ok & (bank.last_t >= t - dt - 1e-9)
            bank.x_seen[stops], bank.cov_seen[stops] = bank.x[stops], bank.cov[stops]
            back = run & ok & spanned
            resumed = back & (t - bank.last_t <= self.resume_span_s + 1e-9)
            # Back after blind steps: widened by what the unseen inputs may have done (dse_kernel.widen_span; a
            # machine in a hard swing changed its speed by seven times the blind walk over 0.13 s of lost frames,
            # and its returning frames' honest innovations exceeded the bad-data bound).
            blind_back = back & ~resumed & (t - bank.last_t <= self.widen_span_s + 1e-9)
            if blind_back.any():
                bank.widen_span(bank.kind, bank.x, bank.cov, bank.par, blind_back, bank.v_last, bank.i_last, v, i,
                                t - bank.last_t, 2 * np.pi * self.freq_hz)
            bank.v_last = np.where(back & ~resumed, v, bank.v_last)
            bank.i_last = np.where(back & ~resumed, i, bank.i_last)
            judge = run & seen & judged
            nis = np.full(len(bank.rows), np.nan)
            for span in np.unique(t - bank.last_t[resumed]):
                again = resumed & (np.abs(t - bank.last_t - span) < 1e-9)
                bank.x[again], bank.cov[again] = bank.x_seen[again], bank.cov_seen[again]
                self._filter(bank, again, again, np.zeros_like(again), v, i, span, judge & again)
                nis = np.where(again, bank.nis, nis)
            going = run & ~resumed
            self._filter(bank, going, going & ok, ~ok | back, np.where(ok, v, bank.v_last),
                         np.where(ok, i, bank.i_last), dt, judge & going)
            bank.nis = np.where(resumed, nis, bank.nis)
            self.nis_[bank.rows] = bank.nis
        if start.any():
            self._initialise(bank, start, v, i)
            bank.learn_t[start] = t
        bank.turned_slowly = np.where(ok, slowly, bank.turned_slowly)
        bank.v_last = np.where(ok, v, bank.v_last)
        bank.i_last = np.where(ok, i, bank.i_last)
        bank.last_t = np.where(ok, t, bank.last_t)
        rows = bank.rows
        self.delta_rad_[rows] = np.where(bank.live, bank.x[:, 0], np.nan)
        self.omega_pu_[rows] = np.where(bank.live, bank.x[:, 1], np.nan)
        self.tm_pu_[rows] = np.where(bank.live, bank.x[:, bank.model.tm_index], np.nan)

    def _filter(self, bank: _Bank, run: np.ndarray, correct: np.ndarray, blind: np.ndarray, v_end: np.ndarray,
                i_end: np.ndarray, dt: float, judge: np.ndarray) -> None:
        """Step the machines in run over dt, inputs linear from the last valid ones to v_end, i_end.

        They are corrected where correct and judged where judge; the kernel sets bank.nis.
        """
        if not run.any():
            return
        steps = max(1, int(np.ceil(dt / bank.step_s - 1e-9)))
        bank.filter_frame(bank.kind, bank.x, bank.cov, bank.aux, bank.q_rate, bank.par, run, correct, blind,
                          bank.v_last, v_end, bank.i_last, i_end, v_end, i_end, dt, steps, 2 * np.pi * self.freq_hz,
                          self.measurement_tve / 3.0, MEASURING_RANGE_FLOOR_PU, self.blind_speed_walk_pu_per_sqrt_s,
                          judge, self.innovation_gate, bank.nis)

    def _initialise(self, bank: _Bank, start: np.ndarray, v: np.ndarray, i: np.ndarray) -> None:
        p = {k: val[start] for k, val in bank.p.items()}
        x0, aux = bank.model.init(v[start], i[start], p)
        prev = self.delta_rad_[bank.rows[start]]
        x0[:, 0] = np.where(np.isfinite(prev), prev + np.angle(np.exp(1j * (x0[:, 0] - prev))), x0[:, 0])
        n = x0.shape[1]
        e_mag = np.abs(v[start] + (p['ra_pu'] + 1j * bank.model.stator_x(p)) * i[start])
        scale = np.ones((len(x0), n))
        tm_idx = bank.model.tm_index
        scale[:, tm_idx] = np.maximum(np.abs(v[start] * np.conj(i[start])), 0.1)
        flux = slice(2, tm_idx)
        scale[:, flux] = np.maximum(e_mag, 0.1)[:, None]
        if n > tm_idx + 1:
            scale[:, tm_idx + 1] = np.maximum(np.abs(x0[:, tm_idx + 1]), 1.0)
        std = np.zeros((len(x0), n))
        std[:, 0] = self.init_delta_std_rad
        std[:, 1] = 1e-3
        std[:, flux] = 0.02 * scale[:, flux]
        std[:, tm_idx] = 0.05 * scale[:, tm_idx]
        if n > tm_idx + 1:
            std[:, tm_idx + 1] = 0.1 * scale[:, tm_idx + 1]
        bank.x[start] = x0
        bank.aux[start] = aux
        bank.q_rate[start] = self._noise_rate(bank.model, scale)
        bank.cov[start] = std[:, :, None] ** 2 * np.eye(n)
        bank.live |= start
        self.n_initialisations_[bank.rows[start]] += 1

    def _noise_rate(self, model: _Model, scale: np.ndarray) -> np.ndarray:
        """Process noise intensity per state, (unit)^2 / s, shape (g, n)."""
        n = scale.shape[1]
        q = np.zeros_like(scale)
        q[:, 0] = 1e-8
        q[:, 1] = 1e-8
        tm_idx = model.tm_index
        q[:, 2:tm_idx] = (self.flux_noise_per_sqrt_s * scale[:, 2:tm_idx]) ** 2
        q[:, tm_idx] = (self.torque_walk_per_sqrt_s * scale[:, tm_idx]) ** 2
        if n > tm_idx + 1:
            q[:, tm_idx + 1] = (self.field_walk_per_sqrt_s * scale[:, tm_idx + 1]) ** 2
        return q


@dataclass
class TagGrid:
    """The coarsest grid every time tag seen so far lies on, in periods of a finer grid (see StreamingDSE).

    A stream at R frames/s tags its frames at multiples of 1/R s; on the grid of a rate R divides, its tags
    are every period-th point, period being the gcd of their distances from the first.
    """

    first: int | None = None  # the first tag seen, in periods of the finer grid
    gcd: int = 0  # of the tags' distances from the first (0 while only one tag was seen)

    def add(self, key: int) -> None:
        """Take a tag, in periods of the finer grid."""
        self.first = key if self.first is None else self.first
        self.gcd = math.gcd(self.gcd, abs(key - self.first))

    @property
    def period(self) -> int:
        """The stream's tag period in periods of the finer grid (1 until two tags were seen)."""
        return max(self.gcd, 1)


class StreamingDSE:
    """RotorAngleDSE fed from frames as a PDC delivers them: on a uniform time-tag grid, some late, some never.

    Why: the filter needs its frames in time order, but frames are published on arrival and may overtake each
    other. Every frame is answered when it arrives, and never again:
    - in order (every earlier tag taken or given up): the filter takes it, and its estimate is the answer;
    - ahead of a missing tag: the filter waits for that tag, and the answer comes from a copy of the filter
      taken through the held frames up to this one (the missing tags skipped: inputs linear across them);
    - after its tag was passed: the answer is the filter's estimate interpolated at its tag.
    A tag still missing once a frame more than ``reorder_s`` newer has arrived is lost to the filter (a
    prediction-only step at its tag, as RotorAngleDSE takes a NaN frame): the longer the wait, the more late
    frames the filter uses, at the cost of the copies' work while it waits (never of latency). Gaps longer
    than the filter's ``max_gap_s`` are not stepped through: the filter re-initialises after them.

    Which tags are missing: a stream at R frames/s tags its frames at multiples of 1/R s (C37.118.2 FRACSEC).
    The standard rates at 60 Hz (10, 12, 15, 20, 30 per second) divide 60, those at 50 Hz (10, 25) divide 50,
    so a stream at any of them has its tags on the grid of ``rate_fps`` = 60 (or 50), every 60/R-th point. The
    stream's own grid is the coarsest one every tag seen so far lies on: the gcd of their distances on the
    rate_fps grid. Only a tag on it is waited for and stepped as lost. Without this, a 30 frames/s stream under
    pmu_ingestion's default rate_fps of 60 had every other tag missing: each a prediction-only step taking the
    electrical torque equal to the mechanical one (wrong during a fault), the frame after it blind, every
    answer a copy of the filter, at twice the work (found in the closed-loop testbed on the Kundur and
    GBnetwork streams). A 60 frames/s stream that lost every odd tag since it started is, until an odd one
    comes, the 30 frames/s stream it looks like; from then on the finer grid holds.

    Args:
        machines: The machines' data, in the column order of the frames.
        rate_fps: The finest time-tag grid, frames per second: the configured reporting rate, or any multiple
            of the stream's.
        reorder_s: Longest wait for a missing time tag before the filter counts it as lost, s.
        history_s: How far back a late frame still gets an interpolated estimate, s.
        **settings: RotorAngleDSE settings (model, freq_hz, max_gap_s, ...).

    Attributes:
        dse: The filter (its ``models_`` says which machines fall back to the steady-state estimate).
        lost_frames: Time tags the filter stepped as lost.
        late_frames: Frames that arrived after their tag was passed.
        ahead_frames: Frames answered by a copy of the filter, ahead of a missing tag.
        innovations: (time tag, RotorAngleDSE.nis_) of each frame the filter took, in order, until the caller
            takes them (at most the frames of ``history_s``): a frame's innovation is known only once the filter
            takes it, which is up to ``reorder_s`` after it came.
        omega_pu_, tm_pu_: The rotor speeds (pu) and mechanical torques (pu, system base) of the latest answer, one
            per machine, found as its angles were (the filter's own at an in-order frame, the copy's ahead of a
            missing tag, interpolated for a late frame); NaN where the angle is NaN and for steady-state machines.
            A stability monitor reads them beside the angles.

    """

    def __init__(self, machines: MachineData, rate_fps: float, reorder_s: float = 0.0, history_s: float = 1.0,
                 **settings) -> None:
        if not rate_fps > 0 or not reorder_s >= 0 or not history_s >= 0:
            raise DSEError(f'rate_fps > 0, reorder_s >= 0 and history_s >= 0 needed, got {rate_fps}, {reorder_s}, '
                           f'{history_s}')
        self.dse = RotorAngleDSE(**settings).fit(machines)
        self.rate_fps, self.reorder_s, self.history_s = float(rate_fps), float(reorder_s), float(history_s)
        self._done: int | None = None  # newest time tag (in periods of rate_fps) the filter has taken
        self._grid = TagGrid()  # the stream's own tag grid, in periods of rate_fps
        self._pending: dict[int, tuple] = {}  # key -> (t, v_mag, v_ang, i_mag, i_ang, valid)
        self._history: deque[tuple[float, np.ndarray, np.ndarray]] = deque()  # (t, angles, (speeds, torques))
        self.omega_pu_ = np.full(len(machines.names), np.nan)
        self.tm_pu_ = np.full(len(machines.names), np.nan)
        self.lost_frames = 0
        self.late_frames = 0
        self.ahead_frames = 0
        self.innovations: deque[tuple[float, np.ndarray]] = deque()

    def fallback_names(self) -> tuple[str, ...]:
        """Machines estimated by the steady-state relation (no usable dynamic data), or not at all ('')."""
        return tuple(n for n, m in zip(self.dse.machines_.names, self.dse.models_, strict=True)
                     if m in ('steady_state', ''))

    def offer(self, t_s: float, v_mag_pu: np.ndarray, v_angle_rad: np.ndarray, i_mag_pu: np.ndarray,
              i_angle_rad: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Take one frame and return its rotor angles, rad, one per machine.

        Args:
            t_s: Time tag, s.
            v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad, valid: As RotorAngleDSE.update (NaN or valid False:
                that machine's data are missing from this frame).

        Returns:
            The estimate at this frame's tag (see the class docstring); NaN where there is none (a late frame
            beyond the history, a machine not yet initialised). A repeated tag gets the same kind of answer as
            a late frame.

        """
        key = int(round(t_s * self.rate_fps))
        self._grid.add(key)
        step = self._grid.period
        if (self._done is not None and key <= self._done) or key in self._pending:
            self.late_frames += 1
            return self._interpolate(t_s)
        frame = (t_s, v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad, valid)
        self._pending[key] = frame
        if self._done is None:
            self._done = key - step
        answer = None
        newest = max(self._pending)
        period = 1.0 / self.rate_fps
        while self._pending:
            nxt = self._done + step
            if nxt in self._pending:
                angles = self._take(*self._pending.pop(nxt))
                if nxt == key:
                    answer = angles
                    self.omega_pu_, self.tm_pu_ = self.dse.omega_pu_.copy(), self.dse.tm_pu_.copy()
            elif (newest - nxt) * period > self.reorder_s + 1e-9:
                first = min(self._pending)
                if (first - nxt) * period > self.dse.max_gap_s:
                    self.lost_frames += (first - nxt) // step
                    nxt = first - step  # the filter re-initialises after so long; no need to step through it
                else:
                    self._take(*self._lost(nxt, t_s, key))
                    self.lost_frames += 1
            else:
                break
            self._done = nxt
        if answer is not None:
            return answer
        self.ahead_frames += 1
        return self._ahead(key)

    def _lost(self, key: int, ref_t: float, ref_key: int) -> tuple:
        nan = np.full(len(self.dse.models_), np.nan)
        # Time tags are absolute (large); stepping from a known tag keeps their sub-microsecond part.
        return ref_t + (key - ref_key) / self.rate_fps, nan, nan, nan, nan, np.zeros(len(nan), dtype=bool)

    def _ahead(self, key: int) -> np.ndarray:
        """Estimate at a held frame: a copy of the filter through the held frames up to it."""
        probe = self.dse.fork()
        angles = None
        # The tags still missing are skipped, not stepped as lost: their inputs are taken as linear between
        # the frames around them, the filter's own rule between frames.
        for k in sorted(k for k in self._pending if k <= key):
            angles = probe.update(*self._pending[k])
        self.omega_pu_, self.tm_pu_ = probe.omega_pu_.copy(), probe.tm_pu_.copy()
        return angles

    def _take(self, t: float, v_mag, v_ang, i_mag, i_ang, valid) -> np.ndarray:
        angles = self.dse.update(t, v_mag, v_ang, i_mag, i_ang, valid)
        if np.isfinite(self.dse.nis_).any():
            self.innovations.append((t, self.dse.nis_.copy()))
            while self.innovations[0][0] < t - self.history_s:
                self.innovations.popleft()
        self._history.append((t, angles, np.stack([self.dse.omega_pu_, self.dse.tm_pu_])))
        while self._history and self._history[0][0] < t - self.history_s:
            self._history.popleft()
        return angles

    def _interpolate(self, t: float) -> np.ndarray:
        times = [h[0] for h in self._history]
        k = int(np.searchsorted(times, t))
        if k == len(times) and k and abs(times[-1] - t) < 1e-9:
            self.omega_pu_, self.tm_pu_ = self._history[-1][2].copy()
            return self._history[-1][1].copy()
        if k == 0 or k == len(times):
            nan = np.full(len(self.dse.models_), np.nan)
            self.omega_pu_, self.tm_pu_ = nan.copy(), nan.copy()
            return nan
        (t0, a0, s0), (t1, a1, s1) = self._history[k - 1], self._history[k]
        w = (t - t0) / (t1 - t0)
        self.omega_pu_, self.tm_pu_ = s0 + w * (s1 - s0)
        return a0 + w * (a1 - a0)

