"""Subcommands of `controlled-islanding`, one module each: argparse and printing only (see controlled_islanding/cli.py).

A command validates its arguments, calls the library, prints the result, and turns the library's errors into a
CliError, which cli.py prints as one line with exit status 2.
"""

from __future__ import annotations

import logging
import shutil
import sys


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def progress_bar(total: int, desc: str, unit: str = 'it'):
    """Return a tqdm bar for a loop a person waits on: on stderr, on a terminal only, and not with --quiet."""
    from tqdm import tqdm

    shown = logging.getLogger('controlled_islanding').isEnabledFor(logging.INFO)
    # A terminal that says it is 0 x 0 (a CI runner's pseudo-terminal, `script`) made tqdm draw nothing: no width
    # for the bar, no row to put it on. shutil falls back to 80 x 24 there.
    size = shutil.get_terminal_size()
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False, disable=None if shown else True,
                ncols=size.columns, nrows=size.lines)


def not_evaluated(failed: list[str], total: int, page) -> int:
    """Return 0, or raise the CliError that names the scenarios a study could not evaluate (its page lists them).

    One scenario whose simulation fails (ANDES does not converge) must not cost the minutes spent on the others:
    the study goes on, writes their page with the failures listed, and still exits non-zero.
    """
    if not failed:
        return 0
    raise CliError(f'{len(failed)} of {total} scenarios not evaluated (the others are written to {page}, which lists '
                   f'these at its end): ' + '; '.join(failed))
