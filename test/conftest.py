"""Shared fixtures: every test that touches ROS 2 gets its own domain, loopback only, logs in build/."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from controlled_islanding.graph.rosenv import isolated_ros_environment

REPO = Path(__file__).resolve().parents[1]
BUILD = REPO / 'build'

# Set before anything imports rclpy, so no test can discover past loopback.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('ROS_LOG_DIR', str(BUILD / 'ros_log'))
os.environ.setdefault('MPLBACKEND', 'Agg')
# Replays and demos run by the tests sign with keys made for the tests, never the user's own.
os.environ['CONTROLLED_ISLANDING_KEYS'] = str(BUILD / 'test_keys')


@pytest.fixture
def ros_env(request: pytest.FixtureRequest) -> Iterator[dict[str, str]]:
    """Yield an environment for child processes: own ROS_DOMAIN_ID, LOCALHOST discovery, ROS_LOG_DIR in build/."""
    with isolated_ros_environment(BUILD / 'ros_log' / request.node.name) as env:
        yield env


@pytest.fixture
def rclpy_context(ros_env: dict[str, str]) -> Iterator[object]:
    """Yield a fresh rclpy Context on the test's own domain; shut it down afterwards."""
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=int(ros_env['ROS_DOMAIN_ID']))
    try:
        yield context
    finally:
        context.try_shutdown()


def pytest_configure(config: pytest.Config) -> None:
    # The islanding_replay fixture comes through the installed package's pytest11 entry point; a venv whose
    # editable install predates that entry point (its metadata is written at install time) lacks it.
    if not config.pluginmanager.has_plugin('controlled_islanding'):
        config.pluginmanager.import_plugin('controlled_islanding.harness.pytest_plugin')
