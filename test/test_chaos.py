"""Faults in the loop (issue 29): seeded faults in closed-loop testbed runs, and the judge of their commands.

The closed-loop runs are real: grid_sim simulating in ANDES, the four nodes as processes under the supervisor,
the fault done to a process this test started. The sweep over many seeds is `testbed --chaos` (docs/nodes.md).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from controlled_islanding.evaluation.chaos_report import opened_text, reasoned, verdict
from controlled_islanding.graph import wan
from controlled_islanding.graph.chaos import KINDS, OFFSET_S, TARGETS, Fault, partition_hosts, plan_fault
from controlled_islanding.graph.testbed import TestbedSettings
from controlled_islanding.harness.chaos_sweep import answer_to, chaos_run, judge
from controlled_islanding.sim.bag import START_TIME_UNIX_S

REPO = Path(__file__).resolve().parents[1]
BUILD = REPO / 'build'
UNAVAILABLE = wan.unavailable_reason()


def test_a_seed_is_one_fault_anywhere_and_a_partition_needs_the_control_and_substation_hosts_apart():
    three = wan.parse_hosts('pdc,control,substation')
    faults = [plan_fault(seed, three) for seed in range(200)]
    assert faults == [plan_fault(seed, three) for seed in range(200)]  # from the seed alone
    assert {f.kind for f in faults} == set(KINDS)
    assert all(-OFFSET_S <= f.offset_s <= OFFSET_S for f in faults)
    assert {f.target for f in faults if f.kind in ('kill', 'stop')} == set(TARGETS)
    assert {f.target for f in faults if f.kind == 'partition'} == {'control|substation'}
    assert {f.target for f in faults if f.kind == 'clock_step'} == set(three)  # a host's clock
    assert any(f.step_s < 0 for f in faults) and any(f.step_s > 0 for f in faults)
    # Stops and partitions both shorter and longer than the watchdog's 10 s hang limit.
    stops = [f.duration_s for f in faults if f.kind == 'stop']
    assert min(stops) < 10.0 < max(stops)
    # On one host, or with control and substation on one host, there is no WAN between them to cut.
    for hosts in (None, wan.parse_hosts('pdc,control+substation')):
        assert partition_hosts(hosts) is None
        assert 'partition' not in {plan_fault(seed, hosts).kind for seed in range(200)}
    assert {plan_fault(seed).target for seed in range(200) if plan_fault(seed).kind == 'clock_step'} <= set(TARGETS)
    assert partition_hosts(wan.parse_hosts('pdc+control,substation')) == ('pdc+control', 'substation')


def _decision(island: dict[int, int], cut: list[str], request_id: str, request_s: float, key: object,
              sign: bool = True) -> object:
    from controlled_islanding.core.grid import Branch
    from controlled_islanding.harness.breaker_soak import decision_msg
    from controlled_islanding.safety import signing

    branches = [Branch(c, *map(int, c.split('-'))) for c in cut]
    msg = decision_msg(island, branches, int((START_TIME_UNIX_S + request_s) * 1e9), key=key, sign=False)
    msg.request_id = request_id
    if sign:
        msg.key_id = signing.fingerprint(key)
        msg.signature = signing.sign(key, signing.decision_payload(msg))
    return msg


def test_the_judge_finds_each_unsafe_command_from_outside_the_node(tmp_path):
    """IEEE 14, G1's island cut by 1-2 and 1-5: one safe run, then each breaker rule broken once."""
    from controlled_islanding_msgs.msg import BreakerCommand

    from controlled_islanding.safety import signing
    from controlled_islanding.sim.scenario import load_scenario

    scenario = load_scenario(REPO / 'bags' / 'ieee14_g1_unstable.yaml')
    key_dir = Path(os.environ['CONTROLLED_ISLANDING_KEYS'])
    signing.init_keys(key_dir)
    key = signing.load_private_key(signing.key_paths(key_dir, 'partitioning').private)
    rid = 'ieee14/closed-loop-request-1'
    island = {b: 0 if b == 1 else 1 for b in range(1, 15)}
    good = _decision(island, ['1-2', '1-5'], rid, scenario.request_s, key)
    unsigned = _decision(island, ['1-2', '1-5'], rid, scenario.request_s, key, sign=False)

    def command_record(msg: object, breakers: list[str]) -> dict:
        return {'event': 'command', 'decision_id': msg.decision_id, 'request_stamp_s': scenario.request_s,
                'commands': [{'command_id': f'{msg.decision_id}/{b}', 'breaker_id': b, 'branch_id': b[3:]}
                             for b in breakers]}

    def run(records: list[dict], decisions: list, received_sim_s: float = 2.0, published: list | None = None) -> dict:
        audit = tmp_path / f'audit-{time.monotonic_ns()}.jsonl'
        audit.write_text(''.join(json.dumps(r) + '\n' for r in records))
        commands = [c for r in records if r['event'] == 'command' for c in r['commands']]
        seen = [BreakerCommand(command_id=c['command_id'], decision_id=c['command_id'].split('/')[0],
                               breaker_id=c['breaker_id'], branch_id=c['branch_id'])
                for c in (commands if published is None else published)]
        obs = SimpleNamespace(decision_log=[(0.0, d) for d in decisions], commands=[(0.0, c) for c in seen],
                              restarts=[], hangs=[], raised={})
        events = [{'what': 'command', 'command_id': c.command_id, 'decision_id': c.decision_id,
                   'received_sim_s': received_sim_s} for c in seen]
        report = {'request_id': rid, 'events': events,
                  'outcome': {'load_served_mw': 0.0, 'load_served_pct': 0.0, 'all_survived': False,
                              'simulation_failed': None, 'request_to_opening_s': None}}
        return judge(scenario, obs, report, audit)

    armed = [{'event': 'start'}, {'event': 'armed'}]
    safe = run([*armed, command_record(good, ['CB-1-2', 'CB-1-5'])], [good])
    assert safe['unsafe'] == [] and safe['answer']['kind'] == 'commanded' and reasoned(safe)
    broken = {
        'while disarmed': run([{'event': 'start'}, command_record(good, ['CB-1-2', 'CB-1-5'])], [good]),
        'unsigned': run([*armed, command_record(unsigned, ['CB-1-2', 'CB-1-5'])], [unsigned]),
        'not the boundary': run([*armed, command_record(good, ['CB-1-2'])], [good]),
        'twice': run([*armed, command_record(good, ['CB-1-2', 'CB-1-5']), command_record(good, ['CB-1-2'])], [good]),
        'stale on the grid clock': run([*armed, command_record(good, ['CB-1-2', 'CB-1-5'])], [good],
                                       received_sim_s=scenario.request_s + 2.0),
        'not audited': run(armed, [good], published=[{'command_id': f'{good.decision_id}/CB-1-2',
                                                      'breaker_id': 'CB-1-2', 'branch_id': '1-2'}]),
    }
    for rule, result in broken.items():
        assert result['unsafe'], rule
    assert 'disarmed' in ' '.join(broken['while disarmed']['unsafe'])
    assert 'after its request' in ' '.join(broken['stale on the grid clock']['unsafe'])


