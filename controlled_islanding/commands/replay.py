"""`controlled-islanding replay BAG`: run a bag through the node graph, as separate processes over DDS."""

from __future__ import annotations

import argparse
import json
import sys
from datetime import UTC, datetime
from pathlib import Path

from controlled_islanding import atomic
from controlled_islanding.commands import CliError, progress_bar
from controlled_islanding.graph import GraphError, wan
from controlled_islanding.graph.replay import replay, replay_repeatedly
from controlled_islanding.graph.results import running
from controlled_islanding.graph.suite import SuiteRun, junit_xml, render_suite, replay_suite, run_names
from controlled_islanding.graph.summary import graph_failure, refused, render

HELP = 'replay a bag through the ROS 2 node graph and print its islanding decision'
DESCRIPTION = """\
Start pmu_ingestion, coherency, partitioning and breaker_command (each its own process, with its
config/*.yaml), plus a recorder; arm the breaker node;
play BAG with bag_player (ground truth withheld); then print the decision: coherent groups, islands
with their buses, cut lines, disrupted MW, generation/load/shed per island, breaker commands, and the
latency from the islanding request to the breaker command, measured by one observer across processes.

The results folder holds the recorded output bag (output_bag/), the breaker audit log, every node's
log, rotor_angles.png (estimated angles coloured by group), network.png (islands and cut lines) and
summary.json; by default it is made under results/ in the current directory. Every child process is
stopped on exit, Ctrl-C or error. A run that fails before writing anything removes its folder; one that fails
later keeps its logs and says why in FAILED.json (INTERRUPTED.json after Ctrl-C), and the same command run
again replaces such a folder (--force: a finished run's too).

DDS domain: if ROS_DOMAIN_ID is set, the graph joins it, so your own tools see its topics (discovery
stays on loopback unless ROS_AUTOMATIC_DISCOVERY_RANGE says otherwise); another graph on that domain
will see and disturb it, unless each runs in its own --namespace. With --isolate, or with ROS_DOMAIN_ID
unset, the graph gets a free private domain on loopback.

Namespace: with --namespace /area1 every node of the graph, the player and the recorder run in /area1
(/area1/pmu/frames, /area1/breaker_command/set_armed, ...), and the bag's clock is /area1/clock, so two
replays in two namespaces share one domain without crosstalk. /diagnostics stays global; each status is
named by its node's full name (/area1/pmu_ingestion).

Hosts: with --hosts pdc,control,substation the graph runs on three emulated hosts, each a network namespace of
its own (pdc: pmu_ingestion and the bag player; control: coherency and partitioning; substation:
breaker_command), joined by a user-space WAN with --wan-delay-ms, --wan-jitter-ms and --wan-loss-pct between
hosts; DDS discovers by multicast across it. Roles joined by '+' share a host (pdc+control,substation). The
observer and the recorder are a fourth host, the operator's, whose view is a tap without delay or loss. Needs
root; without it, says so and exits 2. docs/deployment.md describes the emulation and a real deployment.

Trigger: by default the bag's own islanding request is played, as the paper's operator asks (--trigger bag).
With --trigger monitor the stability monitor (nodes/stability_monitor.py) runs beside the four nodes and is the
only source of requests: the bag's request is not played. The monitor predicts, swing by swing, whether the grid
separates and into which groups (SIME, docs/prediction.md) and asks once per swing that does, stamped at the frame
that decided it, signed with its key; the output names each request, its predicted groups and first pole slip,
or says that none was made (a grid predicted to recover: exit status 0). Real time only (or --rate): the player
holds the graph in step only at requests it plays itself.

Several bags (bags/*/): a regression run. Each bag gets a fresh graph of its own (the nodes keep state a
bag must not inherit: the breaker node's commanded breakers, the time of the last input) on a private
domain, in a child process, --jobs of them at once (default 2: a graph's start-up is mostly one process's
imports at a time, so two graphs keep two cores busier; 17 bags took 211 s instead of 331 s). One report with
a row per bag (decision, agreement with bags/index.yaml, speed, wall time), the overall speed against real
time, start-up included, with the load average, and each failed bag with why. Each bag's results are in a folder
named as the bag (with its parent folders when two bags share a name: site_a__run1, site_b__run1). --junit-xml
FILE writes the same as a JUnit XML report for CI. Exit status 1 if any bag went wrong.

Examples (bag names from bags/index.yaml):
  controlled-islanding replay bags/ieee39_g6g7_unstable            real time
  controlled-islanding replay bags/ieee39_g6g7_unstable --fast --json
  controlled-islanding replay bags/*/ --fast --json            every bag, one report
  controlled-islanding replay bags/*/ --fast --junit-xml build/replay.xml   the same, for CI
  controlled-islanding replay bags/ieee39_g6g7_unstable --probe-hz 20   extra requests: a latency benchmark
  controlled-islanding replay bags/kundur_bus9_unstable --trigger monitor   the monitor asks, not the bag
  controlled-islanding replay bags/ieee39_g6g7_unstable --fast --namespace /area1   one area of several
  controlled-islanding replay bags/ieee39_case2_g3_unstable --fast --hosts pdc,control,substation \
      --wan-delay-ms 20 --wan-jitter-ms 5 --wan-loss-pct 1
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the replay options."""
    parser.add_argument('bag', type=Path, nargs='+',
                        help='rosbag2 bag directory (see bags/index.yaml); several (bags/*/) make a regression run')
    parser.add_argument('--json', action='store_true', help='print one JSON decision on stdout and nothing else')
    parser.add_argument('--jobs', type=int, default=2,
                        help='with several bags: graphs running at once (default 2; see "Several bags" above)')
    parser.add_argument('--warm', action='store_true',
                        help='a regression run on --jobs long-lived workers: each bag on fresh nodes in a '
                             'fresh rclpy Context of the worker (imports and compiled kernels loaded once)')
    parser.add_argument('--fast', action='store_true', help='play as fast as possible (lockstep at requests)')
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor (default 1 = real time)')
    parser.add_argument('--results', type=Path, default=None,
                        help='results folder to create (default ./results/replay-<bag>-<UTC time>); one that '
                             'holds a failed or interrupted run is replaced')
    parser.add_argument('--force', action='store_true',
                        help='replace the --results folder even if it holds a finished run')
    parser.add_argument('--isolate', action='store_true',
                        help='run on a free private ROS_DOMAIN_ID on loopback even if ROS_DOMAIN_ID is set')
    parser.add_argument('--probe-hz', type=float, default=0.0,
                        help='also send islanding requests at this rate once the first decision is out, '
                             'to measure latency over many requests (a benchmark; default 0 = none). Once the '
                             "cut is open the breaker refuses every probe's cut, so probes are timed to their "
                             'decision')
    parser.add_argument('--disarmed', action='store_true',
                        help='leave breaker_command disarmed: decisions are refused and audited, nothing is commanded')
    parser.add_argument('--repeat', type=int, default=1,
                        help='replay N times, each on a fresh node graph, and print the latency over all N '
                             '(a benchmark; results/<folder>/run-<i> per replay)')
    parser.add_argument('--no-figures', action='store_true', help='skip the figures')
    parser.add_argument('--no-record', action='store_true',
                        help='do not run the recorder (no output bag, so no figures): less load while benchmarking')
    parser.add_argument('--timeout', type=float, default=120.0, help='give up after this many wall seconds')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help='run the whole graph in this ROS namespace, e.g. /area1 (default: the root one)')
    parser.add_argument('--estimator', choices=('steady_state', 'dse'), default=None,
                        help="pmu_ingestion's rotor angle estimator: steady_state, or dse (a Kalman filter on each "
                             "machine's model from the snapshot's machine data); default: config/pmu_ingestion.yaml")
    parser.add_argument('--trigger', choices=('bag', 'monitor'), default='bag',
                        help="where islanding requests come from: the bag's own (default, the paper's operator), or "
                             'the stability monitor alone (see "Trigger" above)')
    add_wan_arguments(parser)
    parser.add_argument('--junit-xml', type=Path, default=None, metavar='FILE',
                        help='also write the run as a JUnit XML report, a test case per bag with its reason on '
                             'failure, as pytest --junit-xml does (a regression run, even of one bag)')


