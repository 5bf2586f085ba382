"""Constrained spectral partitioning of the buses (paper eqs. 4 to 8, Algorithm 1 steps 5 to 9), then a repair.

Graph: buses are vertices, in-service branches edges, weighted by eq. 4, W_ij = avg(|P_ij|, |P_ji|) in MW
(parallel branches add up). A branch carrying (almost) no power still joins its buses: every in-service
branch weighs at least 1e-6 of the mean branch weight, so no bus has degree 0 and D^-1/2 exists.

Constraints (eq. 6): Q_ij = +1 between buses whose generators share a coherent group (must-link, the
diagonal of a generator bus included), -1 between generator buses of different groups (cannot-link),
0 elsewhere. L_N = D^-1/2 L D^-1/2 and Q_N = D^-1/2 Q D^-1/2.

Eq. 8 is L_N v = lambda (Q_N - beta/vol I) v. Write B = Q_N - beta/vol I. Q = Z (2 I - 1 1^T) Z^T for the
bus-by-group indicator Z, so Q_N has rank at most k and its nonzero eigenvalues mu are those of a k x k
matrix; B therefore has exactly k-1 positive eigenvalues while beta/vol is below mu_{k-1}, the (k-1)-th
largest eigenvalue of Q_N. An eigenvector with lambda > 0 has v^T B v > 0 (v^T L_N v >= 0), i.e. it meets
eq. 7's constraint v^T Q_N v > beta, so eq. 8 has at most k-1 positive eigenvalues: the k-1 the paper keeps
are all of them. beta is given relative to its upper bound: beta = beta_fraction * mu_{k-1} * vol.

It must also exceed 1^T Q 1 (must-link pairs minus cannot-link pairs). The trivial v0 = D^1/2 1 has
L_N v0 = 0 and v0^T B v0 = 1^T Q 1 - beta; the eigenvectors of positive lambda are B-orthogonal to v0, so if
v0^T B v0 >= 0 it takes one of the k-1 B-positive directions and only k-2 remain. With very unequal groups
(one group holding most generators) beta_fraction * mu_{k-1} * vol can fall below 1^T Q 1; beta is then
raised to the same fraction of the way from 1^T Q 1 to mu_{k-1} * vol.

When 1^T Q 1 >= mu_{k-1} * vol no beta exists for eq. 6's unit weights: 1^T Q 1 = 2 sum c_g^2 - (sum c_g)^2 for
c_g generator buses per group grows with the square of the largest group, mu_{k-1} * vol only with the smaller
groups (Nordic 44's final groups of 15, 2 and 1 generator buses: 136 against 80). The paper allows soft
constraints (Q real, the sign saying must-link or cannot-link), so the fallback (`balance='fallback'`, the
default) lightens the links of large groups: Q_ij = +c_g^-2p within group g, -(c_g c_h)^-p between groups g and
h, i.e. Q = Z C^-p (2 I - 1 1^T) C^-p Z^T. Every must-link and cannot-link keeps its sign, and Q_N keeps k-1
positive eigenvalues (same inertia as 2 I - 1 1^T). At p = 1 each group counts once: 1^T Q 1 = 2k - k^2 <= 0
for k >= 2, so a beta always exists there. p is the least departure from eq. 6 that has a beta: the first of
0.05, 0.10, .. 1 at which 1^T Q 1 < mu_{k-1} vol (on Nordic 44's final groups p = 0.1; one large group and two
single generator buses: Nordic 44 0.2, EI 33 0.1, case118 52/1/1 0.15). Measured on those four groupings with
the refinement, the least p reaches the MILP optimum on all four (without the refinement: +0.8, +24, +19 and 0 %);
p = 1 cuts 22, 88, 0 and 229 % above it. The fit says so (`constraint_weights_`, `balance_power_`,
`fallback_`) and `core.islanding.decide` carries it into the decision; `balance='unit'` refuses instead,
with both figures.
On case39 the lower end of beta_fraction lies
between 0.025 and 0.05; the default 0.2 is the middle of the range (0.125 to 0.3) that reproduces the
paper's Tables I and V on MATPOWER case39 with either pre-outage flows (outaged branches removed) or
post-outage AC flows, without any repair.

Solving eq. 8 at scale without an n x n array. Its positive eigenpairs are the roots of a k x k problem:
with c = sigma lambda and A(c) = L_N + c I (positive definite for c > 0), eq. 8 reads A(c) v = lambda U core U^T v,
so v = lambda Y z with Y = A(c)^-1 U and z = core U^T v, and z solves core S(c) z = (1/lambda) z with
S(c) = U^T Y, k x k and positive definite. lambda > 0 is an eigenvalue of eq. 8 exactly when c mu_j(c) = sigma
for an eigenvalue mu_j of the pencil (core, S(c)^-1). Its j-th largest, j < k, is positive (same inertia as
core), and c mu_j(c) increases with c (t S(c)^-1, t = 1/c, grows in the Loewner order), from at most
1^T Q 1 / vol < sigma near c = 0 to mu_j(Q_N) > sigma as c grows: one root c_j per j, and they are the k-1
positive eigenvalues, lambda_j = c_j / sigma, in the order of j. Each root is found by Newton's method on
log(c mu_j) against log c (derivative 1 - c |Y S^-1 z|^2 for z normalised by z^T S^-1 z = 1), kept inside the
bracket of the evaluations so far; each evaluation is one sparse LU of A(c) (symmetric mode: A(c) is positive
definite, so no pivoting is needed) and k solves, or, near the previous c, iterative refinement with the
previous factors. The eigenvector is v = Y S^-1 z at the root. v0 = D^1/2 1 (lambda = 0) never appears, so
nothing is deflated. Up to _DENSE_MAX_BUSES buses LAPACK solves the pencil deflated of v0 densely instead:
with b0 = B v0, B~ = B - b0 b0^T / (v0^T B v0) and L' = L_N + v0 v0^T / vol, every eigenvector of eq. 8 with
lambda != 0 is v = w + alpha v0 where B~ w = theta L' w, theta = 1/lambda, alpha = -b0^T w / (v0^T B v0).

Step 8/9: the eigenvectors are normalised to sqrt(vol), the k-1 with the lowest eigenvalues are kept,
mapped back to the relaxed island indicators u = D^-1/2 v (the paper's recovery of u from v), and
k-medoids (PAM with BUILD initialisation, deterministic, on the Euclidean distances between rows; see
core/pam.py) groups the buses into k clusters. Clusters are matched to coherent groups by the assignment
that keeps the most generators in their group's cluster (Hungarian algorithm).

Repair (`repair_partition`), because the relaxation carries no guarantee: every generator bus goes to
its group's island; an island whose generators ended up in separate pieces is joined along the shortest
path (fewest branches) through buses that hold no other group's generator; every piece of an island
that is cut off from its generators is released, and released pieces are attached one by one to the
neighbouring island they exchange most flow with. The result: island g is connected and holds exactly
group g's generators.

Refinement (`refine_partition`, on by default; `refine=False` is the paper's method alone): the relaxation
minimises a ratio of cut to volume, not eq. 9 itself, and the repair only makes the islands valid, so single
boundary buses are then moved while each move lowers the cut weight and keeps every island connected with
its generators. On regional groupings of case39, case118, ieee14, nordic44 and EI_33 (k = 2 to 4) this reached
the MILP's optimum in 14 of 15 cases where the repaired relaxation did in 5; it is a local search: on EI_33 with
k = 2 it stopped 2x above the optimum, and on case300 it reached it for k = 3 only (4x above it for k = 2).
"""

