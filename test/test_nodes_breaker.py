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
from controlled_islanding_msgs.msg import BranchStatus, BreakerCommand, IslandingDecision, NetworkSnapshot
from controlled_islanding_msgs.srv import SetArmed
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from nodes_harness import graph
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters

from controlled_islanding.core.grid import Grid
from controlled_islanding.core.remedial import bus_load_mw, remedial_actions
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
    params = {'audit_log': audit, 'max_decision_age_s': 30.0, 'max_breakers': 8, 'max_actions': 8, **overrides}
    return graph(name, [(BREAKER, params)])


def wire(probe):
    probe.publisher(IslandingDecision, topics.ISLANDING_DECISION)
    probe.publisher(NetworkSnapshot, topics.NETWORK_SNAPSHOT)
    probe.publisher(BranchStatus, topics.BRANCH_STATUS)
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


def reclosed(audit: Path) -> int:
    return sum(1 for r in audit_lines(audit) if r['event'] == 'reclosed')


def reclose(probe, cut) -> None:
    """Report the cut's branches back in service, stamped now: their breakers may be commanded again."""
    for b in cut:
        msg = BranchStatus(branch_id=b.branch_id, from_bus=b.from_bus, to_bus=b.to_bus, in_service=True)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now_ns(probe), 1_000_000_000)
        probe.pubs[topics.BRANCH_STATUS].publish(msg)


