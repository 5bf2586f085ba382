"""`controlled-islanding testbed SCENARIO.yaml`: the scenario closed-loop through the node graph and grid_sim."""

from __future__ import annotations

import argparse
import json
import sys
from datetime import UTC, datetime
from pathlib import Path

from controlled_islanding.commands import CliError, progress_bar, testbed_chaos
from controlled_islanding.commands.replay import add_wan_arguments, wan_link
from controlled_islanding.evaluation.testbed_report import monitor_asked_nothing, publish, render
from controlled_islanding.graph import GraphError
from controlled_islanding.graph.processes import sigterm_as_interrupt
from controlled_islanding.graph.results import running
from controlled_islanding.graph.testbed import TestbedSettings, run_all

HELP = 'run a scenario closed-loop (ANDES as the grid, the four nodes deciding) and compare with no action and MILP'
DESCRIPTION = """\
Start pmu_ingestion, coherency, partitioning and breaker_command (armed with a signed operator request, as
replay does) and grid_sim, which runs the scenario's ANDES simulation as the grid: it publishes the snapshot,
PMU frames, trips and the scenario's islanding request, executes the breaker commands in the running
simulation (breaker operating time, then the decision's load sheds and generator trips as breaker_command
commanded them; grid_sim decides none of its own), keeps
simulating, and judges every island (docs/testbed.md and controlled_islanding/sim/closed_loop.py give the
rules and their sources: machines trip by the NERC PRC-024 ride-through curves, with their durations; the
grid's own under-frequency load shedding acts in stages in the style of PRC-006; an island survives when at
the end of the run its machines are in step, none tripped, and its frequency and voltages are back in their
continuous bands). The breakers of one decision open together, in one simulation step. A simulator failure
is its own outcome ("simulation failed at t s: reason"), never load lost; the run is first repeated offline
at a smaller step. The scenario is checked against its case, as simulate checks it, before any node starts.

Then the same scenario runs twice more in-process, with no graph: with no action, and with the exact MILP cut
(core/milp.py, the same generator groups as the decision) opened at the same time as the graph's cut, with the
remedial actions of the same rule (core/remedial.py). One table compares the three: load served at the end (MW
and % of the pre-fault load, in the islands that survived, net of every shed), islands that survived, load lost,
frequency nadir and peak, lowest voltage, request-to-opening time. --json prints per scenario the coherent groups,
the decision, the commanded actions and every run (load_served_mw, load_served_pct, all_survived,
simulation_failed, islands with their reasons in full); progress goes to stderr.
With --oracle, the best found (evaluation/oracle.py) comes last, searched offline with no graph and the same
remedial-action rules: every request time from the clearing of the first fault to the no-action run's first
pole slip, at most --oracle-step-s apart, each with every candidate cut: the exact MILP cut of the true grouping
(from the simulator's own rotor angles) and of its neighbours (two groups merged, one machine moved to the
nearest other group, one machine alone), the spectral cut of the true grouping, and the graph's own cut. Each
candidate is one ANDES run of the whole scenario: identical ones run once, and one whose planned shed leaves it
unable to beat the best so far is not run. It reports the most load served, when and with which cut (row
'oracle', and under `oracle` in --json: load_served_mw, request_s, cut_branch_ids, the search), and the gap of
the closed loop to it. A candidate whose ANDES run fails is listed as failed, not repeated at a smaller step
(--oracle-remedies repeats it, as the closed loop's runs are, at several times the cost). Progress goes to stderr.
A figure per scenario shows the rotor angles coloured by the decision's islands and the bus voltages, for no
action, the closed loop, the MILP cut and the best found (as the paper's Figs. 6 and 11).

With --namespace /area1 the four nodes and grid_sim run in /area1 (/area1/pmu/frames, ..., /area1/clock), as
with `replay --namespace`; each result lists the graph's topic names.

Lockstep (default): the simulation does not step past the request until the decision and its commands came
(bounded waits); the graph's wall-clock latency is then charged to sim time. --rate R paces the simulation at R
times real time instead (ANDES may be slower than that on a busy machine).

Hosts: with --hosts pdc,control,substation the four nodes and grid_sim run on emulated hosts joined by an
emulated WAN, as with `replay --hosts` (grid_sim on the PDC's host, as the PMUs feed it); needs root.

{chaos}
Examples:
  controlled-islanding testbed bags/ieee14_g1_unstable.yaml
  controlled-islanding testbed bags/ieee14_g1_unstable.yaml --hosts pdc,control,substation --wan-delay-ms 10
  controlled-islanding testbed bags/ieee39_g6g7_unstable.yaml --json
  controlled-islanding testbed bags/kundur_bus9_unstable.yaml --oracle   the best found too: 84 candidates,
                                      10 min on a loaded 2-core machine (IEEE 39 G6-G7: 72, 76 min)
  controlled-islanding testbed --all-unstable --markdown docs/testbed.md --figures-dir docs/testbed
                                      every manifest scenario whose expected decision splits (long: minutes each)
"""
DESCRIPTION = DESCRIPTION.replace('{chaos}', testbed_chaos.HELP_TEXT)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the testbed options."""
    parser.add_argument('scenarios', type=Path, nargs='*', help='scenario YAML files (bags/*.yaml)')
    parser.add_argument('--all-unstable', action='store_true',
                        help='every scenario of bags/index.yaml whose expected decision splits')
    parser.add_argument('--json', action='store_true', help='print the results as JSON on stdout and nothing else')
    parser.add_argument('--markdown', type=Path, default=None, help='also write the table as a Markdown page')
    parser.add_argument('--figures-dir', type=Path, default=None,
                        help='write the figures here too (default: only in the results folder)')
    parser.add_argument('--figure-scenarios', default='',
                        help='comma-separated scenario names whose figures go to --figures-dir (default: all)')
    parser.add_argument('--results', type=Path, default=None,
                        help='results folder to create (default ./results/testbed-<UTC time>); one that holds a '
                             'failed or interrupted run is replaced')
    parser.add_argument('--force', action='store_true', help='replace the --results folder even if it holds a '
                        'finished run')
    parser.add_argument('--rate', type=float, default=0.0, help='0 = lockstep (default); R > 0 = R x real time')
    parser.add_argument('--breaker-operating-s', type=float, default=0.05,
                        help='breaker command -> branch open, s (default 0.05, 3 cycles at 60 Hz)')
    parser.add_argument('--shed-delay-s', type=float, default=0.2, help='branch open -> load shed, s (default 0.2)')
    parser.add_argument('--run-after-s', type=float, default=3.0,
                        help='simulate at least this long after the request, s (default 3)')
    parser.add_argument('--render', type=Path, default=None, metavar='RESULTS',
                        help='run nothing: rebuild the table, --markdown and --figures-dir from a results folder of an '
                             'earlier (or still running) testbed run; scenarios not finished yet are listed as missing')
    parser.add_argument('--no-baselines', action='store_true', help='skip the no-action and MILP runs')
    parser.add_argument('--oracle', action='store_true',
                        help='also search offline for the best found: the most load served over request times and '
                             'cuts (long: minutes to hours per scenario; see below)')
    parser.add_argument('--oracle-step-s', type=float, default=0.05,
                        help="the oracle's largest spacing of request times, s (default 0.05; a coarser grid is "
                             'allowed on the largest systems, and the report states the step used)')
    parser.add_argument('--oracle-remedies', action='store_true',
                        help="repeat an oracle candidate whose ANDES run failed at 1/4, then 1/16, of the step, as the "
                             "closed loop's runs are (off by default: it multiplies the search's time, 3x on IEEE 39; "
                             'the failures are listed either way)')
    parser.add_argument('--trigger', choices=('scenario', 'out-of-step', 'monitor'), default='scenario',
                        help="where the islanding request comes from: the scenario's time (default, the paper's "
                             "operator), grid_sim's out-of-step trigger on the measured rotor angles "
                             '(sim/closed_loop.out_of_step), or the stability monitor alone '
                             '(nodes/stability_monitor.py: a request only for a swing predicted to separate, with its '
                             'groups; none for one '
                             "predicted to return, the run then judged from the scenario's request time as no action)")
    parser.add_argument('--timeout', type=float, default=900.0, help='give up on one closed-loop run after this, s')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help='run the graph and grid_sim in this ROS namespace, e.g. /area1 (default: the root one)')
    parser.add_argument('--estimator', choices=('steady_state', 'dse'), default=None,
                        help="pmu_ingestion's rotor angle estimator, as replay --estimator (default: "
                             'config/pmu_ingestion.yaml)')
    add_wan_arguments(parser)
    testbed_chaos.add_arguments(parser)


def _unstable() -> list[Path]:
    from controlled_islanding.sim.manifest import ManifestError, unstable_scenarios

    try:
        return unstable_scenarios()
    except ManifestError as exc:
        raise CliError(str(exc)) from exc


def _publish(results: list[dict], args: argparse.Namespace, missing: list[str]) -> None:
    publish(results, args, missing, page=args.markdown, figures_dir=args.figures_dir,
            figure_scenarios=args.figure_scenarios, cmd='controlled-islanding testbed ' + ' '.join(sys.argv[2:]))


def _settings(args: argparse.Namespace, paths: list[Path], progress: bool) -> TestbedSettings:
    """Return the settings of the options, checked with the scenarios they run."""
    if not paths and args.render is None:
        raise CliError('name at least one scenario YAML, or --all-unstable')
    for p in paths:
        if not p.exists():
            raise CliError(f'scenario {p} does not exist')
    if not args.oracle_step_s > 0:
        raise CliError(f'--oracle-step-s {args.oracle_step_s} must be positive')
    if args.rate < 0:
        raise CliError(f'--rate {args.rate} must be 0 (lockstep) or positive')
    link = wan_link(args)
    # Progress on stderr, --json or not; a chaos sweep says a line per run instead.
    return TestbedSettings(rate=args.rate, breaker_operating_s=args.breaker_operating_s,
                           shed_delay_s=args.shed_delay_s, run_after_s=args.run_after_s, trigger=args.trigger,
                           timeout_s=args.timeout, namespace=args.namespace, estimator=args.estimator,
                           no_baselines=args.no_baselines, oracle=args.oracle, oracle_step_s=args.oracle_step_s,
                           oracle_remedies=args.oracle_remedies, quiet=not progress, hosts=args.hosts,
                           **({'link': link} if link else {}))


def run(args: argparse.Namespace) -> int:
    """Run the testbed subcommand."""
    paths = list(args.scenarios) + (_unstable() if args.all_unstable else [])
    if args.chaos is not None:
        return testbed_chaos.run(args, paths, _settings(args, paths, progress=False))
    if args.render is not None:
        done = sorted(args.render.glob('*/result.json'))
        if not done:
            raise CliError(f'{args.render}: no */result.json; is it a testbed results folder?')
        results = [json.loads(p.read_text()) for p in done]
        wanted = [p.stem for p in paths]
        missing = [n for n in wanted if n not in {r['scenario'] for r in results}]
        _publish(results, args, missing)
        print(json.dumps(results, default=str) if args.json else render(results))
        return 0
    settings = _settings(args, paths, progress=True)
    stamp = datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
    results_dir = args.results or Path('results') / f'testbed-{stamp}'

    def after_each(results: list[dict], missing: list[str]) -> None:
        bar.update()
        _publish(results, args, missing)

    # The baselines run with no supervisor open: a SIGTERM there is marked too.
    try:
        with sigterm_as_interrupt(), running(results_dir, args.force) as results_dir, \
                progress_bar(len(paths), 'testbed', 'scenario') as bar:
            results, failures = run_all(paths, results_dir, settings, after_each)
    except GraphError as exc:
        raise CliError(str(exc)) from exc
    if args.json:
        print(json.dumps(results, default=str))
    else:
        print(render(results))
        print(f'results: {results_dir}')
    for failure in failures:
        print(f'testbed: FAILED: {failure}', file=sys.stderr)
    failed = bool(failures) or any((r['decision'] is None and not monitor_asked_nothing(r)) or r['restarts']
                                   for r in results)
    return 1 if failed else 0
