"""Bounded time for values from the wire: no stamp may run ahead of the receiving node's own clock.

A node that keeps "the newest" of something by its stamp can be poisoned for good by one message stamped in
the future: every later, honest value then looks old. `StampGate` uses a stamp only once it is at most
`future_tolerance_s` ahead of the node clock (sim time during replay):
- further ahead than `hold_horizon_s`: refused at once (a stamp a day or a year ahead is never honest);
- between the two: held until the clock catches up. A node's sim clock can lag the data by seconds when its
  executor was busy (a 1.5 s warm-up while /clock messages queue behind data), and an honest value must not
  be lost for that; held, a value is never used before its time, so it cannot poison anything early;
- while the clock has not started (sim time before the first /clock reads 0): held, and judged once it runs.
At most `max_held` values wait, carrying at most `max_held_elements` elements between them, and at most
HELD_SNAPSHOTS network snapshots; beyond, the oldest (of that kind) is dropped. No rclpy here: the nodes pass their
clock in.

Under use_sim_time the node clock is itself a value from the wire (/clock, which any node may publish):
`SimClockGuard` bounds it against the wall clock (monotonic, and no faster than a multiple of wall time).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar('T')

# A count alone did not bound the memory: 1000 held snapshots of the GB network took 1.1 GB, and at the decoders'
# caps one is tens of MB. In elements (wire.messages.element_count) a snapshot at the caps is 1.16 M and a frame
# of 10,000 stations 90,000 (3.1 MB decoded, the heaviest per element). The budget holds 1000 frames of every
# station of the largest system in bags/ (GB, 394 stations: 3.5 M) beside one snapshot at the caps; at most about
# 170 MB, in 55 frames at the caps.
MAX_HELD_ELEMENTS = 5_000_000
# A snapshot is the whole network: a newer one supersedes it. The topology (safety/topology.py) keeps as many.
HELD_SNAPSHOTS = 4
SNAPSHOT = 'snapshot'


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


class Backlog(Generic[T]):
    """Items kept for later, oldest first, bounded in number and in elements together; beyond, the oldest go.

    For what a node keeps before it can judge it (what waits for the clock in StampGate; frames or rotor angles
    before the first network snapshot): a count alone lets messages at the decoders' caps take GBs (1000 PMU
    frames of 10,000 stations: about 3 GB).
    """

    def __init__(self, max_items: int, max_elements: int = MAX_HELD_ELEMENTS) -> None:
        self.max_items, self.max_elements = int(max_items), int(max_elements)
        self._items: deque[tuple[T, int]] = deque()
        self.elements = 0

    def append(self, item: T, elements: int) -> int:
        """Keep an item of `elements` elements; return how many of the oldest were dropped (never the newest)."""
        self._items.append((item, max(int(elements), 1)))
        self.elements += self._items[-1][1]
        dropped = 0
        while len(self._items) > 1 and (len(self._items) > self.max_items or self.elements > self.max_elements):
            self.popleft()
            dropped += 1
        return dropped

    def remove(self, item: T) -> None:
        """Remove an item kept (that very object)."""
        pair = next(p for p in self._items if p[0] is item)
        self._items.remove(pair)
        self.elements -= pair[1]

    def popleft(self) -> T:
        """Remove and return the oldest item."""
        item, elements = self._items.popleft()
        self.elements -= elements
        return item

    def __getitem__(self, i: int) -> T:
        return self._items[i][0]

    def __iter__(self) -> Iterator[T]:
        return (item for item, _ in self._items)

    def __len__(self) -> int:
        return len(self._items)


@dataclass(eq=False)
class _Held(Generic[T]):
    what: str
    stamp_s: float
    item: T
    elements: int
    kind: str


@dataclass
class StampGate(Generic[T]):
    """Admits, holds or refuses stamped items against a node clock.

    Attributes:
        future_tolerance_s: How far a stamp may lead the node clock and still be used at once, s.
        max_held: How many items may wait for the clock; the oldest is dropped beyond.
        hold_horizon_s: How far a stamp may lead the clock and still be held rather than refused, s.
        max_held_elements: How many elements (wire.messages.element_count) the waiting items may carry together;
            the oldest is dropped beyond, though the newest item is always kept.

    """

    future_tolerance_s: float
    max_held: int = 1000
    hold_horizon_s: float = 60.0
    max_held_elements: int = MAX_HELD_ELEMENTS

    def __post_init__(self) -> None:
        self._held: Backlog[_Held[T]] = Backlog(self.max_held, self.max_held_elements)
        self.dropped_while_held = 0

    def _hold(self, entry: _Held[T]) -> None:
        if entry.kind == SNAPSHOT:
            snapshots = [e for e in self._held if e.kind == SNAPSHOT]
            for old in snapshots[:max(len(snapshots) - HELD_SNAPSHOTS + 1, 0)]:
                self._held.remove(old)
                self.dropped_while_held += 1
        self.dropped_while_held += self._held.append(entry, entry.elements)

    def offer(self, what: str, stamp_s: float, now_s: float, item: T, elements: int = 1, kind: str = '') -> bool:
        """Return True when `item` may be used now; False when it is held until the clock reaches it.

        `elements` is the item's size, `kind` SNAPSHOT for a network snapshot.

        Raises:
            StampError: The stamp leads a running clock by more than `hold_horizon_s`.

        """
        if now_s > 0.0:
            check_not_future(what, stamp_s, now_s, self.hold_horizon_s)
            if stamp_s - now_s <= self.future_tolerance_s:
                return True
        self._hold(_Held(what, stamp_s, item, max(int(elements), 1), kind))
        return False

    def release(self, now_s: float, use: Callable[[T], None], refuse: Callable[[StampError], None]) -> None:
        """Hand every held item the clock has reached to `use`, in arrival order; keep the others.

        `refuse` gets the StampError of an item held before the clock started that turns out to lead it by more
        than `hold_horizon_s`.
        """
        if now_s <= 0.0:
            return
        keep: Backlog[_Held[T]] = Backlog(self.max_held, self.max_held_elements)
        while self._held:
            entry = self._held.popleft()
            try:
                check_not_future(entry.what, entry.stamp_s, now_s, self.hold_horizon_s)
            except StampError as exc:
                refuse(exc)
                continue
            if entry.stamp_s - now_s <= self.future_tolerance_s:
                use(entry.item)
            else:
                keep.append(entry, entry.elements)  # fewer than were held: nothing is dropped
        self._held = keep

    @property
    def held(self) -> int:
        """Number of items waiting for the clock."""
        return len(self._held)

    @property
    def held_elements(self) -> int:
        """Elements the items waiting for the clock carry together."""
        return self._held.elements


@dataclass(frozen=True)
class ClockJump:
    """One reading of sim time that the trusted clock cannot have produced.

    Attributes:
        kind: 'back' (earlier than the trusted time) or 'ahead' (further on than the rate bound allows).
        trusted_s: The trusted sim time before the reading, s.
        read_s: The sim time read, s.
        allowed_s: How far sim time could have advanced since the trusted reading, s.

    """

    kind: str
    trusted_s: float
    read_s: float
    allowed_s: float

    def describe(self) -> str:
        """Return a line naming the jump, for the audit log and diagnostics."""
        lead_s = self.read_s - self.trusted_s
        if self.kind == 'back':
            return f'sim clock jumped back {-lead_s:.3f} s, from {self.trusted_s:.3f} s to {self.read_s:.3f} s'
        return (f'sim clock jumped ahead {lead_s:.3f} s, from {self.trusted_s:.3f} s to {self.read_s:.3f} s, '
                f'more than the {self.allowed_s:.3f} s it may advance by now')


@dataclass
class SimClockGuard:
    """Bounds a sim clock (/clock) against the wall clock, so that no one publisher of /clock can forge time.

    Under use_sim_time any node may publish /clock, and a node's freshness rules trust its clock. A reading is
    consistent when it is no earlier than the trusted sim time (monotonic) and no further on than a token
    bucket allows: `max_jump_s` at once, refilled at `max_rate` seconds of sim time per second of wall time
    (so over any stretch, sim time advances at most max_rate x wall time + max_jump_s). A consistent reading
    becomes the trusted time; an inconsistent one is a ClockJump and moves nothing, so the honest clock,
    still running beside a forger, stays consistent with the trusted time while the forged readings do not.

    The clock is consistent again once `recovery_s` of wall time passed since the last inconsistent reading:
    every reading meanwhile followed the trusted clock. A clock that stays on another timeline (a forger
    alone, or a new bag played into a running node) never does; only a restart of the node trusts it.
    The first reading after the clock started (sim time > 0) is trusted as it is. No rclpy: the node passes
    (wall, sim) readings in, wall on a steady clock.

    Attributes:
        max_rate: Seconds of sim time the clock may advance per second of wall time, on average.
        max_jump_s: Sim time the clock may advance at once (and the most credit a standing clock saves), s.
        recovery_s: Wall time after the last inconsistent reading before the clock is trusted again, s.

    """

    max_rate: float
    max_jump_s: float
    recovery_s: float

    def __post_init__(self) -> None:
        self._wall_s: float | None = None
        self._sim_s = 0.0
        self._budget_s = self.max_jump_s
        self._last_jump_wall_s: float | None = None
        self.last_jump: ClockJump | None = None
        self.jumps = 0

    def observe(self, wall_s: float, sim_s: float) -> ClockJump | None:
        """Take one reading of the sim clock; return the jump it makes, or None when it is consistent."""
        if self._wall_s is None:
            if sim_s > 0.0:
                self._wall_s, self._sim_s = wall_s, sim_s
            return None
        self._budget_s = min(self.max_jump_s, self._budget_s + self.max_rate * max(wall_s - self._wall_s, 0.0))
        self._wall_s = max(wall_s, self._wall_s)
        lead_s = sim_s - self._sim_s
        if 0.0 <= lead_s <= self._budget_s:
            self._budget_s -= lead_s
            self._sim_s = sim_s
            return None
        jump = ClockJump('back' if lead_s < 0.0 else 'ahead', self._sim_s, sim_s, self._budget_s)
        self._last_jump_wall_s, self.last_jump = self._wall_s, jump
        self.jumps += 1
        return jump

    def inconsistency(self, wall_s: float) -> str | None:
        """Why the clock cannot be trusted at `wall_s`, or None when it can.

        Inconsistent: a jump less than `recovery_s` of wall time ago.
        """
        if self._last_jump_wall_s is None or self.last_jump is None:
            return None
        quiet_s = wall_s - self._last_jump_wall_s
        if quiet_s >= self.recovery_s:
            return None
        return (f'{self.last_jump.describe()}, {quiet_s:.3f} s ago (wall); trusted again after {self.recovery_s:g} s '
                'of readings that follow the trusted clock')

    @property
    def trusted_s(self) -> float:
        """The trusted sim time, s (0 before the clock started)."""
        return self._sim_s
