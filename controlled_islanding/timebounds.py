"""Bounded time for values from the wire: no stamp may run ahead of the receiving node's own clock.

A node that keeps "the newest" of something by its stamp can be poisoned for good by one message stamped in
the future: every later, honest value then looks old. `StampGate` admits a stamp only if it is at most
`future_tolerance_s` ahead of the node clock (sim time during replay). While that clock has not started yet
(sim time before the first /clock reads 0), there is nothing to compare with, so stamped values are held, up
to `max_held` of them, and judged once the clock runs. No rclpy here: the nodes pass their clock reading in.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar('T')


class StampError(ValueError):
    """A stamp that must not be trusted; `reason` is the diagnostics key ('future_stamp')."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def check_not_future(what: str, stamp_s: float, now_s: float, future_tolerance_s: float) -> None:
    """Raise unless a stamp is at most `future_tolerance_s` ahead of `now_s` (a clock that has started).

    Raises:
        StampError: reason 'future_stamp', naming `what` and by how much it leads the clock.

    """
    lead_s = stamp_s - now_s
    if lead_s > future_tolerance_s:
        raise StampError('future_stamp', f'{what} stamped {stamp_s:.3f} s, {lead_s:.3f} s ahead of this node clock '
                                         f'({now_s:.3f} s); more than future_tolerance_s={future_tolerance_s}')


@dataclass
class StampGate(Generic[T]):
    """Admits, holds or refuses stamped items against a node clock.

    Attributes:
        future_tolerance_s: How far a stamp may lead the node clock, s.
        max_held: How many items may wait for a clock that has not started; the oldest is dropped beyond.

    """

    future_tolerance_s: float
    max_held: int = 1000

    def __post_init__(self) -> None:
        self._held: deque[tuple[str, float, T]] = deque()
        self.dropped_while_held = 0

    def offer(self, what: str, stamp_s: float, now_s: float, item: T) -> bool:
        """Return True when `item` may be used now; False when it is held for a clock that has not started.

        Raises:
            StampError: The stamp leads a running clock by more than the tolerance.

        """
        if now_s <= 0.0:
            if len(self._held) >= self.max_held:
                self._held.popleft()
                self.dropped_while_held += 1
            self._held.append((what, stamp_s, item))
            return False
        check_not_future(what, stamp_s, now_s, self.future_tolerance_s)
        return True

    def release(self, now_s: float, use: Callable[[T], None], refuse: Callable[[StampError], None]) -> None:
        """Once the clock runs, hand every held item to `use`, or its StampError to `refuse`, in arrival order."""
        if now_s <= 0.0:
            return
        while self._held:
            what, stamp_s, item = self._held.popleft()
            try:
                check_not_future(what, stamp_s, now_s, self.future_tolerance_s)
            except StampError as exc:
                refuse(exc)
                continue
            use(item)

    @property
    def held(self) -> int:
        """Number of items waiting for the clock."""
        return len(self._held)
