"""The best found: an offline search for the most load served over request times and cuts (testbed --oracle).

No graph: every candidate is one whole ANDES run through sim/closed_loop.run_offline, with the closed loop's own
rules (the cut opens breaker_operating_s after the request, in one step; shed_delay_s later each island sheds
its planned load or rejects its surplus generation; the grid's UFLS and the PRC-024 judge as in every run).
There is no graph latency: this is the best the scheme's actions could have done, not what a graph would.

What it searches:
- Request times: from the clearing of the scenario's first fault (its first trip when it has no fault) to the
  first pole slip of its no-action run (sim/truth.first_pole_slip_s: two machines more than pi rad apart), both
  ends included, evenly spaced at most max_step_s apart (request_times). A slip before the clearing leaves the
  clearing instant alone; a run with no slip leaves nothing to save, and only no action is run.
- Cuts, each a partition of the buses into islands (partitions equal up to island numbering are one):
  1. the exact MILP cut (core/milp.py) of each plausible grouping of the machines (neighbour_groupings): the
     truth grouping (sim/truth.truth_groups on the no-action run) and its neighbours, which are
     a. every merge of two of its groups (with three groups or more; two merged from two is no split);
     b. the max_moves single-machine moves to another group nearest by the truth's own measure, the
        complete-linkage distance max_q |d_p - d_q| from the machine to the other group's machines, taken on
        the rotor-angle deviations d = delta(t) - delta(0) at the end of the window (the first pole slip): what
        a grouping made at a request time in the window can see (the final deviations of a slipping run put
        every machine of the other group tens of rad away, alike); a move that would empty the machine's
        group is a merge, in a.; a move that no connected partition allows (no MILP cut) is passed over for
        the next nearest (pick_neighbours);
     c. the max_alone machines loosest in their group (largest mean distance |d_p - d_q| to the other machines
        of their group, at the same instant) each alone in a new group, passed over likewise;
  2. the spectral cut (core/spectral.py, the paper's method) of the truth grouping;
  3. the graph's own cut (the closed-loop decision's islands), when it split;
  and no action. Each grouping is solved once per topology (trips before the request out), the grid as a
  snapshot gives it (pre-fault flows, tripped branches at 0 MW), as the `milp` baseline of the testbed is.
- Every run ends at the same time, max(end_s, request_s + run_after_s, last request time + run_after_s), so
  every candidate is judged at the same instant with at least run_after_s after its cut.

Cost: a candidate is a run of the scenario's whole length (from t = 0; run_offline has no fork). The no-action run
of the testbed is reused when it already ends at that time, and so is every run of an earlier search of the same
simulation (`runs`: the testbed's five IEEE 39 G6-G7 variants differ only in their PMUs, so only the graph's cut
can differ between them). Candidates with the same partition at the same time
are run once, and a candidate whose upper bound (the pre-fault load less its planned shed: the judge only takes
load away, never adds) cannot beat the best found so far is not run (pruned); candidates go in the order of
their source (the truth's MILP cut, the graph's, the spectral, then the neighbours), request times ascending.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from controlled_islanding.core.grid import Grid
from controlled_islanding.core.islanding import evaluate_partition
from controlled_islanding.sim.closed_loop import LoopConfig, Outcome, run_offline
from controlled_islanding.sim.scenario import Scenario

log = logging.getLogger(__name__)

MAX_STEP_S = 0.05  # the largest spacing of request times (on all but the largest systems), s


class OracleError(ValueError):
    """The search cannot be set up: a scenario with no disturbance, or a bad setting."""


@dataclass(frozen=True)
class OracleSettings:
    """How wide the search is (see the module docstring).

    Attributes:
        max_step_s: Largest spacing of the request times, s (the report states the one used).
        max_moves: Single-machine moves of the truth grouping searched, nearest first.
        max_alone: Machines searched alone in a new group, loosest first.
        milp_time_limit_s: HiGHS's wall-clock limit per grouping, s (the testbed's `milp` baseline uses 60 s).
        remedies: Repeat a candidate whose ANDES run failed at 1/4, then 1/16, of the step (run_offline's
            remedies), as the closed loop's runs are. Off by default: the repeats cost 5 and 21 times a run from
            t = 0, two thirds of IEEE 39 G6-G7's search (49 of 74 min, 12 failed candidates); each failure is
            listed in the search's summary, and the best found is then the best of the runs that converged.

    """

    max_step_s: float = MAX_STEP_S
    max_moves: int = 6
    max_alone: int = 3
    milp_time_limit_s: float = 60.0
    remedies: bool = False


def request_times(start_s: float, stop_s: float, max_step_s: float) -> tuple[float, ...]:
    """Return the request times from start_s to stop_s (s, both included), evenly spaced at most max_step_s apart.

    stop_s before start_s leaves start_s alone.

    Raises:
        OracleError: max_step_s not positive, or a time not finite.

    """
    if not (max_step_s > 0 and math.isfinite(max_step_s)):
        raise OracleError(f'the step of the request times must be a positive number of s, got {max_step_s!r}')
    if not (math.isfinite(start_s) and math.isfinite(stop_s)):
        raise OracleError(f'request window {start_s!r} .. {stop_s!r} s is not finite')
    if stop_s <= start_s:
        return (float(start_s),)
    n = max(1, math.ceil((stop_s - start_s) / max_step_s - 1e-9))
    return tuple(float(start_s + (stop_s - start_s) * i / n) for i in range(n + 1))


def first_clearing_s(scenario: Scenario) -> float:
    """Return when the scenario's first disturbance is over, s: its first fault's clearing, else its first trip.

    Raises:
        OracleError: The scenario has neither.

    """
    if scenario.faults:
        return min(scenario.faults, key=lambda f: f.start_s).clear_s
    if scenario.trips:
        return min(t.t_s for t in scenario.trips)
    raise OracleError(f'{scenario.path}: no fault and no trip: no disturbance to search a response to')


def _numbered(labels: Sequence[int]) -> tuple[int, ...]:
    order: dict[int, int] = {}
    return tuple(order.setdefault(int(x), len(order)) for x in labels)


def neighbour_groupings(names: Sequence[str], groups: Sequence[int], dev_rad: Sequence[float]
                        ) -> list[tuple[str, str, tuple[int, ...]]]:
    """Return the truth grouping and every neighbour of it (see the module docstring), each once, truth first.

    Args:
        names: Machine names.
        groups: The truth group of each machine.
        dev_rad: Each machine's rotor-angle deviation d_p = delta_p(t) - delta_p(0) at the end of the request
            window (the first pole slip), rad.

    Returns:
        (kind: 'truth', 'merge', 'move' or 'alone'; what it is; group of each machine numbered in order of first
        appearance) per grouping: the truth, every merge, every move nearest first, every machine alone loosest
        first (pick_neighbours keeps the first of each kind that give a cut).

    """
    truth = _numbered(groups)
    d = np.asarray(dev_rad, dtype=float)
    k = max(truth) + 1 if truth else 0
    members = [[p for p, g in enumerate(truth) if g == h] for h in range(k)]

    def named(h: int) -> str:
        return '+'.join(names[p] for p in members[h][:2]) + (', ...' if len(members[h]) > 2 else '')

    out = [('truth', 'truth', truth)]
    if k >= 3:
        for a in range(k):
            for b in range(a + 1, k):
                out.append(('merge', f'groups of {named(a)} and {named(b)} merged',
                            _numbered([a if g == b else g for g in truth])))
    moves = sorted((float(np.max(np.abs(d[p] - d[members[h]]))), p, h) for p, g in enumerate(truth)
                   for h in range(k) if h != g and len(members[g]) > 1)
    for dist, p, h in moves:
        out.append(('move', f'{names[p]} moved to the group of {named(h)} ({dist:.2f} rad)',
                    _numbered([h if q == p else g for q, g in enumerate(truth)])))
    loose = sorted((-float(np.mean(np.abs(d[p] - d[[q for q in members[g] if q != p]]))), p)
                   for p, g in enumerate(truth) if len(members[g]) > 1)
    for neg, p in loose:
        out.append(('alone', f'{names[p]} alone ({-neg:.2f} rad from its group on average)',
                    _numbered([k if q == p else g for q, g in enumerate(truth)])))
    seen: set[tuple[int, ...]] = set()
    return [(kind, what, g) for kind, what, g in out if not (g in seen or seen.add(g))]


def pick_neighbours(ranked: Sequence[tuple[str, str, tuple[int, ...]]], max_moves: int, max_alone: int,
                    gives_cut: Callable[[str, tuple[int, ...]], bool]) -> list[tuple[str, str, tuple[int, ...]]]:
    """Return the truth, every merge, and the first max_moves moves and max_alone machines alone that give a cut.

    A move or a machine alone that no connected partition allows (gives_cut(what, groups) False) is passed over
    for the next, at most 3 x its kind's count of tries in all. The truth and the merges are kept whatever
    gives_cut says (a merge may give no cut: it is then said, and has no candidate).
    """
    cap = {'move': max_moves, 'alone': max_alone}
    kept: dict[str, int] = {}
    tries: dict[str, int] = {}
    out = []
    for kind, what, groups in ranked:
        if kind in cap:
            if kept.get(kind, 0) >= cap[kind] or tries.get(kind, 0) >= 3 * cap[kind]:
                continue
            tries[kind] = tries.get(kind, 0) + 1
            if not gives_cut(what, groups):
                continue
            kept[kind] = kept.get(kind, 0) + 1
        out.append((kind, what, groups))
    return out


def partition_key(bus_island: Mapping[int, int]) -> frozenset[frozenset[int]]:
    """Return a partition's islands as a set of bus sets: equal for partitions that differ only in numbering."""
    islands: dict[int, set[int]] = {}
    for bus, island in bus_island.items():
        islands.setdefault(int(island), set()).add(int(bus))
    return frozenset(frozenset(b) for b in islands.values())


