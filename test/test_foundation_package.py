"""Static checks of the package: lint as ROS packages do, package.xml, and the launch file that cannot run here."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / 'launch' / 'islanding.launch.py'


def console_scripts() -> set[str]:
    """Names of the console scripts setup.py declares, read from the installed distribution."""
    from importlib.metadata import distribution

    return {ep.name for ep in distribution('controlled_islanding').entry_points if ep.group == 'console_scripts'}


def test_lint_flake8_and_pep257_rules_pass():
    """The ament_flake8 / ament_pep257 rule families, through ruff (config in ruff.toml)."""
    paths = [p for p in ('controlled_islanding', 'test', 'launch', 'tools', 'setup.py') if (REPO / p).exists()]
    result = subprocess.run([sys.executable, '-m', 'ruff', 'check', '--no-cache', *paths],
                            cwd=REPO, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_package_xml_is_format_3_ament_python_with_runtime_depends():
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'controlled_islanding'
    assert root.find('export/build_type').text == 'ament_python'
    exec_depends = {e.text for e in root.findall('exec_depend')}
    assert {'rclpy', 'controlled_islanding_msgs', 'diagnostic_msgs', 'python3-numpy', 'python3-scipy'} <= exec_depends
    msgs = ET.parse(REPO / 'msg_schemas' / 'package.xml').getroot()
    assert msgs.findtext('name') == 'controlled_islanding_msgs'
    assert msgs.findtext('member_of_group') == 'rosidl_interface_packages'


# rosdep keys of the Python modules the package imports; ROS packages are imported under their own names.
ROSDEP_KEY = {'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'sklearn': 'python3-sklearn',
              'networkx': 'python3-networkx', 'matplotlib': 'python3-matplotlib', 'yaml': 'python3-yaml',
              'cryptography': 'python3-cryptography', 'tqdm': 'python3-tqdm', 'rosbags': 'python3-rosbags-pip',
              'numba': 'python3-numba', 'pytest': 'python3-pytest'}
# No rosdep key exists for these: package.xml names them in a comment, and the README installs them with pip.
PIP_ONLY = {'pypower', 'dtaidistance', 'kmedoids', 'andes', 'pandapower'}


def imported_modules() -> set[str]:
    """Top-level third-party modules imported by the package and the launch file."""
    found = set()
    for path in [*(REPO / 'controlled_islanding').rglob('*.py'), LAUNCH]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found |= {a.name.split('.')[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split('.')[0])
    return {m for m in found if m not in sys.stdlib_module_names and m != 'controlled_islanding'}


def test_package_xml_declares_what_is_imported_and_nothing_unused():
    root = ET.parse(REPO / 'package.xml').getroot()
    declared = {e.text for e in root.findall('exec_depend')}
    comments = (REPO / 'package.xml').read_text()
    imported = imported_modules()
    for module in sorted(imported):
        if module in PIP_ONLY:
            assert module.lower() in comments.lower(), f'{module}: pip-only, but package.xml does not say so'
        else:
            assert ROSDEP_KEY.get(module, module) in declared, f'{module} is imported but not an exec_depend'
    unused = {key for module, key in ROSDEP_KEY.items() if key in declared and module not in imported}
    assert not unused, f'declared but never imported: {sorted(unused)}'


def test_every_msg_file_is_listed_in_cmakelists():
    cmake = (REPO / 'msg_schemas' / 'CMakeLists.txt').read_text()
    files = sorted(p.relative_to(REPO / 'msg_schemas').as_posix()
                   for p in (REPO / 'msg_schemas').glob('*/*') if p.suffix in ('.msg', '.srv'))
    listed = sorted(re.findall(r'"((?:msg|srv)/\w+\.(?:msg|srv))"', cmake))
    assert listed == files


def test_every_node_has_a_console_script_and_the_cli_too():
    scripts = console_scripts()
    nodes = {p.stem for p in (REPO / 'controlled_islanding' / 'nodes').glob('*.py') if p.stem != '__init__'}
    assert nodes, 'no node modules found'
    assert nodes <= scripts
    assert 'controlled-islanding' in scripts


def _launch_nodes() -> list[dict[str, object]]:
    """Keyword arguments of every Node(...) call in the launch file, as far as they are literals."""
    tree = ast.parse(LAUNCH.read_text())
    found = []
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, 'id', getattr(call.func, 'attr', None)) == 'Node':
            kwargs = {}
            for kw in call.keywords:
                kwargs[kw.arg] = [n.value for n in ast.walk(kw.value)
                                  if isinstance(n, ast.Constant) and isinstance(n.value, str)]
            found.append(kwargs)
    return found


def test_launch_file_starts_only_console_scripts_with_parameter_files_that_exist():
    """`launch` is not installable here, so check statically what `ros2 launch` would start."""
    compile(LAUNCH.read_text(), str(LAUNCH), 'exec')
    nodes = _launch_nodes()
    assert nodes, 'the launch file starts no Node'
    scripts = console_scripts()
    for kwargs in nodes:
        assert kwargs.get('package') == ['controlled_islanding'], kwargs
        (executable,) = kwargs['executable']
        assert executable in scripts, f'{executable} is not a console script'
        yaml_files = [s for s in kwargs.get('parameters', []) if s.endswith('.yaml')]
        assert yaml_files, f'{executable} names no parameter file'
        for name in yaml_files:
            assert (REPO / 'config' / Path(name).name).is_file(), f'{executable}: config/{Path(name).name} missing'
    launched = {kwargs['executable'][0] for kwargs in nodes}
    pipeline = {'pmu_ingestion', 'coherency', 'partitioning', 'breaker_command'}
    assert pipeline <= launched
