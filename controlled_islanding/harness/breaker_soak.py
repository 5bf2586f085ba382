"""Breaker soak: a seeded adversary against a real breaker_command process, then every rule checked on its log.

The adversary mixes valid decisions (some with remedial actions: load sheds and generator trips) with
duplicates, other spellings of branches, stale and future request stamps, forged and foreign signatures, unset
statuses, cuts missing a branch or naming an inner one, signed decisions whose actions the snapshot does not allow
(a shed beyond a bus's load, at a bus without load, a NaN amount, a bus named twice, an unknown machine), actions
on a decision that is not a split, amounts changed after signing, resends, signed arm and disarm requests, and
kill -9 restarts of the node. The ground truth is the audit log: replayed in order, it must never show a command
while disarmed, for a decision that was not a valid, signed, fresh split, on a cut other than its islands'
boundary or actions other than its own, twice for one decision or one breaker, a machine tripped twice, more shed
at a bus than its load in all, or beyond `max_breakers` or `max_actions`; and every command seen on
/breaker/commands must be in it.

Also the island and message builders the breaker tests use; nothing here assumes IEEE 39.
"""

from __future__ import annotations

import json
import math
import os
import random
import signal
import time
import uuid
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from controlled_islanding.core.grid import Branch, Grid
from controlled_islanding.core.remedial import bus_load_mw
from controlled_islanding.safety import signing
from controlled_islanding.wire import topics

MAX_BREAKERS = 8
MAX_ACTIONS = 6
MAX_DECISION_AGE_S = 30.0


@dataclass(frozen=True)
class Expected:
    """What a valid decision may command: the breakers of its islands' boundary and its own remedial actions.

    Attributes:
        breakers: Breaker ids.
        actions: ('shed', bus, MW) and ('trip', machine) entries.

    """

    breakers: frozenset[str]
    actions: frozenset[tuple] = frozenset()


def _logged_actions(commands: list[dict]) -> set[tuple]:
    out: set[tuple] = set()
    for c in commands:
        if c.get('action') == 'shed':
            out.add(('shed', int(c['bus']), float(c['amount_mw'])))
        elif c.get('action') == 'trip':
            out.add(('trip', str(c['generator'])))
    return out


class SoakError(RuntimeError):
    """The soak could not run (the node did not start or answer)."""


def two_islands(grid: Grid, seed_index: int = 0) -> dict[int, int]:
    """Split a grid into two islands that both hold generation: a breadth-first ball around one generator.

    The ball grows until it holds about half the buses, but it stops before swallowing every generator.
    """
    powered = [g for g in grid.generators if g.p_max_mw > 0]
    start = powered[seed_index % len(powered)].bus
    adjacent: dict[int, list[int]] = {b: [] for b in grid.buses}
    for b in grid.branches:
        if b.in_service:
            adjacent[b.from_bus].append(b.to_bus)
            adjacent[b.to_bus].append(b.from_bus)
    gen_buses = {g.bus for g in powered}
    ball, queue = {start}, deque([start])
    while queue and len(ball) < len(grid.buses) // 2:
        for nxt in adjacent[queue.popleft()]:
            if nxt not in ball and (gen_buses - ball - {nxt}):
                ball.add(nxt)
                queue.append(nxt)
    return {b: 0 if b in ball else 1 for b in grid.buses}


def boundary(grid: Grid, island: dict[int, int]) -> list[Branch]:
    """Return the in-service branches joining two islands."""
    return [b for b in grid.branches if b.in_service and island[b.from_bus] != island[b.to_bus]]


