"""Single poisoned messages on the real partitioning and breaker_command processes, on sim time as in a replay.

The default bag's own snapshot and 13-14 trip, and a request at the bag's request time, give the baseline:
cut 6-11, and the armed breaker node opens CB-6-11. Then, one at a time, the safety issue's poisons (groups
naming one generator alone, a snapshot copy, a "13-14 in service" status), stamped far ahead and within the
clock tolerance; after each a later request must get the baseline cut, and the breaker node may only refuse
it as a repeat, never open another breaker. With no groups for a request's time, the answer is
REFUSED_STALE_GROUPS, never "no split". The groups are the bag's truth groups, restamped for each request as
the coherency node would stamp them: publishing them by hand is what lets a test decide whether they come
before or after a request.
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path

import pytest
from breaker_cases import private_key
from builtin_interfaces.msg import Time
from controlled_islanding_msgs.msg import (
    BranchStatus,
    BreakerCommand,
    CoherentGroups,
    IslandingDecision,
    IslandingRequest,
    NetworkSnapshot,
)
from controlled_islanding_msgs.srv import SetArmed
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from nodes_harness import graph
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader
from rosgraph_msgs.msg import Clock

from controlled_islanding.graph.supervisor import GRAPH
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.safety import signing
from controlled_islanding.sim.manifest import default_bag, manifest_entries
from controlled_islanding.wire import topics
from controlled_islanding.wire.interfaces import typestore
from controlled_islanding.wire.messages import stamp_s

pytestmark = [pytest.mark.ros, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
NODES = [s for s in GRAPH if s.executable in ('partitioning', 'breaker_command')]
HOUR_S, DAY_S, YEAR_S = 3600, 86_400, 365 * 86_400
AHEAD_S = 0.5  # within both nodes' future_tolerance_s (1.0), so these poisons are taken, not refused
# Each step of sim time stays below future_tolerance_s - AHEAD_S: even a node that has not yet seen the
# newest /clock takes a poison stamped AHEAD_S past it, so no test passes only because its poison was refused.
STEP_S = 0.3
GROUPS_WAIT_S = 0.5
GROUPS_TOLERANCE_S = 0.05  # partitioning's groups_tolerance_s (config/partitioning.yaml)
FRAME_S = 1 / 30  # a frame period at 30 frames/s (GBnetwork's bag): further from a request than groups_exact_s
READERS = {topics.NETWORK_SNAPSHOT: ('partitioning', 'breaker_command'),
           topics.BRANCH_STATUS: ('partitioning', 'breaker_command'),
           topics.COHERENT_GROUPS: ('partitioning',), topics.ISLANDING_REQUEST: ('partitioning',)}


def to_time(t_s: float) -> Time:
    sec = int(t_s)
    return Time(sec=sec, nanosec=int(round((t_s - sec) * 1e9)))


def island_map(decision: IslandingDecision) -> dict[int, int]:
    return dict(zip(decision.bus_numbers, decision.bus_island, strict=True))


def bag_messages() -> dict:
    """Return the default bag's snapshot, branch status, truth groups and request, and its manifest entry.

    The request is rebuilt from the manifest (`request_s` after the snapshot, as the scenario stamps it): its
    message type gains fields over time, and a recorded request of an older type no longer decodes.
    """
    entry = default_bag()
    out = {'entry': entry}
    types = {topics.NETWORK_SNAPSHOT: ('snapshot', NetworkSnapshot), topics.BRANCH_STATUS: ('trip', BranchStatus),
             '/truth/coherent_groups': ('groups', CoherentGroups)}
    with AnyReader([REPO / 'bags' / entry['bag']], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic in types and types[conn.topic][0] not in out:
                key, msg_type = types[conn.topic]
                out[key] = deserialize_message(bytes(raw), msg_type)
    missing = {'snapshot', 'trip', 'groups'} - set(out)
    assert not missing, f'the default bag lacks {missing}'
    request = IslandingRequest(request_id=f'{entry["name"]}/request-1', reason='the scenario request')
    request.header.stamp = to_time(stamp_s(out['snapshot'].header.stamp) + float(entry['request_s']))
    out['request'] = request
    return out


class Decisions:
    """The graph under test, driven on sim time by the probe, with what came out of it."""

    def __init__(self, sup, probe, bag: dict, audit: Path) -> None:
        self.sup, self.probe, self.bag, self.audit = sup, probe, bag, audit
        self.decisions = probe.collect(IslandingDecision, topics.ISLANDING_DECISION)
        self.commands = probe.collect(BreakerCommand, topics.BREAKER_COMMANDS)
        self.levels: dict[str, int] = {}
        probe.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, qos_for(topics.DIAGNOSTICS))
        self.t = 0.0
        self.n = 0
        self.sent = {'partitioning': 0, 'breaker_command': 0}
        self.baseline: IslandingDecision | None = None
        # rclpy's time source reads /clock best effort, so one lost message could leave a node behind: the
        # probe repeats the current time while it spins, as a player publishes /clock all along.
        probe.node.create_timer(0.05, self._tick)

    def _tick(self) -> None:
        if self.t > 0:
            self.publish(topics.CLOCK, Clock(clock=to_time(self.t)))

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.levels[status.name.lstrip('/')] = status.level

    def publish(self, topic: str, msg) -> None:
        for node in READERS.get(topic, ()):
            self.sent[node] += 1
        self.probe.pubs[topic].publish(msg)

    def taken(self, *nodes: str) -> None:
        """Wait until the nodes have received everything sent to them (and, the breaker node, every decision).

        /coherent_groups and /network/snapshot keep only the last message, so a second one published before
        the node took the first would replace it: a test that publishes two in a row waits here in between.
        """
        for node in nodes or tuple(self.sent):
            want = self.sent[node] + (len(self.decisions) if node == 'breaker_command' else 0)
            got = self.probe.wait_counter(node, 'received', want)
            assert got >= want, f'{node} received {got} inputs, {want} were sent'

    def past(self, stamp: float) -> None:
        """Step sim time until requests no longer reach groups stamped up to `stamp`."""
        while self.t - GROUPS_TOLERANCE_S <= stamp:
            self.step()

    def clock(self, t_s: float) -> None:
        """Move sim time to t_s and give both nodes a moment to take it."""
        self.t = t_s
        self.publish(topics.CLOCK, Clock(clock=to_time(t_s)))
        self.probe.spin_for(0.1)

    def step(self) -> float:
        self.clock(self.t + STEP_S)
        return self.t

    def groups(self, t_s: float, alone: str | None = None) -> CoherentGroups:
        """Return the bag's truth groups as coherency would publish them at t_s, or `alone` split from the rest."""
        msg = copy.deepcopy(self.bag['groups'])
        msg.method = 'dtw'
        msg.header.stamp = to_time(t_s)
        if alone is not None:
            msg.group = [int(name == alone) for name in msg.generator_names]
            msg.k = 2
        return msg

    def status(self, t_s: float, in_service: bool) -> BranchStatus:
        msg = copy.deepcopy(self.bag['trip'])
        msg.header.stamp = to_time(t_s)
        msg.in_service = in_service
        return msg

    def request(self, t_s: float, request_id: str | None = None) -> IslandingRequest:
        self.n += 1
        msg = IslandingRequest(request_id=request_id or f'poison-decisions-{self.n}', reason='test')
        msg.header.stamp = to_time(t_s)
        return msg

    def decision_for(self, request: IslandingRequest, timeout_s: float = 10.0) -> IslandingDecision:
        found = self.probe.spin_until(lambda: any(d.request_id == request.request_id for d in self.decisions),
                                      timeout_s)
        assert found, f'no decision for request {request.request_id}'
        return next(d for d in self.decisions if d.request_id == request.request_id)

    def audit_records(self) -> list[dict]:
        return [json.loads(line) for line in self.audit.read_text().splitlines()] if self.audit.exists() else []

    def breaker_record(self, decision: IslandingDecision, timeout_s: float = 10.0) -> dict:
        """Return the breaker node's audit record of a decision (every decision it handles gets one)."""
        def record() -> dict | None:
            return next((r for r in self.audit_records() if r.get('decision_id') == decision.decision_id), None)

        assert self.probe.spin_until(lambda: record() is not None, timeout_s), \
            f'breaker_command never handled decision {decision.decision_id}'
        return record()

    def ask(self, groups_first: bool = True) -> tuple[IslandingDecision, dict]:
        """Advance sim time, publish the honest groups of that time and a request; return decision and audit record."""
        t = self.step()
        request = self.request(t)
        if groups_first:
            self.publish(topics.COHERENT_GROUPS, self.groups(t))
        self.publish(topics.ISLANDING_REQUEST, request)
        if not groups_first:
            self.publish(topics.COHERENT_GROUPS, self.groups(t))
        decision = self.decision_for(request)
        return decision, self.breaker_record(decision)

    def counter(self, node: str, key: str) -> int:
        return self.probe.counter(node, key)

    def commanded(self) -> list[str]:
        """Return the breakers commanded open (the remedial actions' commands are not breakers of the cut)."""
        self.probe.spin_for(0.2)
        return sorted(c.breaker_id for c in self.commands if c.action == BreakerCommand.ACTION_OPEN)

    def assert_baseline(self, decision: IslandingDecision, record: dict, what: str) -> None:
        """Check the decision is the baseline's split, and the breaker node refused it as a repeat."""
        base = self.baseline
        assert base is not None, 'the baseline test must run first'
        assert decision.status == IslandingDecision.STATUS_SPLIT, f'{what}: status {decision.status}, ' \
                                                                   f'{decision.status_detail}'
        assert list(decision.cut_branch_ids) == list(base.cut_branch_ids), \
            f'{what}: cut {list(decision.cut_branch_ids)}, baseline {list(base.cut_branch_ids)}'
        assert island_map(decision) == island_map(base), f'{what}: other islands than the baseline'
        assert record['event'] == 'refusal' and record['reason'] == 'branch_out_of_service', \
            f'{what}: breaker_command did {record}'
        assert self.commanded() == self.baseline_breakers(), f'{what}: breakers opened beyond the baseline cut'

    def baseline_breakers(self) -> list[str]:
        return sorted(f'CB-{b}' for b in self.baseline.cut_branch_ids)

    def healthy(self) -> None:
        self.probe.spin_for(0.2)
        self.sup.check_alive()
        for node in ('partitioning', 'breaker_command'):
            errors = {k: v for k, v in self.probe.diagnostics.get(node, {}).items() if k.startswith('error.')}
            assert not errors, f'{node} caught exceptions in callbacks: {errors}'


