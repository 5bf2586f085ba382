"""The network as a node knows it: recent snapshots plus every branch status change, each judged by its stamp.

Both partitioning (to decide) and breaker_command (to check a decision before acting) hold one. No rclpy here.

Time rules, because a value from the wire is never trusted for time:
- A snapshot or status stamped more than `future_tolerance_s` ahead of the node clock is refused, and so is a
  snapshot older than the newest held.
- The network at time t is the newest snapshot stamped at or before t, so a snapshot stamped after t (a copy
  replayed with a later stamp, say) never changes what t sees.
- On top of that snapshot, a branch is out at t when its last change stamped after the snapshot and at or
  before t opened it. Each branch keeps a short history, so a change stamped after t never undoes a trip t
  should see. A snapshot stamped within the tolerance ahead becomes the network once the clock passes its
  stamp: a snapshot is authoritative for its time, as a state estimator's is.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

from controlled_islanding.core.grid import Grid
from controlled_islanding.wire.timebounds import HELD_SNAPSHOTS, StampError, check_not_future


class TopologyError(ValueError):
    """A snapshot or status change that is refused; `reason` is the diagnostics key."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


@dataclass
class Topology:
    """Snapshots and status changes, bounded in time and in memory.

    Attributes:
        future_tolerance_s: How far a stamp may lead the node clock, s.
        max_changes_per_branch: Changes remembered per branch; the oldest go first.
        max_branches_before_snapshot: Distinct branches whose changes are kept while no snapshot is held.

    """

    future_tolerance_s: float = 1.0
    max_changes_per_branch: int = 32
    max_branches_before_snapshot: int = 100_000
    _snapshots: list[tuple[float, Grid]] = field(default_factory=list)
    _changes: dict[str, list[tuple[float, bool]]] = field(default_factory=dict)
    _known: frozenset[str] = frozenset()

    @property
    def snapshot(self) -> Grid | None:
        """The newest snapshot held."""
        return self._snapshots[-1][1] if self._snapshots else None

    @property
    def snapshot_stamp_s(self) -> float:
        """The stamp of the newest snapshot held, s (0 when none)."""
        return self._snapshots[-1][0] if self._snapshots else 0.0

    def _bound(self, what: str, stamp_s: float, now_s: float) -> None:
        if stamp_s <= 0.0:
            raise TopologyError('missing_stamp', f'{what}: header.stamp is zero')
        try:
            check_not_future(what, stamp_s, now_s, self.future_tolerance_s)
        except StampError as exc:
            raise TopologyError(exc.reason, str(exc)) from exc

    def offer_snapshot(self, grid: Grid, stamp_s: float, now_s: float) -> None:
        """Take a snapshot unless it is older than the newest held or stamped in the future.

        Raises:
            TopologyError: reason 'missing_stamp', 'future_stamp' or 'time_backwards'.

        """
        self._bound('network snapshot', stamp_s, now_s)
        if self._snapshots and stamp_s < self._snapshots[-1][0]:
            raise TopologyError('time_backwards', f'snapshot stamped {stamp_s:.3f} s, older than the one held '
                                                  f'({self._snapshots[-1][0]:.3f} s)')
        self._snapshots.append((stamp_s, grid))
        del self._snapshots[:-HELD_SNAPSHOTS]
        self._known = frozenset(b.branch_id for _, g in self._snapshots for b in g.branches)
        self._changes = {k: v for k, v in self._changes.items() if k in self._known}

    def offer_status(self, branch_id: str, in_service: bool, stamp_s: float, now_s: float) -> None:
        """Record one branch status change.

        Raises:
            TopologyError: reason 'empty_message', 'missing_stamp', 'future_stamp', 'unknown_id', or
                'too_large' (more than `max_branches_before_snapshot` branches named before any snapshot).

        """
        if not branch_id:
            raise TopologyError('empty_message', 'branch status without branch_id')
        self._bound(f'branch {branch_id} status', stamp_s, now_s)
        if not self._snapshots:
            # Topics are not ordered against each other: a trip can arrive before the snapshot it applies to.
            # It is kept, and judged against the snapshot's branch ids when that comes; until then only the
            # number of branches bounds the memory.
            if branch_id not in self._changes and len(self._changes) >= self.max_branches_before_snapshot:
                raise TopologyError('too_large', f'branch {branch_id} status: {len(self._changes)} branches '
                                                 f'already named before any network snapshot')
        elif branch_id not in self._known:
            raise TopologyError('unknown_id', f'branch status for unknown branch {branch_id!r}')
        history = self._changes.setdefault(branch_id, [])
        entry = (stamp_s, bool(in_service))
        if entry in history:
            return
        bisect.insort(history, entry)
        del history[:-self.max_changes_per_branch]

    def snapshot_at(self, t_s: float) -> tuple[float, Grid]:
        """Return (stamp, grid) of the newest snapshot stamped at or before t_s (else the oldest held).

        Raises:
            TopologyError: reason 'no_data' when no snapshot is held.

        """
        if not self._snapshots:
            raise TopologyError('no_data', 'no network snapshot')
        i = bisect.bisect_right([s for s, _ in self._snapshots], t_s)
        return self._snapshots[max(i - 1, 0)]

    def outages_at(self, t_s: float) -> tuple[str, ...]:
        """Return the branches opened by their last change stamped after the snapshot valid at t_s, up to t_s."""
        since_s = self.snapshot_at(t_s)[0] if self._snapshots else 0.0
        out = []
        for branch_id, history in self._changes.items():
            i = bisect.bisect_right(history, (t_s, True))
            if i and history[i - 1][0] > since_s and not history[i - 1][1]:
                out.append(branch_id)
        return tuple(sorted(out))

    def grid_at(self, t_s: float) -> tuple[Grid, tuple[str, ...]]:
        """Return the network at t_s and the branches tripped since its snapshot.

        Raises:
            TopologyError: reason 'no_data' when no snapshot is held.

        """
        _, grid = self.snapshot_at(t_s)
        ids = {b.branch_id for b in grid.branches}
        out = tuple(b for b in self.outages_at(t_s) if b in ids)
        return grid.with_outages(out), out

    def changes_known(self, t_s: float) -> int:
        """Return how many status changes stamped after the snapshot valid at t_s, and at or before t_s, are held."""
        since_s = self.snapshot_at(t_s)[0] if self._snapshots else 0.0
        return sum(max(0, bisect.bisect_right(h, (t_s, True)) - bisect.bisect_right(h, (since_s, True)))
                   for h in self._changes.values())
