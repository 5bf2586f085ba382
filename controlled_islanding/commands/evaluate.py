"""`controlled-islanding evaluate`: every islanding method on every bag, tables in the shape of Tables IV/VIII."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from controlled_islanding.commands import CliError
from controlled_islanding.commands.evaluate_attacks import sweep_attacks
from controlled_islanding.commands.evaluate_monitor import judge_monitor
from controlled_islanding.commands.evaluate_predictors import compare_predictors
from controlled_islanding.commands.evaluate_rules import compare_rules, sweep_observability
from controlled_islanding.evaluation.cases import (
    PAPER_CASES,
    EvaluateError,
    closed_loop_outcomes,
    coherency_node_parameters,
    evaluate_bag,
    evaluate_paper_case,
    manifest_entry,
)
from controlled_islanding.evaluation.report import case_to_json, format_case, write_figures, write_report

log = logging.getLogger(__name__)

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
(bags/index.yaml names it), breaker_operating_s (0.05 s) after the request, with the row's remedial actions (load
sheds, generator trips) 0.2 s later, judged per island as the testbed judges it (sim/closed_loop.py: at the
end, machines in step within pi rad, frequency in PRC-024's continuous band (59.5..60.5 Hz at 60 Hz), every bus
in 0.9..1.1 pu, no machine tripped by the PRC-024 ride-through curves or overspeed; the grid's own PRC-006-style
UFLS runs); it shows islands survived / formed, and the first reason an island was lost. Every row's cut opens
at the same time (its compute time is in its own column; the testbed charges the graph's latency), rows with the
same cut share one run, and a row that does not split gets the no-action run. Not for the paper's MATPOWER
cases (no dynamic data). It is off by default because each distinct cut is a time-domain run: a minute or two
for IEEE 39, more for the large cases.

--observability FILE.md instead drops PMUs (the largest machines kept first, and seeded random placements) at
100/75/50/25 % coverage and scores each placement's decision against the truth and the MILP (docs/observability.md).

--predictors FILE.md instead runs the stability predictors (core/stability.py, core/swing_forecast.py) and today's
separation rule frame by frame on the DSE angles of the bags and --andes scenarios: alarm against the first pole
slip, false alarms, groups at the alarm (docs/prediction.md).

--monitor FILE.md instead runs the stability monitor's core (core/final_grouping.py) frame by frame on the DSE
angles of the bags and --andes scenarios, as the node would: every request against the first pole slip, false
requests on runs that stay one group, the groups of the first request against the final grouping; with --testbed
RESULTS (a `testbed --trigger monitor` results folder, repeatable) also the closed loop's load served against no
action and the oracle, from that folder or from a `testbed --oracle` folder of any trigger (docs/monitor.md),
or from an oracle record: the page writes every oracle it judged against beside itself (docs/monitor/oracles.json),
so a searched oracle (hours on IEEE 39) need not be searched again to build the page; with --noise-seeds N also
every scenario simulated once and measured again under seeds 1 to N: how often the PMUs' noise tips the monitor
into a false request, a late one, or other groups (about a minute per seed).

--k-rules FILE.md instead compares every k rule (core/k_rules.py) on the bags and on --andes scenarios
(simulated here, the simulator's own rotor angles), and writes the table (docs/coherency_rules.md).

Examples:
  controlled-islanding evaluate bags/ieee39_g6g7_unstable
  controlled-islanding evaluate --paper-cases                  the paper's two IEEE 39 cases, its own groups
  controlled-islanding evaluate --paper-cases bags/* --json > results/evaluate.json
  controlled-islanding evaluate bags/*/ --k-rules docs/coherency_rules.md
"""

_DEFAULT_OUT = Path('results/evaluate')