def decision_msg(island: dict[int, int], cut: list, request_stamp_ns: int, *, key: object, status: int | None = None,
                 decision_id: str | None = None, sign: bool = True, shed: dict[int, float] | None = None,
                 trips: list[str] | tuple[str, ...] = ()) -> object:
    """Return an (optionally signed) IslandingDecision (rclpy) for an island map, a cut and remedial actions.

    `cut` holds Branch objects or (id, from bus, to bus) tuples; `shed` is the load to shed per bus, MW, `trips` the
    machines to trip.
    """
    from controlled_islanding_msgs.msg import IslandingDecision

    entries = [(b.branch_id, b.from_bus, b.to_bus) if isinstance(b, Branch) else b for b in cut]
    buses = sorted(island)
    status = IslandingDecision.STATUS_SPLIT if status is None else status
    msg = IslandingDecision(
        decision_id=decision_id or str(uuid.uuid4()), request_id=str(uuid.uuid4()), method='dtw',
        status=status, split=status == IslandingDecision.STATUS_SPLIT,
        bus_numbers=buses, bus_island=[island[b] for b in buses],
        cut_branch_ids=[e[0] for e in entries], cut_from_bus=[int(e[1]) for e in entries],
        cut_to_bus=[int(e[2]) for e in entries], shed_bus=[int(b) for b in (shed or {})],
        shed_mw=[float(mw) for mw in (shed or {}).values()], trip_generator_names=list(trips))
    msg.request_stamp.sec, msg.request_stamp.nanosec = divmod(int(request_stamp_ns), 1_000_000_000)
    msg.header.stamp = msg.request_stamp
    if sign:
        msg.key_id = signing.fingerprint(key)
        msg.signature = signing.sign(key, signing.decision_payload(msg))
    return msg


def snapshot_msg(grid: Grid, stamp_ns: int, breaker_ids: dict[str, str] | None = None) -> object:
    """Return a NetworkSnapshot (rclpy) of a grid; `breaker_ids` names breakers as the data would."""
    from controlled_islanding_msgs.msg import NetworkSnapshot

    n = len(grid.branches)
    msg = NetworkSnapshot(
        case_name=grid.name, base_mva=float(grid.base_mva), bus_numbers=list(grid.buses),
        branch_ids=[b.branch_id for b in grid.branches],
        branch_breaker_ids=[(breaker_ids or {}).get(b.branch_id, b.breaker) for b in grid.branches],
        branch_from_bus=[b.from_bus for b in grid.branches], branch_to_bus=[b.to_bus for b in grid.branches],
        branch_in_service=[b.in_service for b in grid.branches],
        branch_p_from_mw=[float(x) for x in grid.p_from_mw] if grid.has_flows else [0.0] * n,
        branch_p_to_mw=[float(x) for x in grid.p_to_mw] if grid.has_flows else [0.0] * n,
        generator_names=[g.name for g in grid.generators], generator_bus=[g.bus for g in grid.generators],
        generator_p_mw=[float(g.p_mw) for g in grid.generators],
        generator_p_max_mw=[float(g.p_max_mw) for g in grid.generators],
        # Rotor-angle estimation is not exercised here; a reactance the validators accept stands in.
        generator_xq_pu=[float(g.xq_pu) if g.xq_pu == g.xq_pu else 0.5 for g in grid.generators],
        generator_ra_pu=[float(g.ra_pu) for g in grid.generators],
        load_bus=[ld.bus for ld in grid.loads], load_p_mw=[float(ld.p_mw) for ld in grid.loads],
        load_q_mvar=[float(ld.q_mvar) for ld in grid.loads])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return msg


@dataclass
class SoakReport:
    """What a soak did and found."""

    trials: int
    seed: int
    restarts: int
    commanded_decisions: int
    broken: list[str] = field(default_factory=list)
    wall_s: float = 0.0

    def render(self) -> str:
        """Return the one-paragraph summary."""
        lines = [f'breaker soak: {self.trials} trials (seed {self.seed}, {self.restarts} kill -9 restarts) in '
                 f'{self.wall_s:.0f} s; {self.commanded_decisions} decisions commanded; '
                 f'{len(self.broken)} rules broken']
        return '\n'.join(lines + [f'  broken: {b}' for b in self.broken[:20]])


