"""breaker_command and partitioning under use_sim_time as real processes: a forged /clock makes nothing fresh.

The honest clock is the test's own /clock at wall speed from the bag era; a second node, with a publisher of
its own, forges /clock beside it (2020, then a day ahead) and then alone. Signed decisions stamped on the
forged clock (a recorded decision played back, say) and on the honest one get no command while the clock is
inconsistent; once the forger stops and the honest clock ran `sim_clock_recovery_s`, one does. partitioning
refuses to stamp a request on the forged clock.
"""

from __future__ import annotations

import json
import time

import pytest
import rclpy
from breaker_cases import boundary, decision_msg, private_key, snapshot_msg, two_islands
from controlled_islanding_msgs.msg import BreakerCommand, IslandingDecision, NetworkSnapshot
from controlled_islanding_msgs.srv import RequestIslanding, SetArmed
from nodes_harness import graph
from rosgraph_msgs.msg import Clock

from controlled_islanding.core.grid import Grid
from controlled_islanding.graph.supervisor import GRAPH
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.safety import signing
from controlled_islanding.wire import topics

pytestmark = [pytest.mark.ros, pytest.mark.slow]

BREAKER = next(s for s in GRAPH if s.executable == 'breaker_command')
NODE = 'breaker_command'
GRID = Grid.from_matpower('case14').with_flows()
BAG_ERA_NS = 1_767_225_600 * 10**9
YEAR_2020_NS = 1_577_836_800 * 10**9
DAY_NS = 86_400 * 10**9
RECOVERY_S = 1.0


class Clocks:
    """The honest /clock (wall speed from the bag era, every 20 ms) and a forger's (every 7 ms), each its own node.

    Two periods, so that each clock is at times the last one a node's keep-last-1 /clock reader took.
    """

    def __init__(self, probe) -> None:
        self.m0 = time.monotonic()
        self.honest_on, self.forged_base_ns = True, None
        honest = probe.publisher(Clock, topics.CLOCK)
        self.forger = rclpy.create_node('clock_forger', context=probe.context)
        forged = self.forger.create_publisher(Clock, topics.CLOCK, qos_for(topics.CLOCK))
        probe.executor.add_node(self.forger)
        probe.node.create_timer(0.02, lambda: self.honest_on and honest.publish(self._msg(self.honest_ns())))
        self.forger.create_timer(0.007, lambda: self.forged_base_ns is not None and forged.publish(
            self._msg(self.forged_ns())))

    def _elapsed_ns(self) -> int:
        return int((time.monotonic() - self.m0) * 1e9)

    def honest_ns(self) -> int:
        return BAG_ERA_NS + self._elapsed_ns()

    def forged_ns(self) -> int:
        return self.forged_base_ns + self._elapsed_ns()

    @staticmethod
    def _msg(t_ns: int) -> Clock:
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(t_ns, 10**9)
        return msg


