"""`controlled-islanding`: the user-facing command line.

Each subcommand lives in controlled_islanding/commands/<name>.py and exposes
`HELP` (one line), `DESCRIPTION` (what it teaches in --help), `add_arguments(parser)`
and `run(args) -> int`. They are imported only when chosen, so `--help` is fast and
one subcommand's heavy imports (ANDES, rclpy) never slow another.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from controlled_islanding.graph.rosenv import RosEnvError

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
"""


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def _module_name(name: str) -> str:
    return f"controlled_islanding.commands.{name.replace('-', '_')}"  # serve-pmu lives in serve_pmu.py


def _load(name: str):
    return importlib.import_module(_module_name(name))


def build_parser(chosen: str | None = None) -> argparse.ArgumentParser:
    """Build the parser; only the chosen subcommand's module is imported for its arguments."""
    parser = argparse.ArgumentParser(
        prog='controlled-islanding', description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', metavar='SUBCOMMAND', required=True)
    for name in SUBCOMMANDS:
        try:
            module = _load(name)
        except ModuleNotFoundError as exc:
            if exc.name != _module_name(name):
                raise
            continue
        sp = sub.add_parser(name, help=module.HELP, description=module.DESCRIPTION,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
        if name == chosen or chosen is None:
            module.add_arguments(sp)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the process exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen = next((a for a in argv if a in SUBCOMMANDS), None)
    args = build_parser(chosen).parse_args(argv)
    try:
        return int(_load(args.command).run(args) or 0)
    except (CliError, RosEnvError) as exc:
        print(f'controlled-islanding {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print('interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    # Run the imported module, not this __main__ copy, so CliError raised by subcommands is the class caught here.
    from controlled_islanding.cli import main as imported_main

    sys.exit(imported_main())