@dataclass
class Candidate:
    """One partition at one request time, and every source that proposed it.

    Attributes:
        request_s: The request time, s (None: no action).
        bus_island: Island of every bus (None: no action).
        sources: What proposed it, e.g. 'milp of truth', 'graph', 'spectral of truth'.
        topology: The branches out of service at the request (the grid it is evaluated on).

    """

    request_s: float | None
    bus_island: dict[int, int] | None
    sources: list[str] = field(default_factory=list)
    topology: tuple[str, ...] = ()


def dedupe(candidates: Sequence[Candidate]) -> list[Candidate]:
    """Return one candidate per (partition, request time, topology), its sources merged, first seen first."""
    out: dict[Any, Candidate] = {}
    for c in candidates:
        key = (None if c.bus_island is None else partition_key(c.bus_island), c.request_s, c.topology)
        if key in out:
            out[key].sources += [s for s in c.sources if s not in out[key].sources]
        else:
            out[key] = Candidate(c.request_s, c.bus_island, list(c.sources), c.topology)
    return list(out.values())


@dataclass(frozen=True)
class Tried:
    """A candidate and what its run served.

    Attributes:
        candidate: The candidate.
        served_mw: Load served at the end, MW (None: not known, see outcome and pruned).
        bound_mw: The most it could serve, the pre-fault load less its planned shed, MW.
        cut_branch_ids: Its cut.
        outcome: Its run (None: pruned).
        pruned: Not run: its bound could not beat the best found before it.

    """

    candidate: Candidate
    served_mw: float | None
    bound_mw: float
    cut_branch_ids: tuple[str, ...] = ()
    outcome: Outcome | None = None
    pruned: bool = False