from __future__ import annotations

from collections.abc import Mapping

import numba
import numpy as np
import scipy.linalg
from scipy import sparse
from scipy.optimize import linear_sum_assignment
from scipy.sparse import linalg as sparse_linalg
from scipy.sparse.csgraph import connected_components

from controlled_islanding.core.grid import Grid
from controlled_islanding.core.pam import pam

_MIN_WEIGHT_FRACTION = 1e-6
# The fallback's exponent p of the group-balanced weights c_g^-p is searched in steps of 1/_BALANCE_STEPS.
_BALANCE_STEPS = 20
# Up to this many buses the deflated pencil is solved densely (case39: about a millisecond). Not beyond: LAPACK's
# eigh on n x n runs OpenBLAS's threads, which fight other work: at load 10 on 2 cores it took 0.23 s at 118 buses
# and 0.88 s at 300 (22 and 43 ms on one thread), where the k x k roots take 15 to 95 ms.
_DENSE_MAX_BUSES = 100
# The roots of eq. 8's k x k problem (module docstring): the first guess of c = sigma lambda (L_N's spectrum lies in
# [0, 2]; roots seen from 2e-6 to 0.25 on case1354pegase .. case9241pegase), Newton's stopping step in log c
# (after a step this small, quadratic convergence leaves the last evaluation exact to rounding), and its limit.
_FIRST_C = 1e-2
_X_TOLERANCE = 1e-9
_NEWTON_STEPS = 100
# Within this distance in log c of the last LU, iterative refinement with it (_REFINE_STEPS at most) replaces a new
# LU: its error shrinks by about |c - c0| / c0 per solve.
_REFINE_WITHIN = 0.02
_REFINE_STEPS = 20


class SpectralError(ValueError):
    """The grid or the groups cannot be partitioned (disconnected grid, conflicting generators, no solution)."""