def test_an_answer_is_a_decision_a_reasoned_refusal_or_said_to_be_neither():
    decisions = [{'decision_id': 'd1', 'request_id': 'r', 'status': 'REFUSED_STALE_GROUPS', 'detail': 'no groups'},
                 {'decision_id': 'd2', 'request_id': 'r', 'status': 'SPLIT', 'detail': ''},
                 {'decision_id': 'd3', 'request_id': 'other', 'status': 'SPLIT', 'detail': ''}]
    refused = [{'event': 'refusal', 'decision_id': 'd2', 'reason': 'not_armed', 'detail': 'node is disarmed'}]
    assert answer_to('r', decisions[:1], []) == {
        'kind': 'refused', 'reason': 'partitioning REFUSED_STALE_GROUPS: no groups', 'answers': [
            {'decision_id': 'd1', 'status': 'REFUSED_STALE_GROUPS', 'kind': 'refused',
             'reason': 'partitioning REFUSED_STALE_GROUPS: no groups'}]}
    two = answer_to('r', decisions, refused)
    assert (two['kind'], two['reason']) == ('refused', 'breaker_command not_armed: node is disarmed')
    assert len(two['answers']) == 2  # a restarted partitioning's second answer to the request is listed
    unheard = answer_to('r', decisions[1:2], [])
    assert unheard['kind'] == 'unheard'
    # Unheard with no reason the run can name is neither a decision carried out nor a reasoned refusal; a breaker
    # node restarted meanwhile, or a partition it reported, is the reason.
    run = {'answer': unheard, 'restarts': [], 'raised': {}, 'chaos': None}
    assert (verdict(run), reasoned(run)) == ('unheard', False)
    restarted = dict(run, restarts=[{'name': 'breaker_command', 'cause': 'hung'}])
    assert (verdict(restarted), reasoned(restarted)) == ('not delivered', True)
    assert verdict(dict(run, restarts=[{'name': 'coherency', 'cause': 'exited'}])) == 'unheard'
    cut = dict(run, chaos={'fault': {'kind': 'partition'}},
               raised={'/breaker_command warn.control_centre_silent': 'no live decision writer'})
    assert verdict(cut) == 'not delivered' and verdict(dict(cut, raised={})) == 'unheard'
    assert answer_to('r', [], [])['kind'] == 'none'
    assert not reasoned({'answer': answer_to('r', [], []), 'restarts': [], 'raised': {}, 'chaos': None})
    commanded = answer_to('r', decisions, [{'event': 'command', 'decision_id': 'd2', 'commands': [{}, {}]}])
    assert (commanded['kind'], commanded['reason']) == ('commanded', '2 breakers')
    # Commanded, but its opening (charged with the wall time held at the request) fell after the run's end.
    events = [{'what': 'switching event', 'at_s': 11.627, 'branch_ids': ['7-8']}]
    assert opened_text({'opened': [], 'events': events}) == 'none: due at 11.63 s (sim), after the run ended'
    assert opened_text({'opened': ['7-8'], 'events': events + [{'what': 'opened', 'branch_id': '7-8'}]}) == '7-8'
    assert opened_text({'opened': [], 'events': []}) == 'none'


