"""`controlled-islanding evaluate`: every islanding method on every bag, tables in the shape of Tables IV/VIII."""

from __future__ import annotations

import json
import math
import re
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from controlled_islanding import atomic
from controlled_islanding.commands import CliError

if TYPE_CHECKING:
    from controlled_islanding.core.grid import Grid
    from controlled_islanding.core.islanding import IslandingDecision
    from controlled_islanding.evaluation.coherency_rules import Detection

HELP = 'compare DTW islanding with the correlation and community baselines and the exact MILP optimum'
DESCRIPTION = """\
Run every islanding method on every scenario bag and print one table per bag, one row per method,
in the shape of the paper's Tables IV and VIII: lines cut, islands formed, load/generation imbalance
(sum over islands of |generation - load|, MW), load to shed (MW), power flow disrupted (eq. 9, MW),
gap to the exact optimum (%) and compute time (ms).

Methods (coherent groups -> islands):
  dtw + spectral           the paper: DTW coherency on PMU-estimated rotor angles, constrained spectral clustering,
                           then our refinement (single boundary buses moved while eq. 9 drops)
  dtw + spectral, unrefined (the paper alone)   the same groups, spectral clustering without the refinement
  correlation + spectral   baseline [24]: correlation coefficients split on their average, same spectral clustering
  community detection      baseline [2]: modularity communities of the network; groups fall out of the islands
  dtw + MILP optimum       exact minimum of eq. 9 under the DTW groups, connected islands (HiGHS)
The gap of a row is its disruption against the exact optimum under that row's own groups, so it measures
how far the bus partitioning is from optimal, not how good the groups are. A MILP that stops at its time
limit says so in the notes with its optimality gap.

Coherency uses the PMU frames of the window (--window-s) that ends at the bag's first islanding request,
as the coherency node does, and chooses k with --k-rule (the node's k_rule); the grid is the bag's network
snapshot with the branches tripped before the request taken out. Figures (rotor angles by DTW group, DTW
distance heatmap, network by island for each method, load-shedding bars) go to --out/<case>/.

Detection lead: for every unstable bag (truth k > 1; truth and first pole slip from the bags/index.yaml beside
the bag), DTW coherency with --k-rule is run on windows ending every --lead-step-s from the first full window to
the end of the bag; the earliest request time whose groups are the final (true) groups is reported against the
first pole slip: lead = slip - found, >= 0 means found before the slip.

--closed-loop adds a column: each row's cut opened in ANDES on the scenario the bag was simulated from
(bags/index.yaml names it), breaker_operating_s (0.05 s) after the request, with the row's load to shed and
generation rejection 0.2 s later, judged per island as the testbed judges it (sim/closed_loop.py: machines
within pi rad, frequency within 0.9633..1.03 pu of nominal, voltage 0.8..1.2 pu, no machine tripped); it shows
islands survived / formed, and the first reason an island was lost. Every row's cut opens at the same time (its
compute time is in its own column; the testbed charges the graph's latency), rows with the same cut share one
run, and a row that does not split gets the no-action run. Not for the paper's MATPOWER cases (no dynamic data).
It is off by default because each distinct cut is a time-domain run: a minute or two for IEEE 39, more for the
large cases.

--observability FILE.md instead drops PMUs (the largest machines kept first, and seeded random placements) at
100/75/50/25 % coverage and scores each placement's decision against the truth and the MILP (docs/observability.md).

--k-rules FILE.md instead compares every k rule (core/k_rules.py) on the bags and on --andes scenarios
(simulated here, the simulator's own rotor angles), and writes the table (docs/coherency_rules.md).

Examples:
  controlled-islanding evaluate bags/ieee39_g6g7_unstable
  controlled-islanding evaluate --paper-cases                  the paper's two IEEE 39 cases, its own groups
  controlled-islanding evaluate --paper-cases bags/* --json > results/evaluate.json
  controlled-islanding evaluate bags/*/ --k-rules docs/coherency_rules.md
"""

_DEFAULT_OUT = Path('results/evaluate')

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


class EvaluateError(ValueError):
    """A case that cannot be evaluated (no usable rotor angles, groups that do not fit the grid)."""


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


