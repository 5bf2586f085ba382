"""Deployment across emulated hosts (controlled_islanding.graph.wan, `replay --hosts`).

The default bag across three network namespaces over a delayed, lossy WAN reaches the manifest's decision and
breaker command, and no namespace can reach past the emulated WAN.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import pytest
from nodes_harness import graph
from test_e2e_bags import ENTRIES, REPO, check_breaker_rules, check_decision, results_dir

from controlled_islanding.graph import wan
from controlled_islanding.graph.replay import replay
from controlled_islanding.graph.supervisor import GRAPH
from controlled_islanding.sim.manifest import default_bag
from controlled_islanding.wire.qos import DECISION_LEASE_S

UNAVAILABLE = wan.unavailable_reason()


def test_hosts_name_every_role_exactly_once():
    assert wan.parse_hosts('pdc,control,substation') == {
        'pdc': ('pdc',), 'control': ('control',), 'substation': ('substation',)}
    assert wan.parse_hosts('pdc+control,substation') == {'pdc+control': ('pdc', 'control'),
                                                          'substation': ('substation',)}
    for bad in ('pdc,control', 'pdc,control,substation,control', 'pdc,control,substation,grid', 'pdc,,control'):
        with pytest.raises(ValueError):
            wan.parse_hosts(bad)
    hosts = wan.parse_hosts('pdc+control,substation')
    assert wan.host_of(hosts, 'bag_player') == 'pdc+control'
    assert wan.host_of(hosts, 'breaker_command') == 'substation'
    assert wan.host_of(hosts, 'recorder') == wan.OPERATOR


def test_without_privileges_replay_hosts_says_so_in_one_line_and_exits_2():
    argv = [sys.executable, '-m', 'controlled_islanding.cli', 'replay', str(REPO / 'bags' / 'no-such-bag'),
            '--hosts', 'pdc,control,substation']
    if os.geteuid() == 0:
        if shutil.which('setpriv') is None:
            pytest.skip('running as root and setpriv (util-linux) is missing to drop the capabilities')
        argv = ['setpriv', '--bounding-set', '-all', '--inh-caps', '-all', '--', *argv]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and 'needs root' in lines[0], done.stderr


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.skipif(bool(UNAVAILABLE), reason=UNAVAILABLE or '')
@pytest.mark.skipif(not ENTRIES, reason='no bag of bags/index.yaml is present')
def test_default_bag_across_three_hosts_over_a_lossy_wan_reaches_the_manifest_decision():
    entry = default_bag()
    delay_ms, jitter_ms = 20.0, 5.0
    summary = replay(REPO / 'bags' / entry['bag'], results_dir('wan'), fast=True, figures=False, quiet=True,
                     record=False, hosts='pdc,control,substation',
                     link=wan.LinkModel(delay_ms=delay_ms, jitter_ms=jitter_ms, loss_pct=1.0, seed=0))
    check_decision(summary, entry)
    check_breaker_rules(summary, armed=True)
    assert summary['breaker_commands'] if entry['expected_decision']['split'] else True
    assert summary['restarts'] == [] and summary['hangs'] == []
    info = summary['wan']
    assert set(info['views']) == {'pdc', 'control', 'substation', wan.OPERATOR}
    for host, view in info['views'].items():
        # Each namespace's own tables, read inside it while the graph ran: only lo and the WAN's TUN device,
        # nothing routed anywhere else, no gateway, no IPv6.
        assert sorted(view['interfaces']) == ['lo', wan.DEVICE], host
        for route in view['routes']:
            words = route.split()
            assert words[words.index('dev') + 1] in ('lo', wan.DEVICE) and 'via' not in words, (host, route)
            assert words[0] != 'default', (host, route)
        assert view['routes_ipv6'] == [], host
    pairs = info['stats']['pairs']
    for path in ('pdc->control', 'control->substation', 'operator->substation'):
        assert pairs[path]['packets'] > 0, path
    assert sum(p['dropped'] for p in pairs.values()) > 0, 'the 1 % loss dropped nothing'
    assert info['stats']['unroutable'] == 0
    # The request crosses pdc -> control and the decision control -> substation: two one-way delays at least.
    assert summary['latency_request_to_command_ms'] >= 2 * (delay_ms - jitter_ms)
    assert not [n for n in wan.our_namespaces() if n.startswith(f'{wan.NAME_PREFIX}{os.getpid()}-')]


# A control centre reduced to its decision writer (partitioning's QoS), in a process of its own.
CONTROL_CENTRE = """
import rclpy
from controlled_islanding_msgs.msg import IslandingDecision
from controlled_islanding.wire import topics
from controlled_islanding.ros.endpoints import qos_for
rclpy.init()
node = rclpy.create_node('partitioning')
node.create_publisher(IslandingDecision, topics.relative(topics.ISLANDING_DECISION), qos_for(topics.ISLANDING_DECISION))
rclpy.spin(node)
"""


@pytest.mark.ros
def test_breaker_reports_a_control_centre_gone_silent_by_liveliness(tmp_path):
    breaker = next(s for s in GRAPH if s.executable == 'breaker_command')
    with graph('liveliness', [(breaker, {'audit_log': tmp_path / 'audit.jsonl'})]) as (sup, probe):
        control = subprocess.Popen([sys.executable, '-c', CONTROL_CENTRE], env=sup.env)
        try:
            status = lambda: probe.diagnostics.get('breaker_command', {})  # noqa: E731
            assert probe.spin_until(lambda: status().get('decision_writers_alive') == '1', 30.0), status()
            probe.spin_for(DECISION_LEASE_S)  # alive and asserting: no alarm
            assert 'warn.control_centre_silent' not in status()
            control.kill()  # no clean goodbye: only the lease running out tells
            control.wait()
            killed = time.monotonic()
            assert probe.spin_until(lambda: 'warn.control_centre_silent' in status(), 15.0), status()
            # Within the lease of the last assertion, plus the diagnostics' way to us on a loaded machine.
            assert time.monotonic() - killed <= DECISION_LEASE_S + 3.0
            assert probe.levels['breaker_command'][0] == b'\x01'  # WARN
            assert status()['decision_writers_alive'] == '0'
        finally:
            if control.poll() is None:
                control.kill()
                control.wait()
