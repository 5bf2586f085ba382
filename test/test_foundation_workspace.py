"""colcon and catkin_pkg (rosdep, bloom) find both packages of this repository in a native workspace.

Both crawlers stop descending at the first package.xml, so the root package hides msg_schemas/. The two
layouts the README gives are checked here with the real tools: a ~/ws/src workspace with msg_schemas
linked beside the clone, and this repository as the workspace root (colcon_defaults.yaml).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from catkin_pkg.packages import find_packages

REPO = Path(__file__).resolve().parents[1]
PACKAGES = {'controlled_islanding': 'ros.ament_python', 'controlled_islanding_msgs': 'ros.ament_cmake'}


def colcon_list(cwd: Path, log_base: Path) -> dict[str, str]:
    colcon = Path(sys.executable).with_name('colcon')
    out = subprocess.run([str(colcon), '--log-base', str(log_base), 'list'], cwd=cwd, capture_output=True,
                         text=True, timeout=120, check=True).stdout
    return {name: kind.strip('()') for name, _path, kind in (line.split('\t') for line in out.splitlines())}


@pytest.fixture
def workspace(tmp_path: Path) -> Path:
    """Make a ~/ws/src layout as the README sets it up: the clone, and msg_schemas linked beside it."""
    src = tmp_path / 'ws' / 'src'
    src.mkdir(parents=True)
    (src / 'controlled_islanding').symlink_to(REPO, target_is_directory=True)
    (src / 'controlled_islanding_msgs').symlink_to(Path('controlled_islanding') / 'msg_schemas',
                                                   target_is_directory=True)
    return src.parent


def test_catkin_pkg_finds_both_packages(workspace: Path) -> None:
    found = {pkg.name for pkg in find_packages(workspace / 'src').values()}
    assert found == set(PACKAGES)


def test_catkin_pkg_alone_misses_the_nested_package() -> None:
    # Why the link is needed: without it the crawler stops at the root package.xml.
    assert {pkg.name for pkg in find_packages(REPO).values()} == {'controlled_islanding'}


def test_colcon_lists_both_packages_in_a_workspace(workspace: Path, tmp_path: Path) -> None:
    assert colcon_list(workspace, tmp_path / 'log') == PACKAGES


def test_colcon_lists_both_packages_with_the_repository_as_workspace(tmp_path: Path) -> None:
    assert colcon_list(REPO, tmp_path / 'log') == PACKAGES