def add_arguments(parser) -> None:
    """Add the evaluate options."""
    parser.add_argument('bags', nargs='*', metavar='BAG', help='scenario bag directories (from simulate)')
    parser.add_argument('--paper-cases', action='store_true',
                        help="also evaluate the paper's two IEEE 39 cases (MATPOWER case39) with its published groups")
    parser.add_argument('--json', action='store_true', help='print one JSON document instead of the tables')
    parser.add_argument('--out', type=Path, default=_DEFAULT_OUT,
                        help=f'folder for the figures, one sub-folder per case (default: {_DEFAULT_OUT})')
    node = _coherency_node_parameters()
    parser.add_argument('--window-s', type=float, default=float(node.get('window_s', 3.0)),
                        help='rotor-angle window before the islanding request, s (default: %(default)s, '
                             'from config/coherency.yaml like the node)')
    parser.add_argument('--max-groups', type=int, default=int(node.get('max_groups', 4)),
                        help='most coherent groups considered (default: %(default)s)')
    parser.add_argument('--dtw-band-samples', type=int, default=int(node.get('dtw_band_samples', 0)),
                        help='Sakoe-Chiba half-width of the DTW path, samples, 0 = none (default: %(default)s)')
    from controlled_islanding.core.k_rules import DEFAULT_RULE, RULES

    parser.add_argument('--k-rule', choices=sorted(RULES), default=str(node.get('k_rule', DEFAULT_RULE)),
                        help='how DTW coherency chooses k (default: %(default)s, from config/coherency.yaml)')
    parser.add_argument('--lead-step-s', type=float, default=0.05,
                        help='spacing of the request times tried for the detection lead, s (default: %(default)s)')
    parser.add_argument('--k-rules', type=Path, metavar='FILE.md',
                        help='compare every k rule on the bags (and --andes scenarios) and write this page instead')
    parser.add_argument('--observability', type=Path, metavar='FILE.md',
                        help='instead, sweep PMU coverage (100/75/50/25 %%: the largest machines first, and '
                             '--draws seeded random placements) on the bags and write the table '
                             '(docs/observability.md)')
    parser.add_argument('--draws', type=int, default=5, help='random placements per coverage (--observability)')
    parser.add_argument('--seed', type=int, default=0, help='seed of the random placements (--observability)')
    parser.add_argument('--andes', action='append', type=Path, metavar='SCENARIO.yaml', default=[],
                        help='with --k-rules: also simulate this scenario in ANDES and compare on its rotor angles')
    parser.add_argument('--time-limit-s', type=float, default=60.0,
                        help='MILP time limit per solve, s (default: 60)')
    parser.add_argument('--closed-loop', action='store_true',
                        help="also run each row's cut in ANDES on the bag's scenario and judge every island "
                             '(sim/closed_loop.py, as the testbed does): the closed-loop column; a minute or more of '
                             'simulation per distinct cut')
    parser.add_argument('--report', type=Path, metavar='FILE.md',
                        help='also write a Markdown page with every table (for docs/evaluation.md)')
    parser.add_argument('--report-figures', action='append', metavar='CASE', default=None,
                        help='case whose figures the report shows (repeatable; default: the first case)')


def _coherency_node_parameters() -> dict[str, Any]:
    """Return the coherency node's parameters from config/coherency.yaml, so evaluate groups as the node does."""
    from controlled_islanding.locations import config_dir

    path = config_dir() / 'coherency.yaml'
    if not path.is_file():
        return {}
    import yaml

    return dict(((yaml.safe_load(path.read_text()) or {}).get('/**/coherency') or {}).get('ros__parameters') or {})


