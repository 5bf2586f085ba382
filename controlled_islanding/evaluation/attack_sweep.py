"""The attack sweep: whether one spoofed or failing PMU station steers the decision, and is flagged in time.

Offline, as the graph decides, frame by frame (`screen`): core/bad_data judges every station; a suspect one is
stepped as lost in core/dse's filter (its data compared with the prediction, never taken), and the filter's
innovations judge every station again, as pmu_ingestion does; the coherency window (3 s, the node's
rule, band and cap from config/coherency.yaml) ending at the request excludes any generator flagged in it (as
nodes/coherency.py does); more suspects than `max_suspect_share` of the generators refuse the request
(STATUS_REFUSED_SUSPECT_DATA, as nodes/partitioning.py; by default, refuse_any_suspect, any suspect does); else
core/islanding.decide with the portfolio. "Steered" = the cut set, or split/no split, differs from the clean bag's
decision under the same pipeline; a refusal is never steered (it commands nothing). The attacks (sim/attacks.py)
start at the bag's first event, whose own frame still shows the grid at rest; 'current+1' is the CT ratio error
from the next frame, inside the event. For each attack the table also gives what it did to the estimate (the
attacked machine's angle against the clean run's, until it was excluded) and how many of the attacked station's
frames carried no usable angle (voltage below core/bad_data's 0.2 pu floor): why an attack was not seen, and
whether it could have steered.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from controlled_islanding.core.bad_data import BadDataDetector
from controlled_islanding.core.coherency import DTWCoherency
from controlled_islanding.core.dse import MachineData, RotorAngleDSE
from controlled_islanding.core.islanding import decide
from controlled_islanding.core.portfolio import PortfolioPartition
from controlled_islanding.sim.attacks import ATTACKS, GAP_S, attack, with_tve_noise

_FIELDS = ('v_mag_pu', 'v_angle_rad', 'i_mag_pu', 'i_angle_rad', 'frequency_hz', 'rocof_hz_per_s')


@dataclass
class Outcome:
    """One run of the pipeline on (possibly attacked) channels.

    Attributes:
        flagged: Station -> (reason, first time tag flagged, s).
        refused: Whether the request was refused for suspect data.
        split: The decision splits.
        cut: Cut branch ids, sorted.
        suspect_generators: Generators excluded at the request.
        error: Why no decision could be computed ('' when one was).
        tags_s, angles_rad: The frames up to the request and the generators' angles (screen's).

    """

    flagged: dict[str, tuple[str, float]] = field(default_factory=dict)
    refused: bool = False
    split: bool = False
    cut: tuple[str, ...] = ()
    suspect_generators: tuple[str, ...] = ()
    error: str = ''
    tags_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    angles_rad: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def key(self) -> tuple:
        """Return what 'steered' compares."""
        return (self.split, self.cut)


@dataclass
class AttackRow:
    """One attack on one bag.

    Attributes:
        angle_moved_deg: The largest change, from the attack's start to the request, of an attacked machine's
            rotor angle as the graph estimates it, against the clean bag's, deg (NaN where it was excluded).
        low_voltage_share: Share of the attacked stations' frames from the attack's start to the request whose
            voltage is below the frequency test's floor (core/bad_data's angle_floor_pu): frames that carry no
            usable angle.

    """

    bag: str
    attack: str
    stations: tuple[str, ...]
    start_s: float
    request_s: float
    outcome: Outcome
    clean: Outcome
    angle_moved_deg: float = math.nan
    low_voltage_share: float = math.nan

    @property
    def steered(self) -> bool:
        """The decision differs from the clean one and is not a refusal."""
        return not self.outcome.refused and self.outcome.key() != self.clean.key()

    @property
    def flagged_in_time(self) -> bool:
        """Every attacked station flagged before the request."""
        return all(s in self.outcome.flagged and self.outcome.flagged[s][1] <= self.request_s for s in self.stations)

    def time_to_flag_s(self) -> list[float]:
        """Seconds from the attack's start to each attacked station's first flag (NaN: never)."""
        return [self.outcome.flagged[s][1] - self.start_s if s in self.outcome.flagged else math.nan
                for s in self.stations]


def screen(bag, channels, *, params: dict, until_s: float = math.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                              dict[str, tuple[str, float]]]:
    """Judge every frame up to `until_s` as pmu_ingestion does.

    core/bad_data's tests on every station with data, then core/dse's filter on each generator's channel (a
    suspect station compared with the filter's prediction, never taken), then the filter's innovation test.

    Returns:
        Time tags (n,); angles (n, generators), NaN without usable data or with a suspect station; suspect
        (n, generators); station -> (reason, first time tag flagged, s).

    """
    gens = bag.grid.generators
    cols = [bag.pmu_column(g.name, g.bus) for g in gens]
    station_of = [bag.station_ids[c] for c in cols]
    det = BadDataDetector()
    dse = RotorAngleDSE(model=str(params.get('dse_model', 'auto')), innovation_gate=det.nis_bound).fit(
        MachineData.of_generators(gens))
    scheduled: dict[str, float] = {}
    for g, sid in zip(gens, station_of, strict=True):
        scheduled[sid] = scheduled.get(sid, 0.0) + g.p_mw / bag.grid.base_mva
    sched = np.array([scheduled.get(sid, np.nan) for sid in channels.station_ids])
    buses = np.asarray(channels.buses, dtype=np.int64)
    angles_at_rest = bag.grid.bus_angles_at(buses)
    flagged: dict[str, tuple[str, float]] = {}
    tags = np.asarray(channels.tag_s, dtype=float)
    rows = np.flatnonzero(np.asarray(bag.frame_present) & (tags <= until_s + 1e-9))
    angles, suspect = np.full((len(rows), len(gens)), np.nan), np.zeros((len(rows), len(gens)), dtype=bool)
    for n, k in enumerate(rows):
        t = float(tags[k])
        values = [np.asarray(getattr(channels, f))[k] for f in _FIELDS]
        usable = np.isfinite(values[0]) & np.isfinite(values[2])
        idx = np.flatnonzero(usable)
        if idx.size:
            det.judge(t, [channels.station_ids[j] for j in idx], *(v[idx] for v in values), sched[idx], buses[idx],
                      angles_at_rest[idx], nominal_hz=bag.grid.freq_hz)
        bad = np.array([s in det.suspects() for s in station_of])
        a = dse.update(t, values[0][cols], values[1][cols], values[2][cols], values[3][cols], usable[cols] & ~bad)
        suspects = det.innovations(t, station_of, dse.nis_)
        for sid, why in suspects.items():
            flagged.setdefault(sid, (why, t))
        suspect[n] = [s in suspects for s in station_of]
        angles[n] = np.where(usable[cols] & ~suspect[n], a, np.nan)
    return tags[rows], angles, suspect, flagged


def run_pipeline(bag, channels, *, params: dict, max_suspect_share: float = 0.25,
                 refuse_any_suspect: bool = True) -> Outcome:
    """Decide at the bag's first request from `channels` (see the module docstring)."""
    grid = bag.grid
    gens = grid.generators
    request_s = float(bag.request_t_s[0])
    window_s = float(params.get('window_s', 3.0))
    out = Outcome()
    tags_arr, block, bad_block, out.flagged = screen(bag, channels, params=params, until_s=request_s)
    out.tags_s, out.angles_rad = tags_arr, block
    in_window = tags_arr >= request_s - window_s - 1e-9
    excluded = bad_block[in_window].any(axis=0)
    seen = (np.isfinite(block[in_window]).sum(axis=0) >= int(params.get('min_samples', 30))) & ~excluded
    out.suspect_generators = tuple(g.name for g, x in zip(gens, excluded, strict=True) if x)
    if out.suspect_generators and (refuse_any_suspect or len(out.suspect_generators) > max_suspect_share * len(gens)):
        out.refused = True
        return out
    names = [g.name for g, s in zip(gens, seen, strict=True) if s]
    unobserved = [g.name for g, s in zip(gens, seen, strict=True) if not s]
    try:
        band = int(params.get('dtw_band_samples', 30)) or None
        model = DTWCoherency(max_groups=int(params.get('max_groups', 8)), window=band,
                             k_rule=str(params.get('k_rule', 'separation')))
        series = [block[in_window][:, j] for j in np.flatnonzero(seen)]
        labels = [0] * len(series) if len(series) == 1 else [int(x) for x in model.fit(series).labels_]
        decision = decide(bag.grid_at(request_s + 1e-9), dict(zip(names, labels, strict=True)), PortfolioPartition(),
                          unobserved=unobserved)
    except Exception as exc:  # a failed split is a result here: the node would refuse it (REFUSED_FAILED)
        out.error = str(exc)[:200]
        out.refused = True
        return out
    out.split = bool(decision.split)
    out.cut = tuple(sorted(b.branch_id for b in decision.cut_branches))
    return out


