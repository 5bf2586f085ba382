"""Start the node graph as separate processes and stop every one of them, whatever happens.

`ros2 launch` is not installable from PyPI, so the CLI starts the executables itself. GRAPH is the one list of
executables and parameter files: launch/islanding.launch.py reads the same table, so both paths start the
same processes with the same parameters.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path


class SupervisorError(RuntimeError):
    """A child process could not be started or died unexpectedly."""


@dataclass(frozen=True)
class NodeSpec:
    """One executable of the package and its parameter file in config/."""

    executable: str
    params_file: str


GRAPH: tuple[NodeSpec, ...] = (
    NodeSpec('pmu_ingestion', 'pmu_ingestion.yaml'),
    NodeSpec('coherency', 'coherency.yaml'),
    NodeSpec('partitioning', 'partitioning.yaml'),
    NodeSpec('breaker_command', 'breaker_command.yaml'),
)
PLAYER = NodeSpec('bag_player', 'bag_player.yaml')
RECORDER = NodeSpec('recorder', 'recorder.yaml')


def config_dir() -> Path:
    """Return config/ of a checkout, else the installed share/controlled_islanding/config.

    Raises:
        SupervisorError: Neither exists.

    """
    here = Path(__file__).resolve().parent
    candidates = [here.parent / 'config']
    if len(here.parents) > 3:
        candidates.append(here.parents[3] / 'share' / 'controlled_islanding' / 'config')
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    raise SupervisorError(f'config/ not found; looked in {", ".join(map(str, candidates))}')


def node_command(spec: NodeSpec, overrides: Mapping[str, object] | None = None) -> list[str]:
    """Return the command line that runs one executable with its parameter file and overrides.

    Args:
        spec: The executable and its parameter file.
        overrides: Parameters set after the file (`-p name:=value`), e.g. use_sim_time.

    Returns:
        The argv list, running the module with this interpreter.

    """
    argv = [sys.executable, '-m', f'controlled_islanding.nodes.{spec.executable}', '--ros-args',
            '--params-file', str(config_dir() / spec.params_file)]
    for name, value in dict(overrides or {}).items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        argv += ['-p', f'{name}:={text}']
    return argv


def _die_with_parent() -> None:
    # A SIGKILLed supervisor cannot run its cleanup; the kernel then stops the children instead.
    try:
        ctypes.CDLL('libc.so.6', use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


class Supervisor:
    """Owns child node processes; `with Supervisor(...)` stops them all on exit, Ctrl-C or error.

    Args:
        env: Environment for the children (from controlled_islanding.rosenv).
        log_dir: Each child's stdout and stderr go to <log_dir>/<name>.log.

    """

    def __init__(self, env: Mapping[str, str], log_dir: Path) -> None:
        self.env = dict(env)
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.children: dict[str, subprocess.Popen] = {}

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop_all()

    def start(self, spec: NodeSpec, overrides: Mapping[str, object] | None = None, name: str | None = None,
              ) -> subprocess.Popen:
        """Start one executable as its own process (own session, so a terminal Ctrl-C reaches only us).

        Raises:
            SupervisorError: A child of that name is already running.

        """
        name = name or spec.executable
        if name in self.children and self.children[name].poll() is None:
            raise SupervisorError(f'{name} is already running (pid {self.children[name].pid})')
        with open(self.log_dir / f'{name}.log', 'ab') as log:
            child = subprocess.Popen(node_command(spec, overrides), env=self.env, stdout=log,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     start_new_session=True, preexec_fn=_die_with_parent)
        self.children[name] = child
        return child

    def check_alive(self, names: Sequence[str] | None = None) -> None:
        """Raise if any (named) child has exited.

        Raises:
            SupervisorError: Names the dead child, its exit status and its log file.

        """
        for name, child in self.children.items():
            if (names is None or name in names) and child.poll() is not None:
                tail = self.log_tail(name)
                raise SupervisorError(f'{name} exited with status {child.returncode}; '
                                      f'log {self.log_dir / (name + ".log")}:\n{tail}')

    def log_tail(self, name: str, lines: int = 15) -> str:
        """Return the last lines of a child's log."""
        path = self.log_dir / f'{name}.log'
        return '\n'.join(path.read_text(errors='replace').splitlines()[-lines:]) if path.exists() else ''

    def stop(self, name: str, timeout_s: float = 5.0) -> int | None:
        """Stop one child: SIGINT, then SIGTERM, then SIGKILL, each after timeout_s; return its exit status."""
        child = self.children.get(name)
        if child is None:
            return None
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if child.poll() is not None:
                break
            try:
                os.kill(child.pid, sig)
            except ProcessLookupError:
                break
            try:
                child.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                continue
        return child.wait()

    def stop_all(self, timeout_s: float = 5.0) -> None:
        """Stop every child, all at once: SIGINT to all, wait, then escalate per child."""
        for child in self.children.values():
            if child.poll() is None:
                try:
                    os.kill(child.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and any(c.poll() is None for c in self.children.values()):
            time.sleep(0.05)
        for name in list(self.children):
            self.stop(name, timeout_s=2.0)
