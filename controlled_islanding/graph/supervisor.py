"""Start the node graph as separate processes, keep it alive, and stop every one of them, whatever happens.

`ros2 launch` is not installable from PyPI, so the CLI starts the executables itself. GRAPH is the one list of
executables and parameter files: launch/islanding.launch.py reads the same table, so both paths start the
same processes with the same parameters.

With a RestartPolicy, `Supervisor.supervise` restarts a pipeline node that died, with backoff, and SIGKILLs
and restarts one whose /diagnostics heartbeat stopped (controlled_islanding.graph.watchdog decides), recording
each in `restarts` and `hangs` so that a run can report that it did not come from a healthy graph.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from controlled_islanding.graph import GraphError
from controlled_islanding.graph.processes import cpu_s, die_with_parent, processes, sigterm_as_interrupt
from controlled_islanding.graph.watchdog import Action, ActionKind, RestartPolicy, Watchdog
from controlled_islanding.locations import config_dir


class SupervisorError(GraphError):
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
# The stability monitor raises the islanding requests itself (`--trigger monitor`): started beside GRAPH then.
MONITOR = NodeSpec('stability_monitor', 'stability_monitor.yaml')
PLAYER = NodeSpec('bag_player', 'bag_player.yaml')
RECORDER = NodeSpec('recorder', 'recorder.yaml')

# The pipeline nodes have no end of their own, so any exit is a failure; the player and the recorder end
# normally when the bag does, and are never restarted.
# A node loads its engines (imports, numba kernels, a first decision on a made-up grid) before its first
# heartbeat: 14-16 s measured for partitioning at load average 12 on the 2-core machine, hence 60 s of grace.
# After it, a 2224-bus decision takes 1.1-1.3 s in one callback there, and a false kill loses the requests a node
# holds, hence 10 s: a node truly hung is still found well within a replay's lockstep waits.
PIPELINE_POLICY = RestartPolicy(nodes=frozenset(spec.executable for spec in (*GRAPH, MONITOR)), hang_timeout_s=10.0,
                                startup_grace_s=60.0)


@dataclass
class RestartRecord:
    """One failure of a supervised child (it exited, or was killed as hung) and its restart.

    Attributes:
        name: The child.
        cause: 'exited' or 'hung'.
        reason: One line: what happened and what the supervisor did.
        exit_status: Exit status of the failed process (negative: the signal that ended it, -9 when killed as hung).
        pid: The failed process.
        failed_after_s: When the failure was noticed, s since the supervisor was created.
        failed_utc: The same, as a UTC ISO 8601 time.
        log_tail: The last lines of its log at that moment.
        restarted_after_s: When it was started again, s since the supervisor was created; None if not (yet).
        new_pid: The restarted process, if any.

    """

    name: str
    cause: str
    reason: str
    exit_status: int | None
    pid: int
    failed_after_s: float
    failed_utc: str
    log_tail: str
    restarted_after_s: float | None = None
    new_pid: int | None = None


@dataclass
class HangRecord:
    """A child found hung: alive, but with no heartbeat on /diagnostics for longer than the policy allows.

    Attributes:
        name: The child.
        pid: The hung process (killed with SIGKILL).
        silent_s: How long no heartbeat had come, s.
        detected_after_s: When it was found, s since the supervisor was created.
        detected_utc: The same, as a UTC ISO 8601 time.

    """

    name: str
    pid: int
    silent_s: float
    detected_after_s: float
    detected_utc: str


def node_command(spec: NodeSpec, overrides: Mapping[str, object] | None = None, namespace: str = '',
                 remaps: Mapping[str, str] | None = None) -> list[str]:
    """Return the command line that runs one executable with its parameter file and overrides.

    Args:
        spec: The executable and its parameter file.
        overrides: Parameters set after the file (`-p name:=value`), e.g. use_sim_time.
        namespace: The node's namespace (`-r __ns:=`), e.g. '/area1'; '' = the root namespace.
        remaps: Name remapping rules (`-r from:=to`), e.g. {'/clock': '/area1/clock'}.

    Returns:
        The argv list, running the module with this interpreter.

    """
    return [sys.executable, '-m', f'controlled_islanding.nodes.{spec.executable}',
            *ros_arguments(spec, overrides, namespace, remaps)]


def ros_arguments(spec: NodeSpec, overrides: Mapping[str, object] | None = None, namespace: str = '',
                  remaps: Mapping[str, str] | None = None) -> list[str]:
    """Return node_command's `--ros-args ...` part: a process's arguments, or a composed node's `cli_args`."""
    argv = ['--ros-args', '--params-file', str(config_dir() / spec.params_file)]
    if namespace.strip('/'):
        argv += ['-r', f'__ns:=/{namespace.strip("/")}']
    for source, target in dict(remaps or {}).items():
        argv += ['-r', f'{source}:={target}']
    for name, value in dict(overrides or {}).items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        argv += ['-p', f'{name}:={text}']
    return argv