def _scenario(bag):
    """Return the scenario file beside the bag, loaded (None when there is none)."""
    from pathlib import Path

    from controlled_islanding.sim.manifest import entry_for_bag
    from controlled_islanding.sim.scenario import load_scenario

    entry = entry_for_bag(bag.path) or {}
    path = Path(bag.path).parent / str(entry.get('scenario', f'{Path(bag.path).name}.yaml'))
    return load_scenario(path) if path.is_file() else None


def attack_start_s(bag) -> float:
    """Return the first event (fault or trip), s after t0, from the scenario file beside the bag (else its request)."""
    scenario = _scenario(bag)
    times = [] if scenario is None else [f.start_s for f in scenario.faults] + [t.t_s for t in scenario.trips]
    return float(min(times)) if times else float(bag.request_t_s[0])


def stations_per_group(bag) -> list[str]:
    """One PMU station per true coherent group (the machine of each group with the largest inertia)."""
    groups: dict[int, list] = {}
    for g in bag.grid.generators:
        groups.setdefault((bag.truth_groups or {}).get(g.name, 0), []).append(g)
    out = []
    for _, members in sorted(groups.items()):
        best = max(members, key=lambda g: (g.m_s if np.isfinite(g.m_s) else 0.0, g.name))
        out.append(bag.station_ids[bag.pmu_column(best.name, best.bus)])
    return out


