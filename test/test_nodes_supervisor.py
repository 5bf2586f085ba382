"""The supervisor stops every child it started, and restarts a pipeline node that dies or hangs.

It stops them on leaving its block, on an error, on Ctrl-C and if killed. A node that dies or hangs is restarted
with its parameters, after a backoff, and the restart is recorded.
"""

from __future__ import annotations

import ast
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from nodes_harness import ctrl_c_as_at_a_terminal, graph

from controlled_islanding.graph.supervisor import (
    GRAPH,
    MONITOR,
    NodeSpec,
    RestartRecord,
    Supervisor,
    SupervisorError,
    node_command,
)
from controlled_islanding.graph.watchdog import RestartPolicy, Watchdog
from controlled_islanding.locations import config_dir

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
            # Every node in the launch's namespace, following its clock topic, as a namespaced replay's graph.
            assert getattr(kw.get('namespace'), 'id', None) == 'namespace', kw['executable'].value
            assert getattr(kw.get('remappings'), 'id', None) == 'clock', kw['executable'].value
    assert launched == [(s.executable, (s.params_file,)) for s in (*GRAPH, MONITOR)]
    declared = {call.args[0].value for call in ast.walk(tree) if isinstance(call, ast.Call)
                and getattr(call.func, 'id', None) == 'DeclareLaunchArgument'}
    assert {'use_sim_time', 'namespace', 'clock'} <= declared
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


# The script restores Python's Ctrl-C handler: a shell that starts a job in the background (`cmd &`) ignores
# SIGINT for all its descendants, and Python keeps an ignored SIGINT ignored.
SCRIPT = textwrap.dedent("""
    import signal, sys, time
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from pathlib import Path
    from controlled_islanding.graph.supervisor import GRAPH, Supervisor
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


def test_a_node_that_keeps_dying_is_restarted_with_backoff_then_given_up_on():
    """A module that does not exist dies at once, every time: three restarts 0.1, 0.2, 0.4 s apart, then an error."""
    missing = NodeSpec('no_such_node', GRAPH[0].params_file)
    policy = RestartPolicy(nodes=frozenset({missing.executable}), backoff_initial_s=0.1, max_restarts=3)
    with Supervisor(dict(os.environ), BUILD / 'give_up' / str(time.time_ns()), policy) as sup:
        first = sup.start(missing)
        end = time.monotonic() + 30.0
        with pytest.raises(SupervisorError, match='no_such_node exited with status 1.*3 restarts.*giving up'):
            while time.monotonic() < end:
                sup.supervise()
                time.sleep(0.01)
    assert [r.cause for r in sup.restarts] == ['exited'] * 4 and [r.exit_status for r in sup.restarts] == [1] * 4
    assert sup.restarts[0].pid == first.pid and sup.restarts[-1].new_pid is None
    assert all('No module named' in r.log_tail for r in sup.restarts)
    waits = [r.restarted_after_s - r.failed_after_s for r in sup.restarts[:3]]
    # The backoff is a lower bound: on a loaded machine a restart may come later, never sooner.
    assert all(w >= want - 0.01 for w, want in zip(waits, (0.1, 0.2, 0.4), strict=True)), waits
    assert sup.hangs == []


def watch(sup: Supervisor, probe, policy: RestartPolicy) -> dict[str, float]:
    """Watch the supervisor's children under policy; return the heartbeat times the probe keeps, by node."""
    from diagnostic_msgs.msg import DiagnosticArray

    from controlled_islanding.ros.endpoints import qos_for
    from controlled_islanding.wire import topics

    beats: dict[str, float] = {}
    sup.watchdog = Watchdog(policy)

    def on_diag(msg: DiagnosticArray) -> None:
        beats.update({status.name: time.monotonic() for status in msg.status})

    probe.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diag, qos_for(topics.DIAGNOSTICS))
    return beats


def parameter(probe, node: str, name: str) -> float:
    """Ask a running node for a double parameter through its parameter service."""
    from rcl_interfaces.srv import GetParameters

    return probe.call(GetParameters, f'/{node}/get_parameters', GetParameters.Request(names=[name])).values[0]\
        .double_value


