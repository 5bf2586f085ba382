"""PMU-estimated rotor angles of a bag's generators: the series every offline study groups.

A module of its own so that evaluation/cases.py and evaluation/coherency_rules.py, which both need them, do
not import each other.
"""

from __future__ import annotations

import numpy as np


class EvaluateError(ValueError):
    """A case that cannot be evaluated (no usable rotor angles, groups that do not fit the grid)."""


def request_time_s(bag) -> float:
    """Return the time the bag's first islanding request is stamped with (the bag's end if none), s after t0."""
    return float(bag.request_t_s[0]) if len(bag.request_t_s) else float(bag.tag_s[-1])


def generator_series(bag, start_s: float, end_s: float) -> tuple[np.ndarray, list[str], np.ndarray]:
    """PMU-estimated rotor angles of every generator between two times.

    Args:
        bag: A BagData.
        start_s: First time tag, s after t0.
        end_s: Last time tag, s after t0.

    Returns:
        (time tags s, generator names, angles rad shaped (n_generators, n_samples), NaN where lost).

    Raises:
        EvaluateError: A generator without a PMU at its bus, or fewer than 2 valid samples for one.

    """
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad
    from controlled_islanding.wire.bagdata import BagDataError

    grid = bag.grid
    try:
        # A machine's own channel where machines share a bus: the bus's one channel would give them one series.
        cols = [bag.pmu_column(g.name, g.bus) for g in grid.generators]
    except BagDataError as exc:
        raise EvaluateError(f'{exc}; coherency needs every generator') from exc
    rows = (bag.tag_s >= start_s - 1e-9) & (bag.tag_s <= end_s + 1e-9)
    angles = np.asarray(estimate_rotor_angle_rad(
        bag.v_mag_pu[np.ix_(rows, cols)], bag.v_angle_rad[np.ix_(rows, cols)], bag.i_mag_pu[np.ix_(rows, cols)],
        bag.i_angle_rad[np.ix_(rows, cols)], np.array([g.xq_pu for g in grid.generators]),
        np.array([g.ra_pu for g in grid.generators])), dtype=float).T
    for g, angle in zip(grid.generators, angles, strict=True):
        if np.isfinite(angle).sum() < 2:
            raise EvaluateError(f'generator {g.name} (PMU at bus {g.bus}) has fewer than 2 valid samples between '
                                f'{start_s:.3f} s and {end_s:.3f} s')
    return bag.tag_s[rows], [g.name for g in grid.generators], angles