def run(args) -> int:
    """Evaluate every case; print tables or JSON; write figures."""
    if not args.bags and not args.paper_cases and not args.andes:
        raise CliError('give at least one BAG directory, or --paper-cases')
    if args.lead_step_s <= 0:
        raise CliError(f'--lead-step-s must be positive, got {args.lead_step_s}')
    if args.window_s <= 0 or args.time_limit_s <= 0 or args.max_groups < 2 or args.dtw_band_samples < 0:
        raise CliError(f'--window-s ({args.window_s}) and --time-limit-s ({args.time_limit_s}) must be positive '
                       f'and --max-groups ({args.max_groups}) at least 2, --dtw-band-samples '
                       f'({args.dtw_band_samples}) not negative')
    from controlled_islanding.wire.bagdata import BagDataError, load_bag

    bags = []
    for path in args.bags:
        try:
            bags.append(load_bag(path))
        except BagDataError as exc:
            raise CliError(str(exc)) from exc
    if args.k_rules:
        return _compare_rules(args, bags)
    if args.observability:
        return _sweep_observability(args, bags)
    if args.andes:
        raise CliError('--andes is for --k-rules')
    cases: list[CaseReport] = []
    if args.paper_cases:
        for name in PAPER_CASES:
            _progress(f'{name}: running every method')
            cases.append(evaluate_paper_case(name, time_limit_s=args.time_limit_s))
    for bag in bags:
        _progress(f'{bag.path.name}: running every method')
        try:
            cases.append(evaluate_bag(bag, window_s=args.window_s, max_groups=args.max_groups,
                                      dtw_band=args.dtw_band_samples or None, time_limit_s=args.time_limit_s,
                                      k_rule=args.k_rule, lead_step_s=args.lead_step_s))
        except EvaluateError as exc:
            raise CliError(f'{bag.path}: {exc}') from exc
        if args.closed_loop:
            entry = _manifest_entry(bag) or {}
            if not entry.get('scenario'):
                raise CliError(f'{bag.path}: --closed-loop needs the scenario the bag came from, and the '
                               f'bags/index.yaml beside it names none')
            closed_loop_outcomes(cases[-1], bag.path.parent / entry['scenario'])
    for case in cases:
        _progress(f'{case.name}: figures')
        case.figures.update(write_figures(case, args.out / case.name, bag=next(
            (b for b in bags if b.path.name == case.name), None), window_s=args.window_s,
            dtw_band=args.dtw_band_samples or None))
    if args.json:
        print(json.dumps([case_to_json(c) for c in cases], indent=2))
    else:
        for case in cases:
            print(format_case(case))
    print(f'figures: {args.out}', file=sys.stderr)
    if args.report:
        shown = set(args.report_figures or [cases[0].name])
        unknown = sorted(shown - {c.name for c in cases})
        if unknown:
            raise CliError(f'--report-figures names cases that were not evaluated: {unknown}')
        command = ' '.join(['controlled-islanding evaluate', *(['--paper-cases'] if args.paper_cases else []),
                            *(['--closed-loop'] if args.closed_loop else []), *args.bags, '--report', str(args.report),
                            *(f'--report-figures {c}' for c in args.report_figures or [])])
        write_report(cases, args.report, figures_for=shown, command=command)
        print(f'report: {args.report}', file=sys.stderr)
    return 0


def _compare_rules(args, bags) -> int:
    """Compare every k rule on the bags and the --andes scenarios; print the tables and write the page."""
    from controlled_islanding.evaluation import coherency_rules as study

    scenarios = []
    for bag in bags:
        scenarios.append(study.scenario_from_bag(bag, _manifest_entry(bag)))
    if args.andes:
        from controlled_islanding.sim.andes_sim import SimulationError, simulate
        from controlled_islanding.sim.scenario import ScenarioError, load_scenario

        for path in args.andes:
            _progress(f'{path}: simulating in ANDES')
            try:
                scenario = load_scenario(path)
                sim = simulate(scenario, progress=False)
            except (ScenarioError, SimulationError) as exc:
                raise CliError(f'{path}: {exc}') from exc
            scenarios.append(study.scenario_from_simulation(scenario.name, sim, scenario.request_s))
    results = study.compare(scenarios, window_s=args.window_s, max_groups=args.max_groups,
                            dtw_band=args.dtw_band_samples or None, step_s=args.lead_step_s, progress=_progress)
    print(study.format_console(results))
    command = ' '.join(['controlled-islanding evaluate', *args.bags, *(f'--andes {p}' for p in args.andes),
                        '--k-rules', str(args.k_rules)])
    study.write_report(results, args.k_rules, chosen=args.k_rule, command=command, window_s=args.window_s,
                       step_s=args.lead_step_s)
    print(f'report: {args.k_rules}', file=sys.stderr)
    return 0


