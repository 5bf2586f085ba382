"""Live C37.118.2 input, process level: serve-pmu (its own process) -> pdc_client -> the pipeline -> a breaker command.

The default bag of bags/index.yaml is served by `controlled-islanding serve-pmu` on a free loopback port. The
bag_player plays everything else of the same bag (snapshot, branch status, request, /clock) with /pmu/frames
withheld, so every PMU value the graph sees crossed TCP as C37.118.2 frames, and the decision must be the
manifest's.

Time: both sides carry the bag's own time. serve-pmu puts each frame's time tag in SOC/FRACSEC and paces by
the bag's log times from pdc_client's START; bag_player drives /clock from the same bag. The player starts once
this probe has seen the stream's first frame, so the stream leads /clock by the player's start-up (the figures
record by how much), never lags it. Data that leads /clock is held by pmu_ingestion and coherency until the clock
gets there (up to max_held_frames = 16 s at 60 frames/s); data that lags it makes the request wait for its groups,
at most groups_wait_s = 2 s, then partitioning refuses. Started together, on the same discovery event, the two
were one discovery round apart, either way: under a loaded full suite the stream once lagged by about 3 s and the
decision was that refusal, not the manifest's.
"""

from __future__ import annotations

import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from breaker_cases import private_key
from controlled_islanding_msgs.msg import BreakerCommand, IslandingDecision, IslandingRequest, PmuFrame
from controlled_islanding_msgs.srv import SetArmed
from nodes_harness import BUILD, graph
from rosgraph_msgs.msg import Clock

from controlled_islanding.graph.supervisor import GRAPH, PLAYER, NodeSpec
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.safety import signing
from controlled_islanding.sim.manifest import default_bag
from controlled_islanding.wire import topics

