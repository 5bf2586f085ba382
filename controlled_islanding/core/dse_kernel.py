"""The compiled step of core/dse.py's filter: one frame's predict and correct for every machine of one model.

Why compiled: per frame the filter is a few hundred operations on arrays of 3 to 16 numbers per machine; as numpy
calls batched over machines, their call overhead, not the arithmetic, took 2 to 11 ms per frame (profiled: about
two thirds in the prediction's RK4 derivatives and sigma points, a third in the correction). Here each machine's
predict and correct are scalar loops with the formulas and operation order of that numpy version, on one core.
The equations and the filter design are in core/dse.py's docstring.

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


@numba.njit(cache=True)
def _derivative(kind, x, vr, vi, ir, ii, p, blind, omega_base, out):
    """State derivative of one machine (out, per second) at states x, terminal V and I (network frame)."""
    tm = x[2] if kind == _CLASSICAL else (x[4] if kind == _TWO_AXIS else x[6])
    # Without data the electrical torque is unknown: the mechanical one is its best guess (no acceleration but
    # the damping's); holding the last measured one would keep accelerating the machine.
    te = tm if blind else vr * ir + vi * ii + p[_RA] * (ir * ir + ii * ii)
    slip = x[1] - 1.0
    out[0] = omega_base * slip
    out[1] = (tm - te - p[_D] * slip) / p[_M]
    if kind == _CLASSICAL:
        out[2] = 0.0
        return
    c, s = np.cos(x[0]), np.sin(x[0])
    i_d, i_q = ir * s - ii * c, ir * c + ii * s
    if kind == _TWO_AXIS:
        out[2] = (x[5] - x[2] - (p[_XD] - p[_XD1]) * i_d) / p[_TD10]
        out[3] = (-x[3] + (p[_XQ] - p[_XQ1]) * i_q) / p[_TQ10]
        out[4] = 0.0
        out[5] = 0.0
        return
    gd1, gq1, gd2, gq2, gqd = p[_GD1], p[_GQ1], p[_GD2], p[_GQ2], p[_GQD]
    e1q, e1d, e2d, e2q = x[2], x[3], x[4], x[5]
    psi2d = gd1 * e1q + (1 - gd1) * e2d
    psi2q = gq1 * e1d + (1 - gq1) * e2q
    psi = np.sqrt(psi2d ** 2 + psi2q ** 2)
    over = max(psi - p[_SAT_A], 0.0)
    se = p[_SAT_B] * over ** 2 / max(psi, 1e-9)
    xad_ifd = e1q + (p[_XD] - p[_XD1]) * (gd1 * i_d - gd2 * e2d + gd2 * e1q) + se * psi2d
    xaq_i1q = e1d + (p[_XQ] - p[_XQ1]) * (gq2 * e1d - gq2 * e2q - gq1 * i_q) + se * psi2q * gqd
    out[2] = (x[7] - xad_ifd) / p[_TD10]
    out[3] = -xaq_i1q / p[_TQ10]
    out[4] = (-e2d + e1q - (p[_XD1] - p[_XL]) * i_d) / p[_TD20]
    out[5] = (-e2q + e1d + (p[_XQ1] - p[_XL]) * i_q) / p[_TQ20]
    out[6] = 0.0
    out[7] = 0.0


@numba.njit(cache=True)
def _internal_voltage(kind, x, aux, ir, ii, p):
    """Return z = V + (ra + j x_s) I as one machine's states predict it: (real, imaginary), network frame."""
    c, s = np.cos(x[0]), np.sin(x[0])
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
        for a in range(j + 1, n):
            acc = 0.5 * (cov[a, j] + cov[j, a])
            for k in range(j):
                acc -= root[a, k] * root[j, k]
            root[a, j] = acc / root[j, j]
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
def filter_frame(kind, x, cov, aux, q_rate, par, run, correct, blind, v0, v_end, i0, i_end, v, i, dt, steps,
                  omega_base, sigma_tve, blind_walk):
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
        blind_walk: Random walk of the speed while blind, pu / sqrt(s).

    """
    g, n = x.shape
    npts = 2 * n
    pts = np.empty((npts, n))
    root = np.empty((n, n))
    k1, k2, k3, k4, tmp = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    mean, jump = np.empty(n), np.empty(n)
    z = np.empty((npts, 2))
    h = dt / steps
    for m in range(g):
        if not run[m]:
            continue
        p = par[m]
        xm, cm = x[m], cov[m]
        vr0, vi0, ir0, ii0 = v0[m].real, v0[m].imag, i0[m].real, i0[m].imag
        dvr, dvi = v_end[m].real - vr0, v_end[m].imag - vi0
        dir_, dii = i_end[m].real - ir0, i_end[m].imag - ii0
        bl = blind[m]
        # ---- predict: each point through RK4 with inputs linear over the step
        _sigma_points(xm, cm, root, pts)
        for k in range(npts):
            st = pts[k]
            for q in range(steps):
                s0, sm, s1 = q / steps, (q + 0.5) / steps, (q + 1) / steps
                _derivative(kind, st, vr0 + dvr * s0, vi0 + dvi * s0, ir0 + dir_ * s0, ii0 + dii * s0, p, bl,
                            omega_base, k1)
                for a in range(n):
                    tmp[a] = st[a] + 0.5 * h * k1[a]
                _derivative(kind, tmp, vr0 + dvr * sm, vi0 + dvi * sm, ir0 + dir_ * sm, ii0 + dii * sm, p, bl,
                            omega_base, k2)
                for a in range(n):
                    tmp[a] = st[a] + 0.5 * h * k2[a]
                _derivative(kind, tmp, vr0 + dvr * sm, vi0 + dvi * sm, ir0 + dir_ * sm, ii0 + dii * sm, p, bl,
                            omega_base, k3)
                for a in range(n):
                    tmp[a] = st[a] + h * k3[a]
                _derivative(kind, tmp, vr0 + dvr * s1, vi0 + dvi * s1, ir0 + dir_ * s1, ii0 + dii * s1, p, bl,
                            omega_base, k4)
                for a in range(n):
                    st[a] = st[a] + (h / 6.0) * (k1[a] + 2 * k2[a] + 2 * k3[a] + k4[a])
        for a in range(n):
            acc = 0.0
            for k in range(npts):
                acc += pts[k, a]
            mean[a] = acc / npts
        # When within the frame the inputs changed is unknown (a fault, a switching): uniformly anywhere, the state
        # reached differs from the linear-input one by up to the change of the derivative times the step.
        _derivative(kind, xm, vr0 + dvr, vi0 + dvi, ir0 + dir_, ii0 + dii, p, bl, omega_base, k1)
        _derivative(kind, xm, vr0, vi0, ir0, ii0, p, bl, omega_base, k2)
        for a in range(n):
            jump[a] = (k1[a] - k2[a]) * dt
        for a in range(n):
            for b in range(a + 1):
                acc = 0.0
                for k in range(npts):
                    acc += (pts[k, a] - mean[a]) * (pts[k, b] - mean[b])
                c = acc / npts
                if a == b:
                    c += q_rate[m, a] * dt
                c += jump[a] * jump[b] / 12.0
                cm[a, b] = c
                cm[b, a] = c
        # With no data the electrical torque is unknown, and so is the speed, to the size of a swing.
        if bl:
            cm[1, 1] += blind_walk ** 2 * dt
        for a in range(n):
            xm[a] = mean[a]
        if not correct[m]:
            continue
        # ---- correct with z = V + (ra + j x_s) I
        _sigma_points(xm, cm, root, pts)
        ir, ii = i[m].real, i[m].imag
        for k in range(npts):
            z[k, 0], z[k, 1] = _internal_voltage(kind, pts[k], aux[m], ir, ii, p)
        xs = p[_XD2] if kind == _GENROU else p[_XD1]
        zr, zi = p[_RA] * ir - xs * ii, p[_RA] * ii + xs * ir
        meas_r, meas_i = v[m].real + zr, v[m].imag + zi
        zm_r, zm_i = 0.0, 0.0
        for k in range(npts):
            zm_r += z[k, 0]
            zm_i += z[k, 1]
        zm_r /= npts
        zm_i /= npts
        r_var = sigma_tve ** 2 * (v[m].real ** 2 + v[m].imag ** 2 + zr ** 2 + zi ** 2)
        s00, s01, s11 = 0.0, 0.0, 0.0
        for k in range(npts):
            dz0, dz1 = z[k, 0] - zm_r, z[k, 1] - zm_i
            s00 += dz0 * dz0
            s01 += dz0 * dz1
            s11 += dz1 * dz1
        s00, s01, s11 = s00 / npts + r_var, s01 / npts, s11 / npts + r_var
        det = s00 * s11 - s01 * s01
        inv00, inv01, inv11 = s11 / det, -s01 / det, s00 / det
        in0, in1 = meas_r - zm_r, meas_i - zm_i
        for a in range(n):  # gain row a = cxz[a] S^-1, kept in k3 (column 0) and k4 (column 1)
            c0, c1 = 0.0, 0.0
            for k in range(npts):
                dx = pts[k, a] - xm[a]
                c0 += dx * (z[k, 0] - zm_r)
                c1 += dx * (z[k, 1] - zm_i)
            c0 /= npts
            c1 /= npts
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
    """Run the kernel once per model on three made-up machines, so that it is compiled or loaded now."""
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
                      1.0 / 60.0, 1, 2 * np.pi * 60.0, 0.01 / 3, 0.005)


warm_up()
