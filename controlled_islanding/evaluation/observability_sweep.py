"""Observability sweeps: how the decision holds up when only some generators have a PMU (issue 17).

For one scenario (rotor angles over the run and its truth, `coherency_rules.Scenario`) and the grid at the
request, each draw keeps the PMUs of a set of generators: the largest machines first, or a seeded random set
at a coverage. Coherency groups the observed machines over the window ending at the request; the unobserved
are left unconstrained in eqs. 4-8 (`core.islanding.decide`) and, as the alternative, given the group the
reactance rule infers (`core.observability.infer_groups`). The islands come from both partitioners the
partitioning node offers: the paper's constrained spectral clustering (`spectral`) and the portfolio that keeps
the lower of it and the exact optimum within a fixed budget (`portfolio`, the node's default;
`core/portfolio.py`). Each draw is scored against:
- the truth of the observed machines (their final grouping, restricted to them);
- the exact MILP optimum under the same groups, the unobserved unconstrained there too;
- the island balance (load to shed, MW, of the portfolio's islands).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from controlled_islanding import atomic
from controlled_islanding.core.grid import Grid
from controlled_islanding.core.islanding import decide
from controlled_islanding.core.milp import ExactPartition, MilpError, gap_pct
from controlled_islanding.core.observability import infer_groups, largest_first, random_placement
from controlled_islanding.core.portfolio import PortfolioPartition
from controlled_islanding.core.spectral import SpectralError
from controlled_islanding.evaluation.coherency_rules import Scenario, blocks, groups_at

COVERAGES = (1.0, 0.75, 0.5, 0.25)


class SweepError(ValueError):
    """A sweep asked for with bad settings."""


@dataclass
class Draw:
    """One PMU placement and what the graph's core would decide with it.

    Attributes:
        observed: Generators with a PMU.
        groups_right: The observed machines' groups equal their truth.
        inferred_right: Observed and inferred groups together equal the whole truth.
        k: Number of groups found among the observed.
        disrupted_mw: Eq. 9 of the spectral decision, MW (None: it failed; see error).
        portfolio_mw: Eq. 9 of the portfolio's decision, MW (None: it failed).
        portfolio_exact: The portfolio kept its exact member's islands (a cut below the spectral one).
        optimum_mw: The MILP's eq. 9 under the same groups, MW (None: no optimum within its limit).
        shed_mw: Load to shed over the portfolio's islands, MW.
        inferred_disrupted_mw: Eq. 9 with the inferred groups as constraints, MW.
        error: Why the decision failed ('' if it did not).
        right_from_s: When the groups are wrong at the request: the first later frame, before the first pole slip,
            whose window gives the right groups, s (None: none, or not looked for; largest-machines draws only).

    """

    observed: tuple[str, ...]
    groups_right: bool
    inferred_right: bool
    k: int
    disrupted_mw: float | None = None
    portfolio_mw: float | None = None
    portfolio_exact: bool = False
    optimum_mw: float | None = None
    shed_mw: float | None = None
    inferred_disrupted_mw: float | None = None
    error: str = ''
    right_from_s: float | None = None

    @property
    def gap_pct(self) -> float | None:
        """Return the spectral decision's disruption above the MILP optimum, % (0 when both are 0)."""
        if self.disrupted_mw is None or self.optimum_mw is None:
            return None
        return gap_pct(self.disrupted_mw, self.optimum_mw)

    @property
    def portfolio_gap_pct(self) -> float | None:
        """Return the portfolio decision's disruption above the MILP optimum, % (0 when both are 0)."""
        if self.portfolio_mw is None or self.optimum_mw is None:
            return None
        return gap_pct(self.portfolio_mw, self.optimum_mw)


@dataclass
class SweepRow:
    """All draws of one placement rule at one coverage on one scenario (its request and first pole slip, s)."""

    scenario: str
    placement: str
    coverage: float
    draws: list[Draw] = field(default_factory=list)
    request_s: float | None = None
    first_pole_slip_s: float | None = None


