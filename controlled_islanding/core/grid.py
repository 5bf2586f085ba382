"""Grid model: buses, branches, generators and loads, loaded from MATPOWER-format case data.

Case data comes from PYPOWER (which ships MATPOWER's cases, IEEE 39 included), from a MATPOWER
``.m`` file, a PYPOWER ``.py`` case file, or a ppc dict; nothing is hand-typed. Branch flows at both
ends come from the caller (a state estimator or a bag's NetworkSnapshot) or from PYPOWER's AC power
flow run on the case data with the current branch statuses (`Grid.with_flows`).
"""

from __future__ import annotations

import contextlib
import copy
import importlib
import io
import re
import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

# MATPOWER column indices (0-based), from the MATPOWER case format documentation.
_BUS_I, _BUS_PD, _BUS_QD = 0, 2, 3
_GEN_BUS, _GEN_PG, _GEN_STATUS, _GEN_PMAX = 0, 1, 7, 8
_BR_F, _BR_T, _BR_X, _BR_STATUS = 0, 1, 3, 10
_BR_PF, _BR_PT = 13, 15

_CASE_ALIASES = {'ieee39': 'case39', 'ieee14': 'case14', 'ieee30': 'case30', 'ieee57': 'case57',
                 'ieee118': 'case118', 'ieee300': 'case300'}


class GridError(ValueError):
    """Bad grid data or a request the grid cannot satisfy (unknown branch, failed power flow)."""


@dataclass(frozen=True)
class Branch:
    """A line or transformer.

    Attributes:
        branch_id: Unique id, for MATPOWER cases ``"<from>-<to>"`` or ``"<from>-<to>#<n>"``.
        from_bus: Bus number of the from end.
        to_bus: Bus number of the to end.
        in_service: False once tripped.
        x_pu: Series reactance, pu on the system base (NaN if unknown).
        breaker_id: The breaker that opens this branch, when the data names one.

    """

    branch_id: str
    from_bus: int
    to_bus: int
    in_service: bool = True
    x_pu: float = float('nan')
    breaker_id: str = ''

    @property
    def breaker(self) -> str:
        """Return the breaker id: the one the data names, else one breaker per branch, 'CB-<branch_id>'."""
        return self.breaker_id or f'CB-{self.branch_id}'


@dataclass(frozen=True)
class Generator:
    """A synchronous generator.

    Attributes:
        name: Unique name from the data (``"G<k>"`` by 1-based generator row for MATPOWER cases).
        bus: Terminal bus number.
        p_mw: Dispatched active power, MW.
        p_max_mw: Active power capacity, MW.
        xq_pu: q-axis synchronous reactance, pu on the system base (NaN if unknown).
        ra_pu: Armature resistance, pu on the system base.
        model: Dynamic model name in the source data (for example GENROU, GENCLS); '' if unknown.
        m_s ... s12: Dynamic data for rotor angle estimation by core.dse (see DYNAMIC_FIELDS and
            core.dse.MachineData for meanings); reactances pu and M = 2H in s on the system base; NaN if unknown.

    """

    name: str
    bus: int
    p_mw: float
    p_max_mw: float
    xq_pu: float = float('nan')
    ra_pu: float = 0.0
    model: str = ''
    m_s: float = float('nan')
    d_pu: float = float('nan')
    xd_pu: float = float('nan')
    xd1_pu: float = float('nan')
    xq1_pu: float = float('nan')
    xd2_pu: float = float('nan')
    xq2_pu: float = float('nan')
    xl_pu: float = float('nan')
    td10_s: float = float('nan')
    tq10_s: float = float('nan')
    td20_s: float = float('nan')
    tq20_s: float = float('nan')
    s10: float = float('nan')
    s12: float = float('nan')


# Generator's numeric dynamic data beyond xq and ra, optional; NetworkSnapshot carries each as generator_<name>.
DYNAMIC_FIELDS = ('m_s', 'd_pu', 'xd_pu', 'xd1_pu', 'xq1_pu', 'xd2_pu', 'xq2_pu', 'xl_pu', 'td10_s', 'tq10_s',
                  'td20_s', 'tq20_s', 's10', 's12')


@dataclass(frozen=True)
class Load:
    """A bus load.

    Attributes:
        bus: Bus number.
        p_mw: Active power demand, MW.
        q_mvar: Reactive power demand, Mvar.

    """

    bus: int
    p_mw: float
    q_mvar: float = 0.0


