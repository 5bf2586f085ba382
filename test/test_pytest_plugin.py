"""The islanding_replay fixture users write their own bag tests with, and its pytest11 entry point."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from controlled_islanding.sim.manifest import manifest_entries

REPO = Path(__file__).resolve().parents[1]
KUNDUR = next((e for e in manifest_entries() if e['name'] == 'kundur_bus9_unstable'
               and (REPO / 'bags' / e['bag']).exists()), None)

USER_TEST = """
def test_the_fixture_comes_from_the_installed_package(islanding_replay, request):
    assert callable(islanding_replay)
    plugin = request.config.pluginmanager.get_plugin('controlled_islanding')
    assert plugin is not None and plugin.__name__ == 'controlled_islanding.harness.pytest_plugin'
"""


def test_the_package_metadata_registers_the_fixture_for_a_users_tests(tmp_path):
    """What `pip install` writes from setup.py makes pytest load the plugin in a project that never imports us."""
    subprocess.run([sys.executable, 'setup.py', '-q', 'egg_info', '--egg-base', str(tmp_path)], cwd=REPO,
                   check=True, capture_output=True)
    user = tmp_path / 'user_project'
    user.mkdir()
    (user / 'test_user.py').write_text(USER_TEST)
    env = {**os.environ, 'PYTHONPATH': os.pathsep.join([str(tmp_path), str(REPO)])}
    done = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider', 'test_user.py'], cwd=user,
                          env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


@pytest.mark.ros
@pytest.mark.skipif(KUNDUR is None, reason='bags/kundur_bus9_unstable is not present')
def test_a_bag_through_the_fixture_decides_as_the_manifest_says(islanding_replay, tmp_path_factory):
    result = islanding_replay(REPO / 'bags' / KUNDUR['bag'], record=False)
    expected = KUNDUR['expected_decision']
    assert result['split'] == expected['split']
    assert sorted(result['cut_branch_ids']) == sorted(expected['cut_branches'])
    opened = {c['branch_id'] for c in result['breaker_commands'] if c['action'] == 'open'}
    assert opened == set(expected['cut_branches'])
    # DDS hygiene: a private domain on loopback, the ROS logs beside the results in pytest's temporary folder.
    results = Path(result['results_dir'])
    assert results.resolve().is_relative_to(tmp_path_factory.getbasetemp().resolve())
    assert any((results / 'ros_log').iterdir()) and (results / 'breaker_audit.jsonl').exists()
