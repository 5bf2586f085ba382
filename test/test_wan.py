"""Deployment across emulated hosts (controlled_islanding.wan, `replay --hosts`).

The default bag across three network namespaces over a delayed, lossy WAN reaches the manifest's decision and
breaker command, and no namespace can reach past the emulated WAN.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
from test_e2e_bags import ENTRIES, REPO, check_breaker_rules, check_decision, results_dir

from controlled_islanding import wan
from controlled_islanding.commands.demo import default_bag
from controlled_islanding.commands.replay import replay

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