@pytest.fixture(scope='module')
def graph_under_test(tmp_path_factory):
    if not manifest_entries():
        pytest.skip('no bags in bags/index.yaml')
    bag = bag_messages()
    audit = tmp_path_factory.mktemp('poison_decisions') / 'audit.jsonl'
    sim = {'use_sim_time': True}
    overrides = {'partitioning': dict(sim, groups_wait_s=GROUPS_WAIT_S, groups_tolerance_s=GROUPS_TOLERANCE_S),
                 'breaker_command': dict(sim, audit_log=str(audit))}
    with graph('test_nodes_poison_decisions', [(s, overrides[s.executable]) for s in NODES]) as (sup, probe):
        for msg_type, topic in ((NetworkSnapshot, topics.NETWORK_SNAPSHOT), (BranchStatus, topics.BRANCH_STATUS),
                                (CoherentGroups, topics.COHERENT_GROUPS), (IslandingRequest, topics.ISLANDING_REQUEST),
                                (Clock, topics.CLOCK)):
            probe.publisher(msg_type, topic)
        g = Decisions(sup, probe, bag, audit)
        probe.wait_matched(topics.CLOCK, 2)
        probe.wait_matched(topics.NETWORK_SNAPSHOT, 2)
        probe.wait_matched(topics.BRANCH_STATUS, 2)
        probe.wait_matched(topics.ISLANDING_REQUEST, 1)
        probe.wait_matched(topics.COHERENT_GROUPS, 1)
        # The baseline decision is volatile: sent before partitioning's writer matched breaker_command's
        # reader, it was lost in one clean-clone CI run, and every later test counted one input short.
        probe.wait_wired(tuple(s.executable for s in NODES))
        yield g


