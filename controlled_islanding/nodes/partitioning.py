"""partitioning: on an islanding request, split the network for the coherent groups of the request's time.

Every request gets exactly one signed decision, and its `status` says what it is: SPLIT, NO_SPLIT, or why
there is no answer (REFUSED_STALE_GROUPS, REFUSED_NO_SNAPSHOT, REFUSED_TOPOLOGY_PENDING, REFUSED_FAILED);
never a silent "no split". A request that says how many branch status changes up to it the requester knows
of (`branch_changes_before`) waits until as many are applied: topics are not ordered against each other, so
a trip stamped just before the request can arrive after it.

Freshness is a precondition: a request stamped T is decided only on groups computed from samples ending at T
(stamped within `groups_tolerance_s` of T, on either side; the coherency node computes them on every request).
A grouping ending at T, or up to `groups_exact_s` after it, answers at once; one before T (say a frame period)
only when coherency computed it for this request (its `request_id`), over every sample up to T: at 30 frames/s
the grouping of the frame before a request at a frame's time split nothing where the request's own frame showed
the separation (at 60 frames/s too, the frame before within groups_exact_s: the monitor's request raised by its
own frame), and a periodic grouping can reach this node after the request while the request's own is still
being computed. The node waits at most `groups_wait_s` of wall time, then takes any grouping within
`groups_tolerance_s`, or refuses. The network is the newest snapshot
stamped at or before T with every branch status change stamped after it and at or before T
(`controlled_islanding.safety.topology`).
Every stamp from the wire is bounded by the node clock (`future_tolerance_s`), so no single message can become
"the newest" for good.

A signed request (the stability monitor's, or an operator's) must verify with the public key of a requester named
in `request_signers`, else it is refused at once (STATUS_REFUSED_UNAUTHENTIC_REQUEST, saying why): a forged or
altered request. An unsigned one is an operator's, the paper's mode, unless `require_signed_requests`.

To keep the request path short, decisions are cached by (groups, tripped branches): whenever new groups or a
topology change arrive, the decision for them is computed ahead of any request.
"""

from __future__ import annotations

import bisect
import sys
import time
import uuid
from collections import OrderedDict, deque
from pathlib import Path

from controlled_islanding_msgs.msg import BranchStatus, CoherentGroups, IslandingDecision, IslandingRequest
from controlled_islanding_msgs.msg import NetworkSnapshot as NetworkSnapshotMsg
from controlled_islanding_msgs.srv import RequestIslanding
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from controlled_islanding.core.final_grouping import STAMP_ROUNDING_S
from controlled_islanding.core.islanding import IslandingDecision as Decision
from controlled_islanding.core.islanding import decide, warm_up
from controlled_islanding.core.portfolio import PortfolioPartition
from controlled_islanding.core.spectral import ConstrainedSpectralPartition
from controlled_islanding.ros.clock_gate import ClockGate
from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.intake import SnapshotIntake
from controlled_islanding.ros.params import NodeSetupError, declare_bounded
from controlled_islanding.ros.pending import PendingRequests
from controlled_islanding.ros.sim_clock import SimClockWatch
from controlled_islanding.ros.spin import settle_heap, spin_node
from controlled_islanding.safety import signing
from controlled_islanding.safety.topology import Topology, TopologyError
from controlled_islanding.wire import topics
from controlled_islanding.wire.messages import (
    MAX_REQUEST_ID,
    Groups,
    MessageError,
    groups_from_msg,
    stamp_s,
)

_KEEP_GROUPS = 16
_KEEP_ANSWERED = 10_000
_KEEP_CACHED = 64
PARTITIONERS = {'spectral': ConstrainedSpectralPartition, 'portfolio': PortfolioPartition}


