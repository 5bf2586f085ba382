"""Bounded time for values from the wire: no stamp may run ahead of the receiving node's own clock.

A node that keeps "the newest" of something by its stamp can be poisoned for good by one message stamped in
the future: every later, honest value then looks old. `StampGate` uses a stamp only once it is at most
`future_tolerance_s` ahead of the node clock (sim time during replay):
- further ahead than `hold_horizon_s`: refused at once (a stamp a day or a year ahead is never honest);
- between the two: held until the clock catches up. A node's sim clock can lag the data by seconds when its
  executor was busy (a 1.5 s warm-up while /clock messages queue behind data), and an honest value must not
  be lost for that; held, a value is never used before its time, so it cannot poison anything early;
- while the clock has not started (sim time before the first /clock reads 0): held, and judged once it runs.
At most `max_held` values wait; beyond, the oldest is dropped. No rclpy here: the nodes pass their clock in.
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
        future_tolerance_s: How far a stamp may lead the node clock and still be used at once, s.
        max_held: How many items may wait for the clock; the oldest is dropped beyond.
        hold_horizon_s: How far a stamp may lead the clock and still be held rather than refused, s.

    """

    future_tolerance_s: float
    max_held: int = 1000
    hold_horizon_s: float = 60.0

    def __post_init__(self) -> None:
        self._held: deque[tuple[str, float, T]] = deque()
        self.dropped_while_held = 0

    def _hold(self, what: str, stamp_s: float, item: T) -> None:
        if len(self._held) >= self.max_held:
            self._held.popleft()
            self.dropped_while_held += 1
        self._held.append((what, stamp_s, item))

    def offer(self, what: str, stamp_s: float, now_s: float, item: T) -> bool:
        """Return True when `item` may be used now; False when it is held until the clock reaches it.

        Raises:
            StampError: The stamp leads a running clock by more than `hold_horizon_s`.

        """
        if now_s > 0.0:
            check_not_future(what, stamp_s, now_s, self.hold_horizon_s)
            if stamp_s - now_s <= self.future_tolerance_s:
                return True
        self._hold(what, stamp_s, item)
        return False

    def release(self, now_s: float, use: Callable[[T], None], refuse: Callable[[StampError], None]) -> None:
        """Hand every held item the clock has reached to `use`, in arrival order; keep the others.

        `refuse` gets the StampError of an item held before the clock started that turns out to lead it by more
        than `hold_horizon_s`.
        """
        if now_s <= 0.0:
            return
        keep: deque[tuple[str, float, T]] = deque()
        while self._held:
            what, stamp_s, item = self._held.popleft()
            try:
                check_not_future(what, stamp_s, now_s, self.hold_horizon_s)
            except StampError as exc:
                refuse(exc)
                continue
            if stamp_s - now_s <= self.future_tolerance_s:
                use(item)
            else:
                keep.append((what, stamp_s, item))
        self._held = keep

    @property
    def held(self) -> int:
        """Number of items waiting for the clock."""
        return len(self._held)