def _sweep_observability(args, bags) -> int:
    """Sweep PMU coverage on every bag; print the table and write the page."""
    from controlled_islanding.evaluation import coherency_rules as study
    from controlled_islanding.evaluation import observability_sweep as obs

    if not bags:
        raise CliError('--observability needs at least one BAG')
    rows = []
    for bag in bags:
        scenario = study.scenario_from_bag(bag, _manifest_entry(bag))
        try:
            rows += obs.sweep(scenario, bag.grid_at(scenario.request_s + 1e-9), draws=args.draws, seed=args.seed,
                              window_s=args.window_s, max_groups=args.max_groups, k_rule=args.k_rule,
                              dtw_band=args.dtw_band_samples or None, time_limit_s=args.time_limit_s,
                              progress=_progress)
        except obs.SweepError as exc:
            raise CliError(str(exc)) from exc
    print('\n'.join(obs.table(rows)))
    command = ' '.join(['controlled-islanding evaluate', *args.bags, '--observability', str(args.observability),
                        f'--draws {args.draws} --seed {args.seed}'])
    obs.write_report(rows, args.observability, command=command, k_rule=args.k_rule, window_s=args.window_s)
    print(f'report: {args.observability}', file=sys.stderr)
    return 0


def _manifest_entry(bag) -> dict | None:
    """Return the bag's entry in the bags/index.yaml beside it (None if there is none)."""
    from controlled_islanding.sim.manifest import entry_for_bag

    return entry_for_bag(bag.path)


def _progress(text: str) -> None:
    print(f'evaluate: {text}', file=sys.stderr, flush=True)


def closed_loop_outcomes(case: CaseReport, scenario_path: Path, config: Any = None) -> None:
    """Run every row's cut of a bag's case in ANDES and judge its islands; fill row.closed_loop and case.no_action.

    The cut opens config.breaker_operating_s after the scenario's request for every row alike; rows with the same
    cut share one run, and a row that does not split is the no-action run (see DESCRIPTION, --closed-loop).

    Args:
        case: A bag's case, its rows decided.
        scenario_path: The scenario YAML the bag was simulated from.
        config: A sim.closed_loop.LoopConfig (default: its defaults, the testbed's).

    Raises:
        CliError: The scenario cannot be read or simulated.

    """
    from controlled_islanding.sim.closed_loop import ClosedLoopError, LoopConfig, run_offline
    from controlled_islanding.sim.scenario import ScenarioError, load_scenario

    config = config or LoopConfig()
    try:
        scenario = load_scenario(scenario_path)
    except ScenarioError as exc:
        raise CliError(str(exc)) from exc
    opened_s = scenario.request_s + config.breaker_operating_s
    runs: dict[tuple[str, ...], dict[str, Any]] = {}

    def outcome(decision: IslandingDecision | None) -> dict[str, Any]:
        cut = tuple(sorted(decision.cut_branch_ids)) if decision is not None and decision.split else ()
        if cut not in runs:
            _progress(f'{case.name}: closed loop, cut {", ".join(cut) or "none"} (ANDES)')
            try:
                if cut:
                    run = run_offline(scenario, 'cut', cut_branch_ids=cut, bus_island=decision.bus_island,
                                      island_shed_mw=list(decision.island_shed_mw), opened_s=opened_s, config=config)
                else:
                    run = run_offline(scenario, 'no action', judged_from_s=opened_s, config=config)
            except (ClosedLoopError, ScenarioError, RuntimeError) as exc:
                raise CliError(f'{scenario_path}: closed loop: {exc}') from exc
            summary = run.summary()
            runs[cut] = {k: summary[k] for k in ('opened_s', 'judged_from_s', 'all_survived', 'load_lost_mw',
                                                 'shed_mw', 'rejected_mw', 'f_nadir_hz', 'f_peak_hz', 'v_min_pu')}
            runs[cut]['islands'] = [{k: i[k] for k in ('island', 'generators', 'survived', 'why_not',
                                                       'max_pair_swing_rad', 'f_nadir_hz', 'f_peak_hz', 'v_min_pu',
                                                       'v_max_pu', 'rejected')} for i in summary['islands']]
        return runs[cut]

    case.no_action = outcome(None)
    for row in case.rows:
        if row.decision is not None:
            row.closed_loop = outcome(row.decision)


