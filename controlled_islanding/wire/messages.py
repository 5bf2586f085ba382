"""Decode and check messages into core data; works on rclpy and on rosbags message objects alike (no rclpy).

Every decoder raises MessageError with a `reason` key the nodes count in /diagnostics. Sizes are checked against
`Limits` before any per-element work, so one oversized message costs no more than its length check.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controlled_islanding.core.grid import DYNAMIC_FIELDS, Branch, Generator, Grid, GridError, Load


class MessageError(ValueError):
    """A message that cannot be used; `reason` is a short stable key such as 'array_length'."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def stamp_s(stamp: object) -> float:
    """Return a builtin_interfaces/Time as seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def split_stamp(t_s: float) -> tuple[int, int]:
    """Return (sec, nanosec) of a builtin_interfaces/Time for a time in s."""
    total_ns = int(round(t_s * 1e9))
    return total_ns // 1_000_000_000, total_ns % 1_000_000_000


def _parallel(msg: object, what: str, fields: tuple[str, ...]) -> int:
    lengths = {f: len(getattr(msg, f)) for f in fields}
    if len(set(lengths.values())) > 1:
        detail = ', '.join(f'{f}={n}' for f, n in lengths.items())
        raise MessageError('array_length', f'{what}: parallel arrays differ in length ({detail})')
    return next(iter(lengths.values()))


@dataclass(frozen=True)
class Limits:
    """Largest message a decoder accepts (counts of elements).

    Room for a large interconnection model, but bounded, so no message can make a node, or every later
    decision, allocate without limit.

    Attributes:
        max_buses: Buses per snapshot.
        max_branches: Branches per snapshot.
        max_generators: Generators per snapshot or per coherent-groups message.
        max_loads: Loads per snapshot.

    """

    max_buses: int = 50_000
    max_branches: int = 100_000
    max_generators: int = 10_000
    max_loads: int = 50_000


def element_count(msg: object) -> int:
    """Return how many elements a message's arrays carry together (a message's size for memory bounds), at least 1.

    A string counts as one element; a message nested in an array counts as many as it has fields (a PMU frame's
    measurements, 9 each), which weighs a decoded measurement (about 310 bytes) more fairly against a number.
    """
    n = 0
    for name in getattr(msg, 'get_fields_and_field_types', dict)():
        value = getattr(msg, name, None)
        if not isinstance(value, (str, bytes)) and hasattr(value, '__len__') and len(value):
            n += len(value) * len(getattr(value[0], 'get_fields_and_field_types', lambda: (0,))())
    return max(n, 1)


def _at_most(msg: object, what: str, fields: tuple[str, ...], cap: int) -> None:
    for f in fields:
        n = len(getattr(msg, f, ()))  # a field newer than the message's type counts as empty
        if n > cap:
            raise MessageError('too_large', f'{what}: {f} has {n} entries, more than the limit of {cap}')


def _finite(values: object, what: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise MessageError('nan_value', f'{what} holds NaN or inf')
    return arr


def _finite_non_negative(values: object, what: str) -> np.ndarray:
    arr = _finite(values, what)
    if (arr < 0).any():
        raise MessageError('bad_value', f'{what} holds a negative value ({float(arr.min())}); it must be >= 0')
    return arr


_BRANCH_FIELDS = ('branch_ids', 'branch_breaker_ids', 'branch_from_bus', 'branch_to_bus', 'branch_in_service',
                  'branch_p_from_mw', 'branch_p_to_mw')
_DYNAMIC_MSG_FIELDS = tuple(f'generator_{name}' for name in DYNAMIC_FIELDS)
_GENERATOR_FIELDS = ('generator_names', 'generator_bus', 'generator_p_mw', 'generator_p_max_mw', 'generator_xq_pu',
                     'generator_ra_pu', 'generator_model') + _DYNAMIC_MSG_FIELDS
# Longest model name accepted; real ones (GENROU, GENCLS, REGCA1) are a few characters.
MAX_MODEL_NAME = 64
# Longest islanding request id accepted (partitioning refuses longer requests).
MAX_REQUEST_ID = 128


def dynamic_data_fields(generators: tuple[Generator, ...]) -> dict[str, object]:
    """Return the NetworkSnapshot machine-data fields of generators, by message field name.

    generator_model is a list of str; each DYNAMIC_FIELDS entry a float64 numpy array, NaN where unknown (rclpy
    needs these as lists: .tolist()).
    """
    out: dict[str, object] = {'generator_model': [str(g.model) for g in generators]}
    for name, field in zip(DYNAMIC_FIELDS, _DYNAMIC_MSG_FIELDS, strict=True):
        out[field] = np.array([getattr(g, name) for g in generators], dtype=np.float64)
    return out


def decode_dynamic_data(msg: object, n_gen: int) -> tuple[list[str], dict[str, np.ndarray]]:
    """Return (model name per generator, DYNAMIC_FIELDS name -> values) of a NetworkSnapshot, NaN / '' = unknown.

    Each array is optional: empty, or absent from a message type older than the fields (an old bag), means
    unknown for every generator.

    Raises:
        MessageError: An array of another length than the generators, an inf or negative value, or a model name
            longer than MAX_MODEL_NAME.

    """
    models = [str(x) for x in getattr(msg, 'generator_model', ())]
    if len(models) not in (0, n_gen):
        raise MessageError('array_length', f'generator_model has {len(models)} entries for {n_gen} generators; '
                                           'give one per generator or none')
    if any(len(m) > MAX_MODEL_NAME for m in models):
        raise MessageError('bad_value', f'generator_model holds a name longer than {MAX_MODEL_NAME} characters')
    values = {}
    for name, field in zip(DYNAMIC_FIELDS, _DYNAMIC_MSG_FIELDS, strict=True):
        arr = np.asarray(getattr(msg, field, ()), dtype=float).reshape(-1)
        if arr.size == 0:
            arr = np.full(n_gen, np.nan)
        elif arr.size != n_gen:
            raise MessageError('array_length', f'{field} has {arr.size} entries for {n_gen} generators; give one '
                                               'per generator or none')
        # NaN is 'unknown'; inf or a negative value is no machine's data (core.dse decides what it can use).
        if np.isinf(arr).any():
            raise MessageError('nan_value', f'{field} holds inf')
        if (arr < 0).any():
            raise MessageError('bad_value', f'{field} holds a negative value ({float(np.nanmin(arr))}); it must '
                                            'be >= 0 or NaN')
        values[name] = arr
    return models or [''] * n_gen, values
_LOAD_FIELDS = ('load_bus', 'load_p_mw', 'load_q_mvar')


def nominal_frequency_hz(grid: Grid) -> float:
    """Return a grid's nominal frequency for NetworkSnapshot.nominal_frequency_hz: Hz, 0 when not known."""
    f0 = float(grid.freq_hz)
    return f0 if np.isfinite(f0) and f0 > 0 else 0.0


