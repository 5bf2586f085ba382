"""Network snapshots decoded alike by every node, within one declared set of size limits."""

from __future__ import annotations

import math

from rclpy.node import Node

from controlled_islanding.core.grid import Grid
from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.params import declare_limits
from controlled_islanding.wire.messages import MessageError, grid_from_snapshot, stamp_s


class SnapshotIntake:
    """Declares the snapshot size limits as parameters (max_buses, max_branches, max_generators, max_loads).

    `grid(msg)` decodes a NetworkSnapshot, or counts and logs why it cannot (its reason in /diagnostics);
    `newer(msg)` also refuses one stamped before the newest it took (`stamp_s`).

    Args:
        node: The node whose parameters hold the limits.
        diag: Its diagnostics.

    """

    def __init__(self, node: Node, diag: Diagnostics) -> None:
        self.limits = declare_limits(node)
        self._diag = diag
        self.stamp_s = -math.inf  # stamp of the newest snapshot newer() took, s

    def grid(self, msg: object) -> Grid | None:
        """Return the snapshot's Grid, or None when it is refused (rejected with its reason)."""
        try:
            return grid_from_snapshot(msg, self.limits)
        except MessageError as exc:
            self._diag.reject(exc.reason, f'network snapshot: {exc}')
            return None

    def newer(self, msg: object) -> Grid | None:
        """Return the snapshot's Grid and hold its stamp, or None when it is refused or older than the one held."""
        grid = self.grid(msg)
        if grid is None:
            return None
        t = stamp_s(msg.header.stamp)
        if t < self.stamp_s:
            self._diag.reject('time_backwards', f'network snapshot stamped {t:.3f} s, older than the one held '
                                                f'({self.stamp_s:.3f} s)')
            return None
        self.stamp_s = t
        return grid
