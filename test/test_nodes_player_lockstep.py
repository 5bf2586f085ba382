"""bag_player's lockstep at a request, as a real process against a probe that plays the graph's part.

The probe answers like the pipeline would, but on a schedule the test sets: rotor angles at once (pmu_ingestion
caught up), coherent groups for the newest frame only HOLD_S later (a coherency node still working through its
backlog, or through its first, slow DTW computation: 1.2-3.0 s measured on a loaded machine). The request must
not go out before those groups: partitioning waits only groups_wait_s of wall time for the request's groups and
then refuses it as stale, which a real-time replay never does. Meanwhile /clock must keep coming: the nodes' time
source reads it best effort, and a node that lost the last sample before the wait would otherwise hold every
stamp ahead of its stale clock for the whole wait.
"""

from __future__ import annotations

import time
import uuid

import pytest
from controlled_islanding_msgs.msg import CoherentGroups, IslandingDecision, IslandingRequest, PmuFrame, RotorAngles
from nodes_harness import BUILD, bag_writer, graph
from rosgraph_msgs.msg import Clock

from controlled_islanding.graph.supervisor import PLAYER
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.wire import topics
from controlled_islanding.wire.messages import split_stamp, stamp_s

pytestmark = [pytest.mark.ros, pytest.mark.slow]

T0_NS = 1_767_225_600 * 1_000_000_000
FPS = 60
N_FRAMES = 91  # 1.5 s
REQUEST_AT = 45  # the request is logged with frame 45, after frames 0..44
HOLD_S = 1.0  # how long the probe's "coherency" lags behind the newest frame, wall s


def frame_ns(k: int) -> int:
    return T0_NS + k * 1_000_000_000 // FPS


def write_bag(path) -> None:
    with bag_writer(path) as put:
        for k in range(N_FRAMES):
            if k == REQUEST_AT:
                request = IslandingRequest(request_id='req-1', reason='test')
                request.header.stamp.sec, request.header.stamp.nanosec = divmod(frame_ns(k), 1_000_000_000)
                put(topics.ISLANDING_REQUEST, request, frame_ns(k))
            frame = PmuFrame()
            frame.header.stamp.sec, frame.header.stamp.nanosec = divmod(frame_ns(k), 1_000_000_000)
            put(topics.PMU_FRAMES, frame, frame_ns(k))


def fresh_bag(prefix: str):
    """Return a new run directory under build/ and the test bag written in it."""
    run = BUILD / 'test_nodes' / f'{prefix}_{uuid.uuid4().hex}'
    run.mkdir(parents=True)
    write_bag(run / 'in_bag')
    return run, run / 'in_bag'


def pipeline_publishers(node):
    """Return the probe's publishers that play the graph's part: rotor angles, coherent groups, decisions."""
    return (node.create_publisher(RotorAngles, topics.ROTOR_ANGLES, qos_for(topics.ROTOR_ANGLES)),
            node.create_publisher(CoherentGroups, topics.COHERENT_GROUPS, qos_for(topics.COHERENT_GROUPS)),
            node.create_publisher(IslandingDecision, topics.ISLANDING_DECISION, qos_for(topics.ISLANDING_DECISION)))