def test_a_forged_clock_beside_the_honest_one_and_alone_gets_no_command(tmp_path):
    audit = tmp_path / 'audit.jsonl'
    island = two_islands(GRID)
    cut = boundary(GRID, island)
    params = {'audit_log': audit, 'max_decision_age_s': 30.0, 'max_breakers': 8, 'use_sim_time': True,
              'sim_clock_recovery_s': RECOVERY_S}
    with graph('breaker_sim_clock', [(BREAKER, params)]) as (sup, probe):
        clocks = Clocks(probe)
        probe.publisher(IslandingDecision, topics.ISLANDING_DECISION)
        probe.publisher(NetworkSnapshot, topics.NETWORK_SNAPSHOT)
        commands = probe.collect(BreakerCommand, topics.BREAKER_COMMANDS)
        probe.wait_matched(topics.ISLANDING_DECISION)
        probe.wait_matched(topics.CLOCK)
        probe.wait_matched(topics.NETWORK_SNAPSHOT)
        probe.spin_for(0.3)
        probe.pubs[topics.NETWORK_SNAPSHOT].publish(snapshot_msg(GRID, clocks.honest_ns()))
        assert probe.spin_until(lambda: probe.diagnostics.get(NODE, {}).get('buses') == str(len(GRID.buses)), 15.0)
        request = signing.signed_arm_request(SetArmed.Request(), private_key('operator'), '/breaker_command', True,
                                             time.time())
        assert probe.call(SetArmed, '/breaker_command/set_armed', request).armed

        def refused(n: int, stamp_ns: int) -> None:
            probe.pubs[topics.ISLANDING_DECISION].publish(decision_msg(island, cut, stamp_ns))
            assert probe.wait_counter(NODE, 'rejected.clock_inconsistent', n) == n, probe.diagnostics.get(NODE)

        # Beside the honest clock: a recorded decision of 2020 on a clock of 2020, and an honest one meanwhile.
        clocks.forged_base_ns = YEAR_2020_NS
        assert probe.spin_until(lambda: 'jumped back' in probe.diagnostics.get(NODE, {}).get(
            'fault.clock_inconsistent', ''), 10.0), probe.diagnostics.get(NODE)
        refused(1, clocks.forged_ns())
        refused(2, clocks.honest_ns())
        # A day ahead, beside the honest clock.
        clocks.forged_base_ns = BAG_ERA_NS + DAY_NS
        assert probe.spin_until(lambda: 'jumped ahead' in probe.diagnostics.get(NODE, {}).get(
            'fault.clock_inconsistent', ''), 10.0), probe.diagnostics.get(NODE)
        refused(3, clocks.forged_ns())
        # Alone: the honest clock stops, the forger's of 2020 runs on, longer than the recovery.
        clocks.honest_on, clocks.forged_base_ns = False, YEAR_2020_NS
        probe.spin_for(RECOVERY_S + 0.5)
        refused(4, clocks.forged_ns())
        assert commands == []
        # The forger stops, the honest clock runs on: trusted again after the recovery, and an honest decision acts.
        clocks.forged_base_ns, clocks.honest_on = None, True
        probe.spin_for(RECOVERY_S + 0.5)
        probe.pubs[topics.ISLANDING_DECISION].publish(decision_msg(island, cut, clocks.honest_ns()))
        assert probe.spin_until(lambda: len(commands) == len(cut), 10.0), probe.diagnostics.get(NODE)
        assert probe.spin_until(lambda: 'fault.clock_inconsistent' not in probe.diagnostics.get(NODE, {}), 5.0)
        probe.spin_for(0.5)
        assert not [k for k in probe.diagnostics[NODE] if k.startswith('error.')], probe.diagnostics[NODE]
        sup.check_alive()
    records = [json.loads(line) for line in audit.read_text().splitlines()]
    jumps = [r for r in records if r['event'] == 'clock_jump']
    assert {r['kind'] for r in jumps} == {'back', 'ahead'}, jumps
    assert all(r['detail'].startswith('sim clock jumped') for r in jumps)
    assert [r['reason'] for r in records if r['event'] == 'refusal'] == ['clock_inconsistent'] * 4
    assert [r['event'] for r in records].count('command') == 1


def test_partitioning_stamps_no_request_on_a_forged_clock():
    partitioning = next(s for s in GRAPH if s.executable == 'partitioning')
    params = {'use_sim_time': True, 'sim_clock_recovery_s': RECOVERY_S}
    with graph('partitioning_sim_clock', [(partitioning, params)]) as (sup, probe):
        clocks = Clocks(probe)
        probe.wait_matched(topics.CLOCK)
        # A match is not a delivery: on a loaded machine the node's first /clock came later than 0.3 s (CI).
        deadline = time.monotonic() + 10.0
        while True:
            response = probe.call(RequestIslanding, '/partitioning/request', RequestIslanding.Request(reason='honest'))
            if response.accepted or 'not started' not in response.message or time.monotonic() > deadline:
                break
            probe.spin_for(0.1)
        assert response.accepted, response.message
        clocks.forged_base_ns = YEAR_2020_NS
        assert probe.spin_until(lambda: 'jumped back' in probe.diagnostics.get('partitioning', {}).get(
            'fault.clock_inconsistent', ''), 10.0), probe.diagnostics.get('partitioning')
        response = probe.call(RequestIslanding, '/partitioning/request', RequestIslanding.Request(reason='forged'))
        assert not response.accepted and 'cannot be trusted' in response.message, response.message
        assert probe.wait_counter('partitioning', 'rejected.clock_inconsistent', 1) == 1
        sup.check_alive()