@pytest.mark.skipif(bool(UNAVAILABLE), reason=UNAVAILABLE or '')
def test_a_wan_partition_cuts_two_hosts_both_ways_until_healed(tmp_path):
    """UDP datagrams between two emulated hosts: through, cut while partitioned (both ways), through again."""
    # Per line on stdin: 'send TOKEN' sends it to the other host; 'recv' prints what came within 0.3 s.
    peer = ('import socket, sys\n'
            's = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind((sys.argv[1], 9999)); s.settimeout(0.3)\n'
            'for line in sys.stdin:\n'
            '    if line.startswith("send"): s.sendto(line.split()[1].encode(), (sys.argv[2], 9999)); continue\n'
            '    got = []\n'
            '    try:\n'
            '        while True: got.append(s.recvfrom(64)[0].decode())\n'
            '    except OSError: print(" ".join(got), flush=True)\n')
    with wan.EmulatedWan(['control', 'substation'], wan.LinkModel(), tmp_path) as net:
        ends = {}
        for here, there in (('control', 'substation'), ('substation', 'control')):
            ends[here] = subprocess.Popen([*net.prefix(here), sys.executable, '-c', peer, net.addresses[here],
                                           net.addresses[there]], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                          text=True)

        def say(host: str, line: str) -> str | None:
            ends[host].stdin.write(line + '\n')
            ends[host].stdin.flush()
            return None if line.startswith('send') else ends[host].stdout.readline().split()

        def exchange(tag: str) -> list[list[str]]:
            say('control', f'send c{tag}')
            say('substation', f'send s{tag}')
            return [say('substation', 'recv'), say('control', 'recv')]

        try:
            time.sleep(0.5)  # both sockets bound
            before = exchange('1')
            wan.set_partitions(net.control_file, [('substation', 'control')])
            time.sleep(0.2)
            during = exchange('2')
            wan.set_partitions(net.control_file, [])
            time.sleep(0.2)
            after = exchange('3')
        finally:
            for p in ends.values():
                p.stdin.close()
                p.wait(timeout=5)
    assert (before, during, after) == ([['c1'], ['s1']], [[], []], [['c3'], ['s3']])
    pairs = net.stats['pairs']
    assert pairs['control->substation']['partitioned'] >= 1 and pairs['substation->control']['partitioned'] >= 1