def rule_actions(island: dict[int, int]) -> tuple[dict[int, float], list[str]]:
    """Return the load to shed per bus and the machines to trip that partitioning would put in the decision."""
    actions = remedial_actions(GRID, island)
    return actions.shed_by_bus, list(actions.trip_generators)


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

        shed, trips = rule_actions(island)
        assert shed and trips, 'the split must shed and trip for this test to prove anything'
        first = decision_msg(island, cut, now_ns(probe), shed=shed, trips=trips)
        send(probe, first)
        assert probe.wait_counter(NODE, 'rejected.not_armed', 1) == 1
        assert arm(probe, True).armed
        send(probe, first)  # handled once already (refused while disarmed): never executed later
        assert probe.wait_counter(NODE, 'rejected.duplicate', 1) == 1

        # Remedial actions the snapshot does not allow, each refusing the whole decision (its cut included).
        loads = bus_load_mw(GRID)
        bus = next(iter(shed))
        island_of_trips = {island[g.bus] for g in GRID.generators if g.name in trips}
        powered = [g.name for g in GRID.generators if g.p_max_mw > 0 and island[g.bus] not in island_of_trips]
        no_load = next(b for b in GRID.buses if loads.get(b, 0.0) <= 0)
        bad_actions = {
            'unknown_load_bus': ({**shed, no_load: 1.0}, trips),
            'shed_beyond_load': ({**shed, bus: loads[bus] + 0.5}, trips),
            'bad_value': ({**shed, bus: float('nan')}, trips),
            'unknown_generator': (shed, [*trips, 'GENROU_999']),
            'duplicate_action': (shed, trips * 2),
            'island_without_generation': ({}, powered),
            'too_many_actions': ({b: 0.1 for b in sorted(loads)[:9]}, []),
        }
        for reason, (sheds, machines) in bad_actions.items():
            send(probe, decision_msg(island, cut, now_ns(probe), shed=sheds, trips=machines))
            assert probe.wait_counter(NODE, f'rejected.{reason}', 1) >= 1, reason
        forged = decision_msg(island, cut, now_ns(probe), shed=shed, trips=trips)
        forged.shed_mw = [mw * 2 for mw in forged.shed_mw]
        send(probe, forged)  # the amounts are signed like the cut
        assert probe.wait_counter(NODE, 'rejected.bad_signature', 1) == 1
        no_split = decision_msg(island, [], now_ns(probe), status=IslandingDecision.STATUS_NO_SPLIT, shed=shed)
        send(probe, no_split)
        assert probe.wait_counter(NODE, 'rejected.inconsistent_status', 1) == 1
        probe.spin_for(0.3)
        assert commands == [], 'a decision with a refused action commanded something'

        # Each cut entry five times and in the other spelling: one command per breaker, named by the data; then
        # one command per remedial action, with its amount.
        aliases = [(f'{b.to_bus}-{b.from_bus}', b.to_bus, b.from_bus) for b in cut]
        good = decision_msg(island, cut * 5 + aliases, now_ns(probe), shed=shed, trips=trips)
        send(probe, good)
        n_commands = len(cut) + len(shed) + len(trips)
        assert probe.spin_until(lambda: len(commands) >= n_commands)
        probe.spin_for(0.3)
        want = {FIELD_NAMES.get(b.branch_id, f'CB-{b.branch_id}') for b in cut}
        opens = [c for c in commands if c.action == BreakerCommand.ACTION_OPEN]
        assert sorted(c.breaker_id for c in opens) == sorted(want)
        assert {(c.bus, c.amount_mw, c.breaker_id) for c in commands if c.action == BreakerCommand.ACTION_SHED_LOAD} \
            == {(b, mw, f'LS-{b}') for b, mw in shed.items()}
        assert [c.generator_name for c in commands if c.action == BreakerCommand.ACTION_TRIP_GENERATOR] == trips
        assert len(commands) == n_commands and all(c.decision_id == good.decision_id for c in commands)
        assert len({c.command_id for c in commands}) == n_commands

        # Nothing twice: the same decision, and a new decision on breakers already opened.
        send(probe, good)
        assert probe.wait_counter(NODE, 'rejected.duplicate', 2) == 2
        send(probe, decision_msg(island, cut, now_ns(probe)))
        assert probe.wait_counter(NODE, 'rejected.branch_out_of_service', 1) == 1
        # The breakers closed again: the cut may open again, but no machine trips twice and no bus sheds more
        # than its load in all.
        reclose(probe, cut)
        assert probe.spin_until(lambda: reclosed(audit) == len(want), 10.0), audit_lines(audit)
        send(probe, decision_msg(island, cut, now_ns(probe), trips=trips))
        assert probe.wait_counter(NODE, 'rejected.generator_already_tripped', 1) == 1
        send(probe, decision_msg(island, cut, now_ns(probe), shed={bus: loads[bus] - shed[bus] + 0.5}))
        assert probe.wait_counter(NODE, 'rejected.shed_beyond_load', 2) == 2
        probe.spin_for(0.3)
        assert len(commands) == n_commands

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
        # Decisions: 5 above, the refused actions, the forged one and the NO_SPLIT with actions, 2 after the
        # reclosure; branch statuses: one per cut branch; then the bad ones and the 3 not to act on.
        decisions = 5 + len(bad_actions) + 2 + 2 + len(bad) + 3
        assert handled(probe, base + decisions + len(cut))
        # Every decision it finished with, refused or not, is counted (a replay's player waits on this count).
        assert probe.wait_counter(NODE, DECISIONS_HANDLED, decisions) == decisions
        probe.spin_for(0.3)
        assert len(commands) == n_commands, 'a refused decision produced a command'

        # Disarm wins: once the disarm is acknowledged, nothing more is commanded, cut or action.
        assert arm(probe, False).armed is False
        other_shed, other_trips = rule_actions(other)
        send(probe, decision_msg(other, other_cut, now_ns(probe), shed=other_shed, trips=other_trips))
        assert probe.wait_counter(NODE, 'rejected.not_armed', 2) == 2
        probe.spin_for(0.2)
        assert len(commands) == n_commands
        # A burst of snapshots into its keep-last-1 reader: each one taken or counted as lost, never silently.
        lost = probe.burst((NODE,), topics.NETWORK_SNAPSHOT, snapshot_msg(GRID, now_ns(probe), FIELD_NAMES), 100)
        assert lost[NODE] > 0, probe.diagnostics
        sup.check_alive()
    records = audit_lines(audit)
    (command,) = [r for r in records if r['event'] == 'command']
    # The audit record of the decision lists its actions with what they name, before any was published.
    assert {(c['bus'], c['amount_mw']) for c in command['commands'] if c['action'] == 'shed'} == set(shed.items())
    assert [c['generator'] for c in command['commands'] if c['action'] == 'trip'] == trips
    assert {r['event'] for r in records} >= {'no_split', 'not_decided', 'armed', 'disarmed', 'start'}
    refusals = {r['reason'] for r in records if r['event'] == 'refusal'}
    assert set(bad) | set(bad_actions) | {'not_armed', 'duplicate', 'branch_out_of_service',
                                          'generator_already_tripped', 'inconsistent_status'} <= refusals