def closed_loop_text(result: dict[str, Any] | None) -> str:
    """Return a closed-loop outcome as a table cell: islands survived / formed, and the first reason one was lost."""
    if result is None:
        return '-'
    islands = result['islands']
    ok = sum(1 for i in islands if i['survived'])
    why = next((f'island {i["island"]}: {i["why_not"][0]}' for i in islands if i['why_not']), '')
    return f'{ok}/{len(islands)}' + (f' ({why})' if why else '')


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


def request_time_s(bag) -> float:
    """Return the time the bag's first islanding request is stamped with (the bag's end if none), s after t0."""
    return float(bag.request_t_s[0]) if len(bag.request_t_s) else float(bag.frame_t_s[-1])


def generator_series(bag, start_s: float, end_s: float) -> tuple[np.ndarray, list[str], np.ndarray]:
    """PMU-estimated rotor angles of every generator between two times.

    Args:
        bag: A BagData.
        start_s: First time tag, s after t0.
        end_s: Last time tag, s after t0.

    Returns:
        (time tags s, generator names, angles rad shaped (n_generators, n_samples), NaN where lost).

    Raises:
        EvaluateError: A generator without a PMU at its bus, or fewer than 2 valid samples for one.

    """
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad
    from controlled_islanding.wire.bagdata import BagDataError

    grid = bag.grid
    try:
        # A machine's own channel where machines share a bus: the bus's one channel would give them one series.
        cols = [bag.pmu_column(g.name, g.bus) for g in grid.generators]
    except BagDataError as exc:
        raise EvaluateError(f'{exc}; coherency needs every generator') from exc
    rows = (bag.frame_t_s >= start_s - 1e-9) & (bag.frame_t_s <= end_s + 1e-9)
    angles = np.asarray(estimate_rotor_angle_rad(
        bag.v_mag_pu[np.ix_(rows, cols)], bag.v_angle_rad[np.ix_(rows, cols)], bag.i_mag_pu[np.ix_(rows, cols)],
        bag.i_angle_rad[np.ix_(rows, cols)], np.array([g.xq_pu for g in grid.generators]),
        np.array([g.ra_pu for g in grid.generators])), dtype=float).T
    for g, angle in zip(grid.generators, angles, strict=True):
        if np.isfinite(angle).sum() < 2:
            raise EvaluateError(f'generator {g.name} (PMU at bus {g.bus}) has fewer than 2 valid samples between '
                                f'{start_s:.3f} s and {end_s:.3f} s')
    return bag.frame_t_s[rows], [g.name for g in grid.generators], angles


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
    scenario = study.scenario_from_bag(bag, _manifest_entry(bag))
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


def _group_text(groups: Mapping[str, int] | None) -> str:
    if groups is None:
        return '-'
    out: dict[int, list[str]] = {}
    for name, k in groups.items():
        out.setdefault(k, []).append(name)
    return ' '.join('(' + ', '.join(out[k]) + ')' for k in sorted(out))


def _same_partition(a: Mapping[str, int], b: Mapping[str, int]) -> bool:
    def blocks(groups: Mapping[str, int]) -> set[frozenset[str]]:
        return {frozenset(n for n, k in groups.items() if k == g) for g in set(groups.values())}

    return blocks(a) == blocks(b)


def _num(value: float | None, fmt: str = '.2f') -> str:
    if value is None:
        return '-'
    if math.isinf(value):
        return 'inf'
    return format(value, fmt)


TABLE_COLUMNS = ('method', 'lines cut', 'islands formed', 'load/generation imbalance (MW)', 'load to shed (MW)',
                 'power flow disrupted (MW)', 'gap to MILP optimum (%)', 'compute time (ms)')


CLOSED_LOOP_COLUMN = 'closed loop: islands survived'


def columns(case: CaseReport) -> tuple[str, ...]:
    """Return the columns of a case's table: TABLE_COLUMNS, and the closed-loop column when it was run."""
    return TABLE_COLUMNS + ((CLOSED_LOOP_COLUMN,) if case.no_action is not None else ())