pytestmark = [pytest.mark.ros, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
PDC_CLIENT = NodeSpec('pdc_client', 'pdc_client.yaml')
INTERNAL = (topics.ROTOR_ANGLES, topics.COHERENT_GROUPS, topics.ISLANDING_DECISION, topics.BREAKER_COMMANDS)


def start_server(bag: Path, map_file: Path, *extra: str) -> tuple[subprocess.Popen, int]:
    """Start serve-pmu on a free loopback port; return the process and its port."""
    server = subprocess.Popen(
        [sys.executable, '-m', 'controlled_islanding.cli', 'serve-pmu', str(bag), '--port', '0', '--write-map',
         str(map_file), *extra], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)
    ready, _, _ = select.select([server.stdout], [], [], 60.0)
    line = server.stdout.readline() if ready else ''
    match = re.search(r'listening on 127\.0\.0\.1:(\d+) ', line)
    if not match:
        stop_server(server)
        pytest.fail(f'serve-pmu did not start: {line!r}')
    return server, int(match.group(1))


def stop_server(server: subprocess.Popen) -> str:
    """Stop the server we started (by its pid) and return what it printed."""
    if server.poll() is None:
        os.kill(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            os.kill(server.pid, signal.SIGKILL)
            server.wait()
    return server.stdout.read() if server.stdout else ''


def arm(probe) -> None:
    client = probe.node.create_client(SetArmed, '/breaker_command/set_armed')
    assert client.wait_for_service(timeout_sec=20.0), 'breaker_command offers no set_armed service'
    # A response Fast DDS sends before our reply reader matched is lost: ask again with a fresh nonce.
    for _ in range(3):
        future = client.call_async(signing.signed_arm_request(SetArmed.Request(), private_key('operator'),
                                                              '/breaker_command', True, time.time()))
        if probe.spin_until(future.done, 5.0):
            assert future.result().armed, future.result().message
            return
    pytest.fail('breaker_command did not answer 3 arm requests')


def wired(probe, timeout_s: float = 20.0) -> dict[str, int]:
    """Wait until every internal topic has a writer and a reader and nothing changed for 1 s."""
    played = (topics.NETWORK_SNAPSHOT, topics.BRANCH_STATUS, topics.ISLANDING_REQUEST, topics.CLOCK)
    before, stable_since, end = None, time.monotonic(), time.monotonic() + timeout_s
    while time.monotonic() < end:
        now = ({t: probe.node.count_subscribers(t) for t in played},
               {t: (probe.node.count_publishers(t), probe.node.count_subscribers(t)) for t in INTERNAL})
        if now != before:
            before, stable_since = now, time.monotonic()
        elif time.monotonic() - stable_since >= 1.0 and all(min(w) > 0 for w in now[1].values()):
            return now[0]
        probe.spin_for(0.1)
    pytest.fail(f'the graph did not wire up within {timeout_s} s: {before}')


def test_live_c37118_stream_drives_the_graph_to_the_manifest_decision():
    entry = default_bag()
    bag = REPO / 'bags' / entry['bag']
    if not bag.exists():
        pytest.skip(f'default bag {bag} is not present')
    run = BUILD / 'test_pdc_live' / f'{time.time_ns()}'
    run.mkdir(parents=True)
    map_file = run / 'channel_map.yaml'
    server, port = start_server(bag, map_file, '--once')
    sim = {'use_sim_time': True}
    specs = [(spec, {**sim, **({'audit_log': run / 'breaker_audit.jsonl'} if spec.executable == 'breaker_command'
                               else {})}) for spec in GRAPH]
    try:
        with graph('pdc_live', specs) as (sup, probe):
            arrivals: list[tuple[float, int]] = []  # (wall s, time tag ns) of each frame pdc_client published
            clock_first: list[float] = []
            requests: dict[str, float] = {}
            decisions: list[tuple[float, IslandingDecision]] = []
            commands: list[tuple[float, BreakerCommand]] = []
            node = probe.node
            node.create_subscription(PmuFrame, topics.PMU_FRAMES, lambda m: arrivals.append(
                (time.monotonic(), m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)),
                qos_for(topics.PMU_FRAMES))
            node.create_subscription(Clock, topics.CLOCK, lambda m: clock_first or clock_first.append(time.monotonic()),
                                     qos_for(topics.CLOCK))
            node.create_subscription(IslandingRequest, topics.ISLANDING_REQUEST,
                                     lambda m: requests.setdefault(m.request_id, time.monotonic()),
                                     qos_for(topics.ISLANDING_REQUEST))
            node.create_subscription(IslandingDecision, topics.ISLANDING_DECISION,
                                     lambda m: decisions.append((time.monotonic(), m)),
                                     qos_for(topics.ISLANDING_DECISION))
            node.create_subscription(BreakerCommand, topics.BREAKER_COMMANDS,
                                     lambda m: commands.append((time.monotonic(), m)),
                                     qos_for(topics.BREAKER_COMMANDS))
            arm(probe)
            counts = wired(probe)
            # pdc_client STARTs the stream once pmu_ingestion and this probe read /pmu/frames; the player, started
            # after the first frame, waits for one more /clock reader than the graph has: pdc_client's.
            counts[topics.CLOCK] += 1
            sup.start(PDC_CLIENT, {'servers': str([f'127.0.0.1:{port}']), 'channel_map_file': map_file,
                                   'wait_for_subscribers': 2, 'use_sim_time': True})
            assert probe.spin_until(lambda: arrivals, 30.0), f'no PMU frame within 30 s: {sup.log_tail("pdc_client")}'
            sup.start(PLAYER, {'bag': bag, 'withhold_topics': str([topics.PMU_FRAMES]), 'wait_for_subscribers_s': 30.0,
                               'min_subscribers': str([f'{t}={n}' for t, n in counts.items()])})
            done = probe.spin_until(lambda: decisions and (commands or not entry['expected_decision']['split']), 40.0)
            # The stream is paced in real time and the bag goes on after its request: wait for its last frames.
            probe.spin_until(lambda: len({t for _, t in arrivals}) >= n_bag_frames(bag), 15.0)
            probe.spin_for(0.5)
            sup.check_alive([spec.executable for spec in GRAPH] + ['pdc_client'])
            diag = {name: dict(values) for name, values in probe.diagnostics.items()}
            logs = {n: sup.log_tail(n) for n in ('pdc_client', 'pmu_ingestion', 'coherency', 'partitioning')}
    finally:
        server_out = stop_server(server)
    assert done, f'no decision (or no breaker command) within 40 s of play; logs: {logs}\nserver: {server_out}'

    # The decision is the manifest's.
    _, decision = decisions[0]
    expected = entry['expected_decision']
    assert decision.split == expected['split'], decision.status_detail
    islands = {}
    for bus, island in zip(decision.bus_numbers, decision.bus_island, strict=True):
        islands.setdefault(island, set()).add(int(bus))
    if expected['split']:
        assert {frozenset(i) for i in islands.values()} == {frozenset(i) for i in expected['islands']}
        assert sorted(decision.cut_branch_ids) == sorted(expected['cut_branches'])
        # The rest of the commands are the decision's remedial actions (load sheds, generator trips).
        opens = {c.branch_id for _, c in commands if c.action == BreakerCommand.ACTION_OPEN}
        assert opens == set(expected['cut_branches'])
        assert {c.action for _, c in commands} <= {BreakerCommand.ACTION_OPEN, BreakerCommand.ACTION_SHED_LOAD,
                                                   BreakerCommand.ACTION_TRIP_GENERATOR}

    # Every frame of the bag crossed TCP once, with its own time tag (to the microsecond of TIME_BASE).
    bag_ns = bag_frame_tags_ns(bag)
    got_ns = np.array(sorted({t for _, t in arrivals}))
    assert len(got_ns) == len(arrivals), 'a time tag was published twice'
    assert len(got_ns) == len(bag_ns), f'{len(bag_ns) - len(got_ns)} frames lost'
    assert np.max(np.abs(got_ns - bag_ns)) <= 500

    # Figures for the report: request -> breaker command, each frame's delay against the stream's own schedule,
    # and how far the PMU stream led /clock.
    t_request = next(iter(requests.values()))
    wall = np.array([a for a, _ in arrivals])
    tags = np.array([t for _, t in arrivals]) * 1e-9
    delay_ms = ((wall - wall[0]) - (tags - tags[0])) * 1e3
    delay_ms -= delay_ms.min()
    figures = {
        'decision': 'split' if decision.split else 'no split', 'cut': list(decision.cut_branch_ids),
        'breaker_commands': [c.breaker_id for _, c in commands],
        'latency_request_to_decision_ms': (decisions[0][0] - t_request) * 1e3,
        'latency_request_to_command_ms': (commands[-1][0] - t_request) * 1e3 if commands else None,
        'frames_in_bag': int(len(bag_ns)), 'frames_published': len(arrivals),
        'frames_lost': int(len(bag_ns) - len(got_ns)),
        'frame_delay_vs_schedule_ms': {'median': float(np.median(delay_ms)), 'p99': float(np.percentile(delay_ms, 99)),
                                       'max': float(delay_ms.max())},
        'stream_lead_over_clock_s': clock_first[0] - wall[0] if clock_first else None,
        'pmu_ingestion_missing_frames': diag.get('pmu_ingestion', {}).get('missing_frames'),
        'pdc_client_rejected': diag.get('pdc_client', {}).get('rejected'),
    }
    (run / 'figures.json').write_text(json.dumps(figures, indent=1))
    print(json.dumps(figures, indent=1))
    assert diag.get('pdc_client', {}).get('rejected') == '0', diag.get('pdc_client')


@lru_cache(maxsize=4)
def bag_frame_tags_ns(bag: Path) -> np.ndarray:
    """Return the time tags of a bag's PMU frames, ns, ascending."""
    from rosbags.highlevel import AnyReader

    from controlled_islanding.wire.interfaces import typestore

    with AnyReader([bag], default_typestore=typestore()) as reader:
        conns = [c for c in reader.connections if c.topic == topics.PMU_FRAMES]
        tags = [reader.deserialize(raw, c.msgtype).header.stamp for c, _, raw in reader.messages(conns)]
    return np.array(sorted(s.sec * 1_000_000_000 + s.nanosec for s in tags))


def n_bag_frames(bag: Path) -> int:
    """Return how many PMU frames a bag holds."""
    return len(bag_frame_tags_ns(bag))
