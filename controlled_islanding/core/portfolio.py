"""A portfolio partitioner: the paper's constrained spectral clustering and the exact optimum, keeping the lower cut.

Both members solve the same problem (issue 12): every bus on the island of a coherent group, each island
connected with its group's generators, generators without a group (no PMU) unconstrained, and the lower eq. 9
disruption (the sum over cut branches of (|P_from| + |P_to|) / 2, MW) wins. A tie keeps the paper's method, so
wherever it is already optimal the decision is the paper's, bus for bus.

The exact member is tried in order of cost, each step exact:
1. Lower bound (no connectivity): for each group g, the minimum cut separating g's generator buses from every
   other group's (an isolating cut, max-flow). Any valid partition cuts at least max_g c_g, and at least
   sum_g c_g / 2 (island g's boundary is at least c_g, and each cut branch bounds two islands). When the
   spectral cut equals this bound it is optimal and nothing more is solved.
2. With two groups the bound is the minimum s-t cut itself; when both its sides are connected it is a valid
   partition, hence optimal, and HiGHS is not needed.
3. Otherwise the MILP of core/milp.py (HiGHS), within a budget that does not depend on machine load: only if
   it has at most `max_milp_binaries` binary variables (buses x groups) and at most `node_limit`
   branch-and-bound nodes. A wall-clock limit is only a safety net: when it fires the MILP's answer is not used
   (a decision must not depend on how busy the machine is) and the result says so.

The min-cut weights are integers for scipy's max-flow (scaled to the int32 range, rounded down): the bound stays
rigorous, and the cut found is optimal to within one rounding step per cut branch (about 1e-5 MW on IEEE 39);
`milp_gap_` says how close.

Measured (load 9-10 on the shared 2-core machine) on the 88 two-group instances the observability sweep builds
from bags/ (GBnetwork included, 25 to 100 % of the PMUs): the portfolio's cut equalled the MILP optimum in all 88,
the spectral cut was above it in 28 (up to 16052 against 293 MW on GBnetwork at 25 %); the minimum cut gave a
connected optimum in all but one, which HiGHS then solved. The exact member took 2-30 ms on IEEE 39 and 20-100 ms
on GBnetwork, where the spectral fit took 3-40 ms and 0.3-1.6 s, and HiGHS alone 35 ms and 3.7-15.5 s. With three or
four regional groups HiGHS took 50-90 ms on IEEE 39 and Nordic 44 (<= 176 binaries) and 3.7-13 s on EI 33 (1584
and 2112 binaries), hence the default cap of 1000 binaries.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import breadth_first_order, connected_components, maximum_flow

from controlled_islanding.core.grid import Grid
from controlled_islanding.core.milp import ExactPartition, MilpError
from controlled_islanding.core.spectral import ConstrainedSpectralPartition, SpectralError

# Two cuts within this of each other are a tie (MW, plus the same fraction of the cut): the figures are sums of
# the same branch flows in different orders.
_TIE_MW = 1e-6
_TIE_FRACTION = 1e-9


class PortfolioPartition:
    """Partition by the paper's spectral method and by the exact optimum within a budget; keep the lower eq. 9.

    Args:
        spectral: The paper's method; default `ConstrainedSpectralPartition()` (refinement on).
        node_limit: Branch-and-bound nodes HiGHS may explore (deterministic budget).
        max_milp_binaries: HiGHS is run only on models with at most this many binary variables, buses x groups
            (deterministic budget; module docstring for the measurements behind the default).
        safety_time_limit_s: Wall-clock cap on HiGHS, s; when it fires its answer is discarded and said so. Below
            the partitioning node's hang limit (10 s without a heartbeat).

    Attributes:
        labels_: Island (= coherent group) of each bus, aligned with `grid.buses`.
        winner_: 'spectral' or 'milp' (the exact member: min cut or HiGHS).
        spectral_: The fitted spectral member (None if it failed).
        spectral_disruption_mw_: Eq. 9 of the spectral partition, MW (None if it failed).
        spectral_error_: Why the spectral fit failed ('' if it did not).
        milp_disruption_mw_: Eq. 9 of the exact member's partition, MW (None if it gave none).
        milp_method_: 'min-cut', 'highs', or '' when no exact partition was computed.
        milp_status_: 'optimal', 'node_limit' (best found within the nodes), 'time_limit' (safety net fired),
            'infeasible', 'error', 'skipped' (over the budget), or 'not needed' (spectral proven optimal).
        milp_gap_: Relative gap (disruption - bound) / disruption of the exact member, fraction (None: no answer).
        lower_bound_mw_: The isolating-cut lower bound on eq. 9, MW.
        milp_reason_: Why the exact member gave no usable partition ('' if it gave one).
        fallback_: The spectral member's eq. 6 fallback when its partition is kept ('' otherwise).
        summary_: One line for logs: the winner, both disruptions, the exact member's status and gap.
        spectral_time_s_, milp_time_s_: Wall time of each member, s.

    """

    def __init__(self, spectral: ConstrainedSpectralPartition | None = None, node_limit: int = 1000,
                 max_milp_binaries: int = 1000, safety_time_limit_s: float = 5.0) -> None:
        self.spectral = spectral
        self.node_limit = node_limit
        self.max_milp_binaries = max_milp_binaries
        self.safety_time_limit_s = safety_time_limit_s

    def fit(self, grid: Grid, generator_groups: Mapping[str, int]) -> PortfolioPartition:
        """Partition the buses.

        Args:
            grid: The grid; flows are computed by AC power flow if absent.
            generator_groups: Group (0-based) of every observed generator, by name; at least two groups.
                A generator left out (no PMU) is unconstrained.

        Returns:
            self.

        Raises:
            SpectralError: The spectral fit failed and the exact member gave no partition either (the spectral
                error, with the exact member's reason appended).

        """
        if self.node_limit < 0 or self.max_milp_binaries < 0 or self.safety_time_limit_s <= 0:
            raise SpectralError(f'node_limit ({self.node_limit}) and max_milp_binaries ({self.max_milp_binaries}) '
                                f'must not be negative, safety_time_limit_s ({self.safety_time_limit_s}) positive')
        if not grid.has_flows:
            grid = grid.with_flows()
        t0 = time.perf_counter()
        self.spectral_, self.spectral_error_, self.spectral_disruption_mw_ = None, '', None
        spectral_labels = None
        try:
            member = ConstrainedSpectralPartition() if self.spectral is None else self.spectral
            spectral_labels = member.fit(grid, generator_groups).labels_
            self.spectral_ = member
            self.spectral_disruption_mw_ = disruption_mw(grid, spectral_labels)
        except SpectralError as exc:
            self.spectral_error_ = str(exc)
        self.spectral_time_s_ = time.perf_counter() - t0

        t0 = time.perf_counter()
        exact_labels = self._exact(grid, generator_groups)
        self.milp_time_s_ = time.perf_counter() - t0

        if spectral_labels is None and exact_labels is None:
            raise SpectralError(f'{self.spectral_error_}; exact partition: {self.milp_reason_}')
        if exact_labels is not None and (spectral_labels is None or _lower(self.milp_disruption_mw_,
                                                                          self.spectral_disruption_mw_)):
            self.winner_, self.labels_, self.fallback_ = 'milp', exact_labels, ''
        else:
            self.winner_, self.labels_ = 'spectral', spectral_labels
            self.fallback_ = str(getattr(self.spectral_, 'fallback_', ''))
        self.summary_ = self._summary()
        return self

    def _exact(self, grid: Grid, generator_groups: Mapping[str, int]) -> np.ndarray | None:
        """Run the exact member within the budget; set its attributes and return its labels (None: none usable)."""
        self.milp_disruption_mw_, self.milp_method_, self.milp_gap_, self.milp_reason_ = None, '', None, ''
        self.lower_bound_mw_ = 0.0
        try:
            bound, min_cut = isolating_cut_bound(grid, generator_groups)
        except ValueError as exc:
            self.milp_status_, self.milp_reason_ = 'error', str(exc)
            return None
        self.lower_bound_mw_ = bound
        if self.spectral_disruption_mw_ is not None and not _lower(bound, self.spectral_disruption_mw_):
            self.milp_status_ = 'not needed'
            self.milp_reason_ = (f'the spectral cut equals the isolating-cut lower bound {bound:.3f} MW, so it is '
                                 'optimal')
            return None
        if min_cut is not None:
            self.milp_method_, self.milp_status_ = 'min-cut', 'optimal'
            self.milp_disruption_mw_ = disruption_mw(grid, min_cut)
            self.milp_gap_ = max(0.0, self.milp_disruption_mw_ - bound) / max(self.milp_disruption_mw_, 1e-9)
            return min_cut
        n_groups = len(set(int(g) for g in generator_groups.values()))
        binaries = len(grid.buses) * n_groups
        if binaries > self.max_milp_binaries:
            self.milp_status_ = 'skipped'
            self.milp_reason_ = (f'the MILP has {binaries} binary variables ({len(grid.buses)} buses x {n_groups} '
                                 f'groups), over max_milp_binaries = {self.max_milp_binaries}')
            return None
        self.milp_method_ = 'highs'
        model = ExactPartition(time_limit_s=self.safety_time_limit_s, node_limit=self.node_limit)
        try:
            model.fit(grid, generator_groups)
        except MilpError as exc:
            self.milp_status_, self.milp_reason_ = exc.status, str(exc)
            if exc.status == 'time_limit':
                self.milp_reason_ = f'the safety-net time limit of {self.safety_time_limit_s:g} s fired: {exc}'
            return None
        self.milp_status_, self.milp_gap_ = model.status_, float(model.gap_)
        self.milp_disruption_mw_ = disruption_mw(grid, model.labels_)
        if model.status_ == 'time_limit' and self.spectral_disruption_mw_ is not None:
            self.milp_reason_ = (f'the safety-net time limit of {self.safety_time_limit_s:g} s fired (gap '
                                 f'{100 * model.gap_:.2f} %); its answer is not used, so the decision does not '
                                 'depend on machine load')
            return None
        if model.status_ not in ('optimal', 'node_limit', 'time_limit'):
            self.milp_reason_ = f'HiGHS ended with status {model.status_}'
            return None
        return model.labels_

    def _summary(self) -> str:
        spectral = ('failed: ' + self.spectral_error_ if self.spectral_disruption_mw_ is None
                    else f'{self.spectral_disruption_mw_:.1f} MW')
        exact = '-' if self.milp_disruption_mw_ is None else f'{self.milp_disruption_mw_:.1f} MW'
        gap = '' if self.milp_gap_ is None else f', gap {100 * self.milp_gap_:.2g} %'
        method = f' by {self.milp_method_}' if self.milp_method_ else ''
        reason = f' ({self.milp_reason_})' if self.milp_reason_ else ''
        return (f'portfolio: {self.winner_} kept; spectral {spectral}, exact {exact}{method} '
                f'[{self.milp_status_}{gap}]{reason}')


def disruption_mw(grid: Grid, labels: np.ndarray) -> float:
    """Return eq. 9 of a partition (labels aligned with grid.buses), MW; summed as `evaluate_partition` does."""
    assert grid.p_from_mw is not None and grid.p_to_mw is not None
    island = dict(zip(grid.buses, np.asarray(labels).tolist(), strict=True))
    return float(sum((abs(pf) + abs(pt)) / 2.0
                     for b, pf, pt in zip(grid.branches, grid.p_from_mw, grid.p_to_mw, strict=True)
                     if b.in_service and island[b.from_bus] != island[b.to_bus]))


def isolating_cut_bound(grid: Grid, generator_groups: Mapping[str, int]) -> tuple[float, np.ndarray | None]:
    """Return a lower bound on eq. 9 over valid partitions, MW, and with two groups a minimum cut when it is valid.

    The bound is max(max_g c_g, sum_g c_g / 2) over the isolating cuts c_g (module docstring), each from a maximum
    flow (scipy's Dinic). That needs integer capacities: the weights are scaled so that all of them together fit
    in int32 and rounded down, so the flow found is feasible for the true weights and the bound is rigorous; the
    cut found is then minimal to within one rounding step per cut branch (2^-30 of the total branch weight each).
    With two groups the cut's sides, as labels aligned with grid.buses, are returned when each side is connected
    (a valid partition, hence optimal to that precision), else None.

    Raises:
        ValueError: A generator not in the grid, or one bus holding generators of two groups.

    """
    assert grid.p_from_mw is not None and grid.p_to_mw is not None
    index = {b: i for i, b in enumerate(grid.buses)}
    by_name = {g.name: index[g.bus] for g in grid.generators}
    bus_group: dict[int, int] = {}
    for name, group in generator_groups.items():
        if name not in by_name:
            raise ValueError(f'generator {name} is not in {grid.name}')
        if bus_group.setdefault(by_name[name], int(group)) != int(group):
            raise ValueError(f'bus {grid.buses[by_name[name]]} holds generators of groups '
                             f'{bus_group[by_name[name]]} and {group}')
    groups = sorted(set(bus_group.values()))
    if len(groups) < 2:
        return 0.0, None
    n = len(grid.buses)
    ends, weights = [], []
    for b, pf, pt in zip(grid.branches, grid.p_from_mw, grid.p_to_mw, strict=True):
        i, j = index[b.from_bus], index[b.to_bus]
        if b.in_service and i != j:
            ends.append((i, j))
            weights.append((abs(pf) + abs(pt)) / 2.0)
    pairs = np.array(ends, dtype=np.int64).reshape(-1, 2)
    weight = np.array(weights)
    scale = 2.0 ** 30 / max(float(weight.sum()), 1e-9)
    capacity = np.floor(weight * scale).astype(np.int64)
    fixed = np.array(sorted(bus_group), dtype=np.int64)
    unbounded = 2 ** 31 - 1  # above any cut, which is at most 2^30 after scaling
    cuts, inside = [], None
    for g in groups[:1] if len(groups) == 2 else groups:
        terminal = np.where([bus_group[int(i)] == g for i in fixed], n, n + 1)
        # Both directions of each branch, and source -> g's buses, the other groups' buses -> sink.
        rows = np.concatenate([pairs[:, 0], pairs[:, 1], np.where(terminal == n, n, fixed)])
        cols = np.concatenate([pairs[:, 1], pairs[:, 0], np.where(terminal == n, fixed, n + 1)])
        data = np.concatenate([capacity, capacity, np.full(len(fixed), unbounded)]).astype(np.int32)
        graph = sparse.csr_array((data, (rows, cols)), shape=(n + 2, n + 2))
        result = maximum_flow(graph, n, n + 1, method='dinic')
        cuts.append(result.flow_value / scale)
        residual = sparse.csr_array(graph - result.flow)
        residual.data = (residual.data > 0).astype(np.int8)
        residual.eliminate_zeros()
        inside = np.zeros(n + 2, dtype=bool)
        inside[breadth_first_order(residual, n, directed=True, return_predecessors=False)] = True
        inside = inside[:n]
    if len(groups) > 2:
        return max(max(cuts), sum(cuts) / 2.0), None
    assert inside is not None
    # Every bus the residual flow reaches is joined to a source bus inside its side. The rest may hold pieces with
    # no sink bus, left out only by branches of (almost) no weight; each borders the source side alone, so moving
    # it there cuts no more.
    piece = _pieces(n, pairs, inside)
    sink_pieces = {int(piece[i]) for i in fixed if bus_group[int(i)] == groups[1]}
    inside = np.array([inside[i] or int(piece[i]) not in sink_pieces for i in range(n)])
    piece = _pieces(n, pairs, inside)
    if len(set(piece[inside].tolist())) == 1 and len(set(piece[~inside].tolist())) == 1:
        return cuts[0], np.where(inside, groups[0], groups[1])
    return cuts[0], None


def _pieces(n: int, pairs: np.ndarray, side: np.ndarray) -> np.ndarray:
    """Return the connected piece of each bus over the branches whose ends are on the same side."""
    same = pairs[side[pairs[:, 0]] == side[pairs[:, 1]]]
    adjacency = sparse.csr_array((np.ones(len(same)), (same[:, 0], same[:, 1])), shape=(n, n))
    return connected_components(adjacency, directed=False)[1]


def _lower(a_mw: float | None, b_mw: float | None) -> bool:
    """Whether a is lower than b beyond a tie (module constants)."""
    if a_mw is None or b_mw is None:
        return False
    return a_mw < b_mw - _TIE_MW - _TIE_FRACTION * max(abs(b_mw), 1.0)

