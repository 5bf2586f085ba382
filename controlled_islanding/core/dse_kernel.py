"""The compiled step of core/dse.py's filter: one frame's predict and correct for every machine of one model.

Why compiled: per frame the filter is a few hundred operations on arrays of 3 to 16 numbers per machine; as numpy
calls batched over machines, their call overhead, not the arithmetic, took 2 to 11 ms per frame (profiled: about
two thirds in the prediction's RK4 derivatives and sigma points, a third in the correction). Here each machine's
predict and correct are loops with the formulas and operation order of that numpy version, on one core; the
prediction takes the machine's points through RK4 stage by stage, the rates of a stage vectorised across points
(_propagate), and the cosine and sine of an angle a point shares with the mean are computed once (_cos_sin).
Divisions by the inertia, time constants and point count are products by reciprocals, which moves the angles
by rounding only. The equations and the filter design are in core/dse.py's docstring.

A module of its own so that importing core.dse (pmu_ingestion does, whatever its estimator) does not load numba:
RotorAngleDSE.fit imports it, and pmu_ingestion at start when its estimator is dse. Importing it compiles the
kernel, or loads it from numba's cache (tools/setup.sh imports it once, so that the cache exists for every later
process).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ['KINDS', 'PARAMS', 'filter_frame', 'warm_up']

_CLASSICAL, _TWO_AXIS, _GENROU = 0, 1, 2
KINDS = {'classical': _CLASSICAL, 'two_axis': _TWO_AXIS, 'genrou': _GENROU}  # core.dse's model names
# Columns of a bank's parameter matrix (a machine's row): the data the kernel reads, then the derived GENROU
# saturation and gains.
PARAMS = ('m_s', 'd_pu', 'ra_pu', 'xd1_pu', 'xd_pu', 'xq_pu', 'xq1_pu', 'td10_s', 'tq10_s', 'xd2_pu', 'xq2_pu',
           'xl_pu', 'td20_s', 'tq20_s', 'sat_a', 'sat_b', 'gd1', 'gq1', 'gd2', 'gq2', 'gqd')
(_M, _D, _RA, _XD1, _XD, _XQ, _XQ1, _TD10, _TQ10, _XD2, _XQ2, _XL, _TD20, _TQ20, _SAT_A, _SAT_B, _GD1, _GQ1, _GD2,
 _GQ2, _GQD) = range(len(PARAMS))
# Positions in the tuple of _machine_values
(_PM, _PD, _PXD_XD1, _PXQ_XQ1, _PTD10, _PTQ10, _PXD1_XL, _PXQ1_XL, _PTD20, _PTQ20, _PGD1, _PGQ1, _PGD2, _PGQ2, _PGQD,
 _PGD1C, _PGQ1C, _PSAT_A, _PSAT_B) = range(19)


@numba.njit(cache=True, inline='always')
def _rates(kind, s, trig, tm, vf, ir, ii, te_in, blind, prm, omega_base):
    """Rates (per second) of the states s = (delta, omega, e'q, e'd, e''d, e''q) of one machine at stage inputs.

    The states a model lacks are 0 in s and their rates are 0; the torque tm and the field voltage vf are random
    walks (rate 0). trig: (cos, sin) of delta, from _cos_sin. ir, ii: terminal current (network frame); te_in:
    the measured electrical torque, unused when blind. prm: the machine's values from _machine_values.
    """
    d, w, e1q, e1d, e2d, e2q = s
    # Without data the electrical torque is unknown: the mechanical one is its best guess (no acceleration but
    # the damping's); holding the last measured one would keep accelerating the machine.
    te = tm if blind else te_in
    slip = w - 1.0
    r_d = omega_base * slip
    r_w = (tm - te - prm[_PD] * slip) * prm[_PM]
    if kind == _CLASSICAL:
        return r_d, r_w, 0.0, 0.0, 0.0, 0.0
    c, sn = trig
    i_d, i_q = ir * sn - ii * c, ir * c + ii * sn
    if kind == _TWO_AXIS:
        return (r_d, r_w, (vf - e1q - prm[_PXD_XD1] * i_d) * prm[_PTD10], (-e1d + prm[_PXQ_XQ1] * i_q) * prm[_PTQ10],
                0.0, 0.0)
    gd1, gq1, gd2, gq2 = prm[_PGD1], prm[_PGQ1], prm[_PGD2], prm[_PGQ2]
    psi2d = gd1 * e1q + prm[_PGD1C] * e2d
    psi2q = gq1 * e1d + prm[_PGQ1C] * e2q
    psi = np.sqrt(psi2d ** 2 + psi2q ** 2)
    over = max(psi - prm[_PSAT_A], 0.0)
    se = prm[_PSAT_B] * over ** 2 / max(psi, 1e-9)
    xad_ifd = e1q + prm[_PXD_XD1] * (gd1 * i_d - gd2 * e2d + gd2 * e1q) + se * psi2d
    xaq_i1q = e1d + prm[_PXQ_XQ1] * (gq2 * e1d - gq2 * e2q - gq1 * i_q) + se * psi2q * prm[_PGQD]
    return (r_d, r_w, (vf - xad_ifd) * prm[_PTD10], -xaq_i1q * prm[_PTQ10],
            (-e2d + e1q - prm[_PXD1_XL] * i_d) * prm[_PTD20], (-e2q + e1d + prm[_PXQ1_XL] * i_q) * prm[_PTQ20])


@numba.njit(cache=True, inline='always')
def _cos_sin(kind, d, memo):
    """Return (cos, sin) of d; memo = (d0, cos d0, sin d0) answers when d equals d0 (no trigonometry: classical).

    Why: the cubature points share the mean's angle but for the two along the first column of the (lower)
    Cholesky factor, and its speed but for four, so most points enter the first two RK4 stages and the correction
    at the same angle; equal inputs give equal values, so this changes no result.
    """
    if kind == _CLASSICAL:
        return 0.0, 0.0
    if d == memo[0]:
        return memo[1], memo[2]
    return np.cos(d), np.sin(d)


@numba.njit(cache=True, inline='always')
def _memo(kind, d):
    """Return (d, cos d, sin d) for _cos_sin (NaN, never equal, for the classical model)."""
    if kind == _CLASSICAL:
        return np.nan, 0.0, 0.0
    return d, np.cos(d), np.sin(d)


@numba.njit(cache=True, inline='always')
def _machine_values(kind, p):
    """Return the values of a parameter row that _rates reads, computed once per frame.

    The inertia and the time constants as reciprocals, so that the rates multiply instead of divide: a division
    costs several products, and this moves the angles by rounding only (at most 1.1e-13 rad on the bags). Only
    the time constants of the model kind: the others may be 0 or NaN.
    """
    td1 = (1.0 / p[_TD10], 1.0 / p[_TQ10]) if kind != _CLASSICAL else (0.0, 0.0)
    td2 = (1.0 / p[_TD20], 1.0 / p[_TQ20]) if kind == _GENROU else (0.0, 0.0)
    return (1.0 / p[_M], p[_D], p[_XD] - p[_XD1], p[_XQ] - p[_XQ1], td1[0], td1[1], p[_XD1] - p[_XL],
            p[_XQ1] - p[_XL], td2[0], td2[1], p[_GD1], p[_GQ1], p[_GD2], p[_GQ2], p[_GQD], 1 - p[_GD1], 1 - p[_GQ1],
            p[_SAT_A], p[_SAT_B])


@numba.njit(cache=True, inline='always')
def _unpack(kind, x):
    """Return (delta, omega, e'q, e'd, e''d, e''q), tm, vf of a state vector of the model kind (0: lacking)."""
    if kind == _CLASSICAL:
        return (x[0], x[1], 0.0, 0.0, 0.0, 0.0), x[2], 0.0
    if kind == _TWO_AXIS:
        return (x[0], x[1], x[2], x[3], 0.0, 0.0), x[4], x[5]
    return (x[0], x[1], x[2], x[3], x[4], x[5]), x[6], x[7]


@numba.njit(cache=True, inline='always')
def _pack(kind, s, x):
    """Write the stepped states s back into the state vector x."""
    x[0], x[1] = s[0], s[1]
    if kind != _CLASSICAL:
        x[2], x[3] = s[2], s[3]
    if kind == _GENROU:
        x[4], x[5] = s[4], s[5]


@numba.njit(cache=True)
def _derivative(kind, x, ir, ii, te_in, blind, prm, omega_base, memo, out):
    """State derivative of one machine (out, per second, in the model's state order) at states x."""
    s, tm, vf = _unpack(kind, x)
    r = _rates(kind, s, _cos_sin(kind, s[0], memo), tm, vf, ir, ii, te_in, blind, prm, omega_base)
    out[:] = 0.0
    _pack(kind, r, out)


@numba.njit(cache=True)
def _rates_all(kind, t, r, ir, ii, te, blind, prm, omega_base):
    """Write in r[:6] the rates of every point (column) of t, at the stage inputs ir, ii, te.

    t: rows 0-5 the states as _rates takes them, 6 and 7 cos and sin of delta, 8 tm, 9 vf.
    """
    for k in range(t.shape[1]):
        q = _rates(kind, (t[0, k], t[1, k], t[2, k], t[3, k], t[4, k], t[5, k]), (t[6, k], t[7, k]), t[8, k], t[9, k],
                   ir, ii, te, blind, prm, omega_base)
        r[0, k], r[1, k], r[2, k], r[3, k], r[4, k], r[5, k] = q


@numba.njit(cache=True)
def _propagate(kind, pts, steps, h, inp, memo1, memo2, blind, prm, omega_base, s, t, r, acc):
    """Take every point (row) of pts through steps RK4 steps of h s, in place.

    inp[q, j] = (ir, ii, te) at step q's start, middle and end (the same for every point); memo1, memo2: the
    angle (and its cosine and sine) of the first step's first and second stage at the mean (see _cos_sin).
    s (6, npts), acc (6, npts), t (10, ncol), r (6, ncol): scratch, the points' states in columns.
    Stage by stage across points, in columns: the rates of a stage are one loop without calls (the
    trigonometry is a loop of its own) that LLVM vectorises across points; each point's arithmetic, and so
    its values, are those of RK4 point by point. LLVM's vector loop takes 32 iterations at a time (8 lanes,
    4 interleaved) and 16 points ran in its scalar remainder at 4 times the cost per point (measured: 10 ns
    against 2.3 ns per point and stage), so t and r may have more columns than points: copies of the first,
    whose rates are computed and never read. tm and vf have rate 0 and are not stepped.
    """
    npts = pts.shape[0]
    nd = 2 if kind == _CLASSICAL else (4 if kind == _TWO_AXIS else 6)  # the states that move
    hh, h6 = 0.5 * h, h / 6.0
    for k in range(npts):
        st, t[8, k], t[9, k] = _unpack(kind, pts[k])
        for a in range(6):
            s[a, k] = st[a]
            t[a, k] = st[a]
    for k in range(npts, t.shape[1]):
        for a in range(10):
            t[a, k] = t[a, 0]
    for q in range(steps):
        for j in range(4):
            if kind != _CLASSICAL:
                memo = memo1 if j == 0 else memo2
                for k in range(npts):
                    t[6, k], t[7, k] = _cos_sin(kind, t[0, k], memo)
            at = 0 if j == 0 else (2 if j == 3 else 1)  # the step's start, middle or end
            _rates_all(kind, t, r, inp[q, at, 0], inp[q, at, 1], inp[q, at, 2], blind, prm, omega_base)
            # RK4: the stage's state, and the sum a + 2 b + 2 c + e in that order
            f = hh if j < 2 else h
            for a in range(nd):
                if j == 0:
                    for k in range(npts):
                        acc[a, k] = r[a, k]
                        t[a, k] = s[a, k] + f * r[a, k]
                elif j < 3:
                    for k in range(npts):
                        acc[a, k] = acc[a, k] + 2 * r[a, k]
                        t[a, k] = s[a, k] + f * r[a, k]
                else:
                    for k in range(npts):
                        s[a, k] = s[a, k] + h6 * (acc[a, k] + r[a, k])
                        t[a, k] = s[a, k]
    for k in range(npts):
        _pack(kind, (s[0, k], s[1, k], s[2, k], s[3, k], s[4, k], s[5, k]), pts[k])


@numba.njit(cache=True)
def _internal_voltage(kind, x, aux, ir, ii, p, memo):
    """Return z = V + (ra + j x_s) I as one machine's states predict it: (real, imaginary), network frame."""
    c, s = (np.cos(x[0]), np.sin(x[0])) if kind == _CLASSICAL else _cos_sin(kind, x[0], memo)
    if kind == _CLASSICAL:
        return aux * c, aux * s
    i_q = ir * c + ii * s
    if kind == _TWO_AXIS:
        d, q = x[3] - (p[_XD1] - p[_XQ1]) * i_q, x[2]
    else:
        psi2d = p[_GD1] * x[2] + (1 - p[_GD1]) * x[4]
        psi2q = p[_GQ1] * x[3] + (1 - p[_GQ1]) * x[5]
        d, q = psi2q - (p[_XD2] - p[_XQ2]) * i_q, psi2d
    # X = (x_d + j x_q) e^(j(delta - pi/2)) = (q - j d) e^(j delta)
    return q * c + d * s, q * s - d * c


@numba.njit(cache=True)
def _sigma_points(x, cov, root, pts):
    """Write in pts the 2n cubature points of mean x and covariance cov (symmetrised); root is scratch (n, n)."""
    n = x.shape[0]
    for a in range(n):
        for b in range(n):
            root[a, b] = 0.0
    ok = True
    for j in range(n):  # Cholesky, lower
        acc = 0.5 * (cov[j, j] + cov[j, j])
        for k in range(j):
            acc -= root[j, k] * root[j, k]
        if not acc > 0.0:
            ok = False
            break
        root[j, j] = np.sqrt(acc)
        inv = 1.0 / root[j, j]
        for a in range(j + 1, n):
            acc = 0.5 * (cov[a, j] + cov[j, a])
            for k in range(j):
                acc -= root[a, k] * root[j, k]
            root[a, j] = acc * inv
    if not ok:
        sym = 0.5 * (cov + cov.T)
        w, vec = np.linalg.eigh(sym)
        for a in range(n):
            for b in range(n):
                root[a, b] = vec[a, b] * np.sqrt(max(w[b], 0.0))
    scale = np.sqrt(n)
    for k in range(n):  # point k: x plus column k of the square root
        for a in range(n):
            off = scale * root[a, k]
            pts[k, a] = x[a] + off
            pts[n + k, a] = x[a] - off


@numba.njit(cache=True)
def widen_span(kind, x, cov, par, back, v0, i0, v1, i1, span, omega_base):
    """Widen the states of machines back after blind steps by what the unseen inputs may have done to them.

    The blind steps held the last valid inputs (v0, i0) and took no acceleration; over the span (s, per machine)
    the inputs went to the returning frame's (v1, i1) by a path no frame shows (a fault's inception or clearing,
    a hard swing). Each state's rate is taken anywhere between its rates at the two ends, constant over the span
    (the speed's: the accelerating power at either end against the blind steps' none), so each state is off by up
    to that rate's difference times the span, and the angle by omega_base times the speed's, times half the span;
    a uniform on +-that, on the diagonal. Not wider: a fault that began and cleared unseen within the span is not
    allowed for, as that would let an offset of tens of degrees, put in place while a station was silent, pass
    (the prediction's own spread after 0.15 s through a fault's inception lets +-20 deg pass already; +pi never).
    """
    g, n = x.shape
    ka, kb, kn = np.empty(n), np.empty(n), np.empty(n)
    for m in range(g):
        if not back[m]:
            continue
        p = par[m]
        prm = _machine_values(kind, p)
        xm = x[m]
        memo = _memo(kind, xm[0])
        ir0, ii0, ir1, ii1 = i0[m].real, i0[m].imag, i1[m].real, i1[m].imag
        te0 = v0[m].real * ir0 + v0[m].imag * ii0 + p[_RA] * (ir0 * ir0 + ii0 * ii0)
        te1 = v1[m].real * ir1 + v1[m].imag * ii1 + p[_RA] * (ir1 * ir1 + ii1 * ii1)
        _derivative(kind, xm, ir0, ii0, te0, False, prm, omega_base, memo, ka)
        _derivative(kind, xm, ir1, ii1, te1, False, prm, omega_base, memo, kb)
        _derivative(kind, xm, ir0, ii0, te0, True, prm, omega_base, memo, kn)
        t = span[m]
        speed = max(abs(ka[1] - kn[1]), abs(kb[1] - kn[1])) * t
        cov[m, 1, 1] += speed * speed / 3.0
        # No wider than keeps the unscented points (sqrt(n) standard deviations out) within a quarter turn: past it
        # they straddle z's angle and the correction may take the wrong branch (IEEE 14, 0.5 s lost: pi off).
        angle = min(omega_base * speed * t * 0.5, np.sqrt(3.0) * 0.5 * np.pi / np.sqrt(n))
        cov[m, 0, 0] += angle * angle / 3.0
        for a in range(2, n):
            d = (kb[a] - ka[a]) * t
            cov[m, a, a] += d * d / 3.0


@numba.njit(cache=True)
def filter_frame(kind, x, cov, aux, q_rate, par, run, correct, blind, v0, v_end, i0, i_end, v, i, dt, steps,
                  omega_base, sigma_tve, v_floor, blind_walk, judge, gate, nis):
    """One frame of the filter for the machines in run: predict over dt, then correct where correct.

    Args:
        kind: Model (_CLASSICAL, _TWO_AXIS, _GENROU).
        x, cov: States (g, n) and covariances (g, n, n), updated in place.
        aux, q_rate, par: Per-machine fixed value (g,), process noise intensity (g, n), parameters (g, PARAMS).
        run, correct, blind: Machines to predict, to correct, and whose electrical torque is unknown (g,).
        v0, v_end, i0, i_end: Inputs at the start and end of the step, linear in between (g,) complex.
        v, i: This frame's measured V and I (g,) complex, read where correct.
        dt, steps: Step, s, and RK4 sub-steps in it.
        omega_base: 2 pi f, rad/s.
        sigma_tve: Standard deviation of the phasors' relative error.
        v_floor: Voltage magnitude below which V's error is taken as at that magnitude, pu: the bottom of the PMU's
            measuring range, below which C37.118.1 sets no accuracy; a converter's error floor is in volts.
        blind_walk: Random walk of the speed while blind, pu / sqrt(s).
        judge: Machines whose measurement (v, i) is compared with the prediction, corrected or not (g,).
        gate: A judged machine whose normalised innovation squared exceeds it is not corrected.
        nis: Out (g,): the normalised innovation squared of the machines in judge (chi-square with 2 degrees of
            freedom when the filter's model and noise hold), NaN elsewhere.

    """
    g, n = x.shape
    npts = 2 * n
    pts = np.empty((npts, n))
    root = np.empty((n, n))
    k1, k2, k3, k4 = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    inp = np.empty((steps, 3, 3))
    mean, jump = np.empty(n), np.empty(n)
    z = np.empty((npts, 2))
    # See _propagate; padded, the two-axis model's 12 points cost more (0.72 against 0.61 ms per frame for 394
    # machines), its scalar rates being cheaper.
    ncol = -(-npts // 32) * 32 if kind == _GENROU else npts
    ws, wt, wr, wa = np.empty((6, npts)), np.empty((10, ncol)), np.empty((6, ncol)), np.empty((6, npts))
    h = dt / steps
    w_pt = 1.0 / npts  # the cubature weight; divisions are the slowest arithmetic here, so one, then products
    for m in range(g):
        nis[m] = np.nan
        if not run[m]:
            continue
        p = par[m]
        prm = _machine_values(kind, p)
        xm, cm = x[m], cov[m]
        vr0, vi0, ir0, ii0 = v0[m].real, v0[m].imag, i0[m].real, i0[m].imag
        dvr, dvi = v_end[m].real - vr0, v_end[m].imag - vi0
        dir_, dii = i_end[m].real - ir0, i_end[m].imag - ii0
        bl = blind[m]
        # ---- predict: each point through RK4 with inputs linear over the step
        for q in range(steps):
            for j in range(3):  # the step's start, middle and end
                s = (q + 0.5 * j) / steps
                ir_s, ii_s = ir0 + dir_ * s, ii0 + dii * s
                inp[q, j, 0], inp[q, j, 1] = ir_s, ii_s
                inp[q, j, 2] = (vr0 + dvr * s) * ir_s + (vi0 + dvi * s) * ii_s + p[_RA] * (ir_s * ir_s + ii_s * ii_s)
        _sigma_points(xm, cm, root, pts)
        memo1 = _memo(kind, xm[0])
        memo2 = _memo(kind, xm[0] + 0.5 * h * (omega_base * (xm[1] - 1.0)))
        _propagate(kind, pts, steps, h, inp, memo1, memo2, bl, prm, omega_base, ws, wt, wr, wa)
        for a in range(n):
            acc = 0.0
            for k in range(npts):
                acc += pts[k, a]
            mean[a] = acc * w_pt
        # When within the frame the inputs changed is unknown (a fault, a switching): uniformly anywhere, the state
        # reached differs from the linear-input one by up to the change of the derivative times the step.
        vr1, vi1, ir1, ii1 = vr0 + dvr, vi0 + dvi, ir0 + dir_, ii0 + dii
        _derivative(kind, xm, ir1, ii1, vr1 * ir1 + vi1 * ii1 + p[_RA] * (ir1 * ir1 + ii1 * ii1), bl, prm, omega_base,
                    memo1, k1)
        _derivative(kind, xm, ir0, ii0, vr0 * ir0 + vi0 * ii0 + p[_RA] * (ir0 * ir0 + ii0 * ii0), bl, prm, omega_base,
                    memo1, k2)
        for a in range(n):
            jump[a] = (k1[a] - k2[a]) * dt
        for a in range(n):
            for b in range(a + 1):
                acc = 0.0
                for k in range(npts):
                    acc += (pts[k, a] - mean[a]) * (pts[k, b] - mean[b])
                c = acc * w_pt
                if a == b:
                    c += q_rate[m, a] * dt
                c += jump[a] * jump[b] * (1.0 / 12.0)
                cm[a, b] = c
                cm[b, a] = c
        # With no data the electrical torque is unknown, and so is the speed, to the size of a swing.
        if bl:
            cm[1, 1] += blind_walk ** 2 * dt
        for a in range(n):
            xm[a] = mean[a]
        if not (correct[m] or judge[m]):
            continue
        # ---- correct with z = V + (ra + j x_s) I
        _sigma_points(xm, cm, root, pts)
        ir, ii = i[m].real, i[m].imag
        memo = _memo(kind, xm[0])
        for k in range(npts):
            z[k, 0], z[k, 1] = _internal_voltage(kind, pts[k], aux[m], ir, ii, p, memo)
        xs = p[_XD2] if kind == _GENROU else p[_XD1]
        zr, zi = p[_RA] * ir - xs * ii, p[_RA] * ii + xs * ir
        meas_r, meas_i = v[m].real + zr, v[m].imag + zi
        zm_r, zm_i = 0.0, 0.0
        for k in range(npts):
            zm_r += z[k, 0]
            zm_i += z[k, 1]
        zm_r *= w_pt
        zm_i *= w_pt
        r_var = sigma_tve ** 2 * (max(v[m].real ** 2 + v[m].imag ** 2, v_floor ** 2) + zr ** 2 + zi ** 2)
        s00, s01, s11 = 0.0, 0.0, 0.0
        for k in range(npts):
            dz0, dz1 = z[k, 0] - zm_r, z[k, 1] - zm_i
            s00 += dz0 * dz0
            s01 += dz0 * dz1
            s11 += dz1 * dz1
        s00, s01, s11 = s00 * w_pt + r_var, s01 * w_pt, s11 * w_pt + r_var
        det = s00 * s11 - s01 * s01
        inv_det = 1.0 / det
        inv00, inv01, inv11 = s11 * inv_det, -s01 * inv_det, s00 * inv_det
        in0, in1 = meas_r - zm_r, meas_i - zm_i
        if judge[m]:
            nis[m] = in0 * (inv00 * in0 + inv01 * in1) + in1 * (inv01 * in0 + inv11 * in1)
            if nis[m] > gate:
                continue
        if not correct[m]:
            continue
        for a in range(n):  # gain row a = cxz[a] S^-1, kept in k3 (column 0) and k4 (column 1)
            c0, c1 = 0.0, 0.0
            for k in range(npts):
                dx = pts[k, a] - xm[a]
                c0 += dx * (z[k, 0] - zm_r)
                c1 += dx * (z[k, 1] - zm_i)
            c0 *= w_pt
            c1 *= w_pt
            k3[a] = c0 * inv00 + c1 * inv01
            k4[a] = c0 * inv01 + c1 * inv11
        for a in range(n):
            xm[a] += k3[a] * in0 + k4[a] * in1
        # P - K S K^T, symmetric by construction
        for a in range(n):
            ga0 = k3[a] * s00 + k4[a] * s01
            ga1 = k3[a] * s01 + k4[a] * s11
            for b in range(a + 1):
                c = cm[a, b] - (ga0 * k3[b] + ga1 * k4[b])
                cm[a, b] = c
                cm[b, a] = c


def warm_up() -> None:
    """Run the kernels once per model on three made-up machines, so that they are compiled or loaded now.

    widen_span too: compiled at its first call, it would stall pmu_ingestion at the first PMU back from a silence,
    in an event.
    """
    g = 3
    for kind, n in ((_CLASSICAL, 3), (_TWO_AXIS, 6), (_GENROU, 8)):
        par = np.tile(np.array([8.0, 0.0, 0.0, 0.3, 1.8, 1.7, 0.5, 6.0, 0.5, 0.2, 0.2, 0.1, 0.03, 0.05, 0.8, 0.1,
                                0.5, 0.5, 2.0, 2.0, 1.0]), (g, 1))
        x = np.zeros((g, n))
        x[:, 1] = 1.0
        cov = np.tile(1e-4 * np.eye(n), (g, 1, 1))
        v = np.ones(g, dtype=complex)
        i = np.full(g, 0.8 - 0.1j)
        on = np.ones(g, dtype=bool)
        filter_frame(kind, x, cov, np.ones(g), np.full((g, n), 1e-6), par, on, on, ~on, v, v, i, i, v, i,
                      1.0 / 60.0, 1, 2 * np.pi * 60.0, 0.01 / 3, 0.1, 0.005, on, np.inf, np.empty(g))
        widen_span(kind, x, cov, par, on, v, i, v, i, np.full(g, 0.15), 2 * np.pi * 60.0)


warm_up()
