"""`evaluate --k-rules FILE.md` and `--observability FILE.md`: the k rules and the PMU coverage sweep.

The k rules compared in evaluation/coherency_rules.py, the coverage sweep in evaluation/observability_sweep.py;
both printed and written as pages.
"""

from __future__ import annotations

import logging

from controlled_islanding.commands import CliError, progress_bar
from controlled_islanding.evaluation.cases import EvaluateError, manifest_entry

log = logging.getLogger(__name__)


def _scenario(study, bag):
    try:
        return study.scenario_from_bag(bag, manifest_entry(bag))
    except EvaluateError as exc:
        raise CliError(f'{bag.path}: {exc}') from exc


def compare_rules(args, bags) -> int:
    """Compare every k rule on the bags and the --andes scenarios; print the tables and write the page."""
    from controlled_islanding.core.k_rules import RULES
    from controlled_islanding.evaluation import coherency_rules as study

    scenarios = [_scenario(study, bag) for bag in bags]
    for path in args.andes:
        log.info('%s: simulating in ANDES', path)
        try:
            scenarios.append(study.scenario_from_andes(path))
        except EvaluateError as exc:
            raise CliError(str(exc)) from exc
    with progress_bar(len(scenarios) * len(RULES), 'k rules', 'rule') as bar:
        def step(text: str) -> None:
            log.info(text)
            bar.update()

        results = study.compare(scenarios, window_s=args.window_s, max_groups=args.max_groups,
                                dtw_band=args.dtw_band_samples or None, step_s=args.lead_step_s, progress=step)
    print(study.format_console(results))
    command = ' '.join(['controlled-islanding evaluate', *args.bags, *(f'--andes {p}' for p in args.andes),
                        '--k-rules', str(args.k_rules)])
    study.write_report(results, args.k_rules, chosen=args.k_rule, command=command, window_s=args.window_s,
                       step_s=args.lead_step_s)
    log.info('report: %s', args.k_rules)
    return 0


def sweep_observability(args, bags) -> int:
    """Sweep PMU coverage on every bag; print the table and write the page."""
    from controlled_islanding.evaluation import coherency_rules as study
    from controlled_islanding.evaluation import observability_sweep as obs

    if not bags:
        raise CliError('--observability needs at least one BAG')
    rows = []
    with progress_bar(len(bags), 'observability', 'bag') as bar:
        for bag in bags:
            scenario = _scenario(study, bag)
            try:
                rows += obs.sweep(scenario, bag.grid_at(scenario.request_s + 1e-9), draws=args.draws,
                                  seed=args.seed, window_s=args.window_s, max_groups=args.max_groups,
                                  k_rule=args.k_rule, dtw_band=args.dtw_band_samples or None,
                                  time_limit_s=args.time_limit_s, progress=log.info)
            except obs.SweepError as exc:
                raise CliError(str(exc)) from exc
            bar.update()
    print('\n'.join(obs.table(rows)))
    command = ' '.join(['controlled-islanding evaluate', *args.bags, '--observability', str(args.observability),
                        f'--draws {args.draws} --seed {args.seed}'])
    obs.write_report(rows, args.observability, command=command, k_rule=args.k_rule, window_s=args.window_s)
    log.info('report: %s', args.observability)
    return 0
