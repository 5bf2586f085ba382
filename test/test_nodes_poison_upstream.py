"""Single poisoned messages on the real pmu_ingestion and coherency processes, on sim time as in a replay.

Each poison of the safety issue (a frame or a rotor-angle sample stamped a day ahead, a snapshot with a NaN
reactance, renamed generators, PMUs with ever new station ids) is refused and counted, the node stays alive,
and good data afterwards is still turned into rotor angles and coherent groups. The probe drives /clock
itself, frame by frame, like the bag player.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from controlled_islanding_msgs.msg import CoherentGroups, IslandingRequest, NetworkSnapshot, PmuFrame, RotorAngles
from nodes_harness import graph
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader
from rosgraph_msgs.msg import Clock

from controlled_islanding.graph.supervisor import GRAPH
from controlled_islanding.sim.manifest import default_bag, manifest_entries
from controlled_islanding.wire import topics
from controlled_islanding.wire.interfaces import typestore
from controlled_islanding.wire.messages import stamp_s

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]
NODES = [s for s in GRAPH if s.executable in ('pmu_ingestion', 'coherency')]
DAY_S = 86_400
MAX_STATIONS = 25  # small, so a few frames of odd station ids overflow it


def bag_messages(n_frames: int, bag: Path | None = None) -> tuple[NetworkSnapshot, list[PmuFrame]]:
    bag = bag or REPO / 'bags' / default_bag()['bag']
    frames, snapshot = [], None
    with AnyReader([bag], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic == topics.NETWORK_SNAPSHOT:
                snapshot = deserialize_message(bytes(raw), NetworkSnapshot)
            elif conn.topic == topics.PMU_FRAMES:
                frames.append(deserialize_message(bytes(raw), PmuFrame))
                if len(frames) >= n_frames:
                    break
    return snapshot, frames


class Upstream:
    """The graph under test and a cursor through the bag's frames, with /clock following them."""

    def __init__(self, sup, probe, snapshot: NetworkSnapshot, frames: list[PmuFrame]) -> None:
        self.sup, self.probe, self.snapshot, self.frames = sup, probe, snapshot, frames
        self.next = 0
        self._all_angles = probe.collect(RotorAngles, topics.ROTOR_ANGLES)
        self._injected: set[tuple] = set()
        self.groups = probe.collect(CoherentGroups, topics.COHERENT_GROUPS)

    @staticmethod
    def _key(msg: RotorAngles) -> tuple:
        return msg.header.stamp.sec, msg.header.stamp.nanosec, tuple(msg.generator_names)

    @property
    def angles(self) -> list[RotorAngles]:
        """Rotor angles pmu_ingestion published (the probe hears its own injected samples too)."""
        return [a for a in self._all_angles if self._key(a) not in self._injected]

    def publish(self, topic: str, msg) -> None:
        if topic == topics.ROTOR_ANGLES:
            self._injected.add(self._key(msg))
        self.probe.pubs[topic].publish(msg)

    def clock(self, stamp: Time) -> None:
        self.publish(topics.CLOCK, Clock(clock=stamp))

    def play(self, n: int, clock: bool = True) -> list[PmuFrame]:
        """Publish the next n good frames, each after /clock at its time tag; return them."""
        played = self.frames[self.next:self.next + n]
        assert len(played) == n, 'the test ran out of bag frames'
        self.next += n
        for frame in played:
            if clock:
                self.clock(frame.header.stamp)
            self.publish(topics.PMU_FRAMES, frame)
        return played

    def angles_after(self, frames: list[PmuFrame], timeout_s: float = 10.0) -> bool:
        """Wait until a rotor-angle sample came for every one of these frames."""
        wanted = {stamp_s(f.header.stamp) for f in frames}
        return self.probe.spin_until(lambda: wanted <= {stamp_s(a.header.stamp) for a in self.angles}, timeout_s)

    def counter(self, node: str, key: str) -> int:
        return self.probe.counter(node, key)

    def wait_counter(self, node: str, key: str, at_least: int) -> int:
        return self.probe.wait_counter(node, key, at_least)

    def healthy(self) -> None:
        """Both nodes alive, and no callback ever raised."""
        self.probe.spin_for(0.2)
        self.sup.check_alive()
        for node in ('pmu_ingestion', 'coherency'):
            errors = {k: v for k, v in self.probe.diagnostics.get(node, {}).items() if k.startswith('error.')}
            assert not errors, f'{node} caught exceptions in callbacks: {errors}'


