"""The stability monitor judged on every scenario (issue 30): its requests on the DSE angles, and the closed loop.

Offline, per scenario (a bag of bags/, or a scenario YAML simulated in ANDES): the PMU frames go through what
pmu_ingestion runs (evaluation/predictors.monitor_inputs: bad-data tests, the streaming filter at the PMUs' nominal
frequency), and every frame, in time-tag order, through the monitor's own core (core/final_grouping.SwingWatch).
Every request it raises is recorded at the delivery time of the frame that raised it:
- on a run that ends in one group, every request is a false one;
- on a run that separates, the lead is the first pole slip (sim/truth.py) minus the first request, and its groups
  are compared with the final grouping (the truth rule of bags/README.md).

Closed loop, from the results folders of `testbed --trigger monitor` (each scenario's result.json): the load served
by the graph with the monitor as the only trigger (the run `dtw`) against no action and, where the folder has it,
the oracle of `testbed --oracle` (the best found); and whether every island survived where the oracle's did.

Noise draws (`--noise-seeds N`): each scenario's simulation measured again under seeds 1 to N, the monitor's core
run on each draw, as above: how often the PMUs' noise tips it into a false request, a late one, or other groups.

Acceptance (issue 30), per scenario: stable, no request (and, closed loop, the load served equals no action's);
unstable, the first request before the first pole slip with the final groups (offline, and the groups the closed
loop's first decision was made on), the closed loop's load served at least 90 % of the oracle's, and every island
surviving wherever the oracle's best keeps every island.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from controlled_islanding.core.stability import TIME_TO_ACT_S

ORACLE_SHARE = 0.9  # the closed loop must serve at least this share of the oracle's load (issue 30's acceptance)


class MonitorStudyError(ValueError):
    """An input of the study it cannot read (an oracle record)."""


@dataclass
class Request:
    """One request the monitor raised: when, for which groups, predicting which first slip."""

    t_s: float
    delivery_s: float
    groups: dict[str, int]
    predicted_slip_s: float


@dataclass
class MonitorRun:
    """The monitor on one scenario, offline.

    Attributes:
        name, source, system: Scenario name, where it came from, its case file.
        scenario_path: The scenario YAML (a bag's from its manifest entry), to find its closed loop.
        truth: Generator name -> final group; first_pole_slip_s: s, None if never.
        requests: Every request raised, in order.
        clearings_s: When the scenario's faults clear, s.
        cpu_ms_per_frame: Mean CPU time of one SwingWatch.update, ms.

    """

    name: str
    source: str
    system: str
    freq_hz: float
    n_machines: int
    truth: dict[str, int]
    first_pole_slip_s: float | None
    requests: list[Request]
    clearings_s: tuple[float, ...] = ()
    cpu_ms_per_frame: float = math.nan
    scenario_path: Path | None = None

    def loop(self, loops: dict[str, ClosedLoop]) -> ClosedLoop | None:
        """Return this scenario's closed loop: by its scenario file, else by name where either file is not known.

        A bag and a scenario file elsewhere may share a name: different files, different runs.
        """
        if self.scenario_path is not None and str(self.scenario_path.resolve()) in loops:
            return loops[str(self.scenario_path.resolve())]
        found = loops.get(self.name)
        if found is not None and found.path is not None and self.scenario_path is not None:
            return None
        return found

    @property
    def stable(self) -> bool:
        """Whether the run ends in one group."""
        return len(set(self.truth.values())) == 1

    @property
    def lead_s(self) -> float | None:
        """First pole slip minus the first request, s (None: no request, or no slip)."""
        if not self.requests or self.first_pole_slip_s is None:
            return None
        return self.first_pole_slip_s - self.requests[0].delivery_s

    @property
    def in_time(self) -> bool:
        """Whether the first request came before the first pole slip."""
        return (self.lead_s or 0) > 0

    @property
    def groups_right(self) -> bool:
        """Whether the first request's groups are the final grouping."""
        from controlled_islanding.evaluation.coherency_rules import blocks

        return bool(self.requests) and blocks(self.requests[0].groups) == blocks(self.truth)


def watch_run(run) -> MonitorRun:
    """Run the monitor's core over a scenario's frames (evaluation/predictors.ScenarioRun); record its requests."""
    from controlled_islanding.core.final_grouping import SwingWatch
    from controlled_islanding.core.stability import MachineSet
    from controlled_islanding.evaluation.predictors import monitor_inputs

    inputs = monitor_inputs(run)
    watch = SwingWatch(MachineSet.of_grid(inputs.grid, inputs.freq_hz))
    requests, cpu = [], 0.0
    for k in range(len(inputs.t_s)):
        start = time.process_time()
        alarm = watch.update(inputs.t_s[k], inputs.delta_rad[k], inputs.omega_pu[k], inputs.pe_pu[k], inputs.v_pu[k],
                             inputs.valid[k], inputs.tm_pu[k])
        cpu += time.process_time() - start
        if alarm is not None:
            requests.append(Request(float(inputs.t_s[k]), float(inputs.delivery_s[k]),
                                    {n: int(g) for n, g in zip(inputs.generator_names, alarm.groups, strict=True)},
                                    float(alarm.first_slip_s)))
    return MonitorRun(inputs.name, inputs.source, str(run.grid.name), inputs.freq_hz, len(inputs.generator_names),
                      inputs.truth, inputs.first_pole_slip_s, requests, inputs.clearings_s,
                      1e3 * cpu / max(len(inputs.t_s), 1), _scenario_path(inputs.source, inputs.name))


@dataclass
class NoiseDraws:
    """The monitor on one scenario's simulation measured again under other seeds (PMU noise and impairments).

    Attributes:
        name: Scenario name.
        noise_tve: The largest total vector error of its PMUs' noise.
        seeds: The seeds drawn, one run each.
        runs: The monitor on each draw; the simulation, and so the truth, is the same in all.

    """

    name: str
    noise_tve: float
    seeds: tuple[int, ...]
    runs: list[MonitorRun]

    @property
    def stable(self) -> bool:
        """Whether the scenario ends in one group."""
        return self.runs[0].stable

    def timely(self) -> list[MonitorRun]:
        """Return the draws whose first request came before the first pole slip."""
        return [r for r in self.runs if r.in_time]


def noise_draws(path: Path, seeds: Sequence[int], simulated=None) -> NoiseDraws:
    """Simulate a scenario YAML once, measure it under each seed, and run the monitor's core on every draw.

    simulated: the scenario's (scenario, simulation) from predictors.simulate_scenario, where already run.
    """
    from controlled_islanding.evaluation.predictors import measured_run, simulate_scenario

    scenario, sim = simulated if simulated is not None else simulate_scenario(path)
    runs = [watch_run(measured_run(scenario, sim, path, seed)) for seed in seeds]
    return NoiseDraws(scenario.name, float(scenario.noise_tve), tuple(seeds), runs)


def report_noise(draws: Sequence[NoiseDraws]) -> list[str]:
    """Return the figures and the per-scenario table of the noise draws as Markdown lines."""
    stable = [d for d in draws if d.stable]
    unstable = [d for d in draws if not d.stable]
    n = len(draws[0].seeds) if draws else 0
    false = sum(bool(r.requests) for d in stable for r in d.runs)
    asked = sum(len(d.timely()) for d in unstable)
    right = sum(r.groups_right for d in unstable for r in d.timely())
    lines = ['| figure | value |', '|---|---|',
             f'| stable draws with a request | {false} / {n * len(stable)} (in '
             f'{sum(any(r.requests for r in d.runs) for d in stable)} of {len(stable)} scenarios) |',
             f'| separating draws asked before the first pole slip | {asked} / {n * len(unstable)} |',
             f'| ... with the final groups | {right} / {n * len(unstable)} |', '',
             '| scenario | final k | noise TVE | draws | stable: draws with a request; separating: asked before the '
             'slip | ... with the final groups | lead, s: median (least) |', '|---|---:|---:|---:|---:|---:|---|']
    for d in draws:
        k = len(set(d.runs[0].truth.values()))
        if d.stable:
            hits, right_cell, lead = sum(bool(r.requests) for r in d.runs), '-', '-'
        else:
            timely = d.timely()
            leads = [r.lead_s for r in timely]
            hits, right_cell = len(timely), str(sum(r.groups_right for r in timely))
            lead = f'{np.median(leads):.2f} ({min(leads):.2f})' if leads else '-'
        lines.append(f'| {d.name} | {k} | {d.noise_tve:g} | {len(d.runs)} | {hits} | {right_cell} | {lead} |')
    return lines


NOISE_INTRO = """\
The figures above are one measurement of each run: the bag's recording, or the scenario's own seed. The monitor
judges noisy phasors, and on a swing near the edge of stability the noise can tip a verdict. Here each scenario's
simulation is measured again under seeds {first} to {last} (`sim/pmu.py`: the PMUs' noise, at the scenario's own
TVE, and its impairments drawn again; the simulation, and so the first pole slip and the final grouping, are
the same in every draw), and the monitor's core is run on each draw as above. Nothing here is a closed loop.
"""


def _scenario_path(source: str, name: str) -> Path | None:
    """Return the scenario YAML of a run: the --andes file, or the bag's from bags/index.yaml beside it."""
    from controlled_islanding.sim.manifest import entry_for_bag

    if source.startswith('ANDES '):
        return Path(source.removeprefix('ANDES '))
    entry = entry_for_bag(Path(source)) or {}
    path = Path(source).parent / str(entry.get('scenario', f'{name}.yaml'))
    return path if path.is_file() else None


@dataclass
class ClosedLoop:
    """One scenario of a `testbed --trigger monitor` results folder.

    Attributes:
        scenario: Its name.
        asked: Whether the monitor asked (a request event from it).
        request_s: The request time, s (None without one).
        served_mw: Load served by the closed loop, MW (None: the simulation failed); likewise none_mw (no action)
            and oracle_mw (the oracle's best, None without `testbed --oracle`).
        survived, none_survived, oracle_survived: Whether every island survived (None: not known).
        path: The scenario file the run was of, resolved (None: the result does not say).
        groups: Generator name -> group of the coherent groups the first decision was made on (None: none).
        oracle: The oracle's figures as read, with their scenario file and where they came from (None: none).

    """

    scenario: str
    asked: bool
    request_s: float | None
    served_mw: float | None
    none_mw: float | None
    oracle_mw: float | None = None
    survived: bool | None = None
    none_survived: bool | None = None
    oracle_survived: bool | None = None
    notes: list[str] = field(default_factory=list)
    path: str | None = None
    groups: dict[str, int] | None = None
    oracle: dict | None = None


def read_testbed(sources: Sequence[Path]) -> dict[str, ClosedLoop]:
    """Return each scenario's closed loop from `testbed --trigger monitor` results folders (*/result.json).

    Keyed by the scenario file's resolved path, and by the scenario's name. A run another trigger asked for is not
    the monitor's closed loop, but its oracle (`testbed --oracle`) is the scenario's whatever the trigger (the search
    spans every request time and candidate cut on its own): it fills in a monitor run's missing oracle. So does a
    source that is a file, an oracle record (write_oracle_record): a search takes hours on IEEE 39, its folders are
    not kept, and it does not depend on the monitor. The first source that has a scenario's oracle lends it.
    """
    out: dict[str, ClosedLoop] = {}
    oracles: dict[str, dict] = {}
    for source in map(Path, sources):
        if source.is_file():
            for key, oracle in read_oracle_record(source).items():
                oracles.setdefault(key, oracle)
            continue
        for path in sorted(source.glob('*/result.json')):
            r = json.loads(path.read_text())
            runs = r.get('runs', {})
            asks = [e for e in r.get('events', []) if e.get('what') == 'request']
            from_monitor = [e for e in asks if e.get('from') == 'stability monitor']
            loop, none, oracle = runs.get('dtw', {}), runs.get('no action', {}), runs.get('oracle')
            scenario_file = str(Path(r['path']).resolve()) if r.get('path') else None
            if oracle is not None:  # by its scenario file where known: a file elsewhere may share the name
                measured = time.strftime('%Y-%m-%d', time.gmtime(path.stat().st_mtime))
                oracle = {**oracle, 'scenario': r['scenario'], 'path': scenario_file, 'from': f'{path} ({measured})',
                          'served_by_request_s': (oracle.get('search') or {}).get('served_by_request_s')}
                oracles.setdefault(scenario_file or r['scenario'], oracle)
            if asks and not from_monitor:
                if oracle is not None or r['scenario'] in out:
                    continue
            item = ClosedLoop(r['scenario'], bool(from_monitor), from_monitor[0]['at_s'] if from_monitor else None,
                              loop.get('load_served_mw'), none.get('load_served_mw'),
                              None if oracle is None else oracle.get('load_served_mw'), loop.get('all_survived'),
                              none.get('all_survived'), None if oracle is None else oracle.get('all_survived'))
            item.oracle = oracle
            listed = (r.get('coherent_groups') or {}).get('groups') or []
            if from_monitor and listed:
                item.groups = {n: k for k, members in enumerate(listed) for n in members}
            if asks and not from_monitor:
                item.notes.append(f'{path.parent}: a request not from the monitor (not a --trigger monitor run)')
            out[r['scenario']] = item
            if scenario_file:
                item.path = scenario_file
                out[item.path] = item
    for item in out.values():
        oracle = oracles.get(item.path or item.scenario)
        if item.oracle is None and oracle is not None:
            item.oracle = oracle
            item.oracle_mw, item.oracle_survived = oracle.get('load_served_mw'), oracle.get('all_survived')
    return out


_RECORDED = ('scenario', 'load_served_mw', 'all_survived', 'request_s', 'cut_branch_ids', 'from')
_RECORDED_WHEN_KNOWN = ('sources', 'served_by_request_s')  # not in the records bootstrapped from docs/testbed.md
ORACLE_RECORD_ABOUT = (
    "The oracles (testbed --oracle, the best found) docs/monitor.md's closed loops are judged against, written by "
    "`controlled-islanding evaluate --monitor` from its --testbed sources; pass this file as one of them to build "
    "the page again without the searches' folders. 'from' says where each came from.")


def read_oracle_record(path: Path) -> dict[str, dict]:
    """Return the oracles of a record (write_oracle_record), keyed by their scenario file's resolved path.

    Raises:
        MonitorStudyError: The file is no oracle record.

    """
    from controlled_islanding.locations import share_dir

    try:
        entries = json.loads(Path(path).read_text())['oracles']
        resolved = [str((share_dir() / e['path']).resolve()) for e in entries]
        return {where: {**e, 'path': where} for where, e in zip(resolved, entries, strict=True)}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise MonitorStudyError(f'{path}: not an oracle record ({type(exc).__name__}: {exc}); one is a JSON '
                                'object whose "oracles" list each scenario\'s "path", "load_served_mw" and '
                                '"all_survived", as `evaluate --monitor` writes it') from None


def oracle_record_path(page: Path) -> Path:
    """Return where the oracle record of a page goes: docs/monitor.md's is docs/monitor/oracles.json."""
    return Path(page).parent / Path(page).stem / 'oracles.json'


def write_oracle_record(path: Path, loops: dict[str, ClosedLoop]) -> None:
    """Write every oracle the closed loops were judged against, so that the page can be built again without them.

    One entry per scenario file: the oracle's figures, its scenario file relative to the checkout, and where it
    came from (a results folder and the day it was written, or the record it was read from).
    """
    from controlled_islanding.atomic import write_text
    from controlled_islanding.locations import share_dir

    root = share_dir().resolve()
    entries = {}
    for loop in loops.values():
        if loop.oracle is None or not loop.oracle.get('path'):
            continue
        scenario = Path(loop.oracle['path']).resolve()
        where = scenario.relative_to(root) if scenario.is_relative_to(root) else scenario
        entries[str(where)] = {'path': str(where), **{k: loop.oracle.get(k) for k in _RECORDED},
                               **{k: loop.oracle[k] for k in _RECORDED_WHEN_KNOWN if loop.oracle.get(k) is not None}}
    record = {'about': ORACLE_RECORD_ABOUT, 'oracles': [entries[k] for k in sorted(entries)]}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_text(Path(path), json.dumps(record, indent=1) + '\n')



def _fmt_mw(x: float | None) -> str:
    return '-' if x is None else f'{x:.0f}'


def _same_groups(groups: dict[str, int], truth: dict[str, int]) -> bool:
    """Whether groups are the final grouping over the machines they list (an unobserved one is in none)."""
    from controlled_islanding.evaluation.coherency_rules import blocks

    return blocks(groups) == blocks({n: g for n, g in truth.items() if n in groups})


def verdict(run: MonitorRun, loop: ClosedLoop | None) -> tuple[bool | None, str]:
    """Return (met, why) for issue 30's acceptance on one scenario; met None where a figure is missing."""
    if run.stable:
        if run.requests:
            return False, f'{len(run.requests)} false request(s)'
        if loop is not None and loop.served_mw is not None and loop.none_mw is not None \
                and abs(loop.served_mw - loop.none_mw) > 1e-6 * max(1.0, loop.none_mw):
            return False, 'closed-loop load served differs from no action'
        return True, 'quiet'
    why = []
    if not run.in_time:
        why.append('no request before the first slip')
    elif not run.groups_right:
        why.append('groups not the final ones')
    if loop is not None and loop.groups is not None and not _same_groups(loop.groups, run.truth):
        why.append("the closed loop's first decision on other groups")
    if loop is None or loop.served_mw is None:
        missing = 'no closed loop' if loop is None else 'closed loop failed'
        return (False if why else None), '; '.join(why + [missing])
    if loop.oracle_mw is None:
        return (False if why else None), '; '.join(why + ['no oracle'])
    if loop.served_mw < ORACLE_SHARE * loop.oracle_mw - 1e-6:
        why.append(f'{100 * loop.served_mw / max(loop.oracle_mw, 1e-9):.0f} % of the oracle')
    if loop.oracle_survived and not loop.survived:
        why.append('an island lost that the oracle keeps')
    return not why, '; '.join(why) or 'met'


def _short_of_oracle(run: MonitorRun, loop: ClosedLoop | None) -> str | None:
    """Return the page's line on a closed loop that served less than ORACLE_SHARE of the oracle's load, else None."""
    if (loop is None or loop.served_mw is None or loop.oracle_mw is None
            or loop.served_mw >= ORACLE_SHARE * loop.oracle_mw - 1e-6):
        return None

    def at(t_s: float) -> str:
        cleared = [c for c in run.clearings_s if c <= t_s + 1e-9]
        return f'{t_s:.3f} s' + (f' ({t_s - cleared[-1]:+.3f} s)' if cleared else '')

    def asked(what: str, t_s) -> str:
        return f'{what} did not ask' if t_s is None else f'{what} asked at {at(t_s)}'

    oracle = loop.oracle or {}
    cut = ', '.join(oracle.get('cut_branch_ids') or []) or 'no cut'
    sources = oracle.get('sources') or []
    if sources and not any(s == 'graph' or s.endswith('of truth') for s in sources):  # oracle.py's source names
        cut += f": {' and '.join(sources)}, not the final grouping's cut"
    line = (f'- {run.name}: {loop.served_mw:.0f} MW against {loop.oracle_mw:.0f} MW; '
            f"{asked(f'the best found ({cut})', oracle.get('request_s'))}, {asked('the monitor', loop.request_s)}")
    by_time = oracle.get('served_by_request_s') or []
    enough = [t for t, mw in by_time if mw is not None and mw >= ORACLE_SHARE * loop.oracle_mw - 1e-6]
    if enough:
        deadline = max(enough)
        later = [(t, mw) for t, mw in by_time if t > deadline]
        line += (f'; {100 * ORACLE_SHARE:.0f} % of the best needs a request by {at(deadline)}, the latest '
                 'request time searched at which a run served that much')
        if later:
            t, mw = later[0]
            line += f" (at {t:.3f} s: {'a failed run' if mw is None else f'{mw:.0f} MW'})"
    return line


def report(runs: Sequence[MonitorRun], loops: dict[str, ClosedLoop], run_note: str = '') -> list[str]:
    """Return the figures and the per-scenario table as Markdown lines."""
    stable = [r for r in runs if r.stable]
    unstable = [r for r in runs if not r.stable]
    in_time = [r for r in unstable if r.in_time]
    right = [r for r in in_time if r.groups_right]
    to_act = [r for r in right if r.lead_s >= TIME_TO_ACT_S - 1e-9]
    leads = [r.lead_s for r in in_time]
    systems = sorted({r.system for r in runs})
    lines = [f'{len(runs)} runs on {len(systems)} case files ({", ".join(systems)}): {len(stable)} stay one group, '
             f'{len(unstable)} separate.' + (f' This run: {run_note}.' if run_note else ''), '',
             '| figure | value |', '|---|---|',
             f'| stable runs without any request | {sum(not r.requests for r in stable)} / {len(stable)} '
             f'({sum(len(r.requests) for r in stable)} false requests in all) |',
             f'| separating runs asked before the first pole slip | {len(in_time)} / {len(unstable)} |',
             f'| ... with the final groups | {len(right)} / {len(unstable)} |',
             f'| ... and at least {TIME_TO_ACT_S:g} s before it | {len(to_act)} / {len(unstable)} |',
             '| lead, s: median (least) | '
             + (f'{np.median(leads):.2f} ({min(leads):.2f})' if leads else '-') + ' |',
             f'| CPU per frame, ms: median (most) | {np.median([r.cpu_ms_per_frame for r in runs]):.2f} '
             f'({max(r.cpu_ms_per_frame for r in runs):.1f}) |']
    looped = [r.loop(loops) for r in runs if r.loop(loops) is not None]
    if looped:
        lines.append(f'| closed loop with the monitor as trigger | {len(looped)} scenarios; oracle for '
                     f'{sum(loop.oracle_mw is not None for loop in looped)} |')
    lines += ['', '| scenario | system, f0 | machines | final k | first slip, s | requests: time, s (lead), k | '
              'groups | closed loop MW | no action MW | oracle MW | acceptance |',
              '|---|---|---:|---:|---:|---|---|---:|---:|---:|---|']
    for r in runs:
        slip = '-' if r.first_pole_slip_s is None else f'{r.first_pole_slip_s:.2f}'
        asks = ', '.join(f'{q.delivery_s:.2f}' + (f' ({r.first_pole_slip_s - q.delivery_s:+.2f})'
                                                  if r.first_pole_slip_s is not None else '')
                         + f' k={len(set(q.groups.values()))}' for q in r.requests) or 'none'
        groups = '-' if not r.requests else ('right' if r.groups_right else 'WRONG')
        loop = r.loop(loops)
        met, why = verdict(r, loop)
        mark = {True: 'met', False: 'NOT MET', None: 'open'}[met]
        lines.append(f'| {r.name} | {r.system}, {r.freq_hz:g} Hz | {r.n_machines} | {len(set(r.truth.values()))} | '
                     f'{slip} | {asks} | {groups} | {_fmt_mw(loop.served_mw if loop else None)} | '
                     f'{_fmt_mw(loop.none_mw if loop else None)} | {_fmt_mw(loop.oracle_mw if loop else None)} | '
                     f'{mark}: {why} |')
    return lines


INTRO = """\
The stability monitor (`controlled_islanding/nodes/stability_monitor.py`) asks for islanding when the chosen
predictor (SIME, [prediction.md](prediction.md)) says with confidence that a swing separates the grid, once per
swing, with the predicted final groups; coherency's groups come from the same rule
(`controlled_islanding/core/final_grouping.py`). This page runs its core on every scenario as the node would:
the PMU frames through pmu_ingestion's bad-data tests and filter (`evaluation/predictors.monitor_inputs`), every
frame in time-tag order through `SwingWatch`; a request is dated by the delivery time of the frame that raised it.
The lead is the first pole slip (two machines pi rad apart, the simulator's own angles, `sim/truth.py`) minus the
first request; its groups are compared with the final grouping (`bags/README.md`'s truth rule). The closed-loop
columns come from `testbed --trigger monitor` results folders, where the monitor is the only source of requests:
the load served (MW, at the end of the run, in islands that survived, net of every shed) against no action and the
oracle's best (`testbed --oracle`) where the folder has it.

Acceptance (issue 30): a stable run gets no request (and the closed loop serves what no action does); a
separating manifest run gets its first request before the first pole slip with the final groups (here, and in the
closed loop, whose own stream can tip the verdict another way), serves at least
90 % of the oracle's load, and keeps every island wherever the oracle's best keeps every island. "open": a figure
the page was not given (no closed loop, or no oracle).
"""


def write_page(runs: Sequence[MonitorRun], loops: dict[str, ClosedLoop], path: Path, *, command: str,
               run_note: str = '', draws: Sequence[NoiseDraws] = (), not_evaluated: Sequence[str] = ()) -> None:
    """Write the page (docs/monitor.md); `not_evaluated`: why each scenario that could not be run was not."""
    from controlled_islanding.atomic import write_text

    notes = list(dict.fromkeys(n for loop in loops.values() for n in loop.notes))
    missed = []
    for r in runs:
        if not r.stable and not r.in_time:
            cleared = [c for c in r.clearings_s if c <= (r.first_pole_slip_s or math.inf)]
            after = (f'{r.first_pole_slip_s - cleared[-1]:.2f} s after its last fault cleared' if cleared
                     else 'no fault cleared before it')
            missed.append(f'- {r.name}: first slip at {r.first_pole_slip_s:.2f} s, {after}')
    body = ['# The stability monitor: requests before the slip, quiet when the grid recovers', '',
            f'Generated by `{command}`; do not edit by hand (the text is in '
            '`controlled_islanding/evaluation/monitor_study.py`).', '', INTRO, '## Figures', '',
            *report(runs, loops, run_note), '']
    if missed:
        body += ['Separating runs the monitor does not ask for before the first pole slip (why such slips cannot be '
                 'predicted: [prediction.md](prediction.md)):', '', *missed, '']
    short = [line for r in runs if (line := _short_of_oracle(r, r.loop(loops)))]
    if short:
        body += ['Closed loops short of the oracle, and when each asked against the last fault clearing before it '
                 "(the oracle's best is searched with hindsight over every request time; a predictor needs some "
                 'of the swing after the clearing):', '', *short, '']
    if draws:
        seeds = draws[0].seeds
        body += ['## Under other noise draws', '', NOISE_INTRO.format(first=seeds[0], last=seeds[-1]),
                 *report_noise(draws), '']
    if notes:
        body += ['Notes:', '', *(f'- {n}' for n in notes), '']
    if not_evaluated:
        body += ['## Not evaluated', '', *(f'- {why}' for why in not_evaluated), '']
    write_text(Path(path), '\n'.join(body))
