"""Network snapshots decoded alike by every node, within one declared set of size limits."""

from __future__ import annotations

from rclpy.node import Node

from controlled_islanding.core.grid import Grid
from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.params import declare_limits
from controlled_islanding.wire.messages import MessageError, grid_from_snapshot


class SnapshotIntake:
    """Declares the snapshot size limits as parameters (max_buses, max_branches, max_generators, max_loads).

    `grid(msg)` decodes a NetworkSnapshot, or counts and logs why it cannot (its reason in /diagnostics).

    Args:
        node: The node whose parameters hold the limits.
        diag: Its diagnostics.

    """

    def __init__(self, node: Node, diag: Diagnostics) -> None:
        self.limits = declare_limits(node)
        self._diag = diag

    def grid(self, msg: object) -> Grid | None:
        """Return the snapshot's Grid, or None when it is refused (rejected with its reason)."""
        try:
            return grid_from_snapshot(msg, self.limits)
        except MessageError as exc:
            self._diag.reject(exc.reason, f'network snapshot: {exc}')
            return None