@pytest.fixture(scope='module')
def upstream():
    if not manifest_entries():
        pytest.skip('no bags in bags/index.yaml')
    snapshot, frames = bag_messages(400)
    sim = {'use_sim_time': True}
    overrides = {'pmu_ingestion': dict(sim, max_stations_remembered=MAX_STATIONS),
                 'coherency': dict(sim, request_wait_s=0.5, min_samples=30, window_s=1.0)}
    with graph('test_nodes_poison_upstream', [(s, overrides[s.executable]) for s in NODES]) as (sup, probe):
        for msg_type, topic in ((PmuFrame, topics.PMU_FRAMES), (NetworkSnapshot, topics.NETWORK_SNAPSHOT),
                                (IslandingRequest, topics.ISLANDING_REQUEST), (RotorAngles, topics.ROTOR_ANGLES),
                                (Clock, topics.CLOCK)):
            probe.publisher(msg_type, topic)
        up = Upstream(sup, probe, snapshot, frames)
        probe.wait_matched(topics.CLOCK, 2)
        probe.wait_matched(topics.NETWORK_SNAPSHOT, 2)
        probe.wait_matched(topics.PMU_FRAMES, 1)
        probe.wait_matched(topics.ROTOR_ANGLES, 2)
        probe.wait_wired(tuple(s.executable for s in NODES))  # as test_nodes_bad_input: volatile angles otherwise lost
        yield up


def renamed(msg, names: list[str]):
    out = copy.deepcopy(msg)
    out.generator_names = names
    return out


@pytest.mark.slow
def test_inputs_before_the_clock_starts_are_held_then_judged(upstream):
    """Before the first /clock sim time is 0, so inputs wait; a renamed first sample is then refused.

    Before, the first sample fixed the generator names for good, so every honest sample was refused after it.
    """
    up = upstream
    up.publish(topics.NETWORK_SNAPSHOT, up.snapshot)
    up.probe.spin_for(0.3)
    first = RotorAngles(generator_names=[f'X{i}' for i in range(len(up.snapshot.generator_names))],
                        generator_buses=list(up.snapshot.generator_bus),
                        angle_rad=[0.1] * len(up.snapshot.generator_names),
                        valid=[True] * len(up.snapshot.generator_names))
    first.header.stamp = up.frames[0].header.stamp
    up.publish(topics.ROTOR_ANGLES, first)
    held = up.play(40, clock=False)
    up.probe.spin_for(1.0)
    assert not up.angles, 'frames were used before the node clock started'
    up.clock(held[-1].header.stamp)
    assert up.angles_after(held), 'frames held for the clock were never released'
    assert up.wait_counter('coherency', 'rejected.unknown_id', 1) >= 1, 'the renamed first sample was not refused'
    assert all(list(a.generator_names) == list(up.snapshot.generator_names) for a in up.angles)
    up.healthy()


@pytest.mark.slow
def test_a_frame_stamped_a_day_ahead_is_refused_and_later_frames_still_count(upstream):
    up = upstream
    poison = copy.deepcopy(up.frames[up.next])
    poison.header.stamp.sec += DAY_S
    up.publish(topics.PMU_FRAMES, poison)
    assert up.wait_counter('pmu_ingestion', 'rejected.future_stamp', 1) >= 1
    good = up.play(20)
    assert up.angles_after(good), 'good frames after a future-stamped one gave no rotor angles'
    assert up.counter('pmu_ingestion', 'rejected.time_backwards') == 0
    assert all(stamp_s(a.header.stamp) < stamp_s(poison.header.stamp) - DAY_S / 2 for a in up.angles)
    up.healthy()


