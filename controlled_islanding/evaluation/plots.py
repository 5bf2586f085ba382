"""Figures for evaluation and the demo: rotor angles, DTW distances, the split network, load shedding.

Every function renders one PNG with matplotlib's object-oriented API (no pyplot, so no global backend
state is touched), writes it to a temporary file beside `path` and renames it, and returns the path.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import networkx as nx
import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from controlled_islanding import atomic

if TYPE_CHECKING:
    from controlled_islanding.core.grid import Grid

_DPI = 120
_LAYOUT_SEED = 7


class PlotError(ValueError):
    """Inputs that cannot be drawn: mismatched lengths, unknown buses, empty data."""


class IslandBalance(Protocol):
    """What plot_shedding reads from an islanding decision (core.islanding.IslandingDecision has it)."""

    island_generation_mw: Sequence[float]
    island_load_mw: Sequence[float]
    island_shed_mw: Sequence[float]


def group_colour(group: int) -> tuple[float, float, float, float]:
    """Colour of a 0-based group or island, shared by every figure so group 1 is always the same colour.

    Args:
        group: 0-based group or island index.

    Returns:
        RGBA tuple.
    """
    from matplotlib import colormaps

    return colormaps['tab10'](group % 10)


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic.replacing(path) as tmp:
        fig.savefig(tmp, format='png', dpi=_DPI, bbox_inches='tight')
    return path


def _groups_or_zero(groups: Sequence[int] | None, n: int, what: str) -> np.ndarray:
    if groups is None:
        return np.zeros(n, dtype=int)
    out = np.asarray(groups, dtype=int)
    if out.shape != (n,):
        raise PlotError(f'{what}: got {out.size} group labels for {n} generators')
    if n and out.min() < 0:
        raise PlotError(f'{what}: group labels must be 0-based non-negative ints, got {out.min()}')
    return out


def plot_rotor_angles(t_s: Sequence[float], angles_rad: Sequence[Sequence[float]], names: Sequence[str],
                      groups: Sequence[int] | None, path: str | Path, *, title: str = '',
                      ylabel: str = 'rotor angle deviation (rad)',
                      marks_s: Mapping[str, float] | None = None) -> Path:
    """Draw one rotor-angle trace per generator, coloured by its coherent group.

    Args:
        t_s: sample times, s, length T.
        angles_rad: one row of T angles (rad) per generator, shape (n_generators, T); NaN = missing sample.
        names: generator names, one per row.
        groups: 0-based group per generator, or None to draw all in one colour.
        path: PNG file to write.
        title: figure title.
        ylabel: y-axis label; keep the unit in it.
        marks_s: vertical marker lines, label -> time (s), e.g. {'islanding request': 9.0}.

    Returns:
        The written path.

    Raises:
        PlotError: if shapes disagree or there is nothing to draw.
    """
    t = np.asarray(t_s, dtype=float)
    angles = np.asarray(angles_rad, dtype=float)
    if angles.ndim != 2 or angles.shape != (len(names), t.size):
        hint = ' (transpose it: rows are generators)' if angles.shape == (t.size, len(names)) else ''
        raise PlotError(f'angles_rad has shape {angles.shape}, expected (n_generators={len(names)}, '
                        f'n_samples={t.size}){hint}')
    if t.size == 0 or not len(names):
        raise PlotError('plot_rotor_angles: no samples or no generators to draw')
    labels = _groups_or_zero(groups, len(names), 'plot_rotor_angles')

    fig = Figure(figsize=(9.0, 4.8))
    ax = fig.add_subplot()
    for row, name, group in zip(angles, names, labels, strict=True):
        ax.plot(t, row, color=group_colour(group), linewidth=1.2, label=name)
    for i, (label, when_s) in enumerate((marks_s or {}).items()):
        ax.axvline(when_s, color='0.3', linestyle=('--', ':', '-.')[i % 3], linewidth=1.0)
        ax.annotate(label, xy=(when_s, 1.0), xycoords=('data', 'axes fraction'), xytext=(3, -3),
                    textcoords='offset points', va='top', fontsize=8, color='0.3', rotation=90)
    ax.set_xlabel('time (s)')
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    handles = [Line2D([], [], color=group_colour(g), linewidth=2,
                      label=_wrap(f'group {g}: ' + ', '.join(n for n, lg in zip(names, labels, strict=True)
                                                             if lg == g)))
               for g in sorted(set(labels.tolist()))]
    ax.legend(handles=handles, loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    if title:
        ax.set_title(title)
    return _save(fig, path)


def _wrap(text: str, width: int = 34) -> str:
    lines, current = [], ''
    for word in text.split(' '):
        if current and len(current) + 1 + len(word) > width:
            lines.append(current)
            current = '  ' + word
        else:
            current = f'{current} {word}' if current else word
    lines.append(current)
    return '\n'.join(lines)


def plot_distance_matrix(distance: Sequence[Sequence[float]], names: Sequence[str], groups: Sequence[int] | None,
                         path: str | Path, *, title: str = '',
                         unit_label: str = 'DTW distance (rad$^2$)') -> Path:
    """Draw a pairwise generator distance matrix as a heatmap, rows and columns ordered by group.

    Args:
        distance: n x n dissimilarities (DTW: sum of squared rad differences, rad^2).
        names: generator names, one per row.
        groups: 0-based group per generator (None = keep the given order, no boundaries).
        path: PNG file to write.
        title: figure title.
        unit_label: colour-bar label; keep the unit in it.

    Returns:
        The written path.

    Raises:
        PlotError: if the matrix is not square or does not match the names.
    """
    d = np.asarray(distance, dtype=float)
    n = len(names)
    if d.shape != (n, n) or n == 0:
        raise PlotError(f'distance has shape {d.shape}, expected ({n}, {n}) for {n} generators')
    labels = _groups_or_zero(groups, n, 'plot_distance_matrix')
    order = np.argsort(labels, kind='stable')
    d = d[np.ix_(order, order)]

    side = min(4.0 + 0.28 * n, 12.0)
    fig = Figure(figsize=(side + 1.4, side))
    ax = fig.add_subplot()
    image = ax.imshow(d, cmap='viridis', interpolation='nearest')
    fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04, label=unit_label)
    if n <= 40:
        ticks = np.arange(n)
        ordered = [names[i] for i in order]
        ax.set_xticks(ticks, ordered, rotation=90, fontsize=8)
        ax.set_yticks(ticks, ordered, fontsize=8)
        for tick_x, tick_y, i in zip(ax.get_xticklabels(), ax.get_yticklabels(), order, strict=True):
            tick_x.set_color(group_colour(labels[i]))
            tick_y.set_color(group_colour(labels[i]))
    if groups is not None:
        for edge in np.flatnonzero(np.diff(labels[order])) + 0.5:
            ax.axhline(edge, color='white', linewidth=1.5)
            ax.axvline(edge, color='white', linewidth=1.5)
    ax.set_xlabel('generator (ordered by group)')
    ax.set_ylabel('generator (ordered by group)')
    if title:
        ax.set_title(title)
    return _save(fig, path)


def network_layout(grid: Grid) -> dict[int, np.ndarray]:
    """Bus positions from the full branch set (tripped ones too), so every figure of a grid lines up.

    Args:
        grid: the network.

    Returns:
        Bus number -> (x, y) position, unitless.
    """
    graph = nx.Graph()
    graph.add_nodes_from(grid.buses)
    graph.add_edges_from((b.from_bus, b.to_bus) for b in grid.branches)
    # Kamada-Kawai spreads meshed grids evenly; seeding it from a fixed spring layout makes it reproducible.
    start = nx.spring_layout(graph, seed=_LAYOUT_SEED)
    if nx.is_connected(graph):
        return nx.kamada_kawai_layout(graph, pos=start)
    return start


def plot_network(grid: Grid, bus_island: Mapping[int, int], cut_branch_ids: Iterable[str], path: str | Path, *,
                 title: str = '', show_labels: bool | None = None) -> Path:
    """Draw the grid with buses coloured by island, cut lines marked, tripped lines dotted, generators as squares.

    Args:
        grid: the network (core.grid.Grid); out-of-service branches are drawn as tripped.
        bus_island: bus number -> 0-based island; buses missing from it are drawn grey.
        cut_branch_ids: ids of branches the decision opens.
        path: PNG file to write.
        title: figure title.
        show_labels: print bus numbers (default: when there are at most 120 buses).

    Returns:
        The written path.

    Raises:
        PlotError: if a cut branch id or an island bus is not in the grid.
    """
    buses = list(grid.buses)
    known = set(buses)
    unknown = sorted(set(bus_island) - known)
    if unknown:
        raise PlotError(f'bus_island names buses not in grid {grid.name!r}: {unknown[:10]}')
    by_id = {b.branch_id: b for b in grid.branches}
    cut = set(cut_branch_ids)
    missing = sorted(cut - set(by_id))
    if missing:
        raise PlotError(f'cut branch ids not in grid {grid.name!r}: {missing[:10]}')
    pos = network_layout(grid)
    gen_buses = {g.bus for g in grid.generators}

    fig = Figure(figsize=(9.0, 7.5))
    ax = fig.add_subplot()
    kinds = {'line': ([], dict(color='0.55', linewidth=1.2, linestyle='-')),
             'tripped': ([], dict(color='0.55', linewidth=1.2, linestyle=':')),
             'cut': ([], dict(color='red', linewidth=3.0, linestyle='--'))}
    for branch in grid.branches:
        kind = 'cut' if branch.branch_id in cut else ('line' if branch.in_service else 'tripped')
        kinds[kind][0].append((branch.from_bus, branch.to_bus))
    graph = nx.Graph()
    graph.add_nodes_from(buses)
    for edges, style in kinds.values():
        if edges:
            nx.draw_networkx_edges(graph, pos, edgelist=edges, ax=ax, width=style['linewidth'],
                                   edge_color=style['color'], style=style['linestyle'])
    for shape, members in (('o', [b for b in buses if b not in gen_buses]), ('s', [b for b in buses
                                                                               if b in gen_buses])):
        if members:
            colours = [group_colour(bus_island[b]) if b in bus_island else (0.8, 0.8, 0.8, 1.0) for b in members]
            nx.draw_networkx_nodes(graph, pos, nodelist=members, node_color=colours, node_shape=shape,
                                   node_size=260 if len(buses) <= 120 else 40, edgecolors='black',
                                   linewidths=0.6, ax=ax)
    if show_labels is None:
        show_labels = len(buses) <= 120
    if show_labels:
        nx.draw_networkx_labels(graph, pos, labels={b: str(b) for b in buses}, font_size=7, ax=ax)
    islands = sorted(set(bus_island.values()))
    handles: list = [Patch(facecolor=group_colour(i), edgecolor='black',
                           label=f'island {i} ({sum(1 for v in bus_island.values() if v == i)} buses)')
                     for i in islands]
    handles += [Line2D([], [], marker='s', color='white', markerfacecolor='white', markeredgecolor='black',
                       markersize=9, label='generator bus'),
                Line2D([], [], color='red', linewidth=3.0, linestyle='--', label=f'cut line ({len(cut)})')]
    if kinds['tripped'][0]:
        handles.append(Line2D([], [], color='0.55', linewidth=1.2, linestyle=':', label='tripped line'))
    ax.legend(handles=handles, loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)
    ax.set_axis_off()
    ax.set_title(title or f'{grid.name}: buses by island')
    return _save(fig, path)


def plot_shedding(decisions: Mapping[str, IslandBalance], path: str | Path, *, title: str = '') -> Path:
    """Bars per island of generation beside load, the load to shed stacked in red on top (the paper's Figs. 7, 10).

    Args:
        decisions: panel label (e.g. method name) -> decision with per-island generation, load and shed, MW.
        path: PNG file to write.
        title: figure title.

    Returns:
        The written path.

    Raises:
        PlotError: if there is nothing to draw or the per-island arrays disagree in length.
    """
    if not decisions:
        raise PlotError('plot_shedding: no decisions to draw')
    n_panels = len(decisions)
    fig = Figure(figsize=(min(4.2 * n_panels, 16.0), 4.6), layout='constrained')
    axes = fig.subplots(1, n_panels, sharey=True, squeeze=False)[0]
    for ax, (label, decision) in zip(axes, decisions.items(), strict=True):
        gen = np.asarray(decision.island_generation_mw, dtype=float)
        load = np.asarray(decision.island_load_mw, dtype=float)
        shed = np.asarray(decision.island_shed_mw, dtype=float)
        if not (gen.shape == load.shape == shed.shape) or gen.size == 0:
            raise PlotError(f'plot_shedding[{label!r}]: per-island arrays have lengths '
                            f'{gen.size}, {load.size}, {shed.size}; expected equal and non-zero')
        x = np.arange(gen.size)
        ax.bar(x - 0.2, gen, width=0.4, color='tab:green', label='generation')
        ax.bar(x + 0.2, load - shed, width=0.4, color='tab:blue', label='load served')
        ax.bar(x + 0.2, shed, width=0.4, bottom=load - shed, color='tab:red', label='load to shed')
        for xi, s in zip(x, shed, strict=True):
            if s > 0:
                ax.annotate(f'{s:.1f} MW', xy=(xi + 0.2, load[xi]), xytext=(0, 2), textcoords='offset points',
                            ha='center', va='bottom', fontsize=8, color='tab:red')
        ax.set_xticks(x, [f'island {i}' for i in x])
        ax.set_title(f'{_wrap(label, 36)}\nload to shed {shed.sum():.1f} MW', fontsize=10)
        ax.grid(True, axis='y', alpha=0.3)
        ax.margins(y=0.12)
    axes[0].set_ylabel('active power (MW)')
    axes[-1].legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


@dataclass(frozen=True)
class ClosedLoopPanel:
    """One run of a closed-loop comparison: its trajectories and when its cut took effect.

    Attributes:
        label: Name of the run, e.g. 'no action'.
        t_s: Step times, s, shape (nt,).
        delta_rad: Rotor angles, rad, shape (nt, n_gen).
        bus_v_pu: Bus voltage magnitudes, pu, shape (nt, n_bus).
        opened_s: When the cut took effect, s (None: no cut).
        survived: Whether every island survived (shown in the row title); None: undetermined.
        failed: "simulation failed at t s: reason" (a black line where the trajectories end), or None.
        served_pct: Load served at the end, % of the pre-fault load (shown in the row title), or None.
        request_s: This run's own islanding request time, s (the dashed line), when not the figure's (the best
            found's).

    """

    label: str
    t_s: Sequence[float]
    delta_rad: Sequence[Sequence[float]]
    bus_v_pu: Sequence[Sequence[float]]
    opened_s: float | None
    survived: bool | None
    failed: str | None = None
    served_pct: float | None = None
    request_s: float | None = None


def plot_closed_loop(panels: Sequence[ClosedLoopPanel], names: Sequence[str], islands: Sequence[int],
                     path: str | Path, *, request_s: float, title: str = '',
                     v_limits_pu: tuple[float, float] = (0.8, 1.2)) -> Path:
    """Draw, per run, the rotor angles coloured by island and the bus voltages (the paper's Figs. 6 and 11).

    Angles are deviations from their pre-fault values, delta(t) - delta(0), rad, so a pole slip shows as a trace
    leaving its island by 2 pi per slip; every run uses the same island colours (the closed loop's decision).

    Args:
        panels: One row per run.
        names: Machine names, the columns of delta_rad.
        islands: 0-based island of each machine.
        path: PNG file to write.
        request_s: Islanding request time, s (a dashed line).
        title: Figure title.
        v_limits_pu: Voltage band drawn as dotted lines, pu.

    Raises:
        PlotError: No panels, or shapes disagree.

    """
    if not panels:
        raise PlotError('plot_closed_loop: no runs to draw')
    labels = _groups_or_zero(islands, len(names), 'plot_closed_loop')
    fig = Figure(figsize=(11.0, 3.2 * len(panels)))
    axes = fig.subplots(len(panels), 2, squeeze=False)
    for row, panel in enumerate(panels):
        t = np.asarray(panel.t_s, dtype=float)
        delta = np.asarray(panel.delta_rad, dtype=float)
        volts = np.asarray(panel.bus_v_pu, dtype=float)
        if delta.shape != (t.size, len(names)) or volts.ndim != 2 or volts.shape[0] != t.size:
            raise PlotError(f'{panel.label}: delta {delta.shape} / voltages {volts.shape} do not match {t.size} '
                            f'times and {len(names)} machines')
        ax_a, ax_v = axes[row]
        dev = delta - delta[:1]
        for j, group in enumerate(labels):
            ax_a.plot(t, dev[:, j], color=group_colour(int(group)), linewidth=1.0)
        ax_v.plot(t, volts, color='0.35', linewidth=0.6)
        for lim in v_limits_pu:
            ax_v.axhline(lim, color='tab:red', linestyle=':', linewidth=0.8)
        for ax in (ax_a, ax_v):
            ax.axvline(request_s if panel.request_s is None else panel.request_s, color='0.3', linestyle='--',
                       linewidth=0.9)
            if panel.opened_s is not None:
                ax.axvline(panel.opened_s, color='tab:red', linestyle='-', linewidth=0.9)
            if panel.failed is not None and t.size:
                ax.axvline(float(t[-1]), color='black', linestyle='-', linewidth=1.6)
            ax.grid(True, alpha=0.3)
        if panel.failed is not None:
            verdict = panel.failed.split(':')[0]
        else:
            verdict = 'every island survived' if panel.survived else 'NOT every island survived'
            if panel.served_pct is not None:
                verdict += f', {panel.served_pct:.0f} % of the load served'
        ax_a.set_title(f'{panel.label}: rotor angles ({verdict})', fontsize=9)
        ax_v.set_title(f'{panel.label}: bus voltages', fontsize=9)
        ax_a.set_ylabel('delta - delta(0) (rad)')
        ax_v.set_ylabel('|V| (pu)')
        ax_v.set_ylim(max(0.0, min(0.6, float(np.nanmin(volts)) - 0.05)), max(1.25, float(np.nanmax(volts)) + 0.05))
    for ax in axes[-1]:
        ax.set_xlabel('time (s)')
    handles = [Line2D([], [], color=group_colour(g), linewidth=2,
                      label=_wrap(f'island {g}: ' + ', '.join(n for n, lg in zip(names, labels, strict=True)
                                                              if lg == g)))
               for g in sorted(set(labels.tolist()))]
    handles += [Line2D([], [], color='0.3', linestyle='--', label='islanding request'),
                Line2D([], [], color='tab:red', label='cut opened')]
    if any(p.failed is not None for p in panels):
        handles.append(Line2D([], [], color='black', linewidth=1.6, label='simulation failed (it stopped here)'))
    fig.legend(handles=handles, loc='lower center', ncol=min(4, len(handles)), fontsize=8, frameon=False,
               bbox_to_anchor=(0.5, -0.02 * max(1, 4 - len(panels))))
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return _save(fig, path)
