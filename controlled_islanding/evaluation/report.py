"""How `controlled-islanding evaluate` shows evaluated cases: tables, JSON, figures, and one Markdown page of them all.

The tables have the shape of the paper's Tables IV and VIII; the page is docs/evaluation.md.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from controlled_islanding import atomic
from controlled_islanding.evaluation.bag_angles import generator_series, request_time_s
from controlled_islanding.evaluation.cases import CaseReport


def closed_loop_text(result: dict[str, Any] | None) -> str:
    """Return a closed-loop outcome as a table cell: islands survived / formed, and the first reason one was lost."""
    if result is None:
        return '-'
    if result.get('simulation_failed'):
        return result['simulation_failed'].split(':')[0]  # undetermined, not a loss
    islands = result['islands']
    ok = sum(1 for i in islands if i['survived'])
    why = next((f'island {i["island"]}: {i["why_not"][0]}' for i in islands if i['why_not']), '')
    return f'{ok}/{len(islands)}' + (f' ({why})' if why else '')


def _group_text(groups: Mapping[str, int] | None) -> str:
    if groups is None:
        return '-'
    out: dict[int, list[str]] = {}
    for name, k in groups.items():
        out.setdefault(k, []).append(name)
    return ' '.join('(' + ', '.join(out[k]) + ')' for k in sorted(out))


def _same_partition(a: Mapping[str, int], b: Mapping[str, int]) -> bool:
    def blocks(groups: Mapping[str, int]) -> set[frozenset[str]]:
        return {frozenset(n for n, k in groups.items() if k == g) for g in set(groups.values())}

    return blocks(a) == blocks(b)


def _num(value: float | None, fmt: str = '.2f') -> str:
    if value is None:
        return '-'
    if math.isinf(value):
        return 'inf'
    return format(value, fmt)


TABLE_COLUMNS = ('method', 'lines cut', 'islands formed', 'load/generation imbalance (MW)', 'load to shed (MW)',
                 'power flow disrupted (MW)', 'gap to MILP optimum (%)', 'compute time (ms)')


CLOSED_LOOP_COLUMN = 'closed loop: islands survived'


def columns(case: CaseReport) -> tuple[str, ...]:
    """Return the columns of a case's table: TABLE_COLUMNS, and the closed-loop column when it was run."""
    return TABLE_COLUMNS + ((CLOSED_LOOP_COLUMN,) if case.no_action is not None else ())


def table_rows(case: CaseReport) -> list[list[str]]:
    """Return the table cells of a case, one list per method, in columns(case) order."""
    out = []
    extra = case.no_action is not None
    for row in case.rows:
        d = row.decision
        if d is None:
            out.append([row.method] + ['-'] * 6 + [_num(1e3 * row.compute_time_s, '.1f') if row.groups else '-']
                       + (['-'] if extra else []))
            continue
        out.append([row.method, str(len(d.cut_branches)), str(d.n_islands),
                    _num(float(np.abs(d.island_imbalance_mw).sum())), _num(float(sum(d.island_shed_mw))),
                    _num(d.disrupted_mw), _num(row.gap_pct), _num(1e3 * row.compute_time_s, '.1f')]
                   + ([closed_loop_text(row.closed_loop)] if extra else []))
    return out


def format_case(case: CaseReport) -> str:
    """Render a case as a Markdown table (readable in a terminal too), then its groups, cut lines and notes."""
    cols = columns(case)
    cells = [list(cols)] + table_rows(case)
    widths = [max(len(r[i]) for r in cells) for i in range(len(cols))]
    lines = [f'### {case.name}', '', f'{case.source}', '']
    if case.truth_groups is not None:
        lines += [f'True coherent groups (final grouping): {_group_text(case.truth_groups)}', '']
    if case.detection is not None:
        from controlled_islanding.evaluation.coherency_rules import detection_text

        truth_k = len(set((case.truth_groups or {}).values()))
        slip = 'never' if case.first_pole_slip_s is None else f'{case.first_pole_slip_s:.2f} s'
        lines += [f'Detection lead (dtw, k rule {case.k_rule}): first pole slip {slip}; '
                  f'{detection_text(truth_k, case.detection)}', '']
    for n, r in enumerate(cells):
        lines.append('| ' + ' | '.join(c.ljust(w) if i == 0 else c.rjust(w)
                                        for i, (c, w) in enumerate(zip(r, widths, strict=True))) + ' |')
        if n == 0:
            lines.append('|' + '|'.join('-' * (w + 1) + (':' if i else '-') for i, w in enumerate(widths)) + '|')
    lines.append('')
    if case.no_action is not None:
        lines += [f'Closed loop (--closed-loop): no action {closed_loop_text(case.no_action)}; each cut opened at '
                  f'{case.no_action["judged_from_s"]:.3f} s (request + breaker time).', '']
    for row in case.rows:
        cut = ', '.join(row.decision.cut_branch_ids) if row.decision is not None else '-'
        detail = f'- {row.method}: groups {_group_text(row.groups)}'
        if case.truth_groups is not None and row.groups is not None:
            detail += ' (= truth)' if _same_partition(row.groups, case.truth_groups) else ' (differ from truth)'
        detail += f'; cut {cut or "nothing"}'
        lines.append(detail + (f'; note: {row.note}' if row.note else ''))
    return '\n'.join(lines) + '\n'


