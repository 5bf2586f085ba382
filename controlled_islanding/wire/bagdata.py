"""Offline reader of the project's scenario bags into plain numpy data.

`load_bag(path)` reads a rosbag2 bag (MCAP) written by `controlled-islanding simulate`
and returns a `BagData`. Conventions:

- Times are in seconds relative to the simulation start `t0_s`, which is the
  header stamp of the (first) NetworkSnapshot; `t0_s` itself is absolute (s since
  the Unix epoch).
- PMU rows lie on the uniform time-tag grid `k / rate_fps` from the simulation
  start to the last time tag in the bag. A frame that is absent from the bag (lost
  entirely, or never delivered) gives a row of NaN with `frame_present` False; a
  measurement whose STAT marks it invalid gives NaN in that PMU's column.
- Columns follow the order of the PMUs in the first frame (`buses`).
- Truth arrays come from the /truth topics; no node may read them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from controlled_islanding.core.grid import DYNAMIC_FIELDS, Branch, Generator, Grid, Load
from controlled_islanding.wire import topics
from controlled_islanding.wire.bagmeta import unreadable
from controlled_islanding.wire.interfaces import typestore
from controlled_islanding.wire.messages import MessageError, decode_dynamic_data, snapshot_frequency_hz

# STAT bits 15-14 set to 10 or 11 mean "do not use" (PmuMeasurement.msg).
_STAT_UNUSABLE_MASK = 0x8000
STAT_ABSENT = 0x8000
_PHASOR_FIELDS = ('voltage_magnitude_pu', 'voltage_angle_rad', 'current_magnitude_pu', 'current_angle_rad',
                  'frequency_hz', 'rocof_hz_per_s')


class BagDataError(ValueError):
    """The bag cannot be read or lacks what a scenario bag must hold."""


@dataclass(frozen=True)
class BranchEvent:
    """A branch status change recorded in the bag.

    Attributes:
        t_s: Time of the change, s after the simulation start.
        branch_id: Branch id as in the snapshot.
        from_bus: From-bus number.
        to_bus: To-bus number.
        in_service: False when the branch opened (tripped).

    """

    t_s: float
    branch_id: str
    from_bus: int
    to_bus: int
    in_service: bool


@dataclass(frozen=True)
class PmuChannels:
    """What the PMU channels measured: one value per channel (a frame), or per time tag and channel (a run).

    Attributes:
        tag_s: Time tag, s; shape (n,) for a run.
        delivery_s: When it reaches the PDC, s (tag + delay); shape (n,) for a run.
        station_ids: Station id of each channel (`PMU_<bus>`, or `PMU_<bus>/<generator>` where a bus has several
            generators, each with its own current).
        buses: Bus of each channel; a bus with several generators has several channels.
        v_mag_pu, v_angle_rad, i_mag_pu, i_angle_rad, frequency_hz, rocof_hz_per_s: Per channel (last axis); NaN
            where lost.
        stat: STAT word per channel; STAT_DATA_INVALID where lost.

    """

    tag_s: float | np.ndarray
    delivery_s: float | np.ndarray
    station_ids: tuple[str, ...]
    buses: tuple[int, ...] | np.ndarray
    v_mag_pu: np.ndarray
    v_angle_rad: np.ndarray
    i_mag_pu: np.ndarray
    i_angle_rad: np.ndarray
    frequency_hz: np.ndarray
    rocof_hz_per_s: np.ndarray
    stat: np.ndarray


@dataclass(frozen=True)
class BagData(PmuChannels):
    """Everything a scenario bag holds, as numpy arrays (see the module docstring for conventions).

    Attributes:
        path: The bag directory.
        t0_s: Absolute time of the simulation start (snapshot stamp), s since the Unix epoch.
        rate_fps: PMU reporting rate, frames per second.
        tag_s, delivery_s, station_ids, buses, v_mag_pu ... stat: The PMU channels (PmuChannels), a row per time tag
            of the uniform grid, s after t0_s: NaN where invalid or absent, delivery_s NaN and stat STAT_ABSENT
            where the frame is absent; buses an array, shape (n_pmu,).
        frame_present: Whether a frame with that time tag is in the bag, shape (n_frames,).
        grid: The pre-fault network snapshot, with branch flows in MW.
        branch_events: Branch status changes in time order.
        request_t_s: Islanding request times, s after t0_s, in order.
        request_ids: Request id of each request.
        truth_t_s: Time tags of the true rotor angles, s after t0_s, shape (n_truth,).
        truth_generator_names: Generator of each truth column.
        truth_generator_buses: Terminal bus of each truth column.
        truth_angles_rad: Simulated rotor angles, rad, unwrapped, shape (n_truth, n_gen).
        truth_groups: Generator name -> true coherent group (0-based), or None if the bag has none.

    """

    path: Path
    t0_s: float
    rate_fps: float
    frame_present: np.ndarray
    grid: Grid
    branch_events: tuple[BranchEvent, ...]
    request_t_s: np.ndarray
    request_ids: tuple[str, ...]
    truth_t_s: np.ndarray
    truth_generator_names: tuple[str, ...]
    truth_generator_buses: np.ndarray
    truth_angles_rad: np.ndarray
    truth_groups: dict[str, int] | None

    @property
    def truth_k(self) -> int | None:
        """Number of true coherent groups, or None if the bag has none."""
        return None if self.truth_groups is None else len(set(self.truth_groups.values()))

    def pmu_column(self, generator: str, bus: int) -> int:
        """Return the PMU column of a generator: its own channel ('<station>/<name>') if it has one, else its bus's.

        Raises:
            BagDataError: No PMU at the generator's bus.

        """
        own = [j for j, s in enumerate(self.station_ids) if s.rpartition('/')[2] == generator and '/' in s]
        at_bus = np.flatnonzero(self.buses == bus)
        if own:
            return own[0]
        if not len(at_bus):
            raise BagDataError(f'{self.path}: no PMU at bus {bus} of generator {generator}')
        return int(at_bus[0])

    def tripped_branch_ids(self, before_s: float | None = None) -> tuple[str, ...]:
        """Return the branches out of service at a time, by replaying the status events.

        Args:
            before_s: Time, s after t0_s; events at or after it are ignored. None: the first request time
                (every event if the bag has no request).

        Returns:
            Branch ids, in the order they opened.

        """
        if before_s is None:
            before_s = float(self.request_t_s[0]) if len(self.request_t_s) else np.inf
        out: dict[str, None] = {}
        for event in self.branch_events:
            if event.t_s >= before_s:
                break
            if event.in_service:
                out.pop(event.branch_id, None)
            else:
                out[event.branch_id] = None
        return tuple(out)

    def grid_at(self, before_s: float | None = None) -> Grid:
        """Return the snapshot grid with the branches tripped before a time taken out (flows kept from the snapshot).

        Args:
            before_s: As in tripped_branch_ids.

        Returns:
            The grid with those branches out of service.

        """
        return self.grid.with_outages(self.tripped_branch_ids(before_s))


def _stamp_ns(stamp: object) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _grid_from_snapshot(msg: object) -> Grid:
    base = float(msg.base_mva)
    xq = np.asarray(msg.generator_xq_pu, dtype=float)
    ra = np.asarray(msg.generator_ra_pu, dtype=float)
    n_gen = len(msg.generator_names)
    if len(xq) != n_gen:
        xq = np.full(n_gen, np.nan)
    if len(ra) != n_gen:
        ra = np.zeros(n_gen)
    branches = tuple(
        Branch(branch_id=str(bid), from_bus=int(f), to_bus=int(t), in_service=bool(s))
        for bid, f, t, s in zip(msg.branch_ids, msg.branch_from_bus, msg.branch_to_bus, msg.branch_in_service,
                                strict=True))
    try:
        models, dynamic = decode_dynamic_data(msg, n_gen)
        f0 = snapshot_frequency_hz(msg)
    except MessageError as exc:
        raise BagDataError(f'snapshot machine data: {exc}') from exc
    generators = tuple(
        Generator(name=str(name), bus=int(bus), p_mw=float(p), p_max_mw=float(pmax), xq_pu=float(x), ra_pu=float(r),
                  model=models[k], **{f: float(dynamic[f][k]) for f in DYNAMIC_FIELDS})
        for k, (name, bus, p, pmax, x, r) in enumerate(zip(msg.generator_names, msg.generator_bus, msg.generator_p_mw,
                                                           msg.generator_p_max_mw, xq, ra, strict=True)))
    loads = tuple(Load(bus=int(b), p_mw=float(p), q_mvar=float(q))
                  for b, p, q in zip(msg.load_bus, msg.load_p_mw, msg.load_q_mvar, strict=True))
    angles = np.asarray(getattr(msg, 'bus_voltage_angle_rad', ()), dtype=float)  # bags from before the field
    return Grid(name=str(msg.case_name), base_mva=base, buses=tuple(int(b) for b in msg.bus_numbers),
                branches=branches, generators=generators, loads=loads,
                p_from_mw=np.asarray(msg.branch_p_from_mw, dtype=float),
                p_to_mw=np.asarray(msg.branch_p_to_mw, dtype=float), freq_hz=f0,
                bus_angle_rad=angles if angles.size and angles.size == len(msg.bus_numbers) else None)


def load_bag(path: str | Path) -> BagData:
    """Read a scenario bag into a BagData.

    Args:
        path: The bag directory (rosbag2, MCAP storage).

    Returns:
        The bag's contents.

    Raises:
        BagDataError: The path is not a readable bag, or it has no NetworkSnapshot or no PMU frames.

    """
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if not path.exists():
        raise BagDataError(f'{path}: no such bag')
    store = typestore()
    snapshot = None
    frames: list[tuple[int, int, object]] = []
    events: list[tuple[int, object]] = []
    requests: list[tuple[int, str]] = []
    truth: list[tuple[int, object]] = []
    groups_msg = None
    try:
        with AnyReader([path], default_typestore=store) as reader:
            for conn, timestamp, raw in reader.messages():
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == topics.NETWORK_SNAPSHOT and snapshot is None:
                    snapshot = msg
                elif conn.topic == topics.PMU_FRAMES:
                    frames.append((_stamp_ns(msg.header.stamp), timestamp, msg))
                elif conn.topic == topics.BRANCH_STATUS:
                    events.append((_stamp_ns(msg.header.stamp), msg))
                elif conn.topic == topics.ISLANDING_REQUEST:
                    requests.append((_stamp_ns(msg.header.stamp), str(msg.request_id)))
                elif conn.topic == topics.TRUTH_ROTOR_ANGLES:
                    truth.append((_stamp_ns(msg.header.stamp), msg))
                elif conn.topic == topics.TRUTH_COHERENT_GROUPS:
                    groups_msg = msg
    except Exception as exc:  # rosbags raises many reader error types; name the bag either way
        raise BagDataError(f'cannot read the bag: {unreadable(path, exc)}') from exc
    if snapshot is None:
        raise BagDataError(f'{path}: no {topics.NETWORK_SNAPSHOT} message')
    if not frames:
        raise BagDataError(f'{path}: no {topics.PMU_FRAMES} messages')
    t0_ns = _stamp_ns(snapshot.header.stamp)

    def rel_s(ns: int) -> float:
        return (ns - t0_ns) * 1e-9

    frames.sort(key=lambda item: item[0])
    tags = np.array([rel_s(f[0]) for f in frames])
    steps = np.diff(tags)
    if len(steps) == 0 or np.min(steps) <= 0:
        raise BagDataError(f'{path}: PMU frame time tags must be distinct and at least two')
    rate = float(np.round(1.0 / np.min(steps)))
    index = np.round(tags * rate).astype(int)
    if np.any(index < 0) or np.max(np.abs(index / rate - tags)) > 0.25 / rate:
        raise BagDataError(f'{path}: PMU time tags are not on a {rate:g} fps grid from the snapshot time')
    n_frames = int(index[-1]) + 1
    first = frames[0][2].measurements
    stations = tuple(str(m.station_id) for m in first)
    column = {s: j for j, s in enumerate(stations)}
    pmu_buses = np.array([int(m.bus) for m in first], dtype=int)
    data = {name: np.full((n_frames, len(stations)), np.nan) for name in _PHASOR_FIELDS}
    stat = np.full((n_frames, len(stations)), STAT_ABSENT, dtype=np.uint16)
    present = np.zeros(n_frames, dtype=bool)
    delivery = np.full(n_frames, np.nan)
    for row, (_, recorded, msg) in zip(index, frames, strict=True):
        present[row] = True
        delivery[row] = rel_s(recorded)
        for m in msg.measurements:
            j = column.get(str(m.station_id))
            if j is None:
                raise BagDataError(f'{path}: PMU {m.station_id!r} appears after the first frame')
            stat[row, j] = int(m.stat)
            if int(m.stat) & _STAT_UNUSABLE_MASK:
                continue
            for name in _PHASOR_FIELDS:
                data[name][row, j] = float(getattr(m, name))

    truth.sort(key=lambda item: item[0])
    if truth:
        names = tuple(str(n) for n in truth[0][1].generator_names)
        gen_buses = np.array([int(b) for b in truth[0][1].generator_buses], dtype=int)
        truth_angles = np.array([np.asarray(m.angle_rad, dtype=float) for _, m in truth])
    else:
        names, gen_buses, truth_angles = (), np.zeros(0, dtype=int), np.zeros((0, 0))
    truth_groups = None
    if groups_msg is not None:
        truth_groups = {str(n): int(g) for n, g in zip(groups_msg.generator_names, groups_msg.group, strict=True)}
    events.sort(key=lambda item: item[0])
    requests.sort()
    return BagData(
        path=path, t0_s=t0_ns * 1e-9, rate_fps=rate,
        tag_s=np.arange(n_frames) / rate, frame_present=present, delivery_s=delivery,
        station_ids=stations, buses=pmu_buses,
        v_mag_pu=data['voltage_magnitude_pu'], v_angle_rad=data['voltage_angle_rad'],
        i_mag_pu=data['current_magnitude_pu'], i_angle_rad=data['current_angle_rad'],
        frequency_hz=data['frequency_hz'], rocof_hz_per_s=data['rocof_hz_per_s'], stat=stat,
        grid=_grid_from_snapshot(snapshot),
        branch_events=tuple(BranchEvent(t_s=rel_s(t), branch_id=str(m.branch_id), from_bus=int(m.from_bus),
                                        to_bus=int(m.to_bus), in_service=bool(m.in_service)) for t, m in events),
        request_t_s=np.array([rel_s(t) for t, _ in requests]), request_ids=tuple(r for _, r in requests),
        truth_t_s=np.array([rel_s(t) for t, _ in truth]), truth_generator_names=names,
        truth_generator_buses=gen_buses, truth_angles_rad=truth_angles, truth_groups=truth_groups)