@dataclass(frozen=True)
class Grid:
    """A power network with optional branch flows.

    Attributes:
        name: Case name.
        base_mva: System MVA base.
        buses: Bus numbers.
        branches: All branches, in and out of service.
        generators: In-service generators.
        loads: Bus loads.
        p_from_mw: Active power entering each branch at its from end, MW (None if unknown).
        p_to_mw: Active power entering each branch at its to end, MW (None if unknown).
        matpower: The MATPOWER ppc the grid came from (None if built otherwise); used by `with_flows`.
        freq_hz: Nominal frequency f0, Hz (NaN if unknown): a machine's speed in pu is of 2 pi f0 rad/s.
        bus_angle_rad: Voltage angle of each bus (parallel to buses) as the flows saw it, rad, any reference
            (None if unknown).

    """

    name: str
    base_mva: float
    buses: tuple[int, ...]
    branches: tuple[Branch, ...]
    generators: tuple[Generator, ...]
    loads: tuple[Load, ...]
    p_from_mw: np.ndarray | None = field(default=None, compare=False)
    p_to_mw: np.ndarray | None = field(default=None, compare=False)
    matpower: Mapping[str, Any] | None = field(default=None, compare=False, repr=False)
    freq_hz: float = field(default=float('nan'), compare=False)
    bus_angle_rad: np.ndarray | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        bus_set = set(self.buses)
        if len(bus_set) != len(self.buses):
            raise GridError(f'grid {self.name!r}: duplicate bus numbers')
        if self.bus_angle_rad is not None and len(self.bus_angle_rad) != len(self.buses):
            raise GridError(f'grid {self.name!r}: {len(self.bus_angle_rad)} bus angles for {len(self.buses)} buses')
        ids = [b.branch_id for b in self.branches]
        if len(set(ids)) != len(ids):
            dup = sorted({i for i in ids if ids.count(i) > 1})
            raise GridError(f'grid {self.name!r}: duplicate branch ids {dup}')
        for b in self.branches:
            if b.from_bus not in bus_set or b.to_bus not in bus_set:
                raise GridError(f'grid {self.name!r}: branch {b.branch_id} joins unknown bus '
                                f'{b.from_bus if b.from_bus not in bus_set else b.to_bus}')
        names = [g.name for g in self.generators]
        if len(set(names)) != len(names):
            raise GridError(f'grid {self.name!r}: duplicate generator names')
        for g in self.generators:
            if g.bus not in bus_set:
                raise GridError(f'grid {self.name!r}: generator {g.name} at unknown bus {g.bus}')
        for ld in self.loads:
            if ld.bus not in bus_set:
                raise GridError(f'grid {self.name!r}: load at unknown bus {ld.bus}')
        for label, flows in (('p_from_mw', self.p_from_mw), ('p_to_mw', self.p_to_mw)):
            if flows is not None:
                arr = np.asarray(flows, dtype=float)
                if arr.shape != (len(self.branches),):
                    raise GridError(f'grid {self.name!r}: {label} has shape {arr.shape}, '
                                    f'expected ({len(self.branches)},)')
                object.__setattr__(self, label, arr)
        if (self.p_from_mw is None) != (self.p_to_mw is None):
            raise GridError(f'grid {self.name!r}: give both p_from_mw and p_to_mw or neither')

    @classmethod
    def from_matpower(cls, case: str | Path | Mapping[str, Any]) -> Grid:
        """Load a MATPOWER-format case.

        Args:
            case: A case name PYPOWER ships (``'case39'``, alias ``'ieee39'``), a path to a MATPOWER ``.m``
                file or a PYPOWER ``.py`` case file, or a ppc dict (baseMVA, bus, gen, branch).

        Returns:
            The grid, without flows (see `with_flows`); the case's own solved flows are not trusted.

        Raises:
            GridError: Unknown case name, unreadable file or malformed data.

        """
        name, ppc = _load_ppc(case)
        return _grid_from_ppc(name, ppc)

    @property
    def has_flows(self) -> bool:
        """Whether branch flows at both ends are known."""
        return self.p_from_mw is not None

    def bus_angles_at(self, buses: Iterable[int]) -> np.ndarray:
        """Return the voltage angle of each given bus as the flows saw it, rad (NaN: not known, or not a bus)."""
        at = {} if self.bus_angle_rad is None else dict(zip(self.buses, self.bus_angle_rad, strict=True))
        return np.array([at.get(int(b), np.nan) for b in buses], dtype=float)

    def generator_by_bus(self) -> dict[int, list[Generator]]:
        """Return the generators at each bus that has any."""
        out: dict[int, list[Generator]] = {}
        for g in self.generators:
            out.setdefault(g.bus, []).append(g)
        return out

    def find_branches(self, outage: str | tuple[int, int]) -> list[int]:
        """Return the indices of the branches an outage names.

        Args:
            outage: A branch id, or a bus pair as ``(from, to)`` or ``"from-to"`` in either order.

        Returns:
            Indices into `branches` (one branch; a bus pair joined by parallel branches must be named by id).

        Raises:
            GridError: No such branch, or a bus pair joined by several branches.

        """
        if isinstance(outage, str):
            for i, b in enumerate(self.branches):
                if b.branch_id == outage:
                    return [i]
            m = re.fullmatch(r'\s*(\d+)\s*-\s*(\d+)\s*', outage)
            if not m:
                raise GridError(f'outage {outage!r} is neither a branch id of {self.name} nor a bus pair "from-to"')
            pair = (int(m.group(1)), int(m.group(2)))
        else:
            pair = (int(outage[0]), int(outage[1]))
        hits = [i for i, b in enumerate(self.branches) if {b.from_bus, b.to_bus} == set(pair) and pair[0] != pair[1]]
        if not hits:
            raise GridError(f'outage {outage!r}: no branch joins buses {pair[0]} and {pair[1]} in {self.name}')
        if len(hits) > 1:
            ids = [self.branches[i].branch_id for i in hits]
            raise GridError(f'outage {outage!r}: buses {pair[0]} and {pair[1]} are joined by parallel branches '
                            f'{ids}; name one by its id')
        return hits

    def with_outages(self, outages: Iterable[str | tuple[int, int]]) -> Grid:
        """Return a copy with the named branches out of service (their flows set to 0 MW).

        Args:
            outages: Branch ids or bus pairs (see `find_branches`).

        Returns:
            The new grid; flows of other branches are kept as they were (not recomputed).

        Raises:
            GridError: An outage names no branch.

        """
        idx: set[int] = set()
        for outage in outages:
            idx.update(self.find_branches(outage))
        branches = tuple(replace(b, in_service=False) if i in idx else b for i, b in enumerate(self.branches))
        p_from, p_to = self.p_from_mw, self.p_to_mw
        if p_from is not None and p_to is not None:
            p_from, p_to = p_from.copy(), p_to.copy()
            p_from[sorted(idx)] = 0.0
            p_to[sorted(idx)] = 0.0
        return replace(self, branches=branches, p_from_mw=p_from, p_to_mw=p_to)

    def without_flows(self) -> Grid:
        """Return a copy with the branch flows forgotten."""
        return replace(self, p_from_mw=None, p_to_mw=None)

    def with_flows(self) -> Grid:
        """Return a copy with branch flows from PYPOWER's AC power flow on the in-service branches.

        Returns:
            The grid with `p_from_mw` / `p_to_mw` (0 MW on out-of-service branches).

        Raises:
            GridError: The grid carries no MATPOWER data, or the power flow does not converge
                (for example because the outages split the network).

        """
        if self.matpower is None:
            raise GridError(f'grid {self.name!r} has no MATPOWER case data, so its flows cannot be computed; '
                            'give flows (p_from_mw, p_to_mw) with the grid')
        from pypower.api import ppoption, runpf

        ppc = copy.deepcopy(dict(self.matpower))
        ppc['branch'][:, _BR_STATUS] = [1.0 if b.in_service else 0.0 for b in self.branches]
        # PYPOWER prints and warns on a singular Jacobian even with VERBOSE=0; the failure is reported below.
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter('ignore')
            result, success = runpf(ppc, ppoption(VERBOSE=0, OUT_ALL=0))
        if not success:
            out = [b.branch_id for b in self.branches if not b.in_service]
            raise GridError(f'AC power flow of {self.name} with branches {out} out of service did not converge')
        on = np.array([b.in_service for b in self.branches])
        p_from = np.where(on, result['branch'][:, _BR_PF], 0.0)
        p_to = np.where(on, result['branch'][:, _BR_PT], 0.0)
        return replace(self, p_from_mw=p_from.astype(float), p_to_mw=p_to.astype(float))