def flow_weights(grid: Grid) -> sparse.csr_array:
    """Return eq. 4's symmetric weight matrix W (MW) as a sparse matrix, rows and columns aligned with `grid.buses`.

    Raises:
        SpectralError: The grid has no flows.

    """
    if grid.p_from_mw is None or grid.p_to_mw is None:
        raise SpectralError(f'grid {grid.name!r} has no branch flows; call Grid.with_flows() first')
    on = [k for k, b in enumerate(grid.branches) if b.in_service and b.from_bus != b.to_bus]
    w = (np.abs(np.asarray(grid.p_from_mw, dtype=float)[on]) + np.abs(np.asarray(grid.p_to_mw, dtype=float)[on])) / 2.0
    if len(w):
        w = np.maximum(w, _MIN_WEIGHT_FRACTION * max(float(w.mean()), 1e-12))
    return _symmetric(grid, [grid.branches[k] for k in on], w)


def _symmetric(grid: Grid, branches: list, w: np.ndarray) -> sparse.csr_array:
    """Return the symmetric sparse matrix with w on each branch's two entries (parallel branches add up)."""
    idx = {b: i for i, b in enumerate(grid.buses)}
    rows = np.array([idx[b.from_bus] for b in branches], dtype=np.int64)
    cols = np.array([idx[b.to_bus] for b in branches], dtype=np.int64)
    n = len(grid.buses)
    out = sparse.coo_array((np.concatenate([w, w]), (np.concatenate([rows, cols]), np.concatenate([cols, rows]))),
                           shape=(n, n)).tocsr()
    out.sum_duplicates()
    out.sort_indices()  # ascending neighbours: the repair's breadth-first searches depend on the order
    return out


def _bus_groups(grid: Grid, generator_groups: Mapping[str, int]) -> dict[int, int]:
    """Return the coherent group of each generator bus; a generator left out of the groups constrains nothing."""
    out: dict[int, int] = {}
    for g in grid.generators:
        if g.name not in generator_groups:
            continue
        k = int(generator_groups[g.name])
        if out.setdefault(g.bus, k) != k:
            raise SpectralError(f'bus {g.bus} holds generators of groups {out[g.bus]} and {k}; '
                                'one bus cannot be in two islands')
    return out


def _check_connected(grid: Grid, w: sparse.csr_array) -> tuple[np.ndarray, np.ndarray]:
    """Return the weight graph's neighbours as CSR arrays (ptr, nbr; ascending neighbours), int64.

    Raises:
        SpectralError: The graph is not connected.

    """
    n_pieces, piece = connected_components(w, directed=False)
    if n_pieces > 1:
        sizes = np.bincount(piece)
        smallest = sorted(grid.buses[i] for i in np.flatnonzero(piece == int(np.argmin(sizes))))
        raise SpectralError(f'grid {grid.name!r} is not connected with its in-service branches: {n_pieces} '
                            f'pieces, the smallest holding buses {smallest}')
    return w.indptr.astype(np.int64), w.indices.astype(np.int64)


