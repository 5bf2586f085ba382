"""Decide when a supervised node is down, hung or due for a restart; pure, so it is tested without processes.

The supervisor feeds `Watchdog.step` the time, each child's exit status and the newest heartbeat of each
node (the arrival time of its DiagnosticStatus on /diagnostics, which every node publishes at least once per
second on the steady clock), and carries out the actions it returns.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum


class WatchdogError(ValueError):
    """A restart policy that cannot work."""


@dataclass(frozen=True)
class RestartPolicy:
    """Which nodes are restarted, how soon, how often, and how long a silent node may live.

    Attributes:
        nodes: Child names that are watched and restarted; any other child is left to end as it will.
        backoff_initial_s: Wait before the first restart after a failure, s.
        backoff_factor: Each further restart within restart_window_s waits this many times longer.
        backoff_max_s: Cap on the wait, s.
        max_restarts: Restarts allowed within restart_window_s; one more failure gives up on the node.
        restart_window_s: Restarts older than this no longer count towards the budget nor the backoff, s.
        hang_timeout_s: A node whose newest heartbeat is older than this is hung, s.
        startup_grace_s: A node that has not sent its first heartbeat this long after its start is hung, s.
        max_step_gap_s: Steps further apart than this mean the supervisor itself stalled; it then judges no
            hang until it has watched for hang_timeout_s again, s.

    """

    nodes: frozenset[str]
    backoff_initial_s: float = 0.5
    backoff_factor: float = 2.0
    backoff_max_s: float = 8.0
    max_restarts: int = 5
    restart_window_s: float = 60.0
    hang_timeout_s: float = 5.0
    startup_grace_s: float = 20.0
    max_step_gap_s: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, 'nodes', frozenset(self.nodes))
        for name in ('backoff_initial_s', 'backoff_max_s', 'restart_window_s', 'hang_timeout_s',
                     'startup_grace_s', 'max_step_gap_s'):
            if not getattr(self, name) > 0:
                raise WatchdogError(f'{name} must be positive, got {getattr(self, name)}')
        if self.backoff_factor < 1:
            raise WatchdogError(f'backoff_factor must be at least 1, got {self.backoff_factor}')
        if self.max_restarts < 0:
            raise WatchdogError(f'max_restarts must not be negative, got {self.max_restarts}')
        # Below one heartbeat period (1 s) every healthy node would count as hung between two heartbeats.
        if self.hang_timeout_s <= 1.0:
            raise WatchdogError(f'hang_timeout_s must exceed the 1 s heartbeat period, got {self.hang_timeout_s}')

    def backoff_s(self, recent_restarts: int) -> float:
        """Return the wait before the next restart, s, given how many restarts the window already holds."""
        return min(self.backoff_max_s, self.backoff_initial_s * self.backoff_factor ** recent_restarts)


class ActionKind(Enum):
    """What the supervisor must do about one node."""

    DOWN = 'down'          # it exited on its own: note it; a restart follows unless gave_up
    KILL = 'kill'          # it is hung: SIGKILL it; a restart follows unless gave_up
    RESTART = 'restart'    # its backoff has passed: start it again with the same parameters


@dataclass(frozen=True)
class Action:
    """One thing the supervisor must do, and why.

    Attributes:
        kind: What to do.
        name: The child.
        reason: One line for logs and reports.
        exit_status: The exit status that made it DOWN (negative: killed by that signal), else None.
        silent_s: For KILL, how long no heartbeat came, s (since its start when none ever came).
        restart_in_s: For DOWN and KILL, the backoff before the RESTART, s; None when giving up.
        gave_up: For DOWN and KILL, the failure exhausted the restart budget: no restart follows.

    """

    kind: ActionKind
    name: str
    reason: str
    exit_status: int | None = None
    silent_s: float | None = None
    restart_in_s: float | None = None
    gave_up: bool = False


@dataclass
class _Watch:
    started_s: float
    heartbeat_s: float | None = None
    restart_at_s: float | None = None  # set while down and waiting out its backoff
    gave_up: bool = False
    restarts_s: deque[float] = field(default_factory=deque)


class Watchdog:
    """Tracks each watched child through running, down (backoff) and restarted, and spots hung ones.

    Args:
        policy: What to watch and the timings.

    """

    def __init__(self, policy: RestartPolicy) -> None:
        self.policy = policy
        self._watches: dict[str, _Watch] = {}
        self._last_step_s: float | None = None
        self._watching_since_s = 0.0

    def watched(self) -> list[str]:
        """Return the names being watched now (started, not stopped on purpose, not given up on)."""
        return [n for n, w in self._watches.items() if not w.gave_up]

    def started(self, name: str, now_s: float) -> None:
        """Note that a child was (re)started at now_s; unwatched names are ignored."""
        if name not in self.policy.nodes:
            return
        previous = self._watches.get(name)
        watch = _Watch(started_s=now_s)
        if previous is not None:
            watch.restarts_s = previous.restarts_s
            if previous.restart_at_s is not None:
                watch.restarts_s.append(now_s)
        self._watches[name] = watch

    def stopped(self, name: str) -> None:
        """Forget a child that the supervisor stops on purpose, so its ending is not a failure."""
        self._watches.pop(name, None)

    def step(self, now_s: float, exit_status: Mapping[str, int | None],
             heartbeats_s: Mapping[str, float]) -> list[Action]:
        """Return what to do now.

        Args:
            now_s: The time, on the clock of started() and heartbeats_s (monotonic), s.
            exit_status: Each child's exit status, None while it runs.
            heartbeats_s: Arrival time of each node's newest heartbeat, s, by child name.

        Returns:
            Actions in the order to carry them out.

        """
        actions: list[Action] = []
        # Heartbeats arrive through the supervising process: if it stalled, their silence is its own, not
        # the nodes', and killing the whole graph for it would turn one slow moment into a failed run.
        if self._last_step_s is None or now_s - self._last_step_s > self.policy.max_step_gap_s:
            self._watching_since_s = now_s
        self._last_step_s = now_s
        judging = now_s - self._watching_since_s > self.policy.hang_timeout_s
        for name, watch in list(self._watches.items()):
            if watch.gave_up:
                continue
            if watch.restart_at_s is not None:
                if now_s >= watch.restart_at_s:
                    actions.append(Action(ActionKind.RESTART, name, 'backoff over'))
                continue
            status = exit_status.get(name)
            if status is not None:
                actions.append(self._down(name, watch, now_s, ActionKind.DOWN,
                                          f'{name} exited with status {status}', exit_status=status))
                continue
            beat = heartbeats_s.get(name)
            # A heartbeat older than the start came from the process this one replaced.
            if beat is not None and beat >= watch.started_s:
                watch.heartbeat_s = beat
            if not judging:
                continue
            if watch.heartbeat_s is None:
                silent_s = now_s - watch.started_s
                if silent_s > self.policy.startup_grace_s:
                    actions.append(self._down(name, watch, now_s, ActionKind.KILL,
                                              f'{name} sent no heartbeat in the {silent_s:.1f} s since its start',
                                              silent_s=silent_s))
            else:
                silent_s = now_s - watch.heartbeat_s
                if silent_s > self.policy.hang_timeout_s:
                    actions.append(self._down(name, watch, now_s, ActionKind.KILL,
                                              f'{name} hung: no heartbeat for {silent_s:.1f} s', silent_s=silent_s))
        return actions

    def _down(self, name: str, watch: _Watch, now_s: float, kind: ActionKind, reason: str,
              exit_status: int | None = None, silent_s: float | None = None) -> Action:
        _expire(watch.restarts_s, now_s - self.policy.restart_window_s)
        recent = len(watch.restarts_s)
        if recent >= self.policy.max_restarts:
            watch.gave_up = True
            return Action(kind, name, f'{reason}; {recent} restarts within {self.policy.restart_window_s:g} s '
                                      'already, giving up', exit_status=exit_status, silent_s=silent_s, gave_up=True)
        delay_s = self.policy.backoff_s(recent)
        watch.restart_at_s = now_s + delay_s
        return Action(kind, name, f'{reason}; restart in {delay_s:g} s', exit_status=exit_status,
                      silent_s=silent_s, restart_in_s=delay_s)

    def gave_up_on(self) -> list[str]:
        """Return the children given up on."""
        return [n for n, w in self._watches.items() if w.gave_up]


def _expire(times_s: deque[float], before_s: float) -> None:
    while times_s and times_s[0] < before_s:
        times_s.popleft()