def bus_voltage_angles(grid: Grid) -> list[float]:
    """Return a grid's bus angles for NetworkSnapshot.bus_voltage_angle_rad: rad, empty when not known."""
    return [] if grid.bus_angle_rad is None else [float(a) for a in grid.bus_angle_rad]


def snapshot_frequency_hz(msg: object) -> float:
    """Return a NetworkSnapshot's nominal frequency, Hz, NaN when not known (0, or a message from before the field).

    Raises:
        MessageError: NaN, inf or negative ('nan_value', 'bad_value').

    """
    f0 = float(getattr(msg, 'nominal_frequency_hz', 0.0))
    if not np.isfinite(f0):
        raise MessageError('nan_value', f'nominal_frequency_hz={f0} is not a number')
    if f0 < 0:
        raise MessageError('bad_value', f'nominal_frequency_hz={f0} Hz must be positive, or 0 when not known')
    return f0 if f0 > 0 else float('nan')


def grid_from_snapshot(msg: object, limits: Limits = Limits()) -> Grid:
    """Build a core Grid (with flows) from a NetworkSnapshot message.

    Args:
        msg: A NetworkSnapshot (rclpy or rosbags).
        limits: Largest network accepted.

    Raises:
        MessageError: Too large ('too_large'), empty, arrays of unequal length, NaN/inf values, negative
            reactance or resistance ('bad_value'), a base that is not positive, or an inconsistent network.
            Machine dynamic data are optional (empty or NaN = unknown) but never inf, negative, or of another
            length than the generators.

    """
    _at_most(msg, 'network snapshot', ('bus_numbers', 'bus_voltage_angle_rad'), limits.max_buses)
    _at_most(msg, 'network snapshot', _BRANCH_FIELDS, limits.max_branches)
    _at_most(msg, 'network snapshot', _GENERATOR_FIELDS, limits.max_generators)
    _at_most(msg, 'network snapshot', _LOAD_FIELDS, limits.max_loads)
    if not len(msg.bus_numbers) or not len(msg.branch_ids) or not len(msg.generator_names):
        raise MessageError('empty_message', 'network snapshot has no buses, branches or generators')
    _parallel(msg, 'snapshot branches', ('branch_ids', 'branch_from_bus', 'branch_to_bus', 'branch_in_service',
                                         'branch_p_from_mw', 'branch_p_to_mw'))
    _parallel(msg, 'snapshot generators', ('generator_names', 'generator_bus', 'generator_p_mw',
                                           'generator_p_max_mw', 'generator_xq_pu', 'generator_ra_pu'))
    _parallel(msg, 'snapshot loads', ('load_bus', 'load_p_mw', 'load_q_mvar'))
    breakers = [str(x) for x in msg.branch_breaker_ids] or [''] * len(msg.branch_ids)
    if len(breakers) != len(msg.branch_ids):
        raise MessageError('array_length', f'branch_breaker_ids has {len(msg.branch_breaker_ids)} entries for '
                                           f'{len(msg.branch_ids)} branches; give one per branch or none')
    p_from = _finite(msg.branch_p_from_mw, 'branch_p_from_mw')
    p_to = _finite(msg.branch_p_to_mw, 'branch_p_to_mw')
    gen_p = _finite(msg.generator_p_mw, 'generator_p_mw')
    gen_p_max = _finite(msg.generator_p_max_mw, 'generator_p_max_mw')
    # A NaN or negative reactance reaches core.rotor_angle, which refuses it on every frame.
    xq = _finite_non_negative(msg.generator_xq_pu, 'generator_xq_pu')
    ra = _finite_non_negative(msg.generator_ra_pu, 'generator_ra_pu')
    models, dynamic = decode_dynamic_data(msg, len(msg.generator_names))
    angles = _finite(getattr(msg, 'bus_voltage_angle_rad', ()), 'bus_voltage_angle_rad')
    if angles.size and angles.size != len(msg.bus_numbers):
        raise MessageError('array_length', f'bus_voltage_angle_rad has {angles.size} entries for '
                                           f'{len(msg.bus_numbers)} buses; give one per bus or none')
    load_p = _finite(msg.load_p_mw, 'load_p_mw')
    load_q = _finite(msg.load_q_mvar, 'load_q_mvar')
    base = float(msg.base_mva)
    f0 = snapshot_frequency_hz(msg)
    if not np.isfinite(base):
        raise MessageError('nan_value', f'base_mva={base} is not a number')
    if base <= 0:
        raise MessageError('bad_value', f'base_mva={base} MVA must be positive')
    try:
        return Grid(
            name=str(msg.case_name), base_mva=base, buses=tuple(int(b) for b in msg.bus_numbers),
            branches=tuple(Branch(str(i), int(f), int(t), bool(s), breaker_id=c) for i, f, t, s, c in zip(
                msg.branch_ids, msg.branch_from_bus, msg.branch_to_bus, msg.branch_in_service, breakers, strict=True)),
            generators=tuple(
                Generator(str(n), int(b), float(p), float(pm), float(x), float(r), model=models[k],
                          **{name: float(dynamic[name][k]) for name in DYNAMIC_FIELDS})
                for k, (n, b, p, pm, x, r) in enumerate(zip(msg.generator_names, msg.generator_bus, gen_p, gen_p_max,
                                                            xq, ra, strict=True))),
            loads=tuple(Load(int(b), float(p), float(q))
                        for b, p, q in zip(msg.load_bus, load_p, load_q, strict=True)),
            p_from_mw=p_from, p_to_mw=p_to, freq_hz=f0, bus_angle_rad=angles if angles.size else None)
    except GridError as exc:
        raise MessageError('unknown_id', str(exc)) from exc


