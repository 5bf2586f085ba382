"""The ROS 2 environment of every run that starts nodes: tests, demos, benchmarks, replays.

Isolated (tests, the demo, benchmarks, and any run whose user set no ROS_DOMAIN_ID): traffic
stays on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), each concurrent run gets a
ROS_DOMAIN_ID of its own (held by an advisory file lock, so two runs on one machine never
share one), and logs go inside the build tree.

A user who set ROS_DOMAIN_ID keeps it (graph_environment with isolate=False), so a replay
shows up in their own tools; discovery still defaults to loopback unless they chose a range.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from controlled_islanding.graph import GraphError

# Fast DDS maps a domain id to UDP ports; ids 0..232 are valid. Low ids are left
# to users' own ROS graphs on the same machine.
FIRST_DOMAIN_ID = 100
LAST_DOMAIN_ID = 232
LOCK_DIR = Path(tempfile.gettempdir()) / 'controlled_islanding_domains'


class RosEnvError(GraphError):
    """No free ROS_DOMAIN_ID could be reserved."""


@contextmanager
def reserved_domain_id() -> Iterator[int]:
    """Reserve a ROS_DOMAIN_ID no other run on this machine holds, until the block exits.

    Yields:
        The reserved domain id.

    Raises:
        RosEnvError: Every id in FIRST_DOMAIN_ID..LAST_DOMAIN_ID is held.

    """
    LOCK_DIR.mkdir(parents=True, exist_ok=True)
    ids = list(range(FIRST_DOMAIN_ID, LAST_DOMAIN_ID + 1))
    start = _rotation() % len(ids)
    for domain_id in ids[start:] + ids[:start]:
        handle = open(LOCK_DIR / f'{domain_id}.lock', 'w')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            continue
        _rotation(domain_id - FIRST_DOMAIN_ID + 1)
        try:
            yield domain_id
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
            handle.close()
        return
    raise RosEnvError(f'all ROS_DOMAIN_IDs {FIRST_DOMAIN_ID}..{LAST_DOMAIN_ID} are in use on this machine')


def _rotation(after: int | None = None) -> int:
    """Return where the next reservation starts looking; with `after`, set it.

    A run should not get the id a run before it just left: whatever that run left alive there (a node a test
    never destroyed, a process slow to die) goes on announcing its endpoints, and the next run's graph shows
    them (CI: a failed test's /clock forger, in a later namespaced testbed's graph).
    """
    path = LOCK_DIR / 'next'
    with open(LOCK_DIR / 'next.lock', 'w') as guard:
        fcntl.flock(guard, fcntl.LOCK_EX)
        if after is not None:
            path.write_text(str(after))
            return after
        try:
            return int(path.read_text())
        except (OSError, ValueError):
            return 0


def ros_environment(domain_id: int, log_dir: Path, base: dict[str, str] | None = None) -> dict[str, str]:
    """Return an environment for ROS 2 processes confined to loopback and one domain.

    Args:
        domain_id: ROS_DOMAIN_ID for every process of the run.
        log_dir: Directory for ROS_LOG_DIR; created if missing.
        base: Environment to extend; defaults to os.environ.

    Returns:
        A new environment mapping.

    """
    log_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ if base is None else base)
    env.update({
        'ROS_DOMAIN_ID': str(domain_id),
        'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
        'ROS_LOG_DIR': str(log_dir),
        'PYTHONUNBUFFERED': '1',
    })
    env.pop('ROS_STATIC_PEERS', None)
    return env


@contextmanager
def isolated_ros_environment(log_dir: Path) -> Iterator[dict[str, str]]:
    """Reserve a domain id and yield a loopback-only environment that uses it.

    Args:
        log_dir: Directory for ROS_LOG_DIR, inside the build tree.

    Yields:
        The environment, to pass to subprocesses or apply to os.environ.

    """
    with reserved_domain_id() as domain_id:
        yield ros_environment(domain_id, log_dir)


@contextmanager
def graph_environment(log_dir: Path, isolate: bool) -> Iterator[dict[str, str]]:
    """Yield the environment for a graph the user started: their ROS_DOMAIN_ID, or an isolated one.

    Args:
        log_dir: Directory for ROS_LOG_DIR.
        isolate: Use a private domain and loopback even if the user set ROS_DOMAIN_ID.

    Yields:
        The environment, as isolated_ros_environment.

    Raises:
        RosEnvError: ROS_DOMAIN_ID is set but not an integer in 0..232.

    """
    user_domain = os.environ.get('ROS_DOMAIN_ID', '').strip()
    if isolate or not user_domain:
        with isolated_ros_environment(log_dir) as env:
            yield env
        return
    if not user_domain.isdigit() or int(user_domain) > LAST_DOMAIN_ID:
        raise RosEnvError(f'ROS_DOMAIN_ID={user_domain!r} is not an integer in 0..{LAST_DOMAIN_ID}')
    env = ros_environment(int(user_domain), log_dir)
    for chosen in ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_STATIC_PEERS'):
        if os.environ.get(chosen):
            env[chosen] = os.environ[chosen]
    yield env