def pick_best(tried: Sequence[Tried]) -> Tried | None:
    """Return the candidate that served the most; ties go to no action, then the fewest branches, the earliest request.

    A run whose simulation failed served an unknown amount and is never picked. None when no run is known.
    """
    known = [t for t in tried if t.served_mw is not None]
    if not known:
        return None
    return min(known, key=lambda t: (-round(t.served_mw, 6), t.candidate.request_s is not None,
                                     len(t.cut_branch_ids), t.candidate.request_s or 0.0, sorted(t.candidate.sources)))


def run_candidate(scenario: Scenario, grid: Grid, bus_island: Mapping[int, int], request_s: float, label: str,
                  config: LoopConfig, beat_mw: float | None = None, remedies: bool = False,
                  ) -> tuple[Outcome | None, tuple[str, ...], float]:
    """Run one candidate: its islands and their remedial actions, through run_offline.

    The actions are evaluate_partition's (core/remedial.py, the decision's own rule: the load to shed per bus and
    the machines to trip), on the grid as it is at the request. The cut opens breaker_operating_s after request_s.
    scenario must already end where every candidate ends.

    Args:
        scenario: The scenario.
        grid: The grid at the request (pre-fault flows, trips before the request out).
        bus_island: Island of every bus.
        request_s: The request time, s.
        label: Name of the run.
        config: The closed loop's settings.
        beat_mw: The best load served found so far, MW: a candidate that cannot serve more is not run.
        remedies: Repeat a failed run at a smaller step (OracleSettings.remedies).

    Returns:
        (its run, or None when not run: nothing to open, or pruned; its cut; its bound: the pre-fault load less
        its planned shed, MW).

    """
    plan = evaluate_partition(grid, bus_island)
    bound_mw = float(sum(plan.island_load_mw) - sum(plan.island_shed_mw))
    if not plan.cut_branch_ids or (beat_mw is not None and bound_mw <= beat_mw):
        return None, plan.cut_branch_ids, bound_mw
    outcome = run_offline(replace(scenario, request_s=request_s), label, cut_branch_ids=plan.cut_branch_ids,
                          bus_island=plan.bus_island, actions=plan.remedial,
                          opened_s=request_s + config.breaker_operating_s, config=config, remedies=remedies)
    return outcome, plan.cut_branch_ids, bound_mw