def test_request_waits_for_groups_up_to_the_newest_frame_while_clock_keeps_coming():
    run, bag = fresh_bag('lockstep')
    with graph('test_nodes_player_lockstep', []) as (sup, probe):
        node = probe.node
        angles_pub, groups_pub, decision_pub = pipeline_publishers(node)
        seen: dict[str, float] = {}  # event -> wall time
        clocks: list[tuple[float, int]] = []  # (wall time, bag time ns)

        def groups_at(stamp) -> CoherentGroups:
            msg = CoherentGroups(generator_names=['G1', 'G2'], group=[0, 1], k=2, method='dtw')
            # Stamped as the coherency node does, through float seconds.
            msg.header.stamp.sec, msg.header.stamp.nanosec = split_stamp(stamp_s(stamp))
            return msg

        def on_frame(frame: PmuFrame) -> None:
            angles_pub.publish(RotorAngles(header=frame.header, generator_names=['G1', 'G2'],
                                           generator_buses=[1, 2], angle_rad=[0.0, 0.0], valid=[True, True]))
            k = round((frame.header.stamp.sec * 1_000_000_000 + frame.header.stamp.nanosec - T0_NS) * FPS / 1e9)
            if k == REQUEST_AT - 15:
                groups_pub.publish(groups_at(frame.header.stamp))  # groups that lag the newest frame are no answer
            if k == REQUEST_AT - 1:
                seen['newest_frame'] = time.monotonic()
                seen['newest_stamp'] = frame.header.stamp

        def on_request(msg: IslandingRequest) -> None:
            seen.setdefault('request', time.monotonic())
            decision_pub.publish(IslandingDecision(request_id=msg.request_id, request_stamp=msg.header.stamp,
                                                   status=IslandingDecision.STATUS_NO_SPLIT))

        node.create_subscription(PmuFrame, topics.PMU_FRAMES, on_frame, qos_for(topics.PMU_FRAMES))
        node.create_subscription(IslandingRequest, topics.ISLANDING_REQUEST, on_request,
                                 qos_for(topics.ISLANDING_REQUEST))
        node.create_subscription(Clock, topics.CLOCK, lambda m: clocks.append(
            (time.monotonic(), m.clock.sec * 1_000_000_000 + m.clock.nanosec)), qos_for(topics.CLOCK))
        player = sup.start(PLAYER, {'bag': bag, 'as_fast_as_possible': True, 'report_file': run / 'report.json',
                                    'lockstep_timeout_s': 5.0, 'clock_min_step_s': 0.05})

        def release_groups() -> bool:
            if 'groups' not in seen and 'newest_frame' in seen and time.monotonic() >= seen['newest_frame'] + HOLD_S:
                groups_pub.publish(groups_at(seen['newest_stamp']))
                seen['groups'] = time.monotonic()
            return player.poll() is not None

        assert probe.spin_until(release_groups, 30.0), 'player did not finish'
        assert player.returncode == 0, sup.log_tail('bag_player')
    assert 'request' in seen, sup.log_tail('bag_player')
    assert 'groups' in seen and seen['request'] >= seen['groups'], (
        f'the request went out {seen["request"] - seen["newest_frame"]:.2f} s after the newest frame, before the '
        f'groups for it ({HOLD_S} s after it)')
    # Nothing else is published while the player holds the request back: every /clock then is a heartbeat.
    held = [ns for t, ns in clocks if seen['newest_frame'] + 0.2 <= t <= seen['groups']]
    assert len(held) >= 5, f'{len(held)} /clock messages in {HOLD_S - 0.2:.1f} s of lockstep wait'
    assert set(held) == {held[0]} and held[0] <= frame_ns(REQUEST_AT - 1)


def test_a_request_lost_by_a_restarted_partitioning_is_sent_again_with_the_same_id():
    run, bag = fresh_bag('resend')
    with graph('test_nodes_player_resend', []) as (sup, probe):
        node = probe.node
        angles_pub, groups_pub, decision_pub = pipeline_publishers(node)
        requests: list[str] = []

        def on_frame(frame: PmuFrame) -> None:
            angles_pub.publish(RotorAngles(header=frame.header, generator_names=['G1', 'G2'],
                                           generator_buses=[1, 2], angle_rad=[0.0, 0.0], valid=[True, True]))
            groups = CoherentGroups(generator_names=['G1', 'G2'], group=[0, 1], k=2, method='dtw')
            groups.header.stamp.sec, groups.header.stamp.nanosec = split_stamp(stamp_s(frame.header.stamp))
            groups_pub.publish(groups)

        def on_request(msg: IslandingRequest) -> None:
            requests.append(msg.request_id)
            if len(requests) >= 2:  # the first one died with the node that held it
                decision_pub.publish(IslandingDecision(request_id=msg.request_id, request_stamp=msg.header.stamp,
                                                       status=IslandingDecision.STATUS_NO_SPLIT))

        node.create_subscription(PmuFrame, topics.PMU_FRAMES, on_frame, qos_for(topics.PMU_FRAMES))
        node.create_subscription(IslandingRequest, topics.ISLANDING_REQUEST, on_request,
                                 qos_for(topics.ISLANDING_REQUEST))
        node.create_subscription(Clock, topics.CLOCK, lambda m: None, qos_for(topics.CLOCK))  # so play starts at once
        player = sup.start(PLAYER, {'bag': bag, 'as_fast_as_possible': True, 'report_file': run / 'report.json',
                                    'lockstep_timeout_s': 2.0, 'clock_min_step_s': 0.05})
        assert probe.spin_until(lambda: player.poll() is not None, 30.0), 'player did not finish'
        assert player.returncode == 0, sup.log_tail('bag_player')
        log = sup.log_tail('bag_player')
    assert requests == ['req-1', 'req-1'], (requests, log)
    assert 're-sending the islanding request (1 of 2)' in log and '(2 of 2)' not in log, log