def sweep_bag(bag, start_s: float, *, params: dict, attacks: Sequence[str] = ATTACKS,
              progress: Callable[[str], None] | None = None) -> list[AttackRow]:
    """Every attack on a station of each true group of one bag (ramp2: on the first two)."""
    clean = run_pipeline(bag, bag, params=params)
    stations = stations_per_group(bag)
    request_s = float(bag.request_t_s[0])
    rows = []
    # The frame at the event's own time tag still shows the grid at rest, where the dispatch test sees a CT ratio
    # error: 'current+1' starts it one frame later, in the event, where only the filter can.
    runs = [(name, start_s) for name in attacks]
    if 'current' in attacks:
        runs.insert(runs.index(('current', start_s)) + 1, ('current+1', start_s + 1.0 / bag.rate_fps))
    for label, start in runs:
        name = label.removesuffix('+1')
        if name == 'gap_step' and request_s <= start + GAP_S:
            continue  # back only after the request: a silent station, which the observability sweep judges
        targets = [tuple(stations[:2])] if name == 'ramp2' else [(s,) for s in stations]
        if name == 'ramp2' and len(stations) < 2:
            continue
        for target in targets:
            attacked = attack(bag, name, list(target), start)
            outcome = run_pipeline(bag, attacked, params=params)
            rows.append(AttackRow(bag.path.name, label, target, start, request_s, outcome, clean,
                                  *_effect(bag, attacked, target, start, request_s, outcome, clean)))
            if progress:
                progress(f'{bag.path.name} {name} {",".join(target)}')
    return rows


