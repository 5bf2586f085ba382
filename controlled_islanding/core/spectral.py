"""Constrained spectral partitioning of the buses (paper eqs. 4 to 8, Algorithm 1 steps 5 to 9), then a repair.

Graph: buses are vertices, in-service branches edges, weighted by eq. 4, W_ij = avg(|P_ij|, |P_ji|) in MW
(parallel branches add up). A branch carrying (almost) no power still joins its buses: every in-service
branch weighs at least 1e-6 of the mean branch weight, so no bus has degree 0 and D^-1/2 exists.

Constraints (eq. 6): Q_ij = +1 between buses whose generators share a coherent group (must-link, the
diagonal of a generator bus included), -1 between generator buses of different groups (cannot-link),
0 elsewhere. L_N = D^-1/2 L D^-1/2 and Q_N = D^-1/2 Q D^-1/2.

Eq. 8, L_N v = lambda (Q_N - beta/vol I) v, is solved as a dense generalized eigenproblem. The
constraint v^T Q_N v > beta is only feasible in k-1 independent directions while beta/vol stays below
the (k-1)-th largest eigenvalue mu_{k-1} of Q_N, so beta is given relative to that bound:
beta = beta_fraction * mu_{k-1} * vol. It must also exceed 1^T Q 1 (must-link pairs minus cannot-link
pairs), or the excluded trivial vector D^1/2 1 alone satisfies the constraint; on case39 that puts the
lower end of beta_fraction between 0.025 and 0.05. The default beta_fraction = 0.2 is the middle of the range
(0.125 to 0.3) that reproduces the paper's Tables I and V on MATPOWER case39 with either pre-outage
flows (outaged branches removed) or post-outage AC flows, without any repair.

Step 8/9: eigenvectors with positive (finite, real) eigenvalues are normalised to sqrt(vol), the k-1 with
the lowest eigenvalues are kept, mapped back to the relaxed island indicators u = D^-1/2 v (the paper's
recovery of u from v), and k-medoids (PAM with BUILD initialisation, deterministic, on the Euclidean
distances between rows) groups the buses into k clusters. Clusters are matched to coherent groups by the
assignment that keeps the most generators in their group's cluster (Hungarian algorithm).

Repair (`repair_partition`), because the relaxation carries no guarantee: every generator bus goes to
its group's island; an island whose generators ended up in separate pieces is joined along the shortest
path (fewest branches) through buses that hold no other group's generator; every piece of an island
that is cut off from its generators is released, and released pieces are attached one by one to the
neighbouring island they exchange most flow with. The result: island g is connected and holds exactly
group g's generators.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping

import kmedoids
import numpy as np
import scipy.linalg
from scipy.optimize import linear_sum_assignment

from controlled_islanding.core.grid import Grid

_MIN_WEIGHT_FRACTION = 1e-6


class SpectralError(ValueError):
    """The grid or the groups cannot be partitioned (disconnected grid, conflicting generators, no solution)."""


def flow_weights(grid: Grid) -> np.ndarray:
    """Return eq. 4's symmetric weight matrix W (MW), rows and columns aligned with `grid.buses`.

    Raises:
        SpectralError: The grid has no flows.

    """
    if grid.p_from_mw is None or grid.p_to_mw is None:
        raise SpectralError(f'grid {grid.name!r} has no branch flows; call Grid.with_flows() first')
    idx = {b: i for i, b in enumerate(grid.buses)}
    on = [k for k, b in enumerate(grid.branches) if b.in_service and b.from_bus != b.to_bus]
    w = np.array([(abs(grid.p_from_mw[k]) + abs(grid.p_to_mw[k])) / 2.0 for k in on])
    if len(w):
        w = np.maximum(w, _MIN_WEIGHT_FRACTION * max(float(w.mean()), 1e-12))
    rows = [idx[grid.branches[k].from_bus] for k in on]
    cols = [idx[grid.branches[k].to_bus] for k in on]
    n = len(grid.buses)
    out = np.zeros((n, n))
    np.add.at(out, (rows, cols), w)
    return out + out.T


def _bus_groups(grid: Grid, generator_groups: Mapping[str, int]) -> dict[int, int]:
    """Return the coherent group of each generator bus."""
    out: dict[int, int] = {}
    for g in grid.generators:
        if g.name not in generator_groups:
            raise SpectralError(f'generator {g.name} has no coherent group')
        k = int(generator_groups[g.name])
        if out.setdefault(g.bus, k) != k:
            raise SpectralError(f'bus {g.bus} holds generators of groups {out[g.bus]} and {k}; '
                                'one bus cannot be in two islands')
    return out


def _check_connected(grid: Grid, w: np.ndarray) -> list[list[int]]:
    """Return the adjacency lists of the weight graph.

    Raises:
        SpectralError: The graph is not connected.

    """
    rows, cols = np.nonzero(w > 0)
    adj = [a.tolist() for a in np.split(cols, np.searchsorted(rows, np.arange(1, len(w))))]
    pieces = _pieces(adj, np.ones(len(adj), dtype=bool))
    if len(pieces) > 1:
        smallest = sorted(grid.buses[i] for i in min(pieces, key=len))
        raise SpectralError(f'grid {grid.name!r} is not connected with its in-service branches: {len(pieces)} '
                            f'pieces, the smallest holding buses {smallest}')
    return adj


class ConstrainedSpectralPartition:
    """Assign every bus to the island of a coherent generator group by constrained spectral clustering.

    Args:
        beta: The satisfaction threshold of eq. 7 as a fraction (0, 1) of its feasibility bound
            mu_{k-1}(Q_N) * vol (see the module docstring).
        random_state: Seed for k-medoids (BUILD initialisation is deterministic; kept for the estimator API).
        repair: Apply `repair_partition` (on by default; off only to study the raw relaxation).

    Attributes:
        labels_: Island (= coherent group, 0-based) of each bus, aligned with `grid.buses`.
        relaxed_labels_: The k-medoids result mapped to groups, before the repair.
        repaired_buses_: Bus numbers the repair moved.
        eigenvalues_: The k-1 eigenvalues of eq. 8 used.
        embedding_: Rows of u = D^-1/2 V* (buses by k-1) that k-medoids clustered.
        beta_: The absolute beta used.

    """

    def __init__(self, beta: float = 0.2, random_state: int = 0, repair: bool = True) -> None:
        self.beta = beta
        self.random_state = random_state
        self.repair = repair

    def fit(self, grid: Grid, generator_groups: Mapping[str, int]) -> ConstrainedSpectralPartition:
        """Partition the buses.

        Args:
            grid: The grid with flows (post-outage topology).
            generator_groups: Group (0-based) of every generator, by name; at least two groups.

        Returns:
            self.

        Raises:
            SpectralError: No flows, a disconnected grid, fewer than two groups, a bus with generators of
                two groups, or too few positive eigenvalues.

        """
        if not 0.0 < self.beta < 1.0:
            raise SpectralError(f'beta must be a fraction in (0, 1) of its feasibility bound, got {self.beta}')
        bus_group = _bus_groups(grid, generator_groups)
        k = len(set(bus_group.values()))
        if k < 2:
            raise SpectralError(f'need at least two coherent groups to split, got {k}')
        w = flow_weights(grid)
        _check_connected(grid, w)
        buses = list(grid.buses)
        idx = {b: i for i, b in enumerate(buses)}
        n = len(buses)
        d = w.sum(axis=1)
        vol = float(d.sum())
        d_isqrt = 1.0 / np.sqrt(d)
        lap_n = np.eye(n) - d_isqrt[:, None] * w * d_isqrt[None, :]
        q = np.zeros((n, n))
        gen_idx = np.array([idx[b] for b in bus_group])
        gen_grp = np.array(list(bus_group.values()))
        q[np.ix_(gen_idx, gen_idx)] = np.where(gen_grp[:, None] == gen_grp[None, :], 1.0, -1.0)
        q_n = d_isqrt[:, None] * q * d_isqrt[None, :]
        mu = np.sort(np.linalg.eigvalsh(q_n))[::-1]
        self.beta_ = float(self.beta * mu[k - 2] * vol)
        trivial = float(q.sum())  # v = D^1/2 1 gives v^T Q_N v = 1^T Q 1
        if self.beta_ <= trivial:
            raise SpectralError(f'beta = {self.beta} gives {self.beta_:.4g}, not above 1^T Q 1 = {trivial:.4g}, so the '
                                f'trivial v = D^1/2 1 meets the constraint and eq. 8 has no useful solution; '
                                f'raise beta above {trivial / (mu[k - 2] * vol):.3g}')
        # B = Q_N - beta/vol I is nonsingular for 0 < beta < mu_{k-1} vol unless beta/vol hits an eigenvalue of
        # Q_N, so eq. 8 is B^-1 L_N v = lambda v; numpy's eig skips scipy's per-vector Python normalisation.
        b_mat = q_n - (self.beta_ / vol) * np.eye(n)
        try:
            lam, vec = np.linalg.eig(np.linalg.solve(b_mat, lap_n))
        except np.linalg.LinAlgError:
            lam, vec = scipy.linalg.eig(lap_n, b_mat)
        keep = np.isfinite(lam) & (np.abs(lam.imag) <= 1e-9 * np.maximum(1.0, np.abs(lam.real))) & (lam.real > 1e-10)
        lam, vec = lam.real[keep], vec.real[:, keep]
        if len(lam) < k - 1:
            raise SpectralError(f'eq. 8 has {len(lam)} positive eigenvalues, {k - 1} are needed for {k} islands '
                                f'(beta = {self.beta})')
        order = np.argsort(lam)[:k - 1]
        v = vec[:, order]
        v = v / np.linalg.norm(v, axis=0) * np.sqrt(vol)
        u = d_isqrt[:, None] * v
        diss = np.sqrt(((u[:, None, :] - u[None, :, :]) ** 2).sum(axis=2))
        clusters = np.asarray(kmedoids.pam(diss, k, init='build', random_state=self.random_state).labels)
        counts = np.zeros((k, k))
        for i, grp in zip(gen_idx, gen_grp, strict=True):
            counts[clusters[i], grp] += 1
        row, col = linear_sum_assignment(-counts)
        to_group = dict(zip(row.tolist(), col.tolist(), strict=True))
        relaxed = np.array([to_group[int(c)] for c in clusters])
        self.eigenvalues_ = lam[order]
        self.embedding_ = u
        self.relaxed_labels_ = relaxed
        self.labels_ = repair_partition(grid, generator_groups, relaxed, w) if self.repair else relaxed.copy()
        self.repaired_buses_ = [b for b, a, c in zip(buses, relaxed, self.labels_, strict=True) if a != c]
        return self


def repair_partition(grid: Grid, generator_groups: Mapping[str, int], labels: np.ndarray,
                     weights: np.ndarray | None = None) -> np.ndarray:
    """Make every island connected and hold exactly its coherent group's generators.

    Args:
        grid: The grid (in-service branches define connectivity).
        generator_groups: Group (0-based) of every generator, by name.
        labels: Proposed island of each bus, aligned with `grid.buses` (island g for group g).
        weights: Eq. 4 weights (MW) used to choose where released buses go; default from the grid's flows,
            or 1 per branch when the grid has none.

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
            weights = np.zeros((n, n))
            for b in grid.branches:
                if b.in_service and b.from_bus != b.to_bus:
                    weights[idx[b.from_bus], idx[b.to_bus]] = weights[idx[b.to_bus], idx[b.from_bus]] = 1.0
    adj = _check_connected(grid, weights)
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
        seeds = np.flatnonzero(owner == grp)
        keep = _reach(adj, seeds, lambda j, g=grp: lab[j] == g)
        free |= (lab == grp) & ~keep
    free |= ~np.isin(lab, list(set(bus_group.values())))
    while free.any():
        best: tuple[float, int, list[int]] | None = None
        for piece in _pieces(adj, free):
            score = np.zeros(lab.max() + 1)
            for i in piece:
                for j in adj[i]:
                    if not free[j]:
                        score[lab[j]] += weights[i, j]
            if score.max() > 0 and (best is None or score.max() > best[0]):
                best = (float(score.max()), int(score.argmax()), piece)
        if best is None:
            raise SpectralError('released buses touch no island')  # unreachable on a connected grid
        lab[best[2]] = best[1]
        free[best[2]] = False
    return lab


