"""Record what the spectral partition decides on every manifest bag, the paper's cases and larger MATPOWER cases.

Written for issue 12, to check that a faster solver of eqs. 4-8 decides exactly as the dense one did:
run it before and after a change and compare the JSON files (``--compare OLD.json``). Bus islands before
and after the repair, the cut and the error text of a refused grouping are recorded; eigenvalues and beta
are recorded too but compared to a relative tolerance only.

Usage:  .venv/bin/python tools/record_spectral_decisions.py OUT.json [--compare OLD.json] [--skip-large]
                                                              [--spectral-module FILE.py]
(--spectral-module: record with another version of core/spectral.py, e.g. `git show HEAD~3:controlled_islanding/
core/spectral.py > /tmp/old_spectral.py`; the results are written as each case finishes.)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from controlled_islanding.core.grid import Grid  # noqa: E402
from controlled_islanding.core.islanding import evaluate_partition  # noqa: E402
from controlled_islanding.core.spectral import ConstrainedSpectralPartition, SpectralError  # noqa: E402
from controlled_islanding.harness.benchmarks import case_path, regional_groups  # noqa: E402

PAPER = {
    'case1': (['16-17', '1-2'], [[30, 37, 38], [31, 32, 33, 34, 35, 36, 39]]),
    'case2': (['13-14', '16-17'], [[33, 34, 35, 36], [30, 31, 32, 37, 38, 39]]),
}


def record(grid: Grid, groups: dict[str, int], beta: float = 0.2) -> dict:
    """Return the partition's outcome as plain JSON data."""
    t0 = time.perf_counter()
    try:
        part = ConstrainedSpectralPartition(beta=beta).fit(grid, groups)
    except SpectralError as exc:
        return {'error': str(exc), 'seconds': time.perf_counter() - t0}
    seconds = time.perf_counter() - t0
    d = evaluate_partition(grid, {b: int(i) for b, i in zip(grid.buses, part.labels_, strict=True)})
    return {'labels': part.labels_.tolist(), 'relaxed': part.relaxed_labels_.tolist(),
            'eigenvalues': [float(x) for x in part.eigenvalues_], 'beta': float(part.beta_),
            'cut': sorted(d.cut_branch_ids), 'disrupted_mw': round(d.disrupted_mw, 6), 'seconds': seconds}


def sized_groups(grid: Grid, sizes: list[int]) -> dict[str, int]:
    """Group generator buses in bus-number order into groups of the given sizes (in buses)."""
    buses = sorted({g.bus for g in grid.generators})
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    at = {b: k for k in range(len(bounds) - 1) for b in buses[bounds[k]:bounds[k + 1]]}
    return {g.name: at[g.bus] for g in grid.generators}


def cases(skip_large: bool):
    """Yield (name, grid, groups, beta)."""
    from controlled_islanding.wire.bagdata import load_bag

    for entry in yaml.safe_load((REPO / 'bags' / 'index.yaml').read_text())['bags']:
        path = REPO / 'bags' / entry['bag']
        if not path.exists():
            continue
        bag = load_bag(path)
        grid = bag.grid.with_outages(entry['tripped_before_request'])
        groups = {n: k for k, names in enumerate(entry['truth_groups']) for n in names}
        if len(set(groups.values())) > 1:
            yield f'bag {entry["name"]}', grid, groups, 0.2
    ieee39 = Grid.from_matpower('ieee39')
    for case, (outages, bus_groups) in PAPER.items():
        at = {g.bus: g.name for g in ieee39.generators}
        groups = {at[b]: k for k, grp in enumerate(bus_groups) for b in grp}
        yield f'paper {case} pre-outage flows', ieee39.with_flows().with_outages(outages), groups, 0.2
        yield f'paper {case} post-outage flows', ieee39.with_outages(outages).with_flows(), groups, 0.2
        for beta in (0.05, 0.125, 0.3, 0.5, 0.9):
            yield f'paper {case} pre-outage flows beta {beta}', ieee39.with_flows().with_outages(outages), groups, beta
    grid = ieee39.with_flows().with_outages(PAPER['case1'][0])
    at = {g.bus: g.name for g in grid.generators}
    three = {at[b]: k for k, grp in enumerate([[30, 37, 38], [33, 34, 35, 36], [31, 32, 39]]) for b in grp}
    yield 'case39 three groups', grid, three, 0.2
    names = ['case14', 'case30', 'case57', 'case118', 'case300', 'case1354pegase', 'GBnetwork', 'case2869pegase']
    for name in names:
        if skip_large and name in ('case1354pegase', 'GBnetwork', 'case2869pegase'):
            continue
        path = case_path(name)
        if path is None:
            print(f'{name}: not available, skipped', file=sys.stderr)
            continue
        grid = Grid.from_matpower(path).with_flows()
        for k in (2, 3, 4):
            yield f'{name} k={k} regional', grid, regional_groups(grid, k), 0.2
        if name == 'GBnetwork':
            n = len({g.bus for g in grid.generators})
            yield f'{name} unequal groups', grid, sized_groups(grid, [n - 101, 98, 1, 2]), 0.2


def main() -> int:
    """Record, and compare when asked; exit 1 if a decision differs."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('out', type=Path)
    parser.add_argument('--compare', type=Path)
    parser.add_argument('--skip-large', action='store_true')
    parser.add_argument('--spectral-module', type=Path)
    args = parser.parse_args()
    if args.spectral_module:
        import importlib.util

        global ConstrainedSpectralPartition, SpectralError
        spec = importlib.util.spec_from_file_location('other_spectral', args.spectral_module)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        ConstrainedSpectralPartition, SpectralError = module.ConstrainedSpectralPartition, module.SpectralError
    out = {}
    for name, grid, groups, beta in cases(args.skip_large):
        out[name] = record(grid, groups, beta)
        r = out[name]
        print(f'{name}: {r.get("error") or "cut " + ", ".join(r["cut"])[:80]} ({r["seconds"]:.3f} s)', flush=True)
        args.out.write_text(json.dumps(out, indent=1))
    if args.compare is None:
        return 0
    old = json.loads(args.compare.read_text())
    bad = 0
    for name, new in out.items():
        if name not in old:
            print(f'NEW  {name}')
            continue
        was = old[name]
        same = all(was.get(key) == new.get(key) for key in ('labels', 'relaxed', 'cut', 'disrupted_mw'))
        same &= ('error' in was) == ('error' in new)
        close = np.allclose(was.get('eigenvalues', []), new.get('eigenvalues', []), rtol=1e-6, atol=0) and \
            np.isclose(was.get('beta', 0), new.get('beta', 0), rtol=1e-9)
        if not same:
            bad += 1
        print(f'{"SAME" if same else "DIFF"} {"" if close else "(eigenvalues/beta differ) "}{name}: '
              f'{was.get("seconds", 0):.3f} s -> {new.get("seconds", 0):.3f} s'
              + (f'\n     was: {was.get("error", "")}\n     now: {new.get("error", "")}' if 'error' in was or
                 'error' in new else ''))
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