def test_baseline_the_bags_request_cuts_6_11_and_the_breaker_opens_it(graph_under_test):
    g = graph_under_test
    bag, want = g.bag, g.bag['entry']['expected_decision']
    g.clock(stamp_s(bag['snapshot'].header.stamp) + 0.1)
    g.publish(topics.NETWORK_SNAPSHOT, bag['snapshot'])
    n_buses = str(len(bag['snapshot'].bus_numbers))
    assert g.probe.spin_until(lambda: all(g.probe.diagnostics.get(n, {}).get('buses') == n_buses
                                          for n in ('partitioning', 'breaker_command')), 15.0), 'snapshot not taken'
    g.clock(stamp_s(bag['trip'].header.stamp))
    g.publish(topics.BRANCH_STATUS, bag['trip'])
    g.taken()
    armed = g.probe.call(SetArmed, '/breaker_command/set_armed', signing.signed_arm_request(
        SetArmed.Request(), private_key('operator'), '/breaker_command', True, time.time()))
    assert armed.armed, armed.message

    request = bag['request']
    g.clock(stamp_s(request.header.stamp))
    g.publish(topics.COHERENT_GROUPS, g.groups(g.t))
    g.publish(topics.ISLANDING_REQUEST, request)
    decision = g.decision_for(request)
    assert decision.status == IslandingDecision.STATUS_SPLIT, decision.status_detail
    assert list(decision.cut_branch_ids) == want['cut_branches']
    islands = {}
    for bus, island in zip(decision.bus_numbers, decision.bus_island, strict=True):
        islands.setdefault(island, []).append(int(bus))
    assert sorted(islands.values()) == sorted(want['islands'])
    g.baseline = decision
    assert g.breaker_record(decision)['event'] == 'command'
    assert g.commanded() == ['CB-6-11']
    # Its remedial actions (island 0 short of 567.9 MW) were commanded with it, each once.
    sheds = {c.bus: c.amount_mw for c in g.commands if c.action == BreakerCommand.ACTION_SHED_LOAD}
    assert sheds == dict(zip(decision.shed_bus, decision.shed_mw, strict=True))
    assert sum(sheds.values()) == pytest.approx(want['island_shed_mw'][0], abs=1e-2)
    # The same split again, from an honest request: the breaker node refuses to open the breaker twice.
    decision, record = g.ask()
    g.assert_baseline(decision, record, 'a second honest request')
    g.healthy()