def test_a_decision_judged_long_after_it_was_published_is_refused_whatever_the_node_clock_says(tmp_path):
    """Rule 6 on the wait in the queue too: a stalled breaker node's clock can be behind the grid.

    Found by the chaos sweep (docs/nodes.md): breaker_command resumed from a SIGSTOP under sim time judged the
    decision on a /clock of before the stall and its commands reached the grid 2.5 s after the request. Here, on
    the wall clock, the request is stamped 0.9 s ahead (within future_tolerance_s), so that after a 1.5 s stall it
    is only 0.6 s old by the node clock: fresh by the stamp, stale by the wait.
    """
    audit = tmp_path / 'audit.jsonl'
    island = two_islands(GRID)
    cut = boundary(GRID, island)
    shed, trips = rule_actions(island)
    with start('breaker_waited', audit, max_decision_age_s=1.0) as (sup, probe):
        commands = wire(probe)
        assert arm(probe, True).armed
        pid = sup.children[NODE].pid
        os.kill(pid, signal.SIGSTOP)
        try:
            send(probe, decision_msg(island, cut, now_ns(probe) + 900_000_000, shed=shed, trips=trips))
            probe.spin_for(1.5)
        finally:
            os.kill(pid, signal.SIGCONT)
        assert probe.wait_counter(NODE, 'rejected.stale', 1) == 1
        probe.spin_for(0.3)
        assert commands == []
        assert [r['reason'] for r in audit_lines(audit) if r['event'] == 'refusal'] == ['stale']


