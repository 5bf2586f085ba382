"""The package's layout rules (docs/architecture.md), checked.

The import-linter contracts in .importlinter, a root that holds only cli.py and two shared modules, thin command
modules, and one module that renames files over others.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'controlled_islanding'
LINT_IMPORTS = Path(sys.executable).with_name('lint-imports')


def _lint(root: Path) -> subprocess.CompletedProcess[str]:
    """Run lint-imports on the package under `root` with `root`'s .importlinter."""
    env = {**os.environ, 'PYTHONPATH': str(root)}
    return subprocess.run([str(LINT_IMPORTS), '--no-cache', str(root / '.importlinter')], cwd=root, env=env,
                          capture_output=True, text=True, timeout=120, check=False)


def test_import_linter_contracts_are_kept() -> None:
    result = _lint(REPO)
    assert result.returncode == 0, result.stdout + result.stderr
    assert re.search(r'Contracts: (\d+) kept, 0 broken', result.stdout), result.stdout
    assert int(re.search(r'Contracts: (\d+) kept', result.stdout).group(1)) >= 4, result.stdout


@pytest.mark.parametrize(('module', 'line', 'contract'), [
    ('core/dtw.py', 'import rclpy', 'never import rclpy'),
    ('wire/topics.py', 'import rclpy.qos', 'never import rclpy'),
    ('core/dtw.py', 'from controlled_islanding.nodes import coherency', 'Layers import only downward'),
    ('sim/pmu.py', 'from controlled_islanding.commands import CliError', 'Only cli.py imports commands/'),
    ('core/grid.py', 'from controlled_islanding.core import dtw', 'No import cycles'),
])
def test_a_broken_rule_fails_the_check_naming_its_contract(tmp_path: Path, module: str, line: str,
                                                           contract: str) -> None:
    """The contracts bite: one forbidden import added to a copy of the package breaks the named one."""
    shutil.copy(REPO / '.importlinter', tmp_path / '.importlinter')
    shutil.copytree(PACKAGE, tmp_path / 'controlled_islanding', ignore=shutil.ignore_patterns('__pycache__'))
    target = tmp_path / 'controlled_islanding' / module
    text = target.read_text()
    # After the module's own imports, so that a cycle closes through a module that imports the other already.
    target.write_text(text + f'\n{line}  # noqa\n')
    if 'cycles' in contract:
        dtw = tmp_path / 'controlled_islanding' / 'core' / 'dtw.py'
        dtw.write_text(dtw.read_text() + '\nfrom controlled_islanding.core import grid  # noqa\n')
    result = _lint(tmp_path)
    assert result.returncode != 0, result.stdout
    broken = [ln for ln in result.stdout.splitlines() if ln.endswith('BROKEN')]
    assert any(contract in ln for ln in broken), result.stdout


def test_the_root_holds_cli_and_at_most_two_shared_modules() -> None:
    root = sorted(p.name for p in PACKAGE.glob('*.py') if p.name not in {'__init__.py', 'cli.py'})
    assert len(root) <= 2, root


def test_every_command_module_is_at_most_250_lines() -> None:
    lengths = {p.name: len(p.read_text().splitlines()) for p in (PACKAGE / 'commands').glob('*.py')}
    assert lengths
    assert {n: k for n, k in lengths.items() if k > 250} == {}


def test_one_module_renames_files_over_others() -> None:
    """Every replace-a-file-whole goes through atomic.py, which fsyncs and cleans up on failure."""
    pattern = re.compile(r'\bos\.(replace|rename)\(|\.rename\(|shutil\.move\(')
    users = sorted(str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob('*.py')
                   if any(pattern.search(ln) for ln in p.read_text().splitlines() if not ln.lstrip().startswith('#')))
    assert users == ['atomic.py']
