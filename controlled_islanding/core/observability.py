"""Partial observability: which generators carry a PMU, and an optional guess of the others' groups.

The paper claims the method "can handle partial observability of the system". A generator with no PMU has no
rotor angle, so coherency cannot group it; `core.islanding.decide` leaves it unconstrained. This module holds
the two placement rules the sweeps use and one documented inference rule, kept apart so that a guess is
never mistaken for a measurement.

Inference rule (`infer_groups`): an unobserved generator joins the group of the observed generator bus
closest to it in effective reactance (the "resistance distance" of the network's susceptance graph,
r_ij = Z_ii + Z_jj - 2 Z_ij with Z the inverse of the bus susceptance matrix grounded at one bus). Two
machines close in reactance are tightly coupled (synchronising power grows as 1/x between them), which is
what slow-coherency theory groups on; it uses the network model only, never the angles.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.sparse import linalg as sparse_linalg

from controlled_islanding.core.grid import Grid


class ObservabilityError(ValueError):
    """A coverage outside (0, 1], or a grid whose generators cannot be reached from the observed ones."""


def largest_first(grid: Grid, fraction: float) -> list[str]:
    """Return the generators a largest-machines-first PMU placement observes, by capacity (MW), then name.

    Args:
        grid: The grid.
        fraction: Share of the generators that carry a PMU, in (0, 1]; at least one is observed.

    """
    count = _count(grid, fraction)
    ranked = sorted(grid.generators, key=lambda g: (-g.p_max_mw, g.name))
    return sorted(g.name for g in ranked[:count])


def random_placement(grid: Grid, fraction: float, rng: np.random.Generator) -> list[str]:
    """Return the generators a random placement (seeded by rng) observes; at least one."""
    names = sorted(g.name for g in grid.generators)
    chosen = rng.choice(len(names), size=_count(grid, fraction), replace=False)
    return sorted(names[int(i)] for i in chosen)


def _count(grid: Grid, fraction: float) -> int:
    if not 0.0 < fraction <= 1.0:
        raise ObservabilityError(f'PMU coverage must be a fraction in (0, 1], got {fraction}')
    return max(1, round(fraction * len(grid.generators)))


def reactance_distance(grid: Grid, from_buses: Collection[int], to_buses: Collection[int]) -> np.ndarray:
    """Return the effective reactance between buses (pu), rows from_buses, columns to_buses.

    Branches with unknown or zero reactance count as 1e-4 pu (a bus tie), which keeps the graph connected
    without inventing impedance.

    Raises:
        ObservabilityError: The in-service network is not connected.

    """
    index = {b: i for i, b in enumerate(grid.buses)}
    rows, cols, vals = [], [], []
    for br in grid.branches:
        if not br.in_service or br.from_bus == br.to_bus:
            continue
        x = abs(br.x_pu) if np.isfinite(br.x_pu) and br.x_pu != 0 else 1e-4
        i, j = index[br.from_bus], index[br.to_bus]
        rows += [i, j, i, j]
        cols += [j, i, i, j]
        vals += [-1 / x, -1 / x, 1 / x, 1 / x]
    n = len(index)
    lap = sparse.csc_array((vals, (rows, cols)), shape=(n, n))
    n_parts, _ = csgraph.connected_components(lap, directed=False)
    if n_parts > 1:
        raise ObservabilityError(f'{grid.name} is in {n_parts} pieces; distances between them are infinite')
    # Grounding bus 0 makes the matrix invertible; differences of its inverse give the same distances.
    solve = sparse_linalg.splu(lap[1:, 1:].tocsc()).solve
    wanted = sorted(set(from_buses) | set(to_buses))
    col = {b: c for c, b in enumerate(wanted)}
    z_sub = np.zeros((n, len(wanted)))
    for b, c in col.items():
        if index[b] > 0:
            unit = np.zeros(n - 1)
            unit[index[b] - 1] = 1.0
            # One column at a time: SuperLU's block solve took 5x longer on GBnetwork (2224 buses, 400 columns).
            z_sub[1:, c] = solve(unit)
    z = np.array([z_sub[index[b]] for b in wanted])
    diag = np.diag(z)
    dist = diag[:, None] + diag[None, :] - 2 * z
    return dist[np.ix_([col[b] for b in from_buses], [col[b] for b in to_buses])]


def infer_groups(grid: Grid, groups: Mapping[str, int], unobserved: Collection[str]) -> dict[str, int]:
    """Guess the group of each unobserved generator by the rule in the module docstring.

    Args:
        grid: The grid (current branch statuses).
        groups: Group of every observed generator, by name.
        unobserved: The generators to place.

    Returns:
        The inferred group of each unobserved generator, by name (the observed ones are not included).

    """
    if not unobserved:
        return {}
    by_name = {g.name: g for g in grid.generators}
    observed = sorted(groups)
    obs_buses = [by_name[n].bus for n in observed]
    un = sorted(unobserved)
    dist = reactance_distance(grid, [by_name[n].bus for n in un], obs_buses)
    # Ties (machines on one bus, distance 0) go to the lowest group, so the answer does not depend on order.
    out = {}
    for r, name in enumerate(un):
        best = min(range(len(observed)), key=lambda c, r=r: (round(float(dist[r, c]), 12), groups[observed[c]]))
        out[name] = int(groups[observed[best]])
    return out
