"""bag_player -> recorder as real processes: bytes unchanged, truth withheld, timing followed, /clock published."""

from __future__ import annotations

import time
import uuid

import pytest
from controlled_islanding_msgs.msg import CoherentGroups, IslandingRequest, PmuFrame, PmuMeasurement
from nodes_harness import BUILD, bag_writer, graph
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader
from rosgraph_msgs.msg import Clock

from controlled_islanding.graph.supervisor import PLAYER, RECORDER
from controlled_islanding.wire import topics
from controlled_islanding.wire.interfaces import typestore

pytestmark = [pytest.mark.ros, pytest.mark.slow]

T0_NS = 1_700_000_000 * 1_000_000_000
SPAN_S = 1.5


def write_bag(path):
    """Write a small bag: 60 fps frames for SPAN_S, one request, one truth message; return {topic: [raw bytes]}."""
    written: dict[str, list[bytes]] = {}
    with bag_writer(path) as write:
        def put(topic, msg, t_ns):
            written.setdefault(topic, []).append(write(topic, msg, t_ns))

        for k in range(int(SPAN_S * 60) + 1):
            t_ns = T0_NS + k * 1_000_000_000 // 60
            frame = PmuFrame(measurements=[PmuMeasurement(station_id='PMU30', bus=30, voltage_magnitude_pu=1.0,
                                                          voltage_angle_rad=0.01 * k)])
            frame.header.stamp.sec, frame.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
            put(topics.PMU_FRAMES, frame, t_ns)
            if k == 45:
                put(topics.ISLANDING_REQUEST, IslandingRequest(request_id='req-1', reason='test'), t_ns)
                put(topics.TRUTH_COHERENT_GROUPS, CoherentGroups(generator_names=['G1'], group=[0], k=1,
                                                                 method='truth'), t_ns)
    return written


def recorded(path) -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = {}
    with AnyReader([path], default_typestore=typestore()) as reader:
        for conn, log_ns, raw in reader.messages():
            # Sim time: messages that beat the first /clock must not be logged at 0 (a bag "56 years" long).
            assert T0_NS <= log_ns <= T0_NS + int(SPAN_S * 1e9), f'{conn.topic} logged at {log_ns} ns'
            out.setdefault(conn.topic, []).append(bytes(raw))
        latched = [c for c in reader.connections if c.topic == topics.ISLANDING_REQUEST]
        # What `ros2 bag play` offers again: the publisher's own QoS, not an empty list.
        assert latched and all(c.ext.offered_qos_profiles for c in latched)
    return out


@pytest.mark.parametrize('fast', [False, True], ids=['real_time', 'as_fast_as_possible'])
def test_player_to_recorder_round_trip(fast):
    run = BUILD / 'test_nodes' / f'player_{uuid.uuid4().hex}'
    run.mkdir(parents=True)
    bag, out = run / 'in_bag', run / 'out_bag'
    written = write_bag(bag)
    played = [topics.PMU_FRAMES, topics.ISLANDING_REQUEST, topics.TRUTH_COHERENT_GROUPS]
    with graph('test_nodes_player', [(RECORDER, {'output': out, 'topics': str(played + [topics.CLOCK]),
                                                 'use_sim_time': True})]) as (sup, probe):
        clocks = probe.collect(Clock, topics.CLOCK)
        frames = probe.collect(PmuFrame, topics.PMU_FRAMES)
        probe.collect(IslandingRequest, topics.ISLANDING_REQUEST)
        started = time.monotonic()
        player = sup.start(PLAYER, {'bag': bag, 'as_fast_as_possible': fast, 'lockstep_on_requests': False,
                                    'report_file': run / 'report.json', 'wait_for_subscriber_count': 2})
        assert probe.spin_until(lambda: player.poll() is not None, 30.0), 'player did not finish'
        wall_s = time.monotonic() - started
        assert player.returncode == 0, sup.log_tail('bag_player')
        probe.spin_until(lambda: len(frames) >= len(written[topics.PMU_FRAMES]), 2.0)
        sup.stop('recorder')
    got = recorded(out)
    # Compared decoded: CDR alignment padding bytes are not defined, so equal messages may differ there.
    for topic, cls in ((topics.PMU_FRAMES, PmuFrame), (topics.ISLANDING_REQUEST, IslandingRequest)):
        assert [deserialize_message(r, cls) for r in got[topic]] == [deserialize_message(r, cls)
                                                                      for r in written[topic]], topic
    assert topics.TRUTH_COHERENT_GROUPS not in got, 'ground truth was published without publish_truth'
    assert clocks and clocks[-1].clock.sec == (T0_NS + int(SPAN_S * 1e9)) // 1_000_000_000
    assert not list(run.glob('.out_bag.partial-*')), 'the recorder left a partial bag behind'
    assert [f.name for f in out.glob('*.mcap')] == ['out_bag.mcap'], 'the storage file kept a temporary name'
    assert 'ros_distro: jazzy' in (out / 'metadata.yaml').read_text()
    if not fast:
        assert wall_s >= SPAN_S, f'real-time replay of {SPAN_S} s took only {wall_s:.2f} s'


def test_player_refuses_a_missing_bag():
    run = BUILD / 'test_nodes' / f'player_{uuid.uuid4().hex}'
    with graph('test_nodes_player_bad', []) as (sup, _probe):
        player = sup.start(PLAYER, {'bag': run / 'no_such_bag'})
        assert player.wait(timeout=30) == 1
        assert 'cannot read' in sup.log_tail('bag_player')
