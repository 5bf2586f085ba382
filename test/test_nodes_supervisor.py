"""The supervisor stops every child it started: on leaving its block, on an error, on Ctrl-C, and if killed."""

from __future__ import annotations

import ast
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from controlled_islanding.supervisor import GRAPH, Supervisor, config_dir, node_command

REPO = Path(__file__).resolve().parents[1]
BUILD = REPO / 'build' / 'test_nodes' / 'supervisor'


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie has exited; only its parent has not reaped it yet.
    stat = Path(f'/proc/{pid}/stat')
    return stat.exists() and stat.read_text().split(')')[-1].split()[0] != 'Z'


def wait_dead(pids: list[int], timeout_s: float = 15.0) -> list[int]:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and any(alive(p) for p in pids):
        time.sleep(0.1)
    return [p for p in pids if alive(p)]


def test_launch_file_starts_the_supervisor_table():
    """launch/islanding.launch.py and supervisor.GRAPH name the same executables and parameter files."""
    tree = ast.parse((REPO / 'launch' / 'islanding.launch.py').read_text())
    launched = []
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, 'id', None) == 'Node':
            kw = {k.arg: k.value for k in call.keywords}
            files = [n.value for n in ast.walk(kw['parameters']) if isinstance(n, ast.Constant)
                     and str(n.value).endswith('.yaml')]
            launched.append((kw['executable'].value, tuple(files)))
    assert launched == [(s.executable, (s.params_file,)) for s in GRAPH]
    for spec in GRAPH:
        assert (config_dir() / spec.params_file).is_file()


def test_node_command_uses_the_parameter_file_and_overrides():
    argv = node_command(GRAPH[0], {'use_sim_time': True, 'x': 1.5})
    assert argv[argv.index('--params-file') + 1] == str(config_dir() / GRAPH[0].params_file)
    assert 'use_sim_time:=true' in argv and 'x:=1.5' in argv


@pytest.mark.ros
def test_an_error_inside_the_block_stops_every_child(ros_env):
    with pytest.raises(RuntimeError, match='boom'):
        with Supervisor(ros_env, BUILD / 'error') as sup:
            children = [sup.start(spec, {'audit_log': BUILD / 'audit.jsonl'}) for spec in GRAPH]
            time.sleep(1.0)
            assert all(c.poll() is None for c in children), 'a node died at start'
            raise RuntimeError('boom')
    assert wait_dead([c.pid for c in children]) == []
    assert all(c.returncode is not None for c in children)


SCRIPT = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from controlled_islanding.supervisor import GRAPH, Supervisor
    import os
    with Supervisor(dict(os.environ), Path(sys.argv[1])) as sup:
        audit = {'audit_log': Path(sys.argv[1]) / 'audit.jsonl'}
        print(' '.join(str(sup.start(spec, audit).pid) for spec in GRAPH), flush=True)
        while True:
            time.sleep(0.1)
""")


@pytest.mark.ros
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGKILL], ids=['ctrl_c', 'killed'])
def test_the_children_die_with_the_supervisor_process(ros_env, sig):
    parent = subprocess.Popen([sys.executable, '-c', SCRIPT, str(BUILD / sig.name)], env=ros_env,
                              stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(p) for p in parent.stdout.readline().split()]
        assert len(pids) == len(GRAPH)
        time.sleep(1.0)
        assert all(alive(p) for p in pids)
        parent.send_signal(sig)
        parent.wait(timeout=30)
        assert wait_dead(pids) == [], 'children outlived their supervisor'
    finally:
        if parent.poll() is None:
            parent.kill()
