"""recorder: write chosen topics, as received serialized CDR bytes, into a rosbag2 MCAP bag.

Topics are subscribed once they appear in the graph (checked every `discovery_period_s`), with the QoS the
publishers offer: transient local only when every publisher latches (a volatile writer and a transient local
reader never match), best effort when any publisher is best effort. Each connection records the QoS its
publishers offered, as `ros2 bag record` does, so `ros2 bag play` offers it again and latched readers match.

Log times are the node's clock at arrival. On sim time that clock reads 0 until the first /clock, and a
message logged at 0 would start the bag in 1970; such early messages wait (at most `max_early_messages`)
and are written at the first valid time. The bag is written inside a temporary directory under its final
name, and that directory's content is renamed to `output` when the node stops, so a half-written bag never
carries the final name and the storage file inside is named after the bag.

Topics are named as in the root namespace (/pmu/frames) and subscribed in the recorder's namespace
(/area1/pmu/frames in /area1), and recorded under the root-namespace name, so the bag of one area replays
into any other; the global /diagnostics carries every area's statuses.
"""

from __future__ import annotations

import os
import shutil
import sys
import time
from pathlib import Path

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import StoragePlugin, Writer

from controlled_islanding import atomic
from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.params import NodeSetupError, declare_bounded, message_class
from controlled_islanding.ros.spin import spin_node
from controlled_islanding.wire.bagmeta import qos_profile, set_ros_distro
from controlled_islanding.wire.interfaces import typestore
from controlled_islanding.wire.topics import relative


class RecorderNode(Node):
    """Records topics into an MCAP bag."""

    def __init__(self, **node_options) -> None:
        super().__init__('recorder', **node_options)
        self.declare_parameter('output', '')
        self.declare_parameter('topics', [''])
        self.declare_parameter('discovery_period_s', 0.2)
        self.max_early = int(declare_bounded(
            self, 'max_early_messages', 10_000, 0, 1_000_000,
            'messages held while the clock still reads 0 (sim time before the first /clock); more are dropped '
            'and counted (rejected.before_clock)', read_only=True))
        output = self.get_parameter('output').value
        self.topics = [t for t in self.get_parameter('topics').value if t]
        if not output:
            raise NodeSetupError('parameter output is empty; it must name the bag directory to write')
        if not self.topics:
            raise NodeSetupError('parameter topics is empty; list the topics to record')
        self.output = Path(output)
        if self.output.exists():
            raise NodeSetupError(f'output {self.output} exists; refusing to overwrite a bag')
        self.tmp = self.output.with_name(f'.{self.output.name}.partial-{os.getpid()}')
        shutil.rmtree(self.tmp, ignore_errors=True)
        self.tmp.mkdir(parents=True)
        self.writer = Writer(self.tmp / self.output.name, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.early: list[tuple[object, bytes]] = []
        self.connections = {}
        self.subs = {}
        self.diag = Diagnostics(self)
        self._discover()
        self.create_timer(float(self.get_parameter('discovery_period_s').value), self._discover,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _qos(self, topic: str) -> QoSProfile:
        infos = self.get_publishers_info_by_topic(relative(topic))
        qos = qos_for(topic)
        if infos and any(i.qos_profile.durability != DurabilityPolicy.TRANSIENT_LOCAL for i in infos):
            qos.durability = DurabilityPolicy.VOLATILE
        if any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        return qos

    def _discover(self) -> None:
        types = dict(self.get_topic_names_and_types())
        for topic in self.topics:
            name = self.resolve_topic_name(relative(topic))
            # A topic seen only through its readers has no offered QoS yet to record, or to match.
            if topic in self.subs or name not in types or not self.get_publishers_info_by_topic(name):
                continue
            msgtype = types[name][0]
            try:
                cls = message_class(msgtype)
                conn = self.writer.add_connection(topic, msgtype, typestore=typestore(),
                                                  offered_qos_profiles=self._offered(topic))
            except Exception as exc:  # an unknown type must not stop the other topics being recorded
                self.diag.reject('unknown_type', f'{topic}: cannot record type {msgtype}: {exc}')
                self.subs[topic] = None
                continue
            self.connections[topic] = conn
            self.subs[topic] = self.create_subscription(
                cls, relative(topic), lambda raw, c=conn: self._write(c, raw), self._qos(topic), raw=True)
            self.get_logger().info(f'recording {name} as {topic} ({msgtype})')

    def _offered(self, topic: str) -> list:
        return [qos_profile(i.qos_profile) for i in self.get_publishers_info_by_topic(relative(topic))]

    def _write(self, conn, raw: bytes) -> None:
        self.diag.arrived()
        now_ns = self.get_clock().now().nanoseconds
        if now_ns <= 0:
            if len(self.early) >= self.max_early:
                self.diag.reject('before_clock', f'{conn.topic}: more than {self.max_early} messages before the '
                                                 'first /clock; dropped')
                return
            self.early.append((conn, raw))
            return
        self._flush_early(now_ns)
        self.writer.write(conn, now_ns, raw)

    def _flush_early(self, at_ns: int) -> None:
        for early_conn, early_raw in self.early:
            self.writer.write(early_conn, at_ns, early_raw)
        self.early.clear()

    def close(self) -> None:
        """Finish the bag and give it its final name."""
        if self.early:
            # No valid clock ever came: the wall clock is the only time these messages had.
            self.get_logger().warning(f'{len(self.early)} messages arrived before any /clock; logged at wall time')
            self._flush_early(time.time_ns())
        self.writer.close()
        set_ros_distro(self.tmp / self.output.name)
        atomic.replace(self.tmp / self.output.name, self.output)
        self.tmp.rmdir()
        self.get_logger().info(f'wrote {self.output}')


def main(args: list[str] | None = None) -> int:
    """Run the recorder node."""
    return spin_node(RecorderNode, args)


if __name__ == '__main__':
    sys.exit(main())
