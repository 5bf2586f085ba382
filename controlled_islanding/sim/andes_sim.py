"""Run a scenario's time-domain simulation in ANDES and return plain arrays.

ANDES generates code on first use; it goes to `build/andes_pycode` in the source tree (or
`$CONTROLLED_ISLANDING_BUILD/andes_pycode`), never to the home directory, and `ensure_pycode` generates it in
one process before any case is loaded (tools/setup.sh calls it).

What is returned, on ANDES' own non-uniform time grid:
- bus voltage magnitude (pu) and angle (rad, against the nominal-frequency reference) at every case bus;
- every synchronous generator's rotor angle delta (rad) and terminal P and Q (pu on the system base);
- the pre-fault power flow as a core Grid: branch flows at both ends (MW), generator dispatch, loads;
- the branch status changes of the case's own events that the scenario keeps.

The case is anything ANDES reads (xlsx, json, MATPOWER .m, PSS/E .raw with a .dyr `addfile`). Devices the
scenario disables get u = 0 before setup; disabled synchronous machines are left out of the generators.
Each generator's reactance for the rotor angle estimate is its xq, or x'd for a classical machine (GENCLS),
whose xq ANDES only copies from xd1 when the time-domain run initialises. Each generator also carries its
machine's dynamic data (`machine_rows`), for rotor angle estimation by a Kalman filter (core/dse.py).

PSS/E branch records: their R, X and B are per unit on the case's system base SBASE, but ANDES 2.0.0's PSS/E
parser gives the lines it makes from them no Sn, so ANDES takes them as per unit on 100 MVA and rescales them
to SBASE. With SBASE = 100 MVA (ieee14.raw) nothing changes; with SBASE = 1000 MVA (nordic44's N44_BC.raw)
every line came out 10 times too long and the power flow diverged. `_psse_line_base` sets those lines' Sn to
SBASE before setup; the power flow of N44_BC.raw then converges in 3 iterations.

A run that reaches its end can still be no solution of the grid. At a fault's clearing ANDES' Newton may
converge to a collapsed network: on PJM 5-bus (GENCLS) the buses of two machines in service sat at 1e-17 pu,
every other bus near 0.1 pu, and no machine carried power, for the rest of the run and whichever line cleared
the fault, while clearing the fault alone did not converge at all. No fault was applied by then, so nothing
held those buses down: a machine's EMF behind its reactance drives its terminal, and only the electrical centre
of a slipping pair passes zero, for an instant. `collapsed_at` finds such a solution and `simulate` refuses
it, as it refuses a run that stopped.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controlled_islanding.core.grid import DYNAMIC_FIELDS, Branch, Generator, Grid, Load
from controlled_islanding.locations import build_dir
from controlled_islanding.sim.scenario import Disable, Scenario, ScenarioError

log = logging.getLogger(__name__)

# Synchronous machine models whose devices are the generators (ANDES group SynGen).
_SYNGEN_GROUP = 'SynGen'
_PROGRESS_CHUNK_S = 1.0
_FAULT_REACTANCE_PU = 1e-4
# A collapsed solution (module docstring): a machine's terminal at most this far above 0 pu, with no fault
# applied, for at least this long. A bolted fault through _FAULT_REACTANCE_PU leaves its bus about 1e-3 pu;
# the electrical centre of a slip at f_s Hz stays below 0.01 pu for about 0.01 / (pi f_s) s, 3 ms at 1 Hz.
COLLAPSED_V_PU = 0.01
COLLAPSED_FOR_S = 0.1


class SimulationError(RuntimeError):
    """ANDES failed: the power flow did not converge or the time-domain run stopped early."""


@dataclass(frozen=True)
class Simulation:
    """Raw results of one ANDES run.

    Attributes:
        t_s: Simulation times, s, non-uniform, strictly increasing, shape (nt,).
        freq_hz: System nominal frequency, Hz.
        bus_numbers: Case buses, in case order (helper buses for mid-line faults excluded).
        bus_v_pu: ANDES' voltage variable, pu, shape (nt, n_bus): the magnitude, negative where ANDES carries
            the phasor turned by pi (sim/pmu.py reports |V| and turns the angle).
        bus_angle_rad: Voltage angle, rad, continuous, shape (nt, n_bus).
        generator_names: Synchronous generator names from the case.
        generator_buses: Terminal bus of each generator.
        delta_rad: Rotor angles, rad, continuous, shape (nt, n_gen).
        p_pu: Electrical power out of each generator, pu on the system base, shape (nt, n_gen).
        q_pu: Reactive power out of each generator, pu on the system base, shape (nt, n_gen).
        grid: Pre-fault power flow as a Grid (branch ids and bus numbers from the case).
        branch_ends: Branch id -> (from bus, to bus), for every case branch.
        trip_branch_ids: Branch id of each of the scenario's trips, in the scenario's order.
        wall_s: Wall time of the time-domain run, s.
        case_branch_changes: (time s, branch id, in service after) of every case event kept, in time order.

    """

    t_s: np.ndarray
    freq_hz: float
    bus_numbers: tuple[int, ...]
    bus_v_pu: np.ndarray
    bus_angle_rad: np.ndarray
    generator_names: tuple[str, ...]
    generator_buses: tuple[int, ...]
    delta_rad: np.ndarray
    p_pu: np.ndarray
    q_pu: np.ndarray
    grid: Grid
    branch_ends: dict[str, tuple[int, int]]
    trip_branch_ids: tuple[str, ...]
    wall_s: float
    case_branch_changes: tuple[tuple[float, str, bool], ...] = ()


def collapsed_at(t_s: np.ndarray, bus_v_pu: np.ndarray, machine_cols: list[int],
                 fault_windows_s: list[tuple[float, float]]) -> tuple[float, list[int]] | None:
    """Find a collapsed network solution: no solution of the grid, though the solver converged.

    Args:
        t_s: Sample times, s, increasing.
        bus_v_pu: Bus voltage magnitudes, pu, one row per sample.
        machine_cols: Columns of the buses with a machine in service.
        fault_windows_s: (start, clear) of every fault, s; inside them a bus may sit at 0 pu.

    Returns:
        (when it began, s; the columns below COLLAPSED_V_PU at that time) for the first machine bus below
        COLLAPSED_V_PU for COLLAPSED_FOR_S or more with no fault applied, or None.

    """
    t = np.asarray(t_s, dtype=float)
    low = np.abs(np.asarray(bus_v_pu, dtype=float)[:, machine_cols]) < COLLAPSED_V_PU
    for start, clear in fault_windows_s:
        low[(t >= start) & (t <= clear)] = False
    since = np.full(len(machine_cols), np.nan)
    for k in range(len(t)):
        since[~low[k]] = np.nan
        since[low[k] & np.isnan(since)] = t[k]
        long = low[k] & (t[k] - since >= COLLAPSED_FOR_S)
        if long.any():
            return float(np.nanmin(since[long])), [machine_cols[j] for j in np.flatnonzero(low[k])]
    return None


def collapse_text(buses: Sequence[int]) -> str:
    """Say what collapsed_at found on the given buses (simulate's error and the closed loop's outcome)."""
    return (f'with no fault applied, bus(es) {", ".join(str(b) for b in buses)} of machines in service stayed below '
            f'{COLLAPSED_V_PU} pu for {COLLAPSED_FOR_S} s or more: ANDES converged to a collapsed network, not a '
            'solution of the grid')


def pycode_dir() -> Path:
    """Return the directory for ANDES' generated code, inside the build tree."""
    return build_dir() / 'andes_pycode'


