"""What a node needs to open an endpoint: each topic's QoS as an rclpy QoSProfile (the table is wire/qos.py)."""

from __future__ import annotations

from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy

from controlled_islanding.wire.qos import TopicQos, qos_of


def profile(qos: TopicQos) -> QoSProfile:
    """Return the rclpy QoSProfile of a topic's QoS: reliable, keep last `depth`, latched or volatile, a lease."""
    out = QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=qos.depth, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if qos.latched else DurabilityPolicy.VOLATILE)
    if qos.lease_s is not None:
        out.liveliness = LivelinessPolicy.AUTOMATIC
        out.liveliness_lease_duration = Duration(nanoseconds=int(qos.lease_s * 1e9))
    return out


def qos_for(topic: str) -> QoSProfile:
    """Return the documented QoS of a topic (wire.qos.qos_of) as an rclpy QoSProfile."""
    return profile(qos_of(topic))