def test_groups_a_year_ahead_naming_one_generator_alone_are_refused(graph_under_test):
    """Before, the newest groups won for good: every later decision cut 1-2, 5-8, 6-7 and CB-1-2 opened."""
    g = graph_under_test
    last = g.bag['groups'].generator_names[-1]
    refused = g.counter('partitioning', 'rejected.future_stamp')
    g.publish(topics.COHERENT_GROUPS, g.groups(g.t + YEAR_S, alone=last))
    assert g.probe.wait_counter('partitioning', 'rejected.future_stamp', refused + 1) == refused + 1
    g.taken()
    for _ in range(2):
        decision, record = g.ask(groups_first=False)
        g.assert_baseline(decision, record, f'after groups a year ahead with {last} alone')
    g.healthy()


def test_a_snapshot_copy_an_hour_ahead_is_refused_and_the_trip_still_counts(graph_under_test):
    """Before, the copy made the 13-14 trip count as already included, and the cut changed."""
    g = graph_under_test
    copy_ahead = copy.deepcopy(g.bag['snapshot'])
    copy_ahead.header.stamp = to_time(g.t + HOUR_S)
    refused = {n: g.counter(n, 'rejected.future_stamp') for n in ('partitioning', 'breaker_command')}
    g.publish(topics.NETWORK_SNAPSHOT, copy_ahead)
    for node, count in refused.items():
        assert g.probe.wait_counter(node, 'rejected.future_stamp', count + 1) == count + 1, node
    g.taken()
    for _ in range(2):
        decision, record = g.ask()
        g.assert_baseline(decision, record, 'after a snapshot copy an hour ahead')
    g.healthy()


def test_an_in_service_status_a_day_ahead_is_refused_and_the_trip_still_counts(graph_under_test):
    """Before, partitioning forgot the trip."""
    g = graph_under_test
    refused = {n: g.counter(n, 'rejected.future_stamp') for n in ('partitioning', 'breaker_command')}
    g.publish(topics.BRANCH_STATUS, g.status(g.t + DAY_S, in_service=True))
    for node, count in refused.items():
        assert g.probe.wait_counter(node, 'rejected.future_stamp', count + 1) == count + 1, node
    g.taken()
    for _ in range(2):
        decision, record = g.ask()
        g.assert_baseline(decision, record, 'after an in-service status a day ahead')
    g.healthy()


