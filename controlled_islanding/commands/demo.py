"""`controlled-islanding demo`: replay the default IEEE 39 bag through the node graph and show the decision."""

from __future__ import annotations

import argparse
from datetime import UTC
from pathlib import Path

from controlled_islanding.commands import CliError
from controlled_islanding.graph import GraphError
from controlled_islanding.graph.replay import replay
from controlled_islanding.graph.summary import graph_failure, refused, render
from controlled_islanding.locations import bags_dir
from controlled_islanding.sim.manifest import ManifestError, default_bag

HELP = 'replay the default IEEE 39 bag through the ROS 2 nodes and print the islanding decision'
DESCRIPTION = """\
The main job, end to end: the default scenario bag of bags/index.yaml (IEEE 39, generators losing
synchronism after a cascade) is played in real time into pmu_ingestion -> coherency -> partitioning ->
breaker_command, each its own process over DDS (loopback only, a private ROS_DOMAIN_ID). The armed
breaker node opens the cut lines. Printed: coherent groups, islands with their buses, cut lines,
disrupted MW, generation/load/shed per island, breaker commands, and the latency from the islanding
request to the breaker command. The results folder (named at the end) holds the recorded output bag,
the breaker audit log, node logs, rotor_angles.png, network.png and summary.json.

Same as `controlled-islanding replay BAG` on the default bag; see that command for more options.
"""

def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the demo options."""
    parser.add_argument('--results', type=Path, default=None,
                        help='results folder to create (default ./results/demo-<UTC time>)')
    parser.add_argument('--fast', action='store_true', help='play as fast as possible instead of real time')
    parser.add_argument('--json', action='store_true', help='print one JSON decision on stdout and nothing else')


def run(args: argparse.Namespace) -> int:
    """Run the demo."""
    import json
    from datetime import datetime

    try:
        entry = default_bag()
    except ManifestError as exc:
        raise CliError(str(exc)) from exc
    bag = bags_dir() / entry['bag']
    if not bag.exists():
        raise CliError(f'default bag {bag} is missing; regenerate it with `controlled-islanding simulate`')
    results = args.results
    if results is None:
        results = Path('results') / f'demo-{datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")}'
    if not args.json:
        print(f'demo: {entry["name"]}: {" ".join(str(entry.get("description", "")).split())}\n', flush=True)
    # The demo never joins the user's domain: it must behave the same on every machine.
    try:
        summary = replay(bag, results, fast=args.fast, quiet=args.json, isolate=True)
    except GraphError as exc:
        raise CliError(str(exc)) from exc
    expected = entry.get('expected_decision', {})
    summary['manifest_agrees'] = (summary['split'] == expected.get('split')
                                  and sorted(summary.get('cut_branch_ids', [])) ==
                                  sorted(expected.get('cut_branches', [])))
    if args.json:
        print(json.dumps(summary, default=str))
    else:
        print(render(summary))
        print(f'manifest expects: cut {", ".join(expected.get("cut_branches", [])) or "nothing"} -> '
              f'{"agrees" if summary["manifest_agrees"] else "DIFFERS"}')
    failed = summary['split'] is None or summary['undecided_requests'] or refused(summary) or graph_failure(summary)
    return 1 if failed else 0
