"""breaker_command: the only part of the graph that acts on the grid. Signed decisions in, breaker commands out.

It follows the remedial-action-scheme yardstick: no misoperation, and no single failure causes one. The rules,
in the order they are checked, are listed in docs/nodes.md ("Breaker rules"), each with the test that proves
it. In short: a decision is executed only if it is signed by the decision key, new (never handled before,
even before a restart: the audit log is read back at start-up), answers a request that is fresh on this
node's clock, the node is armed by a signed operator request, and its cut is exactly the set of in-service
branches between its islands in the network this node holds, within `max_breakers`, with generation in
every island; and its remedial actions (load to shed per bus, machines to trip) name loads and machines of that
network, within what is left of each bus's load and of machines not tripped before, within `max_actions`. Then
every breaker and every action is commanded once, after one fsync'ed audit record that lists them all.
If the audit log cannot be read or written, nothing is commanded and diagnostics say ERROR.

Arming is a state visible to standard ROS tools as the read-only parameter `armed`. A lifecycle node was
the alternative (active = armed), but its change_state service is unauthenticated: anyone on the domain
could arm through it. So arming stays a signed service and the node always starts disarmed.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import yaml
from controlled_islanding_msgs.msg import BranchStatus, BreakerCommand, IslandingDecision
from controlled_islanding_msgs.msg import NetworkSnapshot as NetworkSnapshotMsg
from controlled_islanding_msgs.srv import SetArmed
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter

from controlled_islanding.locations import config_dir
from controlled_islanding.ros.clock_gate import ClockGate
from controlled_islanding.ros.diagnostics import DECISIONS_HANDLED, Diagnostics
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.intake import SnapshotIntake
from controlled_islanding.ros.params import NodeSetupError
from controlled_islanding.ros.sim_clock import SimClockWatch
from controlled_islanding.ros.spin import spin_node
from controlled_islanding.safety import signing
from controlled_islanding.safety.actuation import Refusal, plan_actions, plan_commands
from controlled_islanding.safety.audit import AuditError, AuditLog
from controlled_islanding.safety.topology import Topology, TopologyError
from controlled_islanding.wire import topics
from controlled_islanding.wire.messages import stamp_s
from controlled_islanding.wire.qos import DECISION_LEASE_S
from controlled_islanding.wire.timebounds import ClockJump

_MAX_ID_CHARS = 128
_ACTIONS = {'open': BreakerCommand.ACTION_OPEN, 'shed': BreakerCommand.ACTION_SHED_LOAD,
            'trip': BreakerCommand.ACTION_TRIP_GENERATOR}
_NOT_DECIDED = {
    IslandingDecision.STATUS_REFUSED_STALE_GROUPS: 'stale groups',
    IslandingDecision.STATUS_REFUSED_NO_SNAPSHOT: 'no snapshot',
    IslandingDecision.STATUS_REFUSED_TOPOLOGY_PENDING: 'topology pending',
    IslandingDecision.STATUS_REFUSED_FAILED: 'failed',
    IslandingDecision.STATUS_REFUSED_SUSPECT_DATA: 'suspect data',
    IslandingDecision.STATUS_REFUSED_UNAUTHENTIC_REQUEST: 'unauthentic request',
}


def load_breaker_map(path: str | Path) -> dict[str, str]:
    """Read an optional override file: a YAML mapping `breakers: {branch_id: breaker_id}`.

    Raises:
        NodeSetupError: The file is missing, not YAML, or not a mapping of strings.

    """
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise NodeSetupError(f'breakers_file {path}: {exc}') from exc
    table = data.get('breakers') if isinstance(data, dict) else None
    if not isinstance(table, dict) or not table:
        raise NodeSetupError(f'breakers_file {path}: expected a non-empty mapping under "breakers:"')
    return {str(k): str(v) for k, v in table.items()}


def _check_signature(role: str, key: object, key_id: str, claimed_key_id: str, payload: Callable[[], bytes],
                     signature: object) -> None:
    """Refuse a message not signed by the `role` key: 'unsigned', 'unknown_key' or 'bad_signature'."""
    if not len(signature):
        raise Refusal('unsigned', f'no signature; only messages signed by the {role} key are acted on')
    if claimed_key_id != key_id:
        raise Refusal('unknown_key', f'signed by key {claimed_key_id[:32]!r}, not the {role} key {key_id}')
    try:
        signing.verify(key, payload(), signature)
    except signing.SigningError as exc:
        raise Refusal(exc.reason, str(exc)) from exc


def _descriptor(text: str, low: float | None = None, high: float | None = None, integer: bool = False,
                ) -> ParameterDescriptor:
    # Every parameter is read-only: anyone on the domain can call the standard SetParameters service, and
    # none of these may be loosened at run time.
    desc = ParameterDescriptor(description=text, read_only=True)
    if low is not None and integer:
        desc.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=1)]
    elif low is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
    return desc


class BreakerCommandNode(Node):
    """Executes signed islanding decisions as breaker commands, at most once each, only while armed."""

    def __init__(self, **node_options) -> None:
        super().__init__('breaker_command', **node_options)
        self._armed_descriptor = _descriptor('true while armed; read-only: arm and disarm through the signed '
                                             '~/set_armed service. The node always starts disarmed.')
        self.declare_parameter('armed', False, self._armed_descriptor, ignore_override=True)
        self.declare_parameter('breakers_file', '', _descriptor(
            'optional YAML {breakers: {branch_id: breaker_id}} overriding the snapshot breaker ids; a relative '
            'path is relative to config/'))
        self.declare_parameter('audit_log', 'breaker_audit.jsonl', _descriptor(
            'append-only JSON lines, fsync per record; read back at start-up so a restart never repeats a command'))
        self.declare_parameter('key_dir', '', _descriptor(
            'directory with partitioning.pub (decisions) and operator.pub (arm/disarm); empty = '
            '$CONTROLLED_ISLANDING_KEYS or ~/.config/controlled_islanding/keys'))
        self.declare_parameter('max_decision_age_s', 1.0, _descriptor(
            'refuse a decision whose request is older than this on the node clock, s', 0.001, 3600.0))
        self.declare_parameter('future_tolerance_s', 1.0, _descriptor(
            'refuse stamps further than this ahead of the node clock, s', 0.0, 60.0))
        self.declare_parameter('max_arm_request_age_s', 30.0, _descriptor(
            'refuse an arm/disarm request signed longer ago than this on the wall clock, s', 0.1, 3600.0))
        self.declare_parameter('max_breakers', 20, _descriptor(
            'the most breakers one decision may open', 1, 100000, integer=True))
        self.declare_parameter('max_actions', 80, _descriptor(
            'the most remedial actions (load sheds and generator trips) one decision may take; with max_breakers '
            '(20) within the 100 commands /breaker/commands keeps, so no decision overflows it', 0, 100000,
            integer=True))
        self.declare_parameter('max_remembered_decisions', 100000, _descriptor(
            'decision ids kept in memory; beyond, ids too old to pass the age rule are forgotten', 100, 10**7,
            integer=True))
        p = {name: self.get_parameter(name).value for name in (
            'breakers_file', 'audit_log', 'key_dir', 'max_decision_age_s', 'future_tolerance_s',
            'max_arm_request_age_s', 'max_breakers', 'max_actions', 'max_remembered_decisions')}
        self.max_age_s = float(p['max_decision_age_s'])
        self.future_tolerance_s = float(p['future_tolerance_s'])
        self.max_arm_age_s = float(p['max_arm_request_age_s'])
        self.max_breakers = int(p['max_breakers'])
        self.max_actions = int(p['max_actions'])
        self.max_remembered = int(p['max_remembered_decisions'])
        self.override: dict[str, str] = {}
        if p['breakers_file']:
            path = Path(p['breakers_file'])
            self.override = load_breaker_map(path if path.is_absolute() else config_dir() / path)
        key_dir = Path(p['key_dir']) if p['key_dir'] else signing.default_key_dir()
        try:
            self.decision_key = signing.load_public_key(signing.key_paths(key_dir, 'partitioning').public)
            self.operator_key = signing.load_public_key(signing.key_paths(key_dir, 'operator').public)
        except signing.SigningError as exc:
            raise NodeSetupError(f'{exc} (make keys with: controlled-islanding keys init {key_dir})') from exc
        self.decision_key_id = signing.fingerprint(self.decision_key)
        self.operator_key_id = signing.fingerprint(self.operator_key)

        self.armed = False
        self.diag = Diagnostics(self)
        self.intake = SnapshotIntake(self, self.diag)
        self.limits = self.intake.limits
        self.diag.values['armed'] = 'false'
        self.audit: AuditLog | None = None
        try:
            self.audit = AuditLog(p['audit_log'])
        except AuditError as exc:
            self.diag.fault('audit', f'{exc}; nothing will be commanded')
        self.topology = Topology(future_tolerance_s=self.future_tolerance_s)
        self.clock = SimClockWatch(self, self.diag, self._on_clock_jump)
        self.inputs = ClockGate(self, self.diag, self.future_tolerance_s, 200, self._apply_input, clock=self.clock)
        self.pub = self.create_publisher(BreakerCommand, topics.relative(topics.BREAKER_COMMANDS),
                                         qos_for(topics.BREAKER_COMMANDS))
        self.decision_writers_alive = 0
        self.diag.values['decision_writers_alive'] = '0'
        self.diag.subscribe(IslandingDecision, topics.ISLANDING_DECISION, self.on_decision,
                            event_callbacks=SubscriptionEventCallbacks(
                                liveliness=self.diag.guard(self.on_decision_liveliness)),
                            handled_key=DECISIONS_HANDLED, with_info=True)
        self.diag.subscribe(NetworkSnapshotMsg, topics.NETWORK_SNAPSHOT, self.on_snapshot)
        self.diag.subscribe(BranchStatus, topics.BRANCH_STATUS, self.on_branch_status)
        self.create_service(SetArmed, '~/set_armed', self.diag.guard(self.on_set_armed))
        if self.audit is not None:
            state = self.audit.state
            self._record('start', records_read=state.records, decisions_known=len(state.decisions),
                         breakers_commanded=len(state.commanded), repaired_tail=state.repaired_tail)
        self.get_logger().info(f'disarmed; audit {p["audit_log"]}; decision key {self.decision_key_id}, '
                               f'operator key {self.operator_key_id}; {len(self.override)} breaker overrides')

    # --- time and records ---------------------------------------------------------------------------------------
    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _record(self, event: str, **fields: object) -> bool:
        """Append an audit record; on failure raise the audit fault and return False (nothing may be commanded)."""
        if self.audit is None:
            return False
        record = {'event': event, 'wall_time_s': time.time(), 'ros_time_s': self._now_s(), **fields}
        try:
            self.audit.append(record)
        except AuditError as exc:
            self.audit.close()
            self.audit = None
            self.diag.fault('audit', f'{exc}; nothing will be commanded until the log is fixed and the node '
                                     f'restarted')
            return False
        return True

    def _on_clock_jump(self, jump: ClockJump, jumps: int) -> None:
        self._record('clock_jump', kind=jump.kind, trusted_s=jump.trusted_s, read_s=jump.read_s,
                     allowed_s=jump.allowed_s, jumps=jumps, detail=jump.describe())

    def _refuse(self, reason: str, detail: str, **fields: object) -> None:
        self._record('refusal', reason=reason, detail=detail, **fields)
        self.diag.reject(reason, detail)

    # --- network ------------------------------------------------------------------------------------------------
    def on_snapshot(self, msg: NetworkSnapshotMsg) -> None:
        """Hold the network the decisions are checked against."""
        grid = self.intake.grid(msg)
        if grid is None:
            return
        stamp = stamp_s(msg.header.stamp)
        self.inputs.admit('network snapshot', stamp, ('snapshot', grid, stamp), msg)

    def on_branch_status(self, msg: BranchStatus) -> None:
        """Follow trips and reclosures."""
        item = ('status', str(msg.branch_id), bool(msg.in_service), stamp_s(msg.header.stamp))
        self.inputs.admit(f'branch {msg.branch_id[:64]} status', item[3], item)

    def _apply_input(self, item: tuple) -> None:
        try:
            self._apply(item)
        except TopologyError as exc:
            self.diag.reject(exc.reason, str(exc))

    def _apply(self, item: tuple) -> None:
        if item[0] == 'snapshot':
            self.topology.offer_snapshot(item[1], item[2], self._now_s())
            self.diag.values['buses'] = str(len(item[1].buses))
            return
        _, branch_id, in_service, stamp = item
        self.topology.offer_status(branch_id, in_service, stamp, self._now_s())
        snapshot = self.topology.snapshot
        if not in_service or self.audit is None or snapshot is None:
            return
        branch = next((b for b in snapshot.branches if b.branch_id == branch_id), None)
        if branch is not None:
            breaker = self.override.get(branch_id) or branch.breaker
            opened = self.audit.state.commanded.get(breaker)
            if opened is not None and stamp > opened[1]:
                # Audited, so a restarted node knows the breaker may be opened again.
                self._record('reclosed', breaker_id=breaker, branch_id=branch_id, stamp_s=stamp)

    def _open_breakers(self) -> set[str]:
        assert self.audit is not None
        return set(self.audit.state.commanded)

    # --- arming -------------------------------------------------------------------------------------------------
    def _set_armed(self, armed: bool) -> None:
        self.armed = armed
        self.diag.values['armed'] = str(armed).lower()
        # Read-only for everyone else; the node itself updates it with the descriptor it declared (rclpy skips
        # the read-only check only when the descriptor is given, which is what this private call does).
        self._set_parameters_atomically_common([Parameter('armed', Parameter.Type.BOOL, armed)],
                                               descriptors={'armed': self._armed_descriptor})

    def _check_arm(self, request: SetArmed.Request) -> str:
        if request.action not in (SetArmed.Request.ACTION_ARM, SetArmed.Request.ACTION_DISARM):
            raise Refusal('unset_action', f'action={request.action}: neither ACTION_ARM (1) nor ACTION_DISARM (2)')
        _check_signature('operator', self.operator_key, self.operator_key_id, request.key_id,
                         lambda: signing.arm_payload(request, self.get_fully_qualified_name()), request.signature)
        now_s, stamp = time.time(), stamp_s(request.stamp)
        if not 0 < len(request.nonce) <= _MAX_ID_CHARS:
            raise Refusal('bad_value', f'nonce must have 1 to {_MAX_ID_CHARS} characters')
        if stamp > now_s + self.future_tolerance_s:
            raise Refusal('future_stamp', f'arm request stamped {stamp - now_s:.3f} s ahead of the wall clock')
        if now_s - stamp > self.max_arm_age_s:
            raise Refusal('stale', f'arm request signed {now_s - stamp:.3f} s ago, more than '
                                   f'max_arm_request_age_s={self.max_arm_age_s}')
        nonces = self.audit.state.nonces if self.audit is not None else {}
        if request.nonce in nonces:
            raise Refusal('replay', f'nonce {request.nonce!r} was used before')
        for old in [n for n, s in nonces.items() if now_s - s > self.max_arm_age_s + self.future_tolerance_s]:
            del nonces[old]  # they can never pass the age rule again
        return 'armed' if request.action == SetArmed.Request.ACTION_ARM else 'disarmed'

    def on_set_armed(self, request: SetArmed.Request, response: SetArmed.Response) -> SetArmed.Response:
        """Arm or disarm on a signed operator request; disarm takes effect even when the audit log is broken."""
        try:
            event = self._check_arm(request)
        except Refusal as exc:
            self._refuse(exc.reason, f'arm/disarm request: {exc}', nonce=request.nonce[:_MAX_ID_CHARS])
            response.accepted, response.armed, response.message = False, self.armed, f'refused ({exc.reason}): {exc}'
            return response
        if event == 'disarmed':
            self._set_armed(False)  # before the record: a broken log must never keep the node armed
            self._record(event, nonce=request.nonce, stamp_s=stamp_s(request.stamp), key_id=request.key_id)
            response.accepted, response.armed, response.message = True, False, 'disarmed: nothing is commanded'
        elif self._record(event, nonce=request.nonce, stamp_s=stamp_s(request.stamp), key_id=request.key_id):
            self._set_armed(True)
            response.accepted, response.armed, response.message = True, True, 'armed: valid decisions are executed'
        else:
            self.diag.reject('audit_unavailable', 'arm request: the audit log cannot be written')
            response.accepted, response.armed = False, False
            response.message = f'refused (audit_unavailable): {self.diag.faults.get("audit", "no audit log")}'
        self.get_logger().info(response.message)
        return response

    # --- decisions ----------------------------------------------------------------------------------------------
    def _authenticate(self, msg: IslandingDecision) -> None:
        snapshot = self.topology.snapshot
        max_entries = 2 * len(snapshot.branches) if snapshot is not None else self.limits.max_branches
        if (len(msg.bus_numbers) > self.limits.max_buses or len(msg.cut_branch_ids) > max_entries
                or max(len(msg.shed_bus), len(msg.shed_mw)) > self.limits.max_buses
                or len(msg.trip_generator_names) > self.limits.max_generators):
            raise Refusal('too_large', f'{len(msg.bus_numbers)} buses, {len(msg.cut_branch_ids)} cut entries, '
                                       f'{len(msg.shed_bus)} sheds and {len(msg.trip_generator_names)} trips')
        _check_signature('decision', self.decision_key, self.decision_key_id, msg.key_id,
                         lambda: signing.decision_payload(msg), msg.signature)
        if not 0 < len(msg.decision_id) <= _MAX_ID_CHARS:
            raise Refusal('bad_value', f'decision_id must have 1 to {_MAX_ID_CHARS} characters')

    def _check(self, msg: IslandingDecision, request_s: float) -> None:
        if msg.status not in _NOT_DECIDED and msg.status not in (IslandingDecision.STATUS_SPLIT,
                                                                  IslandingDecision.STATUS_NO_SPLIT):
            raise Refusal('unset_status', f'status={msg.status} is not a decision status')
        if msg.split != (msg.status == IslandingDecision.STATUS_SPLIT):
            raise Refusal('inconsistent_status', f'split={msg.split} but status={msg.status}')
        if not msg.split and (len(msg.shed_bus) or len(msg.shed_mw) or len(msg.trip_generator_names)):
            raise Refusal('inconsistent_status', f'status={msg.status} carries remedial actions; only a split does')
        now_s = self._now_s()
        if request_s <= 0:
            raise Refusal('missing_stamp', 'request_stamp is zero')
        if now_s <= 0:
            raise Refusal('no_clock', 'this node clock has not started (no /clock yet)')
        if request_s - now_s > self.future_tolerance_s:
            raise Refusal('future_stamp', f'request stamped {request_s - now_s:.3f} s ahead of this node clock')
        if now_s - request_s > self.max_age_s:
            raise Refusal('stale', f'request made {now_s - request_s:.3f} s ago, more than '
                                   f'max_decision_age_s={self.max_age_s}')

    def _check_wait(self, info: dict | None) -> None:
        """Refuse a decision that waited longer than max_decision_age_s (wall) between publication and this check.

        The node clock can be behind the grid: a process resumed after a stall (SIGSTOP, a swapped-out host) under
        sim time takes its queued /clock values and its queued decision in no set order, and judged one on the
        /clock of before the stall (a chaos run: 0.72 s after the request by this clock, 2.5 s by the grid's, and
        14 commands reached the grid late). The wait is on the wall clock, from the publisher's DDS source
        timestamp (deployment.md: wall clocks in sync); a forged one can only refuse, which any rule may.
        """
        source_ns = (info or {}).get('source_timestamp')
        if not source_ns:
            return
        waited_s = time.time() - float(source_ns) * 1e-9
        if waited_s > self.max_age_s:
            raise Refusal('stale', f'published {waited_s:.3f} s ago (wall clock) and judged only now, more than '
                                   f'max_decision_age_s={self.max_age_s}: this node clock may be behind')

    def _forget_old(self) -> None:
        assert self.audit is not None
        known = self.audit.state.decisions
        if len(known) < self.max_remembered:
            return
        horizon_s = self._now_s() - self.max_age_s - self.future_tolerance_s
        for decision_id in [d for d, s in known.items() if s < horizon_s]:
            del known[decision_id]  # too old to pass the age rule again
        if len(known) >= self.max_remembered:
            raise Refusal('overloaded', f'{len(known)} fresh decision ids held, max_remembered_decisions='
                                        f'{self.max_remembered}')

    def on_decision_liveliness(self, info: object) -> None:
        """Report a silent control centre: every decision writer that was alive lost its lease or left.

        WARN `control_centre_silent` while none is alive after one was; never before the first, since a
        breaker node may start before the control centre does.
        """
        was = self.decision_writers_alive
        self.decision_writers_alive = int(info.alive_count)
        self.diag.values['decision_writers_alive'] = str(self.decision_writers_alive)
        if self.decision_writers_alive == 0 and was > 0:
            self.diag.warn('control_centre_silent',
                           f'no live decision writer since {time.time():.3f} (wall, s): no decision can arrive '
                           f'(liveliness lease {DECISION_LEASE_S:g} s)')
        elif self.decision_writers_alive > 0:
            self.diag.warn('control_centre_silent', None)

    def on_decision(self, msg: IslandingDecision, info: dict | None = None) -> None:
        """Check a decision against every rule; command its breakers only if all hold."""
        t0 = time.perf_counter()
        ids = {'decision_id': msg.decision_id[:_MAX_ID_CHARS], 'request_id': msg.request_id[:_MAX_ID_CHARS]}
        if self.audit is None:
            self.diag.reject('audit_unavailable', f'decision {ids["decision_id"]!r}: '
                                                  f'{self.diag.faults.get("audit", "no audit log")}')
            return
        try:
            self._authenticate(msg)
        except Refusal as exc:
            self._refuse(exc.reason, f'decision {ids["decision_id"]!r}: {exc}', authenticated=False, **ids)
            return
        request_s = stamp_s(msg.request_stamp)
        if msg.decision_id in self.audit.state.decisions:
            self.diag.reject('duplicate', f'decision {msg.decision_id!r} was handled before')
            self._record('refusal', reason='duplicate', **ids)
            return
        seen = {'authenticated': True, 'request_stamp_s': request_s, **ids}
        try:
            why = self.clock.inconsistency()
            if why is not None:  # before anything uses the clock: a forged one would make old ids forgettable
                raise Refusal('clock_inconsistent', f'this node clock cannot be trusted: {why}')
            self._forget_old()
            self._check_wait(info)
            self._check(msg, request_s)
        except Refusal as exc:
            self._refuse(exc.reason, f'decision {msg.decision_id!r}: {exc}', **seen)
            return
        if msg.status == IslandingDecision.STATUS_NO_SPLIT:
            self._record('no_split', **seen)
            return
        if msg.status in _NOT_DECIDED:
            self._record('not_decided', status=int(msg.status), detail=msg.status_detail[:500], **seen)
            return
        if not self.armed:
            self._refuse('not_armed', f'decision {msg.decision_id!r}: node is disarmed', **seen)
            return
        try:
            grid, _ = self.topology.grid_at(self._now_s())
        except TopologyError:
            self._refuse('no_snapshot', f'decision {msg.decision_id!r}: no network snapshot to check it against',
                         **seen)
            return
        try:
            plan = plan_commands(grid, msg.bus_numbers, msg.bus_island, msg.cut_branch_ids, msg.cut_from_bus,
                                 msg.cut_to_bus, max_breakers=self.max_breakers,
                                 open_breakers=self._open_breakers(), breaker_override=self.override)
            state = self.audit.state
            actions = plan_actions(grid, msg.bus_numbers, msg.bus_island, msg.shed_bus, msg.shed_mw,
                                   msg.trip_generator_names, max_actions=self.max_actions,
                                   shed_before_mw=state.shed_mw, tripped_before=state.tripped)
        except Refusal as exc:
            self._refuse(exc.reason, f'decision {msg.decision_id!r}: {exc}', **seen)
            return
        commands = [{'command_id': f'{msg.decision_id}/{c.breaker_id}', 'breaker_id': c.breaker_id,
                     'branch_id': c.branch_id, 'action': 'open'} for c in plan.commands]
        commands += [{'command_id': f'{msg.decision_id}/{a.device_id}', 'breaker_id': a.device_id, 'branch_id': '',
                      'action': a.kind, 'bus': a.bus, **({'amount_mw': a.amount_mw} if a.kind == 'shed' else
                                                         {'generator': a.generator})} for a in actions]
        # One record for the whole decision, cut and actions, on disk before the first command leaves: a crash can
        # lose commands but never repeat one, and never leaves a half-recorded decision.
        if not self._record('command', commands=commands, islands=plan.n_islands, **seen):
            self.diag.reject('audit_unavailable', f'decision {msg.decision_id!r}: the command record could not '
                                                  f'be written; nothing commanded')
            return
        stamp = self.get_clock().now().to_msg()
        for c in commands:
            out = BreakerCommand(command_id=c['command_id'], decision_id=msg.decision_id, breaker_id=c['breaker_id'],
                                 branch_id=c['branch_id'], action=_ACTIONS[c['action']], bus=int(c.get('bus', 0)),
                                 generator_name=c.get('generator', ''), amount_mw=float(c.get('amount_mw', 0.0)))
            out.header.stamp = stamp
            self.pub.publish(out)
        self.diag.computed(time.perf_counter() - t0)
        shed = sum(a.amount_mw for a in actions)
        self.get_logger().info(f'decision {msg.decision_id}: opened {len(plan.commands)} breakers '
                               f'{", ".join(c.breaker_id for c in plan.commands)}; shed {shed:.1f} MW at '
                               f'{sum(1 for a in actions if a.kind == "shed")} buses; tripped '
                               f'{", ".join(a.generator for a in actions if a.kind == "trip") or "no machine"}')

    def close(self) -> None:
        """Close the audit log."""
        if self.audit is not None:
            self.audit.close()


def main(args: list[str] | None = None) -> int:
    """Run the breaker_command node."""
    return spin_node(BreakerCommandNode, args)


if __name__ == '__main__':
    sys.exit(main())