@dataclass(frozen=True)
class OracleResult:
    """What the search found (see the module docstring).

    Attributes:
        best: The candidate that served the most (None: every run failed).
        window_s: First and last request time searched, s.
        step_s: The spacing of the request times, s (0 with one time).
        times_s: The request times searched, s.
        end_s: Where every run ends, s.
        first_pole_slip_s: The no-action run's first pole slip, s (None: none).
        groupings: (what it is, machine names per group) of every grouping searched.
        skipped: Groupings or cuts that gave no candidate, with why.
        tried: Every candidate, run or not, no action first.
        runs_made: ANDES runs the search made (no action's included, when it made them).
        runs_reused: Runs it took from earlier searches (the `runs` it was given).
        wall_s: Wall time of the search, s.
        remedies: Whether failed runs were repeated at a smaller step.

    """

    best: Tried | None
    window_s: tuple[float, float]
    step_s: float
    times_s: tuple[float, ...]
    end_s: float
    first_pole_slip_s: float | None
    groupings: tuple[tuple[str, tuple[tuple[str, ...], ...]], ...]
    skipped: tuple[str, ...]
    tried: tuple[Tried, ...]
    runs_made: int
    runs_reused: int
    wall_s: float
    remedies: bool = False

    def summary(self) -> dict[str, Any] | None:
        """Return the best run as the testbed's other runs (Outcome.summary) with its search; None: no best."""
        if self.best is None or self.best.outcome is None:
            return None
        return dict(self.best.outcome.summary(), label='oracle', request_s=self.best.candidate.request_s,
                    sources=list(self.best.candidate.sources), search=self.search_summary())

    def search_summary(self) -> dict[str, Any]:
        """Return what was searched and how, as JSON-ready data."""
        ran = [t for t in self.tried if t.outcome is not None]
        per_cut: dict[tuple[str, ...], Tried] = {}
        for t in ran:
            key = t.cut_branch_ids
            if t.served_mw is not None and (key not in per_cut or pick_best([per_cut[key], t]) is t):
                per_cut[key] = t
        return {
            'window_s': list(self.window_s), 'step_s': self.step_s, 'request_times': len(self.times_s),
            'end_s': self.end_s, 'first_pole_slip_s': self.first_pole_slip_s, 'remedies': self.remedies,
            'groupings': [{'what': w, 'groups': [list(g) for g in gs]} for w, gs in self.groupings],
            'skipped': list(self.skipped), 'candidates': len(self.tried) - 1,
            'runs': self.runs_made, 'runs_reused': self.runs_reused,
            'pruned': sum(t.pruned for t in self.tried),
            'failed': [f'{"+".join(t.candidate.sources)} at {t.candidate.request_s}: {t.outcome.simulation_failed}'
                       for t in ran if t.outcome.simulation_failed],
            'best_per_cut': [{'cut_branch_ids': list(c), 'load_served_mw': t.served_mw,
                              'request_s': t.candidate.request_s, 'sources': t.candidate.sources}
                             for c, t in sorted(per_cut.items(), key=lambda kv: -kv[1].served_mw)],
            'served_by_request_s': self.served_by_request_s(),
            'wall_s': self.wall_s}

    def served_by_request_s(self) -> list[list[float | None]]:
        """Return [request time, s; the most load a run asked then served, MW (None: none known)] per time searched.

        How late a request may come and still save what the best saves: a pruned candidate's load is unknown, so
        at a time where some were pruned the figure is a lower bound.
        """
        most: dict[float, float] = {}
        for t in self.tried:
            when = t.candidate.request_s
            if when is not None and t.served_mw is not None:
                most[when] = max(most.get(when, t.served_mw), t.served_mw)
        return [[when, most.get(when)] for when in self.times_s]


