"""Every islanding method on one case: a scenario bag, or one of the paper's IEEE 39 cases.

The logic of `controlled-islanding evaluate`, whose --help explains the methods and the columns; the rows of a
case are rendered by evaluation/report.py (tables, JSON, figures, the Markdown page).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from controlled_islanding.evaluation.bag_angles import EvaluateError, generator_series, request_time_s

if TYPE_CHECKING:
    from controlled_islanding.core.grid import Grid
    from controlled_islanding.core.islanding import IslandingDecision
    from controlled_islanding.evaluation.coherency_rules import Detection

log = logging.getLogger(__name__)

# The paper's cascades on IEEE 39 (MATPOWER case39) and the groups it published, by generator name
# (G<k> = k-th generator row, G1 at bus 30 ... G10 at bus 39). The paper's text leaves G10 out of its DTW
# groups; its Tables I and V put bus 39 with G2-G7 in case 1 and with G1-G3, G8, G9 in case 2.
PAPER_CASES: dict[str, dict[str, Any]] = {
    'paper_case1': {
        'description': 'Section IV-A: line 16-17 then line 2-1 tripped; islanding at 9 s',
        'outages': ('16-17', '1-2'),
        'groups': {
            'dtw': [['G1', 'G8', 'G9'], ['G2', 'G3', 'G4', 'G5', 'G6', 'G7', 'G10']],
            'correlation': [['G2', 'G3', 'G10'], ['G4', 'G5', 'G6', 'G7'], ['G1', 'G8', 'G9']],
        },
    },
    'paper_case2': {
        'description': 'Section IV-B: line 13-14 then line 16-17 tripped',
        'outages': ('13-14', '16-17'),
        'groups': {
            'dtw': [['G1', 'G2', 'G3', 'G8', 'G9', 'G10'], ['G4', 'G5', 'G6', 'G7']],
        },
    },
}


@dataclass
class MethodResult:
    """One row of a table.

    Attributes:
        method: Row label.
        groups: Generator name -> coherent group used (None if the method failed before grouping).
        decision: The islanding decision (None if the method failed).
        compute_time_s: Wall time of coherency plus partitioning, s.
        coherency_time_s: Wall time of the coherency part alone, s.
        optimum_mw: Exact minimum of eq. 9 under this row's groups, MW (None if unknown).
        note: What went wrong or what to know (MILP status and gap, failures).

    """

    method: str
    groups: dict[str, int] | None
    decision: IslandingDecision | None
    compute_time_s: float
    coherency_time_s: float = 0.0
    optimum_mw: float | None = None
    note: str = ''
    closed_loop: dict[str, Any] | None = None

    @property
    def gap_pct(self) -> float | None:
        """Disruption above the exact optimum under the same groups, % of the optimum (None if unknown)."""
        if self.decision is None or self.optimum_mw is None:
            return None
        from controlled_islanding.core.milp import gap_pct

        return gap_pct(self.decision.disrupted_mw, self.optimum_mw)


@dataclass
class CaseReport:
    """All methods on one case.

    Attributes:
        name: Case name (bag directory name or paper case id).
        source: Where the case came from.
        grid: The grid the methods split.
        truth_groups: The bag's true groups (None for paper cases).
        rows: One result per method.
        figures: Figure name -> path.
        k_rule: The k rule DTW coherency used (bags only).
        first_pole_slip_s: First time two machines were pi rad apart, s (None: never, or not a bag).
        detection: When the k rule first found the true groups (unstable bags only).

    """

    name: str
    source: str
    grid: Grid
    truth_groups: dict[str, int] | None
    rows: list[MethodResult]
    figures: dict[str, Path] = field(default_factory=dict)
    k_rule: str = ''
    first_pole_slip_s: float | None = None
    detection: Detection | None = None
    no_action: dict[str, Any] | None = None


def coherency_node_parameters() -> dict[str, Any]:
    """Return the coherency node's parameters from config/coherency.yaml, so evaluate groups as the node does."""
    from controlled_islanding.locations import config_dir

    path = config_dir() / 'coherency.yaml'
    if not path.is_file():
        return {}
    import yaml

    return dict(((yaml.safe_load(path.read_text()) or {}).get('/**/coherency') or {}).get('ros__parameters') or {})


