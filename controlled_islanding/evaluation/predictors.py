"""The stability predictors of core/stability.py compared on scenarios, offline, on the DSE's angles and speeds.

For every scenario (a bag of bags/, or a scenario YAML simulated here in ANDES), the PMU frames go through what
pmu_ingestion runs, in delivery order: core/bad_data.py's detector (a suspect station's generator is invalid)
and core/dse.py's StreamingDSE (angles and speeds of every machine, the filter's nominal frequency taken from the
PMUs' own reported frequency). Each predictor then takes the frames in time-tag order, as the monitor node will,
with each machine's measured electrical power Re(V I*) and terminal voltage from its own PMU channel.

Measured per predictor and scenario:
- the alarm: the first frame after which the predictor says ``separates_``, at that frame's delivery time;
- the lead: the first pole slip (sim/truth.py, the simulator's own angles) minus the alarm, s (> 0: in time);
- false alarms: an alarm on a run that stays one group;
- the groups at the alarm against the final grouping (sim/truth.py: the truth rule of the manifest).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from controlled_islanding.core.stability import TIME_TO_ACT_S

_FIELDS = ('v_mag_pu', 'v_angle_rad', 'i_mag_pu', 'i_angle_rad', 'frequency_hz', 'rocof_hz_per_s')


class PredictionStudyError(ValueError):
    """A scenario that cannot be studied (no PMU for a generator, a failed simulation)."""


@dataclass
class MonitorInputs:
    """What the monitor node would read over a run, one row per frame in time-tag order.

    Attributes:
        name: Scenario name.
        source: Where it came from (bag path, or 'ANDES <scenario file>').
        generator_names: One per column.
        t_s: Time tags, s, increasing.
        delivery_s: When each frame reached the PDC, s.
        delta_rad: The filter's rotor angles, rad, (n_frames, n_gen), NaN where none.
        omega_pu: The filter's speeds, pu.
        tm_pu: The filter's mechanical torques, pu on the system base.
        pe_pu: Measured Re(V I*), pu on the system base, NaN where the channel was lost or suspect.
        v_pu: Measured terminal voltage magnitude, pu, NaN where lost or suspect.
        valid: Whether each machine's estimate had usable data in the frame.
        freq_hz: Nominal frequency the filter ran at, Hz.
        grid: The network snapshot (machine data, dispatch).
        truth: Generator name -> final group (sim/truth.py).
        first_pole_slip_s: First time two machines are more than pi rad apart, s; None if never.
        scenario_request_s: The scenario's own fixed islanding request time, s.

    """

    name: str
    source: str
    generator_names: list[str]
    t_s: np.ndarray
    delivery_s: np.ndarray
    delta_rad: np.ndarray
    omega_pu: np.ndarray
    tm_pu: np.ndarray
    pe_pu: np.ndarray
    v_pu: np.ndarray
    valid: np.ndarray
    freq_hz: float
    grid: object
    truth: dict[str, int]
    first_pole_slip_s: float | None
    scenario_request_s: float
    clearings_s: tuple[float, ...] = ()
    notes: list[str] = field(default_factory=list)

    @property
    def truth_k(self) -> int:
        """Return the number of final groups."""
        return len(set(self.truth.values()))


def _columns(station_ids: Sequence[str], buses, generators) -> list[int]:
    """Each generator's PMU channel: its own ('<station>/<name>') if it has one, else its bus's."""
    buses = np.asarray(buses)
    out = []
    for g in generators:
        own = [j for j, s in enumerate(station_ids) if '/' in s and s.rpartition('/')[2] == g.name]
        at_bus = np.flatnonzero(buses == g.bus)
        if not own and not len(at_bus):
            raise PredictionStudyError(f'no PMU at bus {g.bus} of generator {g.name}')
        out.append(own[0] if own else int(at_bus[0]))
    return out


@dataclass
class ScenarioRun:
    """One scenario's PMU channels over the whole run, its network snapshot and its truth.

    Attributes:
        name, source: Scenario name; bag path or 'ANDES <scenario file>'.
        channels: PmuChannels with a leading time axis (a BagData, or sim.pmu.measure's PmuData).
        frame_present: Whether each time tag's frame exists.
        rate_fps: PMU reporting rate, frames/s.
        grid: The pre-fault network snapshot (core.grid.Grid, machine data and dispatch).
        truth: Generator name -> final group (sim/truth.py).
        first_pole_slip_s: First time two machines are more than pi rad apart, s; None if never.
        request_s: The scenario's own fixed islanding request, s.
        end_s: The last time tag, s.
        clearings_s: When the scenario's faults clear, s (from its YAML; empty when unknown).

    """

    name: str
    source: str
    channels: object
    frame_present: np.ndarray
    rate_fps: float
    grid: object
    truth: dict[str, int]
    first_pole_slip_s: float | None
    request_s: float
    end_s: float
    clearings_s: tuple[float, ...] = ()


def monitor_inputs(run: ScenarioRun) -> MonitorInputs:
    """Run a scenario's PMU channels through pmu_ingestion's core, offline, and return what the monitor reads.

    Frames are taken in delivery order, as the node takes them: bad-data tests first, then the streaming filter,
    which answers each frame at once (ahead of a missing tag from a copy of the filter, a late frame
    interpolated). The rows returned are those answers, sorted by time tag, late duplicates of a tag dropped.
    """
    from controlled_islanding.core.bad_data import BadDataDetector
    from controlled_islanding.core.dse import DSEError, MachineData, StreamingDSE, nominal_hz

    channels, gens = run.channels, run.grid.generators
    try:
        cols = _columns(channels.station_ids, channels.buses, gens)
        f0 = nominal_hz(channels.frequency_hz)
    except (PredictionStudyError, DSEError) as exc:
        raise PredictionStudyError(f'{run.source}: {exc}; a predictor needs every generator') from None
    stream = StreamingDSE(MachineData.of_generators(gens), run.rate_fps, 0.1, history_s=1.0, freq_hz=f0)
    detector = BadDataDetector()
    buses = np.asarray(channels.buses)
    angles_at_rest = run.grid.bus_angles_at(buses)
    station_of = [channels.station_ids[c] for c in cols]
    present = np.flatnonzero(np.asarray(run.frame_present))
    order = present[np.argsort(np.asarray(channels.delivery_s)[present], kind='stable')]
    rows: dict[float, tuple] = {}
    flagged: set[str] = set()
    stat = np.asarray(channels.stat)
    for k in order:
        t = float(channels.tag_s[k])
        values = [np.asarray(getattr(channels, f))[k] for f in _FIELDS]
        usable = np.isfinite(values[0]) & np.isfinite(values[2]) & ((stat[k] & 0x8000) == 0)
        idx = np.flatnonzero(usable)
        suspects = detector.judge(t, [channels.station_ids[j] for j in idx], *(v[idx] for v in values),
                                  buses=buses[idx], bus_angle_rad=angles_at_rest[idx], nominal_hz=f0) \
            if idx.size else detector.suspects()
        flagged |= set(suspects)
        bad = np.array([s in suspects for s in station_of])
        ok = usable[cols] & ~bad
        v = np.where(ok, values[0][cols], np.nan)
        i = np.where(ok, values[2][cols], np.nan)
        angles = stream.offer(t, v, values[1][cols], i, values[3][cols], ok)
        if t in rows:
            continue
        pe = (v * np.exp(1j * values[1][cols]) * np.conj(i * np.exp(1j * values[3][cols]))).real
        rows[t] = (float(channels.delivery_s[k]), angles, stream.omega_pu_.copy(), stream.tm_pu_.copy(), pe, v,
                   ok & np.isfinite(angles))
    tags = np.array(sorted(rows))
    pick = [rows[t] for t in tags]
    notes = [f'stations flagged as suspect data: {", ".join(sorted(flagged))}'] if flagged else []
    col = [np.array([p[j] for p in pick]) for j in range(7)]
    return MonitorInputs(name=run.name, source=run.source, generator_names=[g.name for g in gens], t_s=tags,
                         delivery_s=col[0], delta_rad=col[1], omega_pu=col[2], tm_pu=col[3], pe_pu=col[4],
                         v_pu=col[5], valid=col[6], freq_hz=f0, grid=run.grid, truth=run.truth,
                         first_pole_slip_s=run.first_pole_slip_s, scenario_request_s=run.request_s,
                         clearings_s=run.clearings_s, notes=notes)


def run_from_bag(path: str | Path) -> ScenarioRun:
    """Return a bag's run; truth and first pole slip from the manifest beside it, else the bag's own angles."""
    from controlled_islanding.sim.manifest import entry_for_bag
    from controlled_islanding.sim.truth import first_pole_slip_s, truth_groups
    from controlled_islanding.wire.bagdata import BagDataError, load_bag

    try:
        bag = load_bag(path)
    except BagDataError as exc:
        raise PredictionStudyError(str(exc)) from exc
    entry = entry_for_bag(bag.path) or {}
    if entry.get('truth_groups'):
        truth = {n: k for k, members in enumerate(entry['truth_groups']) for n in members}
        slip = entry.get('first_pole_slip_s')
    else:
        labels = truth_groups(bag.truth_t_s, bag.truth_angles_rad)
        truth = {n: int(k) for n, k in zip(bag.truth_generator_names, labels, strict=True)}
        slip = first_pole_slip_s(bag.truth_t_s, bag.truth_angles_rad)
    request = float(bag.request_t_s[0]) if len(bag.request_t_s) else math.nan
    return ScenarioRun(bag.path.name, str(bag.path), bag, np.asarray(bag.frame_present), bag.rate_fps, bag.grid,
                       truth, None if slip is None else float(slip), request, float(bag.tag_s[-1]),
                       _clearings(bag.path.parent / str(entry.get('scenario', f'{bag.path.name}.yaml'))))


def run_from_scenario(path: str | Path) -> ScenarioRun:
    """Simulate a scenario YAML in ANDES and measure it as its PMUs would (sim/pmu.py); truth by sim/truth.py."""
    scenario, sim = simulate_scenario(path)
    return measured_run(scenario, sim, path)


def simulate_scenario(path: str | Path):
    """Return (scenario, ANDES simulation) of a scenario YAML."""
    from controlled_islanding.sim.andes_sim import SimulationError, simulate
    from controlled_islanding.sim.scenario import ScenarioError, load_scenario

    try:
        scenario = load_scenario(path)
        return scenario, simulate(scenario, progress=False)
    except (ScenarioError, SimulationError) as exc:
        raise PredictionStudyError(f'{path}: {exc}') from exc


def measured_run(scenario, sim, path: str | Path, seed: int | None = None) -> ScenarioRun:
    """Return a simulation measured as the scenario's PMUs would, under its own seed or `seed` (noise, impairments)."""
    from controlled_islanding.sim.pmu import measure
    from controlled_islanding.sim.truth import first_pole_slip_s, truth_groups

    if seed is not None:
        scenario = replace(scenario, seed=int(seed))
    data = measure(sim, scenario)
    labels = truth_groups(data.tag_s, data.truth_delta_rad)
    truth = {n: int(k) for n, k in zip(sim.generator_names, labels, strict=True)}
    return ScenarioRun(scenario.name, f'ANDES {Path(path)}', data, np.asarray(data.frame_present),
                       float(scenario.rate_fps), sim.grid, truth, first_pole_slip_s(data.tag_s, data.truth_delta_rad),
                       scenario.request_s, float(data.tag_s[-1]), tuple(f.clear_s for f in scenario.faults))


def _clearings(path: Path) -> tuple[float, ...]:
    """Return when the faults of the scenario YAML at path clear, s (empty when there is no such file)."""
    from controlled_islanding.sim.scenario import ScenarioError, load_scenario

    try:
        return tuple(f.clear_s for f in load_scenario(path).faults) if path.is_file() else ()
    except ScenarioError:
        return ()


class SeparationRuleMonitor:
    """Today's rule as a monitor, for comparison.

    The coherency node's separation rule (core/k_rules.py) on the window of DSE angles that ends at a frame,
    every ``period_s`` of time tags (the node's own periodic recompute, config/coherency.yaml); it alarms when
    it splits. It names no slip time.
    """

    def __init__(self, names: Sequence[str], *, window_s: float, period_s: float, max_groups: int,
                 dtw_band: int | None, min_samples: int) -> None:
        self.names, self.window_s, self.period_s = list(names), window_s, period_s
        self.max_groups, self.dtw_band, self.min_samples = max_groups, dtw_band, min_samples
        self.rows: list[tuple[float, np.ndarray]] = []
        self.next_s = -math.inf
        self.separates_, self.groups_, self.first_slip_s_ = False, np.zeros(len(names), dtype=int), math.nan

    def update(self, t_s, delta_rad, omega_pu, pe_pu, v_pu=None, valid=None, pm_pu=None):
        """Take one frame (as core/stability.py's predictors); judge the window every period_s."""
        from controlled_islanding.core.coherency import CoherencyError, DTWCoherency

        t = float(t_s)
        self.rows.append((t, np.where(np.asarray(valid, dtype=bool), delta_rad, np.nan)))
        self.rows = [r for r in self.rows if r[0] >= t - self.window_s - 1e-9]
        if t < self.next_s or len(self.rows) < self.min_samples:
            return self
        self.next_s = t + self.period_s - 1e-9
        block = np.array([r[1] for r in self.rows]).T
        try:
            labels = DTWCoherency(max_groups=self.max_groups, window=self.dtw_band).fit(list(block)).labels_
        except (CoherencyError, ValueError):
            return self
        self.groups_ = np.asarray(labels, dtype=int)
        self.separates_ = bool(self.groups_.max() > 0)
        return self


def make_predictor(name: str, inputs: MonitorInputs):
    """Return a fresh predictor of that name for one scenario (PREDICTORS)."""
    from controlled_islanding.core.stability import MachineSet, SIMEPredictor
    from controlled_islanding.core.swing_forecast import ForecastPredictor
    from controlled_islanding.evaluation.cases import coherency_node_parameters

    machines = MachineSet.of_grid(inputs.grid, inputs.freq_hz)
    if name == 'sime':
        return SIMEPredictor(machines)
    if name == 'forecast':
        return ForecastPredictor(machines)
    if name == 'separation rule':
        node = coherency_node_parameters()
        band = int(node.get('dtw_band_samples', 30)) or None
        return SeparationRuleMonitor(inputs.generator_names, window_s=float(node.get('window_s', 3.0)),
                                     period_s=float(node.get('period_s', 0.2)),
                                     max_groups=int(node.get('max_groups', 8)), dtw_band=band,
                                     min_samples=int(node.get('min_samples', 30)))
    raise PredictionStudyError(f'unknown predictor {name!r}; known: {list(PREDICTORS)}')


PREDICTORS = ('sime', 'forecast', 'separation rule')


@dataclass
class Outcome:
    """One predictor on one scenario.

    Attributes:
        alarm_s: Delivery time of the frame after which the predictor first said separates_, s (None: never).
        groups: Generator name -> group at the alarm (None: no alarm).
        predicted_slip_s: The first pole slip the predictor named at the alarm, s (None: none).
        cpu_ms_per_frame: Mean CPU time of one update, ms.

    """

    alarm_s: float | None = None
    groups: dict[str, int] | None = None
    predicted_slip_s: float | None = None
    cpu_ms_per_frame: float = math.nan


def run_predictor(inputs: MonitorInputs, predictor) -> Outcome:
    """Feed a fresh predictor every frame in time-tag order; record its first alarm."""
    import time

    out = Outcome()
    cpu, frames = 0.0, 0
    for k in range(len(inputs.t_s)):
        start = time.process_time()
        predictor.update(inputs.t_s[k], inputs.delta_rad[k], inputs.omega_pu[k], inputs.pe_pu[k], inputs.v_pu[k],
                         inputs.valid[k], inputs.tm_pu[k])
        cpu += time.process_time() - start
        frames += 1
        if predictor.separates_:
            out.alarm_s = float(inputs.delivery_s[k])
            out.groups = {n: int(g) for n, g in zip(inputs.generator_names, predictor.groups_, strict=True)}
            slip = float(predictor.first_slip_s_)
            out.predicted_slip_s = slip if math.isfinite(slip) else None
            break
    out.cpu_ms_per_frame = 1e3 * cpu / max(frames, 1)
    return out


@dataclass
class ScenarioResult:
    """Every predictor on one scenario."""

    inputs: MonitorInputs
    system: str
    outcomes: dict[str, Outcome]

    def lead_s(self, name: str) -> float | None:
        """First pole slip minus the alarm, s (None: no alarm, or a run that stays one group)."""
        o, slip = self.outcomes[name], self.inputs.first_pole_slip_s
        return None if o.alarm_s is None or slip is None else slip - o.alarm_s

    def groups_right(self, name: str) -> bool:
        """Whether the groups at the alarm are the final grouping."""
        from controlled_islanding.evaluation.coherency_rules import blocks

        o = self.outcomes[name]
        return o.groups is not None and blocks(o.groups) == blocks(self.inputs.truth)


def study(run: ScenarioRun, names: Sequence[str] = PREDICTORS) -> ScenarioResult:
    """Every predictor on one scenario run."""
    inputs = monitor_inputs(run)
    return ScenarioResult(inputs, str(run.grid.name), {n: run_predictor(inputs, make_predictor(n, inputs))
                                                       for n in names})


@dataclass
class Score:
    """One predictor over every scenario."""

    stable: int = 0
    quiet: int = 0
    unstable: int = 0
    in_time: int = 0
    right_in_time: int = 0
    right_to_act: int = 0
    leads_s: list[float] = field(default_factory=list)
    cpu_ms: list[float] = field(default_factory=list)


def score(results: Sequence[ScenarioResult], name: str) -> Score:
    """Count a predictor's quiet stable runs, alarms before the first pole slip, and right groups among them."""
    out = Score()
    for r in results:
        out.cpu_ms.append(r.outcomes[name].cpu_ms_per_frame)
        if r.inputs.truth_k == 1:
            out.stable += 1
            out.quiet += r.outcomes[name].alarm_s is None
            continue
        out.unstable += 1
        lead = r.lead_s(name)
        if lead is not None and lead > 0:
            out.in_time += 1
            out.leads_s.append(lead)
            out.right_in_time += r.groups_right(name)
            out.right_to_act += r.groups_right(name) and lead >= TIME_TO_ACT_S - 1e-9
    return out


def _cell(r: ScenarioResult, name: str) -> str:
    o = r.outcomes[name]
    if r.inputs.truth_k == 1:
        return 'quiet' if o.alarm_s is None else f'FALSE ALARM {o.alarm_s:.2f}'
    if o.alarm_s is None:
        return 'no alarm'
    lead = r.lead_s(name)
    k = len(set(o.groups.values()))
    when = f'{o.alarm_s:.2f}, lead {lead:+.2f}' if lead is not None else f'{o.alarm_s:.2f}'
    return f'{when}, k={k} {"right" if r.groups_right(name) else "WRONG"}'


def report(results: Sequence[ScenarioResult], names: Sequence[str] = PREDICTORS, run: str = '') -> list[str]:
    """Return the figures and the per-scenario table, as Markdown lines (run: the run's wall time and load)."""
    cases = sorted({r.system for r in results})
    lines = [f'{len(results)} runs on {len(cases)} case files ({", ".join(cases)}; one system may come in two '
             f'formats): {sum(r.inputs.truth_k == 1 for r in results)} stay one group, '
             f'{sum(r.inputs.truth_k > 1 for r in results)} separate.'
             + (f' This run: {run}.' if run else ''), '',
             '| predictor | stable runs quiet | unstable runs alarmed before the first slip | ... with the final '
             f'groups | ... and at least {TIME_TO_ACT_S:g} s before | lead, s: median (least) | CPU per frame, ms: '
             'median (most) |', '|---|---|---|---|---|---|---|']
    for name in names:
        sc = score(results, name)
        leads = (f'{np.median(sc.leads_s):.2f} ({min(sc.leads_s):.2f})' if sc.leads_s else '-')
        cpu = np.asarray(sc.cpu_ms, dtype=float)
        lines.append(f'| {name} | {sc.quiet} / {sc.stable} | {sc.in_time} / {sc.unstable} | '
                     f'{sc.right_in_time} / {sc.unstable} | {sc.right_to_act} / {sc.unstable} | {leads} | '
                     f'{np.nanmedian(cpu):.2f} ({np.nanmax(cpu):.1f}) |')
    lines += ['', '| scenario | system, f0 | machines | final k | first slip, s | '
              + ' | '.join(f'{n}: alarm, s' for n in names) + ' |', '|---|---|---:|---:|---:|' + '---|' * len(names)]
    names_seen = [r.inputs.name for r in results]
    for r in results:
        slip = r.inputs.first_pole_slip_s
        label = r.inputs.name
        if names_seen.count(label) > 1:  # a bag and a scenario file of one name: say which
            label += f' ({Path(r.inputs.source.removeprefix("ANDES ")).parent.name})'
        lines.append(f'| {label} | {r.system}, {r.inputs.freq_hz:g} Hz | {len(r.inputs.generator_names)} | '
                     f'{r.inputs.truth_k} | {"none" if slip is None else f"{slip:.2f}"} | '
                     + ' | '.join(_cell(r, n) for n in names) + ' |')
    wrong = [(r, n) for r in results for n in names
             if r.inputs.truth_k > 1 and r.outcomes[n].groups is not None and not r.groups_right(n)]
    if wrong:
        lines += ['', 'Groups at the alarm where they differ from the final grouping (machines of the largest '
                  'group left out):', '']
        for r, n in wrong:
            lines.append(f'- {r.inputs.name}, {n}: {_small_groups(r.outcomes[n].groups)}; final '
                         f'{_small_groups(r.inputs.truth)}')
    notes = [f'- {r.inputs.name}: {note}' for r in results for note in r.inputs.notes]
    if notes:
        lines += ['', 'Notes:', '', *notes]
    return lines


def _small_groups(groups: dict[str, int]) -> str:
    """Every group but the largest, as '(a, b) (c)'."""
    members: dict[int, list[str]] = {}
    for n, g in groups.items():
        members.setdefault(g, []).append(n)
    biggest = max(members, key=lambda g: len(members[g]))
    return ' '.join('(' + ', '.join(m) + ')' for g, m in sorted(members.items()) if g != biggest) or '(none)'


INTRO = """\
What issue 30's stability monitor will stand on: each predictor reads, frame by frame, what pmu_ingestion's core
makes of a scenario's PMU frames, offline (`controlled_islanding/evaluation/predictors.py`): core/bad_data.py's
tests, then core/dse.py's StreamingDSE in delivery order, its nominal frequency taken from the PMUs' own reported
frequency (50 Hz for Nordic 44). Each predictor gets the filter's angles, speeds and mechanical torques, each
machine's measured Re(V I*) and terminal voltage, and the snapshot's inertia, damping and dispatch; nothing of the
simulator's. The alarm is the first frame after which a predictor says the grid separates, at that frame's
delivery time; the lead is the first pole slip (two machines more than pi rad apart, `sim/truth.py`, the
simulator's own angles) minus the alarm. The groups at the alarm are compared with the final grouping (the
truth rule of `bags/README.md`). Bags come with `bags/index.yaml`'s truth; the other scenarios are simulated here
from their YAML files (`docs/coherency_rules/`, `docs/prediction/`).

- **sime**: emergency SIME (`core/stability.py`): the critical machines by the widest angular gap, their
  one-machine equivalent's power-angle curve fitted to the swing since the last network switching, and its
  equal-area margin, alarmed at 3 standard errors.
- **forecast**: every machine's swing equation run 1 s ahead from the filter's state (`core/swing_forecast.py`),
  each machine's accelerating power extrapolated from its own swing; alarmed when quadratic and cubic curves
  both slip, with the same groups, within their reach.
- **separation rule**: today's coherency rule (`core/k_rules.py`) on the 3 s window of the filter's angles every
  0.2 s of time tags, as the coherency node recomputes; for comparison.
"""

CHOICE = """\
## The predictor chosen: {chosen}

{reasons}

Runs that separate where neither predictor alarms before the first pole slip:

{missed}

A slip within about 0.1 s of the clearing comes with the machines already past their unstable equilibrium when
the fault clears: a prediction from the faulted network is no prediction, since the monitor cannot know when
protection will clear. SIME judges the first frame after the clearing on its own (core/stability.py, step 10: past
the crest, moving apart and accelerating is past the unstable equilibrium), which names the separation a frame
or two before such a slip; faster, only protection acting on the fault itself (out-of-step tripping) is in time. A
slip on a later swing, after the first has come back (a second swing, or an oscillation that grows), is beyond
the forecast, which judges first swings, and SIME judges a later swing only once it decelerates. And where the
clearing leaves the terminal voltages where the fault held them (the electrical centre of the separation at the
faulted bus), no switching is seen at all, so no swing is judged.

## What the monitor node will need (issue 30, second part)

- `RotorAngles`: the filter's speed (pu) and mechanical torque (pu, system base) per generator, beside the angle
  (core/dse.py's StreamingDSE gives both with every answer, `omega_pu_` and `tm_pu_`), and each generator's
  measured Re(V I*) and terminal voltage magnitude (or the monitor subscribes to /pmu/frames for them).
- `NetworkSnapshot`: the nominal frequency. The filter's omega_base and the predictors' kinetic energy depend on
  it; pmu_ingestion's filter runs at 60 Hz today whatever the grid (on Nordic 44, 50 Hz, its speeds are scaled
  by 5/6). This study takes it from the PMUs' reported frequency.
- `IslandingRequest`: the predicted groups (generator names per group) and the predicted time of the first pole
  slip, signed as the operator's.
"""


def write_report(results: Sequence[ScenarioResult], path, *, command: str, run: str = '',
                 not_evaluated: Sequence[str] = ()) -> None:
    """Write the page (docs/prediction.md): the figures, every scenario, the choice and what the node needs.

    `not_evaluated`: why each scenario that could not be run was not (listed at the end).
    """
    from pathlib import Path as _Path

    from controlled_islanding.atomic import write_text

    chosen = choose(results)
    missed = []
    for r in results:
        if r.inputs.truth_k > 1 and not any((r.lead_s(n) or 0) > 0 for n in ('sime', 'forecast') if n in r.outcomes):
            cleared = [c for c in r.inputs.clearings_s if c <= (r.inputs.first_pole_slip_s or math.inf)]
            after = f'{r.inputs.first_pole_slip_s - cleared[-1]:.2f} s after its last fault cleared' if cleared \
                else 'no fault cleared before it'
            missed.append(f'- {r.inputs.name}: first slip at {r.inputs.first_pole_slip_s:.2f} s, {after}')
    body = ['# Predicting the separation: the stability predictors compared', '',
            f'Generated by `{command}`; do not edit by hand (the text is in '
            '`controlled_islanding/evaluation/predictors.py`).', '', INTRO, '## Figures', '',
            *report(results, run=run), '', CHOICE.format(chosen=chosen, reasons=choice_reasons(results, chosen),
                                                 missed='\n'.join(missed) or '- none'), '']
    if not_evaluated:
        body += ['## Not evaluated', '', *(f'- {why}' for why in not_evaluated), '']
    write_text(_Path(path), '\n'.join(body))


TRAITS = {
    'sime': ('its verdict comes with a standard error, so its bar is a false-alarm rate (3 sigma); its one-machine '
             'equivalent cuts the machines in two at a time, and a machine that swings out with the critical '
             'group and comes back can be named with it'),
    'forecast': ("its groups are sim/truth.py's own rule applied to a forecast of every machine, so any number of "
                 'groups can come out of one forecast; it judges the first swing after a cleared fault only, looks '
                 '1 s ahead, and its confidence is only the agreement of its quadratic and cubic curves'),
}


def choose(results: Sequence[ScenarioResult], names: Sequence[str] = ('sime', 'forecast')) -> str:
    """Return the predictor that names the final groups in time to act on the most separating runs.

    In time to act: at least TIME_TO_ACT_S before the first pole slip (core/stability.py: the breakers' operating
    time and the graph's latency), since a cut asked for later cannot open before the slip. Ties go to the fewer
    false alarms, then to the more right groups before the slip at all, then to the longer median lead.
    """
    def key(name: str) -> tuple:
        sc = score(results, name)
        return (sc.right_to_act, sc.quiet, sc.right_in_time,
                float(np.median(sc.leads_s)) if sc.leads_s else -math.inf)

    return max(names, key=key)


def choice_reasons(results: Sequence[ScenarioResult], chosen: str) -> str:
    """Return the reasons for the choice, with this run's figures."""
    other = 'sime' if chosen == 'forecast' else 'forecast'
    a, b, rule = score(results, chosen), score(results, other), score(results, 'separation rule')

    def lead(sc: Score) -> str:
        return f'{np.median(sc.leads_s):.2f} s' if sc.leads_s else 'none'

    return (f'The rule of choice: the predictor that names the final groups in time to act (at least '
            f"{TIME_TO_ACT_S:g} s before the first pole slip: the breakers' 50 ms and the graph's latency) on the "
            f'most runs that separate, then the fewer false alarms. **{chosen}** does on {a.right_to_act} of '
            f'{a.unstable}, {other} on {b.right_to_act}. Before the slip at all, {chosen} names the final groups '
            f'on {a.right_in_time} and {other} on {b.right_in_time}; {chosen} alarms before the slip on {a.in_time} '
            f'(median lead {lead(a)}), {other} on {b.in_time} (median lead {lead(b)}). Of the {a.stable} runs that '
            f'stay one group, {chosen} stays quiet on {a.quiet} and {other} on {b.quiet}, where the separation rule '
            f'alarms on {rule.stable - rule.quiet}: the predictors answer where the swing ends, the rule where it '
            'is.\n\n'
            f'- {chosen}: {TRAITS[chosen]}.\n- {other}: {TRAITS[other]}.\n\n'
            f'The monitor of the second part should run {chosen}; the other stays in core/ as the comparison, and the '
            'coherency node can call the chosen one on its window (`fit`) so that the request and the decision '
            'agree on the groups.')