MONITOR_FIELDS = ('omega_pu', 'tm_pu', 'pe_pu', 'v_pu')  # RotorAngles' optional arrays: empty or one per name


def sample_columns(msg: object, column: dict[str, int]) -> dict[str, np.ndarray] | None:
    """Return a RotorAngles sample's arrays in column order (NaN: not known); None if it names other generators.

    column: generator name -> column (the snapshot's machines). Keys: delta_rad, omega_pu, pm_pu, pe_pu, v_pu
    (float) and valid (bool). A machine's angle is kept where the sample is valid or the filter has its speed (its
    prediction); its power and voltage only where valid.
    """
    names = [str(x) for x in msg.generator_names]
    cols = [column.get(x, -1) for x in names]
    n = len(column)
    if -1 in cols or len(set(cols)) != len(cols) or len(cols) != n:
        return None
    valid = np.zeros(n, dtype=bool)
    valid[cols] = np.asarray(msg.valid, dtype=bool)
    out = {'valid': valid}
    for field, key in (('angle_rad', 'delta_rad'), ('omega_pu', 'omega_pu'), ('tm_pu', 'pm_pu'),
                       ('pe_pu', 'pe_pu'), ('v_pu', 'v_pu')):
        values = np.asarray(getattr(msg, field, ()), dtype=float)
        row = np.full(n, np.nan)
        if values.size:
            row[cols] = values
        out[key] = row
    out['delta_rad'] = np.where(valid | np.isfinite(out['omega_pu']), out['delta_rad'], np.nan)
    out['pe_pu'] = np.where(valid, out['pe_pu'], np.nan)
    out['v_pu'] = np.where(valid, out['v_pu'], np.nan)
    return out


