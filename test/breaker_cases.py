"""Grids, island splits and signed decisions for the breaker tests, on any network (nothing assumes IEEE 39)."""

from __future__ import annotations

import uuid
from collections import deque
from functools import cache
from pathlib import Path

from controlled_islanding import signing
from controlled_islanding.core.grid import Grid

BUILD = Path(__file__).resolve().parents[1] / 'build'

# The ANDES systems every breaker rule is checked on: (case, PSS/E dynamic file or None).
ANDES_CASES = {
    'ieee14': ('ieee14/ieee14_full.xlsx', None),
    'pjm5bus': ('5bus/pjm5bus.xlsx', None),
    'EI_33': ('ei/EI_33.xlsx', None),
    'GBnetwork': ('GBnetwork/GBnetwork.xlsx', None),
    'nordic44': ('nordic44/N44_BC.raw', 'N44_BC.dyr'),
    'ieee39': ('ieee39/ieee39_full.xlsx', None),
}


@cache
def andes_grid(name: str) -> Grid:
    """Return an ANDES system's network after its power flow."""
    from controlled_islanding.sim.andes_sim import power_flow_grid

    case, addfile = ANDES_CASES[name]
    return power_flow_grid(case, addfile)


@cache
def made_test_keys() -> Path:
    """Return a key directory made for this test run (never the user's own keys)."""
    directory = BUILD / 'test_keys'
    signing.init_keys(directory)
    return directory


def private_key(role: str):
    """Return a test private key of a role."""
    return signing.load_private_key(signing.key_paths(made_test_keys(), role).private)


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


def boundary(grid: Grid, island: dict[int, int]) -> list:
    """Return the in-service branches joining two islands."""
    return [b for b in grid.branches if b.in_service and island[b.from_bus] != island[b.to_bus]]


def decision_msg(island: dict[int, int], cut: list, request_stamp_ns: int, *, key=None, status=None,
                 decision_id: str | None = None, sign: bool = True):
    """Return a signed IslandingDecision (rclpy) for an island map and a cut.

    `cut` holds Branch objects or (id, from bus, to bus) tuples.
    """
    from controlled_islanding_msgs.msg import IslandingDecision

    entries = [(b.branch_id, b.from_bus, b.to_bus) if hasattr(b, 'branch_id') else b for b in cut]
    buses = sorted(island)
    status = IslandingDecision.STATUS_SPLIT if status is None else status
    msg = IslandingDecision(
        decision_id=decision_id or str(uuid.uuid4()), request_id=str(uuid.uuid4()), method='dtw',
        status=status, split=status == IslandingDecision.STATUS_SPLIT,
        bus_numbers=buses, bus_island=[island[b] for b in buses],
        cut_branch_ids=[e[0] for e in entries], cut_from_bus=[int(e[1]) for e in entries],
        cut_to_bus=[int(e[2]) for e in entries])
    msg.request_stamp.sec, msg.request_stamp.nanosec = divmod(int(request_stamp_ns), 1_000_000_000)
    msg.header.stamp = msg.request_stamp
    if sign:
        key = key or private_key('partitioning')
        msg.key_id = signing.fingerprint(key)
        msg.signature = signing.sign(key, signing.decision_payload(msg))
    return msg


def snapshot_msg(grid: Grid, stamp_ns: int, breaker_ids: dict[str, str] | None = None):
    """Return a NetworkSnapshot (rclpy) of a grid; `breaker_ids` names breakers as the data would."""
    from controlled_islanding_msgs.msg import NetworkSnapshot

    flows = grid if grid.has_flows else None
    msg = NetworkSnapshot(
        case_name=grid.name, base_mva=float(grid.base_mva), bus_numbers=list(grid.buses),
        branch_ids=[b.branch_id for b in grid.branches],
        branch_breaker_ids=[(breaker_ids or {}).get(b.branch_id, b.breaker) for b in grid.branches],
        branch_from_bus=[b.from_bus for b in grid.branches], branch_to_bus=[b.to_bus for b in grid.branches],
        branch_in_service=[b.in_service for b in grid.branches],
        branch_p_from_mw=[float(x) for x in flows.p_from_mw] if flows else [0.0] * len(grid.branches),
        branch_p_to_mw=[float(x) for x in flows.p_to_mw] if flows else [0.0] * len(grid.branches),
        generator_names=[g.name for g in grid.generators], generator_bus=[g.bus for g in grid.generators],
        generator_p_mw=[float(g.p_mw) for g in grid.generators],
        generator_p_max_mw=[float(g.p_max_mw) for g in grid.generators],
        generator_xq_pu=[float(g.xq_pu) if g.xq_pu == g.xq_pu else 0.5 for g in grid.generators],
        generator_ra_pu=[float(g.ra_pu) for g in grid.generators],
        load_bus=[ld.bus for ld in grid.loads], load_p_mw=[float(ld.p_mw) for ld in grid.loads],
        load_q_mvar=[float(ld.q_mvar) for ld in grid.loads])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return msg
