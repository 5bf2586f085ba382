"""`evaluate --attacks FILE.md`: the PMU attack sweep (evaluation/attack_sweep.py), printed and written as a page."""

from __future__ import annotations

import logging

from controlled_islanding.commands import CliError, progress_bar

log = logging.getLogger(__name__)


def sweep_attacks(args, bags) -> int:
    """Every attack on every bag; print the figures and the table; write the page."""
    from controlled_islanding.evaluation import attack_sweep

    if not bags:
        raise CliError('--attacks needs at least one BAG')
    with progress_bar(len(bags), 'attacks', 'bag') as bar:
        lines = attack_sweep.sweep(bags, seed=args.seed, progress=log.info, done=bar.update)
    print('\n'.join(lines))
    attack_sweep.write_report(lines, args.attacks,
                              command=f'controlled-islanding evaluate {" ".join(map(str, args.bags))} --attacks '
                                      f'{args.attacks}')
    log.info('report: %s', args.attacks)
    return 0
