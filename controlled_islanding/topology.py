"""The network as a node knows it: the latest snapshot plus every branch status change stamped after it.

Both partitioning (to decide) and breaker_command (to check a decision before acting) hold one. No rclpy here.

Time rules, because a value from the wire is never trusted for time:
- A snapshot or status stamped more than `future_tolerance_s` ahead of the node clock is refused.
- "Latest" is latest within that bound; an older snapshot than the one held is refused.
- Each branch keeps a short history of its changes, and the state at time t is the last change stamped at or
  before t. So a change stamped after t (a fake "back in service" a second ahead, say) never undoes a trip
  that t should see, and a refused or expired value blocks nothing that follows.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

from controlled_islanding.core.grid import Grid
from controlled_islanding.timebounds import StampError, check_not_future


class TopologyError(ValueError):
    """A snapshot or status change that is refused; `reason` is the diagnostics key."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


@dataclass
class Topology:
    """Snapshot and status changes, bounded in time and in memory.

    Attributes:
        future_tolerance_s: How far a stamp may lead the node clock, s.
        max_changes_per_branch: Changes remembered per branch; the oldest go first.

    """

    future_tolerance_s: float = 1.0
    max_changes_per_branch: int = 32
    snapshot: Grid | None = None
    snapshot_stamp_s: float = 0.0
    _changes: dict[str, list[tuple[float, bool]]] = field(default_factory=dict)
    _known: frozenset[str] = frozenset()

    def _bound(self, what: str, stamp_s: float, now_s: float) -> None:
        if stamp_s <= 0.0:
            raise TopologyError('missing_stamp', f'{what}: header.stamp is zero')
        try:
            check_not_future(what, stamp_s, now_s, self.future_tolerance_s)
        except StampError as exc:
            raise TopologyError(exc.reason, str(exc)) from exc

    def offer_snapshot(self, grid: Grid, stamp_s: float, now_s: float) -> None:
        """Take a snapshot unless it is older than the one held or stamped in the future.

        Raises:
            TopologyError: reason 'missing_stamp', 'future_stamp' or 'time_backwards'.

        """
        self._bound('network snapshot', stamp_s, now_s)
        if self.snapshot is not None and stamp_s < self.snapshot_stamp_s:
            raise TopologyError('time_backwards', f'snapshot stamped {stamp_s:.3f} s, older than the one held '
                                                  f'({self.snapshot_stamp_s:.3f} s)')
        self._known = frozenset(b.branch_id for b in grid.branches)
        self._changes = {k: v for k, v in self._changes.items() if k in self._known}
        self.snapshot, self.snapshot_stamp_s = grid, stamp_s

    def offer_status(self, branch_id: str, in_service: bool, stamp_s: float, now_s: float) -> None:
        """Record one branch status change.

        Raises:
            TopologyError: reason 'empty_message', 'missing_stamp', 'future_stamp', 'no_data' (no snapshot
                yet: its branch ids are what bounds the memory) or 'unknown_id'.

        """
        if not branch_id:
            raise TopologyError('empty_message', 'branch status without branch_id')
        self._bound(f'branch {branch_id} status', stamp_s, now_s)
        if self.snapshot is None:
            raise TopologyError('no_data', f'branch {branch_id} status before any network snapshot')
        if branch_id not in self._known:
            raise TopologyError('unknown_id', f'branch status for unknown branch {branch_id!r}')
        history = self._changes.setdefault(branch_id, [])
        entry = (stamp_s, bool(in_service))
        if entry in history:
            return
        bisect.insort(history, entry)
        del history[:-self.max_changes_per_branch]

    def outages_at(self, t_s: float) -> tuple[str, ...]:
        """Return the branches whose last change stamped after the snapshot and at or before t_s opened them."""
        out = []
        for branch_id, history in self._changes.items():
            i = bisect.bisect_right(history, (t_s, True))
            if i and history[i - 1][0] > self.snapshot_stamp_s and not history[i - 1][1]:
                out.append(branch_id)
        return tuple(sorted(out))

    def grid_at(self, t_s: float) -> tuple[Grid, tuple[str, ...]]:
        """Return the network at t_s and the branches tripped since the snapshot.

        Raises:
            TopologyError: reason 'no_data' when no snapshot is held.

        """
        if self.snapshot is None:
            raise TopologyError('no_data', 'no network snapshot')
        out = self.outages_at(t_s)
        return self.snapshot.with_outages(out), out

    def changes_known(self, t_s: float) -> int:
        """Return how many changes stamped after the snapshot and at or before t_s are held."""
        return sum(bisect.bisect_right(h, (t_s, True)) - bisect.bisect_right(h, (self.snapshot_stamp_s, True))
                   for h in self._changes.values())

    def changes_after(self, t_s: float) -> int:
        """Return how many remembered changes are stamped after t_s (later than a request, for instance)."""
        return sum(len(h) - bisect.bisect_right(h, (t_s, True)) for h in self._changes.values())