def add_wan_arguments(parser: argparse.ArgumentParser) -> None:
    """Add --hosts and the WAN's options (replay and testbed)."""
    parser.add_argument('--hosts', default=None, metavar='H1,H2,...',
                        help='run the graph on emulated hosts joined by an emulated WAN (needs root): comma-separated '
                             'hosts, each a role (pdc, control, substation) or roles joined by +')
    parser.add_argument('--wan-delay-ms', type=float, default=0.0, help='with --hosts: one-way delay between hosts, ms')
    parser.add_argument('--wan-jitter-ms', type=float, default=0.0,
                        help='with --hosts: each packet delayed uniformly within delay +- jitter, ms')
    parser.add_argument('--wan-loss-pct', type=float, default=0.0,
                        help='with --hosts: probability that a packet between hosts is lost, %%')
    parser.add_argument('--wan-seed', type=int, default=0, help='with --hosts: seed of the loss and jitter draws')


def wan_link(args: argparse.Namespace) -> wan.LinkModel | None:
    """Return the WAN of --hosts and its options, None without --hosts."""
    wan_set = args.wan_delay_ms or args.wan_jitter_ms or args.wan_loss_pct
    if not args.hosts:
        if wan_set:
            raise CliError('--wan-delay-ms, --wan-jitter-ms and --wan-loss-pct need --hosts')
        return None
    try:
        return wan.LinkModel(args.wan_delay_ms, args.wan_jitter_ms, args.wan_loss_pct, args.wan_seed)
    except ValueError as exc:
        raise CliError(str(exc)) from exc


