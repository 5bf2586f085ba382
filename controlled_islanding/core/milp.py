"""The exact minimum power-flow-disruption partition (eq. 9) as a mixed-integer program, solved by HiGHS.

This is the yardstick for the spectral heuristic: the same coherency constraints (every generator on its
group's island), every island connected, and the objective of eq. 9, the sum over cut branches of
(|P_from| + |P_to|) / 2 in MW.

Formulation, for buses i, in-service edges e = {i, j} (parallel branches merged, weights summed) and islands c:
    x[i, c] in {0, 1}     bus i is on island c;  sum_c x[i, c] = 1;  x[bus(g), group(g)] = 1
    y[e] >= |x[i, c] - x[j, c]|  for every c   (y[e] = 1 iff e is cut; continuous, the minimisation makes it 0/1)
    minimise sum_e w[e] y[e]
Connectivity is a single-commodity flow per island: one generator bus of the group is the root, every other
bus on the island consumes one unit, and flow may only use arcs with both ends on the island. Buses in a part
of the network that the outages already cut off keep that part's own roots (one per group present there); a
part with no generator is dead, its buses carry no connectivity constraint and join island 0.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping

import networkx as nx
import numpy as np
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, milp

from controlled_islanding.core.grid import Grid

_STATUS = {0: 'optimal', 1: 'time_limit', 2: 'infeasible', 3: 'unbounded', 4: 'error'}
# HiGHS's own model status on reaching mip_max_nodes; scipy has no code for it and reports 4 with this in the text.
_NODE_LIMIT_TEXT = 'HiGHS Status 16:'


class MilpError(ValueError):
    """The partition problem is malformed, infeasible, or the solver found no solution in time.

    Attributes:
        status: 'infeasible', 'time_limit', 'node_limit' or 'error' (malformed input, or any other solver end).

    """

    def __init__(self, message: str, status: str = 'error') -> None:
        super().__init__(message)
        self.status = status


class ExactPartition:
    """Minimum-disruption partition with connected, coherency-constrained islands (scikit-learn style).

    Args:
        time_limit_s: Wall-clock limit for HiGHS, s. On hitting it the best solution found is kept and
            `status_` is 'time_limit' with `gap_` > 0 (or MilpError if none was found).
        mip_rel_gap: Relative optimality gap at which HiGHS may stop, fraction (0 = prove optimality).
        node_limit: Branch-and-bound nodes HiGHS may explore (None = no limit): a budget that, unlike the time
            limit, does not depend on machine load. On hitting it the best solution found is kept and `status_` is
            'node_limit' (or MilpError if none was found).

    Attributes:
        labels_: Island per bus, aligned with grid.buses (island = the generator group number).
        disruption_mw_: Eq. 9 objective of the returned partition, MW.
        bound_mw_: Best lower bound on eq. 9 the solver proved, MW.
        gap_: Relative optimality gap (disruption - bound) / disruption, fraction; 0 when optimal.
        status_: 'optimal', 'time_limit' or 'node_limit'.
        optimal_: Whether optimality was proved (within mip_rel_gap).
        solve_time_s_: Wall time of the solve, s.
        cut_branch_ids_: In-service branches joining two islands.

    """

    def __init__(self, time_limit_s: float = 60.0, mip_rel_gap: float = 0.0, node_limit: int | None = None) -> None:
        self.time_limit_s = time_limit_s
        self.mip_rel_gap = mip_rel_gap
        self.node_limit = node_limit

    def fit(self, grid: Grid, generator_groups: Mapping[str, int]) -> ExactPartition:
        """Solve the partition problem.

        Args:
            grid: Network with branch flows (p_from_mw, p_to_mw); without them PYPOWER's AC flow is run.
            generator_groups: Generator name -> 0-based coherent group. Generators left out are unconstrained.

        Returns:
            self.

        Raises:
            MilpError: Unknown generator names, one bus holding generators of two groups, a group whose
                generators cannot share a connected island, or no solution within the time limit.

        """
        if self.time_limit_s <= 0:
            raise MilpError(f'time_limit_s must be positive, got {self.time_limit_s}')
        start = time.perf_counter()
        if not grid.has_flows:
            grid = grid.with_flows()
        bus_index = {b: n for n, b in enumerate(grid.buses)}
        fixed = _fixed_buses(grid, generator_groups)
        n_bus = len(grid.buses)
        groups = sorted(set(fixed.values()))
        if len(groups) <= 1:
            self._finish(np.full(n_bus, groups[0] if groups else 0, dtype=int), grid, 0.0, 0.0, 'optimal', start)
            return self
        k = len(groups)
        col = {g: c for c, g in enumerate(groups)}

        edges, weights = _edges(grid, bus_index)
        n_edge = len(edges)
        n_x, n_y, n_f = n_bus * k, n_edge, 2 * n_edge * k

        def xv(i: int, c: int) -> int:
            return i * k + c

        def fv(e: int, direction: int, c: int) -> int:
            return n_x + n_y + (e * 2 + direction) * k + c

        lb = np.zeros(n_x + n_y + n_f)
        ub = np.concatenate([np.ones(n_x + n_y), np.full(n_f, float(n_bus))])
        roots = _roots(grid, bus_index, edges, fixed, col, lb, ub, xv)

        rows: list[int] = []
        cols: list[int] = []
        vals: list[float] = []
        lo: list[float] = []
        hi: list[float] = []

        def add(terms: list[tuple[int, float]], low: float, high: float) -> None:
            r = len(lo)
            for v, a in terms:
                rows.append(r)
                cols.append(v)
                vals.append(a)
            lo.append(low)
            hi.append(high)

        for i in range(n_bus):
            add([(xv(i, c), 1.0) for c in range(k)], 1.0, 1.0)
        for e, (i, j) in enumerate(edges):
            for c in range(k):
                add([(n_x + e, 1.0), (xv(i, c), -1.0), (xv(j, c), 1.0)], 0.0, np.inf)
                add([(n_x + e, 1.0), (xv(i, c), 1.0), (xv(j, c), -1.0)], 0.0, np.inf)
                for direction, (a, b) in enumerate(((i, j), (j, i))):
                    add([(fv(e, direction, c), 1.0), (xv(a, c), -float(n_bus))], -np.inf, 0.0)
                    add([(fv(e, direction, c), 1.0), (xv(b, c), -float(n_bus))], -np.inf, 0.0)
        incident: list[list[tuple[int, int, int]]] = [[] for _ in range(n_bus)]
        for e, (i, j) in enumerate(edges):
            incident[i].append((e, 1, 0))  # arc j->i (direction 1) flows into i
            incident[i].append((e, 0, 1))
            incident[j].append((e, 0, 0))
            incident[j].append((e, 1, 1))
        for i in range(n_bus):
            if roots[i] is None:
                continue
            for c in range(k):
                if c in roots[i]:
                    continue
                terms = [(fv(e, d, c), 1.0 if not out else -1.0) for e, d, out in incident[i]]
                add(terms + [(xv(i, c), -1.0)], 0.0, 0.0)

        matrix = sparse.csr_array((vals, (rows, cols)), shape=(len(lo), n_x + n_y + n_f))
        cost = np.concatenate([np.zeros(n_x), weights, np.zeros(n_f)])
        integrality = np.concatenate([np.ones(n_x), np.zeros(n_y + n_f)])
        options = {'time_limit': float(self.time_limit_s), 'mip_rel_gap': float(self.mip_rel_gap), 'disp': False}
        if self.node_limit is not None:
            options['node_limit'] = int(self.node_limit)
        result = milp(cost, integrality=integrality, bounds=Bounds(lb, ub),
                      constraints=LinearConstraint(matrix, lo, hi), options=options)
        status = _STATUS.get(result.status, 'error')
        if status == 'error' and _NODE_LIMIT_TEXT in str(result.message):
            status = 'node_limit'
        if result.x is None:
            if status == 'infeasible':
                raise MilpError(f'no partition of {grid.name} keeps every group on one connected island with its '
                                'generators (a group is split by the outages or separated by another group)', status)
            raise MilpError(f'HiGHS found no partition of {grid.name} ({status}: {result.message}) within '
                            f'{self.time_limit_s} s and {self.node_limit} nodes', status)
        x = np.rint(result.x[:n_x]).reshape(n_bus, k)
        labels = np.array([groups[int(c)] for c in x.argmax(axis=1)], dtype=int)
        objective = float(result.fun)
        bound = float(getattr(result, 'mip_dual_bound', objective) or objective)
        self._finish(labels, grid, objective, bound, status, start)
        return self

    def _finish(self, labels: np.ndarray, grid: Grid, objective_mw: float, bound_mw: float, status: str,
                start: float) -> None:
        self.labels_ = labels
        self.disruption_mw_ = objective_mw
        self.bound_mw_ = min(bound_mw, objective_mw)
        self.gap_ = 0.0 if objective_mw <= 1e-9 else max(0.0, (objective_mw - self.bound_mw_) / objective_mw)
        self.status_ = status
        self.optimal_ = status == 'optimal'
        self.solve_time_s_ = time.perf_counter() - start
        island = dict(zip(grid.buses, labels.tolist(), strict=True))
        self.cut_branch_ids_ = tuple(b.branch_id for b in grid.branches
                                     if b.in_service and island[b.from_bus] != island[b.to_bus])


def gap_pct(disrupted_mw: float, optimum_mw: float) -> float:
    """Return a partition's disruption above the exact optimum, % of the optimum (0 within 1e-6 MW; inf over 0)."""
    excess_mw = disrupted_mw - optimum_mw
    if abs(excess_mw) <= 1e-6:
        return 0.0
    return math.inf if optimum_mw <= 1e-9 else 100.0 * excess_mw / optimum_mw


