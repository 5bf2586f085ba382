"""`controlled-islanding bench`: time the DTW distance matrix against dtaidistance, and the whole core on IEEE 39."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from controlled_islanding.cli import CliError

HELP = 'benchmark: DTW distance matrix against dtaidistance, and the core pipeline on IEEE 39'

DESCRIPTION = """\
Print, in one run:
  1. the DTW distance-matrix time of controlled_islanding.core.dtw against dtaidistance's own C
     distance_matrix_fast (its defaults) on the same data, as a ratio (> 1: ours is faster), for
     10 series of 600 samples and 400 series of 180 samples, and the largest relative difference
     of the values (dtaidistance's result squared, as it returns the square root of eq. 3);
  2. the time of the core from rotor angles to decision on IEEE 39 with 4 s of 60 fps data:
     DTW coherency (band 30 samples = 0.5 s as config/coherency.yaml, and 15) plus the islanding decision
     (constrained spectral partition, repair, cut set, balance). The angles and the grid come from the
     first scenario bag in bags/index.yaml that has a split, else from synthetic swings on MATPOWER case39;
  3. the rotor angle estimation error against the simulator's truth on every bag without impairments.

Figures are wall-clock medians (and best) over --repeat runs; the machine's load affects them.
Example:  controlled-islanding bench --quick
"""

SIZES = ((10, 600), (400, 180))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the bench options."""
    parser.add_argument('--repeat', type=int, default=3, help='runs per timing; the large DTW case runs once '
                        'fewer (default 3)')
    parser.add_argument('--quick', action='store_true', help='skip the 400 x 180 DTW case (about a minute)')
    parser.add_argument('--bags', type=Path, default=Path('bags'), help='bag directory with index.yaml (default bags)')


def _time(fn: Callable[[], object], repeat: int) -> tuple[float, float, object]:
    """Return (median s, best s, last result) over repeat calls, after one warm-up call."""
    result = fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(min(times)), result


def _time_interleaved(fns: list[Callable[[], object]], repeat: int) -> tuple[list[float], list[object]]:
    """Return the median s of each function and its last result, calling them in turn repeat times."""
    results = [fn() for fn in fns]
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeat):
        for k, fn in enumerate(fns):
            t0 = time.perf_counter()
            results[k] = fn()
            times[k].append(time.perf_counter() - t0)
    return [float(np.median(t)) for t in times], results


def _swing_series(n: int, length: int, seed: int) -> list[np.ndarray]:
    """Rotor-angle-like series (rad): damped swings on a random walk, one per generator."""
    rng = np.random.default_rng(seed)
    t = np.arange(length) / 60.0
    return [np.cumsum(rng.normal(0, 0.01, length)) + rng.uniform(0.1, 0.5) * np.sin(2 * np.pi * rng.uniform(0.5, 1.5)
                                                                                  * t + rng.uniform(0, 6))
            for _ in range(n)]


def bench_dtw(quick: bool, repeat: int) -> None:
    """Print the DTW distance-matrix comparison."""
    from dtaidistance import dtw as dtai

    from controlled_islanding.core.dtw import dtw_distance_matrix

    print('DTW distance matrix (eq. 3, no window), ours vs dtaidistance.dtw.distance_matrix_fast:')
    print('  ratio = dtaidistance time / ours (> 1: ours faster); par = OpenMP over pairs, dtaidistance default')
    print(f'  {"series x samples":>17} {"ours s":>9} {"ours par s":>10} {"dtai s":>9} {"ratio":>6} {"ratio par":>9} '
          f'{"max rel diff":>12}')
    for n, length in SIZES:
        if quick and n > 100:
            continue
        reps = max(1, repeat - 1) if n > 100 else repeat
        sys.stdout.flush()
        print(f'  timing {n} x {length} ...', file=sys.stderr, flush=True)
        series = _swing_series(n, length, seed=n)
        # Interleaved, so a change in the machine's load hits all three alike.
        (ours, par, base), (d_ours, _, d_base) = _time_interleaved(
            [lambda s=series: dtw_distance_matrix(s), lambda s=series: dtw_distance_matrix(s, parallel=True),
             lambda s=series: dtai.distance_matrix_fast(s)], reps)
        ref = np.asarray(d_base) ** 2
        off = ~np.eye(n, dtype=bool)
        rel = float(np.max(np.abs(d_ours[off] - ref[off]) / np.maximum(ref[off], 1e-300)))
        print(f'  {f"{n} x {length}":>17} {ours:>9.4f} {par:>10.4f} {base:>9.4f} {base / ours:>6.2f} '
              f'{base / par:>9.2f} {rel:>12.2e}')


def _bag_case(bags: Path):
    """Return (label, grid with trips, rotor angle series) from the first split bag, or None."""
    import yaml

    from controlled_islanding.bagdata import load_bag
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad

    index = bags / 'index.yaml'
    if not index.exists():
        return None
    for entry in yaml.safe_load(index.read_text()).get('bags', []):
        if entry.get('synchronous', True) or not (bags / entry['bag']).exists():
            continue
        bag = load_bag(bags / entry['bag'])
        request = float(bag.request_t_s[0])
        rows = (bag.frame_t_s >= request - 4.0) & (bag.frame_t_s < request)
        col = {int(b): k for k, b in enumerate(bag.pmu_buses)}
        gens = bag.grid.generators
        cols = [col[g.bus] for g in gens]

        def estimate(rows=rows, cols=cols, bag=bag, gens=gens):
            return estimate_rotor_angle_rad(
                bag.v_mag_pu[np.ix_(rows, cols)], bag.v_angle_rad[np.ix_(rows, cols)],
                bag.i_mag_pu[np.ix_(rows, cols)], bag.i_angle_rad[np.ix_(rows, cols)],
                np.array([g.xq_pu for g in gens]), np.array([g.ra_pu for g in gens]))
        return f'bag {entry["name"]}', bag.grid_at(request), estimate
    return None


