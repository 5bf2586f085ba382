"""The set-up script: a no-op when done, and never trusted after a failed interface build."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
VENV = REPO / '.venv'


def run_setup(root: Path, venv: Path) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(('VIRTUAL_ENV', 'PYTHONHOME'))}
    return subprocess.run(['bash', str(root / 'tools' / 'setup.sh')], env={**env, 'VENV': str(venv)},
                          capture_output=True, text=True)


def test_second_run_is_a_silent_no_op():
    stamp = VENV / '.setup-complete'
    before = stamp.stat().st_mtime_ns
    result = run_setup(REPO, VENV)
    assert result.returncode == 0, result.stderr
    assert result.stdout == '' and result.stderr == ''
    assert stamp.stat().st_mtime_ns == before


def link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:  # another file system
        shutil.copy2(src, dst)


@pytest.mark.slow
def test_broken_interface_stops_setup_naming_the_step_and_leaves_venv_untrusted(tmp_path):
    tree = tmp_path / 'clone'
    files = subprocess.run(['git', 'ls-files', '-z'], cwd=REPO, capture_output=True, check=True).stdout.split(b'\0')
    for name in filter(None, files):
        target = tree / name.decode()
        target.parent.mkdir(parents=True, exist_ok=True)
        if (REPO / name.decode()).is_file():
            shutil.copy2(REPO / name.decode(), target)
    # The finished venv, so only the interface stage runs again: hard links, as a copy of its 1.6 GB took 20 s.
    # The failed stage writes nothing into it; the stamp it removes is an unlink, which leaves VENV's own.
    venv = tree / '.venv'
    shutil.copytree(VENV, venv, symlinks=True, copy_function=link_or_copy)
    broken = tree / 'msg_schemas' / 'msg' / 'BranchStatus.msg'
    broken.write_text(broken.read_text() + 'no_such_pkg/NoSuchType field_of_unknown_type\n')

    for _ in range(2):  # and a rerun does not trust what the failed run left
        result = run_setup(tree, venv)
        assert result.returncode != 0
        assert "FAILED at step 'compile msg_schemas" in result.stderr, result.stderr
        assert not (venv / '.setup-complete').exists()
    assert (VENV / '.setup-complete').exists(), 'the hard-linked copy took the real venv down with it'