def _grid_at(base: Grid, changes: Sequence[tuple[float, str, bool]], t_s: float) -> tuple[tuple[str, ...], Grid]:
    out: set[str] = set()
    for at, bid, up in sorted(changes):
        if at <= t_s + 1e-9:
            (out.discard if up else out.add)(bid)
    return tuple(sorted(out)), base.with_outages(sorted(out))


def search(scenario: Scenario, config: LoopConfig | None = None, settings: OracleSettings = OracleSettings(), *,
           graph_islands: Mapping[int, int] | None = None, no_action: Outcome | None = None,
           runs: dict | None = None, say: Callable[[str], None] = log.info) -> OracleResult:
    """Search request times and cuts for the most load served (see the module docstring).

    Args:
        scenario: The scenario (its own request time sets only where the runs end).
        config: The closed loop's settings (breaker operating time, shed delay, run_after_s, the judge); None:
            the defaults.
        settings: How wide the search is.
        graph_islands: The closed-loop decision's island of every bus, when it split.
        no_action: The scenario's no-action run, if made already (reused when it ends where the runs end).
        runs: Runs of earlier searches, reused by simulation, request time, partition and config, and added to (the
            testbed keeps one for all its scenarios: variants of one simulation share every run but the graph's).
        say: Where progress goes.

    Raises:
        OracleError: The scenario has no disturbance, or a bad setting.
        ClosedLoopError: A run could not start.

    """
    from controlled_islanding.sim.truth import first_pole_slip_s, truth_groups

    start = time.monotonic()
    config = LoopConfig() if config is None else config
    runs = {} if runs is None else runs
    made = reused = 0
    clearing = first_clearing_s(scenario)
    base_end = max(scenario.end_s, scenario.request_s + config.run_after_s)
    if no_action is None or not (no_action.simulation_failed or abs(no_action.t_s[-1] - base_end) <= scenario.step_s):
        say(f'{scenario.name} oracle: no action (ANDES in-process)')
        no_action, done = _cached(runs, (scenario.simulation_key(), None, None, config),
                                  lambda: run_offline(scenario, 'no action', config=config))
        made, reused = made + done, reused + (not done)
    slip = first_pole_slip_s(no_action.t_s, no_action.delta_rad)
    times = () if slip is None else request_times(clearing, slip, settings.max_step_s)
    end_s = max(base_end, times[-1] + config.run_after_s) if times else base_end
    ending = replace(scenario, end_s=end_s)
    if not no_action.simulation_failed and abs(no_action.t_s[-1] - end_s) > scenario.step_s:
        say(f'{scenario.name} oracle: no action to {end_s:.3f} s, where every run ends (ANDES in-process)')
        no_action, done = _cached(runs, (ending.simulation_key(), None, None, config),
                                  lambda: run_offline(ending, 'no action', config=config))
        made, reused = made + done, reused + (not done)
    if no_action.judged_from_s != scenario.request_s and no_action.simulation_failed is None:
        no_action = no_action.rejudged(scenario.request_s, config)
    names = no_action.generator_names
    at_slip = int(np.searchsorted(no_action.t_s, times[-1] - 1e-9)) if times else 0
    ranked = neighbour_groupings(names, truth_groups(no_action.t_s, no_action.delta_rad),
                                 no_action.delta_rad[at_slip] - no_action.delta_rad[0]) if times else []
    candidates, grids, groupings, skipped, proposed = _candidates(scenario, names, ranked, times, graph_islands,
                                                                  settings, say)
    say(f'{scenario.name} oracle: {len(times)} request times {times[0]:.3f} .. {times[-1]:.3f} s, '
        f'{len(groupings)} groupings, {len(candidates)} distinct candidates (of {proposed} proposed)'
        if times else f'{scenario.name} oracle: no pole slip without action: only no action is searched')
    tried = [Tried(Candidate(None, None, ['no action']), no_action.load_served_mw, no_action.pre_fault_load_mw,
                   (), no_action)]
    best = pick_best(tried)
    ran_wall = []
    for i, c in enumerate(candidates):
        t0 = time.monotonic()
        assert c.request_s is not None and c.bus_island is not None
        key = (ending.simulation_key(), c.request_s, partition_key(c.bus_island), config, settings.remedies)
        if key in runs:
            outcome, cut, bound = runs[key]
            reused += 1
        else:
            outcome, cut, bound = run_candidate(ending, grids[c.topology], c.bus_island, c.request_s, 'oracle',
                                                config, None if best is None else best.served_mw,
                                                settings.remedies)
            if outcome is not None:
                runs[key] = (outcome, cut, bound)
                made += 1
                ran_wall.append(time.monotonic() - t0)
        served = None if outcome is None else outcome.load_served_mw
        tried.append(Tried(c, served, bound, cut, outcome, pruned=outcome is None and bool(cut)))
        best = pick_best(tried)
        left = (len(candidates) - i - 1) * (sum(ran_wall) / len(ran_wall)) if ran_wall else 0.0
        verdict = (('nothing to open' if not cut else f'pruned (it serves at most {bound:.0f} MW)')
                   if outcome is None else outcome.simulation_failed or f'{served:.0f} MW')
        say(f'{scenario.name} oracle {i + 1}/{len(candidates)}: request {c.request_s:.3f} s, cut '
            f'{", ".join(cut)} ({"; ".join(c.sources)}): {verdict}; best {best.served_mw if best else 0:.0f} MW; '
            f'{time.monotonic() - start:.0f} s so far, up to about {left:.0f} s left')
    named = tuple((what, tuple(tuple(n for n, g in zip(names, gs, strict=True) if g == h) for h in range(max(gs) + 1)))
                  for _, what, gs in groupings)
    return OracleResult(best=best, window_s=(times[0], times[-1]) if times else (clearing, clearing),
                        step_s=0.0 if len(times) < 2 else times[1] - times[0], times_s=times, end_s=end_s,
                        first_pole_slip_s=slip, groupings=named, skipped=tuple(skipped), tried=tuple(tried),
                        runs_made=made, runs_reused=reused, wall_s=time.monotonic() - start,
                        remedies=settings.remedies)