def bench_pipeline(bags: Path, repeat: int) -> None:
    """Print the core pipeline timing on IEEE 39."""
    from controlled_islanding.core.coherency import DTWCoherency
    from controlled_islanding.core.grid import Grid
    from controlled_islanding.core.islanding import decide

    case = _bag_case(bags)
    if case is None:
        grid = Grid.from_matpower('ieee39').with_flows().with_outages(['16-17', '1-2'])
        slip = {g.name for g in grid.generators if g.bus in (30, 37, 38)}
        base = _swing_series(len(grid.generators), 240, seed=1)
        t = np.arange(240) / 60.0
        angles = np.array([s + (t ** 2 if g.name in slip else 0.0) for s, g in zip(base, grid.generators,
                                                                                    strict=True)]).T
        label = 'synthetic swings on MATPOWER case39, G1/G8/G9 slipping, outages 16-17 and 1-2'

        def estimate():
            return angles
    else:
        label, grid, estimate = case
    angles = estimate()
    names = [g.name for g in grid.generators]

    reps = max(repeat, 20)
    t_est, _, _ = _time(estimate, reps)
    print(f'Core pipeline on IEEE 39 ({label}), {angles.shape[0]} samples x {angles.shape[1]} generators, '
          f'median (best) of {reps}:')
    print(f'  rotor angle estimation   {t_est * 1e3:8.3f} ms   (before the pipeline: PMU phasors -> angles)')
    for band in (30, 15):
        def pipeline(band=band):
            model = DTWCoherency(window=band).fit(list(angles.T))
            return model, decide(grid, dict(zip(names, model.labels_.tolist(), strict=True)))

        t_coh, b_coh, model = _time(lambda band=band: DTWCoherency(window=band).fit(list(angles.T)), reps)
        groups = dict(zip(names, model.labels_.tolist(), strict=True))
        t_dec, b_dec, _ = _time(lambda groups=groups: decide(grid, groups), reps)
        t_all, b_all, (model, decision) = _time(pipeline, reps)
        print(f'  DTW band {band} samples ({band / 60:.2f} s at 60 fps):')
        print(f'    DTW coherency            {t_coh * 1e3:8.3f} ms ({b_coh * 1e3:.3f})')
        print(f'    islanding decision       {t_dec * 1e3:8.3f} ms ({b_dec * 1e3:.3f})')
        print(f'    rotor angles -> decision {t_all * 1e3:8.3f} ms ({b_all * 1e3:.3f})   target < 5 ms')
        groups_txt = ' | '.join(','.join(n for n, g in zip(names, model.labels_, strict=True) if g == k)
                                for k in range(model.n_groups_))
        print(f'    groups: {groups_txt}; cut: {", ".join(decision.cut_branch_ids) or "none"}; '
              f'disrupted {decision.disrupted_mw:.1f} MW')


def bench_rotor_angle_error(bags: Path) -> None:
    """Print the rotor angle estimation error against the simulator's truth on every bag without impairments."""
    import yaml

    from controlled_islanding.bagdata import load_bag
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad

    index = bags / 'index.yaml'
    if not index.exists():
        print('Rotor angle error: no bags/index.yaml')
        return
    print('Rotor angle estimation error |angle(V + (ra + j xq) I) - ANDES delta|, deg, p50 / p99 / max:')
    print(f'  {"bag":<30} {"before the first event":>24} {"after it":>24}')
    for entry in yaml.safe_load(index.read_text()).get('bags', []):
        if entry.get('impairments') or not (bags / entry['bag']).exists():
            continue
        bag = load_bag(bags / entry['bag'])
        col = {int(b): k for k, b in enumerate(bag.pmu_buses)}
        gens = bag.grid.generators
        cols = [col[g.bus] for g in gens]
        est = estimate_rotor_angle_rad(bag.v_mag_pu[:, cols], bag.v_angle_rad[:, cols], bag.i_mag_pu[:, cols],
                                       bag.i_angle_rad[:, cols], np.array([g.xq_pu for g in gens]),
                                       np.array([g.ra_pu for g in gens]))
        truth = np.column_stack([np.interp(bag.frame_t_s, bag.truth_t_s,
                                           bag.truth_angles_rad[:, bag.truth_generator_names.index(g.name)])
                                 for g in gens])
        err = np.degrees(np.abs(np.angle(np.exp(1j * (est - truth)))))
        # The first fault starts before the first trip; half a second covers the bags' faults.
        first = min([e.t_s for e in bag.branch_events] + [float(bag.frame_t_s[-1])]) - 0.5
        before = bag.frame_t_s < first
        cells = []
        for part in (err[before], err[~before]):
            part = part[~np.isnan(part)]
            cells.append(' / '.join(f'{v:.2f}' for v in (np.percentile(part, 50), np.percentile(part, 99),
                                                           part.max())) if part.size else 'n/a')
        print(f'  {entry["name"]:<30} {cells[0]:>24} {cells[1]:>24}')


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and print the figures."""
    if args.repeat < 1:
        raise CliError(f'--repeat must be >= 1, got {args.repeat}')
    bench_dtw(args.quick, args.repeat)
    print(flush=True)
    bench_pipeline(args.bags, args.repeat)
    print()
    bench_rotor_angle_error(args.bags)
    return 0