def check_audit(records: list[dict], valid: Mapping[str, Expected], published: list[str],
                max_breakers: int = MAX_BREAKERS, max_actions: int = MAX_ACTIONS,
                bus_load: Mapping[int, float] | None = None) -> tuple[list[str], set[str]]:
    """Replay an audit log in order and return (rules broken, decision ids commanded).

    Args:
        records: The audit log's records, in file order.
        valid: Decision id -> what it may command, for every decision sent that was a valid, signed, fresh split
            (any other commanded decision breaks a rule).
        published: Command ids seen on /breaker/commands.
        max_breakers: The node's cap on breakers.
        max_actions: The node's cap on remedial actions.
        bus_load: Each bus's load in the snapshot, MW (None: sheds are not checked against it).

    """
    armed, opened, commanded, broken = False, set(), set(), []
    tripped: set[str] = set()
    shed: dict[int, float] = {}
    for r in records:
        if r['event'] == 'start':
            armed = False
        elif r['event'] in ('armed', 'disarmed'):
            armed = r['event'] == 'armed'
        elif r['event'] == 'reclosed':
            opened.discard(r['breaker_id'])
        if r['event'] != 'command':
            continue
        breakers = {c['breaker_id'] for c in r['commands'] if c.get('action', 'open') == 'open'}
        actions = _logged_actions(r['commands'])
        decision = r['decision_id']
        if not armed:
            broken.append(f'command while disarmed: {decision}')
        if decision not in valid:
            broken.append(f'command for a decision that must be refused: {decision}')
        else:
            if breakers != valid[decision].breakers:
                broken.append(f'cut {sorted(breakers)} differs from the boundary {sorted(valid[decision].breakers)}')
            if actions != valid[decision].actions:
                broken.append(f'decision {decision}: actions {sorted(actions)} differ from its own '
                              f'{sorted(valid[decision].actions)}')
        if decision in commanded:
            broken.append(f'decision {decision} commanded twice')
        if breakers & opened:
            broken.append(f'breakers {sorted(breakers & opened)} commanded twice')
        if len(breakers) > max_breakers:
            broken.append(f'{len(breakers)} breakers > max_breakers={max_breakers}')
        if len(actions) > max_actions:
            broken.append(f'{len(actions)} actions > max_actions={max_actions}')
        machines = {a[1] for a in actions if a[0] == 'trip'}
        if machines & tripped:
            broken.append(f'machines {sorted(machines & tripped)} tripped twice')
        tripped |= machines
        for _, bus, mw in (a for a in actions if a[0] == 'shed'):
            shed[bus] = shed.get(bus, 0.0) + mw
            if not (math.isfinite(mw) and mw > 0) or (
                    bus_load is not None and shed[bus] > bus_load.get(bus, 0.0) + 1e-6):
                broken.append(f'bus {bus}: {shed[bus]:.3f} MW shed in all (this time {mw}), its load '
                              f'{(bus_load or {}).get(bus, float("nan")):.3f} MW')
        commanded.add(decision)
        opened |= breakers
    logged = {c['command_id'] for r in records if r['event'] == 'command' for c in r['commands']}
    missing = sorted(set(published) - logged)
    if missing:
        broken.append(f'published commands missing from the audit log: {missing[:5]}')
    return broken, commanded


def _grid() -> tuple[Grid, dict[str, str]]:
    grid = Grid.from_matpower('case14').with_flows()
    # Some breakers named by the data, the rest by default: both must be honoured.
    return grid, {'2-3': 'BRK-NORTH-7', '4-5': 'BRK-SOUTH-2'}