@pytest.mark.ros
@pytest.mark.slow
def test_partitioning_killed_right_before_the_request_is_restarted_and_the_request_answered_and_commanded():
    """IEEE 14: kill -9 of partitioning 20 ms of sim time before the request; the request it lost is sent again."""
    out = BUILD / 'test_chaos' / f'kill-{time.time_ns()}'
    out.mkdir(parents=True)
    fault = Fault(seed=-1, kind='kill', offset_s=-0.02, target='partitioning')
    result = chaos_run(REPO / 'bags' / 'ieee14_g1_unstable.yaml', None, out,
                       TestbedSettings(quiet=True, run_after_s=2.0, timeout_s=300.0), fault=fault)
    chaos = result['chaos']
    assert chaos['fired'] and -0.1 <= chaos['fired_after_request_s'] <= 0.0, chaos  # before the request went out
    (restart,) = result['restarts']
    assert restart['name'] == 'partitioning' and restart['exit_status'] == -9 and restart['new_pid']
    assert chaos['recovered'], chaos
    assert any(e['what'] == 'request sent again' for e in result['events']), result['events']
    assert result['answer']['kind'] == 'commanded', result['answer']
    (decision,) = [d for d in result['decisions'] if d['status'] == 'SPLIT']
    commanded = {e['item'] for e in result['events']
                 if e['what'] == 'command' and not e['item'].startswith(('shed:', 'trip:'))}
    assert decision['signed'] and commanded == set(decision['cut_branch_ids'])
    assert result['unsafe'] == []
    # Lockstep charges the wall time since the first request to sim time: 10 s and more here, past the run's end,
    # so the cut commanded this late is never opened in the simulation.
    assert result['request_to_opening_s'] is None or result['request_to_opening_s'] >= 5.0


@pytest.mark.ros
@pytest.mark.slow
def test_breaker_command_clock_stepped_back_a_day_before_the_request_commands_nothing_and_says_why():
    """Kundur: breaker_command's sim clock (through the relay) steps back a day; every decision is refused."""
    out = BUILD / 'test_chaos' / f'clock-{time.time_ns()}'
    out.mkdir(parents=True)
    fault = Fault(seed=-1, kind='clock_step', offset_s=-0.5, target='breaker_command', step_s=-86400.0)
    result = chaos_run(REPO / 'bags' / 'kundur_bus9_unstable.yaml', None, out,
                       TestbedSettings(quiet=True, run_after_s=2.0, timeout_s=300.0), fault=fault)
    assert result['chaos']['fired'] and result['chaos']['stepped_nodes'] == ['breaker_command']
    assert result['answer']['kind'] == 'refused', result['answer']
    assert result['answer']['reason'].startswith('breaker_command clock_inconsistent'), result['answer']
    assert result['opened'] == [] and result['unsafe'] == [] and result['restarts'] == []
    assert '/breaker_command fault.clock_inconsistent' in result['raised']
    # Only breaker_command's clock stepped: partitioning decided on its own, honest one.
    assert any(d['status'] == 'SPLIT' and d['signed'] for d in result['decisions'])
