"""recorder: write chosen topics, as received serialized CDR bytes, into a rosbag2 MCAP bag.

Topics are subscribed once they appear in the graph (checked every `discovery_period_s`), with the QoS the
publishers offer: transient local only when every publisher latches (a volatile writer and a transient local
reader never match), best effort when any publisher is best effort. The bag is written under a temporary name
and renamed to `output` when the node stops, so a half-written bag never carries the final name.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import StoragePlugin, Writer

from controlled_islanding.interfaces import typestore
from controlled_islanding.node_common import Diagnostics, NodeSetupError, message_class, qos_for, spin_node


class RecorderNode(Node):
    """Records topics into an MCAP bag."""

    def __init__(self) -> None:
        super().__init__('recorder')
        self.declare_parameter('output', '')
        self.declare_parameter('topics', [''])
        self.declare_parameter('discovery_period_s', 0.2)
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
        self.output.parent.mkdir(parents=True, exist_ok=True)
        self.writer = Writer(self.tmp, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.connections = {}
        self.subs = {}
        self.diag = Diagnostics(self)
        self._discover()
        self.create_timer(float(self.get_parameter('discovery_period_s').value), self._discover,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _qos(self, topic: str) -> QoSProfile:
        infos = self.get_publishers_info_by_topic(topic)
        qos = qos_for(topic)
        if infos and any(i.qos_profile.durability != DurabilityPolicy.TRANSIENT_LOCAL for i in infos):
            qos.durability = DurabilityPolicy.VOLATILE
        if any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        return qos

    def _discover(self) -> None:
        types = dict(self.get_topic_names_and_types())
        for topic in self.topics:
            if topic in self.subs or topic not in types:
                continue
            msgtype = types[topic][0]
            try:
                cls = message_class(msgtype)
                conn = self.writer.add_connection(topic, msgtype, typestore=typestore())
            except Exception as exc:  # an unknown type must not stop the other topics being recorded
                self.diag.reject('unknown_type', f'{topic}: cannot record type {msgtype}: {exc}')
                self.subs[topic] = None
                continue
            self.connections[topic] = conn
            self.subs[topic] = self.create_subscription(
                cls, topic, lambda raw, c=conn: self._write(c, raw), self._qos(topic), raw=True)
            self.get_logger().info(f'recording {topic} ({msgtype})')

    def _write(self, conn, raw: bytes) -> None:
        self.diag.arrived()
        now_ns = self.get_clock().now().nanoseconds
        self.writer.write(conn, now_ns if now_ns > 0 else 0, raw)

    def close(self) -> None:
        """Finish the bag and give it its final name."""
        self.writer.close()
        os.replace(self.tmp, self.output)
        self.get_logger().info(f'wrote {self.output}')


def main(args: list[str] | None = None) -> int:
    """Run the recorder node."""
    return spin_node(RecorderNode, args)


if __name__ == '__main__':
    sys.exit(main())
