"""Where the package's files are: the checkout it runs from, else its installed share directory.

A checkout is the package beside package.xml and msg_schemas/ (the source tree, or an editable install of it).
Installed, the share directory is found through the ament index, as ROS 2 tools find it (AMENT_PREFIX_PATH,
set by a sourced workspace), else under this interpreter's prefix (a pip install into a venv, which sets no
AMENT_PREFIX_PATH). Bags and build products live only in a checkout; installed, the build tree is the
current directory's build/.
"""

from __future__ import annotations

import os
import sys
from functools import cache
from pathlib import Path

PACKAGE = 'controlled_islanding'


class LocationError(FileNotFoundError):
    """A file or folder the package needs is in none of the places it looks."""


@cache
def checkout() -> Path | None:
    """Return the source tree this package runs from, or None when it runs installed."""
    root = Path(__file__).resolve().parent.parent
    return root if (root / 'package.xml').is_file() and (root / 'msg_schemas').is_dir() else None


@cache
def share_dir() -> Path:
    """Return the checkout, else the installed share/controlled_islanding."""
    root = checkout()
    if root is not None:
        return root
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        return Path(get_package_share_directory(PACKAGE))
    except (ImportError, LookupError, OSError, PackageNotFoundError):  # no index, or the package is not in it
        return Path(sys.prefix) / 'share' / PACKAGE


def _existing(name: str) -> Path:
    path = share_dir() / name
    if not path.is_dir():
        raise LocationError(f'{name}/ not found in {share_dir()} (the checkout, else the installed share of '
                            f'{PACKAGE})')
    return path


def config_dir() -> Path:
    """Return config/, the nodes' parameter files.

    Raises:
        LocationError: It is not there.

    """
    return _existing('config')


def schema_dir() -> Path:
    """Return msg_schemas/, the one definition of every message type.

    Raises:
        LocationError: It is not there.

    """
    return _existing('msg_schemas')


def bags_dir() -> Path:
    """Return bags/, the scenarios, their bags and the manifest (a checkout's; may not exist when installed)."""
    return share_dir() / 'bags'


def manifest_path() -> Path:
    """Return bags/index.yaml, the manifest of the scenario bags."""
    return bags_dir() / 'index.yaml'


def build_dir() -> Path:
    """Return the build tree: $CONTROLLED_ISLANDING_BUILD, else the checkout's build/, else ./build."""
    explicit = os.environ.get('CONTROLLED_ISLANDING_BUILD')
    if explicit:
        return Path(explicit)
    root = checkout()
    return (root if root is not None else Path.cwd()) / 'build'