def _cached(runs: dict, key: tuple[Any, ...], run: Callable[[], Outcome]) -> tuple[Outcome, bool]:
    """Return the run under key, made now if it is not there yet, and whether it was made now."""
    if key in runs:
        return runs[key][0], False
    runs[key] = (run(), (), 0.0)
    return runs[key][0], True


def _candidates(scenario: Scenario, names: Sequence[str], ranked: Sequence[tuple[str, str, tuple[int, ...]]],
                times: Sequence[float], graph_islands: Mapping[int, int] | None, settings: OracleSettings,
                say: Callable[[str], None]) -> tuple[list[Candidate], dict[tuple[str, ...], Grid],
                                                     list[tuple[str, str, tuple[int, ...]]], list[str], int]:
    """Return the candidates in running order, each topology's grid, the groupings, what gave no cut, how many.

    The candidates are distinct (dedupe), the groupings those searched, the count that of the candidates proposed.
    Each grouping's MILP (and the truth's spectral) cut is solved once per topology; which neighbours are searched
    is settled on the topology of the first request time (pick_neighbours).
    """
    from controlled_islanding.core.milp import ExactPartition, MilpError
    from controlled_islanding.core.spectral import ConstrainedSpectralPartition, SpectralError
    from controlled_islanding.sim.andes_sim import prepare_case

    case = prepare_case(scenario)
    changes = case.scheduled_changes(scenario)
    skipped: list[str] = []
    proposed: list[Candidate] = []
    solved: dict[tuple[Any, ...], dict[int, int] | None] = {}
    grids: dict[tuple[str, ...], Grid] = {}

    def partition(kind: str, what: str, groups: tuple[int, ...], topology: tuple[str, ...]) -> dict[int, int] | None:
        key = (kind, groups, topology)
        if key not in solved:
            grid = grids[topology]
            present = {g.name for g in grid.generators}
            try:
                model = (ExactPartition(time_limit_s=settings.milp_time_limit_s) if kind == 'milp'
                         else ConstrainedSpectralPartition()).fit(
                             grid, {n: g for n, g in zip(names, groups, strict=True) if n in present})
                solved[key] = dict(zip(grid.buses, (int(x) for x in model.labels_), strict=True))
            except (MilpError, SpectralError, ValueError) as exc:  # this grouping gives no cut: said, not fatal
                solved[key] = None
                skipped.append(f'{kind} of {what}: {exc}')
                say(f'{scenario.name} oracle: no {kind} cut for {what}: {exc}')
        return solved[key]

    groupings: list[tuple[str, str, tuple[int, ...]]] = []
    if times:
        first, grids[first] = _grid_at(case.grid, changes, times[0])
        groupings = pick_neighbours(ranked, settings.max_moves, settings.max_alone,
                                    lambda what, groups: partition('milp', what, groups, first) is not None)
    for t in times:
        topology, grid = _grid_at(case.grid, changes, t)
        grids.setdefault(topology, grid)
        if graph_islands is not None:
            proposed.append(Candidate(t, {b: int(graph_islands.get(b, 0)) for b in grid.buses}, ['graph'], topology))
        for kind, (_, what, groups) in [('milp', groupings[0]), ('spectral', groupings[0])] + \
                [('milp', g) for g in groupings[1:]]:
            bus_island = partition(kind, what, groups, topology)
            if bus_island is not None and len(set(bus_island.values())) > 1:
                proposed.append(Candidate(t, bus_island, [f'{kind} of {what}'], topology))
    rank = ['milp of truth', 'graph', 'spectral of truth']
    candidates = sorted(dedupe(proposed), key=lambda c: (min(rank.index(s) if s in rank else len(rank)
                                                             for s in c.sources), c.request_s))
    return candidates, grids, groupings, skipped, len(proposed)