def _fixed_buses(grid: Grid, generator_groups: Mapping[str, int]) -> dict[int, int]:
    by_name = {g.name: g for g in grid.generators}
    unknown = sorted(set(generator_groups) - set(by_name))
    if unknown:
        raise MilpError(f'generator_groups names generators not in {grid.name}: {unknown[:10]}')
    fixed: dict[int, int] = {}
    for name, group in generator_groups.items():
        if int(group) < 0:
            raise MilpError(f'generator {name}: group must be a 0-based int, got {group}')
        bus = by_name[name].bus
        if fixed.setdefault(bus, int(group)) != int(group):
            raise MilpError(f'bus {bus} holds generators of groups {fixed[bus]} and {group}; one bus cannot be '
                            'on two islands')
    return fixed


def _edges(grid: Grid, bus_index: Mapping[int, int]) -> tuple[list[tuple[int, int]], np.ndarray]:
    """In-service edges between distinct buses, parallel branches merged, with eq. 9 weights in MW."""
    assert grid.p_from_mw is not None and grid.p_to_mw is not None
    weight: dict[tuple[int, int], float] = {}
    for b, pf, pt in zip(grid.branches, grid.p_from_mw, grid.p_to_mw, strict=True):
        i, j = bus_index[b.from_bus], bus_index[b.to_bus]
        if not b.in_service or i == j:
            continue
        key = (min(i, j), max(i, j))
        weight[key] = weight.get(key, 0.0) + (abs(pf) + abs(pt)) / 2.0
    edges = sorted(weight)
    return edges, np.array([weight[e] for e in edges], dtype=float)


def _roots(grid: Grid, bus_index: Mapping[int, int], edges: list[tuple[int, int]], fixed: Mapping[int, int],
           col: Mapping[int, int], lb: np.ndarray, ub: np.ndarray, xv) -> list[set[int] | None]:
    """Fix generator buses, forbid islands absent from a network part, and pick one flow root per part and group.

    Returns, per bus, the island columns it is the root of (empty set = a consumer), or None for a dead bus.
    """
    k = len(col)
    graph = nx.Graph()
    graph.add_nodes_from(range(len(grid.buses)))
    graph.add_edges_from(edges)
    roots: list[set[int] | None] = [set() for _ in grid.buses]
    for part in nx.connected_components(graph):
        present: dict[int, int] = {}
        for i in sorted(part):
            group = fixed.get(grid.buses[i])
            if group is not None:
                present.setdefault(col[group], i)
                lb[xv(i, col[group])] = 1.0
        if not present:
            for i in part:
                roots[i] = None
                for c in range(1, k):
                    ub[xv(i, c)] = 0.0
            continue
        for i in part:
            for c in range(k):
                if c not in present:
                    ub[xv(i, c)] = 0.0
        for c, i in present.items():
            roots[i].add(c)
    return roots