def ensure_pycode() -> Path:
    """Generate ANDES' numerical code in this process unless this ANDES version's is there; return its directory.

    andes.load generates missing code itself, in a multiprocessing pool forked from the calling process. Forked
    from a node whose DDS threads hold locks (grid_sim), the children can deadlock: a closed-loop run from a fresh
    checkout hung at its first scenario, grid_sim's forked child asleep and the log empty. One process here, under
    a file lock so that concurrent runs do not write the same files (about 17 s on one core).
    """
    import fcntl

    import andes

    pycode = pycode_dir()
    pycode.mkdir(parents=True, exist_ok=True)
    stamp = f"__version__ = '{andes.__version__}'"
    with open(pycode / '.generating.lock', 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        init = pycode / '__init__.py'  # ANDES writes it last, naming its version
        if not (init.exists() and init.read_text().startswith(stamp)):
            andes.prepare(quick=True, incremental=False, nomp=True, pycode_path=str(pycode))
    return pycode


def branch_ids(pairs: list[tuple[int, int]]) -> list[str]:
    """Name branches `"<from>-<to>"`, and `"<from>-<to>#<n>"` for the n-th parallel one (n >= 2).

    Args:
        pairs: (from bus, to bus) of every branch, in case order.

    Returns:
        One id per branch.

    """
    seen: dict[frozenset[int], int] = {}
    out = []
    for f, t in pairs:
        key = frozenset((f, t))
        seen[key] = seen.get(key, 0) + 1
        out.append(f'{f}-{t}' if seen[key] == 1 else f'{f}-{t}#{seen[key]}')
    return out


def _find_branch(where: str, ref: str, ids: list[str], pairs: list[tuple[int, int]]) -> int:
    if ref in ids:
        return ids.index(ref)
    head, _, parallel = ref.partition('#')
    try:
        a, b = (int(x) for x in head.split('-'))
    except ValueError:
        raise ScenarioError(f'{where}: {ref!r} is not a branch id "<from>-<to>"') from None
    if parallel:
        flipped = f'{b}-{a}#{parallel}'
        if flipped in ids:
            return ids.index(flipped)
    else:
        hits = [i for i, (f, t) in enumerate(pairs) if {f, t} == {a, b} and '#' not in ids[i]]
        if hits:
            return hits[0]
    raise ScenarioError(f'{where}: unknown branch {ref!r}; no line joins buses {a} and {b} in the case')


def quiet_andes(stream_level: int = logging.CRITICAL) -> None:
    """Set ANDES' own logger before a case is loaded: the console at stream_level only, no log file.

    ANDES logs 'Time step reduced to zero' at the end of runs that did reach it; real failures are raised by the
    callers. Its log file is off because by default every call made a new <tmp>/andes-XXXXXXXX folder
    (andes.utils.paths.get_log_dir), one per case loaded and never removed, the first of each process with a DEBUG
    log of all its runs: 2,101 folders and 644 MB after four hours of testbed searches here, one log of 134 MB.
    """
    import andes

    andes.config_logger(stream_level=stream_level, file=False, log_path=tempfile.gettempdir())


def _load_case(scenario: Scenario) -> Any:
    import andes

    quiet_andes()
    pycode = ensure_pycode()
    extra = {} if scenario.addfile is None else {'addfile': str(scenario.addfile)}
    field = 'case' if scenario.addfile is None else 'case/addfile'
    try:
        ss = andes.load(str(scenario.case), setup=False, no_output=True, default_config=True,
                        pycode_path=str(pycode), **extra)
    except Exception as exc:  # ANDES raises assorted parser errors for a file it cannot read
        raise ScenarioError(f'{scenario.path}: {field}: ANDES cannot read {scenario.case}: {exc}') from exc
    if ss is None:  # some input formats make andes.load log the problem and return None
        raise ScenarioError(f'{scenario.path}: {field}: ANDES cannot read {scenario.case}')
    _psse_line_base(ss, scenario.case)
    return ss


def _psse_line_base(ss: Any, case: Path) -> None:
    """Put the lines of a PSS/E case on the system base, as PSS/E defines them (see the module docstring)."""
    if case.suffix.lower() != '.raw':
        return
    for i in range(ss.Line.n):
        if not ss.Line.trans.v[i]:
            ss.Line.Sn.v[i] = float(ss.config.mva)


def _apply_disable(ss: Any, where: str, entries: tuple[Disable, ...]) -> None:
    """Set u = 0 on every model or device the scenario disables (before setup)."""
    for entry in entries:
        if entry.model is not None:
            model = ss.models.get(entry.model)
            if model is None:
                raise ScenarioError(f'{where}: {entry.source}.model: the case has no model {entry.model!r}')
            if entry.name not in list(model.idx.v):
                raise ScenarioError(f'{where}: {entry.source}.idx: {entry.model} has no device {entry.name!r} '
                                    f'(it has {model.n}, e.g. {list(model.idx.v)[:3]})')
            model.u.v[list(model.idx.v).index(entry.name)] = 0
            continue
        model = ss.models.get(entry.name) if isinstance(entry.name, str) else None
        if model is not None:
            if model.n == 0:
                raise ScenarioError(f'{where}: {entry.source}: the case has no {entry.name} device')
            for i in range(model.n):
                model.u.v[i] = 0
            continue
        owners = [m for m in ss.models.values() if m.n and entry.name in list(m.idx.v)]
        if len(owners) != 1:
            what = 'no model and no device' if not owners else \
                f'a device of {len(owners)} models ({", ".join(m.class_name for m in owners)}); give {{model, idx}}'
            raise ScenarioError(f'{where}: {entry.source}: {entry.name!r} is {what}')
        owners[0].u.v[list(owners[0].idx.v).index(entry.name)] = 0


def _case_events(ss: Any, scenario: Scenario, ids: list[str], line_idx: list[Any]) -> list[tuple[float, str, bool]]:
    """Keep or disable the case's own Toggle/Alter events before end_s; return the kept line switchings."""
    where = f'{scenario.path}'
    events = [(model.class_name, i, float(model.t.v[i])) for model in (ss.Toggle, ss.Alter) for i in range(model.n)
              if model.u.v[i] and float(model.t.v[i]) < scenario.end_s]
    if not events:
        return []
    names = ', '.join(f'{m} {getattr(ss, m).idx.v[i]} at {t:g} s' for m, i, t in events)
    if scenario.case_events is None:
        raise ScenarioError(f'{where}: case_events: the case has its own events before end_s ({names}); say '
                            'case_events: keep or case_events: disable')
    if scenario.case_events == 'disable':
        for model, i, _ in events:
            getattr(ss, model).u.v[i] = 0
        return []
    status = {idx: int(u) for idx, u in zip(line_idx, ss.Line.u.v, strict=True)}
    changes = []
    for model, i, t in sorted(events, key=lambda e: e[2]):
        dev = ss.Toggle.dev.v[i] if model == 'Toggle' else None
        if model != 'Toggle' or ss.Toggle.model.v[i] != 'Line' or dev not in status:
            raise ScenarioError(f'{where}: case_events: keep: {model} {getattr(ss, model).idx.v[i]} at {t:g} s does '
                                'not switch a line, so the bag cannot record it; use case_events: disable')
        status[dev] = 1 - status[dev]
        changes.append((t, ids[line_idx.index(dev)], bool(status[dev])))
    return changes


@dataclass
class PreparedCase:
    """A scenario's ANDES System, set up and power-flowed, with its events added: ready for a time-domain run.

    Attributes:
        ss: The ANDES System.
        grid: The pre-fault power flow as the core Grid a network snapshot carries.
        bus_numbers: The case's buses (a mid-line fault's extra bus is not one).
        branch_ids: Branch id of each case line, in ANDES' Line order.
        branch_ends: Branch id -> (from bus, to bus).
        line_idx: ANDES Line idx of each case line.
        trip_rows: Line row of each scenario trip.
        midline_off: Line rows split into two sections for a mid-line fault.
        case_changes: (time s, branch id, in service after) of the case's own kept events.
        syn_models: The synchronous machine models in service.

    """

    ss: Any
    grid: Grid
    bus_numbers: list[int]
    branch_ids: list[str]
    branch_ends: dict[str, tuple[int, int]]
    line_idx: list[Any]
    trip_rows: list[int]
    midline_off: list[int]
    case_changes: list[tuple[float, str, bool]]
    syn_models: list[Any]

    def scheduled_changes(self, scenario: Scenario) -> list[tuple[float, str, bool]]:
        """Return (time s, branch id, in service after) of the scenario's trips and the kept case events, in order."""
        trips = [(trip.t_s, self.branch_ids[row], False) for trip, row in zip(scenario.trips, self.trip_rows,
                                                                                  strict=True)]
        return sorted(trips + list(self.case_changes))

    def line_of(self) -> dict[str, Any]:
        """Return branch id -> the ANDES Line idx that opens it (a mid-line-faulted line's first section)."""
        return {bid: (f'{self.line_idx[k]}_section1' if k in self.midline_off else self.line_idx[k])
                for k, bid in enumerate(self.branch_ids)}


def prepare_case(scenario: Scenario) -> PreparedCase:
    """Load the scenario's case, check the scenario against it, add its faults and trips, solve the power flow.

    The one setup of a scenario's case: `simulate` runs it in the time domain, sim.closed_loop steps it with a
    hook, and a baseline or an export takes its grid.

    Raises:
        ScenarioError: The scenario names a bus or branch the case does not have, or asks for what the case cannot
            do (a mid-line fault on a transformer, a PMU on no bus).
        SimulationError: The power flow did not converge.

    """
    ss = _load_case(scenario)
    where = f'{scenario.path}'
    try:
        bus_numbers = [int(b) for b in ss.Bus.idx.v]
    except (TypeError, ValueError):
        raise ScenarioError(f'{where}: case: bus idx must be integer bus numbers, got e.g. {ss.Bus.idx.v[:3]}') \
            from None
    line_idx = list(ss.Line.idx.v)
    pairs = [(int(a), int(b)) for a, b in zip(ss.Line.bus1.v, ss.Line.bus2.v, strict=True)]
    ids = branch_ids(pairs)
    _apply_disable(ss, where, scenario.disable)
    case_changes = _case_events(ss, scenario, ids, line_idx)
    syn_models = [m for m in ss.groups[_SYNGEN_GROUP].models.values() if m.n > 0 and any(m.u.v)]
    if not syn_models:
        raise ScenarioError(f'{where}: case: {scenario.case.name} has no synchronous machine in service, so no rotor '
                            'angles to record (a static case needs dynamic data: addfile)')
    gen_buses_all = [int(b) for m in syn_models for b, u in zip(m.bus.v, m.u.v, strict=True) if u]

    def check_bus(field: str, bus: int) -> None:
        if bus not in bus_numbers:
            raise ScenarioError(f'{where}: {field}: unknown bus {bus}; the case has buses '
                                f'{min(bus_numbers)}..{max(bus_numbers)} ({len(bus_numbers)} buses)')

    for fault in scenario.faults:
        if fault.bus is not None:
            check_bus(f'{fault.source}.bus', fault.bus)
    if scenario.pmu_buses is not None:
        for b in scenario.pmu_buses:
            check_bus('pmu.buses', b)
    if scenario.impairments.silent_pmu_bus is not None:
        check_bus('impairments.silent_pmu_bus', scenario.impairments.silent_pmu_bus)
        pmu_buses = scenario.pmu_buses if scenario.pmu_buses is not None else gen_buses_all
        if scenario.impairments.silent_pmu_bus not in pmu_buses:
            raise ScenarioError(f'{where}: impairments.silent_pmu_bus: bus {scenario.impairments.silent_pmu_bus} '
                                f'carries no PMU')
    trip_rows = [_find_branch(f'{where}: {t.source}.branch', t.branch, ids, pairs) for t in scenario.trips]

    # A mid-line fault needs a bus part way along the line: split it into two sections before setup.
    midline_off: list[int] = []
    next_bus = max(bus_numbers) + 1
    fault_buses: list[int] = []
    for fault in scenario.faults:
        if fault.bus is not None:
            fault_buses.append(fault.bus)
            continue
        row = _find_branch(f'{where}: {fault.source}.branch', fault.branch or '', ids, pairs)
        if row in trip_rows:
            raise ScenarioError(f'{where}: {fault.source}: a mid-line fault on a branch that is also tripped is not '
                                'supported; use a bus fault at one end with the trip')
        if float(ss.Line.tap.v[row]) != 1.0 or float(ss.Line.phi.v[row]) != 0.0:
            raise ScenarioError(f'{where}: {fault.source}: branch {ids[row]} is a transformer; a mid-line fault '
                                'needs a line')
        fault_buses.append(_split_line(ss, row, next_bus, fault.position))
        midline_off.append(row)
        next_bus += 1
    for i, (fault, bus) in enumerate(zip(scenario.faults, fault_buses, strict=True)):
        ss.add('Fault', dict(idx=f'ScenarioFault_{i}', name=f'ScenarioFault_{i}', bus=bus, tf=fault.start_s,
                             tc=fault.clear_s, xf=_FAULT_REACTANCE_PU, rf=0.0))
    for i, (trip, row) in enumerate(zip(scenario.trips, trip_rows, strict=True)):
        ss.add('Toggle', dict(idx=f'ScenarioTrip_{i}', name=f'ScenarioTrip_{i}', model='Line', dev=line_idx[row],
                              t=trip.t_s))
    dispatch = _dispatch_plan(ss, scenario) if scenario.dispatch else None
    ss.setup()
    if dispatch is not None:
        for model, name, idx, value in dispatch:
            getattr(ss, model).set(name, idx, value)  # system base, as .v holds it
    for row in midline_off:
        ss.Line.set_status(line_idx[row], 0)
    if scenario.load_scale != 1.0:
        for model, params in ((ss.PQ, ('p0', 'q0')), (ss.PV, ('p0',))):
            for name in params:
                values = np.array(getattr(model, name).v, dtype=float) * scenario.load_scale
                for idx, value in zip(model.idx.v, values, strict=True):
                    model.set(name, idx, float(value))  # system base, as .v holds it

    if not ss.PFlow.run() or not ss.PFlow.converged:
        raise SimulationError(f'{where}: the ANDES power flow of {scenario.case.name} did not converge')
    grid = _snapshot(ss, scenario.case.name, bus_numbers, ids, pairs, midline_off)
    return PreparedCase(ss=ss, grid=grid, bus_numbers=bus_numbers, branch_ids=ids,
                        branch_ends=dict(zip(ids, pairs, strict=True)), line_idx=line_idx, trip_rows=trip_rows,
                        midline_off=midline_off, case_changes=list(case_changes), syn_models=syn_models)


def simulate(scenario: Scenario, progress: bool = True) -> Simulation:
    """Run the scenario's power flow and time-domain simulation.

    Args:
        scenario: The scenario.
        progress: Print simulated time / end time on stderr as the run goes.

    Returns:
        The results.

    Raises:
        ScenarioError: The scenario names a bus or branch the case does not have.
        SimulationError: The power flow or the time-domain simulation failed.

    """
    case = prepare_case(scenario)
    ss, grid, bus_numbers, ids, trip_rows = case.ss, case.grid, case.bus_numbers, case.branch_ids, case.trip_rows
    syn_models, case_changes = case.syn_models, case.case_changes
    where = f'{scenario.path}'

    tds = ss.TDS
    tds.config.tstep = scenario.step_s
    tds.config.criteria = 0  # the default stops at 180 deg of angle spread: the loss of synchronism we record
    # ANDES' own bar, on a terminal only (it writes to stdout); elsewhere a line a simulated second, with -v.
    tds.config.no_tqdm = 0 if progress and log.isEnabledFor(logging.INFO) else 1
    start = time.monotonic()
    next_report = [_PROGRESS_CHUNK_S]

    def report(t: float, _system: Any) -> None:
        if progress and t >= next_report[0]:
            log.debug('%s: t = %5.2f / %.2f s (%.1f s wall)', scenario.name, t, scenario.end_s,
                      time.monotonic() - start)
            next_report[0] += _PROGRESS_CHUNK_S

    if progress:
        log.info('%s: simulating %g s of %s in ANDES', scenario.name, scenario.end_s, scenario.case.name)
    tds.config.tf = scenario.end_s
    tds.callpert = report
    tds.run()
    reached = float(ss.dae.ts.t[-1]) if len(ss.dae.ts.t) else 0.0
    if reached < scenario.end_s - 1e-6:
        raise SimulationError(f'{where}: ANDES stopped at t = {reached:.3f} s before end_s = '
                              f'{scenario.end_s} s (the solver did not converge)')
    wall = time.monotonic() - start

    ts = ss.dae.ts
    t = np.asarray(ts.t, dtype=float)
    # ANDES records both sides of a switching instant at the same time; keep the later (post-switching) one.
    keep = np.append(np.diff(t) > 0, True)
    n_case_bus = len(bus_numbers)
    bus_v = np.asarray(ts.get_data(ss.Bus.v))[keep][:, :n_case_bus]
    bus_a = np.asarray(ts.get_data(ss.Bus.a))[keep][:, :n_case_bus]
    names, gbus, delta, pe, qe = [], [], [], [], []
    for model in syn_models:
        on = np.asarray(model.u.v, dtype=bool)
        names += [str(n) for n, u in zip(model.name.v, on, strict=True) if u]
        gbus += [int(b) for b, u in zip(model.bus.v, on, strict=True) if u]
        delta.append(np.asarray(ts.get_data(model.delta))[keep][:, on])
        pe.append(np.asarray(ts.get_data(model.Pe))[keep][:, on])
        qe.append(np.asarray(ts.get_data(model.Qe))[keep][:, on])
    collapsed = collapsed_at(t[keep], bus_v, sorted({bus_numbers.index(b) for b in gbus}),
                             [(f.start_s, f.clear_s) for f in scenario.faults])
    if collapsed is not None:
        at_s, cols = collapsed
        raise SimulationError(f'{where}: from t = {at_s:.3f} s, {collapse_text([bus_numbers[c] for c in cols])} '
                              '(sim/andes_sim.py); try another fault duration, clearing or case')
    return Simulation(
        t_s=t[keep], freq_hz=float(ss.config.freq), bus_numbers=tuple(bus_numbers), bus_v_pu=bus_v,
        bus_angle_rad=bus_a, generator_names=tuple(names), generator_buses=tuple(gbus),
        delta_rad=np.hstack(delta), p_pu=np.hstack(pe), q_pu=np.hstack(qe), grid=grid,
        branch_ends=case.branch_ends, trip_branch_ids=tuple(ids[r] for r in trip_rows),
        wall_s=wall, case_branch_changes=tuple(case_changes))


def _dispatch_plan(ss: Any, scenario: Scenario) -> list[tuple[str, str, Any, float]]:
    """Match the MATPOWER dispatch to the case by bus; add loads where the case has none (before setup)."""
    from controlled_islanding.core.grid import Grid, GridError

    where = f'{scenario.path}: dispatch'
    try:
        mp = Grid.from_matpower(scenario.dispatch)
    except GridError as exc:
        raise ScenarioError(f'{where}: {exc}') from None
    mva = float(ss.config.mva)
    if abs(mp.base_mva - mva) > 1e-9:
        raise ScenarioError(f'{where}: MATPOWER base {mp.base_mva} MVA differs from the case base {mva} MVA')
    buses = [int(b) for b in ss.Bus.idx.v]
    load_pq: dict[int, list[float]] = {}
    for ld in mp.loads:
        if ld.bus not in buses:
            raise ScenarioError(f'{where}: load at bus {ld.bus}, which the case does not have')
        acc = load_pq.setdefault(ld.bus, [0.0, 0.0])
        acc[0] += ld.p_mw / mva
        acc[1] += ld.q_mvar / mva
    plan: list[tuple[str, str, Any, float]] = []
    pq_buses = [int(b) for b in ss.PQ.bus.v]
    for idx, bus in zip(ss.PQ.idx.v, pq_buses, strict=True):
        p, q = load_pq.get(bus, (0.0, 0.0))
        share = 1.0 / pq_buses.count(bus)
        plan += [('PQ', 'p0', idx, p * share), ('PQ', 'q0', idx, q * share)]
    for bus, (p, q) in load_pq.items():
        if bus not in pq_buses:
            row = buses.index(bus)
            ss.add('PQ', dict(idx=f'DispatchPQ_{bus}', name=f'DispatchPQ_{bus}', bus=bus, Vn=ss.Bus.Vn.v[row],
                              p0=p, q0=q))
    static = [(m.class_name, idx, int(b)) for m in ss.groups['StaticGen'].models.values() if m.n > 0
              for idx, b in zip(m.idx.v, m.bus.v, strict=True)]
    for gen in mp.generators:
        hits = [(model, idx) for model, idx, b in static if b == gen.bus]
        if len(hits) != 1:
            raise ScenarioError(f'{where}: generator {gen.name} at bus {gen.bus} matches {len(hits)} static '
                                'generators of the case; exactly one is needed')
        plan.append((hits[0][0], 'p0', hits[0][1], gen.p_mw / mva))
    return plan


def _split_line(ss: Any, row: int, new_bus: int, position: float) -> int:
    line = ss.Line
    bus1 = line.bus1.v[row]
    bus_row = list(ss.Bus.idx.v).index(bus1)
    ss.add('Bus', dict(idx=new_bus, name=f'MIDLINE_{new_bus}', Vn=ss.Bus.Vn.v[bus_row], v0=ss.Bus.v0.v[bus_row],
                       a0=ss.Bus.a0.v[bus_row], area=ss.Bus.area.v[bus_row], zone=ss.Bus.zone.v[bus_row],
                       owner=ss.Bus.owner.v[bus_row]))
    common = dict(Vn1=line.Vn1.v[row], Vn2=line.Vn2.v[row], fn=line.fn.v[row])
    for k, (a, b, share) in enumerate(((bus1, new_bus, position), (new_bus, line.bus2.v[row], 1.0 - position))):
        ss.add('Line', dict(idx=f'{line.idx.v[row]}_section{k + 1}', name=f'{line.name.v[row]}_section{k + 1}',
                            bus1=a, bus2=b, r=line.r.v[row] * share, x=line.x.v[row] * share,
                            b=line.b.v[row] * share, g=line.g.v[row] * share, **common))
    return new_bus


def load_power_flow(case: str | Path, addfile: str | Path | None = None) -> Any:
    """Return an ANDES System of a case after its power flow (PSS/E lines put on the system base first).

    Args:
        case: A case file, or a case bundled with ANDES such as 'ieee14/ieee14_full.xlsx'.
        addfile: A dynamic data file for a PSS/E .raw case (its .dyr).

    Raises:
        SimulationError: ANDES cannot read the case.

    """
    import andes

    quiet_andes()
    path = Path(case) if Path(case).exists() else Path(andes.get_case(str(case)))
    pycode = ensure_pycode()
    extra = {'addfile': str(Path(path).parent / addfile)} if addfile else {}
    ss = andes.load(str(path), setup=False, no_output=True, default_config=True, pycode_path=str(pycode), **extra)
    if ss is None:
        raise SimulationError(f'ANDES cannot read {case}')
    _psse_line_base(ss, path)
    ss.setup()
    ss.PFlow.run()
    return ss


def power_flow_grid(case: str | Path, addfile: str | Path | None = None) -> Grid:
    """Return an ANDES case's network after its power flow, as the core Grid a snapshot would carry.

    Args:
        case: A case file, or a case bundled with ANDES such as 'ieee14/ieee14_full.xlsx'.
        addfile: A dynamic data file for a PSS/E .raw case (its .dyr).

    Raises:
        SimulationError: ANDES cannot read the case, or its buses are not numbered.

    """
    path = Path(case)
    ss = load_power_flow(case, addfile)
    try:
        bus_numbers = [int(b) for b in ss.Bus.idx.v]
    except (TypeError, ValueError):
        raise SimulationError(f'{case}: bus idx are not bus numbers, e.g. {ss.Bus.idx.v[:3]}') from None
    pairs = [(int(a), int(b)) for a, b in zip(ss.Line.bus1.v, ss.Line.bus2.v, strict=True)]
    return _snapshot(ss, path.name, bus_numbers, branch_ids(pairs), pairs, [])


# Machine data as ANDES holds it after setup (per unit on the system base, M = 2H on the system base), by the
# core.dse.MachineData column (and Generator field) each fills. Classical machines (GENCLS) have only M, D, ra
# and x'd.
ANDES_MACHINE_COLUMNS = {'m_s': 'M', 'd_pu': 'D', 'ra_pu': 'ra', 'xd1_pu': 'xd1', 'xd_pu': 'xd', 'xq_pu': 'xq',
                         'xq1_pu': 'xq1', 'td10_s': 'Td10', 'tq10_s': 'Tq10', 'xd2_pu': 'xd2', 'xq2_pu': 'xq2',
                         'xl_pu': 'xl', 'td20_s': 'Td20', 'tq20_s': 'Tq20', 's10': 'S10', 's12': 'S12'}


def machine_rows(ss: Any) -> dict[str, dict[str, Any]]:
    """Return machine name -> {ANDES_MACHINE_COLUMNS column: value, 'model': ANDES model name} of a set-up System.

    A classical machine's xq is x'd (what its stator presents; ANDES copies it only at TDS initialisation);
    its saturation is NaN, since the model has none.
    """
    from andes.core.param import NumParam

    rows: dict[str, dict[str, Any]] = {}
    for model in (m for m in ss.groups[_SYNGEN_GROUP].models.values() if m.n > 0):
        for k, name in enumerate(model.name.v):
            row: dict[str, Any] = {}
            for col, attr in ANDES_MACHINE_COLUMNS.items():
                param = getattr(model, attr, None)
                row[col] = float(param.v[k]) if isinstance(param, NumParam) else float('nan')
            if model.class_name == 'GENCLS':
                row['xq_pu'] = row['xd1_pu']
                row['s10'] = row['s12'] = float('nan')
            row['model'] = model.class_name
            rows[str(name)] = row
    return rows


def andes_machine_data(ss: Any, names: list[str]):
    """Return core.dse.MachineData of the named synchronous machines of a set-up ANDES System, in that order."""
    from controlled_islanding.core.dse import MachineData

    rows = machine_rows(ss)
    missing = [n for n in names if n not in rows]
    if missing:
        raise ValueError(f'ANDES case has no synchronous machine named {missing[:3]}')
    columns = {col: np.array([rows[n][col] for n in names]) for col in ANDES_MACHINE_COLUMNS}
    return MachineData(names=tuple(names), model=tuple(rows[n]['model'] for n in names), **columns)


def _snapshot(ss: Any, case_name: str, bus_numbers: list[int], ids: list[str], pairs: list[tuple[int, int]],
              midline_off: list[int]) -> Grid:
    mva = float(ss.config.mva)
    line = ss.Line
    v = dict(zip(ss.Bus.idx.v, ss.Bus.v.v, strict=True))
    a = dict(zip(ss.Bus.idx.v, ss.Bus.a.v, strict=True))

    def flows(k: int) -> tuple[float, float]:
        # ANDES' Line power equations (andes/models/line/line.py): power leaving each end into the line.
        v1, v2 = v[line.bus1.v[k]], v[line.bus2.v[k]]
        a1, a2 = a[line.bus1.v[k]], a[line.bus2.v[k]]
        gh, ghk, bhk = line.gh.v[k], line.ghk.v[k], line.bhk.v[k]
        itap, itap2, phi = line.itap.v[k], line.itap2.v[k], line.phi.v[k]
        u = float(line.u.v[k])
        p1 = u * (v1 ** 2 * (gh + ghk) * itap2 - v1 * v2 * (ghk * np.cos(a1 - a2 - phi) + bhk * np.sin(a1 - a2 - phi))
                  * itap)
        p2 = u * (v2 ** 2 * (gh + ghk) - v1 * v2 * (ghk * np.cos(a1 - a2 - phi) - bhk * np.sin(a1 - a2 - phi)) * itap)
        return float(p1) * mva, float(p2) * mva

    n_case = len(ids)
    p_from = np.zeros(n_case)
    p_to = np.zeros(n_case)
    all_idx = list(line.idx.v)
    for k in range(n_case):
        if k in midline_off:
            # The faulted line is two sections in the simulation; the network still sees one line.
            s1 = all_idx.index(f'{all_idx[k]}_section1')
            s2 = all_idx.index(f'{all_idx[k]}_section2')
            p_from[k], p_to[k] = flows(s1)[0], flows(s2)[1]
        else:
            p_from[k], p_to[k] = flows(k)
    branches = tuple(Branch(branch_id=bid, from_bus=f, to_bus=t, in_service=bool(line.u.v[k]) or k in midline_off,
                            x_pu=float(line.x.v[k]))
                     for k, (bid, (f, t)) in enumerate(zip(ids, pairs, strict=True)))

    static_p: dict[Any, float] = {}
    static_pmax: dict[Any, float] = {}
    for model in (m for m in ss.groups['StaticGen'].models.values() if m.n > 0):
        p_values = model.p.v if hasattr(model, 'p') else model.p0.v
        for idx, p, pmax in zip(model.idx.v, p_values, model.pmax.v, strict=True):
            static_p[idx] = float(p) * mva
            static_pmax[idx] = float(pmax) * mva
    generators = []
    machines = machine_rows(ss)
    for model in (m for m in ss.groups[_SYNGEN_GROUP].models.values() if m.n > 0):
        for name, bus, gen, u in zip(model.name.v, model.bus.v, model.gen.v, model.u.v, strict=True):
            if not u:
                continue
            row = machines[str(name)]
            generators.append(Generator(name=str(name), bus=int(bus), p_mw=static_p.get(gen, float('nan')),
                                        p_max_mw=static_pmax.get(gen, float('nan')), xq_pu=row['xq_pu'],
                                        ra_pu=row['ra_pu'], model=row['model'],
                                        **{f: row[f] for f in DYNAMIC_FIELDS}))
    loads = tuple(Load(bus=int(b), p_mw=float(p) * mva, q_mvar=float(q) * mva)
                  for b, p, q, u in zip(ss.PQ.bus.v, ss.PQ.p0.v, ss.PQ.q0.v, ss.PQ.u.v, strict=True) if u)
    name = case_name
    for suffix in ('.xlsx', '.json', '.raw', '.m'):
        name = name.removesuffix(suffix)
    return Grid(name=name, base_mva=mva, buses=tuple(bus_numbers), branches=branches,
                generators=tuple(generators), loads=loads, p_from_mw=p_from, p_to_mw=p_to,
                freq_hz=float(ss.config.freq), bus_angle_rad=np.array([float(a[b]) for b in bus_numbers]))
