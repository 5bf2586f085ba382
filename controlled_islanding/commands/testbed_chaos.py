"""`testbed --chaos SEED`: closed-loop runs with one seeded fault each (harness/chaos_sweep.py), and their report."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from datetime import UTC, datetime
from pathlib import Path

from controlled_islanding.commands import CliError, progress_bar

log = logging.getLogger(__name__)

HELP_TEXT = """\
Chaos (--chaos SEED [--chaos-runs N]): each scenario runs closed-loop 3 times unfaulted, then once per seed SEED ..
SEED+N-1 with one fault drawn from the seed (graph/chaos.py), fired when the graph's /clock reaches the request's
time plus a seeded offset within +-1 s: kill -9 of a pipeline node (the supervisor restarts it), SIGSTOP and a
SIGCONT after a seeded pause (past the watchdog's 10 s hang limit, the supervisor kills and restarts it first),
a step of one node's sim clock (with --hosts, one host's), back or ahead, or, with --hosts, a partition of the
emulated WAN between the control and substation hosts for a seeded time. One seed is the same fault on every
system. Each run reports whether the supervisor recovered, the decision or the refusal and its reason, every
unsafe command (a breaker rule of docs/nodes.md broken, judged from the audit log, /breaker/commands and the
grid's clock) and the load served against the unfaulted runs. Runs go into --results (default
results/chaos-<UTC time>), one folder each; the same command again skips the finished runs, so a sweep resumes
after Ctrl-C or a kill, or grows with --chaos-runs. Progress on stderr, a line per run. --markdown PAGE puts the
report into PAGE as a generated section (docs/nodes.md); --render RESULTS only rebuilds it. Exit status 1 if any
run commanded unsafely or ended without a decision or a reasoned refusal.
  controlled-islanding testbed bags/ieee14_g1_unstable.yaml --chaos 7
  controlled-islanding testbed bags/ieee14_g1_unstable.yaml bags/kundur_bus9_unstable.yaml \\
      bags/ieee39_g6g7_unstable.yaml --chaos 0 --chaos-runs 35 --hosts pdc,control,substation \\
      --results build/chaos --markdown docs/nodes.md     the sweep of docs/nodes.md (hours; resumable)
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the chaos options."""
    parser.add_argument('--chaos', type=int, default=None, metavar='SEED',
                        help='run each scenario with one seeded fault near the request (see Chaos below)')
    parser.add_argument('--chaos-runs', type=int, default=1, metavar='N',
                        help='with --chaos: seeds SEED to SEED+N-1 (default 1)')


def run(args: argparse.Namespace, paths: list[Path], settings: object) -> int:
    """Run or render the chaos sweep, print it, and write its section into --markdown."""
    from controlled_islanding.evaluation import chaos_report
    from controlled_islanding.graph import GraphError
    from controlled_islanding.harness import chaos_sweep

    if args.chaos_runs < 1:
        raise CliError(f'--chaos-runs {args.chaos_runs} must be at least 1')
    if args.render is not None:
        results = chaos_sweep.collect(args.render)
        if not results:
            raise CliError(f'{args.render}: no */*/{chaos_sweep.RESULT}; is it a chaos sweep folder?')
        base = args.render
    else:
        base = args.results or Path('results') / f'chaos-{datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")}'
        seeds = list(range(args.chaos, args.chaos + args.chaos_runs))
        with progress_bar(len(paths) * (len(seeds) + chaos_sweep.UNFAULTED_RUNS), 'chaos', 'run') as bar, \
                chaos_sweep.logged(base, _command()) as ran:
            def done(result: dict, i: int, n: int) -> None:
                bar.update()
                ran.append(result)
                log.info('run %d/%d: %s', i, n, _line(result))

            try:
                results = chaos_sweep.sweep(paths, seeds, base, settings, done)
            except GraphError as exc:
                raise CliError(str(exc)) from exc
    if args.markdown:
        held = chaos_sweep.settings_of(base)
        if held is None:
            raise CliError(f'{base}: no {chaos_sweep.SETTINGS}, so the settings of its runs are not known')
        chaos_report.write_section(args.markdown, chaos_report.section(
            results, _command(), _settings_text(held), chaos_sweep.invocations(base)))
        log.info('report: %s', args.markdown)
    print(json.dumps(results, default=str) if args.json else chaos_report.render(results))
    if not args.json:
        print(f'results: {base}')
    f = chaos_report.figures(results)
    return 0 if f['unsafe'] == 0 and f['reasoned'] == f['runs'] else 1


def _command() -> str:
    return 'controlled-islanding testbed ' + ' '.join(sys.argv[2:])


def _line(r: dict) -> str:
    from controlled_islanding.evaluation.chaos_report import reason, served, verdict

    what = (f'unfaulted {r.get("baseline", 0) + 1}' if r['seed'] is None
            else f'seed {r["seed"]} ({(r["chaos"] or {}).get("describe")})')
    if 'error' in r:
        return f'{r["scenario"]} {what}: run failed: {r["error"].splitlines()[0]}'
    rec = (r['chaos'] or {}).get('recovered')
    return (f'{r["scenario"]} {what}: {verdict(r)} ({reason(r)[:100]}); '
            f'{"" if rec is None else "recovered; " if rec else "NOT recovered; "}'
            f'{len(r["unsafe"])} unsafe; load served {served(r)}; {r["wall_s"]:.0f} s')


def _settings_text(settings: dict) -> str:
    mode = ('lockstep (sim time stands at the request while the graph works)' if not settings['rate'] else
            f'paced at {settings["rate"]:g}x real time')
    link = settings['link']
    hosts = (f'on emulated hosts {settings["hosts"]} (WAN delay {link["delay_ms"]:g} ms, jitter {link["jitter_ms"]:g} '
             f'ms, loss {link["loss_pct"]:g} %)' if settings['hosts'] else 'on one host')
    return (f'Closed loop {mode}, {hosts}; breaker operating time {settings["breaker_operating_s"]:g} s, simulated '
            f'{settings["run_after_s"]:g} s past the request.')