def manifest_entry(bag) -> dict | None:
    """Return the bag's entry in the bags/index.yaml beside it (None if there is none)."""
    from controlled_islanding.sim.manifest import entry_for_bag

    return entry_for_bag(bag.path)


def closed_loop_outcomes(case: CaseReport, scenario_path: Path, config: Any = None) -> None:
    """Run every row's cut of a bag's case in ANDES and judge its islands; fill row.closed_loop and case.no_action.

    The cut opens config.breaker_operating_s after the scenario's request for every row alike; rows with the same
    cut share one run, and a row that does not split is the no-action run (`controlled-islanding evaluate --help`,
    --closed-loop).

    Args:
        case: A bag's case, its rows decided.
        scenario_path: The scenario YAML the bag was simulated from.
        config: A sim.closed_loop.LoopConfig (default: its defaults, the testbed's).

    Raises:
        EvaluateError: The scenario cannot be read or simulated.

    """
    from controlled_islanding.sim.closed_loop import ClosedLoopError, LoopConfig, run_offline
    from controlled_islanding.sim.scenario import ScenarioError, load_scenario

    config = config or LoopConfig()
    try:
        scenario = load_scenario(scenario_path)
    except ScenarioError as exc:
        raise EvaluateError(str(exc)) from exc
    opened_s = scenario.request_s + config.breaker_operating_s
    runs: dict[tuple[str, ...], dict[str, Any]] = {}

    def outcome(decision: IslandingDecision | None) -> dict[str, Any]:
        cut = tuple(sorted(decision.cut_branch_ids)) if decision is not None and decision.split else ()
        if cut not in runs:
            log.info('%s: closed loop, cut %s (ANDES)', case.name, ', '.join(cut) or 'none')
            try:
                if cut:
                    run = run_offline(scenario, 'cut', cut_branch_ids=cut, bus_island=decision.bus_island,
                                      actions=decision.remedial, opened_s=opened_s, config=config)
                else:
                    run = run_offline(scenario, 'no action', judged_from_s=opened_s, config=config)
            except (ClosedLoopError, ScenarioError, RuntimeError) as exc:
                raise EvaluateError(f'{scenario_path}: closed loop: {exc}') from exc
            summary = run.summary()
            runs[cut] = {k: summary[k] for k in ('opened_s', 'judged_from_s', 'all_survived', 'load_lost_mw',
                                                 'shed_mw', 'rejected_mw', 'f_nadir_hz', 'f_peak_hz', 'v_min_pu',
                                                 'load_served_mw', 'load_served_pct', 'simulation_failed')}
            runs[cut]['islands'] = [{k: i[k] for k in ('island', 'generators', 'survived', 'why_not',
                                                       'max_pair_swing_rad', 'f_nadir_hz', 'f_peak_hz', 'v_min_pu',
                                                       'v_max_pu', 'rejected')} for i in summary['islands']]
        return runs[cut]

    case.no_action = outcome(None)
    for row in case.rows:
        if row.decision is not None:
            row.closed_loop = outcome(row.decision)


def _groups_from_lists(lists: Sequence[Sequence[str]]) -> dict[str, int]:
    return {name: k for k, names in enumerate(lists) for name in names}


def evaluate_paper_case(name: str, *, time_limit_s: float = 60.0) -> CaseReport:
    """Run every method on one of the paper's cases, using the groups the paper published.

    The grid is MATPOWER case39 with its pre-fault AC flows (the paper islands with pre-fault power-flow
    conditions) and the case's two tripped lines taken out. DTW and correlation groups are the paper's;
    community detection computes its own. A method the paper gives no groups for is a row saying so.

    Args:
        name: A key of PAPER_CASES.
        time_limit_s: MILP time limit per solve, s.

    Returns:
        The case report.

    Raises:
        EvaluateError: Unknown case name.

    """
    from controlled_islanding.core.grid import Grid

    if name not in PAPER_CASES:
        raise EvaluateError(f'unknown paper case {name!r}; known: {sorted(PAPER_CASES)}')
    spec = PAPER_CASES[name]
    grid = Grid.from_matpower('case39').with_flows().with_outages(spec['outages'])
    published = {m: _groups_from_lists(g) for m, g in spec['groups'].items()}
    methods: list[tuple[str, Callable[[], dict[str, int]] | None, str]] = []
    for label, key in (('dtw (paper groups) + spectral', 'dtw'), ('correlation (paper groups) + spectral',
                                                                    'correlation')):
        groups = published.get(key)
        methods.append((label, (lambda g=groups: g) if groups else None,
                        '' if groups else f'the paper publishes no {key} groups for this case'))
    rows = run_methods(grid, methods, exact_for='dtw (paper groups)', time_limit_s=time_limit_s)
    return CaseReport(name=name, source=f"MATPOWER case39, {spec['description']}", grid=grid, truth_groups=None,
                      rows=rows)


