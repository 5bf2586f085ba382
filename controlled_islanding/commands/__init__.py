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