def _reach(adj: list[list[int]], seeds: np.ndarray, allowed) -> np.ndarray:
    """Return the buses reachable from seeds through allowed buses (breadth first)."""
    seen = np.zeros(len(adj), dtype=bool)
    seen[seeds] = True
    queue = deque(int(s) for s in seeds)
    while queue:
        i = queue.popleft()
        for j in adj[i]:
            if not seen[j] and allowed(j):
                seen[j] = True
                queue.append(j)
    return seen


def _pieces(adj: list[list[int]], mask: np.ndarray) -> list[list[int]]:
    """Return the connected pieces of the buses in mask."""
    seen = ~mask.copy()
    out = []
    for s in np.flatnonzero(mask):
        if seen[s]:
            continue
        piece = np.flatnonzero(_reach(adj, np.array([s]), lambda j: mask[j]) & mask)
        seen[piece] = True
        out.append(piece.tolist())
    return out


def _join_group(lab: np.ndarray, owner: np.ndarray, adj: list[list[int]], grp: int, buses: list[int]) -> bool:
    """Relabel shortest paths so that all of group grp's generator buses share one connected piece.

    Returns:
        Whether any bus was relabelled.

    """
    gens = np.flatnonzero(owner == grp)
    changed = False
    while True:
        main = _reach(adj, gens[:1], lambda j: lab[j] == grp)
        apart = [int(g) for g in gens if not main[g]]
        if not apart:
            return changed
        changed = True
        # Breadth-first from the main piece through buses no other group owns, to the nearest stranded generator.
        prev = {int(i): -1 for i in np.flatnonzero(main)}
        queue = deque(prev)
        target = -1
        while queue and target < 0:
            i = queue.popleft()
            for j in adj[i]:
                if j in prev or (owner[j] >= 0 and owner[j] != grp):
                    continue
                prev[j] = i
                if owner[j] == grp:
                    target = j
                    break
                queue.append(j)
        if target < 0:
            raise SpectralError(f'the generators of group {grp} at buses {[buses[g] for g in apart]} cannot reach '
                                f"bus {buses[int(gens[0])]} without crossing another group's generator bus")
        while target >= 0:
            lab[target] = grp
            target = prev[target]