def score_draw(scenario: Scenario, grid: Grid, observed: Sequence[str], *, window_s: float, max_groups: int,
               k_rule: str, dtw_band: int | None, time_limit_s: float) -> Draw:
    """Group the observed machines at the request and decide; see the module docstring."""
    row = {n: i for i, n in enumerate(scenario.generator_names)}
    observed = tuple(sorted(observed))
    unobserved = sorted(set(scenario.generator_names) - set(observed))
    seen = replace(scenario, generator_names=list(observed), angles_rad=scenario.angles_rad[[row[n] for n in observed]])
    groups = groups_at(seen, scenario.request_s, rule=k_rule, window_s=window_s, max_groups=max_groups,
                       dtw_band=dtw_band)
    truth = scenario.truth
    draw = Draw(observed, blocks(groups) == blocks({n: truth[n] for n in observed}), False,
                len(set(groups.values())))
    try:
        inferred = infer_groups(grid, groups, unobserved)
        draw.inferred_right = blocks({**groups, **inferred}) == blocks(truth)
        draw.disrupted_mw = decide(grid, groups, unobserved=unobserved).disrupted_mw
        portfolio = PortfolioPartition()
        decision = decide(grid, groups, portfolio, unobserved=unobserved)
        draw.portfolio_mw = decision.disrupted_mw
        draw.portfolio_exact = getattr(portfolio, 'winner_', '') == 'milp'
        draw.shed_mw = float(sum(decision.island_shed_mw))
        draw.inferred_disrupted_mw = decide(grid, {**groups, **inferred}).disrupted_mw
    except (ValueError, SpectralError) as exc:
        draw.error = str(exc)
        return draw
    if len(set(groups.values())) < 2:
        draw.optimum_mw = 0.0
        return draw
    try:
        exact = ExactPartition(time_limit_s=time_limit_s).fit(grid, groups)
        draw.optimum_mw = float(exact.disruption_mw_) if exact.optimal_ else None
    except MilpError:
        draw.optimum_mw = None
    return draw


def first_right_s(scenario: Scenario, observed: Sequence[str], *, window_s: float, max_groups: int, k_rule: str,
                  dtw_band: int | None) -> float | None:
    """Return the first frame after the request, before the first pole slip, at which the observed groups are right, s.

    A request that late would still come before any machine slips a pole; None when no frame does (or the scenario
    never slips).
    """
    slip = scenario.first_pole_slip_s
    if slip is None:
        return None
    row = {n: i for i, n in enumerate(scenario.generator_names)}
    seen = replace(scenario, generator_names=list(observed), angles_rad=scenario.angles_rad[[row[n] for n in observed]])
    truth = blocks({n: scenario.truth[n] for n in observed})
    for end in scenario.t_s[(scenario.t_s > scenario.request_s + 1e-9) & (scenario.t_s < slip - 1e-9)]:
        groups = groups_at(seen, float(end), rule=k_rule, window_s=window_s, max_groups=max_groups, dtw_band=dtw_band)
        if blocks(groups) == truth:
            return float(end)
    return None


def sweep(scenario: Scenario, grid: Grid, *, coverages: Sequence[float] = COVERAGES, draws: int = 5, seed: int = 0,
          window_s: float = 3.0, max_groups: int = 4, k_rule: str, dtw_band: int | None = None,
          time_limit_s: float = 20.0, progress: Callable[[str], None] | None = None) -> list[SweepRow]:
    """Run the largest-machines placement and `draws` seeded random placements at each coverage.

    Raises:
        SweepError: No coverage, a coverage outside (0, 1], or fewer than one draw.

    """
    if not coverages or any(not 0.0 < c <= 1.0 for c in coverages):
        raise SweepError(f'coverages must be fractions in (0, 1], got {list(coverages)}')
    if draws < 1:
        raise SweepError(f'draws must be at least 1, got {draws}')
    settings = dict(window_s=window_s, max_groups=max_groups, k_rule=k_rule, dtw_band=dtw_band,
                    time_limit_s=time_limit_s)
    rng = np.random.default_rng(seed)
    rows = []
    for coverage in coverages:
        if progress:
            progress(f'{scenario.name}: {coverage:.0%} of the PMUs')
        largest = SweepRow(scenario.name, 'largest machines', coverage, request_s=scenario.request_s,
                           first_pole_slip_s=scenario.first_pole_slip_s)
        draw = score_draw(scenario, grid, largest_first(grid, coverage), **settings)
        if not draw.groups_right:
            draw.right_from_s = first_right_s(scenario, draw.observed, window_s=window_s, max_groups=max_groups,
                                              k_rule=k_rule, dtw_band=dtw_band)
        largest.draws.append(draw)
        rows.append(largest)
        if coverage < 1.0:
            rand = SweepRow(scenario.name, 'random', coverage)
            rand.draws = [score_draw(scenario, grid, random_placement(grid, coverage, rng), **settings)
                          for _ in range(draws)]
            rows.append(rand)
    return rows


def _median(values: list[float]) -> str:
    return f'{float(np.median(values)):.1f}' if values else '-'


def _gaps(values: list[float | None]) -> str:
    gaps = [g for g in values if g is not None]
    return f'{_median(gaps)} / {max(gaps):.1f}' if gaps else '- / -'