class ConstrainedSpectralPartition:
    """Assign every bus to the island of a coherent generator group by constrained spectral clustering.

    Args:
        beta: The satisfaction threshold of eq. 7 as a fraction (0, 1) of its feasibility bound
            mu_{k-1}(Q_N) * vol, or of the way from 1^T Q 1 to it when that is higher (see the module docstring).
        random_state: Kept for the API; nothing is random (the eigensolvers and PAM's BUILD are deterministic).
        repair: Apply `repair_partition` (on by default; off only to study the raw relaxation).
        refine: After the repair, move single boundary buses while that lowers eq. 9 (`refine_partition`).
            On by default; off, the fit stops at the repaired relaxation, as the paper's method does.
        balance: 'fallback' (default): eq. 6's unit weights, or group-balanced weights when no beta exists for
            them (module docstring), said in `fallback_`; 'unit': eq. 6's unit weights or a refusal.

    Attributes:
        labels_: Island (= coherent group, 0-based) of each bus, aligned with `grid.buses`.
        relaxed_labels_: The k-medoids result mapped to groups, before the repair.
        repaired_buses_: Bus numbers the repair moved.
        refined_buses_: Bus numbers the refinement moved (empty without refine).
        eigenvalues_: The k-1 eigenvalues of eq. 8 used.
        embedding_: Rows of u = D^-1/2 V* (buses by k-1) that k-medoids clustered.
        beta_: The absolute beta used.
        constraint_weights_: 'unit' (eq. 6 as written) or 'group-balanced' (the fallback).
        balance_power_: The fallback's exponent p of the weights c_g^-p (0 with unit weights).
        fallback_: Why the fallback was used ('' when it was not): the unit-weight figures that left no beta.

    """

    def __init__(self, beta: float = 0.2, random_state: int = 0, repair: bool = True, refine: bool = True,
                 balance: str = 'fallback') -> None:
        self.beta = beta
        self.random_state = random_state
        self.repair = repair
        self.refine = refine
        self.balance = balance

    def fit(self, grid: Grid, generator_groups: Mapping[str, int]) -> ConstrainedSpectralPartition:
        """Partition the buses.

        Args:
            grid: The grid with flows (post-outage topology).
            generator_groups: Group (0-based) of every generator, by name; at least two groups. A generator left out
                (no PMU) is unconstrained: its bus is placed like a load bus.

        Returns:
            self.

        Raises:
            SpectralError: No flows, a disconnected grid, fewer than two groups, a bus with generators of
                two groups, a grouping for which no beta exists, or too few positive eigenvalues.

        """
        if not 0.0 < self.beta < 1.0:
            raise SpectralError(f'beta must be a fraction in (0, 1) of its feasibility bound, got {self.beta}')
        if self.balance not in ('fallback', 'unit'):
            raise SpectralError(f"balance must be 'fallback' or 'unit', got {self.balance!r}")
        bus_group = _bus_groups(grid, generator_groups)
        groups = sorted(set(bus_group.values()))
        k = len(groups)
        if k < 2:
            raise SpectralError(f'need at least two coherent groups to split, got {k}')
        w = flow_weights(grid)
        _check_connected(grid, w)
        buses = list(grid.buses)
        idx = {b: i for i, b in enumerate(buses)}
        d = np.asarray(w.sum(axis=1)).ravel()
        vol = float(d.sum())
        d_isqrt = 1.0 / np.sqrt(d)
        gen_idx = np.array([idx[b] for b in bus_group])
        gen_grp = np.array(list(bus_group.values()))
        column = np.searchsorted(groups, gen_grp)
        counts = np.bincount(column, minlength=k).astype(float)
        core = 2.0 * np.eye(k) - 1.0
        self.constraint_weights_, self.fallback_, self.balance_power_ = 'unit', '', 0.0
        u_mat, trivial, bound = _constraints(d_isqrt, gen_idx, column, np.ones(k), core, vol)
        if trivial >= bound:
            why = (f'no beta exists for these {k} groups with unit constraint weights (generator buses per group: '
                   f'{counts.astype(int).tolist()}): 1^T Q 1 = {trivial:.4g} is not below mu_{{k-1}} vol = '
                   f'{bound:.4g}, so the trivial v = D^1/2 1 meets every constraint eq. 8 can still satisfy in '
                   f'{k - 1} directions; one group holds too large a share of the generators for a {k}-way split')
            if self.balance == 'unit':
                raise SpectralError(why)
            # The least departure from unit weights that has a beta: c_g^-p with p the first of 0.05, 0.10, ..
            # 1 that is feasible (p = 1 always is).
            for step in range(1, _BALANCE_STEPS + 1):
                power = step / _BALANCE_STEPS
                u_mat, trivial, bound = _constraints(d_isqrt, gen_idx, column, counts ** -power, core, vol)
                if trivial < bound:
                    break
            self.balance_power_ = power
            self.constraint_weights_ = 'group-balanced'
            self.fallback_ = f'{why}; constraint weights c_g^-{power:g} per generator-bus pair of group g'
        self.beta_ = float(self.beta * bound)
        if self.beta_ <= trivial:
            self.beta_ = float(trivial + self.beta * (bound - trivial))
        sigma = self.beta_ / vol
        lam, v = _positive_eigenpairs(w, d_isqrt, u_mat, core, sigma, k - 1)
        if len(lam) < k - 1:
            raise SpectralError(f'eq. 8 has {len(lam)} positive eigenvalues, {k - 1} are needed for {k} islands '
                                f'(beta = {self.beta})')
        v = v / np.linalg.norm(v, axis=0) * np.sqrt(vol)
        u = d_isqrt[:, None] * v
        clusters, _ = pam(u, k)
        counts_kk = np.zeros((k, k))
        for i, grp in zip(gen_idx, gen_grp, strict=True):
            counts_kk[clusters[i], grp] += 1
        row, col = linear_sum_assignment(-counts_kk)
        to_group = dict(zip(row.tolist(), col.tolist(), strict=True))
        relaxed = np.array([to_group[int(c)] for c in clusters])
        self.eigenvalues_ = lam
        self.embedding_ = u
        self.relaxed_labels_ = relaxed
        self.labels_ = repair_partition(grid, generator_groups, relaxed, w) if self.repair else relaxed.copy()
        self.repaired_buses_ = [b for b, a, c in zip(buses, relaxed, self.labels_, strict=True) if a != c]
        self.refined_buses_ = []
        if self.refine and self.repair:
            repaired = self.labels_
            self.labels_ = refine_partition(grid, generator_groups, repaired, w)
            self.refined_buses_ = [b for b, a, c in zip(buses, repaired, self.labels_, strict=True) if a != c]
        return self


