"""bag_player, as fast as possible, plays on after a latched message only once every matched reader acknowledged it.

A reader that misses a latched message's one delivery (the network snapshot) gets it again only on the writer's
next heartbeat, while the frames after it flood on; the player therefore waits for the acknowledgements, at most
`latched_ack_timeout_s`. Here one reader's process is stopped (SIGSTOP) after it matched: it cannot acknowledge,
so the frames must come only after that timeout, and the report must say which topic went unacknowledged.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid

import pytest
from controlled_islanding_msgs.msg import NetworkSnapshot, PmuFrame
from nodes_harness import BUILD, bag_writer, graph

from controlled_islanding.graph.supervisor import PLAYER
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.wire import topics

pytestmark = [pytest.mark.ros, pytest.mark.slow]

T0_NS = 1_767_225_600 * 1_000_000_000
ACK_TIMEOUT_S = 1.5

# A reader of the snapshot in a process of its own, which says once it has matched the player's writer.
READER = """
import sys, time, rclpy
from controlled_islanding_msgs.msg import NetworkSnapshot
from controlled_islanding.ros.endpoints import qos_for
rclpy.init()
node = rclpy.create_node('stopped_reader')
sub = node.create_subscription(NetworkSnapshot, '/network/snapshot', lambda m: None, qos_for('/network/snapshot'))
while sub.get_publisher_count() == 0:
    rclpy.spin_once(node, timeout_sec=0.02)
print('matched', flush=True)
try:
    while True:
        rclpy.spin_once(node, timeout_sec=0.1)
except BaseException:  # stopped by the test: the context is shut down under the spin
    sys.exit(0)
"""


def test_frames_wait_until_every_reader_acknowledged_the_snapshot_or_the_timeout():
    run = BUILD / 'test_nodes' / f'acks_{uuid.uuid4().hex}'
    run.mkdir(parents=True)
    with bag_writer(run / 'in_bag') as put:
        put(topics.NETWORK_SNAPSHOT, NetworkSnapshot(), T0_NS)
        for k in range(30):
            frame = PmuFrame()
            frame.header.stamp.sec, frame.header.stamp.nanosec = divmod(T0_NS + k * 16_666_667, 1_000_000_000)
            put(topics.PMU_FRAMES, frame, T0_NS + k * 16_666_667)
    go_file = run / 'go.json'
    with graph('test_nodes_player_acks', []) as (sup, probe):
        arrivals: dict[str, float] = {}
        probe.node.create_subscription(NetworkSnapshot, topics.NETWORK_SNAPSHOT,
                                       lambda m: arrivals.setdefault('snapshot', time.monotonic()),
                                       qos_for(topics.NETWORK_SNAPSHOT))
        probe.node.create_subscription(PmuFrame, topics.PMU_FRAMES,
                                       lambda m: arrivals.setdefault('frame', time.monotonic()),
                                       qos_for(topics.PMU_FRAMES))
        player = sup.start(PLAYER, {'bag': run / 'in_bag', 'as_fast_as_possible': True, 'go_file': go_file,
                                    'report_file': run / 'report.json', 'latched_ack_timeout_s': ACK_TIMEOUT_S,
                                    'lockstep_on_requests': False, 'wait_for_subscribers_s': 5.0})
        reader = subprocess.Popen([sys.executable, '-c', READER], env=sup.env, stdout=subprocess.PIPE,
                                  stdin=subprocess.DEVNULL, text=True)
        try:
            assert reader.stdout.readline().strip() == 'matched'
            # The player's writer must match the reader too before it stops; the player says so in /diagnostics.
            key = f'matched.{topics.NETWORK_SNAPSHOT}'
            assert probe.spin_until(lambda: probe.diagnostics.get('bag_player', {}).get(key) == '2', 20.0), \
                probe.diagnostics.get('bag_player')
            os.kill(reader.pid, signal.SIGSTOP)
            go_file.write_text(json.dumps({'min_subscribers': [f'{topics.NETWORK_SNAPSHOT}=2',
                                                               f'{topics.PMU_FRAMES}=1', f'{topics.CLOCK}=0']}))
            assert probe.spin_until(lambda: player.poll() is not None and 'frame' in arrivals, 30.0), \
                sup.log_tail('bag_player')
        finally:
            os.kill(reader.pid, signal.SIGCONT)
            reader.terminate()
            reader.wait(timeout=10)
        assert player.returncode == 0, sup.log_tail('bag_player')
        log = sup.log_tail('bag_player')
    report = json.loads((run / 'report.json').read_text())
    assert report['latched_unacked'] == [topics.NETWORK_SNAPSHOT], log
    assert report['latched_ack_waits_s'][0] >= ACK_TIMEOUT_S
    assert arrivals['frame'] - arrivals['snapshot'] >= ACK_TIMEOUT_S - 0.2, arrivals
    assert 'not acknowledged by every reader' in log
