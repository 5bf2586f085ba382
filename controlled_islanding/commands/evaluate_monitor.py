"""`evaluate --monitor FILE.md`: the stability monitor on every scenario (evaluation/monitor_study.py), written."""

from __future__ import annotations

import logging

from controlled_islanding.commands import CliError, progress_bar

log = logging.getLogger(__name__)


def judge_monitor(args, bag_paths) -> int:
    """Run the monitor's core on every bag and --andes scenario, beside --testbed closed loops; print; write."""
    import time

    from controlled_islanding.evaluation import monitor_study
    from controlled_islanding.evaluation import predictors as study
    from controlled_islanding.harness.benchmarks import load_average

    sources = [('bag', p) for p in bag_paths] + [('andes', p) for p in args.andes]
    if not sources:
        raise CliError('--monitor needs at least one BAG or --andes SCENARIO.yaml')
    if args.noise_seeds < 0:
        raise CliError(f'--noise-seeds must be 0 or more, got {args.noise_seeds}')
    missing = [str(p) for p in args.testbed if not p.is_dir()]
    if missing:
        raise CliError(f'--testbed folders do not exist: {", ".join(missing)}')
    loops = monitor_study.read_testbed(args.testbed)
    runs = []
    start, load_start = time.monotonic(), load_average()
    with progress_bar(len(sources), 'monitor', 'scenario') as bar:
        for kind, path in sources:
            log.info('%s: %s', path, 'simulating in ANDES' if kind == 'andes' else 'reading the bag')
            try:
                runs.append(monitor_study.watch_run(study.run_from_bag(path) if kind == 'bag'
                                                    else study.run_from_scenario(path)))
            except study.PredictionStudyError as exc:
                raise CliError(str(exc)) from exc
            bar.update()
    draws = []
    if args.noise_seeds > 0:
        paths = list(dict.fromkeys(r.scenario_path.resolve() for r in runs if r.scenario_path is not None))
        seeds = range(1, args.noise_seeds + 1)
        with progress_bar(len(paths), 'noise draws', 'scenario') as bar:
            for path in paths:
                log.info('%s: simulating in ANDES, measuring under seeds %d to %d', path, seeds[0], seeds[-1])
                try:
                    draws.append(monitor_study.noise_draws(path, seeds))
                except study.PredictionStudyError as exc:
                    raise CliError(str(exc)) from exc
                bar.update()
    note = f'{time.monotonic() - start:.0f} s wall, {load_start} at the start and {load_average()} at the end'
    print('\n'.join(monitor_study.report(runs, loops, note)))
    if draws:
        print('\n'.join(['', *monitor_study.report_noise(draws)]))
    command = ' '.join(['controlled-islanding evaluate', *map(str, bag_paths), *(f'--andes {p}' for p in args.andes),
                        *(f'--testbed {p}' for p in args.testbed),
                        *([f'--noise-seeds {args.noise_seeds}'] if draws else []), '--monitor', str(args.monitor)])
    monitor_study.write_page(runs, loops, args.monitor, command=command, run_note=note, draws=draws)
    log.info('page: %s', args.monitor)
    return 0
