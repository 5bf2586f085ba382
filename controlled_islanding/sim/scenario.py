"""Scenario files: what to simulate with ANDES and how the PMUs report it.

A scenario is a YAML mapping. Every key except `case`, `end_s` and `islanding_request_s` is optional::

    name: ieee39_case1_unstable          # bag and manifest name; default: the file name without .yaml
    description: Why this scenario exists.
    case: ieee39/ieee39_full.xlsx        # ANDES case: a path relative to this file, else a case ANDES bundles;
                                         # any format ANDES reads: .xlsx, .json, MATPOWER .m, PSS/E .raw
    addfile: ieee14/ieee14.dyr           # PSS/E dynamic data for a .raw case (resolved like case)
    disable:                             # switched off (u = 0) before the power flow, e.g. a device that fails
      - IEEEST                           #   initialisation: a model name disables all its devices,
      - IEEEG1_9                         #   a device idx that only one model has disables that device,
      - {model: GENCLS, idx: 3}          #   a model and an idx (or a list of them) for idx several models share
    case_events: keep                    # the case's own Toggle/Alter events that fall before end_s: keep or
                                         # disable; required when there are any. Kept ones must switch lines,
                                         # and are recorded in the bag as branch status changes
    dispatch: case39                     # optional MATPOWER case (a PYPOWER case name, or a .m / .py file relative
                                         # to this file): its loads and generator P replace the case's, matched by
                                         # bus (voltage set points stay the ANDES case's)
    load_scale: 1.0                      # multiplies every load (P and Q) and every PV generator's P before the
                                         # power flow, after any dispatch; the slack takes up the difference
    step_s: 0.008333                     # integration step, s (default 1/120 s)
    end_s: 11.0                          # simulated time, s
    events:                              # in any order; times in s from the simulation start
      - {type: fault, bus: 17, start_s: 5.0, clear_s: 5.15}                    # 3-phase bus fault
      - {type: fault, branch: 16-17, position: 0.5, start_s: 7.0, clear_s: 7.1}  # mid-line fault
      - {type: trip, branch: 16-17, t_s: 5.15}                                 # a branch opens
    pmu:
      rate_fps: 60                       # 60 (default) or 30 frames per second
      buses: generators                  # "generators" (every generator terminal, default) or a list of buses
      noise_tve: 0.005                   # largest total vector error of the phasor noise (<= 0.01, C37.118)
    seed: 1                              # noise and impairment random seed
    impairments:                         # each optional; none by default
      frame_loss_rate: 0.05              # each PMU's data in each frame lost with this probability
      initial_gap_s: 6.0                 # every PMU's frames with time tags before this are missing
      delay_mean_s: 0.05                 # delivery delay: mean, s ...
      delay_jitter_s: 0.02               # ... and standard deviation, s (frames can arrive out of order)
      silent_pmu_bus: 35                 # this bus's PMU stops reporting ...
      silent_from_s: 6.0                 # ... from this time, s
    islanding_request_s: 9.0             # when the islanding request is published, s (a design choice: bags/README.md
                                         # states the rule the scenarios on other systems follow)

Branches are named `"<from>-<to>"` by the bus numbers of the case's Line data, `"<from>-<to>#<n>"` for the n-th
parallel line; either bus order is accepted in a scenario. A mid-line fault's `position` is the fraction of the
line's length from its from bus.

A case without synchronous machine models (a static MATPOWER .m, say) loads, but has no rotor angles to
record: `simulate` refuses it, naming `case`.

Checks that need only the file are made by `load_scenario`; checks against the case (unknown bus or branch) are
made when the case is loaded, before anything is written.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

PMU_RATES_FPS = (30, 60)
MAX_TVE = 0.01


class ScenarioError(ValueError):
    """A scenario file is missing, malformed, or names something the case does not have."""


@dataclass(frozen=True)
class Fault:
    """A 3-phase fault at a bus or part way along a branch.

    Attributes:
        start_s: Fault inception, s.
        clear_s: Fault clearing, s.
        bus: Faulted bus number (None for a mid-line fault).
        branch: Faulted branch id (None for a bus fault).
        position: Fraction of the branch length from its from bus (mid-line faults only).
        source: Where the scenario file gives it, e.g. ``events[0]``, for error messages.

    """

    start_s: float
    clear_s: float
    bus: int | None = None
    branch: str | None = None
    position: float = 0.5
    source: str = field(default='', compare=False)


@dataclass(frozen=True)
class Trip:
    """A branch opening.

    Attributes:
        branch: Branch id, either bus order.
        t_s: Time the branch opens, s.
        source: Where the scenario file gives it, e.g. ``events[1]``, for error messages.

    """

    branch: str
    t_s: float
    source: str = field(default='', compare=False)


@dataclass(frozen=True)
class Impairments:
    """Measurement impairments (see the module docstring).

    Attributes:
        frame_loss_rate: Probability that one PMU's data in one frame is lost.
        initial_gap_s: Frames with time tags before this are missing at every PMU, s.
        delay_mean_s: Mean delivery delay, s.
        delay_jitter_s: Standard deviation of the delivery delay, s.
        silent_pmu_bus: Bus of the PMU that goes silent (None: none).
        silent_from_s: Time from which that PMU is silent, s.

    """

    frame_loss_rate: float = 0.0
    initial_gap_s: float = 0.0
    delay_mean_s: float = 0.0
    delay_jitter_s: float = 0.0
    silent_pmu_bus: int | None = None
    silent_from_s: float = math.inf


@dataclass(frozen=True)
class Disable:
    """A model, or one device of it, to switch off before the power flow.

    Attributes:
        name: A model name, or a device idx (model None) that only one model may have.
        model: The model of a device given as {model, idx}, else None.
        source: Where the scenario file gives it, e.g. ``disable[1]``, for error messages.

    """

    name: str | int
    model: str | None = None
    source: str = field(default='', compare=False)


CASE_EVENT_CHOICES = ('keep', 'disable')


@dataclass(frozen=True)
class Scenario:
    """A validated scenario file.

    Attributes:
        name: Scenario name.
        description: Free text.
        path: The YAML file.
        case: The ANDES case file, resolved.
        case_ref: `case` as written in the file.
        addfile: PSS/E dynamic data file for a .raw case, resolved, or None.
        disable: Models (idx None) and devices switched off before the power flow, as written.
        case_events: 'keep' or 'disable' the case's own events before end_s; None when not given.
        dispatch: MATPOWER case whose loads and dispatch replace the case's (a PYPOWER name or a resolved path),
            or None.
        load_scale: Load and PV dispatch multiplier.
        step_s: Integration step, s.
        end_s: Simulated time, s.
        faults: Faults in start order.
        trips: Trips in time order.
        rate_fps: PMU reporting rate, frames/s.
        pmu_buses: PMU buses, or None for every generator terminal.
        noise_tve: Largest total vector error of the phasor noise.
        seed: Random seed.
        impairments: Impairments.
        request_s: Islanding request time, s.

    """

    name: str
    description: str
    path: Path
    case: Path
    case_ref: str
    dispatch: str | None
    load_scale: float
    step_s: float
    end_s: float
    faults: tuple[Fault, ...]
    trips: tuple[Trip, ...]
    rate_fps: int
    pmu_buses: tuple[int, ...] | None
    noise_tve: float
    seed: int
    impairments: Impairments = field(default_factory=Impairments)
    request_s: float = 0.0
    addfile: Path | None = None
    disable: tuple[Disable, ...] = ()
    case_events: str | None = None

    def simulation_key(self) -> tuple[Any, ...]:
        """Return what determines the ANDES run (not the PMUs), so runs can be shared between scenarios."""
        return (str(self.case), str(self.addfile), self.disable, self.case_events, self.dispatch, self.load_scale,
                self.step_s, self.end_s, self.faults, self.trips)


_TOP_KEYS = {'name', 'description', 'case', 'addfile', 'disable', 'case_events', 'dispatch', 'load_scale', 'step_s',
             'end_s', 'events', 'pmu', 'seed', 'impairments', 'islanding_request_s'}
_PMU_KEYS = {'rate_fps', 'buses', 'noise_tve'}
_IMPAIRMENT_KEYS = {'frame_loss_rate', 'initial_gap_s', 'delay_mean_s', 'delay_jitter_s', 'silent_pmu_bus',
                    'silent_from_s'}
_EVENT_KEYS = {'fault': {'type', 'bus', 'branch', 'position', 'start_s', 'clear_s'}, 'trip': {'type', 'branch', 't_s'}}


def _number(where: str, value: Any, *, low: float = -math.inf, high: float = math.inf, low_open: bool = False,
            integer: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ScenarioError(f'{where}: expected a finite number, got {value!r}')
    if integer and int(value) != value:
        raise ScenarioError(f'{where}: expected an integer, got {value!r}')
    if value < low or (low_open and value == low) or value > high:
        bound = f'({low}, {high}]' if low_open else f'[{low}, {high}]'
        raise ScenarioError(f'{where}: {value!r} is outside {bound}')
    return int(value) if integer else float(value)


def _mapping(where: str, value: Any, allowed: set[str]) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ScenarioError(f'{where}: expected a mapping, got {type(value).__name__}')
    unknown = sorted(set(map(str, value)) - allowed)
    if unknown:
        raise ScenarioError(f'{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}')
    return value


def _branch(where: str, value: Any) -> str:
    if isinstance(value, int) or not isinstance(value, str) or '-' not in value:
        raise ScenarioError(f'{where}: expected a branch id "<from>-<to>" (quote it in YAML), got {value!r}')
    return value.strip()


def resolve_case(ref: str, base_dir: Path, key: str = 'case') -> Path:
    """Find an ANDES case file: relative to the scenario's directory first, then among ANDES' bundled cases.

    Args:
        ref: The `case` value.
        base_dir: The scenario file's directory.
        key: The scenario key, for the error message.

    Returns:
        The existing case file.

    Raises:
        ScenarioError: Neither exists.

    """
    local = (base_dir / ref).resolve()
    if local.is_file():
        return local
    import andes

    bundled = Path(andes.get_case(ref, check=False))
    if bundled.is_file():
        return bundled
    raise ScenarioError(f'{key}: unknown case file {ref!r}: neither {local} nor an ANDES bundled case')


def _dispatch(ref: Any, base_dir: Path) -> str | None:
    if ref is None:
        return None
    if not isinstance(ref, str) or not ref:
        raise ScenarioError(f'dispatch: expected a MATPOWER case name or file, got {ref!r}')
    local = base_dir / ref
    if local.suffix in ('.m', '.py'):
        if not local.is_file():
            raise ScenarioError(f'dispatch: unknown MATPOWER file {ref!r} ({local} does not exist)')
        return str(local.resolve())
    from controlled_islanding.core.grid import Grid, GridError

    try:
        Grid.from_matpower(ref)
    except GridError as exc:
        raise ScenarioError(f'dispatch: unknown MATPOWER case {ref!r}: {exc}') from None
    return ref


def _disable(raw: Any) -> tuple[Disable, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, list):
        raise ScenarioError('disable: expected a list of model names, device idx or {model, idx} mappings')
    out: list[Disable] = []
    for i, item in enumerate(raw):
        where = f'disable[{i}]'
        if isinstance(item, dict):
            _mapping(where, item, {'model', 'idx'})
            if not isinstance(item.get('model'), str) or 'idx' not in item:
                raise ScenarioError(f'{where}: expected {{model: <model name>, idx: <device idx or list>}}, '
                                    f'got {item!r}')
            idxs = item['idx'] if isinstance(item['idx'], list) else [item['idx']]
            for idx in idxs:
                if isinstance(idx, bool) or not isinstance(idx, str | int) or idx == '':
                    raise ScenarioError(f'{where}.idx: expected a device idx (string or integer), got {idx!r}')
                out.append(Disable(name=idx, model=item['model'], source=where))
        elif isinstance(item, str | int) and not isinstance(item, bool) and item != '':
            out.append(Disable(name=item, source=where))
        else:
            raise ScenarioError(f'{where}: expected a model name, a device idx or {{model, idx}}, got {item!r}')
    return tuple(out)


def load_scenario(path: str | Path) -> Scenario:
    """Read and check a scenario file (everything that does not need the case loaded).

    Args:
        path: The YAML file.

    Returns:
        The scenario.

    Raises:
        ScenarioError: The file is missing or unreadable, a field is missing, unknown or out of range,
            an event falls after the end time, or the case file does not exist.

    """
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ScenarioError(f'{path}: cannot read scenario file: {exc.strerror}') from exc
    except yaml.YAMLError as exc:
        raise ScenarioError(f'{path}: not valid YAML: {exc}') from exc
    try:
        return _parse(raw, path)
    except ScenarioError as exc:
        raise ScenarioError(f'{path}: {exc}') from None


def _parse(raw: Any, path: Path) -> Scenario:
    top = _mapping('scenario', raw, _TOP_KEYS)
    for key in ('case', 'end_s', 'islanding_request_s'):
        if key not in top:
            raise ScenarioError(f'{key}: missing (required)')
    if not isinstance(top['case'], str):
        raise ScenarioError(f'case: expected a file name, got {top["case"]!r}')
    if 'addfile' in top and not isinstance(top['addfile'], str):
        raise ScenarioError(f'addfile: expected a file name, got {top["addfile"]!r}')
    case_events = top.get('case_events')
    if case_events is not None and case_events not in CASE_EVENT_CHOICES:
        raise ScenarioError(f'case_events: expected one of {list(CASE_EVENT_CHOICES)}, got {case_events!r}')
    end_s = _number('end_s', top['end_s'], low=0.0, low_open=True)
    step_s = _number('step_s', top.get('step_s', 1 / 120), low=0.0, high=0.05, low_open=True)
    request_s = _number('islanding_request_s', top['islanding_request_s'], low=0.0, high=end_s)

    faults: list[Fault] = []
    trips: list[Trip] = []
    events = top.get('events', [])
    if not isinstance(events, list):
        raise ScenarioError('events: expected a list')
    for i, ev in enumerate(events):
        where = f'events[{i}]'
        if not isinstance(ev, dict) or ev.get('type') not in _EVENT_KEYS:
            raise ScenarioError(f'{where}.type: expected one of {sorted(_EVENT_KEYS)}, got '
                                f'{ev.get("type") if isinstance(ev, dict) else ev!r}')
        _mapping(where, ev, _EVENT_KEYS[ev['type']])
        if ev['type'] == 'trip':
            for key in ('branch', 't_s'):
                if key not in ev:
                    raise ScenarioError(f'{where}.{key}: missing (required for a trip)')
            t_s = _number(f'{where}.t_s', ev['t_s'], low=0.0)
            if t_s >= end_s:
                raise ScenarioError(f'{where}.t_s: {t_s} s is not before end_s = {end_s} s')
            trips.append(Trip(branch=_branch(f'{where}.branch', ev['branch']), t_s=t_s, source=where))
            continue
        for key in ('start_s', 'clear_s'):
            if key not in ev:
                raise ScenarioError(f'{where}.{key}: missing (required for a fault)')
        start = _number(f'{where}.start_s', ev['start_s'], low=0.0, low_open=True)
        clear = _number(f'{where}.clear_s', ev['clear_s'], low=start, low_open=True)
        if clear >= end_s:
            raise ScenarioError(f'{where}.clear_s: {clear} s is not before end_s = {end_s} s')
        if ('bus' in ev) == ('branch' in ev):
            raise ScenarioError(f'{where}: give exactly one of bus (bus fault) or branch (mid-line fault)')
        if 'bus' in ev:
            if 'position' in ev:
                raise ScenarioError(f'{where}.position: only for a mid-line fault (with branch)')
            faults.append(Fault(start_s=start, clear_s=clear,
                                bus=int(_number(f'{where}.bus', ev['bus'], low=0, integer=True)), source=where))
        else:
            faults.append(Fault(start_s=start, clear_s=clear, branch=_branch(f'{where}.branch', ev['branch']),
                                position=_number(f'{where}.position', ev.get('position', 0.5), low=0.0, high=1.0,
                                                 low_open=True), source=where))
            if faults[-1].position == 1.0:
                raise ScenarioError(f'{where}.position: must be below 1 (a fault at 1 is a bus fault)')

    pmu = _mapping('pmu', top.get('pmu', {}) or {}, _PMU_KEYS)
    rate = pmu.get('rate_fps', 60)
    if rate not in PMU_RATES_FPS or isinstance(rate, bool):
        raise ScenarioError(f'pmu.rate_fps: {rate!r} is not one of {list(PMU_RATES_FPS)}')
    buses_raw = pmu.get('buses', 'generators')
    if buses_raw == 'generators':
        pmu_buses = None
    elif isinstance(buses_raw, list) and buses_raw:
        pmu_buses = tuple(int(_number(f'pmu.buses[{i}]', b, low=0, integer=True)) for i, b in enumerate(buses_raw))
        if len(set(pmu_buses)) != len(pmu_buses):
            raise ScenarioError(f'pmu.buses: duplicate bus in {list(pmu_buses)}')
    else:
        raise ScenarioError(f'pmu.buses: expected "generators" or a non-empty list of bus numbers, got {buses_raw!r}')
    noise_tve = _number('pmu.noise_tve', pmu.get('noise_tve', 0.005), low=0.0, high=MAX_TVE)

    imp_raw = _mapping('impairments', top.get('impairments', {}) or {}, _IMPAIRMENT_KEYS)
    if ('silent_pmu_bus' in imp_raw) != ('silent_from_s' in imp_raw):
        raise ScenarioError('impairments: give silent_pmu_bus and silent_from_s together')
    impairments = Impairments(
        frame_loss_rate=_number('impairments.frame_loss_rate', imp_raw.get('frame_loss_rate', 0.0), low=0.0,
                                high=0.99),
        initial_gap_s=_number('impairments.initial_gap_s', imp_raw.get('initial_gap_s', 0.0), low=0.0,
                              high=request_s),
        delay_mean_s=_number('impairments.delay_mean_s', imp_raw.get('delay_mean_s', 0.0), low=0.0, high=10.0),
        delay_jitter_s=_number('impairments.delay_jitter_s', imp_raw.get('delay_jitter_s', 0.0), low=0.0, high=10.0),
        silent_pmu_bus=(None if 'silent_pmu_bus' not in imp_raw else
                        int(_number('impairments.silent_pmu_bus', imp_raw['silent_pmu_bus'], low=0, integer=True))),
        silent_from_s=(math.inf if 'silent_from_s' not in imp_raw else
                       _number('impairments.silent_from_s', imp_raw['silent_from_s'], low=0.0, high=end_s)),
    )
    if pmu_buses is not None and impairments.silent_pmu_bus is not None and \
            impairments.silent_pmu_bus not in pmu_buses:
        raise ScenarioError(f'impairments.silent_pmu_bus: bus {impairments.silent_pmu_bus} carries no PMU '
                            f'(pmu.buses = {list(pmu_buses)})')

    name = top.get('name', path.stem.removesuffix('.yaml'))
    if not isinstance(name, str) or not name or '/' in name:
        raise ScenarioError(f'name: expected a non-empty string without "/", got {name!r}')
    description = top.get('description', '')
    if not isinstance(description, str):
        raise ScenarioError('description: expected a string')
    return Scenario(
        name=name, description=description.strip(), path=path.resolve(),
        case=resolve_case(top['case'], path.resolve().parent), case_ref=top['case'],
        addfile=None if 'addfile' not in top else resolve_case(top['addfile'], path.resolve().parent, 'addfile'),
        disable=_disable(top.get('disable')), case_events=case_events,
        dispatch=_dispatch(top.get('dispatch'), path.resolve().parent),
        load_scale=_number('load_scale', top.get('load_scale', 1.0), low=0.0, high=3.0, low_open=True),
        step_s=step_s, end_s=end_s,
        faults=tuple(sorted(faults, key=lambda f: f.start_s)), trips=tuple(sorted(trips, key=lambda t: t.t_s)),
        rate_fps=int(rate), pmu_buses=pmu_buses, noise_tve=noise_tve,
        seed=int(_number('seed', top.get('seed', 0), low=0, integer=True)),
        impairments=impairments, request_s=request_s)