def decision_to_msg(decision: Decision, request: IslandingRequest, method: str, compute_time_s: float,
                    generator_bus: dict[str, int] | None = None, suspect: tuple[str, ...] = ()) -> IslandingDecision:
    """Encode a core decision as an (unsigned) IslandingDecision message answering a request.

    generator_bus (name -> bus) places the decision's unobserved generators; it must name each of them.
    """
    buses = sorted(decision.bus_island)
    unobserved = list(decision.unobserved_generators)
    return IslandingDecision(
        decision_id=str(uuid.uuid4()), request_id=request.request_id, request_stamp=request.header.stamp,
        method=method, split=decision.split,
        status=IslandingDecision.STATUS_SPLIT if decision.split else IslandingDecision.STATUS_NO_SPLIT,
        bus_numbers=buses, bus_island=[decision.bus_island[b] for b in buses],
        cut_branch_ids=[b.branch_id for b in decision.cut_branches],
        cut_from_bus=[b.from_bus for b in decision.cut_branches], cut_to_bus=[b.to_bus for b in decision.cut_branches],
        island_generation_mw=list(decision.island_generation_mw), island_load_mw=list(decision.island_load_mw),
        island_imbalance_mw=list(decision.island_imbalance_mw), island_shed_mw=list(decision.island_shed_mw),
        disrupted_mw=decision.disrupted_mw, compute_time_s=compute_time_s,
        unobserved_generator_names=unobserved,
        unobserved_generator_island=[decision.bus_island[(generator_bus or {})[n]] for n in unobserved],
        partitioner=decision.partitioner_summary, constraint_fallback=decision.constraint_fallback,
        suspect_generator_names=list(suspect), shed_bus=list(decision.remedial.shed_bus),
        shed_mw=list(decision.remedial.shed_mw), trip_generator_names=list(decision.remedial.trip_generators))


