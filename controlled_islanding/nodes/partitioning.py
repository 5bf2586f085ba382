"""partitioning: on an islanding request, split the current network for the latest coherent groups.

The network is the latest snapshot with every branch status change stamped after it applied, in stamp order
(so the order the two topics arrive in does not matter). A request waits for groups at least as new as the
request (within `groups_tolerance_s`: the coherency node recomputes on every request), at most
`groups_wait_s` of wall time, then uses the latest groups it has.

To keep the request path short, decisions are cached by (groups, tripped branches): every time new groups
or a topology change arrive, the decision for them is computed ahead of any request. A request whose fresh
groups equal the warm ones is answered from the cache.
"""

from __future__ import annotations

import sys
import time
import uuid
from dataclasses import dataclass

from controlled_islanding_msgs.msg import BranchStatus, CoherentGroups, IslandingDecision, IslandingRequest
from controlled_islanding_msgs.msg import NetworkSnapshot as NetworkSnapshotMsg
from controlled_islanding_msgs.srv import RequestIslanding
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from controlled_islanding import topics
from controlled_islanding.core.grid import Grid
from controlled_islanding.core.islanding import IslandingDecision as Decision
from controlled_islanding.core.islanding import decide
from controlled_islanding.core.spectral import ConstrainedSpectralPartition  # noqa: F401  imported now, not mid-request
from controlled_islanding.messages import Groups, MessageError, grid_from_snapshot, groups_from_msg, stamp_s
from controlled_islanding.node_common import Diagnostics, qos_for, settle_heap, spin_node


@dataclass
class _Pending:
    request: IslandingRequest
    deadline: float


def decision_to_msg(decision: Decision, request: IslandingRequest, method: str, compute_time_s: float,
                    ) -> IslandingDecision:
    """Encode a core decision as an IslandingDecision message answering a request."""
    buses = sorted(decision.bus_island)
    msg = IslandingDecision(
        decision_id=str(uuid.uuid4()), request_id=request.request_id, request_stamp=request.header.stamp,
        method=method, split=decision.split, bus_numbers=buses, bus_island=[decision.bus_island[b] for b in buses],
        cut_branch_ids=[b.branch_id for b in decision.cut_branches],
        cut_from_bus=[b.from_bus for b in decision.cut_branches], cut_to_bus=[b.to_bus for b in decision.cut_branches],
        island_generation_mw=list(decision.island_generation_mw), island_load_mw=list(decision.island_load_mw),
        island_imbalance_mw=list(decision.island_imbalance_mw), island_shed_mw=list(decision.island_shed_mw),
        disrupted_mw=decision.disrupted_mw, compute_time_s=compute_time_s)
    return msg


