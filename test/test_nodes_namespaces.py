"""Two control areas side by side on one domain, and diagnostics levels that follow the current state (issue 14).

pmu_ingestion and partitioning run in /area1 and in /area2, on one domain, on wall time. Each node's whole
interface (topics, services) lies in its namespace, apart from the global /diagnostics, /rosout and
/parameter_events, and its config/*.yaml reaches it there. A request in one area is decided there, on that area's
data, and nowhere else. On /area1/pmu_ingestion, fed 60 frames/s from the default bag (restamped to now):
/pmu/frames has a diagnostic_updater frequency status that meets 60 Hz; a PMU left out of the frames for longer
than `stale_pmu_s` turns the node WARN, naming it, and OK again once it is back; a rejected frame is WARN for
`diagnostics_hold_s`, then OK, while its counter stays; when the frames stop, the frequency status falls.
"""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path

import pytest
import yaml
from builtin_interfaces.msg import Time
from controlled_islanding_msgs.msg import CoherentGroups, IslandingDecision, IslandingRequest, NetworkSnapshot, PmuFrame
from diagnostic_msgs.msg import DiagnosticStatus
from nodes_harness import graph
from rcl_interfaces.srv import GetParameters
from rclpy._rclpy_pybind11 import NodeNameNonExistentError
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader

from controlled_islanding.graph.supervisor import GRAPH
from controlled_islanding.locations import config_dir
from controlled_islanding.sim.manifest import default_bag, manifest_entries
from controlled_islanding.wire import topics
from controlled_islanding.wire.interfaces import typestore

