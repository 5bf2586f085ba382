"""Audit log recovery, signatures and time-bounded topology: the pure parts under breaker_command (fast)."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
from types import SimpleNamespace

import pytest

from controlled_islanding.core.grid import Grid
from controlled_islanding.safety import signing
from controlled_islanding.safety.audit import AuditError, AuditLog, read_state
from controlled_islanding.safety.topology import Topology, TopologyError
from controlled_islanding.wire.timebounds import (
    HELD_SNAPSHOTS,
    SNAPSHOT,
    Backlog,
    SimClockGuard,
    StampError,
    StampGate,
)


# --- audit ------------------------------------------------------------------------------------------------------
def test_state_survives_a_restart(tmp_path):
    path = tmp_path / 'audit.jsonl'
    with AuditLog(path) as log:
        log.append({'event': 'armed', 'nonce': 'n1', 'stamp_s': 5.0})
        log.append({'event': 'command', 'decision_id': 'd1', 'authenticated': True, 'request_stamp_s': 9.0,
                    'ros_time_s': 9.5, 'commands': [{'breaker_id': 'CB-1', 'branch_id': '1-2'}]})
        log.append({'event': 'refusal', 'decision_id': 'forged', 'authenticated': False, 'reason': 'unsigned'})
        log.append({'event': 'command', 'decision_id': 'd2', 'authenticated': True, 'request_stamp_s': 10.0,
                    'ros_time_s': 10.5, 'commands': [{'breaker_id': 'CB-2', 'branch_id': '2-3'}]})
        log.append({'event': 'reclosed', 'breaker_id': 'CB-2', 'branch_id': '2-3', 'stamp_s': 11.0})
        log.append({'event': 'command', 'decision_id': 'd3', 'authenticated': True, 'request_stamp_s': 12.0,
                    'ros_time_s': 12.5, 'commands': [
                        {'breaker_id': 'LS-4', 'branch_id': '', 'action': 'shed', 'bus': 4, 'amount_mw': 30.0},
                        {'breaker_id': 'GCB-G2', 'branch_id': '', 'action': 'trip', 'bus': 2, 'generator': 'G2'}]})
        log.append({'event': 'command', 'decision_id': 'd4', 'authenticated': True, 'request_stamp_s': 13.0,
                    'ros_time_s': 13.5, 'commands': [
                        {'breaker_id': 'LS-4', 'branch_id': '', 'action': 'shed', 'bus': 4, 'amount_mw': 12.5}]})
    assert oct(path.stat().st_mode & 0o777) == '0o600'
    state = AuditLog(path).state
    assert state.decisions == {'d1': 9.0, 'd2': 10.0, 'd3': 12.0, 'd4': 13.0}, \
        'an unauthenticated id must not block the real decision'
    assert state.commanded == {'CB-1': ('d1', 9.5)}, 'a reclosed breaker must be closable again after a restart'
    assert state.nonces == {'n1': 5.0}
    # The remedial actions are remembered too: what was shed at each bus, in all, and which machines were tripped.
    assert state.shed_mw == {4: 42.5} and state.tripped == {'G2': 'd3'}


def test_a_torn_last_record_is_cut_off_and_nothing_else(tmp_path):
    path = tmp_path / 'audit.jsonl'
    good = json.dumps({'event': 'command', 'decision_id': 'd1', 'authenticated': True,
                       'commands': [{'breaker_id': 'CB-1'}]})
    path.write_text(good + '\n' + '{"event": "command", "decision_id": "d2", "comm')
    state = read_state(path)
    assert state.repaired_tail and list(state.decisions) == ['d1']
    assert path.read_text() == good + '\n'


def test_a_corrupt_record_inside_the_log_refuses(tmp_path):
    path = tmp_path / 'audit.jsonl'
    path.write_text('{"event": "start"}\nnot json\n{"event": "start"}\n')
    with pytest.raises(AuditError, match='line 2'):
        AuditLog(path)


def test_a_log_that_is_not_a_file_refuses(tmp_path):
    with pytest.raises(AuditError, match='not a regular file'):
        AuditLog('/dev/full')
    with pytest.raises(AuditError):
        AuditLog(tmp_path)


# --- signatures -------------------------------------------------------------------------------------------------
def _decision(**fields):
    base = dict(decision_id='d', request_id='r', request_stamp=SimpleNamespace(sec=5, nanosec=7), status=1,
                split=True, bus_numbers=[1, 2], bus_island=[0, 1], cut_branch_ids=['1-2'], cut_from_bus=[1],
                cut_to_bus=[2], shed_bus=[2], shed_mw=[15.5], trip_generator_names=['G1'], key_id='k')
    base.update(fields)
    return SimpleNamespace(**base)


def test_signature_covers_every_field_the_breaker_acts_on(tmp_path):
    signing.init_keys(tmp_path)
    key = signing.load_private_key(tmp_path / 'partitioning.key')
    public = signing.load_public_key(tmp_path / 'partitioning.pub')
    msg = _decision()
    sig = signing.sign(key, signing.decision_payload(msg))
    signing.verify(public, signing.decision_payload(msg), sig)
    changes = {'decision_id': 'e', 'request_id': 's', 'request_stamp': SimpleNamespace(sec=6, nanosec=7),
               'status': 2, 'split': False, 'bus_numbers': [1, 3], 'bus_island': [0, 0], 'cut_branch_ids': ['2-1'],
               'cut_from_bus': [2], 'cut_to_bus': [1], 'key_id': 'x', 'shed_bus': [1], 'shed_mw': [15.50001],
               'trip_generator_names': ['G2']}
    for name, value in changes.items():
        with pytest.raises(signing.SigningError) as info:
            signing.verify(public, signing.decision_payload(_decision(**{name: value})), sig)
        assert info.value.reason == 'bad_signature', name
    other = signing.load_public_key(tmp_path / 'operator.pub')
    with pytest.raises(signing.SigningError):
        signing.verify(other, signing.decision_payload(msg), sig)
    with pytest.raises(signing.SigningError, match='no signature'):
        signing.verify(public, signing.decision_payload(msg), [])


def test_an_arm_signature_never_passes_as_another_request(tmp_path):
    signing.init_keys(tmp_path)
    key = signing.load_private_key(tmp_path / 'operator.key')
    public = signing.load_public_key(tmp_path / 'operator.pub')
    req = signing.signed_arm_request(SimpleNamespace(stamp=SimpleNamespace(sec=0, nanosec=0)), key,
                                     '/breaker_command', True, 1_000.5)
    signing.verify(public, signing.arm_payload(req, '/breaker_command'), req.signature)
    with pytest.raises(signing.SigningError):
        signing.verify(public, signing.arm_payload(req, '/area2/breaker_command'), req.signature)
    req.action = 2
    with pytest.raises(signing.SigningError):
        signing.verify(public, signing.arm_payload(req, '/breaker_command'), req.signature)


def test_private_keys_are_owner_only(tmp_path):
    made = signing.init_keys(tmp_path)
    assert oct(tmp_path.stat().st_mode & 0o777) == '0o700'
    for paths in made.values():
        assert oct(paths.private.stat().st_mode & 0o777) == '0o600'
    os.chmod(made['operator'].private, 0o644)
    with pytest.raises(signing.SigningError, match='readable by others'):
        signing.load_private_key(made['operator'].private)
    before = made['partitioning'].public.read_bytes()
    signing.init_keys(tmp_path)
    assert made['partitioning'].public.read_bytes() == before, 'init must keep existing keys'


# --- time-bounded topology --------------------------------------------------------------------------------------
GRID = Grid.from_matpower('case14')


def test_future_values_never_become_the_newest():
    topo = Topology(future_tolerance_s=1.0)
    topo.offer_snapshot(GRID, 100.0, now_s=100.0)
    with pytest.raises(TopologyError) as info:
        topo.offer_snapshot(GRID, 100.0 + 3600.0, now_s=100.5)
    assert info.value.reason == 'future_stamp'
    topo.offer_status('2-3', False, 101.0, now_s=101.0)
    with pytest.raises(TopologyError):
        topo.offer_status('2-3', True, 101.0 + 86400.0, now_s=101.2)
    # Within the tolerance, a 'back in service' stamped after the request cannot undo the trip it must see.
    topo.offer_status('2-3', True, 102.0, now_s=101.5)
    assert topo.outages_at(101.5) == ('2-3',)
    assert topo.outages_at(102.0) == ()
    topo.offer_snapshot(GRID, 103.0, now_s=103.0)
    with pytest.raises(TopologyError) as info:
        topo.offer_snapshot(GRID, 102.5, now_s=103.0)
    assert info.value.reason == 'time_backwards'


def test_status_memory_is_bounded_and_a_trip_may_come_before_its_snapshot():
    topo = Topology(future_tolerance_s=1.0, max_changes_per_branch=8, max_branches_before_snapshot=2)
    # A trip that overtakes its snapshot is kept for it; ids the snapshot does not have are then dropped.
    topo.offer_status('2-3', False, 1.5, now_s=1.5)
    topo.offer_status('ghost', False, 1.5, now_s=1.5)
    with pytest.raises(TopologyError) as info:
        topo.offer_status('other-ghost', False, 1.5, now_s=1.5)
    assert info.value.reason == 'too_large'
    topo.offer_snapshot(GRID, 1.0, now_s=1.6)
    assert topo.outages_at(2.0) == ('2-3',) and topo.changes_known(2.0) == 1
    with pytest.raises(TopologyError) as info:
        topo.offer_status('99-100', False, 1.0, now_s=1.0)
    assert info.value.reason == 'unknown_id'
    rng = random.Random(3)
    for _ in range(1000):
        topo.offer_status('2-3', rng.random() < 0.5, 1.0 + rng.random() * 50, now_s=60.0)
    assert len(topo._changes['2-3']) == 8


def test_stamp_gate_holds_until_the_clock_runs():
    gate = StampGate(future_tolerance_s=0.5, max_held=3, hold_horizon_s=60.0)
    assert not gate.offer('a', 10.0, 0.0, 'a')
    for item, stamp in (('b', 20.0), ('c', 500.0), ('d', 10.1)):
        gate.offer(item, stamp, 0.0, item)
    assert gate.held == 3 and gate.dropped_while_held == 1
    used, refused = [], []
    gate.release(10.2, used.append, refused.append)
    # a was dropped as the oldest; d is due; b waits for the clock; c leads it by 490 s: never honest.
    assert used == ['d'] and [e.reason for e in refused] == ['future_stamp'] and gate.held == 1
    gate.release(19.6, used.append, refused.append)
    assert used == ['d', 'b'] and gate.held == 0


def test_what_waits_for_the_clock_is_bounded_in_size_and_keeps_only_the_newest_snapshots():
    gate = StampGate(future_tolerance_s=0.5, hold_horizon_s=60.0, max_held_elements=100)
    for i in range(10):
        gate.offer(f'snapshot {i}', 1.0 + i, 0.0, f'snapshot {i}', elements=5, kind=SNAPSHOT)
        gate.offer(f'frame {i}', 1.0 + i, 0.0, f'frame {i}', elements=1)
    # The oldest six snapshots were superseded; no frame was dropped for them.
    assert gate.held == HELD_SNAPSHOTS + 10 and gate.held_elements == 5 * HELD_SNAPSHOTS + 10
    gate.offer('big frame', 5.0, 0.0, 'big frame', elements=80)
    assert gate.held_elements <= 100 and gate.dropped_while_held == 6 + 7
    # One item larger than the whole budget is still held: the newest input is never lost to the bound.
    gate.offer('huge', 5.0, 0.0, 'huge', elements=1000)
    assert gate.held == 1 and gate.held_elements == 1000
    used = []
    gate.release(20.0, used.append, pytest.fail)
    assert used == ['huge'] and gate.held == 0 and gate.held_elements == 0


def test_a_backlog_keeps_the_newest_within_its_count_and_its_elements():
    backlog = Backlog(max_items=5, max_elements=100)
    assert [backlog.append(i, 10) for i in range(7)] == [0, 0, 0, 0, 0, 1, 1]
    assert len(backlog) == 5 and backlog[0] == 2 and backlog.elements == 50
    assert backlog.append('big', 80) == 3 and [backlog[i] for i in range(len(backlog))] == [5, 6, 'big']
    # One item over the whole budget is still kept: the newest is never the one dropped.
    assert backlog.append('huge', 1000) == 3 and len(backlog) == 1 and backlog.elements == 1000
    assert backlog.popleft() == 'huge' and backlog.elements == 0 and not backlog


def test_a_clock_that_lags_the_data_delays_a_value_but_never_loses_or_uses_it_early():
    gate = StampGate(future_tolerance_s=1.0, hold_horizon_s=60.0)
    assert gate.offer('trip', 5.25, 5.0, 'trip')
    assert not gate.offer('trip', 5.25, 0.001, 'trip-lagging')
    used = []
    gate.release(3.0, used.append, pytest.fail)
    assert used == [], 'used 2.25 s before its time'
    gate.release(4.3, used.append, pytest.fail)
    assert used == ['trip-lagging']
    with pytest.raises(StampError):
        gate.offer('poison', 4.3 + 86400.0, 4.3, 'poison')


# --- sim clock bound ---------------------------------------------------------------------------------------------
T0 = 1_700_000_000.0  # a bag's start, POSIX s


def sim_guard(readings: list[tuple[float, float]], max_rate: float = 100.0, max_jump_s: float = 5.0,
              recovery_s: float = 2.0) -> tuple[SimClockGuard, list]:
    """Feed (wall_s, sim_s) readings to a guard; return it and the jumps it found, one per reading (or None)."""
    guard = SimClockGuard(max_rate=max_rate, max_jump_s=max_jump_s, recovery_s=recovery_s)
    return guard, [guard.observe(w, s) for w, s in readings]


def test_sim_clock_starting_standing_and_advancing_within_bounds_is_consistent():
    # Not started (0), started at the bag's time, standing (a lockstep wait), then 100 x wall for 10 s.
    readings = [(0.0, 0.0), (0.5, T0), (3.0, T0), (3.0, T0)] + [(3.0 + i * 0.01, T0 + i) for i in range(1, 1001)]
    guard, jumps = sim_guard(readings)
    assert jumps == [None] * len(readings)
    assert guard.inconsistency(13.0) is None and guard.trusted_s == T0 + 1000


def test_sim_clock_going_back_is_a_jump_and_moves_nothing():
    guard, jumps = sim_guard([(0.0, T0), (1.0, T0 + 1.0), (1.1, T0 + 0.999)])
    assert jumps[2].kind == 'back' and 'jumped back' in jumps[2].describe()
    assert guard.trusted_s == T0 + 1.0
    forged_2020 = 1_577_836_800.0
    assert guard.observe(1.2, forged_2020).kind == 'back'
    assert guard.trusted_s == T0 + 1.0
    assert 'jumped back' in guard.inconsistency(1.3)


def test_sim_clock_faster_than_its_rate_bound_is_a_jump_ahead():
    # At 100 x wall with 5 s at once: 150 x wall for long enough exhausts the credit.
    readings = [(0.0, T0)] + [(i * 0.01, T0 + i * 1.5) for i in range(1, 20)]
    _, jumps = sim_guard(readings)
    first = next(i for i, j in enumerate(jumps) if j is not None)
    # The credit starts full (5 s); each 0.01 s adds 1 s and the clock takes 1.5 s: spent at the 9th reading.
    assert jumps[first].kind == 'ahead' and first == 9
    # The same advance at 90 x wall never is.
    _, jumps = sim_guard([(0.0, T0)] + [(i * 0.01, T0 + i * 0.9) for i in range(1, 2000)])
    assert jumps == [None] * 2000


def test_sim_clock_a_day_ahead_is_a_jump_even_after_a_long_standstill():
    # A clock that stood for an hour saved at most max_jump_s of credit.
    guard, jumps = sim_guard([(0.0, T0), (3600.0, T0), (3600.0, T0 + 5.0), (3600.0, T0 + 5.0 + 86400.0)])
    assert jumps[:3] == [None] * 3
    assert jumps[3].kind == 'ahead' and 'jumped ahead 86400.000 s' in jumps[3].describe()
    assert guard.trusted_s == T0 + 5.0


def test_sim_clock_is_trusted_again_only_after_recovery_of_readings_on_the_trusted_clock():
    guard = SimClockGuard(max_rate=100.0, max_jump_s=5.0, recovery_s=2.0)
    guard.observe(0.0, T0)
    assert guard.observe(1.0, T0 - 86400.0) is not None
    # The honest clock goes on; the forger's readings interleave until wall 3.0, each one a jump.
    for i in range(1, 21):
        assert guard.observe(1.0 + i * 0.1, T0 + i * 0.1) is None
        if i <= 10:
            assert guard.observe(1.0 + i * 0.1, T0 - 86400.0) is not None
    assert guard.inconsistency(3.9) is not None  # 1.9 s after the last forged reading
    assert guard.inconsistency(4.0) is None
    # A clock that stays on the forged timeline never is: each reading of it is a jump of its own.
    assert guard.observe(6.0, T0 - 86400.0) is not None
    assert guard.observe(100.0, T0 - 86400.0) is not None and guard.inconsistency(101.9) is not None
    assert guard.jumps == 13


def test_processes_initialising_one_directory_at_once_leave_matching_pairs(tmp_path):
    # Two replays started together on a fresh key directory once left one's private key beside the other's public.
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    code = 'import sys; from controlled_islanding.safety import signing; signing.init_keys(sys.argv[1])'
    for attempt in range(3):
        directory = tmp_path / str(attempt)
        children = [subprocess.Popen([sys.executable, '-c', code, str(directory)]) for _ in range(6)]
        assert [c.wait(timeout=60) for c in children] == [0] * 6
        for role in signing.ROLES:
            paths = signing.key_paths(directory, role)
            derived = signing.load_private_key(paths.private).public_key().public_bytes(
                Encoding.PEM, PublicFormat.SubjectPublicKeyInfo)
            assert derived == paths.public.read_bytes(), (attempt, role)
