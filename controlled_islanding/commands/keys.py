"""`controlled-islanding keys`: make the signing keys breaker_command trusts."""

from __future__ import annotations

import argparse
from pathlib import Path

from controlled_islanding.commands import CliError
from controlled_islanding.locations import checkout
from controlled_islanding.safety import signing

HELP = "make the Ed25519 keys that sign decisions, arm/disarm requests and the monitor's islanding requests"
DESCRIPTION = """\
breaker_command acts only on signed messages (the ROS 2 wheels from PyPI have no DDS security, so
SROS2 cannot authenticate anyone on the domain). Three key pairs are used:

  partitioning.key / .pub   the partitioning node signs every islanding decision
  operator.key / .pub       an operator signs every arm and disarm request (and may sign islanding requests)
  monitor.key / .pub        the stability monitor signs its islanding requests

breaker_command needs the partitioning and operator public keys, partitioning those of its request_signers
(monitor, operator): a signed request that does not verify is refused. Private keys are written 0600 in a 0700
directory, never inside the repository. Existing keys are kept unless --force.

  controlled-islanding keys init              # into $CONTROLLED_ISLANDING_KEYS or ~/.config/controlled_islanding/keys
  controlled-islanding keys init /secure/keys # elsewhere; then set key_dir on the nodes
  controlled-islanding keys show              # print the key ids (fingerprints) the nodes log at start
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the keys arguments."""
    parser.add_argument('action', choices=('init', 'show'), help='init: make missing keys; show: print key ids')
    parser.add_argument('directory', nargs='?', type=Path, default=None,
                        help=f'key directory (default: {signing.default_key_dir()})')
    parser.add_argument('--force', action='store_true', help='replace existing keys (old signatures stop verifying)')


def run(args: argparse.Namespace) -> int:
    """Make or show the keys."""
    directory = args.directory or signing.default_key_dir()
    repo = checkout()
    if repo is not None and directory.resolve().is_relative_to(repo) and \
            not directory.resolve().is_relative_to(repo / 'build'):
        raise CliError(f'{directory} is inside the repository; keep private keys out of it')
    try:
        paths = signing.init_keys(directory, force=args.force) if args.action == 'init' else {
            role: signing.key_paths(directory, role) for role in signing.ROLES}
        for role, kp in paths.items():
            key_id = signing.fingerprint(signing.load_public_key(kp.public))
            print(f'{role:13s} key id {key_id}  private {kp.private}  public {kp.public}')
    except signing.SigningError as exc:
        raise CliError(str(exc)) from exc
    return 0