def _load_ppc(case: str | Path | Mapping[str, Any]) -> tuple[str, dict[str, Any]]:
    if isinstance(case, Mapping):
        return str(case.get('name', 'ppc')), {k: copy.deepcopy(v) for k, v in case.items()}
    text = str(case)
    path = Path(text)
    if path.suffix in ('.m', '.py'):
        if not path.is_file():
            raise GridError(f'case file {text!r} does not exist')
        if path.suffix == '.m':
            return path.stem, _parse_matpower_m(path)
        from pypower.loadcase import loadcase

        try:
            return path.stem, loadcase(str(path))
        except Exception as exc:  # PYPOWER raises bare Exceptions on bad files
            raise GridError(f'case file {text!r} is not a PYPOWER case: {exc}') from exc
    name = _CASE_ALIASES.get(text.lower(), text)
    if not re.fullmatch(r'case[0-9A-Za-z_]+', name):
        raise GridError(f'case {text!r} is not a PYPOWER case name (e.g. case39, ieee39) nor a .m/.py file')
    try:
        module = importlib.import_module(f'pypower.{name}')
    except ModuleNotFoundError as exc:
        raise GridError(f'case {text!r}: PYPOWER ships no case named {name!r}') from exc
    return name, getattr(module, name)()


def _parse_matpower_m(path: Path) -> dict[str, Any]:
    """Read baseMVA, bus, gen and branch from a MATPOWER .m case file."""
    text = '\n'.join(line.split('%', 1)[0] for line in path.read_text().splitlines())
    ppc: dict[str, Any] = {}
    m = re.search(r'mpc\.baseMVA\s*=\s*([-+0-9.eE]+)\s*;', text)
    if not m:
        raise GridError(f'case file {path}: no "mpc.baseMVA = ...;"')
    ppc['baseMVA'] = float(m.group(1))
    for key in ('bus', 'gen', 'branch'):
        m = re.search(rf'mpc\.{key}\s*=\s*\[(.*?)\]\s*;', text, flags=re.S)
        if not m:
            raise GridError(f'case file {path}: no "mpc.{key} = [...];" matrix')
        rows = [r.split() for r in re.split(r'[;\n]', m.group(1).replace(',', ' ')) if r.strip()]
        try:
            ppc[key] = np.array([[float(v) for v in r] for r in rows], dtype=float)
        except ValueError as exc:
            raise GridError(f'case file {path}: mpc.{key} is not a numeric matrix ({exc})') from exc
        if ppc[key].ndim != 2 or len({len(r) for r in rows}) != 1:
            raise GridError(f'case file {path}: mpc.{key} rows have different lengths')
    return ppc


