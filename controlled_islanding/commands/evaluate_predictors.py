"""`evaluate --predictors FILE.md`: the stability predictors compared (evaluation/predictors.py), printed, written."""

from __future__ import annotations

import logging

from controlled_islanding.commands import CliError, not_evaluated, progress_bar

log = logging.getLogger(__name__)


def compare_predictors(args, bag_paths) -> int:
    """Every predictor on every bag and --andes scenario; print the figures and the table; write the page."""
    import time

    from controlled_islanding.evaluation import predictors as study
    from controlled_islanding.harness.benchmarks import load_average

    sources = [('bag', p) for p in bag_paths] + [('andes', p) for p in args.andes]
    if not sources:
        raise CliError('--predictors needs at least one BAG or --andes SCENARIO.yaml')
    results, failed = [], []
    start, load_start = time.monotonic(), load_average()
    with progress_bar(len(sources), 'predictors', 'scenario') as bar:
        for kind, path in sources:
            log.info('%s: %s', path, 'simulating in ANDES' if kind == 'andes' else 'reading the bag')
            try:
                run = study.run_from_bag(path) if kind == 'bag' else study.run_from_scenario(path)
                results.append(study.study(run))
            except study.PredictionStudyError as exc:
                log.error('%s', exc)
                failed.append(str(exc))
            bar.update()
    if not results:
        raise CliError('no scenario could be evaluated: ' + '; '.join(failed))
    # CPU per frame depends on what else runs: the run's wall time and load go beside it.
    run = f'{time.monotonic() - start:.0f} s wall, {load_start} at the start and {load_average()} at the end'
    lines = study.report(results, run=run)
    print('\n'.join(lines))
    command = ' '.join(['controlled-islanding evaluate', *map(str, bag_paths), *(f'--andes {p}' for p in args.andes),
                        '--predictors', str(args.predictors)])
    study.write_report(results, args.predictors, command=command, run=run, not_evaluated=failed)
    log.info('report: %s', args.predictors)
    return not_evaluated(failed, len(sources), args.predictors)
