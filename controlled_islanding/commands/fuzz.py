"""`controlled-islanding fuzz`: soak the live node graph with malformed and adversarial messages."""

from __future__ import annotations

import argparse
import json
import sys
from datetime import UTC, datetime
from pathlib import Path

from controlled_islanding.commands import CliError
from controlled_islanding.locations import bags_dir, build_dir

HELP = 'soak the live node graph with malformed and adversarial messages, then check a good replay'
DESCRIPTION = """\
Start pmu_ingestion, coherency, partitioning and breaker_command (each its own process, supervised,
on sim time from this command, on a private ROS_DOMAIN_ID confined to loopback) and arm the breaker
node with a signed operator request. Then, topic by topic (/pmu/frames, /network/snapshot,
/network/branch_status, /islanding/request, /rotor_angles, /coherent_groups, /islanding/decision),
publish N seeded messages, each with a defect: NaN/inf and negative values, arrays at and beyond the
nodes' caps, parallel arrays of unequal length, empty, unknown, duplicate and renamed ids, zero,
far-past and far-future stamps, unset enums, unsigned and forged decisions. One line per topic shows
progress. Afterwards the default bag of bags/index.yaml is played, as fast as possible, through the
SAME node processes.

Checks (exit status 0 only if all hold):
  - each topic: the receiving nodes counted rejections in /diagnostics (rejected.*), and no
    exception escaped a callback (error.*);
  - no node died or hung (the supervisor restarts and records them);
  - each node's resident memory (VmRSS) grew by less than 20 MB over the fuzz;
  - no breaker command was issued during the fuzz;
  - the replay afterwards decides the manifest's expected cut.

Keys are made for the run under build/ (never your own); node logs, the breaker audit log and
report.json go to the results folder. Exit status 1: a check failed; 2: the soak could not run.

With --namespace /area1 the graph, the adversary and the replay run in /area1 (/area1/pmu/frames, ...,
/area1/clock), as with `replay --namespace`; report.json lists the graph's topic names.

With --breaker-trials N, breaker_command alone gets N seeded adversarial decisions and signed arm and
disarm requests (duplicates, other spellings, stale and future stamps, forged and foreign signatures,
inconsistent cuts, resends, recloses, and kill -9 restarts); its audit log is then replayed against every
breaker rule (docs/nodes.md) and the rules broken are printed. Exit status 1 if any.

Examples:
  controlled-islanding fuzz --per-topic 30            a quick check (about a minute)
  controlled-islanding fuzz --breaker-trials 20000    the breaker soak
  controlled-islanding fuzz --per-topic 10000 --seed 7 --json
  controlled-islanding fuzz --per-topic 30 --namespace /area1
"""



def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the fuzz options."""
    parser.add_argument('--per-topic', type=int, default=1000, metavar='N',
                        help='messages per input topic (default 1000; the documented soak is 10000)')
    parser.add_argument('--seed', type=int, default=1, metavar='S', help='random seed of the messages (default 1)')
    parser.add_argument('--bag', type=Path, default=None,
                        help='bag to replay afterwards, listed in bags/index.yaml (default: its default bag)')
    parser.add_argument('--json', action='store_true', help='print one JSON report on stdout, progress on stderr')
    parser.add_argument('--results', type=Path, default=None,
                        help='results folder to create (default build/fuzz/<UTC time>)')
    parser.add_argument('--breaker-trials', type=int, default=0, metavar='N',
                        help='instead: soak breaker_command alone with N adversarial decisions and arm requests '
                             '(kill -9 restarts included) and check its audit log against every breaker rule')
    parser.add_argument('--warm-rounds', type=int, default=None, metavar='R',
                        help='most rounds of the largest messages of every kind before the RSS baseline; rounds stop '
                             "once two in a row raise no node's RSS 1 MB above its high so far (default 12)")
    parser.add_argument('--keys', type=Path, default=None,
                        help='signing key directory, made if missing (default build/fuzz/keys)')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help='run the graph in this ROS namespace, e.g. /area1 (default: the root one; not with '
                             '--breaker-trials)')


def _manifest_entry(bag: Path | None) -> tuple[Path, dict]:
    from controlled_islanding.sim.manifest import ManifestError, default_bag, manifest_entries

    if bag is None:
        try:
            entry = default_bag()
        except ManifestError as exc:
            raise CliError(str(exc)) from exc
        return bags_dir() / entry['bag'], entry
    for entry in manifest_entries():
        if Path(entry['bag']).name == bag.name:
            return bag, entry
    raise CliError(f'bag {bag} is not listed in bags/index.yaml, so there is no expected decision to check')


def run(args: argparse.Namespace) -> int:
    """Run the soak and print its tables (or JSON)."""
    from controlled_islanding.graph import GraphError
    from controlled_islanding.graph.replay import namespace_name
    from controlled_islanding.harness import fuzzing

    try:
        namespace = namespace_name(args.namespace)
    except GraphError as exc:
        raise CliError(str(exc)) from exc
    if args.breaker_trials:
        if namespace:
            raise CliError('--namespace applies to the graph soak, not to --breaker-trials')
        return _run_breaker_soak(args)
    if args.per_topic < 1:
        raise CliError(f'--per-topic {args.per_topic} must be at least 1')
    if args.warm_rounds is not None and args.warm_rounds < 1:
        raise CliError(f'--warm-rounds {args.warm_rounds} must be at least 1')
    bag, entry = _manifest_entry(args.bag)
    if not bag.exists():
        raise CliError(f'bag {bag} does not exist')
    results = args.results or build_dir() / 'fuzz' / datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
    results = results.resolve()
    if results.exists() and any(results.iterdir()):
        raise CliError(f'results folder {results} exists and is not empty; name a new one')
    keys = (args.keys or build_dir() / 'fuzz' / 'keys').resolve()

    def progress(line: str) -> None:
        print(line, file=sys.stderr if args.json else sys.stdout, flush=True)

    try:
        report = fuzzing.run_soak(args.per_topic, args.seed, bag, entry, results, keys, progress,
                                  warm_rounds=fuzzing.WARM_ROUNDS if args.warm_rounds is None else args.warm_rounds,
                                  namespace=namespace)
    except fuzzing.FuzzError as exc:
        raise CliError(str(exc)) from exc
    if args.json:
        print(json.dumps(report.as_dict(), default=str))
    else:
        print()
        print(fuzzing.render(report))
    return 0 if report.passed else 1


def _run_breaker_soak(args: argparse.Namespace) -> int:
    from controlled_islanding.harness import breaker_soak

    if args.breaker_trials < 1:
        raise CliError(f'--breaker-trials {args.breaker_trials} must be at least 1')
    results = (args.results or build_dir() / 'fuzz' / f'breaker-{datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")}')
    keys = (args.keys or build_dir() / 'fuzz' / 'keys').resolve()
    try:
        report = breaker_soak.run_breaker_soak(args.breaker_trials, args.seed, keys, results.resolve(),
                                               lambda line: print(line, file=sys.stderr, flush=True))
    except breaker_soak.SoakError as exc:
        raise CliError(str(exc)) from exc
    print(json.dumps(report.__dict__) if args.json else report.render())
    return 0 if not report.broken else 1