def table(rows: Sequence[SweepRow]) -> list[str]:
    """Return the markdown table of a sweep, one line per scenario, placement and coverage."""
    out = ['| scenario | PMUs | placement | draws | observed groups right | decided | split '
           '| spectral cut vs MILP, median / max % | portfolio cut vs MILP, median / max % | exact kept '
           '| load shed, median MW | inferred groups right | inferred cut, median MW |',
           '|---|---:|---|---:|---:|---:|---:|---|---|---:|---:|---:|---:|']
    for r in rows:
        n = len(r.draws)
        out.append(
            f'| {r.scenario} | {r.coverage:.0%} | {r.placement} | {n} | {sum(d.groups_right for d in r.draws)} / {n} '
            f'| {sum(not d.error for d in r.draws)} / {n} | {sum(d.k > 1 and not d.error for d in r.draws)} / {n} '
            f'| {_gaps([d.gap_pct for d in r.draws])} | {_gaps([d.portfolio_gap_pct for d in r.draws])} '
            f'| {sum(d.portfolio_exact for d in r.draws)} / {n} '
            f'| {_median([d.shed_mw for d in r.draws if d.shed_mw is not None])} '
            f'| {sum(d.inferred_right for d in r.draws)} / {n} '
            f'| {_median([d.inferred_disrupted_mw for d in r.draws if d.inferred_disrupted_mw is not None])} |')
    return out


def acceptance(rows: Sequence[SweepRow], coverage: float = 0.5, within_pct: float = 10.0) -> list[str]:
    """Return issue 17's check per scenario, for each partitioner.

    Met when, at `coverage` of the PMUs placed largest machines first, the observed groups are right and the cut
    is within `within_pct` % of the optimum under the same groups.
    """
    out = []
    for r in rows:
        if r.placement != 'largest machines' or abs(r.coverage - coverage) > 1e-9:
            continue
        d = r.draws[0]
        verdict = []
        for name, gap in (('spectral', d.gap_pct), ('portfolio', d.portfolio_gap_pct)):
            ok = d.groups_right and not d.error and gap is not None and gap <= within_pct
            verdict.append(f'{name} {"meets" if ok else "fails"} ({"-" if gap is None else f"{gap:.1f}"} %)')
        out.append(f'- {r.scenario}: groups {"right" if d.groups_right else "wrong" + _late(r, d)}; '
                   + ', '.join(verdict))
    return out


def _late(row: SweepRow, draw: Draw) -> str:
    """Return ' (right from ...)' saying when wrong groups became right, if the row can say."""
    if row.request_s is None or row.first_pole_slip_s is None or row.first_pole_slip_s <= row.request_s:
        return ''
    if draw.right_from_s is None:
        return f' (and still wrong up to the first pole slip, {row.first_pole_slip_s:.3f} s)'
    return (f' (right from {draw.right_from_s:.3f} s, {1000 * (draw.right_from_s - row.request_s):.0f} ms after the '
            f'request, {1000 * (row.first_pole_slip_s - draw.right_from_s):.0f} ms before the first pole slip)')


def write_report(rows: Sequence[SweepRow], path: Path, *, command: str, k_rule: str, window_s: float) -> Path:
    """Write the sweep page (docs/observability.md), atomically."""
    errors = sorted({(r.scenario, f'{r.coverage:.0%}', d.error) for r in rows for d in r.draws if d.error})
    lines = ['# Partial observability: decisions with PMUs at some generators only', '',
             f'Generated by `{command}`; do not edit by hand '
             '(code: `controlled_islanding/evaluation/observability_sweep.py`).',
             '', __doc__.split('\n\n', 1)[1].strip(), '',
             f'Coherency: DTW with the `{k_rule}` k rule over the {window_s:g} s window ending at the request. '
             '"observed groups right": the observed machines grouped exactly as their final grouping (vacuously so '
             'when one machine is observed). "decided": the constrained spectral clustering gave islands. "split": '
             'the observed machines formed two groups or more, so the grid is split. Cut vs MILP: eq. 9 of each '
             "partitioner's decision above the exact optimum under the same groups (draws whose MILP stopped at its "
             'time limit are left out). "exact kept": draws where the portfolio kept its exact member\'s islands, '
             'a cut below the spectral one. '
             '"inferred": the unobserved machines given the group of the nearest observed machine in effective '
             'reactance; right when every machine, observed or inferred, is in its true group.', '',
             *table(rows), '',
             "Issue 17's acceptance, per scenario: with 50% of the PMUs, largest machines first, the observed "
             'groups match the truth and the cut is within 10% of the optimum under the same observability. Where '
             'the groups are wrong at the request, the line says from which later frame, before the first pole slip, '
             'the same machines give the right groups (`first_right_s`).', '',
             *acceptance(rows), '']
    if errors:
        lines += ['Decisions that failed:', '']
        lines += [f'- {name} at {cov}: {err}' for name, cov, err in errors]
        lines.append('')
    atomic.write_text(path, '\n'.join(lines))
    return path
