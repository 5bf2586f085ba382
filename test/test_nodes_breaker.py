"""breaker_command as a real process: every breaker rule of docs/nodes.md, adversarially.

The node runs on the system clock (no use_sim_time), so request stamps are 'now' in wall time. Decisions are
signed with keys this test run made (breaker_cases.made_test_keys); a foreign key is made per test.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest
from breaker_cases import boundary, decision_msg, made_test_keys, private_key, snapshot_msg, two_islands
from controlled_islanding_msgs.msg import BreakerCommand, IslandingDecision, NetworkSnapshot
from controlled_islanding_msgs.srv import SetArmed
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from nodes_harness import graph
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters

from controlled_islanding.core.grid import Grid
from controlled_islanding.graph.supervisor import GRAPH
from controlled_islanding.harness import breaker_soak
from controlled_islanding.ros.diagnostics import DECISIONS_HANDLED
from controlled_islanding.safety import signing
from controlled_islanding.wire import topics

BUILD_DIR = Path(__file__).resolve().parents[1] / 'build'

pytestmark = [pytest.mark.ros, pytest.mark.slow]

BREAKER = next(s for s in GRAPH if s.executable == 'breaker_command')
NODE = 'breaker_command'
SERVICE = '/breaker_command/set_armed'
# A non-IEEE-39 network, breakers named by the data for some branches and by default for the rest.
GRID = Grid.from_matpower('case14').with_flows()
FIELD_NAMES = {'2-3': 'BRK-NORTH-7', '4-5': 'BRK-SOUTH-2'}


def audit_lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def now_ns(probe) -> int:
    return probe.node.get_clock().now().nanoseconds


def arm(probe, armed: bool, key=None, **changes):
    request = signing.signed_arm_request(SetArmed.Request(), key or private_key('operator'), '/breaker_command', armed,
                                         time.time())
    for name, value in changes.items():
        setattr(request, name, value)
    return probe.call(SetArmed, SERVICE, request)


def get_armed(probe) -> bool:
    response = probe.call(GetParameters, '/breaker_command/get_parameters', GetParameters.Request(names=['armed']))
    return response.values[0].bool_value


def start(name: str, audit: Path | str, **overrides):
    params = {'audit_log': audit, 'max_decision_age_s': 30.0, 'max_breakers': 8, **overrides}
    return graph(name, [(BREAKER, params)])


def wire(probe):
    probe.publisher(IslandingDecision, topics.ISLANDING_DECISION)
    probe.publisher(NetworkSnapshot, topics.NETWORK_SNAPSHOT)
    commands = probe.collect(BreakerCommand, topics.BREAKER_COMMANDS)
    probe.wait_matched(topics.ISLANDING_DECISION)
    probe.wait_matched(topics.NETWORK_SNAPSHOT)
    probe.pubs[topics.NETWORK_SNAPSHOT].publish(snapshot_msg(GRID, now_ns(probe), FIELD_NAMES))
    assert probe.spin_until(lambda: probe.diagnostics.get(NODE, {}).get('buses') == str(len(GRID.buses)), 15.0)
    return commands


def send(probe, msg) -> None:
    probe.pubs[topics.ISLANDING_DECISION].publish(msg)


def handled(probe, n: int) -> bool:
    return probe.wait_counter(NODE, 'received', n, timeout_s=15.0) >= n


def test_arming_is_signed_audited_and_visible(tmp_path):
    audit = tmp_path / 'audit.jsonl'
    with start('breaker_arming', audit) as (sup, probe):
        wire(probe)
        assert get_armed(probe) is False
        # Standard parameter service: refused, the state unchanged (as `ros2 param set` would see it).
        result = probe.call(SetParameters, '/breaker_command/set_parameters', SetParameters.Request(parameters=[
            ParameterMsg(name='armed', value=ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=True))]))
        assert not result.results[0].successful and 'read-only' in result.results[0].reason
        assert get_armed(probe) is False
        # A foreign key, no signature, a forged signature, an unset action, a stale and a replayed request.
        foreign = Ed25519PrivateKey.generate()
        assert not arm(probe, True, key=foreign).accepted
        assert not arm(probe, True, signature=[]).accepted
        assert not arm(probe, True, signature=[1] * 64).accepted
        assert not arm(probe, True, action=SetArmed.Request.ACTION_UNSET).accepted
        old = signing.signed_arm_request(SetArmed.Request(), private_key('operator'), '/breaker_command', True,
                                         time.time() - 3600)
        assert not probe.call(SetArmed, SERVICE, old).accepted
        assert get_armed(probe) is False
        good = signing.signed_arm_request(SetArmed.Request(), private_key('operator'), '/breaker_command', True,
                                          time.time())
        assert probe.call(SetArmed, SERVICE, good).armed is True
        assert get_armed(probe) is True
        assert not probe.call(SetArmed, SERVICE, good).accepted, 'a replayed arm request was accepted'
        assert arm(probe, False).armed is False and get_armed(probe) is False
        sup.check_alive()
    reasons = [r.get('reason') for r in audit_lines(audit) if r['event'] == 'refusal']
    assert {'unknown_key', 'unsigned', 'bad_signature', 'unset_action', 'stale', 'replay'} <= set(reasons)
    assert [r['event'] for r in audit_lines(audit) if r['event'] in ('armed', 'disarmed')] == ['armed', 'disarmed']


def test_breaker_rules_on_a_real_process(tmp_path):
    audit = tmp_path / 'audit.jsonl'
    island = two_islands(GRID)
    cut = boundary(GRID, island)
    with start('breaker_rules', audit) as (sup, probe):
        commands = wire(probe)
        base = probe.counter(NODE, 'received')

        first = decision_msg(island, cut, now_ns(probe))
        send(probe, first)
        assert probe.wait_counter(NODE, 'rejected.not_armed', 1) == 1
        assert arm(probe, True).armed
        send(probe, first)  # handled once already (refused while disarmed): never executed later
        assert probe.wait_counter(NODE, 'rejected.duplicate', 1) == 1

        # Each cut entry five times and in the other spelling: one command per breaker, named by the data.
        aliases = [(f'{b.to_bus}-{b.from_bus}', b.to_bus, b.from_bus) for b in cut]
        good = decision_msg(island, cut * 5 + aliases, now_ns(probe))
        send(probe, good)
        assert probe.spin_until(lambda: len(commands) >= len(cut))
        probe.spin_for(0.3)
        want = {FIELD_NAMES.get(b.branch_id, f'CB-{b.branch_id}') for b in cut}
        assert sorted(c.breaker_id for c in commands) == sorted(want)
        assert all(c.action == BreakerCommand.ACTION_OPEN and c.decision_id == good.decision_id for c in commands)

        # Nothing twice: the same decision, and a new decision on breakers already opened.
        send(probe, good)
        assert probe.wait_counter(NODE, 'rejected.duplicate', 2) == 2
        send(probe, decision_msg(island, cut, now_ns(probe)))
        assert probe.wait_counter(NODE, 'rejected.branch_out_of_service', 1) == 1

        other = two_islands(GRID, seed_index=2)
        other_cut = boundary(GRID, other)
        year_s = 365 * 86400
        inner = next(b for b in GRID.branches if island[b.from_bus] == island[b.to_bus])
        each_bus = {b: i for i, b in enumerate(GRID.buses)}
        parity = {b: b % 2 for b in GRID.buses}
        assert len(boundary(GRID, parity)) > 8
        bad = {
            'unsigned': decision_msg(other, other_cut, now_ns(probe), sign=False),
            'unknown_key': decision_msg(other, other_cut, now_ns(probe), key=Ed25519PrivateKey.generate()),
            'stale': decision_msg(other, other_cut, now_ns(probe) - int(120e9)),
            'future_stamp': decision_msg(other, other_cut, now_ns(probe) + int(year_s * 1e9)),
            'unset_status': decision_msg(other, other_cut, now_ns(probe), status=0),
            'unknown_branch': decision_msg(other, other_cut + [('99-100', 99, 100)], now_ns(probe)),
            'inconsistent_cut': decision_msg(island, [inner], now_ns(probe)),
            'island_without_generation': decision_msg(each_bus, boundary(GRID, each_bus), now_ns(probe)),
            'too_many_breakers': decision_msg(parity, boundary(GRID, parity), now_ns(probe)),
            'too_large': decision_msg(other, [('1-2', 1, 2)] * 100_000, now_ns(probe), sign=False),
        }
        forged = decision_msg(other, other_cut, now_ns(probe))
        forged.cut_branch_ids = list(reversed(forged.cut_branch_ids))
        bad['bad_signature'] = forged
        for reason, msg in bad.items():
            send(probe, msg)
            assert probe.wait_counter(NODE, f'rejected.{reason}', 1) >= 1, reason
        no_split = decision_msg(other, [], now_ns(probe), status=IslandingDecision.STATUS_NO_SPLIT)
        stale_groups = decision_msg(other, [], now_ns(probe), status=IslandingDecision.STATUS_REFUSED_STALE_GROUPS)
        suspect = decision_msg(other, [], now_ns(probe), status=IslandingDecision.STATUS_REFUSED_SUSPECT_DATA)
        send(probe, no_split)
        send(probe, stale_groups)
        send(probe, suspect)
        assert handled(probe, base + 5 + len(bad) + 3)
        # Every decision it finished with, refused or not, is counted (a replay's player waits on this count).
        assert probe.wait_counter(NODE, DECISIONS_HANDLED, 5 + len(bad) + 3) == 5 + len(bad) + 3
        probe.spin_for(0.3)
        assert len(commands) == len(cut), 'a refused decision produced a command'

        # Disarm wins: once the disarm is acknowledged, nothing more is commanded.
        assert arm(probe, False).armed is False
        send(probe, decision_msg(other, other_cut, now_ns(probe)))
        assert probe.wait_counter(NODE, 'rejected.not_armed', 2) == 2
        probe.spin_for(0.2)
        assert len(commands) == len(cut)
        # A burst of snapshots into its keep-last-1 reader: each one taken or counted as lost, never silently.
        lost = probe.burst((NODE,), topics.NETWORK_SNAPSHOT, snapshot_msg(GRID, now_ns(probe), FIELD_NAMES), 100)
        assert lost[NODE] > 0, probe.diagnostics
        sup.check_alive()
    records = audit_lines(audit)
    assert [r['event'] for r in records].count('command') == 1
    assert {r['event'] for r in records} >= {'no_split', 'not_decided', 'armed', 'disarmed', 'start'}
    refusals = {r['reason'] for r in records if r['event'] == 'refusal'}
    assert set(bad) | {'not_armed', 'duplicate', 'branch_out_of_service'} <= refusals


def test_restart_never_repeats_a_command(tmp_path):
    audit = tmp_path / 'audit.jsonl'
    island = two_islands(GRID)
    cut = boundary(GRID, island)
    with start('breaker_restart', audit) as (sup, probe):
        commands = wire(probe)
        assert arm(probe, True).armed
        decision = decision_msg(island, cut, now_ns(probe))
        send(probe, decision)
        assert probe.spin_until(lambda: len(commands) == len(cut))
        os.kill(sup.children[NODE].pid, signal.SIGKILL)
        sup.children[NODE].wait()
        sup.start(BREAKER, {'audit_log': audit, 'max_decision_age_s': 30.0, 'max_breakers': 8})
        probe.diagnostics.pop(NODE, None)
        probe.wait_matched(topics.ISLANDING_DECISION)
        assert probe.spin_until(lambda: probe.diagnostics.get(NODE, {}).get('armed') == 'false', 15.0), \
            'a restarted breaker node must start disarmed'
        probe.pubs[topics.NETWORK_SNAPSHOT].publish(snapshot_msg(GRID, now_ns(probe), FIELD_NAMES))
        assert probe.spin_until(lambda: probe.diagnostics.get(NODE, {}).get('buses') == str(len(GRID.buses)), 15.0)
        assert arm(probe, True).armed
        decision.request_stamp.sec, decision.request_stamp.nanosec = divmod(now_ns(probe), 1_000_000_000)
        send(probe, decision)  # same id, fresh stamp: the signature no longer verifies, and the id is known
        again = decision_msg(island, cut, now_ns(probe), decision_id=decision.decision_id)
        send(probe, again)  # re-signed under the same id: refused as a duplicate
        send(probe, decision_msg(island, cut, now_ns(probe)))  # new id, same breakers: already open
        assert probe.wait_counter(NODE, 'rejected.duplicate', 1) == 1
        assert probe.wait_counter(NODE, 'rejected.branch_out_of_service', 1) == 1
        probe.spin_for(0.3)
        assert len(commands) == len(cut)
        sup.check_alive()
    assert sum(1 for r in audit_lines(audit) if r['event'] == 'command') == 1


def test_an_unusable_audit_log_refuses_and_the_node_lives():
    with start('breaker_dev_full', '/dev/full') as (sup, probe):
        commands = wire(probe)
        response = arm(probe, True)
        assert not response.accepted and not response.armed and 'audit' in response.message
        island = two_islands(GRID)
        send(probe, decision_msg(island, boundary(GRID, island), now_ns(probe)))
        assert probe.wait_counter(NODE, 'rejected.audit_unavailable', 2) >= 2
        assert 'not a regular file' in probe.diagnostics[NODE].get('fault.audit', '')
        probe.spin_for(0.3)
        assert commands == []
        sup.check_alive()


def test_randomized_adversary_never_breaks_a_rule(tmp_path):
    """A seeded adversary with kill -9 restarts (breaker_soak); its audit log is checked against every rule.

    `controlled-islanding fuzz --breaker-trials 20000` is the soak; CI runs a few hundred trials.
    """
    report = breaker_soak.run_breaker_soak(240, seed=7, key_dir=made_test_keys(), results=tmp_path)
    print(report.render())
    assert report.broken == []
    assert report.restarts >= 2
    assert report.commanded_decisions >= 2, 'the adversary never got a command through: it proves nothing'


def test_the_rule_checker_catches_each_broken_rule():
    cmd = {'event': 'command', 'decision_id': 'd1', 'commands': [{'breaker_id': 'CB-1', 'command_id': 'd1/CB-1'}]}
    armed = {'event': 'armed'}
    valid = {'d1': {'CB-1'}}
    assert breaker_soak.check_audit([armed, cmd], valid, ['d1/CB-1'])[0] == []
    assert breaker_soak.check_audit([cmd], valid, [])[0], 'a command while disarmed passed'
    assert breaker_soak.check_audit([armed, cmd], {}, [])[0], 'a command for an invalid decision passed'
    assert breaker_soak.check_audit([armed, cmd], {'d1': {'CB-2'}}, [])[0], 'a wrong cut passed'
    assert breaker_soak.check_audit([armed, cmd, cmd], valid, [])[0], 'a repeated command passed'
    assert breaker_soak.check_audit([armed, cmd, {'event': 'start'}, cmd], valid, [])[0]
    reclosed = {'event': 'reclosed', 'breaker_id': 'CB-1'}
    again = {**cmd, 'decision_id': 'd2'}
    assert breaker_soak.check_audit([armed, cmd, reclosed, again], {**valid, 'd2': {'CB-1'}}, [])[0] == []
    assert breaker_soak.check_audit([armed, cmd], valid, ['ghost/CB-9'])[0], 'an unlogged command passed'


def test_a_disk_that_fills_up_mid_run_refuses_and_the_node_lives():
    import subprocess
    import uuid

    mount = BUILD_DIR / 'test_nodes' / f'fullfs-{uuid.uuid4().hex[:8]}'
    mount.mkdir(parents=True)
    # A 12 KiB tmpfs of which 8 KiB are taken: the audit log gets one 4 KiB page, then ENOSPC.
    made = subprocess.run(['mount', '-t', 'tmpfs', '-o', 'size=12k', 'tmpfs', str(mount)], capture_output=True)
    if made.returncode != 0:
        pytest.skip(f'cannot mount a small tmpfs here: {made.stderr.decode().strip()}')
    try:
        (mount / 'filler').write_bytes(b'x' * 8192)
        with start('breaker_disk_full', mount / 'audit.jsonl') as (sup, probe):
            commands = wire(probe)
            island = two_islands(GRID)
            cut = boundary(GRID, island)
            sent = 0
            while 'fault.audit' not in probe.diagnostics.get(NODE, {}) and sent < 40:
                send(probe, decision_msg(island, cut, now_ns(probe)))  # disarmed: each refusal is a record
                sent += 1
                probe.spin_for(0.1)
            fault = probe.diagnostics[NODE].get('fault.audit', '')
            assert 'No space left' in fault or 'short write' in fault, probe.diagnostics.get(NODE)
            response = arm(probe, True)
            assert not response.accepted and not response.armed
            send(probe, decision_msg(island, cut, now_ns(probe)))
            assert probe.wait_counter(NODE, 'rejected.audit_unavailable', 2) >= 2
            probe.spin_for(0.3)
            assert commands == []
            sup.check_alive()
            assert sup.children[NODE].poll() is None
    finally:
        subprocess.run(['umount', str(mount)], check=False)


def test_a_parameter_out_of_its_range_stops_the_node_with_the_reason(tmp_path):
    with start('breaker_bad_parameter', tmp_path / 'audit.jsonl', max_decision_age_s=-5.0) as (sup, probe):
        child = sup.children[NODE]
        assert child.wait(timeout=30) == 1
        log = sup.log_tail(NODE)
        assert 'max_decision_age_s' in log and 'error' in log, log


def test_no_private_key_is_tracked():
    import subprocess

    repo = Path(__file__).resolve().parents[1]
    tracked = subprocess.run(['git', 'ls-files', '*.key', '*.pem'], cwd=repo, capture_output=True, text=True)
    assert tracked.returncode != 0 or tracked.stdout == '', f'private keys in the repository: {tracked.stdout}'