def _effect(bag, attacked, stations, start_s: float, request_s: float, outcome: Outcome,
            clean: Outcome) -> tuple[float, float]:
    """AttackRow's angle_moved_deg and low_voltage_share."""
    tags = np.asarray(bag.tag_s)
    frames = np.flatnonzero(np.asarray(bag.frame_present) & (tags >= start_s - 1e-9) & (tags <= request_s + 1e-9))
    cols = [bag.station_ids.index(s) for s in stations]
    v = np.abs(np.asarray(attacked.v_mag_pu)[np.ix_(frames, cols)])
    v = v[np.isfinite(v)]
    low = float(np.mean(v < BadDataDetector().angle_floor_pu)) if v.size else math.nan
    gens = [j for j, g in enumerate(bag.grid.generators) if bag.station_ids[bag.pmu_column(g.name, g.bus)] in stations]
    if outcome.angles_rad.shape != clean.angles_rad.shape or not gens:
        return math.nan, low
    rows = outcome.tags_s >= start_s - 1e-9
    # Wrapped: estimates whole turns apart are one angle (a 20 deg step read as 701 deg moved).
    moved = np.abs(np.angle(np.exp(1j * (outcome.angles_rad[np.ix_(rows, gens)]
                                         - clean.angles_rad[np.ix_(rows, gens)]))))
    return (float(np.degrees(np.nanmax(moved))) if np.isfinite(moved).any() else math.nan), low


def false_alarms(bag, *, params: dict, noise_tve: float = 0.01, seed: int = 0) -> tuple[int, int]:
    """Stations flagged over the whole clean bag, and over it with TVE noise brought up to `noise_tve` in all.

    The bag's phasors already carry its scenario's noise; the noise added is what takes the total to noise_tve
    (C37.118.1's bound), not noise_tve on top of it, which would be PMUs outside the standard the tests assume.
    """
    scenario = _scenario(bag)
    present = scenario.noise_tve if scenario is not None else 0.0
    counts = []
    for channels in (bag, with_tve_noise(bag, noise_tve, seed, present_tve=present)):
        counts.append(len(screen(bag, channels, params=params)[3]))
    return counts[0], counts[1]


def table(rows: Sequence[AttackRow]) -> list[str]:
    """Return the sweep as a Markdown table."""
    lines = ['| bag | attack | station(s) | clean decision | attacked decision | steered | flagged before request '
             '| time to flag, s (test) | angle moved, deg | frames below 0.2 pu |', '|---' * 10 + '|']

    def show(o: Outcome) -> str:
        if o.refused:
            return 'refused: suspect data' if not o.error else 'refused: failed'
        return ('cut ' + ', '.join(o.cut)) if o.split else 'no split'

    def num(x: float, fmt: str) -> str:
        return '-' if math.isnan(x) else format(x, fmt)

    for r in rows:
        ttf = ', '.join('never' if math.isnan(x) else f'{x:.3f} ({r.outcome.flagged[s][0]})'
                        for s, x in zip(r.stations, r.time_to_flag_s(), strict=True))
        lines.append(f'| {r.bag} | {r.attack} | {", ".join(r.stations)} | {show(r.clean)} | {show(r.outcome)} | '
                     f'{"yes" if r.steered else "no"} | {"yes" if r.flagged_in_time else "no"} | {ttf} | '
                     f'{num(r.angle_moved_deg, ".1f")} | {num(100 * r.low_voltage_share, ".0f")} % |')
    return lines


def _apart_line(what: str, rows: Sequence[AttackRow]) -> str:
    steered = [f'{r.bag} {r.stations[0]}' for r in rows if r.steered]
    return (f'- {what}: {len(rows)}; steered {len(steered)}' + (f' ({", ".join(steered)})' if steered else '')
            + f'; flagged before the request in {sum(r.flagged_in_time for r in rows)}')