HANDLE_S = 1.0  # how long the stand-in breaker_command takes to handle the decision, wall s


def test_clock_stays_at_the_request_until_breaker_command_says_it_handled_the_decision():
    """/clock moves past a request only once breaker_command has handled its decision, however long it takes.

    breaker_command refuses a decision older than max_decision_age_s on its clock; it says at once in its
    /diagnostics (decisions_handled) that it has handled one.
    """
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    from controlled_islanding.ros.diagnostics import DECISIONS_HANDLED

    run, bag = fresh_bag('handled')
    with graph('test_nodes_player_handled', []) as (sup, probe):
        node = probe.node
        angles_pub, groups_pub, decision_pub = pipeline_publishers(node)
        breaker = rclpy_node('breaker_command', probe)  # a stand-in, named as the player expects
        diag_pub = breaker.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, qos_for(topics.DIAGNOSTICS))
        seen: dict[str, float] = {}
        clocks: list[tuple[float, int]] = []

        def on_frame(frame: PmuFrame) -> None:
            angles_pub.publish(RotorAngles(header=frame.header, generator_names=['G1', 'G2'],
                                           generator_buses=[1, 2], angle_rad=[0.0, 0.0], valid=[True, True]))
            groups = CoherentGroups(generator_names=['G1', 'G2'], group=[0, 1], k=2, method='dtw')
            groups.header.stamp.sec, groups.header.stamp.nanosec = split_stamp(stamp_s(frame.header.stamp))
            groups_pub.publish(groups)

        def on_request(msg: IslandingRequest) -> None:
            seen.setdefault('decision', time.monotonic())
            decision_pub.publish(IslandingDecision(request_id=msg.request_id, request_stamp=msg.header.stamp,
                                                   status=IslandingDecision.STATUS_NO_SPLIT))

        def handle() -> bool:
            if 'decision' in seen and 'handled' not in seen and time.monotonic() >= seen['decision'] + HANDLE_S:
                status = DiagnosticStatus(name='/breaker_command', values=[KeyValue(key=DECISIONS_HANDLED, value='1')])
                diag_pub.publish(DiagnosticArray(status=[status]))
                seen['handled'] = time.monotonic()
            return player.poll() is not None

        node.create_subscription(PmuFrame, topics.PMU_FRAMES, on_frame, qos_for(topics.PMU_FRAMES))
        node.create_subscription(IslandingRequest, topics.ISLANDING_REQUEST, on_request,
                                 qos_for(topics.ISLANDING_REQUEST))
        breaker.create_subscription(IslandingDecision, topics.ISLANDING_DECISION, lambda m: None,
                                    qos_for(topics.ISLANDING_DECISION))
        node.create_subscription(Clock, topics.CLOCK, lambda m: clocks.append(
            (time.monotonic(), m.clock.sec * 1_000_000_000 + m.clock.nanosec)), qos_for(topics.CLOCK))
        player = sup.start(PLAYER, {'bag': bag, 'as_fast_as_possible': True, 'report_file': run / 'report.json',
                                    'lockstep_timeout_s': 5.0, 'clock_min_step_s': 0.05})
        assert probe.spin_until(handle, 30.0), 'player did not finish'
        assert player.returncode == 0, sup.log_tail('bag_player')
        breaker.destroy_node()
    assert 'handled' in seen, sup.log_tail('bag_player')
    moved = [t for t, ns in clocks if ns > frame_ns(REQUEST_AT)]
    assert moved and moved[0] >= seen['handled'], (
        f'/clock moved past the request {seen["handled"] - moved[0]:.2f} s before breaker_command had handled the '
        'decision')
    held = [ns for t, ns in clocks if seen['decision'] + 0.2 <= t <= seen['handled']]
    assert len(held) >= 5 and set(held) == {frame_ns(REQUEST_AT)}, held


def rclpy_node(name: str, probe: object) -> object:
    """Return another rclpy node in the probe's Context, spun by the probe's executor."""
    import rclpy

    node = rclpy.create_node(name, context=probe.context)
    probe.executor.add_node(node)
    return node