def run_breaker_soak(trials: int, seed: int, key_dir: Path, results: Path,
                     progress: Callable[[str], None] = lambda _line: None) -> SoakReport:
    """Run the adversary against a real breaker_command process and check its audit log.

    Args:
        trials: Decisions and arm/disarm requests to send.
        seed: Random seed.
        key_dir: Signing keys (made if missing); the node trusts these.
        results: Folder for the audit log and node log (made).
        progress: Called with a line every 1000 trials.

    Raises:
        SoakError: The node did not start, or stopped answering.

    """
    import rclpy
    from controlled_islanding_msgs.msg import BranchStatus, BreakerCommand, IslandingDecision, NetworkSnapshot
    from controlled_islanding_msgs.srv import SetArmed
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.signals import SignalHandlerOptions

    from controlled_islanding.graph.rosenv import isolated_ros_environment
    from controlled_islanding.graph.supervisor import GRAPH, Supervisor
    from controlled_islanding.ros.endpoints import qos_for

    spec = next(s for s in GRAPH if s.executable == 'breaker_command')
    rng = random.Random(seed)
    grid, field_names = _grid()
    splits = [(island, boundary(grid, island)) for island in
              (two_islands(grid, seed_index=i) for i in range(len(grid.generators)))]
    signing.init_keys(key_dir)
    decision_key = signing.load_private_key(signing.key_paths(key_dir, 'partitioning').private)
    operator_key = signing.load_private_key(signing.key_paths(key_dir, 'operator').private)
    results.mkdir(parents=True, exist_ok=True)
    audit = results / 'breaker_audit.jsonl'
    params = {'audit_log': audit, 'max_decision_age_s': MAX_DECISION_AGE_S, 'max_breakers': MAX_BREAKERS,
              'max_actions': MAX_ACTIONS, 'key_dir': key_dir}
    loads = bus_load_mw(grid)
    load_buses = sorted(b for b, mw in loads.items() if mw > 0)
    valid: dict[str, Expected] = {}
    sent: list[object] = []
    published: list[str] = []
    diagnostics: dict[str, str] = {}
    restarts = 0
    t0 = time.monotonic()
    with isolated_ros_environment(results / 'ros_log') as env, Supervisor(env, results / 'logs') as sup:
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=int(env['ROS_DOMAIN_ID']),
                   signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node('breaker_soak', context=context)
        executor = rclpy.executors.SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            def spin(seconds: float, done: Callable[[], bool] = lambda: False) -> bool:
                end = time.monotonic() + seconds
                while not done() and time.monotonic() < end:
                    executor.spin_once(timeout_sec=0.02)
                return done()

            def on_diag(msg: DiagnosticArray) -> None:
                for status in msg.status:
                    if status.name.lstrip('/') == 'breaker_command':
                        diagnostics.clear()
                        diagnostics.update({kv.key: kv.value for kv in status.values})

            node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diag, qos_for(topics.DIAGNOSTICS))
            node.create_subscription(BreakerCommand, topics.BREAKER_COMMANDS, lambda m: published.append(m.command_id),
                                     qos_for(topics.BREAKER_COMMANDS))
            decisions = node.create_publisher(IslandingDecision, topics.ISLANDING_DECISION,
                                              qos_for(topics.ISLANDING_DECISION))
            snapshots = node.create_publisher(NetworkSnapshot, topics.NETWORK_SNAPSHOT,
                                              qos_for(topics.NETWORK_SNAPSHOT))
            statuses = node.create_publisher(BranchStatus, topics.BRANCH_STATUS, qos_for(topics.BRANCH_STATUS))
            arm_client = node.create_client(SetArmed, '/breaker_command/set_armed')

            def reclose_all() -> None:
                # Every breaker closable again, so later valid decisions are executed, not refused as open.
                for b in grid.branches:
                    status = BranchStatus(branch_id=b.branch_id, from_bus=b.from_bus, to_bus=b.to_bus, in_service=True)
                    status.header.stamp.sec, status.header.stamp.nanosec = divmod(now_ns(), 1_000_000_000)
                    statuses.publish(status)

            def now_ns() -> int:
                return node.get_clock().now().nanoseconds

            def start_node() -> None:
                diagnostics.clear()
                sup.start(spec, params)
                if not arm_client.wait_for_service(timeout_sec=30.0):
                    raise SoakError(f'breaker_command did not start:\n{sup.log_tail("breaker_command")}')
                snapshots.publish(snapshot_msg(grid, now_ns(), field_names))
                if not spin(15.0, lambda: diagnostics.get('buses') == str(len(grid.buses))):
                    raise SoakError('breaker_command did not take the network snapshot within 15 s')

            def arm(armed: bool) -> None:
                request = signing.signed_arm_request(SetArmed.Request(), operator_key, '/breaker_command', armed,
                                                     time.time())
                future = arm_client.call_async(request)
                if not spin(10.0, future.done):
                    raise SoakError('breaker_command did not answer an arm request within 10 s')

            start_node()
            for trial in range(trials):
                if trial and trial % max(trials // 3, 50) == 0:
                    os.kill(sup.children['breaker_command'].pid, signal.SIGKILL)
                    sup.children['breaker_command'].wait()
                    restarts += 1
                    start_node()
                if rng.random() < 0.12:
                    arm(rng.random() < 0.7)
                    continue
                if rng.random() < 0.05:
                    reclose_all()
                    spin(0.1)
                    continue
                island, cut = rng.choice(splits)
                entries: list = list(cut)
                kind = rng.choice(['good', 'good', 'alias', 'dup', 'stale', 'future', 'forged', 'foreign',
                                   'missing', 'extra', 'resend', 'unset', 'unsigned', 'good', 'over_shed',
                                   'ghost_load', 'ghost_machine', 'nan_shed', 'twice_shed', 'forged_amount',
                                   'no_split_actions'])
                # Small sheds at a few load buses, sometimes a trip: each valid on its own, refused once a bus's
                # load is used up or the machine tripped before.
                shed = {b: round(rng.uniform(0.01, 0.3) * loads[b], 3)
                        for b in rng.sample(load_buses, rng.randint(0, 3))} if rng.random() < 0.6 else {}
                trips = [rng.choice(grid.generators).name] if rng.random() < 0.1 else []
                if kind == 'over_shed':
                    b = rng.choice(load_buses)
                    shed[b] = loads[b] * rng.uniform(1.01, 100.0)
                elif kind == 'ghost_load':
                    shed[rng.choice([b for b in grid.buses if loads.get(b, 0.0) <= 0] + [max(grid.buses) + 7])] = 1.0
                elif kind == 'ghost_machine':
                    trips = [*trips, 'GENROU_999']
                elif kind == 'nan_shed':
                    shed[rng.choice(load_buses)] = rng.choice([float('nan'), float('inf'), -1.0, 0.0])
                stamp = now_ns()
                if kind == 'alias':
                    entries = [(f'{b.to_bus}-{b.from_bus}', b.to_bus, b.from_bus) for b in cut] + entries
                elif kind == 'dup':
                    entries = entries * rng.randint(2, 6)
                elif kind == 'stale':
                    stamp -= int(rng.choice([45, 600, 86400, 365 * 86400]) * 1e9)
                elif kind == 'future':
                    stamp += int(rng.choice([2, 3600, 365 * 86400]) * 1e9)
                elif kind == 'missing' and len(entries) > 1:
                    entries = entries[1:]
                elif kind == 'extra':
                    entries = entries + [next(b for b in grid.branches if island[b.from_bus] == island[b.to_bus])]
                if kind == 'resend' and sent:
                    msg = rng.choice(sent)
                else:
                    key = Ed25519PrivateKey.generate() if kind == 'foreign' else decision_key
                    status = 0 if kind == 'unset' else 2 if kind == 'no_split_actions' else None  # 2: NO_SPLIT
                    if kind in ('no_split_actions', 'forged_amount') and not shed:
                        shed = {load_buses[0]: 1.0}
                    msg = decision_msg(island, entries, stamp, key=key, status=status, sign=kind != 'unsigned',
                                       shed=shed, trips=trips)
                    if kind == 'twice_shed':
                        msg.shed_bus, msg.shed_mw = [load_buses[0]] * 2, [0.5, 0.5]
                        msg.signature = signing.sign(key, signing.decision_payload(msg))
                    if kind == 'forged':
                        msg.bus_island = [1 - x for x in msg.bus_island]
                    if kind == 'forged_amount':
                        msg.shed_mw = [mw + 0.001 for mw in msg.shed_mw]
                    if kind in ('good', 'alias', 'dup') or (kind == 'missing' and len(cut) == 1):
                        valid[msg.decision_id] = Expected(
                            frozenset(field_names.get(b.branch_id, f'CB-{b.branch_id}') for b in cut),
                            frozenset([('shed', b, mw) for b, mw in shed.items()] + [('trip', n) for n in trips]))
                    sent.append(msg)
                    del sent[:-50]
                decisions.publish(msg)
                if trial % 20 == 19:
                    spin(0.05)
                if trial % 1000 == 999:
                    progress(f'breaker soak: {trial + 1}/{trials} trials, {len(published)} commands so far')
            spin(2.0)
            if sup.children['breaker_command'].poll() is not None:
                raise SoakError(f'breaker_command died:\n{sup.log_tail("breaker_command")}')
        finally:
            node.destroy_node()
            context.try_shutdown()
    records = [json.loads(line) for line in audit.read_text().splitlines()]
    broken, commanded = check_audit(records, valid, published, bus_load=loads)
    return SoakReport(trials=trials, seed=seed, restarts=restarts, commanded_decisions=len(commanded),
                      broken=broken, wall_s=time.monotonic() - t0)
