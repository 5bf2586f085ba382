"""`controlled-islanding`: the user-facing command line.

Each subcommand lives in controlled_islanding/commands/<name>.py and exposes
`HELP` (one line), `DESCRIPTION` (what it teaches in --help), `add_arguments(parser)`
and `run(args) -> int`. They are imported only when chosen, so `--help` is fast and
one subcommand's heavy imports (ANDES, rclpy) never slow another.

Results go to stdout; progress and messages go to stderr through `logging`, one line each,
"<subcommand>: <message>", so that --quiet and --verbose set one level for every part of the package.
A progress bar (tqdm) shows only on a terminal; log lines written meanwhile go around it.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

SUBCOMMANDS = ('demo', 'replay', 'partition', 'simulate', 'evaluate', 'bench', 'keys', 'fuzz', 'serve-pmu', 'export',
               'testbed')

DESCRIPTION = """\
Online PMU-driven controlled islanding (Banna et al.): estimate rotor angles from PMU
phasors, group coherent generators with dynamic time warping, assign every bus to an
island by constrained spectral clustering, and command the breakers on the cut lines.

Start with:
  controlled-islanding demo                  replay the default IEEE 39 bag through the ROS 2 nodes
  controlled-islanding partition --case ieee39 --outage 16-17 --outage 1-2 \\
      --group 30,37,38 --group 31,32,33,34,35,36,39
                                             split a grid for given coherent groups
Run `controlled-islanding SUBCOMMAND --help` for each subcommand's options.
-q/--quiet shows only warnings and errors on stderr, -v/--verbose adds detail; either goes before or after
the subcommand.
"""


def _module_name(name: str) -> str:
    return f"controlled_islanding.commands.{name.replace('-', '_')}"  # serve-pmu lives in serve_pmu.py


def _load(name: str):
    return importlib.import_module(_module_name(name))


def _verbosity() -> argparse.ArgumentParser:
    # SUPPRESS: given after the subcommand, the subparser's value must not be overwritten by the main parser's default.
    common = argparse.ArgumentParser(add_help=False)
    group = common.add_mutually_exclusive_group()
    group.add_argument('-q', '--quiet', dest='log_level', action='store_const', const=logging.WARNING,
                       default=argparse.SUPPRESS, help='only warnings and errors on stderr')
    group.add_argument('-v', '--verbose', dest='log_level', action='store_const', const=logging.DEBUG,
                       default=argparse.SUPPRESS, help='more detail on stderr')
    return common


def build_parser(chosen: str | None = None) -> argparse.ArgumentParser:
    """Build the parser: every subcommand's help, or, with one chosen, only it and its arguments."""
    common = _verbosity()
    parser = argparse.ArgumentParser(
        prog='controlled-islanding', description=DESCRIPTION, parents=[common],
        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', metavar='SUBCOMMAND', required=True)
    # A chosen subcommand needs only its own module: a regression run starts one CLI process per bag.
    for name in (chosen,) if chosen else SUBCOMMANDS:
        try:
            module = _load(name)
        except ModuleNotFoundError as exc:
            if exc.name != _module_name(name):
                raise
            continue
        sp = sub.add_parser(name, help=module.HELP, description=module.DESCRIPTION, parents=[common],
                            formatter_class=argparse.RawDescriptionHelpFormatter)
        if chosen:
            module.add_arguments(sp)
    return parser


class _Formatter(logging.Formatter):
    """'<subcommand>: message', and 'warning:' or 'error:' before the message at those levels."""

    def __init__(self, command: str) -> None:
        super().__init__()
        self.command = command

    def format(self, record: logging.LogRecord) -> str:
        level = '' if record.levelno < logging.WARNING else f'{record.levelname.lower()}: '
        text = f'{self.command}: {level}{record.getMessage()}'
        if record.exc_info:
            text += '\n' + self.formatException(record.exc_info)
        return text


def configure_logging(command: str, level: int) -> None:
    """Send the package's log records to stderr at `level`, one line each (what the command line does)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter(command))
    package = logging.getLogger('controlled_islanding')
    package.handlers[:] = [handler]
    package.setLevel(level)
    package.propagate = False


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the process exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen = next((a for a in argv if a in SUBCOMMANDS), None)
    args = build_parser(chosen).parse_args(argv)
    configure_logging(args.command, getattr(args, 'log_level', logging.INFO))
    from tqdm.contrib.logging import logging_redirect_tqdm

    from controlled_islanding.commands import CliError
    from controlled_islanding.graph.rosenv import RosEnvError

    try:
        with logging_redirect_tqdm(loggers=[logging.getLogger('controlled_islanding')]):
            return int(_load(args.command).run(args) or 0)
    except (CliError, RosEnvError) as exc:
        print(f'controlled-islanding {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