class Supervisor:
    """Owns child node processes; `with Supervisor(...)` stops them all on exit, Ctrl-C, SIGTERM or error.

    Args:
        env: Environment for the children (from controlled_islanding.graph.rosenv).
        log_dir: Each child's stdout and stderr go to <log_dir>/<name>.log.
        policy: Which children `supervise` restarts and watches for hangs, and how; None: none (a dead
            child is only seen by `check_alive`).
        namespace: Namespace of every child not started with its own, e.g. '/area1'; '' = the root one.
        remaps: Name remapping rules for every child, e.g. {'/clock': '/area1/clock'}.

    """

    def __init__(self, env: Mapping[str, str], log_dir: Path, policy: RestartPolicy | None = None,
                 namespace: str = '', remaps: Mapping[str, str] | None = None) -> None:
        self.env = dict(env)
        self.namespace = namespace
        self.remaps = dict(remaps or {})
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.children: dict[str, subprocess.Popen] = {}
        self.watchdog = Watchdog(policy) if policy is not None else None
        self.restarts: list[RestartRecord] = []
        self.hangs: list[HangRecord] = []
        self._launch: dict[str, tuple[NodeSpec, dict[str, object], str, list[str], dict[str, str]]] = {}
        self.cpu_s: dict[str, float] = {}  # CPU time (user + system) of each child that ran to stop_all, s
        self._t0_s = time.monotonic()

    def __enter__(self) -> Supervisor:
        self._sigterm = sigterm_as_interrupt()
        self._sigterm.__enter__()
        return self

    def __exit__(self, *exc_info: object) -> None:
        try:
            self.stop_all()
        finally:
            self._sigterm.__exit__(None, None, None)

    def start(self, spec: NodeSpec, overrides: Mapping[str, object] | None = None, name: str | None = None,
              namespace: str | None = None, prefix: Sequence[str] = (),
              remaps: Mapping[str, str] | None = None) -> subprocess.Popen:
        """Start one executable as its own process (own session, so a terminal Ctrl-C reaches only us).

        Args:
            spec: The executable and its parameter file.
            overrides: Parameters set after the file.
            name: The child's name here (its log file); default the executable's.
            namespace: The node's namespace; default the supervisor's.
            prefix: Command that runs the node, e.g. `ip netns exec <netns>` to put it on an emulated host
                (controlled_islanding.graph.wan); a restart uses it again.
            remaps: This child's own remapping rules, over the supervisor's; a restart keeps them.

        Raises:
            SupervisorError: A child of that name is already running.

        """
        name = name or spec.executable
        if name in self.children and self.children[name].poll() is None:
            raise SupervisorError(f'{name} is already running (pid {self.children[name].pid})')
        self._launch[name] = (spec, dict(overrides or {}), self.namespace if namespace is None else namespace,
                              list(prefix), {**self.remaps, **dict(remaps or {})})
        return self._spawn(name)

    def _spawn(self, name: str) -> subprocess.Popen:
        spec, overrides, namespace, prefix, remaps = self._launch[name]
        with open(self.log_dir / f'{name}.log', 'ab') as log:
            child = subprocess.Popen([*prefix, *node_command(spec, overrides, namespace, remaps)], env=self.env,
                                     stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     start_new_session=True, preexec_fn=die_with_parent)
        self.children[name] = child
        if self.watchdog is not None:
            self.watchdog.started(name, time.monotonic())
        return child

    def supervise(self, heartbeats_s: Mapping[str, float] | None = None) -> list[Action]:
        """Restart the watched children that died or hung, each after its backoff; call this often.

        Args:
            heartbeats_s: Arrival time (time.monotonic, s) of each node's newest DiagnosticStatus, by node
                name with or without the leading '/'. Without heartbeats, no node can be found hung until
                the policy's start-up grace has passed, and then every one is: pass them.

        Returns:
            What was done, in order (empty almost always).

        Raises:
            SupervisorError: A child failed once more than the policy's restart budget allows.

        """
        if self.watchdog is None:
            return []
        now_s = time.monotonic()
        beats = {name.lstrip('/'): t for name, t in (heartbeats_s or {}).items()}
        status = {name: self.children[name].poll() for name in self.watchdog.watched()}
        actions = self.watchdog.step(now_s, status, beats)
        for action in actions:
            child = self.children[action.name]
            if action.kind is ActionKind.KILL:
                self._kill_hung(child)
                self.hangs.append(HangRecord(action.name, child.pid, action.silent_s or 0.0, now_s - self._t0_s,
                                             _utc_now()))
            if action.kind in (ActionKind.KILL, ActionKind.DOWN):
                self.restarts.append(RestartRecord(
                    action.name, 'hung' if action.kind is ActionKind.KILL else 'exited', action.reason,
                    child.returncode, child.pid, now_s - self._t0_s, _utc_now(), self.log_tail(action.name)))
                self._log_note(action.name, action.reason)
                if action.gave_up:
                    raise SupervisorError(f'{action.reason}; log {self.log_dir / (action.name + ".log")}:\n'
                                          f'{self.restarts[-1].log_tail}')
            elif action.kind is ActionKind.RESTART:
                new = self._spawn(action.name)
                record = next(r for r in reversed(self.restarts) if r.name == action.name)
                record.restarted_after_s = time.monotonic() - self._t0_s
                record.new_pid = new.pid
        return actions

    def _kill_hung(self, child: subprocess.Popen) -> None:
        # A hung (or stopped) process cannot run a clean shutdown: SIGKILL is the one signal it cannot ignore.
        try:
            os.killpg(child.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        child.wait()

    def _log_note(self, name: str, text: str) -> None:
        # The restarted process appends to the same log; a marker tells where the failed one ended.
        with open(self.log_dir / f'{name}.log', 'a') as log:
            log.write(f'--- supervisor {_utc_now()}: {text}\n')

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
        """Stop one child and its process group: SIGINT, then SIGTERM, then SIGKILL; return its exit status."""
        child = self.children.get(name)
        if child is None:
            return None
        if self.watchdog is not None:
            self.watchdog.stopped(name)
        _end_groups([child], timeout_s)
        return child.returncode

    def stop_all(self, timeout_s: float = 5.0) -> None:
        """Stop every child and its process group, all at once: SIGINT, then SIGTERM, then SIGKILL.

        Ends within about timeout_s + 4 s. A SIGINT or SIGTERM that comes meanwhile is held until every child
        is gone (a second Ctrl-C must not leave orphans), then raised as KeyboardInterrupt.
        """
        if self.watchdog is not None:
            for name in self.children:
                self.watchdog.stopped(name)
        for name, child in self.children.items():
            if child.poll() is None:
                self.cpu_s[name] = cpu_s(child.pid)
        held: list[int] = []
        saved = _hold_signals(held)
        try:
            _end_groups(list(self.children.values()), timeout_s)
        finally:
            for sig, handler in saved.items():
                signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        if held:
            raise KeyboardInterrupt(f'signal {held[0]} while stopping the children')


def _hold_signals(held: list[int]) -> dict[int, object]:
    """Record SIGINT and SIGTERM in `held` instead of acting on them; return the handlers to put back."""
    if threading.current_thread() is not threading.main_thread():
        return {}  # only the main thread may set handlers; stop_all off it is not interrupted by them anyway
    saved = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        saved[sig] = signal.signal(sig, lambda signum, _frame: held.append(signum))
    return saved


def _end_groups(children: Sequence[subprocess.Popen], timeout_s: float) -> None:
    # Each child leads its own process group (start_new_session), which holds whatever it forked: ANDES' code
    # generation pool, a shell's job. Signalling the leader's PID alone left those running after it died.
    for sig, wait_s in ((signal.SIGINT, timeout_s), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
        live = _live_groups(children)
        if not live:
            return
        for child in live:
            try:
                os.killpg(child.pid, sig)
            except (ProcessLookupError, PermissionError):
                pass
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline and _live_groups(live):
            time.sleep(0.05)


def _live_groups(children: Sequence[subprocess.Popen]) -> list[subprocess.Popen]:
    """Return the children still running, or whose process group still has a running (not zombie) process."""
    exited = {c.pid: c for c in children if c.poll() is not None}  # poll reaps an exited leader
    live = [c for c in children if c.pid not in exited]
    if exited:
        groups = set()
        for pid, state, pgid in processes():
            if state != 'Z':
                groups.add(pgid)
                # A reaped leader's number is reused only once its group is empty: a live one is someone else.
                exited.pop(pid, None)
        live += [c for pid, c in exited.items() if pid in groups]
    return live


def _utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec='milliseconds')