def case_to_json(case: CaseReport) -> dict[str, Any]:
    """Return a case as plain JSON data."""
    rows = []
    for row in case.rows:
        d = row.decision
        rows.append({
            'method': row.method, 'groups': row.groups, 'note': row.note,
            'compute_time_s': row.compute_time_s, 'optimum_mw': row.optimum_mw, 'closed_loop': row.closed_loop,
            'gap_pct': None if row.gap_pct is None or math.isinf(row.gap_pct) else row.gap_pct,
            'decision': None if d is None else {
                'split': d.split, 'n_islands': d.n_islands, 'cut_branch_ids': list(d.cut_branch_ids),
                'lines_cut': len(d.cut_branches),
                'imbalance_mw': float(np.abs(d.island_imbalance_mw).sum()), 'shed_mw': float(sum(d.island_shed_mw)),
                'disrupted_mw': d.disrupted_mw, 'island_generation_mw': list(d.island_generation_mw),
                'island_load_mw': list(d.island_load_mw), 'island_shed_mw': list(d.island_shed_mw),
                'bus_island': {str(b): i for b, i in sorted(d.bus_island.items())}},
        })
    det = case.detection
    return {'case': case.name, 'source': case.source, 'truth_groups': case.truth_groups, 'rows': rows,
            'figures': {k: str(v) for k, v in case.figures.items()}, 'k_rule': case.k_rule,
            'first_pole_slip_s': case.first_pole_slip_s, 'no_action': case.no_action,
            'detection': None if det is None else {'found_s': det.found_s, 'kept_from_s': det.kept_from_s,
                                                   'lead_s': det.lead_s}}


def _slug(text: str) -> str:
    return re.sub(r'[^0-9A-Za-z]+', '_', text).strip('_')


def write_figures(case: CaseReport, folder: Path, *, bag=None, window_s: float = 3.0,
                  dtw_band: int | None = None) -> dict[str, Path]:
    """Write the case's figures.

    Args:
        case: The evaluated case.
        folder: Output folder (created).
        bag: The case's BagData, for the rotor-angle and distance figures (None for paper cases).
        window_s: Window used for coherency, s (marked on the rotor-angle figure).
        dtw_band: Sakoe-Chiba half-width used for the DTW distances, samples (None = none).

    Returns:
        Figure name -> path.

    """
    from controlled_islanding.evaluation import plots

    out: dict[str, Path] = {}
    dtw = next((r for r in case.rows if r.method.startswith('dtw') and r.groups is not None), None)
    if bag is not None:
        from controlled_islanding.core.coherency import DTWCoherency

        end_s = request_time_s(bag)
        t_s, names, angles = generator_series(bag, 0.0, float(bag.tag_s[-1]))
        first = np.array([row[np.isfinite(row)][0] for row in angles])
        groups = [dtw.groups[n] for n in names] if dtw else None
        events = {f'trip {e.branch_id}': e.t_s for e in bag.branch_events if not e.in_service}
        out['rotor_angles'] = plots.plot_rotor_angles(
            t_s, angles - first[:, None], names, groups, folder / 'rotor_angles.png',
            title=f'{case.name}: PMU-estimated rotor angles, coloured by DTW group',
            marks_s=events | {'coherency window start': end_s - window_s, 'islanding request': end_s})
        _, _, window = generator_series(bag, end_s - window_s, end_s)
        # Every pair: the figure shows the distances, which the grouping alone may not need (all_pairs).
        model = DTWCoherency(window=dtw_band, all_pairs=True).fit(list(window))
        out['dtw_distance'] = plots.plot_distance_matrix(
            model.distance_matrix_, names, groups, folder / 'dtw_distance.png',
            title=f'{case.name}: DTW distances over the {window_s:g} s window')
    for row in case.rows:
        if row.decision is None:
            continue
        slug = _slug(row.method)
        out[f'network_{slug}'] = plots.plot_network(
            case.grid, row.decision.bus_island, row.decision.cut_branch_ids, folder / f'network_{slug}.png',
            title=f'{case.name}, {row.method}: {row.decision.disrupted_mw:.1f} MW disrupted')
    decided = {r.method: r.decision for r in case.rows if r.decision is not None}
    if decided:
        out['shedding'] = plots.plot_shedding(decided, folder / 'shedding.png',
                                              title=f'{case.name}: generation, load and load to shed per island')
    return out


def write_report(cases: Sequence[CaseReport], path: Path, figures_for: set[str] | None = None,
                 command: str = 'controlled-islanding evaluate ... --report') -> list[Path]:
    """Write a Markdown page with every table and the rotor-angle, DTW network and shedding figures of some cases.

    The figures it shows are copied into a folder named after the page (docs/evaluation.md ->
    docs/evaluation/), so the page stands alone however scratch the --out folder is.

    Args:
        cases: Evaluated cases with their figures.
        path: The .md file.
        figures_for: Names of the cases whose figures are shown (None: every case).
        command: The command line that regenerates the page, quoted at its top.

    Returns:
        The page and the figures copied beside it.

    """
    folder = path.parent / path.stem
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    lines = ['# Evaluation', '',
             f'Generated by `{command}`; do not edit by hand. `controlled-islanding evaluate --help` explains the '
             "methods and the columns. Each row's gap is its disruption against the exact minimum of eq. 9 "
             "under that row's own coherent groups (the MILP), so it grades the bus partitioning, not the groups.",
             '']
    for case in cases:
        lines.append(format_case(case))
        if figures_for is not None and case.name not in figures_for:
            continue
        for key in ('rotor_angles', 'network_dtw_paper_groups_spectral', 'network_dtw_spectral', 'shedding'):
            if key in case.figures:
                target = folder / f'{case.name}_{key}.png'
                atomic.write_bytes(target, case.figures[key].read_bytes())
                written.append(target)
                lines += [f'![{case.name}: {key.replace("_", " ")}]({path.stem}/{target.name})', '']
    atomic.write_bytes(path, '\n'.join(lines).encode())
    return [path, *written]
