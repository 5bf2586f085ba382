"""Islanding requests that wait for what answers them: coherency for rotor angles, partitioning for groups."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

from rclpy.clock import Clock, ClockType
from rclpy.node import Node


class PendingRequests:
    """Requests held in arrival order, each until it is ready or its wall-clock wait is over.

    `serve()` hands every request for which `ready(request)` holds, or whose wait has ended, to `answer(request)`
    and keeps the others. A steady timer calls it every `period_s` only while a request waits (no 100 Hz wake-ups
    when idle); a node also calls it whenever new input may have made a request ready.

    Args:
        node: The node; the timer is its.
        guard: Wraps the timer callback (Diagnostics.guard), so that a failure is counted, never fatal.
        wait_s: How long a request may wait, wall s.
        ready: Whether a request can be answered now.
        answer: Answers one request (which is no longer held).
        period_s: Wall time between looks while something waits, s.

    """

    def __init__(self, node: Node, guard: Callable, wait_s: float, ready: Callable[[object], bool],
                 answer: Callable[[object], None], period_s: float = 0.01) -> None:
        self.wait_s = wait_s
        self._ready, self._answer = ready, answer
        self._held: list[tuple[object, float]] = []  # (request, wall deadline, time.monotonic s)
        self._timer = node.create_timer(period_s, guard(self.serve), clock=Clock(clock_type=ClockType.STEADY_TIME))

    def __len__(self) -> int:
        return len(self._held)

    def __iter__(self) -> Iterator[object]:
        return (request for request, _ in self._held)

    def waited_s(self, request: object) -> float:
        """Return how long a held request has waited so far, wall s (0 for one not held)."""
        deadline = next((d for r, d in self._held if r is request), None)
        return 0.0 if deadline is None else time.monotonic() - (deadline - self.wait_s)

    def add(self, request: object) -> None:
        """Hold a request for at most wait_s, and serve at once what can be."""
        self._held.append((request, time.monotonic() + self.wait_s))
        self._timer.reset()
        self.serve()

    def serve(self) -> None:
        """Answer, in arrival order, every held request that is ready or has waited long enough."""
        if not self._held:
            self._timer.cancel()
            return
        now = time.monotonic()
        for item in list(self._held):
            request, deadline = item
            if not self._ready(request) and now < deadline:
                continue
            self._held.remove(item)
            self._answer(request)
