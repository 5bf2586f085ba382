"""A suspect PMU station through the real pmu_ingestion, coherency and partitioning node code, in one process.

The nodes are constructed as they run, and their inputs are handed to the methods their subscriptions call
(after the clock gate); what each publishes is caught at its publisher. The wire itself is covered by the
process tests (test_nodes_bad_input.py); these check what the new message fields carry.
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import pytest
from breaker_cases import made_test_keys
from controlled_islanding_msgs.msg import IslandingDecision, IslandingRequest, NetworkSnapshot, PmuFrame, RotorAngles
from nodes_harness import default_context
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader

from controlled_islanding.sim.manifest import default_bag, manifest_entries
from controlled_islanding.wire import topics
from controlled_islanding.wire.interfaces import typestore
from controlled_islanding.wire.messages import groups_from_msg, split_stamp, stamp_s

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(scope='module')
def bag():
    if not manifest_entries():
        pytest.skip('no bags in bags/index.yaml')
    frames, snapshot = [], None
    with AnyReader([REPO / 'bags' / default_bag()['bag']], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic == topics.NETWORK_SNAPSHOT and snapshot is None:
                snapshot = deserialize_message(bytes(raw), NetworkSnapshot)
            elif conn.topic == topics.PMU_FRAMES and len(frames) < 200:
                frames.append(deserialize_message(bytes(raw), PmuFrame))
    with default_context():  # the nodes made here join it
        yield snapshot, frames


def caught(node, attribute: str) -> list:
    out: list = []
    getattr(node, attribute).publish = out.append
    return out


def frozen_samples(snapshot, frames) -> tuple[list[RotorAngles], object, str]:
    from controlled_islanding.nodes.pmu_ingestion import PmuIngestionNode

    node = PmuIngestionNode()
    angles = caught(node, 'pub')
    node._take_snapshot(snapshot)
    for frame in frames:
        msg = copy.deepcopy(frame)
        msg.measurements[0] = copy.deepcopy(frames[0].measurements[0])  # one station frozen, STAT good
        node._take_frame(msg)
    return angles, node, frames[0].measurements[0].station_id


def test_pmu_ingestion_marks_a_frozen_station_invalid_with_its_reason_and_warns(bag):
    snapshot, frames = bag
    angles, node, victim = frozen_samples(snapshot, frames)
    gen = next(g for g, b in zip(snapshot.generator_names, snapshot.generator_bus, strict=True)
               if b == frames[0].measurements[0].bus)
    j = list(angles[-1].generator_names).index(gen)
    marked = [a for a in angles if a.suspect_reason]
    assert marked and all(a.suspect_reason[j] == f'frozen: {victim}' and not a.valid[j] for a in marked)
    assert all(not any(r for i, r in enumerate(a.suspect_reason) if i != j) for a in marked)
    # Flagged after frozen_frames repeats, and kept to the end: the values never move again.
    assert len(marked) >= len(frames) - 5 and angles[-1].suspect_reason[j]
    assert victim in node.diag.values['suspect_stations'] and node.diag.values['suspect_flags'] == '1'
    assert 'suspect_data' in node.diag.warnings
    node.destroy_node()


def test_an_honest_stream_marks_nothing(bag):
    from controlled_islanding.nodes.pmu_ingestion import PmuIngestionNode

    snapshot, frames = bag
    node = PmuIngestionNode()
    angles = caught(node, 'pub')
    node._take_snapshot(snapshot)
    for frame in frames:
        node._take_frame(frame)
    assert len(angles) == len(frames) and not any(a.suspect_reason for a in angles)
    assert all(all(a.valid) for a in angles[1:])
    assert node.diag.values['grid_at_rest'] == 'yes' and 'last_event_s' not in node.diag.values
    # Every voltage 10 % down at once is an event: the tests against the snapshot stop and the time is shown.
    dip = copy.deepcopy(frames[-1])
    dip.header.stamp.sec, dip.header.stamp.nanosec = split_stamp(stamp_s(frames[-1].header.stamp) + 1 / 60)
    for m in dip.measurements:
        m.voltage_magnitude_pu *= 0.9
    node._take_frame(dip)
    assert node.diag.values['grid_at_rest'] == 'no'
    assert node.diag.values['last_event_s'] == f'{stamp_s(dip.header.stamp):.3f}'
    node.destroy_node()


def test_each_snapshot_taken_is_the_bad_data_tests_reference_from_its_stamp(bag):
    """After an event, the tests at rest judge again only under a snapshot stamped since (core/bad_data.py)."""
    from controlled_islanding.nodes.pmu_ingestion import PmuIngestionNode

    snapshot, frames = bag
    node = PmuIngestionNode()
    node._take_snapshot(snapshot)
    assert node.detector.reference_s == stamp_s(snapshot.header.stamp)
    newer = copy.deepcopy(snapshot)
    newer.header.stamp = frames[-1].header.stamp
    node._take_snapshot(newer)
    assert node.detector.reference_s == stamp_s(frames[-1].header.stamp) > stamp_s(snapshot.header.stamp)
    node.destroy_node()


def test_pmu_ingestion_names_a_station_offset_from_the_snapshot_and_from_the_others_of_its_bus(bag):
    """Nordic 44's bus 6000 has four machines, each with its own channel: one offset 20 deg from its first frame."""
    import math

    from controlled_islanding.nodes.pmu_ingestion import PmuIngestionNode

    frames, snapshot = [], None
    with AnyReader([REPO / 'bags' / 'nordic44_bus6000_three_groups'], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic == topics.NETWORK_SNAPSHOT and snapshot is None:
                snapshot = deserialize_message(bytes(raw), NetworkSnapshot)
            elif conn.topic == topics.PMU_FRAMES and len(frames) < 20:
                frames.append(deserialize_message(bytes(raw), PmuFrame))
    victim = 'PMU_6000/GENROU_34'
    blind = copy.deepcopy(snapshot)
    blind.bus_voltage_angle_rad = []
    # With the snapshot's bus angles the angle test at rest names it; without, the other stations of its bus do.
    for snap, why in ((snapshot, 'angle_mismatch'), (blind, 'bus_disagreement')):
        node = PmuIngestionNode()
        angles = caught(node, 'pub')
        node._take_snapshot(snap)
        for frame in frames:
            msg = copy.deepcopy(frame)
            m = next(m for m in msg.measurements if m.station_id == victim)
            m.voltage_angle_rad += math.radians(20.0)
            m.current_angle_rad += math.radians(20.0)
            node._take_frame(msg)
        j = list(angles[0].generator_names).index('GENROU_34')
        assert all(a.suspect_reason[j] == f'{why}: {victim}' and not a.valid[j] for a in angles)
        assert not any(r for a in angles for i, r in enumerate(a.suspect_reason) if i != j)
        assert victim in node.diag.values['suspect_stations'] and 'suspect_data' in node.diag.warnings
        node.destroy_node()


def test_coherency_lists_the_suspect_apart_and_partitioning_refuses_naming_it(bag):
    from controlled_islanding.nodes.coherency import CoherencyNode
    from controlled_islanding.nodes.partitioning import PartitioningNode

    snapshot, frames = bag
    angles, ingestion, victim = frozen_samples(snapshot, frames)
    ingestion.destroy_node()
    coherency = CoherencyNode()
    groups = caught(coherency, 'pub')
    coherency._take_snapshot(snapshot)
    for sample in angles:
        coherency._take_angles(sample)
    coherency._compute(coherency.t_s[-1], 'r1')
    msg = groups[-1]
    gen = next(g for g, b in zip(snapshot.generator_names, snapshot.generator_bus, strict=True)
               if b == frames[0].measurements[0].bus)
    assert list(msg.suspect_generator_names) == [gen] and list(msg.suspect_reasons) == [f'frozen: {victim}']
    assert gen in msg.unobserved_generator_names and gen not in msg.generator_names
    coherency.destroy_node()

    made_test_keys()  # the node signs with CONTROLLED_ISLANDING_KEYS (conftest), which no other test need have made
    partitioning = PartitioningNode()
    decisions = caught(partitioning, 'decision_pub')
    partitioning._apply_input(('snapshot', *partitioning_snapshot(partitioning, snapshot)))
    decoded = groups_from_msg(msg, partitioning.intake.limits)
    assert decoded.suspect == ((gen, f'frozen: {victim}'),)
    request = IslandingRequest(request_id='r1', reason='test')
    request.header.stamp = msg.header.stamp
    partitioning._answer(request, decoded)
    decision = decisions[-1]
    assert decision.status == IslandingDecision.STATUS_REFUSED_SUSPECT_DATA and not decision.split
    assert list(decision.suspect_generator_names) == [gen] and victim in decision.status_detail
    assert not decision.cut_branch_ids
    partitioning.destroy_node()


def partitioning_snapshot(node, snapshot) -> tuple:
    from controlled_islanding.wire.messages import stamp_s

    grid = node.intake.grid(snapshot)
    assert grid is not None
    return grid, stamp_s(snapshot.header.stamp)


@pytest.mark.parametrize('ratio', [
    2.0,
    pytest.param(1.5, marks=pytest.mark.xfail(strict=True, reason=(
        "found in CI: the innovation of G6's station peaks at 42 against the 55.3 bound (chi-square(2) at 1e-12) "
        "and decays within 0.1 s. Diagnosed: the error starts on the fault's first frame (5.017 s), which the "
        'innovation test judges for no machine (every current turns against its voltage by more than the chord '
        "allows), so the filter takes it whole: its field voltage walks from 2.3 to 34 pu in that frame, E'q rises "
        "11 % and the torque 25 % (to 9.2 pu, 9.7 by 5.17 s); what is left for the judged frames after is 42. An "
        'exciter-ceiling bound on that state is no test: on clean IEEE 14 the filter takes its field to 10 times '
        "its start, and the CT error on IEEE 39's PMU_39 moves it 2 to 4.5 times. Judging that first frame where "
        "the machine is not slipping (its speed turns it less than the chord in a frame) flags it (NIS 382) and 3 "
        "more of the sweep's 33 current+1 attacks, but honest fault-inception frames then reach 43.9 (IEEE 39 "
        'paper case 1, PMU_37 at 7.017 s) and 54.9 with 1 % TVE noise: no false-alarm rate can be claimed until '
        "the inception frame's own model error is in the innovation covariance. docs/attacks.md counts such misses "
        '(current+1)'))),
])
def test_pmu_ingestion_flags_a_ct_ratio_error_by_the_filters_innovation_and_marks_the_frames_after(bag, ratio):
    """A CT ratio error on G6's station from the fault's first frame of the default bag: only the filter can see it."""
    from controlled_islanding.nodes.pmu_ingestion import PmuIngestionNode
    from controlled_islanding.wire.messages import stamp_s

    snapshot, _ = bag
    frames = []
    with AnyReader([REPO / 'bags' / default_bag()['bag']], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic == topics.PMU_FRAMES:
                frames.append(deserialize_message(bytes(raw), PmuFrame))
    t0 = stamp_s(snapshot.header.stamp)
    frames = [f for f in frames if stamp_s(f.header.stamp) - t0 <= 5.3]
    node = PmuIngestionNode()
    angles = caught(node, 'pub')
    node._take_snapshot(snapshot)
    for frame in frames:
        msg = copy.deepcopy(frame)
        if stamp_s(msg.header.stamp) - t0 > 5.01:
            m = next(m for m in msg.measurements if m.station_id == 'PMU_35')
            m.current_magnitude_pu *= ratio
        node._take_frame(msg)
    j = list(angles[-1].generator_names).index(next(
        g for g, b in zip(snapshot.generator_names, snapshot.generator_bus, strict=True) if b == 35))
    marked = [stamp_s(a.header.stamp) - t0 for a in angles if a.suspect_reason and a.suspect_reason[j]]
    assert marked and 5.01 < marked[0] < 5.2 and marked[-1] == pytest.approx(5.3, abs=0.02)
    assert all(a.suspect_reason[j] == 'innovation: PMU_35' and not a.valid[j]
               for a in angles if a.suspect_reason and a.suspect_reason[j])
    assert not any(r for a in angles if a.suspect_reason for i, r in enumerate(a.suspect_reason) if i != j)
    assert 'PMU_35 (innovation)' in node.diag.values['suspect_stations']
    node.destroy_node()


@pytest.mark.parametrize('stat,usable', [
    (0, True),
    (0x4000, False),                        # bits 15-14 = 01: PMU error, no information about the data
    (0x1000, False),                        # bit 12: sorted by arrival, the tag is not the data's own
    (4 << 6, True), (5 << 6, False),        # PMU time quality within 1e-4 s, within 1e-3 s
    (7 << 6, False),                        # time error unknown or over 10 ms
    (1 << 4, False),                        # lock lost 10 s or more before
    (0x2000, False)])                       # bit 13: not synchronised
def test_pmu_ingestion_uses_data_only_with_a_good_stat_and_a_time_it_can_trust(bag, stat, usable):
    from controlled_islanding.nodes.pmu_ingestion import PmuIngestionNode

    snapshot, frames = bag
    node = PmuIngestionNode()
    node._take_snapshot(snapshot)
    m = copy.deepcopy(frames[0].measurements[0])
    m.stat = stat
    assert node._judge(m, set()) == ('use' if usable else 'unusable')
    synced = stat & 0xC000 or usable
    assert node.diag.values.get('unsynced_measurements', '0') == ('0' if synced else '1')
    node.destroy_node()


def test_a_station_silent_alone_longer_than_dse_max_gap_s_in_an_event_is_held_with_its_reason(bag):
    """The node gives the filter's bridge to the bad-data tests.

    A station back from a longer silence alone, in the default bag's fault, is marked `gap_in_event`
    (core/bad_data.py) until the grid is at rest again.
    """
    from rclpy.parameter import Parameter

    from controlled_islanding.nodes.pmu_ingestion import PmuIngestionNode

    snapshot, _ = bag
    frames = []
    with AnyReader([REPO / 'bags' / default_bag()['bag']], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic == topics.PMU_FRAMES:
                frame = deserialize_message(bytes(raw), PmuFrame)
                if 4.5 <= stamp_s(frame.header.stamp) - stamp_s(snapshot.header.stamp) <= 6.5:
                    frames.append(frame)
    node = PmuIngestionNode(parameter_overrides=[Parameter('dse_max_gap_s', value=0.3)])
    assert node.detector.max_gap_s == 0.3
    angles = caught(node, 'pub')
    node._take_snapshot(snapshot)
    victim = frames[0].measurements[-1].station_id
    t0 = stamp_s(snapshot.header.stamp)
    for frame in frames:
        msg = copy.deepcopy(frame)
        if 5.1 <= stamp_s(msg.header.stamp) - t0 < 5.5:  # 0.4 s, more than the filter bridges here
            msg.measurements = [m for m in msg.measurements if m.station_id != victim]
        node._take_frame(msg)
    gen = next(g for g, b in zip(snapshot.generator_names, snapshot.generator_bus, strict=True)
               if b == frames[0].measurements[-1].bus)
    j = list(angles[-1].generator_names).index(gen)
    back = [a for a in angles if stamp_s(a.header.stamp) - t0 >= 5.5 - 1e-6]
    assert back and all(a.suspect_reason[j] == f'gap_in_event: {victim}' and not a.valid[j] for a in back)
    assert not any(a.suspect_reason for a in angles if stamp_s(a.header.stamp) - t0 < 5.1)
    assert node.diag.values['grid_at_rest'] == 'no' and victim in node.diag.values['suspect_stations']
    node.destroy_node()
