"""`evaluate --monitor FILE.md`: the stability monitor on every scenario (evaluation/monitor_study.py), written."""

from __future__ import annotations

import logging

from controlled_islanding.commands import CliError, not_evaluated, progress_bar

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
    missing = [str(p) for p in args.testbed if not p.exists()]
    if missing:
        raise CliError(f'--testbed folders or oracle records do not exist: {", ".join(missing)}')
    try:
        loops = monitor_study.read_testbed(args.testbed)
    except monitor_study.MonitorStudyError as exc:
        raise CliError(str(exc)) from None
    runs, draws, drawn, failed = [], [], set(), []
    seeds = range(1, args.noise_seeds + 1)
    start, load_start = time.monotonic(), load_average()
    with progress_bar(len(sources), 'monitor', 'scenario') as bar:
        for kind, path in sources:
            log.info('%s: %s', path, 'simulating in ANDES' if kind == 'andes' else 'reading the bag')
            try:
                simulated = study.simulate_scenario(path) if kind == 'andes' else None
                runs.append(monitor_study.watch_run(study.run_from_bag(path) if simulated is None
                                                    else study.measured_run(*simulated, path)))
                scenario_path = runs[-1].scenario_path
                if seeds and scenario_path is not None and scenario_path.resolve() not in drawn:
                    drawn.add(scenario_path.resolve())
                    log.info('%s: measuring under seeds %d to %d', scenario_path, seeds[0], seeds[-1])
                    # A bag's scenario is simulated here; an --andes one reuses the simulation above.
                    draws.append(monitor_study.noise_draws(scenario_path, seeds, simulated))
            except study.PredictionStudyError as exc:
                log.error('%s', exc)
                failed.append(str(exc))
            bar.update()
    if not runs:
        raise CliError('no scenario could be evaluated: ' + '; '.join(failed))
    note = f'{time.monotonic() - start:.0f} s wall, {load_start} at the start and {load_average()} at the end'
    print('\n'.join(monitor_study.report(runs, loops, note)))
    if draws:
        print('\n'.join(['', *monitor_study.report_noise(draws)]))
    command = ' '.join(['controlled-islanding evaluate', *map(str, bag_paths), *(f'--andes {p}' for p in args.andes),
                        *(f'--testbed {p}' for p in args.testbed),
                        *([f'--noise-seeds {args.noise_seeds}'] if draws else []), '--monitor', str(args.monitor)])
    monitor_study.write_page(runs, loops, args.monitor, command=command, run_note=note, draws=draws,
                             not_evaluated=failed)
    log.info('page: %s', args.monitor)
    record = monitor_study.oracle_record_path(args.monitor)
    if any(loop.oracle for loop in loops.values()):
        monitor_study.write_oracle_record(record, loops)
        log.info('the oracles it judged against: %s', record)
    return not_evaluated(failed, len(sources), args.monitor)