def add_arguments(parser) -> None:
    """Add the evaluate options."""
    parser.add_argument('bags', nargs='*', metavar='BAG', help='scenario bag directories (from simulate)')
    parser.add_argument('--paper-cases', action='store_true',
                        help="also evaluate the paper's two IEEE 39 cases (MATPOWER case39) with its published groups")
    parser.add_argument('--json', action='store_true', help='print one JSON document instead of the tables')
    parser.add_argument('--out', type=Path, default=_DEFAULT_OUT,
                        help=f'folder for the figures, one sub-folder per case (default: {_DEFAULT_OUT})')
    node = coherency_node_parameters()
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
    parser.add_argument('--attacks', type=Path, metavar='FILE.md', help='instead, the attack sweep (docs/attacks.md)')
    parser.add_argument('--predictors', type=Path, metavar='FILE.md',
                        help='instead, compare the stability predictors and write this page (docs/prediction.md); a '
                             'scenario that cannot be run (ANDES does not converge) is listed on it, the others are '
                             'still written, and the exit status is 2')
    parser.add_argument('--monitor', type=Path, metavar='FILE.md',
                        help='instead, judge the stability monitor on every scenario and write this page '
                             '(docs/monitor.md); a scenario that cannot be run is listed on it, as with --predictors')
    parser.add_argument('--testbed', action='append', type=Path, metavar='RESULTS', default=[],
                        help='with --monitor: a `testbed --trigger monitor` results folder whose closed loops the page '
                             'shows, or a `testbed --oracle` one whose oracle they are judged against, or an oracle '
                             'record (docs/monitor/oracles.json) (repeatable)')
    parser.add_argument('--noise-seeds', type=int, default=0, metavar='N',
                        help='with --monitor: also simulate each scenario once and measure it again under seeds 1 to '
                             'N (PMU noise and impairments), the monitor run on every draw: how often noise tips '
                             'its verdict (default: 0, none)')
    parser.add_argument('--draws', type=int, default=5, help='random placements per coverage (--observability)')
    parser.add_argument('--seed', type=int, default=0, help='seed of the random placements (--observability)')
    parser.add_argument('--andes', action='append', type=Path, metavar='SCENARIO.yaml', default=[],
                        help='with --k-rules, --predictors or --monitor: also simulate this scenario in ANDES')
    parser.add_argument('--time-limit-s', type=float, default=60.0, help='MILP time limit per solve, s (default: 60)')
    parser.add_argument('--closed-loop', action='store_true',
                        help="also run each row's cut in ANDES on the bag's scenario and judge every island "
                             '(sim/closed_loop.py, as the testbed does): the closed-loop column; a minute or more of '
                             'simulation per distinct cut')
    parser.add_argument('--report', type=Path, metavar='FILE.md',
                        help='also write a Markdown page with every table (for docs/evaluation.md)')
    parser.add_argument('--report-figures', action='append', metavar='CASE', default=None,
                        help='case whose figures the report shows (repeatable; default: the first case)')


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
    if args.predictors:
        return compare_predictors(args, args.bags)
    if args.monitor:
        return judge_monitor(args, args.bags)
    if args.testbed or args.noise_seeds:
        raise CliError('--testbed and --noise-seeds are for --monitor')
    from controlled_islanding.wire.bagdata import BagDataError, load_bag

    bags = []
    for path in args.bags:
        try:
            bags.append(load_bag(path))
        except BagDataError as exc:
            raise CliError(str(exc)) from exc
    if args.k_rules:
        return compare_rules(args, bags)
    if args.observability or args.attacks:
        return sweep_observability(args, bags) if args.observability else sweep_attacks(args, bags)
    if args.andes:
        raise CliError('--andes is for --k-rules, --predictors and --monitor')
    cases = []
    if args.paper_cases:
        for name in PAPER_CASES:
            log.info('%s: running every method', name)
            cases.append(evaluate_paper_case(name, time_limit_s=args.time_limit_s))
    for bag in bags:
        log.info('%s: running every method', bag.path.name)
        try:
            cases.append(evaluate_bag(bag, window_s=args.window_s, max_groups=args.max_groups,
                                      dtw_band=args.dtw_band_samples or None, time_limit_s=args.time_limit_s,
                                      k_rule=args.k_rule, lead_step_s=args.lead_step_s))
        except EvaluateError as exc:
            raise CliError(f'{bag.path}: {exc}') from exc
        if args.closed_loop:
            entry = manifest_entry(bag) or {}
            if not entry.get('scenario'):
                raise CliError(f'{bag.path}: --closed-loop needs the scenario the bag came from, and the '
                               f'bags/index.yaml beside it names none')
            try:
                closed_loop_outcomes(cases[-1], bag.path.parent / entry['scenario'])
            except EvaluateError as exc:
                raise CliError(str(exc)) from exc
    for case in cases:
        log.info('%s: figures', case.name)
        case.figures.update(write_figures(case, args.out / case.name, bag=next(
            (b for b in bags if b.path.name == case.name), None), window_s=args.window_s,
            dtw_band=args.dtw_band_samples or None))
    if args.json:
        print(json.dumps([case_to_json(c) for c in cases], indent=2))
    else:
        for case in cases:
            print(format_case(case))
    log.info('figures: %s', args.out)
    if args.report:
        shown = set(args.report_figures or [cases[0].name])
        unknown = sorted(shown - {c.name for c in cases})
        if unknown:
            raise CliError(f'--report-figures names cases that were not evaluated: {unknown}')
        command = ' '.join(['controlled-islanding evaluate', *(['--paper-cases'] if args.paper_cases else []),
                            *(['--closed-loop'] if args.closed_loop else []), *args.bags, '--report', str(args.report),
                            *(f'--report-figures {c}' for c in args.report_figures or [])])
        write_report(cases, args.report, figures_for=shown, command=command)
        log.info('report: %s', args.report)
    return 0