def test_an_in_service_status_after_the_request_never_undoes_a_trip_before_it(graph_under_test):
    g = graph_under_test
    t = g.step()
    refused = g.counter('partitioning', 'rejected.future_stamp')
    g.publish(topics.BRANCH_STATUS, g.status(t + AHEAD_S, in_service=True))
    g.taken()
    assert g.counter('partitioning', 'rejected.future_stamp') == refused, 'the status within tolerance was refused'
    request = g.request(t)
    g.publish(topics.COHERENT_GROUPS, g.groups(t))
    g.publish(topics.ISLANDING_REQUEST, request)
    decision = g.decision_for(request)
    g.assert_baseline(decision, g.breaker_record(decision), 'a request stamped before an in-service status')
    # The reclosure is real from its stamp on; the line trips again, and decisions after that are the baseline.
    g.clock(t + AHEAD_S + 0.1)
    g.publish(topics.BRANCH_STATUS, g.status(g.t, in_service=False))
    g.taken()
    decision, record = g.ask()
    g.assert_baseline(decision, record, 'after the line tripped again')
    g.healthy()


def test_without_groups_for_the_request_time_the_answer_is_stale_groups_never_no_split(graph_under_test):
    """Before, partitioning decided on whatever groups it held: with coherency stopped, a silent "no split"."""
    g = graph_under_test
    held = max(stamp_s(d.request_stamp) for d in g.decisions)
    g.past(held)
    request = g.request(g.t)
    g.publish(topics.ISLANDING_REQUEST, request)
    decision = g.decision_for(request, timeout_s=GROUPS_WAIT_S + 10.0)
    assert decision.status == IslandingDecision.STATUS_REFUSED_STALE_GROUPS, \
        f'status {decision.status}: {decision.status_detail}'
    assert not decision.split and not decision.cut_branch_ids
    assert decision.signature, 'a refusal is a signed decision too'
    record = g.breaker_record(decision)
    assert record['event'] == 'not_decided' and record['status'] == IslandingDecision.STATUS_REFUSED_STALE_GROUPS
    assert g.commanded() == g.baseline_breakers()

    def faulted() -> bool:
        return (g.levels.get('partitioning') == DiagnosticStatus.ERROR
                and 'fault.last_request' in g.probe.diagnostics.get('partitioning', {}))

    assert g.probe.spin_until(faulted, 5.0), 'partitioning diagnostics did not go to ERROR with fault.last_request'
    assert request.request_id in g.probe.diagnostics['partitioning']['fault.last_request']
    # Fresh groups again: the next request is the baseline decision and the fault clears.
    decision, record = g.ask(groups_first=False)
    g.assert_baseline(decision, record, 'after a stale-groups refusal')
    assert g.probe.spin_until(lambda: 'fault.last_request' not in g.probe.diagnostics.get('partitioning', {}), 5.0)
    g.healthy()


def test_groups_half_a_second_ahead_never_hide_the_honest_groups_already_held(graph_under_test):
    g = graph_under_test
    last = g.bag['groups'].generator_names[-1]
    t = g.step()
    g.publish(topics.COHERENT_GROUPS, g.groups(t))
    g.taken()
    g.publish(topics.COHERENT_GROUPS, g.groups(t + AHEAD_S, alone=last))
    g.taken()
    request = g.request(t)
    g.publish(topics.ISLANDING_REQUEST, request)
    decision = g.decision_for(request)
    try:
        g.assert_baseline(decision, g.breaker_record(decision), f'groups {AHEAD_S} s ahead with {last} alone')
    finally:
        g.past(t + AHEAD_S)
    g.healthy()


def test_groups_half_a_second_ahead_are_never_used_before_the_honest_groups_come(graph_under_test):
    """As in the live graph: coherency recomputes on the request, so its groups for T come after the request.

    A grouping stamped AHEAD_S past T naming one generator alone, taken before the request, must not be the
    request's groups; the honest ones, published right after the request, are.
    """
    g = graph_under_test
    last = g.bag['groups'].generator_names[-1]
    t = g.step()
    g.publish(topics.COHERENT_GROUPS, g.groups(t + AHEAD_S, alone=last))
    g.taken()
    request = g.request(t)
    g.publish(topics.ISLANDING_REQUEST, request)
    g.probe.spin_for(0.05)
    g.publish(topics.COHERENT_GROUPS, g.groups(t))
    decision = g.decision_for(request)
    try:
        g.assert_baseline(decision, g.breaker_record(decision), f'groups {AHEAD_S} s ahead with {last} alone, '
                                                                f'honest groups after the request')
    finally:
        g.past(t + AHEAD_S)
    g.healthy()