class PartitioningNode(Node):
    """Keeps the network and the groups; answers islanding requests with decisions."""

    def __init__(self) -> None:
        super().__init__('partitioning')
        self.declare_parameter('groups_tolerance_s', 0.05)
        self.declare_parameter('groups_wait_s', 0.5)
        self.declare_parameter('groups_method', 'dtw')
        self.tolerance_s = float(self.get_parameter('groups_tolerance_s').value)
        self.wait_s = float(self.get_parameter('groups_wait_s').value)
        self.method = str(self.get_parameter('groups_method').value)
        self.snapshot: Grid | None = None
        self.snapshot_stamp_s = 0.0
        self.events: dict[str, tuple[float, bool]] = {}  # branch id -> (stamp s, in service) of its latest change
        self.groups: Groups | None = None
        self.cache: dict[tuple, Decision] = {}
        self.pending: list[_Pending] = []
        self.answered: set[str] = set()
        self.diag = Diagnostics(self)
        self.decision_pub = self.create_publisher(IslandingDecision, topics.ISLANDING_DECISION,
                                                  qos_for(topics.ISLANDING_DECISION))
        self.request_pub = self.create_publisher(IslandingRequest, topics.ISLANDING_REQUEST,
                                                 qos_for(topics.ISLANDING_REQUEST))
        self.create_subscription(NetworkSnapshotMsg, topics.NETWORK_SNAPSHOT, self.on_snapshot,
                                 qos_for(topics.NETWORK_SNAPSHOT))
        self.create_subscription(BranchStatus, topics.BRANCH_STATUS, self.on_branch_status,
                                 qos_for(topics.BRANCH_STATUS))
        self.create_subscription(CoherentGroups, topics.COHERENT_GROUPS, self.on_groups,
                                 qos_for(topics.COHERENT_GROUPS))
        self.create_subscription(IslandingRequest, topics.ISLANDING_REQUEST, self.on_request,
                                 qos_for(topics.ISLANDING_REQUEST))
        self.create_service(RequestIslanding, '~/request', self.on_service)
        # Polls for the wait deadlines only while a request waits (no 100 Hz wake-ups when idle).
        self.pending_timer = self.create_timer(0.01, self._serve_pending, clock=Clock(clock_type=ClockType.STEADY_TIME))

    # --- inputs -------------------------------------------------------------------------------------------------
    def on_snapshot(self, msg: NetworkSnapshotMsg) -> None:
        """Replace the network snapshot."""
        self.diag.arrived()
        try:
            grid = grid_from_snapshot(msg)
        except MessageError as exc:
            self.diag.reject(exc.reason, f'network snapshot: {exc}')
            return
        stamp = stamp_s(msg.header.stamp)
        if self.snapshot is not None and stamp < self.snapshot_stamp_s:
            self.diag.reject('time_backwards', f'snapshot stamped {stamp:.3f} s, older than the one held')
            return
        self.snapshot, self.snapshot_stamp_s = grid, stamp
        self.cache.clear()
        self.diag.values['buses'] = str(len(grid.buses))
        self._warm_up(grid)
        self._warm()

    def on_branch_status(self, msg: BranchStatus) -> None:
        """Record a branch status change."""
        self.diag.arrived()
        stamp = stamp_s(msg.header.stamp)
        if not msg.branch_id:
            self.diag.reject('empty_message', 'branch status without branch_id')
            return
        if self.snapshot is not None and msg.branch_id not in {b.branch_id for b in self.snapshot.branches}:
            self.diag.reject('unknown_id', f'branch status for unknown branch {msg.branch_id!r}')
            return
        held = self.events.get(msg.branch_id)
        if held is not None and stamp < held[0]:
            self.diag.reject('time_backwards', f'branch {msg.branch_id} status stamped {stamp:.3f} s, '
                                               f'before its last change at {held[0]:.3f} s')
            return
        self.events[msg.branch_id] = (stamp, bool(msg.in_service))
        self._warm()

    def on_groups(self, msg: CoherentGroups) -> None:
        """Take new coherent groups; compute their decision ahead of a request."""
        self.diag.arrived()
        try:
            groups = groups_from_msg(msg)
        except MessageError as exc:
            self.diag.reject(exc.reason, f'coherent groups: {exc}')
            return
        if self.method and groups.method != self.method:
            self.diag.reject('unknown_id', f'groups of method {groups.method!r}; this node uses {self.method!r}')
            return
        if self.groups is not None and groups.stamp_s < self.groups.stamp_s:
            self.diag.reject('time_backwards', f'groups stamped {groups.stamp_s:.3f} s, older than the ones held')
            return
        if self.snapshot is not None:
            unknown = sorted(set(groups.names) ^ {g.name for g in self.snapshot.generators})
            if unknown:
                self.diag.reject('unknown_id', f'groups and network disagree on generators {unknown}')
                return
        self.groups = groups
        self.diag.values['k'] = str(groups.k)
        self._serve_pending()
        self._warm()

    def on_request(self, msg: IslandingRequest) -> None:
        """Queue a request until fresh groups arrive (or the wait ends)."""
        self.diag.arrived()
        if not msg.request_id:
            self.diag.reject('empty_message', 'islanding request without request_id')
            return
        if stamp_s(msg.header.stamp) <= 0:
            self.diag.reject('missing_stamp', f'request {msg.request_id}: header.stamp is zero')
            return
        if msg.request_id in self.answered or any(p.request.request_id == msg.request_id for p in self.pending):
            return  # our own service requests come back on the topic; a repeat is answered once
        self.pending.append(_Pending(msg, time.monotonic() + self.wait_s))
        self.pending_timer.reset()
        self._serve_pending()

    def on_service(self, request: RequestIslanding.Request, response: RequestIslanding.Response,
                   ) -> RequestIslanding.Response:
        """Publish a request on the topic (so the coherency node recomputes too) and queue it."""
        if self.snapshot is None or self.groups is None:
            response.accepted = False
            response.message = 'no network snapshot or coherent groups yet; nothing to decide on'
            self.diag.reject('no_data', f'service request: {response.message}')
            return response
        msg = IslandingRequest(request_id=str(uuid.uuid4()), reason=request.reason)
        msg.header.stamp = self.get_clock().now().to_msg()
        if stamp_s(msg.header.stamp) <= 0:
            msg.header.stamp.sec = max(1, int(self.groups.stamp_s))
        self.request_pub.publish(msg)
        self.on_request(msg)
        response.accepted, response.request_id, response.message = True, msg.request_id, 'queued'
        return response

    # --- deciding -----------------------------------------------------------------------------------------------
    def _grid_at(self, t_s: float) -> tuple[Grid, tuple[str, ...]]:
        assert self.snapshot is not None
        # Changes stamped at or before the snapshot are already in it.
        out = tuple(sorted(b for b, (stamp, in_service) in self.events.items()
                           if self.snapshot_stamp_s < stamp <= t_s and not in_service))
        return self.snapshot.with_outages(out), out

    def _decide(self, groups: Groups, t_s: float) -> tuple[Decision, float]:
        grid, out = self._grid_at(t_s)
        key = (groups.names, groups.labels, out)
        t0 = time.perf_counter()
        if key not in self.cache:
            self.cache[key] = decide(grid, groups.as_mapping())
        return self.cache[key], time.perf_counter() - t0

    def _warm_up(self, grid: Grid) -> None:
        # The first split pays one-off costs (library set-up, caches) of about 1.5 s here: pay them now, on a
        # trial split of the first generator from the rest, not on the first request.
        if len(grid.generators) < 2:
            return
        trial = {g.name: int(i == 0) for i, g in enumerate(grid.generators)}
        t0 = time.perf_counter()
        try:
            decide(grid, trial)
        except Exception as exc:  # a trial split may be infeasible; it only warms caches
            self.get_logger().info(f'warm-up split failed ({exc}); continuing')
        self.diag.values['warm_up_ms'] = f'{(time.perf_counter() - t0) * 1e3:.1f}'
        settle_heap()

    def _warm(self) -> None:
        if self.snapshot is None or self.groups is None or self.pending:
            return
        try:
            _, seconds = self._decide(self.groups, float('inf'))
        except Exception as exc:  # a failed warm-up is retried, and reported, when a request needs it
            self.get_logger().warning(f'precomputing the decision failed: {exc}')
            return
        self.diag.values['warm_compute_ms'] = f'{seconds * 1e3:.1f}'

    def _serve_pending(self) -> None:
        if not self.pending:
            self.pending_timer.cancel()
            return
        now = time.monotonic()
        for item in list(self.pending):
            req_s = stamp_s(item.request.header.stamp)
            fresh = self.groups is not None and self.groups.stamp_s >= req_s - self.tolerance_s
            if not fresh and now < item.deadline:
                continue
            self.pending.remove(item)
            self._answer(item.request, fresh)

    def _answer(self, request: IslandingRequest, fresh: bool) -> None:
        if self.snapshot is None or self.groups is None:
            self.diag.reject('no_data', f'request {request.request_id}: no network snapshot or coherent groups '
                                        f'within groups_wait_s={self.wait_s}')
            return
        if not fresh:
            self.get_logger().warning(f'request {request.request_id}: no groups newer than the request within '
                                      f'{self.wait_s} s; deciding on groups from {self.groups.stamp_s:.3f} s')
        t0 = time.perf_counter()
        try:
            decision, _ = self._decide(self.groups, stamp_s(request.header.stamp))
        except Exception as exc:  # the core's errors name the bad input; the node must keep running
            self.diag.reject('decision_failed', f'request {request.request_id}: {exc}')
            return
        msg = decision_to_msg(decision, request, self.groups.method, time.perf_counter() - t0)
        now = self.get_clock().now().to_msg()
        # A decision is never older than its request: under a replayed /clock this node's clock may lag.
        msg.header.stamp = max(now, request.header.stamp, key=lambda t: (t.sec, t.nanosec))
        self.decision_pub.publish(msg)
        self.answered.add(request.request_id)
        self.diag.computed(msg.compute_time_s)
        self.get_logger().info(f'request {request.request_id}: split={decision.split}, '
                               f'cut {list(msg.cut_branch_ids)}, {msg.compute_time_s * 1e3:.1f} ms')


def main(args: list[str] | None = None) -> int:
    """Run the partitioning node."""
    return spin_node(PartitioningNode, args)


if __name__ == '__main__':
    sys.exit(main())