def table_rows(case: CaseReport) -> list[list[str]]:
    """Return the table cells of a case, one list per method, in columns(case) order."""
    out = []
    extra = case.no_action is not None
    for row in case.rows:
        d = row.decision
        if d is None:
            out.append([row.method] + ['-'] * 6 + [_num(1e3 * row.compute_time_s, '.1f') if row.groups else '-']
                       + (['-'] if extra else []))
            continue
        out.append([row.method, str(len(d.cut_branches)), str(d.n_islands),
                    _num(float(np.abs(d.island_imbalance_mw).sum())), _num(float(sum(d.island_shed_mw))),
                    _num(d.disrupted_mw), _num(row.gap_pct), _num(1e3 * row.compute_time_s, '.1f')]
                   + ([closed_loop_text(row.closed_loop)] if extra else []))
    return out


def format_case(case: CaseReport) -> str:
    """Render a case as a Markdown table (readable in a terminal too), then its groups, cut lines and notes."""
    cols = columns(case)
    cells = [list(cols)] + table_rows(case)
    widths = [max(len(r[i]) for r in cells) for i in range(len(cols))]
    lines = [f'### {case.name}', '', f'{case.source}', '']
    if case.truth_groups is not None:
        lines += [f'True coherent groups (final grouping): {_group_text(case.truth_groups)}', '']
    if case.detection is not None:
        from controlled_islanding.evaluation.coherency_rules import detection_text

        truth_k = len(set((case.truth_groups or {}).values()))
        slip = 'never' if case.first_pole_slip_s is None else f'{case.first_pole_slip_s:.2f} s'
        lines += [f'Detection lead (dtw, k rule {case.k_rule}): first pole slip {slip}; '
                  f'{detection_text(truth_k, case.detection)}', '']
    for n, r in enumerate(cells):
        lines.append('| ' + ' | '.join(c.ljust(w) if i == 0 else c.rjust(w)
                                        for i, (c, w) in enumerate(zip(r, widths, strict=True))) + ' |')
        if n == 0:
            lines.append('|' + '|'.join('-' * (w + 1) + (':' if i else '-') for i, w in enumerate(widths)) + '|')
    lines.append('')
    if case.no_action is not None:
        lines += [f'Closed loop (--closed-loop): no action {closed_loop_text(case.no_action)}; each cut opened at '
                  f'{case.no_action["judged_from_s"]:.3f} s (request + breaker time).', '']
    for row in case.rows:
        cut = ', '.join(row.decision.cut_branch_ids) if row.decision is not None else '-'
        detail = f'- {row.method}: groups {_group_text(row.groups)}'
        if case.truth_groups is not None and row.groups is not None:
            detail += ' (= truth)' if _same_partition(row.groups, case.truth_groups) else ' (differ from truth)'
        detail += f'; cut {cut or "nothing"}'
        lines.append(detail + (f'; note: {row.note}' if row.note else ''))
    return '\n'.join(lines) + '\n'


def case_to_json(case: CaseReport) -> dict[str, Any]:
    """Return a case as plain JSON data."""
    rows = []
    for row in case.rows:
        d = row.decision
        rows.append({
            'method': row.method, 'groups': row.groups, 'note': row.note,
            'compute_time_s': row.compute_time_s, 'optimum_mw': row.optimum_mw, 'closed_loop': row.closed_loop,
            'gap_pct': None if row.gap_pct is None or math.isinf(row.gap_pct) else row.gap_pct,
            'decision': None if d is None else {
                'split': d.split, 'n_islands': d.n_islands, 'cut_branch_ids': list(d.cut_branch_ids),
                'lines_cut': len(d.cut_branches),
                'imbalance_mw': float(np.abs(d.island_imbalance_mw).sum()), 'shed_mw': float(sum(d.island_shed_mw)),
                'disrupted_mw': d.disrupted_mw, 'island_generation_mw': list(d.island_generation_mw),
                'island_load_mw': list(d.island_load_mw), 'island_shed_mw': list(d.island_shed_mw),
                'bus_island': {str(b): i for b, i in sorted(d.bus_island.items())}},
        })
    det = case.detection
    return {'case': case.name, 'source': case.source, 'truth_groups': case.truth_groups, 'rows': rows,
            'figures': {k: str(v) for k, v in case.figures.items()}, 'k_rule': case.k_rule,
            'first_pole_slip_s': case.first_pole_slip_s, 'no_action': case.no_action,
            'detection': None if det is None else {'found_s': det.found_s, 'kept_from_s': det.kept_from_s,
                                                   'lead_s': det.lead_s}}