pytestmark = [pytest.mark.ros, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
AREAS = ('/area1', '/area2')
NODES = [s for s in GRAPH if s.executable in ('pmu_ingestion', 'partitioning')]
HOLD_S = 1.0  # diagnostics_hold_s of pmu_ingestion here (10 s by default)
RATE_HZ = 60.0


def to_time(t_s: float) -> Time:
    return Time(sec=int(t_s), nanosec=int(round((t_s - int(t_s)) * 1e9)) % 1_000_000_000)


def bag_messages() -> tuple[NetworkSnapshot, CoherentGroups, list[PmuFrame]]:
    snapshot, groups, frames = None, None, []
    with AnyReader([REPO / 'bags' / default_bag()['bag']], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic == topics.NETWORK_SNAPSHOT and snapshot is None:
                snapshot = deserialize_message(bytes(raw), NetworkSnapshot)
            elif conn.topic == topics.TRUTH_COHERENT_GROUPS and groups is None:
                groups = deserialize_message(bytes(raw), CoherentGroups)
            elif conn.topic == topics.PMU_FRAMES and len(frames) < 60:
                frames.append(deserialize_message(bytes(raw), PmuFrame))
    return snapshot, groups, frames


@pytest.fixture(scope='module')
def areas():
    if not manifest_entries():
        pytest.skip('no bags in bags/index.yaml')
    snapshot, groups, frames = bag_messages()
    # Stream loops one second of the bag under fresh time tags, which the bad-data tests rightly take for replayed
    # frames (test_nodes_suspect_data covers them); this module is about names and diagnostics levels.
    overrides = {'pmu_ingestion': {'diagnostics_hold_s': HOLD_S, 'rate_fps': RATE_HZ, 'bad_data': False},
                 'partitioning': {}}
    specs = [(s, overrides[s.executable], area) for area in AREAS for s in NODES]
    with graph('test_nodes_namespaces', specs) as (sup, probe):
        for area in AREAS:
            for msg_type, topic in ((NetworkSnapshot, topics.NETWORK_SNAPSHOT), (PmuFrame, topics.PMU_FRAMES),
                                    (CoherentGroups, topics.COHERENT_GROUPS),
                                    (IslandingRequest, topics.ISLANDING_REQUEST)):
                probe.publisher(msg_type, topics.in_namespace(topic, area))
            probe.collect(IslandingDecision, topics.in_namespace(topics.ISLANDING_DECISION, area))
        probe.collect(IslandingDecision, topics.ISLANDING_DECISION)
        for area in AREAS:
            probe.wait_matched(topics.in_namespace(topics.NETWORK_SNAPSHOT, area), 2)
            probe.wait_matched(topics.in_namespace(topics.PMU_FRAMES, area), 1)
            probe.wait_matched(topics.in_namespace(topics.ISLANDING_REQUEST, area), 1)
        yield sup, probe, snapshot, groups, frames


def interface(probe, node: str, area: str) -> set[str]:
    """Return every topic and service name a node uses (empty while discovery has not seen it)."""
    found = probe.node
    try:
        return {name for query in (found.get_publisher_names_and_types_by_node,
                                   found.get_subscriber_names_and_types_by_node,
                                   found.get_service_names_and_types_by_node)
                for name, _ in query(node, area)}
    except NodeNameNonExistentError:
        return set()


def test_every_name_of_a_namespaced_node_is_in_its_namespace(areas):
    sup, probe, *_ = areas
    want = {'pmu_ingestion': ('/rotor_angles', '/pmu/frames', '/network/snapshot'),
            'partitioning': ('/islanding/decision', '/islanding/request', '/coherent_groups',
                             '/network/branch_status', '/partitioning/request')}
    for area in AREAS:
        for node, names in want.items():
            expected = {f'{area}{n}' for n in names}
            assert probe.spin_until(lambda n=node, a=area, e=expected: e <= interface(probe, n, a), 20.0), \
                f'{area}/{node} lacks {expected - interface(probe, node, area)}'
            outside = sorted(n for n in interface(probe, node, area)
                             if not n.startswith(f'{area}/') and n not in topics.GLOBAL)
            assert not outside, f'{area}/{node} uses names outside its namespace: {outside}'
    # The parameter files key each node as /**/<name>, so they reach it in any namespace.
    configured = yaml.safe_load((config_dir() / 'partitioning.yaml').read_text())['/**/partitioning']
    wait_s = configured['ros__parameters']['groups_wait_s']
    assert wait_s != 0.5, 'the configured value must differ from the default for this check to mean anything'
    for area in AREAS:
        got = probe.call(GetParameters, f'{area}/partitioning/get_parameters', GetParameters.Request(
            names=['groups_wait_s'])).values[0].double_value
        assert got == wait_s, f'{area}/partitioning runs without config/partitioning.yaml'
    for topic in (topics.PMU_FRAMES, topics.ROTOR_ANGLES, topics.ISLANDING_DECISION, topics.NETWORK_SNAPSHOT):
        users = [i.node_name for i in (probe.node.get_publishers_info_by_topic(topic)
                                       + probe.node.get_subscriptions_info_by_topic(topic))]
        assert set(users) <= {probe.node.get_name()}, f'{topic} in the root namespace is used by {users}'
    sup.check_alive()


def test_a_request_is_decided_in_its_own_area_on_its_own_data_and_nowhere_else(areas):
    sup, probe, snapshot, groups, _frames = areas
    decisions = {area: probe.received[topics.in_namespace(topics.ISLANDING_DECISION, area)] for area in AREAS}
    root = probe.received[topics.ISLANDING_DECISION]
    one_group = copy.deepcopy(groups)
    one_group.group, one_group.k = [0] * len(groups.generator_names), 1
    status = {}
    for area, area_groups in zip(AREAS, (groups, one_group), strict=True):
        t = time.time()
        snap = copy.deepcopy(snapshot)
        snap.header.stamp = to_time(t - 1.0)
        probe.pubs[topics.in_namespace(topics.NETWORK_SNAPSHOT, area)].publish(snap)
        node = f'{area.strip("/")}/partitioning'
        buses = str(len(snap.bus_numbers))
        assert probe.spin_until(lambda n=node, b=buses: probe.diagnostics.get(n, {}).get('buses') == b, 15.0), \
            f'{node} did not take the snapshot'
        t = time.time()
        msg = copy.deepcopy(area_groups)
        msg.method, msg.header.stamp = 'dtw', to_time(t)
        probe.pubs[topics.in_namespace(topics.COHERENT_GROUPS, area)].publish(msg)
        request = IslandingRequest(request_id=f'request-in-{area.strip("/")}', reason='test')
        request.header.stamp = to_time(t)
        probe.pubs[topics.in_namespace(topics.ISLANDING_REQUEST, area)].publish(request)
        assert probe.spin_until(lambda a=area: len(decisions[a]) == 1, 15.0), f'no decision in {area}'
        probe.spin_for(0.5)  # room for a stray decision elsewhere
        assert decisions[area][0].request_id == request.request_id
        assert all(len(d) == 1 for a, d in decisions.items() if a <= area), \
            {a: [m.request_id for m in d] for a, d in decisions.items()}
        assert not root, 'a decision reached the root namespace'
        status[area] = decisions[area][0].status
    assert status == {'/area1': IslandingDecision.STATUS_SPLIT, '/area2': IslandingDecision.STATUS_NO_SPLIT}, status
    sup.check_alive()


class Stream:
    """Publishes the bag's frames at RATE_HZ into one area, restamped to now, while the probe spins."""

    def __init__(self, probe, frames: list[PmuFrame], area: str) -> None:
        self.probe, self.frames, self.n = probe, frames, 0
        self.pub = probe.pubs[topics.in_namespace(topics.PMU_FRAMES, area)]
        self.t0 = time.time()

    def until(self, predicate, timeout_s: float, leave_out: str | None = None, poison: bool = False) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            due = self.t0 + self.n / RATE_HZ
            if time.time() >= due:
                frame = copy.deepcopy(self.frames[self.n % len(self.frames)])
                frame.header.stamp = to_time(due)
                if leave_out is not None:
                    frame.measurements = [m for m in frame.measurements if m.station_id != leave_out]
                if poison:
                    frame.measurements[0].voltage_angle_rad, frame.measurements[0].stat = math.nan, 0
                    poison = False
                self.pub.publish(frame)
                self.n += 1
                continue
            self.probe.executor.spin_once(timeout_sec=min(0.005, max(0.0, due - time.time())))
            if predicate():
                return True
        return predicate()


def test_levels_follow_the_current_state_and_pmu_frames_has_a_frequency_status(areas):
    sup, probe, snapshot, _groups, frames = areas
    node = 'area1/pmu_ingestion'
    frames_status = 'area1/pmu_ingestion: /area1/pmu/frames topic status'
    snap = copy.deepcopy(snapshot)
    snap.header.stamp = to_time(time.time() - 1.0)
    probe.pubs[topics.in_namespace(topics.NETWORK_SNAPSHOT, '/area1')].publish(snap)

    def level(name: str) -> int:
        return probe.levels.get(name, (b'', ''))[0]

    def message(name: str) -> str:
        return probe.levels.get(name, (b'', ''))[1]

    stream = Stream(probe, frames, '/area1')
    # The rate window spans 5 one-second publishes: it must first fill with streaming.
    met = stream.until(lambda: level(frames_status) == DiagnosticStatus.OK and level(node) == DiagnosticStatus.OK
                       and message(frames_status) == 'Desired frequency met', 15.0)
    assert met, (probe.levels.get(node), probe.levels.get(frames_status), probe.diagnostics.get(frames_status))
    values = probe.diagnostics[frames_status]
    assert values['Target frequency (Hz)'].startswith('60.0')
    assert 0.9 * RATE_HZ <= float(values['Actual frequency (Hz)']) <= 1.1 * RATE_HZ

    silent = frames[0].measurements[0].station_id
    assert stream.until(lambda: level(node) == DiagnosticStatus.WARN and silent in message(node), 5.0,
                        leave_out=silent), f'a PMU silent beyond stale_pmu_s is not WARN: {probe.levels.get(node)}'
    assert silent in probe.diagnostics[node]['warn.stale_pmus']
    assert stream.until(lambda: level(node) == DiagnosticStatus.OK, 5.0), \
        f'the PMU is back, yet: {probe.levels.get(node)}'

    before = probe.counter(node, 'rejected.nan_value')
    assert stream.until(lambda: level(node) == DiagnosticStatus.WARN and 'nan_value' in message(node), 5.0,
                        poison=True), f'a rejected frame is not WARN: {probe.levels.get(node)}'
    warned_at = time.monotonic()
    assert stream.until(lambda: level(node) == DiagnosticStatus.OK, HOLD_S + 3.0), \
        f'WARN did not clear after the hold: {probe.levels.get(node)}'
    assert time.monotonic() - warned_at >= HOLD_S - 0.5, 'WARN cleared before the hold'
    assert probe.counter(node, 'rejected.nan_value') == before + 1, 'the reject counter is a total'

    assert probe.spin_until(lambda: level(frames_status) >= DiagnosticStatus.WARN, 4.0), \
        f'frames stopped, yet: {probe.levels.get(frames_status)}'
    other_frames = probe.diagnostics['area2/pmu_ingestion: /area2/pmu/frames topic status']
    assert other_frames['Events since startup'] == '0', 'area2 received the frames sent to area1'
    sup.check_alive()