def _grid_from_ppc(name: str, ppc: Mapping[str, Any]) -> Grid:
    for key in ('baseMVA', 'bus', 'gen', 'branch'):
        if key not in ppc:
            raise GridError(f'case {name!r} has no {key!r}')
    bus = np.atleast_2d(np.asarray(ppc['bus'], dtype=float))
    gen = np.atleast_2d(np.asarray(ppc['gen'], dtype=float))
    branch = np.atleast_2d(np.asarray(ppc['branch'], dtype=float))
    if bus.shape[1] < 13 or gen.shape[1] < 10 or branch.shape[1] < 11:
        raise GridError(f'case {name!r}: bus/gen/branch matrices have too few MATPOWER columns '
                        f'({bus.shape[1]}, {gen.shape[1]}, {branch.shape[1]})')
    buses = tuple(int(b) for b in bus[:, _BUS_I])
    branches: list[Branch] = []
    seen: dict[frozenset[int], int] = {}
    for row in branch:
        f, t = int(row[_BR_F]), int(row[_BR_T])
        key = frozenset((f, t))
        seen[key] = seen.get(key, 0) + 1
        bid = f'{f}-{t}' if seen[key] == 1 else f'{f}-{t}#{seen[key]}'
        branches.append(Branch(bid, f, t, bool(row[_BR_STATUS] > 0), float(row[_BR_X])))
    generators = tuple(
        Generator(f'G{k + 1}', int(row[_GEN_BUS]), float(row[_GEN_PG]), float(row[_GEN_PMAX]))
        for k, row in enumerate(gen) if row[_GEN_STATUS] > 0)
    loads = tuple(Load(int(r[_BUS_I]), float(r[_BUS_PD]), float(r[_BUS_QD]))
                  for r in bus if r[_BUS_PD] != 0.0 or r[_BUS_QD] != 0.0)
    matpower = {'baseMVA': float(ppc['baseMVA']), 'bus': bus.copy(), 'gen': gen.copy(), 'branch': branch.copy()}
    return Grid(name=name, base_mva=float(ppc['baseMVA']), buses=buses, branches=tuple(branches),
                generators=generators, loads=loads, matpower=matpower)