def _constraints(d_isqrt: np.ndarray, gen_idx: np.ndarray, column: np.ndarray, weight: np.ndarray, core: np.ndarray,
                 vol: float) -> tuple[np.ndarray, float, float]:
    """Return U (Q_N = U core U^T), 1^T Q 1 and the feasibility bound mu_{k-1}(Q_N) * vol for per-group weights.

    Q = Z W core W Z^T with Z the bus-by-group indicator and W = diag(weight): unit weights are eq. 6.
    """
    n, k = len(d_isqrt), len(core)
    u_mat = np.zeros((n, k))
    u_mat[gen_idx, column] = d_isqrt[gen_idx] * weight[column]
    # U^T U is diagonal, so Q_N's nonzero eigenvalues are those of G^1/2 core G^1/2; the rest are 0.
    g_half = np.sqrt((u_mat ** 2).sum(axis=0))
    mu = np.sort(np.concatenate([np.linalg.eigvalsh(g_half[:, None] * core * g_half[None, :]),
                                 np.zeros(max(n - k, 0))]))[::-1]
    per_group = weight * np.bincount(column, minlength=k)
    trivial = float(per_group @ core @ per_group)  # 1^T Q 1; v0 = D^1/2 1 gives v0^T Q_N v0
    return u_mat, trivial, float(mu[k - 2] * vol)