def test_a_periodic_grouping_a_frame_before_the_request_never_answers_it_before_its_own(graph_under_test):
    """A periodic grouping a frame before the request that reaches partitioning after the request is no answer.

    Found on GBnetwork in a suite run: coherency's periodic grouping of the frame before the request, which saw
    no separation yet, reached partitioning after the request and was taken; the request's own came later.
    """
    g = graph_under_test
    last = g.bag['groups'].generator_names[-1]
    t = g.step()
    request = g.request(t)
    g.publish(topics.ISLANDING_REQUEST, request)
    g.probe.spin_for(0.2)  # loopback delivers in milliseconds; the request must be in before the groups
    g.publish(topics.COHERENT_GROUPS, g.groups(t - FRAME_S, alone=last))
    answer = g.groups(t)
    answer.request_id = request.request_id
    g.publish(topics.COHERENT_GROUPS, answer)  # within groups_wait_s: both are held (depth 16), in this order
    decision = g.decision_for(request)
    g.assert_baseline(decision, g.breaker_record(decision), f'periodic groups {FRAME_S} s before the request '
                                                            f'with {last} alone, after the request')
    g.healthy()


def test_a_periodic_grouping_of_the_frame_before_held_before_the_request_never_answers_it(graph_under_test):
    """At 60 frames/s the frame before is 16.7 ms, within groups_exact_s; its grouping is still no answer.

    Found in `testbed --trigger monitor` on IEEE 39 G6-G7 (loss, silent PMU): coherency's periodic grouping of the
    frame before the monitor's request, made before that request's own frame raised the alarm, was already held
    when the request came, and decided it: no split.
    """
    g = graph_under_test
    last = g.bag['groups'].generator_names[-1]
    t = g.step()
    g.publish(topics.COHERENT_GROUPS, g.groups(t - 1 / 60, alone=last))
    g.taken('partitioning')
    request = g.request(t)
    g.publish(topics.ISLANDING_REQUEST, request)
    g.probe.spin_for(0.2)
    answer = g.groups(t)
    answer.request_id = request.request_id
    g.publish(topics.COHERENT_GROUPS, answer)
    decision = g.decision_for(request)
    g.assert_baseline(decision, g.breaker_record(decision), 'periodic groups 1/60 s before the request with '
                                                            f'{last} alone, held before it')
    g.healthy()


def test_the_requests_own_grouping_a_frame_before_it_answers_it_before_the_wait_ends(graph_under_test):
    """Where the request's own frame is missing, coherency's answer ends a frame earlier and carries its id.

    A periodic grouping further before, within the tolerance, with one generator alone, is also held: at the end
    of the wait the earliest within the tolerance would be taken, so only the answer taken at once gives the
    baseline.
    """
    g = graph_under_test
    last = g.bag['groups'].generator_names[-1]
    t = g.step()
    g.publish(topics.COHERENT_GROUPS, g.groups(t - 0.9 * GROUPS_TOLERANCE_S, alone=last))
    g.taken('partitioning')
    request = g.request(t)
    g.publish(topics.ISLANDING_REQUEST, request)
    g.probe.spin_for(0.2)
    answer = g.groups(t - FRAME_S)
    answer.request_id = request.request_id
    g.publish(topics.COHERENT_GROUPS, answer)
    decision = g.decision_for(request)
    g.assert_baseline(decision, g.breaker_record(decision), "the request's own groups a frame before it")
    g.healthy()


def test_a_snapshot_copy_after_the_request_never_undoes_a_trip_before_it(graph_under_test):
    """A snapshot copy stamped AHEAD_S past T must not make the 13-14 trip, stamped before T, count as included."""
    g = graph_under_test
    t = g.step()
    copy_ahead = copy.deepcopy(g.bag['snapshot'])
    copy_ahead.header.stamp = to_time(t + AHEAD_S)
    g.publish(topics.NETWORK_SNAPSHOT, copy_ahead)
    g.taken()
    request = g.request(t)
    g.publish(topics.COHERENT_GROUPS, g.groups(t))
    g.publish(topics.ISLANDING_REQUEST, request)
    decision = g.decision_for(request)
    g.assert_baseline(decision, g.breaker_record(decision), f'a snapshot copy stamped {AHEAD_S} s after the request')
    g.healthy()