@dataclass(frozen=True)
class Groups:
    """Coherent groups decoded from a CoherentGroups message, labels renumbered canonically.

    Attributes:
        names: Generator names.
        labels: Group of each generator, renumbered 0.. in order of first appearance, so the same partition
            always has the same labels.
        k: Number of groups.
        stamp_s: Time tag of the newest sample in the window, s.
        method: Coherency method.
        unobserved: Generators in no group because they had no usable data (partial observability).
        request_id: The islanding request coherency computed these groups for ('' for a periodic grouping).
        suspect: (generator, reason) for those of `unobserved` excluded because their PMU data were suspect.

    """

    names: tuple[str, ...]
    labels: tuple[int, ...]
    k: int
    stamp_s: float
    method: str
    unobserved: tuple[str, ...] = ()
    request_id: str = ''
    suspect: tuple[tuple[str, str], ...] = ()

    def as_mapping(self) -> dict[str, int]:
        """Return generator name -> group."""
        return dict(zip(self.names, self.labels, strict=True))


def groups_from_msg(msg: object, limits: Limits = Limits()) -> Groups:
    """Decode and check a CoherentGroups message.

    Args:
        msg: A CoherentGroups message (rclpy or rosbags).
        limits: `max_generators` bounds the generators named.

    Raises:
        MessageError: Too large, empty, arrays of unequal length, duplicate names (a generator both grouped and
            unobserved included), NaN/inf or negative distances, k not matching the labels, or a request id
            longer than MAX_REQUEST_ID.

    """
    _at_most(msg, 'coherent groups', ('generator_names', 'generator_buses', 'group', 'unobserved_generator_names'),
             limits.max_generators)
    n = _parallel(msg, 'coherent groups', ('generator_names', 'generator_buses', 'group'))
    if n == 0:
        raise MessageError('empty_message', 'coherent groups name no generator')
    names = tuple(str(x) for x in msg.generator_names)
    unobserved = tuple(str(x) for x in msg.unobserved_generator_names)
    if len(set(names) | set(unobserved)) != n + len(unobserved):
        raise MessageError('unknown_id', 'coherent groups name a generator twice (grouped or unobserved)')
    if len(msg.distance) not in (0, n * n):
        raise MessageError('array_length', f'distance has {len(msg.distance)} values, expected 0 or {n * n}')
    _finite_non_negative(msg.distance, 'coherent groups distance')
    raw = [int(g) for g in msg.group]
    if int(msg.k) != len(set(raw)) or max(raw) >= int(msg.k):
        raise MessageError('bad_value', f'k={msg.k} does not match the group labels {sorted(set(raw))}')
    order: dict[int, int] = {}
    labels = tuple(order.setdefault(g, len(order)) for g in raw)
    stamp = stamp_s(msg.header.stamp)
    if stamp <= 0:
        raise MessageError('missing_stamp', 'coherent groups header.stamp is zero')
    request_id = str(getattr(msg, 'request_id', ''))
    if len(request_id) > MAX_REQUEST_ID:
        raise MessageError('bad_value', f'coherent groups request_id is longer than {MAX_REQUEST_ID} characters')
    suspect_names = [str(x) for x in getattr(msg, 'suspect_generator_names', ())]
    reasons = [str(x) for x in getattr(msg, 'suspect_reasons', ())]
    if len(reasons) != len(suspect_names) or len(suspect_names) > limits.max_generators:
        raise MessageError('array_length', f'{len(suspect_names)} suspect generators but {len(reasons)} reasons')
    if not set(suspect_names) <= set(unobserved):
        raise MessageError('unknown_id', 'coherent groups list suspect generators that are not unobserved')
    return Groups(names=names, labels=labels, k=len(order), stamp_s=stamp, method=str(msg.method),
                  unobserved=tuple(sorted(unobserved)), request_id=request_id,
                  suspect=tuple(sorted(zip(suspect_names, reasons, strict=True))))
