"""Our bags play into our readers the way `ros2 bag play` (Jazzy) would play them.

rosbag2 offers each topic with the QoS its connections recorded (`offered_qos_profiles`); a bag that
records none is played volatile, and the nodes' transient-local readers of the snapshot, the branch
status and the groups then never match. Here every bag's recorded QoS is offered over real DDS by a
publisher that has already published before the reader exists (a node started after the play began),
and each latched reader, with the QoS the nodes use, must still receive.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import rclpy
import yaml
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosbags.highlevel import AnyReader

from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.params import message_class
from controlled_islanding.sim.manifest import manifest_entries
from controlled_islanding.wire.interfaces import typestore

pytestmark = [pytest.mark.ros]

BAGS = Path(__file__).resolve().parents[1] / 'bags'
ENTRIES = [e for e in manifest_entries(BAGS / 'index.yaml') if (BAGS / e['bag']).is_dir()]


def rclpy_qos(recorded: object) -> QoSProfile:
    """Return the QoS rosbag2 plays a recorded profile with."""
    def duration(t: object) -> Duration:
        return Duration(seconds=t.sec, nanoseconds=t.nsec)

    return QoSProfile(history=HistoryPolicy(recorded.history.value), depth=recorded.depth,
                      reliability=ReliabilityPolicy(recorded.reliability.value),
                      durability=DurabilityPolicy(recorded.durability.value),
                      deadline=duration(recorded.deadline), lifespan=duration(recorded.lifespan),
                      liveliness=LivelinessPolicy(recorded.liveliness.value),
                      liveliness_lease_duration=duration(recorded.liveliness_lease_duration))


@pytest.mark.parametrize('entry', ENTRIES, ids=[e['name'] for e in ENTRIES])
def test_bag_records_its_qos_for_rosbag2(entry: dict) -> None:
    meta = yaml.safe_load((BAGS / entry['bag'] / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['ros_distro'] == 'jazzy'
    with AnyReader([BAGS / entry['bag']], default_typestore=typestore()) as reader:
        for conn in reader.connections:
            assert conn.ext.offered_qos_profiles, f'{conn.topic}: no offered QoS recorded'
            offered = rclpy_qos(conn.ext.offered_qos_profiles[0])
            wanted = qos_for(conn.topic)
            assert rclpy.qos.qos_check_compatible(offered, wanted)[0] != rclpy.qos.QoSCompatibility.ERROR, conn.topic


def test_latched_readers_receive_a_bag_played_with_its_recorded_qos(ros_env: dict[str, str]) -> None:
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        node = rclpy.create_node('native_play_check', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        for entry in ENTRIES:
            with AnyReader([BAGS / entry['bag']], default_typestore=typestore()) as reader:
                latched = [c for c in reader.connections
                           if qos_for(c.topic).durability == DurabilityPolicy.TRANSIENT_LOCAL]
                assert latched, f'{entry["name"]}: no latched topic'
                firsts = {}
                for conn, _t, raw in reader.messages(connections=latched):
                    firsts.setdefault(conn.topic, (conn, bytes(raw)))
            pubs = []
            for topic, (conn, raw) in firsts.items():
                cls = message_class(conn.msgtype)
                offered = rclpy_qos(conn.ext.offered_qos_profiles[0])
                pub = node.create_publisher(cls, f'/{entry["name"]}{topic}', offered)
                pub.publish(deserialize_message(raw, cls))
                pubs.append(pub)
            got: set[str] = set()
            subs = [node.create_subscription(message_class(conn.msgtype), f'/{entry["name"]}{topic}',
                                             lambda _m, t=topic, seen=got: seen.add(t),
                                             qos_for(topic)) for topic, (conn, _raw) in firsts.items()]
            for _ in range(500):
                if len(got) == len(firsts):
                    break
                executor.spin_once(timeout_sec=0.02)
            assert set(got) == set(firsts), f'{entry["name"]}: latched readers got nothing on {set(firsts) - set(got)}'
            for handle in pubs:
                node.destroy_publisher(handle)
            for handle in subs:
                node.destroy_subscription(handle)
    finally:
        rclpy.shutdown(context=context)