@pytest.mark.slow
def test_a_rotor_angle_sample_stamped_a_day_ahead_does_not_blind_coherency(upstream):
    up = upstream
    assert up.angles, 'no rotor angles yet'
    poison = copy.deepcopy(up.angles[-1])
    poison.header.stamp.sec += DAY_S
    up.publish(topics.ROTOR_ANGLES, poison)
    assert up.wait_counter('coherency', 'rejected.future_stamp', 1) >= 1
    request = IslandingRequest(request_id='poison-far-future', reason='test')
    request.header.stamp = copy.deepcopy(poison.header.stamp)
    up.publish(topics.ISLANDING_REQUEST, request)
    assert up.wait_counter('coherency', 'rejected.future_stamp', 2) >= 2, 'a request a day ahead was not refused'
    before = len(up.groups)
    good = up.play(40)
    request = IslandingRequest(request_id='after-poison', reason='test')
    request.header.stamp = good[-1].header.stamp
    up.publish(topics.ISLANDING_REQUEST, request)
    newest = stamp_s(good[-1].header.stamp)
    assert up.probe.spin_until(lambda: any(stamp_s(g.header.stamp) >= newest - 0.02 for g in up.groups[before:])), \
        'coherency published no groups for the good samples after a future-stamped one'
    assert list(up.groups[-1].generator_names) == list(up.snapshot.generator_names)
    assert up.counter('coherency', 'rejected.time_backwards') == 0
    up.healthy()


@pytest.mark.slow
def test_a_snapshot_with_a_nan_or_negative_reactance_or_too_many_buses_is_refused(upstream):
    up = upstream
    nan = copy.deepcopy(up.snapshot)
    nan.generator_xq_pu = [math.nan] + list(nan.generator_xq_pu)[1:]
    negative = copy.deepcopy(up.snapshot)
    negative.generator_ra_pu = [-0.1] * len(negative.generator_ra_pu)
    huge = copy.deepcopy(up.snapshot)
    huge.bus_numbers = list(range(1, 60_002))
    for reason, msg in (('nan_value', nan), ('bad_value', negative), ('too_large', huge)):
        up.publish(topics.NETWORK_SNAPSHOT, msg)
        for node in ('pmu_ingestion', 'coherency'):
            assert up.wait_counter(node, f'rejected.{reason}', 1) >= 1, f'{node} did not refuse {reason}'
    good = up.play(10)
    assert up.angles_after(good), 'pmu_ingestion gave no rotor angles after a bad snapshot'
    assert all(a.valid[0] for a in up.angles[-10:]), 'the refused NaN reactance was used'
    up.healthy()


@pytest.mark.slow
def test_ever_new_station_ids_are_bounded_and_unknown_buses_not_remembered(upstream):
    up = upstream
    unknown_before = up.counter('pmu_ingestion', 'rejected.unknown_id')
    frames = up.frames[up.next:up.next + 60]
    up.next += 60
    for k, frame in enumerate(frames):
        odd = copy.deepcopy(frame)
        for i, m in enumerate(odd.measurements):
            m.station_id = f'odd-{k}-{i}'
        stray = copy.deepcopy(odd.measurements[0])
        stray.station_id, stray.bus = f'stray-{k}', 99_999
        odd.measurements.append(stray)
        up.clock(odd.header.stamp)
        up.publish(topics.PMU_FRAMES, odd)
    assert up.angles_after(frames), 'frames from renamed PMUs on known buses gave no rotor angles'
    assert up.wait_counter('pmu_ingestion', 'rejected.unknown_id', unknown_before + 60) >= unknown_before + 60
    assert up.wait_counter('pmu_ingestion', 'stations_forgotten', 1) >= 1
    assert up.counter('pmu_ingestion', 'stations_remembered') <= MAX_STATIONS
    up.healthy()