def _positive_eigenpairs(w: sparse.csr_array, d_isqrt: np.ndarray, u_mat: np.ndarray, core: np.ndarray, sigma: float,
                         count: int, dense: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Return eq. 8's positive eigenvalues, ascending, and their eigenvectors v (columns), at most count of them.

    Eq. 8 is L_N v = lambda (Q_N - sigma I) v with Q_N = U core U^T; solved (module docstring) by LAPACK on
    the deflated dense pencil up to _DENSE_MAX_BUSES buses (dense=None), else through its k x k roots.
    """
    n = len(d_isqrt)
    if dense is None:
        dense = n <= _DENSE_MAX_BUSES
    rows = np.repeat(np.arange(n), np.diff(w.indptr))
    adjacency_n = sparse.csr_array((w.data * d_isqrt[rows] * d_isqrt[w.indices], w.indices, w.indptr), shape=w.shape)
    if not dense:
        lam, v = _secular_eigenpairs(adjacency_n, u_mat, core, sigma, count)
        keep = lam > 1e-10  # the dense solver's threshold for lambda = 0
        return lam[keep], v[:, keep]
    v0 = 1.0 / d_isqrt  # D^1/2 1: L_N v0 = 0
    v0_unit = v0 / np.linalg.norm(v0)

    def b_apply(x: np.ndarray) -> np.ndarray:
        return u_mat @ (core @ (u_mat.T @ x)) - sigma * x

    b0 = b_apply(v0)
    b00 = float(v0 @ b0)  # = 1^T Q 1 - beta < 0
    lap_p = np.eye(n) - adjacency_n.toarray() + np.outer(v0_unit, v0_unit)
    b_tilde = b_apply(np.eye(n)) - np.outer(b0, b0) / b00
    theta, wv = scipy.linalg.eigh(b_tilde, lap_p, subset_by_index=[n - count, n - 1])
    keep = (theta > 0.0) & (theta * 1e-10 < 1.0)  # lambda = 1/theta > 1e-10
    theta, wv = theta[keep], wv[:, keep]
    order = np.argsort(-theta)[:count]  # largest theta = smallest lambda
    theta, wv = theta[order], wv[:, order]
    return 1.0 / theta, wv - np.outer(v0, (b0 @ wv) / b00)


class _Resolvent:
    """Y = (L_N + c I)^-1 U for a c that moves a little at a time (Newton's steps towards a root).

    A sparse LU of L_N + c I per new c, or, within _REFINE_WITHIN of the last factored c (in log c), iterative
    refinement with those factors: its error shrinks by |c - c0| / c0 per step, so a few solves replace an LU.
    """

    def __init__(self, lap: sparse.csc_array, u_mat: np.ndarray) -> None:
        self.lap, self.u_mat = lap, u_mat
        self.eye = sparse.identity(lap.shape[0], format='csc')
        self.c0 = None
        self.lu = None
        self.y = None

    def solve(self, c: float) -> np.ndarray:
        if self.lu is not None and abs(np.log(c / self.c0)) <= _REFINE_WITHIN:
            y, last = self.y.copy(), np.inf
            for _ in range(_REFINE_STEPS):
                dy = self.lu.solve(self.u_mat - (self.lap @ y + c * y))
                y += dy
                size, scale = float(np.abs(dy).max()), float(np.abs(y).max())
                # converged, or stalled at rounding (refinement in working precision stops there)
                if size <= 4.0 * np.finfo(float).eps * scale or (size > 0.5 * last and size <= 1e-12 * scale):
                    self.y = y
                    return y
                last = size
        # symmetric mode: L_N + c I is positive definite, so the diagonal pivots need no search
        self.lu = sparse_linalg.splu(self.lap + c * self.eye, permc_spec='MMD_AT_PLUS_A', diag_pivot_thresh=0.0,
                                     options={'SymmetricMode': True})
        self.c0, self.y = c, self.lu.solve(self.u_mat)
        return self.y


def _secular_eigenpairs(adjacency_n: sparse.csr_array, u_mat: np.ndarray, core: np.ndarray, sigma: float,
                        count: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the count smallest positive eigenvalues of eq. 8 and their eigenvectors, as roots c mu_j(c) = sigma.

    Module docstring: Newton's method on log(c mu_j(c) / sigma) against x = log c, bracketed by every evaluation.
    """
    n = u_mat.shape[0]
    lap = (sparse.identity(n, format='csr') - adjacency_n).tocsc()
    gen = np.flatnonzero(np.any(u_mat != 0.0, axis=1))  # U is zero off the generator buses
    resolvent = _Resolvent(lap, u_mat)
    seen: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []  # (x, f_j, slope_j, Y S^-1 z_j) per c

    def evaluate(x: float) -> None:
        c = float(np.exp(x))
        y = resolvent.solve(c)
        s = u_mat[gen].T @ y[gen]
        s = (s + s.T) / 2.0
        mu, p = scipy.linalg.eigh(s @ core @ s, s)  # core z = mu S^-1 z with p = S^-1 z, p^T S p = 1
        yp = y @ p[:, ::-1][:, :count]
        seen.append((x, np.log(np.maximum(c * mu[::-1][:count] / sigma, 1e-300)), 1.0 - c * (yp ** 2).sum(axis=0), yp))

    lam, vectors = np.empty(count), np.empty((n, count))
    evaluate(np.log(_FIRST_C))
    for j in range(count):
        for _ in range(_NEWTON_STEPS):
            lo = max((e[0] for e in seen if e[1][j] < 0.0), default=-np.inf)
            hi = min((e[0] for e in seen if e[1][j] >= 0.0), default=np.inf)
            x, f, slope, _ = min(seen, key=lambda e: abs(e[1][j]))  # Newton from the evaluation nearest the root
            if f[j] == 0.0:
                break
            nxt = x - f[j] / slope[j] if slope[j] > 0.0 else np.nan
            if not lo < nxt < hi:  # outside the bracket (or no slope): halve it, or widen it by e^2
                nxt = (lo + hi) / 2.0 if np.isfinite(lo) and np.isfinite(hi) else x + (2.0 if f[j] < 0.0 else -2.0)
            evaluate(nxt)
            if abs(nxt - x) <= _X_TOLERANCE:
                break
        else:
            raise SpectralError(f'eq. 8: no root for eigenvalue {j + 1} after {_NEWTON_STEPS} Newton steps')
        x, _, _, yp = seen[-1] if abs(seen[-1][0] - x) <= _X_TOLERANCE else min(seen, key=lambda e: abs(e[1][j]))
        lam[j], vectors[:, j] = np.exp(x) / sigma, yp[:, j]
    return lam, vectors


def repair_partition(grid: Grid, generator_groups: Mapping[str, int], labels: np.ndarray,
                     weights: sparse.csr_array | np.ndarray | None = None) -> np.ndarray:
    """Make every island connected and hold exactly its coherent group's generators.

    Args:
        grid: The grid (in-service branches define connectivity).
        generator_groups: Group (0-based) of every generator, by name; generators left out are unconstrained.
        labels: Proposed island of each bus, aligned with `grid.buses` (island g for group g).
        weights: Eq. 4 weights (MW, sparse or dense n x n) used to choose where released buses go; default
            from the grid's flows, or 1 per branch when the grid has none.

    Returns:
        The repaired island of each bus.

    Raises:
        SpectralError: The grid is disconnected, or a group's generators cannot be joined without crossing
            another group's generator bus.

    """
    bus_group = _bus_groups(grid, generator_groups)
    buses = list(grid.buses)
    idx = {b: i for i, b in enumerate(buses)}
    n = len(buses)
    if weights is None:
        if grid.has_flows:
            weights = flow_weights(grid)
        else:
            on = [b for b in grid.branches if b.in_service and b.from_bus != b.to_bus]
            weights = _symmetric(grid, on, np.ones(len(on)))
            weights.data[:] = 1.0  # 1 per joined pair, parallel branches or not
    weights = sparse.csr_array(weights)
    weights.sum_duplicates()
    weights.sort_indices()
    adj = _check_connected(grid, weights)
    coo = weights.tocoo()
    edges = (coo.row.astype(np.int64), coo.col.astype(np.int64), coo.data)
    lab = np.array(labels, dtype=int).copy()
    if lab.shape != (n,):
        raise SpectralError(f'labels have shape {lab.shape}, expected ({n},)')
    owner = np.full(n, -1)
    for bus, grp in bus_group.items():
        owner[idx[bus]] = grp
        lab[idx[bus]] = grp
    # Joining one group's path may cut through another group's island, so repeat until a pass changes nothing.
    for _ in range(n + 1):
        if not any([_join_group(lab, owner, adj, grp, buses) for grp in sorted(set(bus_group.values()))]):
            break
    else:
        raise SpectralError("could not join every group's generators into one connected island")
    free = np.zeros(n, dtype=bool)
    for grp in sorted(set(bus_group.values())):
        piece = _pieces_within(adj, lab == grp)
        seeded = np.unique(piece[owner == grp])
        free |= (lab == grp) & ~np.isin(piece, seeded)
    free |= ~np.isin(lab, list(set(bus_group.values())))
    rows, cols, w_mw = edges
    while free.any():
        # Pieces are numbered by their lowest bus index and argmax takes the first maximum, so ties go to the
        # lowest piece and then the lowest island, whatever the solver's order.
        piece = _pieces_within(adj, free)
        out = free[rows] & ~free[cols]
        score = np.zeros((int(piece.max()) + 1, int(lab.max()) + 1))
        np.add.at(score, (piece[rows[out]], lab[cols[out]]), w_mw[out])
        best = int(np.argmax(score.max(axis=1)))
        if score[best].max() <= 0:
            raise SpectralError('released buses touch no island')  # unreachable on a connected grid
        chosen = piece == best
        lab[chosen] = int(np.argmax(score[best]))
        free[chosen] = False
    return lab


def refine_partition(grid: Grid, generator_groups: Mapping[str, int], labels: np.ndarray,
                     weights: sparse.csr_array) -> np.ndarray:
    """Move single buses across island boundaries while each move lowers the cut weight (eq. 9).

    A bus may move to a neighbouring island when it holds no grouped generator, the move lowers the weight
    of the cut branches by more than 1e-9 of the total weight, and its own island stays connected without
    it. The largest gain moves first (ties: lowest bus index, then lowest island). Every move lowers the cut,
    so it ends. This is a local search from the repaired relaxation: it does not reach the MILP's optimum
    in general, only a partition no single bus move improves.

    Args:
        grid: The grid.
        generator_groups: Group (0-based) of every grouped generator, by name; the others are free to move.
        labels: A repaired partition (connected islands, each holding exactly its group's generator buses).
        weights: Eq. 4 weights, MW, symmetric.

    Returns:
        The refined island of each bus, aligned with `grid.buses`.

    """
    bus_group = _bus_groups(grid, generator_groups)
    idx = {b: i for i, b in enumerate(grid.buses)}
    n = len(idx)
    lab = np.array(labels, dtype=int).copy()
    fixed = np.zeros(n, dtype=bool)
    fixed[[idx[b] for b in bus_group]] = True
    w = sparse.csr_array(weights)
    w.sum_duplicates()
    w.sort_indices()
    ptr, nbr = _check_connected(grid, w)
    _refine_moves(ptr, nbr, w.data, lab, fixed, int(lab.max()) + 1, 1e-9 * float(w.data.sum()))
    return lab


@numba.njit(cache=True)
def _refine_moves(ptr, nbr, wt, lab, fixed, k, tol):
    """Make refine_partition's moves in place on lab (compiled: at 9241 buses a move's numpy pass took ms).

    to[i, c] is the weight from bus i to island c, so a move of i to c gains to[i, c] - to[i, lab[i]]; each step
    takes the largest gain (the first in bus-then-island order on ties) above tol, unless the move would split
    i's island, in which case that (bus, island) is blocked until the next move.
    """
    n = lab.shape[0]
    to = np.zeros((n, k))
    for i in range(n):
        for e in range(ptr[i], ptr[i + 1]):
            to[i, lab[nbr[e]]] += wt[e]
    blocked = np.zeros((n, k), dtype=np.bool_)
    seen, queue = np.zeros(n, dtype=np.int64), np.empty(n, dtype=np.int64)  # the searches' scratch
    searches = 0
    while True:
        best, bi, bc = -np.inf, -1, -1
        for i in range(n):
            if fixed[i]:
                continue
            here = to[i, lab[i]]
            for c in range(k):
                if c != lab[i] and not blocked[i, c]:
                    g = to[i, c] - here
                    if g > best:
                        best, bi, bc = g, i, c
        if not best > tol:
            return
        searches += 1
        if not _stays_connected(ptr, nbr, lab, bi, seen, queue, searches):
            blocked[bi, bc] = True
            continue
        old = lab[bi]
        lab[bi] = bc
        for e in range(ptr[bi], ptr[bi + 1]):
            to[nbr[e], old] -= wt[e]
        for e in range(ptr[bi], ptr[bi + 1]):
            to[nbr[e], bc] += wt[e]
        blocked[:, :] = False


@numba.njit(cache=True)
def _stays_connected(ptr, nbr, lab, i, seen, queue, stamp):
    """Return whether bus i's island stays connected without it (a breadth-first search that stops early).

    Compiled, with the CSR neighbours: refine_partition asks once per move tried, and at 9241 buses a search in
    Python took 8 ms. seen marks this search's buses with stamp (a number no earlier search used), queue is
    scratch of n.
    """
    own = lab[i]
    targets = 0
    start = -1
    for e in range(ptr[i], ptr[i + 1]):
        j = nbr[e]
        if j != i and lab[j] == own and seen[j] != -stamp:
            seen[j] = -stamp  # a target not reached yet (parallel branches list a neighbour twice)
            targets += 1
            start = j
    if targets <= 1:
        return True
    seen[i] = stamp
    seen[start] = stamp
    targets -= 1
    queue[0] = start
    head, tail = 0, 1
    while head < tail and targets > 0:
        b = queue[head]
        head += 1
        for e in range(ptr[b], ptr[b + 1]):
            j = nbr[e]
            if seen[j] != stamp and lab[j] == own:
                if seen[j] == -stamp:
                    targets -= 1
                seen[j] = stamp
                queue[tail] = j
                tail += 1
    return targets == 0


@numba.njit(cache=True)
def _pieces_within(adj, mask):
    """Return the connected piece of each bus of mask, numbered in order of their lowest bus index; -1 elsewhere.

    adj is the (ptr, nbr) pair of _check_connected. Compiled: the repair asks hundreds of times, and building a
    sparse matrix for scipy's connected_components each time cost more than the search.
    """
    ptr, nbr = adj
    n = mask.shape[0]
    out = np.full(n, -1, dtype=np.int64)
    queue = np.empty(n, dtype=np.int64)
    pieces = 0
    for root in range(n):
        if not mask[root] or out[root] >= 0:
            continue
        out[root] = pieces
        queue[0] = root
        head, tail = 0, 1
        while head < tail:
            b = queue[head]
            head += 1
            for e in range(ptr[b], ptr[b + 1]):
                j = nbr[e]
                if mask[j] and out[j] < 0:
                    out[j] = pieces
                    queue[tail] = j
                    tail += 1
        pieces += 1
    return out


@numba.njit(cache=True)
def _path_to_stranded(ptr, nbr, main, owner, grp):
    """Breadth-first from the main piece through buses no other group owns, to the nearest stranded generator.

    Returns (prev, target): each reached bus's predecessor (-1 for the main piece's buses, -2 unreached), and the
    generator bus found (-1 if none). The main piece's buses start the queue in ascending order.
    """
    n = main.shape[0]
    prev = np.full(n, -2, dtype=np.int64)
    queue = np.empty(n, dtype=np.int64)
    tail = 0
    for b in range(n):
        if main[b]:
            prev[b] = -1
            queue[tail] = b
            tail += 1
    head = 0
    while head < tail:
        b = queue[head]
        head += 1
        for e in range(ptr[b], ptr[b + 1]):
            j = nbr[e]
            if prev[j] != -2 or (owner[j] >= 0 and owner[j] != grp):
                continue
            prev[j] = b
            if owner[j] == grp:
                return prev, j
            queue[tail] = j
            tail += 1
    return prev, -1


def _join_group(lab: np.ndarray, owner: np.ndarray, adj: tuple[np.ndarray, np.ndarray], grp: int,
                buses: list[int]) -> bool:
    """Relabel shortest paths so that all of group grp's generator buses share one connected piece.

    Returns:
        Whether any bus was relabelled.

    """
    gens = np.flatnonzero(owner == grp)
    changed = False
    while True:
        piece = _pieces_within(adj, lab == grp)
        main = piece == piece[gens[0]]
        apart = [int(g) for g in gens if not main[g]]
        if not apart:
            return changed
        changed = True
        prev, target = _path_to_stranded(adj[0], adj[1], main, owner, grp)
        if target < 0:
            raise SpectralError(f'the generators of group {grp} at buses {[buses[g] for g in apart]} cannot reach '
                                f"bus {buses[int(gens[0])]} without crossing another group's generator bus")
        while target >= 0:
            lab[target] = grp
            target = prev[target]


# Compile (or load from numba's cache) the search kernels now, at import, with the types the repair and the
# refinement pass (a 3-bus line): a node pays it at start-up, not at its first decision, and tools/setup.sh compiles
# them once for every later process.
_line = (np.array([0, 1, 3, 4], dtype=np.int64), np.array([1, 0, 2, 1], dtype=np.int64))
_pieces_within(_line, np.ones(3, dtype=bool))
_path_to_stranded(*_line, np.array([True, False, False]), np.array([0, -1, 0]), 0)
_stays_connected(*_line, np.zeros(3, dtype=int), 1, np.zeros(3, dtype=np.int64), np.empty(3, dtype=np.int64), 1)
_refine_moves(*_line, np.ones(4), np.array([0, 1, 1]), np.array([True, False, True]), 2, 1e-9)
del _line