def supervise_until(sup: Supervisor, probe, beats: dict[str, float], done, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while not done() and time.monotonic() < end:
        probe.spin_for(0.02)
        sup.supervise(beats)
    return done()


ROS_POLICY = RestartPolicy(nodes=frozenset({'pmu_ingestion'}), backoff_initial_s=0.5, max_restarts=2,
                           hang_timeout_s=2.0, startup_grace_s=30.0)


@pytest.mark.ros
def test_a_killed_node_is_restarted_with_the_same_parameters_and_answers_again():
    with graph('supervisor_restart', []) as (sup, probe):
        beats = watch(sup, probe, ROS_POLICY)
        old = sup.start(GRAPH[0], {'max_delay_s': 0.75})
        assert supervise_until(sup, probe, beats, lambda: '/pmu_ingestion' in beats, 30.0), 'no first heartbeat'
        assert parameter(probe, 'pmu_ingestion', 'max_delay_s') == 0.75
        os.kill(old.pid, signal.SIGKILL)
        killed_s = time.monotonic()
        assert supervise_until(sup, probe, beats, lambda: sup.restarts and sup.restarts[0].new_pid
                               and beats['/pmu_ingestion'] > killed_s + 0.5, 30.0), 'not restarted'
        record = sup.restarts[0]
        assert (record.name, record.cause, record.exit_status, record.pid) == ('pmu_ingestion', 'exited', -9, old.pid)
        assert record.new_pid == sup.children['pmu_ingestion'].pid != old.pid
        assert parameter(probe, 'pmu_ingestion', 'max_delay_s') == 0.75
        assert sup.hangs == [] and len(sup.restarts) == 1


@pytest.mark.ros
def test_a_stopped_node_is_reported_hung_killed_and_restarted():
    with graph('supervisor_hang', []) as (sup, probe):
        beats = watch(sup, probe, ROS_POLICY)
        old = sup.start(GRAPH[0])
        try:
            assert supervise_until(sup, probe, beats, lambda: '/pmu_ingestion' in beats, 30.0), 'no first heartbeat'
            os.kill(old.pid, signal.SIGSTOP)
            stopped_s = time.monotonic()
            assert supervise_until(sup, probe, beats, lambda: sup.hangs, 10.0), 'the stopped node was not found hung'
            found_after_s = time.monotonic() - stopped_s
            assert not alive(old.pid), 'the hung node was not killed'
            assert supervise_until(sup, probe, beats, lambda: sup.restarts[0].new_pid
                                   and beats['/pmu_ingestion'] > stopped_s + found_after_s, 30.0), 'not restarted'
        finally:
            if alive(old.pid):  # never leave a stopped process behind, whatever failed
                os.kill(old.pid, signal.SIGKILL)
        hang, record = sup.hangs[0], sup.restarts[0]
        assert (hang.name, hang.pid) == ('pmu_ingestion', old.pid)
        assert ROS_POLICY.hang_timeout_s < hang.silent_s < ROS_POLICY.hang_timeout_s + 1.5
        assert found_after_s < ROS_POLICY.hang_timeout_s + 1.0  # the last heartbeat came up to 1 s before the stop
        assert (record.cause, record.exit_status, record.pid) == ('hung', -signal.SIGKILL, old.pid)
        assert len(sup.hangs) == len(sup.restarts) == 1
        new = sup.children['pmu_ingestion']
    assert wait_dead([old.pid, new.pid]) == []


RECORD = {'name': 'coherency', 'cause': 'hung', 'reason': 'coherency hung: no heartbeat for 5.2 s; restart in 0.5 s',
          'exit_status': -9, 'pid': 4242, 'failed_after_s': 12.0, 'failed_utc': '2025-01-01T00:00:00.000+00:00',
          'log_tail': '', 'restarted_after_s': 12.5, 'new_pid': 4343}


def test_a_clean_replay_reports_no_restarts_and_keeps_its_output(tmp_path):
    from controlled_islanding.graph.observer import Observation
    from controlled_islanding.graph.summary import graph_failure, render, summarize

    summary = summarize(tmp_path / 'bag', tmp_path, Observation(), {})
    assert summary['restarts'] == [] and summary['hangs'] == []
    assert graph_failure(summary) is None and 'FAILED' not in render(summary)


@pytest.mark.parametrize('json_out', [False, True], ids=['text', 'json'])
def test_a_replay_whose_graph_lost_a_node_exits_non_zero_with_one_line_why(monkeypatch, capsys, tmp_path, json_out):
    import argparse

    from controlled_islanding.commands import replay
    from controlled_islanding.graph.observer import Observation
    from controlled_islanding.graph.summary import graph_failure, summarize

    summary = summarize(tmp_path / 'bag', tmp_path, Observation(restarts=[RestartRecord(**RECORD)]), {})
    monkeypatch.setattr(replay, 'replay', lambda *args, **kwargs: summary)
    parser = argparse.ArgumentParser()
    replay.add_arguments(parser)
    assert replay.run(parser.parse_args([str(tmp_path / 'bag')] + (['--json'] if json_out else []))) == 1
    out, err = capsys.readouterr()
    why = graph_failure(summary)
    assert why == 'graph not healthy during the replay: coherency hung (restarted); see restarts in summary.json ' \
                  'and the node logs'
    assert (json_out and err.strip() == f'replay: FAILED: {why}') or f'FAILED: {why}' in out.splitlines()


def children_of(pid: int) -> dict[str, int]:
    """Return the node processes a process started, by node module name."""
    found = {}
    for stat in Path('/proc').glob('[0-9]*/stat'):
        try:
            fields = stat.read_text().rsplit(')', 1)[1].split()
            argv = (stat.parent / 'cmdline').read_bytes().split(b'\0')
        except OSError:
            continue
        if int(fields[1]) == pid and b'-m' in argv:
            module = argv[argv.index(b'-m') + 1].decode()
            if module.startswith('controlled_islanding.nodes.'):
                found[module.rsplit('.', 1)[1]] = int(stat.parent.name)
    return found


@pytest.mark.ros
def test_the_replay_cli_fails_loudly_when_a_node_died_during_it():
    """breaker_command is killed as the bag starts: the replay still ends, lists it and exits 1."""
    from controlled_islanding.sim.manifest import default_bag

    bag = REPO / 'bags' / default_bag()['bag']
    if not bag.exists():
        pytest.skip(f'{bag} is not present')
    results = BUILD / 'replay_killed' / str(time.time_ns())
    cli = subprocess.Popen([sys.executable, '-m', 'controlled_islanding.cli', 'replay', str(bag), '--fast', '--json',
                            '--no-figures', '--no-record', '--timeout', '60', '--results', str(results)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        end = time.monotonic() + 60.0
        # The player starts with the graph; the replay tells it to play through this file once the graph is wired.
        while not (results / 'player_go.json').exists() and cli.poll() is None and time.monotonic() < end:
            time.sleep(0.05)
        victim = children_of(cli.pid).get('breaker_command')
        assert victim is not None, 'the replay did not get as far as playing the bag'
        os.kill(victim, signal.SIGKILL)
        out, err = cli.communicate(timeout=90)
    finally:
        if cli.poll() is None:
            cli.send_signal(signal.SIGINT)
            cli.wait(timeout=30)
    assert cli.returncode == 1, err
    summary = json.loads(out)
    assert [(r['name'], r['cause'], r['exit_status'], r['pid']) for r in summary['restarts']] == \
        [('breaker_command', 'exited', -9, victim)]
    assert summary['hangs'] == []
    assert err.strip().splitlines()[-1].startswith('replay: FAILED: graph not healthy during the replay: '
                                                   'breaker_command exited with status -9')
    assert json.loads((results / 'summary.json').read_text())['restarts'] == summary['restarts']


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['ctrl_c', 'sigterm'])
def test_an_interrupted_replay_says_so_in_its_results_and_leaves_no_node(sig):
    """Interrupted while the bag plays in real time: no summary, a marker saying why, every node ended."""
    from controlled_islanding.sim.manifest import default_bag

    bag = REPO / 'bags' / default_bag()['bag']
    if not bag.exists():
        pytest.skip(f'{bag} is not present')
    results = BUILD / 'replay_interrupted' / str(time.time_ns())
    cli = subprocess.Popen([sys.executable, '-m', 'controlled_islanding.cli', 'replay', str(bag), '--isolate',
                            '--no-figures', '--no-record', '--timeout', '60', '--results', str(results)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                           preexec_fn=ctrl_c_as_at_a_terminal)
    nodes: dict[str, int] = {}
    try:
        end = time.monotonic() + 60.0
        while not (results / 'player_go.json').exists() and cli.poll() is None and time.monotonic() < end:
            time.sleep(0.05)
        nodes = children_of(cli.pid)
        assert len(nodes) >= 4, f'the replay did not get as far as playing the bag: {nodes}'
        cli.send_signal(sig)
        _, err = cli.communicate(timeout=60)
    finally:
        if cli.poll() is None:
            cli.kill()
            cli.wait(timeout=30)
    assert cli.returncode != 0, err
    marker = json.loads((results / 'INTERRUPTED.json').read_text())
    assert marker['bag'] == str(bag) and marker['interrupted_utc']
    assert not (results / 'summary.json').exists()
    left = [name for name, pid in nodes.items() if alive(pid)]
    assert not left, f'nodes outlived the interrupted replay: {left}'


# A node that forked a helper into its process group, as andes.load's code generation pool did inside grid_sim
# (until b5e904f): the shell's background `sleep` ignores SIGINT, as such a worker may.
GROUP_SCRIPT = textwrap.dedent("""
    import os, signal, sys, time
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from pathlib import Path
    from controlled_islanding.graph.supervisor import GRAPH, Supervisor
    with Supervisor(dict(os.environ), Path(sys.argv[1])) as sup:
        node = sup.start(GRAPH[0], prefix=['sh', '-c', 'sleep 300 & exec "$@"', 'sh'])
        print(node.pid, flush=True)
        while True:
            time.sleep(0.1)
""")


def group_of(pgid: int) -> list[int]:
    return [int(s.parent.name) for s in Path('/proc').glob('[0-9]*/stat')
            if alive(int(s.parent.name)) and _pgid(s) == pgid]


def _pgid(stat: Path) -> int | None:
    try:
        return int(stat.read_text().rsplit(')', 1)[1].split()[2])
    except (OSError, IndexError, ValueError):
        return None


@pytest.mark.ros
@pytest.mark.parametrize('sigs', [(signal.SIGINT,), (signal.SIGTERM,), (signal.SIGINT, signal.SIGINT)],
                         ids=['ctrl_c', 'sigterm', 'ctrl_c_twice'])
def test_what_a_node_forked_dies_with_it_when_its_supervisor_is_interrupted(ros_env, sigs):
    # Twice: the second Ctrl-C comes while the supervisor waits for the helper, which ignores the first.
    parent = subprocess.Popen([sys.executable, '-c', GROUP_SCRIPT, str(BUILD / f'group_{len(sigs)}_{sigs[0].name}')],
                              env=ros_env, stdout=subprocess.PIPE, text=True)
    group: list[int] = []
    try:
        node = int(parent.stdout.readline())
        end = time.monotonic() + 10.0
        while time.monotonic() < end and len(group) < 2:
            group = group_of(node)
            time.sleep(0.1)
        assert node in group and len(group) == 2, f'the node and its helper did not both start: {group}'
        for sig in sigs:
            parent.send_signal(sig)
            time.sleep(1.0)
        parent.wait(timeout=20)
        assert wait_dead(group, timeout_s=5.0) == [], 'a process of the node outlived its interrupted supervisor'
    finally:
        for pid in [p for p in group if alive(p)] + ([parent.pid] if parent.poll() is None else []):
            os.kill(pid, signal.SIGKILL)
