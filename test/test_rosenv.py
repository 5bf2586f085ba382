"""Which DDS domain a graph joins: the user's ROS_DOMAIN_ID unless isolation is asked for or it is unset."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from controlled_islanding.commands import replay
from controlled_islanding.graph.rosenv import (
    FIRST_DOMAIN_ID,
    LAST_DOMAIN_ID,
    RosEnvError,
    graph_environment,
    reserved_domain_id,
)

REPO = Path(__file__).resolve().parents[1]


def test_user_domain_wins_without_isolate(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv('ROS_DOMAIN_ID', '7')
    monkeypatch.delenv('ROS_AUTOMATIC_DISCOVERY_RANGE', raising=False)
    with graph_environment(tmp_path, isolate=False) as env:
        assert env['ROS_DOMAIN_ID'] == '7'
        assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'SUBNET')
    with graph_environment(tmp_path, isolate=False) as env:
        assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'


@pytest.mark.parametrize('user_domain', ['7', ''])
def test_isolated_when_asked_or_unset(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, user_domain: str) -> None:
    monkeypatch.setenv('ROS_DOMAIN_ID', user_domain)
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'SUBNET')
    with graph_environment(tmp_path, isolate=bool(user_domain)) as env:
        assert FIRST_DOMAIN_ID <= int(env['ROS_DOMAIN_ID']) <= LAST_DOMAIN_ID
        assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
        assert env['ROS_LOG_DIR'] == str(tmp_path)


def test_a_run_never_gets_the_domain_the_run_before_it_just_left() -> None:
    """What a run leaves alive goes on announcing itself there; one after another, reservations walk the range."""
    taken = []
    for _ in range(3):
        with reserved_domain_id() as domain_id:
            taken.append(domain_id)
    assert taken[0] != taken[1] != taken[2]
    with reserved_domain_id() as outer, reserved_domain_id() as inner:  # held at once: distinct, as before
        assert outer != inner


@pytest.mark.parametrize('bad', ['abc', '-1', '233', '1.5'])
def test_bad_user_domain_is_named(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, bad: str) -> None:
    monkeypatch.setenv('ROS_DOMAIN_ID', bad)
    with pytest.raises(RosEnvError, match=rf'ROS_DOMAIN_ID={re.escape(repr(bad))}'):
        with graph_environment(tmp_path, isolate=False):
            pass


def test_help_examples_name_real_bags() -> None:
    named = re.findall(r'replay (bags/\S+)', replay.DESCRIPTION)
    assert named
    for example in named:
        bags = sorted(REPO.glob(example)) if '*' in example else [REPO / example]  # as the shell expands it
        assert bags, f'replay --help names {example}, which matches nothing'
        for bag in bags:
            assert (bag / 'metadata.yaml').is_file(), f'replay --help names {example}, and {bag} is not a bag'


_TOPICS_SEEN = """
import sys, time, rclpy
rclpy.init(domain_id=int(sys.argv[1]))
node = rclpy.create_node('observer')
end = time.monotonic() + 2.0
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.1)
print(' '.join(name for name, _ in node.get_topic_names_and_types()))
"""


@pytest.mark.ros
def test_a_closed_probe_leaves_no_endpoint_on_its_domain() -> None:
    """Nodes a test added to the probe go with it: the next graph on the domain (another process) must not see them."""
    import os
    import subprocess
    import sys

    import rclpy
    from nodes_harness import Probe
    from rosgraph_msgs.msg import Clock

    with reserved_domain_id() as domain_id:
        probe = Probe(domain_id)
        extra = rclpy.create_node('clock_forger', context=probe.context)
        probe.executor.add_node(extra)
        extra.create_publisher(Clock, '/clock', 10)
        probe.spin_for(0.5)
        probe.close()
        seen = subprocess.run([sys.executable, '-c', _TOPICS_SEEN, str(domain_id)], capture_output=True, text=True,
                              timeout=60, env=dict(os.environ), check=True).stdout.split()
    assert '/clock' not in seen, seen
