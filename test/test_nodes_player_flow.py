"""bag_player's flow control, as a real process against a probe that answers frames like a slow pmu_ingestion.

As fast as possible, the player may hold at most `flow_window_frames` PMU frames unanswered on /rotor_angles:
frame n goes out only once the answer to frame n - W is in. The probe answers one frame every ANSWER_EVERY_S
of wall time, in order, so without flow control it would hold the whole bag at once. After STALL_AFTER frames it
stops answering (frames refused one after another, say): the player must then wait `flow_stall_s`, say so, and
play the rest without flow control.
"""

from __future__ import annotations

import json
import time
import uuid

import pytest
from controlled_islanding_msgs.msg import PmuFrame, RotorAngles
from nodes_harness import BUILD, bag_writer, graph
from rosgraph_msgs.msg import Clock
from test_nodes_player_lockstep import frame_ns, pipeline_publishers

from controlled_islanding.graph.supervisor import PLAYER
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.wire import topics

pytestmark = [pytest.mark.ros, pytest.mark.slow]

N_FRAMES = 100
WINDOW = 8
ANSWER_EVERY_S = 0.005
STALL_AFTER = 40  # frames answered before the probe falls silent
STALL_S = 1.0


def test_no_more_than_the_window_of_frames_is_unanswered_and_a_silent_graph_ends_flow_control():
    run = BUILD / 'test_nodes' / f'flow_{uuid.uuid4().hex}'
    run.mkdir(parents=True)
    with bag_writer(run / 'in_bag') as put:
        for k in range(N_FRAMES):
            frame = PmuFrame()
            frame.header.stamp.sec, frame.header.stamp.nanosec = divmod(frame_ns(k), 1_000_000_000)
            put(topics.PMU_FRAMES, frame, frame_ns(k))
    with graph('test_nodes_player_flow', []) as (sup, probe):
        node = probe.node
        angles_pub, _, _ = pipeline_publishers(node)  # the lockstep's ends must exist before the play starts
        frames: list[tuple[float, PmuFrame]] = []  # (arrival, frame)
        answered: list[float] = []  # when each answer went out
        outstanding: list[int] = []  # frames received and not answered, at each arrival

        def on_frame(frame: PmuFrame) -> None:
            frames.append((time.monotonic(), frame))
            outstanding.append(len(frames) - len(answered))

        def answer() -> bool:
            # One frame every ANSWER_EVERY_S, in order, until STALL_AFTER: a pmu_ingestion slower than the player.
            due = not answered or time.monotonic() >= answered[-1] + ANSWER_EVERY_S
            if due and len(answered) < min(len(frames), STALL_AFTER):
                angles_pub.publish(RotorAngles(header=frames[len(answered)][1].header, generator_names=['G1'],
                                               generator_buses=[1], angle_rad=[0.0], valid=[True]))
                answered.append(time.monotonic())
            return player.poll() is not None

        node.create_subscription(PmuFrame, topics.PMU_FRAMES, on_frame, qos_for(topics.PMU_FRAMES))
        node.create_subscription(Clock, topics.CLOCK, lambda m: None, qos_for(topics.CLOCK))  # so play starts at once
        player = sup.start(PLAYER, {'bag': run / 'in_bag', 'as_fast_as_possible': True,
                                    'report_file': run / 'report.json', 'flow_window_frames': WINDOW,
                                    'flow_stall_s': STALL_S, 'clock_min_step_s': 0.05})
        assert probe.spin_until(answer, 60.0), 'player did not finish'
        assert player.returncode == 0, sup.log_tail('bag_player')
        log = sup.log_tail('bag_player')
    report = json.loads((run / 'report.json').read_text())
    assert len(frames) == N_FRAMES, (len(frames), log)
    # Up to the stall the player never got more than the window ahead of the answers.
    assert max(outstanding[:STALL_AFTER + WINDOW]) == WINDOW, outstanding
    # Then the frames answered by none held it for flow_stall_s, once, and it played the rest at once.
    assert report['flow_stalled_at_frame'] == STALL_AFTER + WINDOW, report
    gap_s = frames[STALL_AFTER + WINDOW][0] - frames[STALL_AFTER + WINDOW - 1][0]
    assert gap_s >= STALL_S - 0.1, gap_s
    assert 'playing on without flow control' in log, log
    assert report['lockstep_waits_s']['flow control (frames answered on /rotor_angles)'] >= STALL_S
