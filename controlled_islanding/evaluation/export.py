"""An islanding decision in the forms other grid tools take to apply it: MATPOWER cases, pandapower nets, ANDES events.

All start from the ANDES case the decision's network came from (ANDES reads MATPOWER, PSS/E and its own
formats), so branch ids are matched in either orientation: ANDES names transformer 6-31 "31-6".

- MATPOWER: the whole case with the cut branches (and any outages the decision saw) at status 0, one
  reference bus per island (the island's largest in-service generator, unless it holds the case's own),
  and the decision's load shed at each bus it names (a decision without remedial actions: each island's load
  scaled down by its load to shed), so every island solves on its own. The machines the decision trips stay in
  service in the case: the island's generation is the decision's scheduled generation.
  `island_cases` splits it into one case per island, which MATPOWER or PYPOWER run as they are
  (pandapower's converter misreads some transformers of it: use `pandapower_net`).
- pandapower: that MATPOWER case through pandapower's own converter, every line, transformer and impedance
  named by its branch id, the cut ones (and the outages) out of service, one ext_grid per island: `pp.runpp`
  solves every island of it at once, and `pp.from_json` reads it back from `pandapower_json`.
- ANDES: one Toggle per cut branch at a time given, as the rows `System.add('Toggle', row)` takes.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controlled_islanding import atomic

# MATPOWER columns (0-based), from the MATPOWER case format documentation.
_BUS_I, _BUS_TYPE, _BUS_PD, _BUS_QD, _BUS_GS, _BUS_BS, _BUS_BASE_KV = 0, 1, 2, 3, 4, 5, 9
_GEN_BUS, _GEN_PG, _GEN_STATUS = 0, 1, 7
_BR_F, _BR_T, _BR_R, _BR_X, _BR_B, _BR_TAP, _BR_SHIFT, _BR_STATUS = 0, 1, 2, 3, 4, 8, 9, 10
_REF, _PV, _PQ = 3, 2, 1


class ExportError(ValueError):
    """A decision or case that cannot be exported as asked."""


@dataclass(frozen=True)
class Decision:
    """The parts of an islanding decision an export needs.

    Attributes:
        cut_branch_ids: Branches to open, "<bus>-<bus>" or "<bus>-<bus>#<n>".
        islands: Bus numbers of each island, island 0 first.
        island_shed_mw: Load to shed in each island, MW.
        outages: Branches already out when the decision was made.
        island_load_mw: Load in each island before the shed, MW, as the decision saw it (empty: not known).
        island_generation_mw: Scheduled generation in each island, MW, as the decision saw it (empty: not known).
        shed_mw_by_bus: The decision's load shed at each bus, MW (its remedial actions, core/remedial.py); empty
            for a decision that carries no actions, whose island shed is then spread over every load bus of the
            island in proportion.

    """

    cut_branch_ids: tuple[str, ...]
    islands: tuple[tuple[int, ...], ...]
    island_shed_mw: tuple[float, ...]
    outages: tuple[str, ...] = ()
    island_load_mw: tuple[float, ...] = ()
    island_generation_mw: tuple[float, ...] = ()
    shed_mw_by_bus: tuple[tuple[int, float], ...] = ()

    @classmethod
    def from_summary(cls, summary: Mapping[str, Any], outages: Iterable[str] = ()) -> Decision:
        """Read a `replay`/`demo` summary.json, or a manifest entry's expected_decision.

        Raises:
            ExportError: It holds no split decision, or its fields are malformed.

        """
        if not summary.get('split'):
            raise ExportError(f'the decision is not a split (split={summary.get("split")!r}, '
                              f'status={summary.get("status", "-")}); there is nothing to export')
        try:
            cut = tuple(str(b) for b in summary.get('cut_branch_ids', summary.get('cut_branches')))
            raw = summary['islands']
            load: tuple[float, ...] = ()
            generation: tuple[float, ...] = ()
            if raw and isinstance(raw[0], Mapping):
                islands = tuple(tuple(int(b) for b in isl['buses']) for isl in raw)
                shed = tuple(float(isl['shed_mw']) for isl in raw)
                if all('load_mw' in isl and 'generation_mw' in isl for isl in raw):
                    load = tuple(float(isl['load_mw']) for isl in raw)
                    generation = tuple(float(isl['generation_mw']) for isl in raw)
            else:
                islands = tuple(tuple(int(b) for b in isl) for isl in raw)
                shed = tuple(float(s) for s in summary['island_shed_mw'])
            by_bus = tuple(sorted((int(b), float(mw)) for b, mw in
                                  (summary.get('remedial_actions') or {}).get('shed_mw_by_bus', {}).items()))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ExportError(f'decision: missing or malformed field ({exc!r}); expected cut_branch_ids (or '
                              'cut_branches) and islands with shed_mw (or island_shed_mw)') from None
        if len(shed) != len(islands):
            raise ExportError(f'decision: {len(islands)} islands but {len(shed)} shed values')
        return cls(cut, islands, shed, tuple(outages), load, generation, by_bus)


def load_case(case: str | Path, addfile: str | Path | None = None) -> Any:
    """Return an ANDES System of a case (a file, or one bundled with ANDES) after its power flow.

    Raises:
        ExportError: ANDES cannot load the case or solve its power flow.

    """
    from controlled_islanding.sim.andes_sim import SimulationError, load_power_flow

    try:
        ss = load_power_flow(case, addfile)
    except (SimulationError, FileNotFoundError, OSError) as exc:
        raise ExportError(f'case {case}: ANDES could not load it: {exc}') from exc
    if not ss.PFlow.converged:
        raise ExportError(f'case {case}: its ANDES power flow did not converge')
    return ss


def scenario_case(scenario_file: str | Path, request_s: float | None = None) -> tuple[Any, tuple[str, ...]]:
    """Return a scenario's case as the simulator set it up, after its power flow, and the branches out at a time.

    The case is `sim.andes_sim.prepare_case`'s, so it holds the scenario's loads and dispatch (load_scale,
    dispatch) and its disabled devices, as the decision's snapshot did.

    Args:
        scenario_file: The scenario YAML.
        request_s: The decision's request, s from the simulation start (None: the scenario's own); the
            branches its trips and kept case events have opened before it are returned.

    Raises:
        ExportError: The scenario cannot be read or set up.

    """
    from dataclasses import replace

    from controlled_islanding.sim.andes_sim import SimulationError, prepare_case
    from controlled_islanding.sim.scenario import ScenarioError, load_scenario

    try:
        scenario = load_scenario(Path(scenario_file))
        # Faults act only in the time domain, but a mid-line one splits its line at a bus no decision names.
        case = prepare_case(replace(scenario, faults=()))
    except (ScenarioError, SimulationError, OSError) as exc:
        raise ExportError(f'scenario {scenario_file}: {exc}') from exc
    at_s = scenario.request_s if request_s is None else request_s
    out: dict[str, None] = {}
    for t_s, branch, in_service in case.scheduled_changes(scenario):
        # As the bag manifest counts them: a change at the request itself came too late for the decision.
        if t_s < at_s:
            if in_service:
                out.pop(branch, None)
            else:
                out[branch] = None
    return case.ss, tuple(out)


def line_rows(ss: Any, branch_ids: Sequence[str]) -> list[int]:
    """Return the ANDES Line position of each branch id, in either orientation.

    Raises:
        ExportError: A branch id names no line of the case.

    """
    from controlled_islanding.sim.andes_sim import branch_ids as name_branches

    pairs = [(int(a), int(b)) for a, b in zip(ss.Line.bus1.v, ss.Line.bus2.v, strict=True)]
    ids = name_branches(pairs)
    flipped = name_branches([(b, a) for a, b in pairs])
    rows = []
    for ref in branch_ids:
        if ref in ids:
            rows.append(ids.index(ref))
        elif ref in flipped:
            rows.append(flipped.index(ref))
        else:
            raise ExportError(f'branch {ref!r}: no line or transformer of the case joins those buses')
    return rows


def andes_toggles(ss: Any, decision: Decision, t_s: float) -> list[dict[str, Any]]:
    """Return one ANDES Toggle row per cut branch, opening it at t_s (s of simulation time)."""
    idx = list(ss.Line.idx.v)
    return [{'model': 'Line', 'dev': idx[row], 't': float(t_s)} for row in line_rows(ss, decision.cut_branch_ids)]


def matpower_case(ss: Any, decision: Decision) -> dict[str, Any]:
    """Return the case as a MATPOWER ppc with the decision applied (see the module docstring).

    Raises:
        ExportError: An island has no generator in service, or names a bus the case lacks.

    """
    from andes.io.matpower import system2mpc

    ppc = system2mpc(ss)
    ppc = {'version': '2', 'baseMVA': float(ppc['baseMVA']), 'bus': np.array(ppc['bus'], dtype=float),
           'gen': np.array(ppc['gen'], dtype=float), 'branch': np.array(ppc['branch'], dtype=float)}
    bus, gen = ppc['bus'], ppc['gen']
    mva = float(ss.config.mva)
    # system2mpc writes each load over the one before it at the same bus, switched-off ones included.
    bus[:, [_BUS_PD, _BUS_QD]] = 0.0
    if ss.PQ.n:
        pq_rows = ss.Bus.idx2uid(ss.PQ.bus.v)
        on = np.asarray(ss.PQ.u.v, dtype=float)
        np.add.at(bus[:, _BUS_PD], pq_rows, on * np.asarray(ss.PQ.p0.v, dtype=float) * mva)
        np.add.at(bus[:, _BUS_QD], pq_rows, on * np.asarray(ss.PQ.q0.v, dtype=float) * mva)
    # Shunts too: EI 33 has 22 GVAr more of them than system2mpc keeps, and no power flow of its case then solves.
    bus[:, [_BUS_GS, _BUS_BS]] = 0.0
    if ss.Shunt.n:
        shunt_rows = ss.Bus.idx2uid(ss.Shunt.bus.v)
        on = np.asarray(ss.Shunt.u.v, dtype=float)
        np.add.at(bus[:, _BUS_GS], shunt_rows, on * np.asarray(ss.Shunt.g.v, dtype=float) * mva)
        np.add.at(bus[:, _BUS_BS], shunt_rows, on * np.asarray(ss.Shunt.b.v, dtype=float) * mva)
    # The slack's dispatch is what its power flow gave it, as the decision's snapshot has it, not its set point.
    gen[:ss.Slack.n, _GEN_PG] = np.asarray(ss.Slack.p.v, dtype=float) * mva
    ppc['branch'][line_rows(ss, [*decision.outages, *decision.cut_branch_ids]), _BR_STATUS] = 0
    row_of = {int(b): i for i, b in enumerate(bus[:, _BUS_I])}
    for b, shed_mw in decision.shed_mw_by_bus:
        load_mw = float(bus[row_of[b], _BUS_PD]) if b in row_of else 0.0
        if load_mw < shed_mw - 1e-6:
            raise ExportError(f'the decision sheds {shed_mw:.1f} MW at bus {b}, which has {load_mw:.1f} MW of load '
                              'in the case')
        # Keeping the bus's power factor, as a shed of whole feeders of like loads would.
        bus[row_of[b], [_BUS_PD, _BUS_QD]] *= max(0.0, 1.0 - shed_mw / load_mw)
    for k, (buses, shed_mw) in enumerate(zip(decision.islands, decision.island_shed_mw, strict=True)):
        unknown = [b for b in buses if b not in row_of]
        if unknown:
            raise ExportError(f'island {k}: bus(es) {unknown[:5]} are not in the case')
        rows = [row_of[b] for b in buses]
        on = [g for g in range(len(gen)) if gen[g, _GEN_STATUS] > 0 and int(gen[g, _GEN_BUS]) in set(buses)]
        if not on:
            raise ExportError(f'island {k}: no generator in service, so no reference bus')
        refs = [r for r in rows if bus[r, _BUS_TYPE] == _REF]
        keep = refs[0] if refs else row_of[int(gen[max(on, key=lambda g: gen[g, _GEN_PG]), _GEN_BUS])]
        for r in rows:
            if bus[r, _BUS_TYPE] == _REF and r != keep:
                bus[r, _BUS_TYPE] = _PV
        bus[keep, _BUS_TYPE] = _REF
        load_mw = float(bus[rows, _BUS_PD].sum())
        if shed_mw > 0 and load_mw > 0 and not decision.shed_mw_by_bus:
            # Shed in proportion at every bus, keeping each load's power factor.
            scale = max(0.0, 1.0 - shed_mw / load_mw)
            bus[rows, _BUS_PD] *= scale
            bus[rows, _BUS_QD] *= scale
    _check_against_decision(ppc, decision)
    return ppc


def island_power_mw(ppc: Mapping[str, Any], islands: Sequence[Sequence[int]]) -> list[tuple[float, float]]:
    """Return (load, scheduled generation in service) of each island of a ppc, MW."""
    bus, gen = ppc['bus'], ppc['gen']
    out = []
    for buses in islands:
        inside = np.isin(bus[:, _BUS_I].astype(int), list(buses))
        gen_in = np.isin(gen[:, _GEN_BUS].astype(int), list(buses)) & (gen[:, _GEN_STATUS] > 0)
        out.append((float(bus[inside, _BUS_PD].sum()), float(gen[gen_in, _GEN_PG].sum())))
    return out


def _check_against_decision(ppc: Mapping[str, Any], decision: Decision) -> None:
    """Refuse a case whose islands do not hold the load and generation the decision counted on.

    Raises:
        ExportError: An island's load (after the shed) or scheduled generation differs from the decision's by
            more than 0.5 MW and 0.5 %.

    """
    if not decision.island_load_mw:
        return
    wanted = zip(decision.island_load_mw, decision.island_shed_mw, decision.island_generation_mw, strict=True)
    for k, ((load_mw, gen_mw), (decided_load_mw, shed_mw, decided_gen_mw)) in enumerate(
            zip(island_power_mw(ppc, decision.islands), wanted, strict=True)):
        for what, got, expected in (('load', load_mw, decided_load_mw - shed_mw),
                                    ('generation', gen_mw, decided_gen_mw)):
            if abs(got - expected) > max(0.5, 0.005 * abs(expected)):
                raise ExportError(f'island {k}: the case holds {got:.1f} MW of {what} where the decision counted '
                                  f'{expected:.1f} MW{" after its shed" if what == "load" else ""}: it is not the '
                                  'case the decision was made on (give its scenario: --case SCENARIO.yaml)')


def pandapower_net(ss: Any, decision: Decision) -> Any:
    """Return the case as a pandapower net with the decision applied (see the module docstring).

    Raises:
        ExportError: As `matpower_case`.

    """
    import warnings

    from pandapower.converter.pypower import from_ppc

    from controlled_islanding.sim.andes_sim import branch_ids

    ppc = matpower_case(ss, decision)
    ppc = _transformers_for_pandapower(ppc)
    names = branch_ids([(int(a), int(b)) for a, b in zip(ss.Line.bus1.v, ss.Line.bus2.v, strict=True)])
    ppc['branch_name'] = np.array(names, dtype=object)
    with warnings.catch_warnings():
        # pandas' deprecation notices from inside the converter say nothing about the case.
        warnings.simplefilter('ignore', FutureWarning)
        net = from_ppc(ppc, f_hz=float(ss.config.freq), validate_conversion=False)
    # The converter leaves a branch it makes an impedance (ends at different base kV, no tap) in service and
    # unnamed, so status and name are set on every element the branch rows became.
    lookup = net._from_ppc_lookups['branch']
    for row, (element, kind) in enumerate(zip(lookup['element'], lookup['element_type'], strict=True)):
        net[kind].at[int(element), 'in_service'] = bool(ppc['branch'][row, _BR_STATUS] > 0)
        net[kind].at[int(element), 'name'] = names[row]
    return net


def _transformers_for_pandapower(ppc: Mapping[str, Any]) -> dict[str, Any]:
    """Return the ppc with its transformers written as pandapower's converter (3.5.6) models them faithfully.

    The converter puts a MATPOWER tap on the higher-voltage end whichever end the case gives it at (IEEE 39's
    31-6, 12-11 and 12-13 then moved the solved voltages by up to 0.09 pu), and makes a transformer's charging
    susceptance an inductive magnetising current at the middle of a T (GBnetwork: 0.007 pu). A tap t at one end
    with admittance y and charging b behind it is the tap 1/t at the other end with y/t**2 and b/t**2, a phase
    shift changing sign; an in-service transformer's charging, b/2/t**2 at the tap end and b/2 at the other, goes
    to the buses' shunts.
    """
    bus, branch = ppc['bus'].copy(), ppc['branch'].copy()
    row_of = {int(b): i for i, b in enumerate(bus[:, _BUS_I])}
    tap = np.where(branch[:, _BR_TAP] == 0, 1.0, branch[:, _BR_TAP])
    transformer = (tap != 1.0) | (branch[:, _BR_SHIFT] != 0)
    low_first = np.array([bus[row_of[int(f)], _BUS_BASE_KV] < bus[row_of[int(t)], _BUS_BASE_KV]
                          for f, t in branch[:, [_BR_F, _BR_T]]], dtype=bool)
    flip = transformer & low_first
    t = tap[flip]
    branch[flip, _BR_F], branch[flip, _BR_T] = branch[flip, _BR_T], branch[flip, _BR_F]
    branch[flip, _BR_TAP] = 1.0 / t
    branch[flip, _BR_R] *= t ** 2
    branch[flip, _BR_X] *= t ** 2
    branch[flip, _BR_B] /= t ** 2
    branch[flip, _BR_SHIFT] *= -1.0
    tap = np.where(branch[:, _BR_TAP] == 0, 1.0, branch[:, _BR_TAP])
    for k in np.flatnonzero(transformer & (branch[:, _BR_B] != 0) & (branch[:, _BR_STATUS] > 0)):
        half_mvar = branch[k, _BR_B] / 2.0 * ppc['baseMVA']
        bus[row_of[int(branch[k, _BR_F])], _BUS_BS] += half_mvar / tap[k] ** 2
        bus[row_of[int(branch[k, _BR_T])], _BUS_BS] += half_mvar
        branch[k, _BR_B] = 0.0
    return {**ppc, 'bus': bus, 'branch': branch}


def pandapower_json(net: Any, path: Path) -> Path:
    """Write a pandapower net as the JSON `pandapower.from_json` reads, atomically."""
    import pandapower as pp

    return atomic.write_text(path, pp.to_json(net))


def island_cases(ppc: Mapping[str, Any], islands: Sequence[Sequence[int]]) -> list[dict[str, Any]]:
    """Split a ppc into one ppc per island: its buses, the in-service branches inside it, its generators."""
    out = []
    for buses in islands:
        inside = set(int(b) for b in buses)
        bus_rows = np.isin(ppc['bus'][:, _BUS_I].astype(int), list(inside))
        br = ppc['branch']
        br_rows = (np.isin(br[:, _BR_F].astype(int), list(inside)) & np.isin(br[:, _BR_T].astype(int), list(inside))
                   & (br[:, _BR_STATUS] > 0))
        gen_rows = np.isin(ppc['gen'][:, _GEN_BUS].astype(int), list(inside))
        out.append({'version': '2', 'baseMVA': ppc['baseMVA'], 'bus': ppc['bus'][bus_rows].copy(),
                    'gen': ppc['gen'][gen_rows].copy(), 'branch': br[br_rows].copy()})
    return out


def write_matpower(ppc: Mapping[str, Any], path: Path) -> Path:
    """Write a ppc as a MATPOWER .m case file, atomically; the function is named after the file, as MATPOWER needs."""
    def rows(a: np.ndarray) -> str:
        return '\n'.join('\t' + '\t'.join(f'{v:.10g}' for v in row) + ';' for row in a)

    if path.suffix != '.m' or not path.stem.isidentifier():
        raise ExportError(f'{path}: a MATPOWER case file is NAME.m with NAME a valid function name')
    text = (f'function mpc = {path.stem}\n% Written by controlled-islanding export: the case with an islanding '
            f'decision applied.\nmpc.version = \'2\';\nmpc.baseMVA = {ppc["baseMVA"]:.10g};\n'
            f'mpc.bus = [\n{rows(ppc["bus"])}\n];\nmpc.gen = [\n{rows(ppc["gen"])}\n];\n'
            f'mpc.branch = [\n{rows(ppc["branch"])}\n];\n')
    return atomic.write_text(path, text)