def report(rows: Sequence[AttackRow], alarms: Sequence[tuple[str, int, int]]) -> list[str]:
    """Return the figures, the table and the false alarms, as Markdown lines."""
    apart = {'ramp_back': "ramp_back (-2 rad/s, against a faulted machine's own acceleration)",
             'gap_step': f'gap_step (silent {GAP_S:g} s from the event, longer than the filter bridges, then back '
                         'half a cycle off)'}
    single = [r for r in rows if r.attack not in ('ramp2', 'current+1', *apart)]
    pair = [r for r in rows if r.attack == 'ramp2']
    late = [r for r in rows if r.attack == 'current+1']
    refused = sum(r.outcome.refused and not r.outcome.error for r in rows)
    lines = [f'- single-station attacks: {len(single)}; steered {sum(r.steered for r in single)}; every attacked '
             f'station flagged before the request in {sum(r.flagged_in_time for r in single)}',
             f'- two-station ramp: {len(pair)}; steered {sum(r.steered for r in pair)}; both flagged before the '
             f'request in {sum(r.flagged_in_time for r in pair)}',
             f"- current x1.5 from the event's first frame (current+1): {len(late)}; steered "
             f'{sum(r.steered for r in late)}; flagged before the request in {sum(r.flagged_in_time for r in late)}',
             *(_apart_line(what, [r for r in rows if r.attack == name]) for name, what in apart.items()),
             f'- refused for suspect data: {refused} of {len(rows)}; refused because the split failed: '
             f'{sum(bool(r.outcome.error) for r in rows)}',
             f'- false alarms: stations flagged on clean bags {sum(a[1] for a in alarms)}, with TVE noise brought to '
             f'1 % {sum(a[2] for a in alarms)} (over {len(alarms)} bags)']
    missed = [r for r in single if not r.flagged_in_time]
    if missed:
        worst = max(missed, key=lambda r: -1.0 if math.isnan(r.angle_moved_deg) else r.angle_moved_deg)
        lines.append(f'- single-station attacks not flagged before the request: {len(missed)}, of which steered '
                     f"{sum(r.steered for r in missed)}; the largest move of an attacked machine's estimated angle "
                     'among them: '
                     f'{worst.angle_moved_deg:.1f} deg ({worst.bag}, {worst.attack} on {", ".join(worst.stations)})')
    lines.append('')
    lines += table(rows)
    lines += ['', '| bag | stations flagged, clean | with TVE noise brought to 1 % |', '|---|---|---|']
    lines += [f'| {name} | {clean} | {noisy} |' for name, clean, noisy in alarms]
    return lines


def write_report(lines: Sequence[str], path, *, command: str) -> None:
    """Write the generated page."""
    from pathlib import Path

    from controlled_islanding.atomic import write_text

    body = ['# PMU attack sweep: does one spoofed or failing station steer the cut?', '',
            f'Generated by `{command}`; do not edit by hand (code: `controlled_islanding/evaluation/attack_sweep.py`).',
            '',
            'What one spoofed or failing PMU station does to the decision (evaluation/attack_sweep.py: the '
            "graph's pipeline offline, frame by frame; attacks of sim/attacks.py from each bag's first event; "
            'bad-data tests of core/bad_data.py).', '', *lines, '']
    write_text(Path(path), '\n'.join(body))


def sweep(bags, *, seed: int = 0, progress: Callable[[str], None] | None = None,
          done: Callable[[], object] | None = None) -> list[str]:
    """Run the sweep and the false alarms on every bag, with the coherency node's parameters; return the page lines."""
    from controlled_islanding.evaluation.cases import coherency_node_parameters

    params = coherency_node_parameters()
    rows, alarms = [], []
    for bag in bags:
        alarms.append((bag.path.name, *false_alarms(bag, params=params, seed=seed)))
        rows += sweep_bag(bag, attack_start_s(bag), params=params, progress=progress)
        if done:
            done()
    return report(rows, alarms)