def _options(args: argparse.Namespace) -> dict:
    return {'fast': args.fast, 'rate': args.rate, 'probe_hz': args.probe_hz, 'timeout_s': args.timeout,
            'arm': not args.disarmed, 'record': not args.no_record, 'isolate': args.isolate,
            'namespace': args.namespace, 'estimator': args.estimator, 'hosts': args.hosts, 'link': wan_link(args),
            'trigger': args.trigger}


def run(args: argparse.Namespace) -> int:
    """Run the replay subcommand."""
    try:
        if len(args.bag) > 1 or args.junit_xml or args.warm:
            return _run_suite(args)
        args.bag = args.bag[0]
        if args.repeat < 1:
            raise CliError(f'--repeat {args.repeat} must be at least 1')
        if args.repeat > 1:
            return _run_repeated(args)
        summary = replay(args.bag, args.results, figures=not args.no_figures, quiet=args.json, force=args.force,
                         **_options(args))
    except GraphError as exc:
        raise CliError(str(exc)) from exc
    print(json.dumps(summary, default=str) if args.json else render(summary))
    if graph_failure(summary):
        if args.json:  # render() already said it on stdout otherwise
            print(f'replay: FAILED: {graph_failure(summary)}', file=sys.stderr)
        return 1
    quiet_monitor = args.trigger == 'monitor' and not summary['requests']
    return 1 if (summary['split'] is None and not quiet_monitor) or summary['undecided_requests'] \
        or refused(summary) else 0


def _run_repeated(args: argparse.Namespace) -> int:
    stamp = datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
    base = (args.results or Path('results') / f'bench-{args.bag.name}-{stamp}').resolve()
    result = replay_repeatedly(args.bag, base, args.repeat, quiet=args.json, **_options(args))
    failures = result.pop('failures')
    if args.json:
        print(json.dumps(result))
    else:
        lat, spd = result['latency_ms'], result['speed_vs_real_time']
        print(f'{args.repeat} replays of {args.bag} ({"as fast as possible" if args.fast else "real time"}): '
              f'{len(result["distinct_decisions"])} distinct decision(s) {result["distinct_decisions"]}')
        if lat['n']:
            print(f'latency over {lat["n"]} requests, to the breaker command ({lat["to_command"]} of them) or else to '
                  f'the decision (nothing to command): median {lat["median"]:.1f} ms, p99 {lat["p99"]:.1f} ms, '
                  f'max {lat["max"]:.1f} ms')
        if spd['median'] is not None:
            print(f'speed against real time: median {spd["median"]:.1f}x, slowest {spd["min"]:.1f}x')
        print(f'results: {base}')
    for i, failure in enumerate(failures):
        if failure:
            print(f'replay {i + 1}/{args.repeat}: FAILED: {failure}', file=sys.stderr)
    return 0 if len(result['distinct_decisions']) == 1 and not any(failures) else 1


def _run_suite(args: argparse.Namespace) -> int:
    for flag, value in (('--repeat', args.repeat != 1), ('--probe-hz', args.probe_hz), ('--hosts', args.hosts),
                        ('--namespace', args.namespace)):
        if value:
            raise CliError(f'{flag} takes one bag, not {len(args.bag)}')
    if args.jobs < 1:
        raise CliError(f'--jobs {args.jobs} must be at least 1')
    missing = [str(b) for b in args.bag if not b.exists()]
    if missing:
        raise CliError(f'bags do not exist: {", ".join(missing)}')
    options = ['--rate', str(args.rate), '--timeout', str(args.timeout)]
    options += [flag for flag, on in (('--fast', args.fast), ('--disarmed', args.disarmed),
                                      ('--no-record', args.no_record), ('--no-figures', args.no_figures)) if on]
    if args.estimator:
        options += ['--estimator', args.estimator]
    if args.trigger != 'bag':
        options += ['--trigger', args.trigger]
    try:
        names = run_names(args.bag)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    stamp = datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
    base = args.results or Path('results') / f'replay-suite-{stamp}'
    with running(base, args.force) as base, progress_bar(len(names), 'replay', 'bag') as bar:
        report = replay_suite([SuiteRun(n, b, tuple(options)) for n, b in zip(names, args.bag, strict=True)], base,
                              jobs=args.jobs, quiet=args.json, done=lambda name, outcome: bar.update(),
                              warm=args.warm)
        atomic.write_text(base / 'suite.json', json.dumps(report, indent=2, default=str))
        if args.junit_xml:
            atomic.write_text(args.junit_xml, junit_xml(report))
    print(json.dumps(report, default=str) if args.json else render_suite(report))
    return 0 if all(r['ok'] for r in report['rows']) else 1
