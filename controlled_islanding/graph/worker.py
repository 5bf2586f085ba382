"""A warm regression worker: a long-lived process that replays bag after bag, each on a fresh composed graph.

Started by graph/suite.py (`replay_suite(warm=True)`), it does its imports and loads its compiled kernels once,
then reads one job a line on stdin (JSON: name, bag, results, options, stderr) and, for each, replays the bag
with graph/composed.py: fresh node objects in a fresh rclpy Context on a private domain of its own (graph/rosenv),
a new results folder and audit log, everything destroyed after the bag. It answers each job with one JSON line
{name, status} on stdout (status as `controlled-islanding replay` exits: 0 decided, 1 no decision, refused or a
failed node, 2 the replay could not run). What crosses from one bag to the next is code, never state: no node,
context, subscription or file survives a bag, and no message resets anything. A worker that dies costs the bag
it was replaying; the suite reports it and starts another.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import traceback
from pathlib import Path

from controlled_islanding.graph import GraphError
from controlled_islanding.graph.summary import graph_failure, refused

log = logging.getLogger('controlled_islanding.graph.worker')  # also when run as __main__


def _option_parser() -> argparse.ArgumentParser:
    # The replay options a regression run passes on (graph/suite.py SuiteRun.options), as `replay` spells them.
    parser = argparse.ArgumentParser(prog='worker', add_help=False, exit_on_error=False)
    parser.add_argument('--fast', action='store_true')
    parser.add_argument('--rate', type=float, default=1.0)
    parser.add_argument('--timeout', dest='timeout_s', type=float, default=120.0)
    parser.add_argument('--probe-hz', type=float, default=0.0)
    parser.add_argument('--disarmed', dest='arm', action='store_false')
    parser.add_argument('--no-record', dest='record', action='store_false')
    parser.add_argument('--no-figures', dest='figures', action='store_false')
    parser.add_argument('--estimator', choices=('steady_state', 'dse'), default=None)
    return parser


def replay_options(options: list[str]) -> dict:
    """Return replay()'s keyword options for a SuiteRun's option strings.

    Raises:
        GraphError: An option a warm worker does not take (--hosts, --namespace, --repeat, ...).

    """
    try:
        parsed, unknown = _option_parser().parse_known_args(options)
    except (argparse.ArgumentError, SystemExit) as exc:
        raise GraphError(f'bad replay options {options}: {exc}') from exc
    if unknown:
        raise GraphError(f'a warm worker does not take {" ".join(unknown)}')
    return vars(parsed)


def exit_status(summary: dict) -> int:
    """Return the status `controlled-islanding replay BAG` exits with for this summary."""
    if graph_failure(summary) or summary['split'] is None or summary['undecided_requests'] or refused(summary):
        return 1
    return 0


def run_job(job: dict) -> int:
    """Replay one job's bag on a fresh composed graph; write its error, if any, to job['stderr']; return a status."""
    from controlled_islanding.graph.replay import replay

    with open(job['stderr'], 'w') as err:
        try:
            summary = replay(Path(job['bag']), Path(job['results']), in_process=True, isolate=True, quiet=True,
                             **replay_options(job['options']))
        except GraphError as exc:
            err.write(f'error: {exc}\n')
            return 2
        except Exception:
            err.write(traceback.format_exc())
            return 2
        if graph_failure(summary):
            err.write(f'replay: FAILED: {graph_failure(summary)}\n')
        return exit_status(summary)


def warm_up() -> None:
    """Import every node and its engines once (what each bag would otherwise pay for in every process)."""
    import importlib

    from controlled_islanding.graph.composed import NODE_CLASSES
    from controlled_islanding.ros.spin import dds_memory_profile, settle_heap

    for module in NODE_CLASSES:
        importlib.import_module(f'controlled_islanding.nodes.{module}')
    importlib.import_module('controlled_islanding.graph.replay')
    # Fast DDS reads the profile when this process's first participant is made; it stays for the worker's life.
    profile = dds_memory_profile()
    if profile is not None:
        import atexit

        atexit.register(lambda: Path(profile).unlink(missing_ok=True))
    settle_heap()


def main() -> int:
    """Serve jobs from stdin until it closes; one JSON answer line per job on the original stdout."""
    answers = os.fdopen(os.dup(1), 'w')
    os.dup2(2, 1)  # a stray print must not break the answer stream
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter('%(asctime)s %(name)s: %(message)s'))
    logging.getLogger('controlled_islanding').addHandler(handler)
    logging.getLogger('controlled_islanding').setLevel(logging.INFO)
    warm_up()
    answers.write(json.dumps({'ready': os.getpid()}) + '\n')
    answers.flush()
    for line in sys.stdin:
        if not line.strip():
            continue
        job = json.loads(line)
        log.info('replaying %s', job['name'])
        status = run_job(job)
        answers.write(json.dumps({'name': job['name'], 'status': status}) + '\n')
        answers.flush()
    return 0


if __name__ == '__main__':
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        sys.exit(130)