def evaluate_bag(bag, *, window_s: float = 3.0, max_groups: int = 4, dtw_band: int | None = None,
                 time_limit_s: float = 60.0, k_rule: str | None = None, lead_step_s: float = 0.05) -> CaseReport:
    """Run every method on one scenario bag.

    Args:
        bag: A BagData (controlled_islanding.wire.bagdata.load_bag).
        window_s: Rotor-angle window before the islanding request, s.
        max_groups: Most coherent groups considered.
        dtw_band: Sakoe-Chiba half-width of the DTW path, samples (None = none).
        time_limit_s: MILP time limit per solve, s.
        k_rule: How DTW coherency chooses k (core.k_rules.RULES; None: the core's default).
        lead_step_s: Spacing of the request times tried for the detection lead, s.

    Returns:
        The case report; truth and first pole slip from the bags/index.yaml beside the bag when it lists it.

    Raises:
        EvaluateError: The bag's PMU data cannot give rotor angles for every generator.

    """
    from controlled_islanding.core.coherency import DTWCoherency
    from controlled_islanding.core.correlation import CorrelationCoherency
    from controlled_islanding.core.k_rules import DEFAULT_RULE
    from controlled_islanding.evaluation import coherency_rules as study

    k_rule = k_rule or DEFAULT_RULE
    end_s = request_time_s(bag)
    _, names, angles = generator_series(bag, end_s - window_s, end_s)
    grid = bag.grid_at(end_s + 1e-9)
    series = list(angles)

    def coherency(model) -> dict[str, int]:
        labels = model.fit(series).labels_
        return {n: int(k) for n, k in zip(names, labels, strict=True)}

    methods = [('dtw + spectral', lambda: coherency(DTWCoherency(max_groups=max_groups, window=dtw_band,
                                                                  k_rule=k_rule)), ''),
               ('correlation + spectral', lambda: coherency(CorrelationCoherency()), '')]
    rows = run_methods(grid, methods, exact_for='dtw', time_limit_s=time_limit_s)
    scenario = study.scenario_from_bag(bag, manifest_entry(bag))
    detection = None
    if scenario.truth_k > 1:
        detection = study.detect(scenario, rule=k_rule, window_s=window_s, max_groups=max_groups, dtw_band=dtw_band,
                                 step_s=lead_step_s)
    return CaseReport(name=bag.path.name, source=str(bag.path), grid=grid, truth_groups=scenario.truth, rows=rows,
                      k_rule=k_rule, first_pole_slip_s=scenario.first_pole_slip_s, detection=detection)


