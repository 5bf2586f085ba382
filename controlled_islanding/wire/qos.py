"""Each topic's QoS, as plain data: ros/endpoints.py makes it an rclpy QoSProfile, and bags record it.

What every node shares: per-topic QoS, bad-input accounting with /diagnostics, and the process main loop.

QoS per topic (reliable everywhere: a lost request, decision or command is a lost control action):
- /pmu/frames, /rotor_angles: KEEP_LAST 1000, volatile. Deep enough that an as-fast-as-possible replay
  of a whole window never drops a frame; live, a late frame is useless, so nothing is latched.
- /network/snapshot: KEEP_LAST 1, transient local: a late joiner gets the latest state.
- /coherent_groups: KEEP_LAST 16, transient local: coherency publishes the groups ending at a request and,
  moments later, periodic ones on newer data; with KEEP_LAST 1 a busy partitioning node lost the first to the
  second and refused the request as stale. 16 = the groupings partitioning keeps, each for its own time.
- /network/branch_status: KEEP_LAST 100, transient local: a late partitioning node still learns every trip.
- /islanding/request, /islanding/decision, /breaker/commands: KEEP_LAST 100, volatile. Never latched: a
  breaker node that starts late must not execute a decision made before it existed.
- /islanding/decision also has an AUTOMATIC liveliness lease of DECISION_LEASE_S: the topic is silent between
  requests by design, so only liveliness tells a breaker node that the control centre is gone (process dead,
  host or WAN down). A reader matches only writers offering a lease no longer than the one it requests.
- /diagnostics: KEEP_LAST 10, volatile (the diagnostic_aggregator convention).
- /clock: KEEP_LAST 1, volatile; rclpy's time source subscribes best effort, which a reliable writer serves.
"""

from __future__ import annotations

from dataclasses import dataclass

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

from controlled_islanding.wire import topics

# rmw_fastrtps asserts AUTOMATIC liveliness every 2/3 of the lease, so one lost assertion outlasts it; a lease of
# 3 s at 2 s assertions gives a writer's silence away within 3-5 s (measured in docs/deployment.md).
DECISION_LEASE_S = 3.0


@dataclass(frozen=True)
class TopicQos:
    """One topic's QoS; reliable and keep-last for every topic.

    Attributes:
        depth: History depth, messages.
        latched: Transient local (a late joiner gets the latest), else volatile.
        lease_s: AUTOMATIC liveliness lease, s; None: the middleware's default.

    """

    depth: int
    latched: bool = False
    lease_s: float | None = None


TOPIC_QOS: dict[str, TopicQos] = {
    topics.PMU_FRAMES: TopicQos(1000),
    topics.ROTOR_ANGLES: TopicQos(1000),
    topics.NETWORK_SNAPSHOT: TopicQos(1, latched=True),
    topics.COHERENT_GROUPS: TopicQos(16, latched=True),
    topics.BRANCH_STATUS: TopicQos(100, latched=True),
    topics.ISLANDING_REQUEST: TopicQos(100),
    topics.ISLANDING_DECISION: TopicQos(100, lease_s=DECISION_LEASE_S),
    topics.BREAKER_COMMANDS: TopicQos(100),
    topics.DIAGNOSTICS: TopicQos(10),
    topics.CLOCK: TopicQos(1),
    topics.TRUTH_ROTOR_ANGLES: TopicQos(1000),
    topics.TRUTH_COHERENT_GROUPS: TopicQos(1, latched=True),
}
_UNKNOWN = TopicQos(100)


def qos_of(topic: str) -> TopicQos:
    """Return the documented QoS of a topic; unknown topics get reliable, volatile, depth 100.

    The topic may be named as in the root namespace (/pmu/frames), relative (pmu/frames) or in any namespace
    (/area1/pmu/frames): a name ending in a documented one has its QoS.
    """
    name = topic if topic.startswith('/') else f'/{topic}'
    known = [k for k in TOPIC_QOS if name.endswith(k)]
    return TOPIC_QOS[max(known, key=len)] if known else _UNKNOWN


def bag_qos(topic: str) -> Qos:
    """Return a topic's QoS as rosbag2 records it among a bag topic's offered QoS profiles."""
    qos = qos_of(topic)
    lease = QosTime(0, 0) if qos.lease_s is None else QosTime(*divmod(int(qos.lease_s * 1e9), 1_000_000_000))
    return Qos(history=QosHistory.KEEP_LAST, depth=qos.depth, reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL if qos.latched else QosDurability.VOLATILE,
               deadline=QosTime(0, 0), lifespan=QosTime(0, 0),
               liveliness=QosLiveliness.SYSTEM_DEFAULT if qos.lease_s is None else QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=lease, avoid_ros_namespace_conventions=False)