@pytest.mark.slow
def test_a_snapshot_with_another_generator_set_starts_a_new_window(upstream):
    up = upstream
    names = [f'NEW_{n}' for n in up.snapshot.generator_names]
    other = renamed(up.snapshot, names)
    up.clock(up.frames[up.next].header.stamp)
    other.header.stamp.sec += 1  # newer than the snapshot held, and within the clock's tolerance
    up.publish(topics.NETWORK_SNAPSHOT, other)
    assert up.wait_counter('coherency', 'window_resets', 1) >= 1
    unknown_before = up.counter('coherency', 'rejected.unknown_id')
    # The flood of stations before evicted the bag's own from pmu_ingestion's memory: back, they are new stations
    # to core/bad_data for its clean_s (1 s), and coherency leaves out a generator flagged within its window (1 s).
    good = up.play(130)
    assert up.angles_after(good)
    assert list(up.angles[-1].generator_names) == names, 'pmu_ingestion did not follow the new snapshot'
    request = IslandingRequest(request_id='new-generators', reason='test')
    request.header.stamp = good[-1].header.stamp
    up.publish(topics.ISLANDING_REQUEST, request)
    assert up.probe.spin_until(lambda: up.groups and list(up.groups[-1].generator_names) == names), \
        'coherency did not group the new generator set'
    assert up.counter('coherency', 'rejected.unknown_id') == unknown_before
    up.healthy()


def test_machines_sharing_a_bus_get_the_rotor_angle_of_their_own_channel():
    """Where machines share a bus each has a PMU channel '<station>/<generator>'; a bus total fits none of them."""
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad

    entry = next((e for e in manifest_entries() if any('/' in s for s in _station_ids(e))), None)
    if entry is None:
        pytest.skip('no bag with machines sharing a bus')
    snapshot, frames = bag_messages(20, REPO / 'bags' / entry['bag'])
    shared = [n for n in snapshot.generator_names
              if any(m.station_id.endswith(f'/{n}') for m in frames[0].measurements)]
    with graph('test_nodes_shared_bus', [(s, {'use_sim_time': True}) for s in NODES
                                         if s.executable == 'pmu_ingestion']) as (sup, probe):
        for msg_type, topic in ((PmuFrame, topics.PMU_FRAMES), (NetworkSnapshot, topics.NETWORK_SNAPSHOT),
                                (Clock, topics.CLOCK)):
            probe.publisher(msg_type, topic)
        angles = probe.collect(RotorAngles, topics.ROTOR_ANGLES)
        probe.wait_matched(topics.NETWORK_SNAPSHOT, 1)
        probe.wait_matched(topics.PMU_FRAMES, 1)
        probe.pubs[topics.NETWORK_SNAPSHOT].publish(snapshot)
        probe.spin_for(0.5)
        frame = frames[0]
        probe.pubs[topics.CLOCK].publish(Clock(clock=frame.header.stamp))
        probe.pubs[topics.PMU_FRAMES].publish(frame)
        assert probe.spin_until(lambda: angles, 10.0), 'no rotor angles for the frame'
    got = dict(zip(angles[0].generator_names, angles[0].angle_rad, strict=True))
    row = list(snapshot.generator_names)
    for name in shared:
        m = next(m for m in frame.measurements if m.station_id.endswith(f'/{name}'))
        k = row.index(name)
        own = estimate_rotor_angle_rad(*([getattr(m, f)] for f in ('voltage_magnitude_pu', 'voltage_angle_rad',
                                                                     'current_magnitude_pu', 'current_angle_rad')),
                                       snapshot.generator_xq_pu[k], snapshot.generator_ra_pu[k])[0]
        assert math.isclose(float(np.angle(np.exp(1j * (got[name] - own)))), 0.0, abs_tol=1e-6), name
    assert len({round(got[n], 6) for n in shared}) == len(shared), 'machines on one bus got one angle'


def _station_ids(entry: dict) -> set[str]:
    _snapshot, frames = bag_messages(1, REPO / 'bags' / entry['bag'])
    return {m.station_id for m in frames[0].measurements}