def _slug(text: str) -> str:
    return re.sub(r'[^0-9A-Za-z]+', '_', text).strip('_')


def write_figures(case: CaseReport, folder: Path, *, bag=None, window_s: float = 3.0,
                  dtw_band: int | None = None) -> dict[str, Path]:
    """Write the case's figures.

    Args:
        case: The evaluated case.
        folder: Output folder (created).
        bag: The case's BagData, for the rotor-angle and distance figures (None for paper cases).
        window_s: Window used for coherency, s (marked on the rotor-angle figure).
        dtw_band: Sakoe-Chiba half-width used for the DTW distances, samples (None = none).

    Returns:
        Figure name -> path.

    """
    from controlled_islanding.evaluation import plots

    out: dict[str, Path] = {}
    dtw = next((r for r in case.rows if r.method.startswith('dtw') and r.groups is not None), None)
    if bag is not None:
        from controlled_islanding.core.coherency import DTWCoherency

        end_s = request_time_s(bag)
        t_s, names, angles = generator_series(bag, 0.0, float(bag.frame_t_s[-1]))
        first = np.array([row[np.isfinite(row)][0] for row in angles])
        groups = [dtw.groups[n] for n in names] if dtw else None
        events = {f'trip {e.branch_id}': e.t_s for e in bag.branch_events if not e.in_service}
        out['rotor_angles'] = plots.plot_rotor_angles(
            t_s, angles - first[:, None], names, groups, folder / 'rotor_angles.png',
            title=f'{case.name}: PMU-estimated rotor angles, coloured by DTW group',
            marks_s=events | {'coherency window start': end_s - window_s, 'islanding request': end_s})
        _, _, window = generator_series(bag, end_s - window_s, end_s)
        model = DTWCoherency(window=dtw_band).fit(list(window))
        out['dtw_distance'] = plots.plot_distance_matrix(
            model.distance_matrix_, names, groups, folder / 'dtw_distance.png',
            title=f'{case.name}: DTW distances over the {window_s:g} s window')
    for row in case.rows:
        if row.decision is None:
            continue
        slug = _slug(row.method)
        out[f'network_{slug}'] = plots.plot_network(
            case.grid, row.decision.bus_island, row.decision.cut_branch_ids, folder / f'network_{slug}.png',
            title=f'{case.name}, {row.method}: {row.decision.disrupted_mw:.1f} MW disrupted')
    decided = {r.method: r.decision for r in case.rows if r.decision is not None}
    if decided:
        out['shedding'] = plots.plot_shedding(decided, folder / 'shedding.png',
                                              title=f'{case.name}: generation, load and load to shed per island')
    return out


def write_report(cases: Sequence[CaseReport], path: Path, figures_for: set[str] | None = None,
                 command: str = 'controlled-islanding evaluate ... --report') -> list[Path]:
    """Write a Markdown page with every table and the rotor-angle, DTW network and shedding figures of some cases.

    The figures it shows are copied into a folder named after the page (docs/evaluation.md ->
    docs/evaluation/), so the page stands alone however scratch the --out folder is.

    Args:
        cases: Evaluated cases with their figures.
        path: The .md file.
        figures_for: Names of the cases whose figures are shown (None: every case).
        command: The command line that regenerates the page, quoted at its top.

    Returns:
        The page and the figures copied beside it.

    """
    folder = path.parent / path.stem
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    lines = ['# Evaluation', '',
             f'Generated by `{command}`; do not edit by hand. `controlled-islanding evaluate --help` explains the '
             "methods and the columns. Each row's gap is its disruption against the exact minimum of eq. 9 "
             "under that row's own coherent groups (the MILP), so it grades the bus partitioning, not the groups.",
             '']
    for case in cases:
        lines.append(format_case(case))
        if figures_for is not None and case.name not in figures_for:
            continue
        for key in ('rotor_angles', 'network_dtw_paper_groups_spectral', 'network_dtw_spectral', 'shedding'):
            if key in case.figures:
                target = folder / f'{case.name}_{key}.png'
                atomic.write_bytes(target, case.figures[key].read_bytes())
                written.append(target)
                lines += [f'![{case.name}: {key.replace("_", " ")}]({path.stem}/{target.name})', '']
    atomic.write_bytes(path, '\n'.join(lines).encode())
    return [path, *written]
