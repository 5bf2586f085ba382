"""Subcommands of `controlled-islanding`, one module each: argparse and printing only (see controlled_islanding/cli.py).

A command validates its arguments, calls the library, prints the result, and turns the library's errors into a
CliError, which cli.py prints as one line with exit status 2.
"""

from __future__ import annotations

import logging
import sys


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def progress_bar(total: int, desc: str, unit: str = 'it'):
    """Return a tqdm bar for a loop a person waits on: on stderr, on a terminal only, and not with --quiet."""
    from tqdm import tqdm

    shown = logging.getLogger('controlled_islanding').isEnabledFor(logging.INFO)
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False, disable=None if shown else True)
