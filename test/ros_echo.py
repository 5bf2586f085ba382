"""Echo every message of one type from one topic to another; a separate process for round-trip tests.

Usage: python ros_echo.py TYPE_NAME IN_TOPIC OUT_TOPIC   (TYPE_NAME like PmuFrame)
"""

from __future__ import annotations

import importlib
import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy


class Echo(Node):
    """Republish each received message unchanged."""

    def __init__(self, msg_type: type, in_topic: str, out_topic: str) -> None:
        super().__init__('echo')
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.publisher = self.create_publisher(msg_type, out_topic, qos)
        self.subscription = self.create_subscription(msg_type, in_topic, self.publisher.publish, qos)


def main() -> None:
    """Run the echo node until interrupted."""
    type_name, in_topic, out_topic = sys.argv[1:4]
    msg_type = getattr(importlib.import_module('controlled_islanding_msgs.msg'), type_name)
    rclpy.init()
    node = Echo(msg_type, in_topic, out_topic)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
