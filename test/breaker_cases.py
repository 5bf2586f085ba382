"""Grids, island splits and signed decisions for the breaker tests, on any network (nothing assumes IEEE 39)."""

from __future__ import annotations

from functools import cache
from pathlib import Path

from controlled_islanding.core.grid import Grid
from controlled_islanding.harness import breaker_soak
from controlled_islanding.harness.breaker_soak import boundary, snapshot_msg, two_islands  # noqa: F401  re-exported
from controlled_islanding.safety import signing

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


def decision_msg(island: dict[int, int], cut: list, request_stamp_ns: int, *, key=None, **kwargs):
    """Return an IslandingDecision signed with the test decision key unless another key is given."""
    return breaker_soak.decision_msg(island, cut, request_stamp_ns, key=key or private_key('partitioning'), **kwargs)