class PartitioningNode(Node):
    """Keeps the network and recent groups; answers every islanding request with one signed decision."""

    def __init__(self, **node_options) -> None:
        super().__init__('partitioning', **node_options)
        self.tolerance_s = float(declare_bounded(
            self, 'groups_tolerance_s', 0.05, 0.0, 10.0,
            "groups whose newest sample is within this of the request stamp are the request's groups, s", True))
        self.max_suspect_share = float(declare_bounded(
            self, 'max_suspect_share', 0.25, 0.0, 1.0,
            'largest share of the generators whose PMU data may be suspect (excluded by pmu_ingestion) for a '
            'decision; with more, the request is refused (STATUS_REFUSED_SUSPECT_DATA): a coordinated attack on '
            'that many stations leaves too little trusted evidence', True))
        self.declare_parameter('refuse_any_suspect', True)
        # Whether excluding a suspect machine changes k cannot be known from trusted data: its own data are the
        # doubt, and where it is the only evidence of a separation the others show none. So by default any
        # suspect in the window refuses; false decides with the suspects unconstrained (partial observability).
        self.refuse_any_suspect = bool(self.get_parameter('refuse_any_suspect').value)
        self.exact_s = float(declare_bounded(
            self, 'groups_exact_s', 0.02, 0.0, 10.0,
            "groups whose newest sample is at the request stamp or up to this after it answer it at once; others "
            "within groups_tolerance_s only when computed for the request (coherency's sample_tolerance_s), s",
            True))
        self.wait_s = float(declare_bounded(
            self, 'groups_wait_s', 0.5, 0.0, 60.0,
            "wait at most this long (wall) for the request's groups, then refuse as stale, s", True))
        self.future_tolerance_s = float(declare_bounded(
            self, 'future_tolerance_s', 1.0, 0.0, 60.0, 'refuse stamps further than this ahead of the node clock, s',
            True))
        self.max_pending = int(declare_bounded(
            self, 'max_pending_requests', 100, 1, 100000, 'requests waiting for groups at once; more are refused',
            True))
        self.declare_parameter('groups_method', 'dtw', ParameterDescriptor(
            description='only groups of this coherency method are used', read_only=True))
        self.declare_parameter('key_dir', '', ParameterDescriptor(
            description='directory with partitioning.key, the decision signing key; empty = '
                        '$CONTROLLED_ISLANDING_KEYS or ~/.config/controlled_islanding/keys', read_only=True))
        self.declare_parameter('partitioner', 'portfolio', ParameterDescriptor(
            description="how buses are given to islands: 'spectral' (the paper's eqs. 4-8, refined) or 'portfolio' "
                        '(that and the exact minimum cut within a fixed budget, the lower eq. 9 kept; '
                        'core/portfolio.py)', read_only=True))
        self.method = str(self.get_parameter('groups_method').value)
        self.partitioner = str(self.get_parameter('partitioner').value)
        if self.partitioner not in PARTITIONERS:
            raise NodeSetupError(f'partitioner must be one of {sorted(PARTITIONERS)}, got {self.partitioner!r}')
        self.declare_parameter('request_signers', ['monitor', 'operator'], ParameterDescriptor(
            description='roles whose public keys (<role>.pub in key_dir) verify a signed islanding request',
            read_only=True))
        self.declare_parameter('require_signed_requests', False, ParameterDescriptor(
            description="refuse unsigned islanding requests too (false: an unsigned request is an operator's, the "
                        "paper's mode)", read_only=True))
        self.require_signed = bool(self.get_parameter('require_signed_requests').value)
        key_dir = self.get_parameter('key_dir').value
        key_dir = Path(key_dir) if key_dir else signing.default_key_dir()
        key_path = signing.key_paths(key_dir, 'partitioning').private
        try:
            self.key = signing.load_private_key(key_path)
            self.request_keys = {}
            for role in self.get_parameter('request_signers').value:
                public = signing.load_public_key(signing.key_paths(key_dir, str(role)).public)
                self.request_keys[signing.fingerprint(public)] = public
        except signing.SigningError as exc:
            raise NodeSetupError(f'{exc} (make keys with: controlled-islanding keys init {key_dir})') from exc
        self.key_id = signing.fingerprint(self.key)
        self.topology = Topology(future_tolerance_s=self.future_tolerance_s)
        self.groups: list[Groups] = []  # recent groups, ordered by stamp
        self.cache: OrderedDict[tuple, Decision] = OrderedDict()
        self.answered: deque[str] = deque(maxlen=_KEEP_ANSWERED)
        self.answered_set: set[str] = set()
        self.diag = Diagnostics(self)
        self.intake = SnapshotIntake(self, self.diag)
        self.diag.values['partitioner'] = self.partitioner
        self.clock = SimClockWatch(self, self.diag)
        self.inputs = ClockGate(self, self.diag, self.future_tolerance_s, 1000, self._apply_input, clock=self.clock)
        self.decision_pub = self.create_publisher(IslandingDecision, topics.relative(topics.ISLANDING_DECISION),
                                                  qos_for(topics.ISLANDING_DECISION))
        self.request_pub = self.create_publisher(IslandingRequest, topics.relative(topics.ISLANDING_REQUEST),
                                                 qos_for(topics.ISLANDING_REQUEST))
        self.diag.subscribe(NetworkSnapshotMsg, topics.NETWORK_SNAPSHOT, self.on_snapshot)
        self.diag.subscribe(BranchStatus, topics.BRANCH_STATUS, self.on_branch_status)
        self.diag.subscribe(CoherentGroups, topics.COHERENT_GROUPS, self.on_groups)
        self.diag.subscribe(IslandingRequest, topics.ISLANDING_REQUEST, self.on_request)
        guard = self.diag.guard
        self.create_service(RequestIslanding, '~/request', guard(self.on_service))
        self.pending = PendingRequests(self, guard, self.wait_s, self._ready, self._serve)
        t0 = time.perf_counter()
        try:
            # before spinning: within the supervisor's start-up grace, not in a callback
            warm_up(PARTITIONERS[self.partitioner]())
        except Exception as exc:  # noqa: BLE001  only loads the engine; a real request reports its own failure
            self.get_logger().warning(f'engine warm-up failed ({exc}); the first decision will pay the loading')
        self.diag.values['warm_up_ms'] = f'{(time.perf_counter() - t0) * 1e3:.1f}'
        self.get_logger().info(f'signing decisions with key {self.key_id}')

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    # --- inputs -------------------------------------------------------------------------------------------------
    def _apply_input(self, item: tuple) -> None:
        try:
            self._apply(item)
        except TopologyError as exc:
            self.diag.reject(exc.reason, str(exc))

    def _apply(self, item: tuple) -> None:
        kind = item[0]
        if kind == 'snapshot':
            _, grid, stamp = item
            self.topology.offer_snapshot(grid, stamp, self._now_s())
            self.cache.clear()
            self.diag.values['buses'] = str(len(grid.buses))
            settle_heap()
            self._warm()
        elif kind == 'status':
            _, branch_id, in_service, stamp = item
            self.topology.offer_status(branch_id, in_service, stamp, self._now_s())
            self._warm()
        elif kind == 'groups':
            self._take_groups(item[1])
        elif kind == 'request':
            self._queue(item[1])

    def on_snapshot(self, msg: NetworkSnapshotMsg) -> None:
        """Take a new network snapshot."""
        grid = self.intake.grid(msg)
        if grid is None:
            return
        stamp = stamp_s(msg.header.stamp)
        self.inputs.admit('network snapshot', stamp, ('snapshot', grid, stamp), msg)

    def on_branch_status(self, msg: BranchStatus) -> None:
        """Record a branch status change."""
        stamp = stamp_s(msg.header.stamp)
        item = ('status', str(msg.branch_id), bool(msg.in_service), stamp)
        self.inputs.admit(f'branch {msg.branch_id[:64]} status', stamp, item)

    def on_groups(self, msg: CoherentGroups) -> None:
        """Take new coherent groups; compute their decision ahead of a request."""
        try:
            groups = groups_from_msg(msg, self.intake.limits)
        except MessageError as exc:
            self.diag.reject(exc.reason, f'coherent groups: {exc}')
            return
        if self.method and groups.method != self.method:
            self.diag.reject('unknown_id', f'groups of method {groups.method!r}; this node uses {self.method!r}')
            return
        self.inputs.admit('coherent groups', groups.stamp_s, ('groups', groups), msg)

    def _take_groups(self, groups: Groups) -> None:
        snapshot = self.topology.snapshot
        if snapshot is not None:
            unknown = sorted((set(groups.names) | set(groups.unobserved)) ^ {g.name for g in snapshot.generators})
            if unknown:
                self.diag.reject('unknown_id', f'groups and network disagree on generators {unknown[:10]}')
                return
        # Several recent groupings are kept, each for the requests of its own time: a grouping stamped ahead
        # (within the tolerance) never hides the honest one a request needs.
        stamps = [g.stamp_s for g in self.groups]
        i = bisect.bisect_left(stamps, groups.stamp_s)
        if i < len(stamps) and stamps[i] == groups.stamp_s:
            if groups.request_id or not self.groups[i].request_id:  # a periodic repeat keeps the request's answer
                self.groups[i] = groups
        else:
            self.groups.insert(i, groups)
        del self.groups[:-_KEEP_GROUPS]
        self.diag.values['k'] = str(groups.k)
        self.pending.serve()
        self._warm()

    def on_request(self, msg: IslandingRequest) -> None:
        """Queue a request until its groups arrive (or the wait ends)."""
        if not 0 < len(msg.request_id) <= MAX_REQUEST_ID:
            self.diag.reject('empty_message', f'islanding request without request_id (or longer than {MAX_REQUEST_ID} '
                                              'characters)')
            return
        if stamp_s(msg.header.stamp) <= 0:
            self.diag.reject('missing_stamp', f'request {msg.request_id}: header.stamp is zero')
            return
        self.inputs.admit(f'request {msg.request_id}', stamp_s(msg.header.stamp), ('request', msg), msg)

    def _queue(self, msg: IslandingRequest) -> None:
        if msg.request_id in self.answered_set or any(p.request_id == msg.request_id for p in self.pending):
            return  # our own service requests come back on the topic; a repeat is answered once
        if signing.check_request(msg, self.request_keys, self.require_signed) is not None:
            self._answer(msg, None)  # refused at once: no groups make a forged request authentic
            return
        if len(self.pending) >= self.max_pending:
            self.diag.reject('overloaded', f'request {msg.request_id}: {len(self.pending)} requests already wait '
                                           f'(max_pending_requests)')
            return
        self.pending.add(msg)

    def on_service(self, request: RequestIslanding.Request, response: RequestIslanding.Response,
                   ) -> RequestIslanding.Response:
        """Publish a request stamped now on the topic (so the coherency node recomputes too) and queue it."""
        msg = IslandingRequest(request_id=str(uuid.uuid4()), reason=request.reason[:500])
        msg.header.stamp = self.get_clock().now().to_msg()
        if stamp_s(msg.header.stamp) <= 0:
            response.accepted = False
            response.message = 'this node clock has not started (no /clock yet); nothing to stamp a request with'
            self.diag.reject('no_clock', f'service request: {response.message}')
            return response
        why = self.clock.inconsistency()
        if why is not None:
            response.accepted = False
            response.message = f'this node clock cannot be trusted to stamp a request with: {why}'
            self.diag.reject('clock_inconsistent', f'service request: {response.message}')
            return response
        self.request_pub.publish(msg)
        self._queue(msg)
        response.accepted, response.request_id, response.message = True, msg.request_id, 'queued'
        return response

    # --- deciding -----------------------------------------------------------------------------------------------
    def _groups_for(self, t_s: float, request_id: str | None = None) -> Groups | None:
        """Return the groups whose samples end at t_s (stamped within groups_tolerance_s of it), if any.

        The earliest such grouping is taken, and never one ending more than the tolerance after t_s: a grouping
        stamped further ahead could otherwise be served before the honest one arrives. The tolerance is two-sided
        because coherency answers a request with groups it already holds when they end within its own
        sample_tolerance_s of the stamp, which can be just after it. With `request_id` (before the wait ends), a
        grouping ending before t_s (beyond the stamps' rounding) counts only if coherency computed it for that
        request, and one further than groups_exact_s after t_s not at all: a grouping stamped ahead that arrives
        first must not win over the honest one held. A periodic grouping of the frame before, 16.7 ms at 60
        frames/s and so within groups_exact_s, was computed before that frame's prediction: the monitor's request
        at 5.617 s on IEEE 39 G6-G7 was decided on the groups of 5.600 s, before the alarm, and nothing was split.
        """
        return next((g for g in self.groups if abs(g.stamp_s - t_s) <= self.tolerance_s and (
            request_id is None or (g.stamp_s - t_s <= self.exact_s and (
                t_s - g.stamp_s <= STAMP_ROUNDING_S or g.request_id == request_id)))), None)

    def _decide(self, groups: Groups, t_s: float) -> tuple[Decision, float]:
        grid, out = self.topology.grid_at(t_s)
        key = (groups.names, groups.labels, groups.unobserved, out)
        t0 = time.perf_counter()
        if key not in self.cache:
            self.cache[key] = decide(grid, groups.as_mapping(), PARTITIONERS[self.partitioner](),
                                     unobserved=groups.unobserved)
            while len(self.cache) > _KEEP_CACHED:
                self.cache.popitem(last=False)
        return self.cache[key], time.perf_counter() - t0

    def _warm(self) -> None:
        if self.topology.snapshot is None or not self.groups or self.pending:
            return
        try:
            _, seconds = self._decide(self.groups[-1], float('inf'))
        except Exception as exc:  # a failed warm-up is retried, and reported, when a request needs it
            self.get_logger().warning(f'precomputing the decision failed: {exc}')
            return
        self.diag.values['warm_compute_ms'] = f'{seconds * 1e3:.1f}'

    def _ready(self, request: IslandingRequest) -> bool:
        groups = self._groups_for(stamp_s(request.header.stamp), request.request_id)
        return groups is not None and not self._topology_pending(request)

    def _serve(self, request: IslandingRequest) -> None:
        t_s = stamp_s(request.header.stamp)
        self._answer(request, self._groups_for(t_s, request.request_id) or self._groups_for(t_s))

    def _topology_pending(self, request: IslandingRequest) -> bool:
        """Whether fewer branch changes up to the request are applied than the requester knows of.

        Topics are not ordered against each other: a trip stamped just before a request can arrive after it.
        """
        if self.topology.snapshot is None:
            return False
        return self.topology.changes_known(stamp_s(request.header.stamp)) < int(request.branch_changes_before)

    def _too_suspect(self, groups: Groups) -> bool:
        total = len(groups.names) + len(groups.unobserved)
        many = len(groups.suspect) > self.max_suspect_share * total
        return bool(groups.suspect) and (self.refuse_any_suspect or many)

    def _refusal(self, request: IslandingRequest, status: int, detail: str) -> IslandingDecision:
        self.diag.fault('last_request', f'request {request.request_id}: {detail}')
        self.diag.reject('refused', f'request {request.request_id}: {detail}')
        return IslandingDecision(decision_id=str(uuid.uuid4()), request_id=request.request_id,
                                 request_stamp=request.header.stamp, method=self.method, status=status,
                                 status_detail=detail, split=False)

    def _answer(self, request: IslandingRequest, groups: Groups | None) -> None:
        t0 = time.perf_counter()
        req_s = stamp_s(request.header.stamp)
        unauthentic = signing.check_request(request, self.request_keys, self.require_signed)
        if unauthentic is not None:
            msg = self._refusal(request, IslandingDecision.STATUS_REFUSED_UNAUTHENTIC_REQUEST, unauthentic)
        elif self.topology.snapshot is None:
            msg = self._refusal(request, IslandingDecision.STATUS_REFUSED_NO_SNAPSHOT, 'no network snapshot')
        elif self._topology_pending(request):
            msg = self._refusal(request, IslandingDecision.STATUS_REFUSED_TOPOLOGY_PENDING,
                                f'{self.topology.changes_known(req_s)} branch status changes stamped up to the '
                                f'request applied, the requester knows of {request.branch_changes_before}, after '
                                f'groups_wait_s={self.wait_s}')
        elif groups is not None and self._too_suspect(groups):
            names = ', '.join(f'{g} ({why})' for g, why in groups.suspect)
            msg = self._refusal(request, IslandingDecision.STATUS_REFUSED_SUSPECT_DATA,
                                f'{len(groups.suspect)} of {len(groups.names) + len(groups.unobserved)} generators '
                                f'have suspect PMU data (refuse_any_suspect={self.refuse_any_suspect}, '
                                f'max_suspect_share={self.max_suspect_share:g}): {names}'[:500])
            msg.suspect_generator_names = [g for g, _ in groups.suspect]
        elif groups is None:
            held = ', '.join(f'{g.stamp_s:.3f}' for g in self.groups[-3:]) or 'none'
            msg = self._refusal(request, IslandingDecision.STATUS_REFUSED_STALE_GROUPS,
                                f'no coherent groups from samples reaching the request stamp {req_s:.3f} s '
                                f'(groups_tolerance_s={self.tolerance_s}) within groups_wait_s={self.wait_s} '
                                f'(newest held: {held})')
        else:
            try:
                decision, _ = self._decide(groups, req_s)
                if decision.constraint_fallback:
                    self.get_logger().warning(f'request {request.request_id}: {decision.constraint_fallback}; '
                                              'split with group-balanced constraint weights')
                if decision.partitioner_summary:
                    self.get_logger().info(f'request {request.request_id}: {decision.partitioner_summary}')
                    self.diag.values['last_partition'] = decision.partitioner_summary[:200]
                grid = self.topology.snapshot_at(req_s)[1]
                msg = decision_to_msg(decision, request, groups.method, time.perf_counter() - t0,
                                      {g.name: g.bus for g in grid.generators}, tuple(g for g, _ in groups.suspect))
                self.diag.fault('last_request', None)
            except Exception as exc:  # the core's errors name the bad input; the node must keep running
                msg = self._refusal(request, IslandingDecision.STATUS_REFUSED_FAILED, f'split failed: {exc}'[:500])
        msg.compute_time_s = time.perf_counter() - t0
        now = self.get_clock().now()
        msg.header.stamp = now.to_msg() if now.nanoseconds > 0 else request.header.stamp
        msg.key_id = self.key_id
        msg.signature = signing.sign(self.key, signing.decision_payload(msg))
        self.decision_pub.publish(msg)
        if len(self.answered) == self.answered.maxlen:
            self.answered_set.discard(self.answered[0])
        self.answered.append(request.request_id)
        self.answered_set.add(request.request_id)
        self.diag.computed(msg.compute_time_s)
        self.get_logger().info(f'request {request.request_id}: status {msg.status}, cut {list(msg.cut_branch_ids)}, '
                               f'{msg.compute_time_s * 1e3:.1f} ms')


def main(args: list[str] | None = None) -> int:
    """Run the partitioning node."""
    return spin_node(PartitioningNode, args)


if __name__ == '__main__':
    sys.exit(main())