def run_methods(grid: Grid, coherency_methods: Sequence[tuple[str, Callable[[], dict[str, int]] | None, str]], *,
                exact_for: str, time_limit_s: float) -> list[MethodResult]:
    """Run the coherency methods through the spectral partitioning, then community detection and the MILP.

    Args:
        grid: Grid with flows and the outages applied.
        coherency_methods: (row label ending in ' + spectral', groups factory or None, note) per method.
        exact_for: Label prefix of the row whose groups the MILP row uses.
        time_limit_s: MILP time limit per solve, s.

    Returns:
        The rows, each with the exact optimum under its own groups.

    """
    from controlled_islanding.core import spectral  # imported here so no row's time includes the import
    from controlled_islanding.core.community import CommunityPartition
    from controlled_islanding.core.islanding import decide, evaluate_partition

    rows: list[MethodResult] = []
    for label, factory, note in coherency_methods:
        if factory is None:
            rows.append(MethodResult(label, None, None, 0.0, note=note))
            continue
        start = time.perf_counter()
        groups = None
        try:
            groups = factory()
            grouped = time.perf_counter()
            decision = decide(grid, groups)
        except ValueError as exc:
            rows.append(MethodResult(label, groups, None, time.perf_counter() - start, note=f'failed: {exc}'))
            continue
        rows.append(MethodResult(label, groups, decision, time.perf_counter() - start, grouped - start, note=note))

    base = next((r for r in rows if r.method.startswith(exact_for) and r.groups is not None), None)
    if base is not None:
        # The refinement is ours, not the paper's: this row shows what it changed, on the same groups.
        label = base.method.replace(' + spectral', ' + spectral, unrefined (the paper alone)')
        start = time.perf_counter()
        try:
            decision = decide(grid, base.groups, spectral.ConstrainedSpectralPartition(refine=False))
            rows.append(MethodResult(label, dict(base.groups), decision, time.perf_counter() - start,
                                     note='partitioning time only: the groups are those of the row above'))
        except ValueError as exc:
            rows.append(MethodResult(label, dict(base.groups), None, time.perf_counter() - start,
                                     note=f'failed: {exc}'))

    start = time.perf_counter()
    community = CommunityPartition().fit(grid)
    decision = evaluate_partition(grid, dict(zip(grid.buses, community.labels_.tolist(), strict=True)))
    rows.append(MethodResult('community detection', dict(community.generator_groups_), decision,
                             time.perf_counter() - start))

    base = next((r for r in rows if r.method.startswith(exact_for)), None)
    exact = _exact_row(grid, base, exact_for, time_limit_s)
    optimum_cache: dict[tuple, tuple[float | None, str]] = {}
    for row in rows:
        if row.groups is None:
            continue
        key = tuple(sorted(row.groups.items()))
        if key not in optimum_cache:
            optimum_cache[key] = _optimum(grid, row.groups, time_limit_s)
        row.optimum_mw, extra = optimum_cache[key]
        row.note = '; '.join(x for x in (row.note, extra) if x)
    if exact is not None:
        rows.append(exact)
    return rows


def _optimum(grid: Grid, groups: Mapping[str, int], time_limit_s: float) -> tuple[float | None, str]:
    from controlled_islanding.core.milp import ExactPartition, MilpError

    try:
        model = ExactPartition(time_limit_s=time_limit_s).fit(grid, groups)
    except MilpError as exc:
        return None, f'no exact optimum: {exc}'
    if not model.optimal_:
        # The bound, not the incumbent, is what the row's disruption can honestly be compared with.
        return model.bound_mw_, f'MILP hit its {time_limit_s:g} s limit: gap to bound {100 * model.gap_:.2f} %'
    return model.disruption_mw_, ''


def _exact_row(grid: Grid, base: MethodResult | None, exact_for: str, time_limit_s: float) -> MethodResult | None:
    from controlled_islanding.core.islanding import evaluate_partition
    from controlled_islanding.core.milp import ExactPartition, MilpError

    label = f'{exact_for} + MILP optimum'
    if base is None or base.groups is None:
        return MethodResult(label, None, None, 0.0, note=f'no {exact_for} groups to optimise for')
    start = time.perf_counter()
    try:
        model = ExactPartition(time_limit_s=time_limit_s).fit(grid, base.groups)
    except MilpError as exc:
        return MethodResult(label, dict(base.groups), None, time.perf_counter() - start, note=f'failed: {exc}')
    decision = evaluate_partition(grid, dict(zip(grid.buses, model.labels_.tolist(), strict=True)))
    note = '' if model.optimal_ else (f'TIME LIMIT {time_limit_s:g} s hit: not proven optimal, '
                                      f'gap {100 * model.gap_:.2f} % to bound {model.bound_mw_:.2f} MW')
    # The groups cost what they cost the base row; count them so compute times compare like with like.
    return MethodResult(label, dict(base.groups), decision, base.coherency_time_s + model.solve_time_s_,
                        base.coherency_time_s,
                        optimum_mw=model.bound_mw_ if not model.optimal_ else model.disruption_mw_, note=note)