def test_restart_never_repeats_a_command(tmp_path):
    audit = tmp_path / 'audit.jsonl'
    island = two_islands(GRID)
    cut = boundary(GRID, island)
    shed, trips = rule_actions(island)
    n_commands = len(cut) + len(shed) + len(trips)
    with start('breaker_restart', audit) as (sup, probe):
        commands = wire(probe)
        assert arm(probe, True).armed
        decision = decision_msg(island, cut, now_ns(probe), shed=shed, trips=trips)
        send(probe, decision)
        assert probe.spin_until(lambda: len(commands) == n_commands)
        os.kill(sup.children[NODE].pid, signal.SIGKILL)
        sup.children[NODE].wait()
        sup.start(BREAKER, {'audit_log': audit, 'max_decision_age_s': 30.0, 'max_breakers': 8, 'max_actions': 8})
        probe.diagnostics.pop(NODE, None)
        probe.wait_matched(topics.ISLANDING_DECISION)
        assert probe.spin_until(lambda: probe.diagnostics.get(NODE, {}).get('armed') == 'false', 15.0), \
            'a restarted breaker node must start disarmed'
        probe.pubs[topics.NETWORK_SNAPSHOT].publish(snapshot_msg(GRID, now_ns(probe), FIELD_NAMES))
        assert probe.spin_until(lambda: probe.diagnostics.get(NODE, {}).get('buses') == str(len(GRID.buses)), 15.0)
        assert arm(probe, True).armed
        decision.request_stamp.sec, decision.request_stamp.nanosec = divmod(now_ns(probe), 1_000_000_000)
        send(probe, decision)  # same id, fresh stamp: the signature no longer verifies, and the id is known
        again = decision_msg(island, cut, now_ns(probe), decision_id=decision.decision_id, shed=shed, trips=trips)
        send(probe, again)  # re-signed under the same id: refused as a duplicate
        send(probe, decision_msg(island, cut, now_ns(probe)))  # new id, same breakers: already open
        assert probe.wait_counter(NODE, 'rejected.duplicate', 1) == 1
        assert probe.wait_counter(NODE, 'rejected.branch_out_of_service', 1) == 1
        # Breakers closed again since; the restarted node still knows the machines tripped and the load shed.
        reclose(probe, cut)
        assert probe.spin_until(lambda: reclosed(audit) == len({c.breaker_id for c in commands
                                                                 if c.action == BreakerCommand.ACTION_OPEN}), 10.0)
        send(probe, decision_msg(island, cut, now_ns(probe), trips=trips))
        assert probe.wait_counter(NODE, 'rejected.generator_already_tripped', 1) == 1
        bus, mw = next(iter(shed.items()))
        send(probe, decision_msg(island, cut, now_ns(probe), shed={bus: bus_load_mw(GRID)[bus] - mw + 0.5}))
        assert probe.wait_counter(NODE, 'rejected.shed_beyond_load', 1) == 1
        probe.spin_for(0.3)
        assert len(commands) == n_commands
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
    Expected = breaker_soak.Expected
    cmd = {'event': 'command', 'decision_id': 'd1', 'commands': [{'breaker_id': 'CB-1', 'command_id': 'd1/CB-1'}]}
    armed = {'event': 'armed'}
    valid = {'d1': Expected(frozenset({'CB-1'}))}
    assert breaker_soak.check_audit([armed, cmd], valid, ['d1/CB-1'])[0] == []
    assert breaker_soak.check_audit([cmd], valid, [])[0], 'a command while disarmed passed'
    assert breaker_soak.check_audit([armed, cmd], {}, [])[0], 'a command for an invalid decision passed'
    assert breaker_soak.check_audit([armed, cmd], {'d1': Expected(frozenset({'CB-2'}))}, [])[0], 'a wrong cut passed'
    assert breaker_soak.check_audit([armed, cmd, cmd], valid, [])[0], 'a repeated command passed'
    assert breaker_soak.check_audit([armed, cmd, {'event': 'start'}, cmd], valid, [])[0]
    reclosed = {'event': 'reclosed', 'breaker_id': 'CB-1'}
    again = {**cmd, 'decision_id': 'd2'}
    assert breaker_soak.check_audit([armed, cmd, reclosed, again], {**valid, 'd2': valid['d1']}, [])[0] == []
    assert breaker_soak.check_audit([armed, cmd], valid, ['ghost/CB-9'])[0], 'an unlogged command passed'
    # Remedial actions: only the decision's own, no machine twice, never more shed at a bus than its load.
    shed = {'breaker_id': 'LS-4', 'command_id': 'd3/LS-4', 'action': 'shed', 'bus': 4, 'amount_mw': 30.0}
    trip = {'breaker_id': 'GCB-G2', 'command_id': 'd3/GCB-G2', 'action': 'trip', 'bus': 2, 'generator': 'G2'}
    acts = {'event': 'command', 'decision_id': 'd3', 'commands': [cmd['commands'][0], shed, trip]}
    own = Expected(frozenset({'CB-1'}), frozenset({('shed', 4, 30.0), ('trip', 'G2')}))
    load = {4: 50.0}
    assert breaker_soak.check_audit([armed, acts], {'d3': own}, ['d3/LS-4'], bus_load=load)[0] == []
    assert breaker_soak.check_audit([acts], {'d3': own}, [], bus_load=load)[0], 'an action while disarmed passed'
    assert breaker_soak.check_audit([armed, acts], {'d3': Expected(frozenset({'CB-1'}))}, [], bus_load=load)[0], \
        'an action the decision does not carry passed'
    later = {'event': 'command', 'decision_id': 'd4', 'commands': [trip, {**shed, 'amount_mw': 25.0}]}
    later_own = Expected(frozenset(), frozenset({('shed', 4, 25.0), ('trip', 'G2')}))
    broken = breaker_soak.check_audit([armed, acts, later], {'d3': own, 'd4': later_own}, [], bus_load=load)[0]
    assert any('tripped twice' in b for b in broken) and any('bus 4' in b for b in broken), broken
    assert breaker_soak.check_audit([armed, acts], {'d3': own}, [], max_actions=1, bus_load=load)[0]


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
