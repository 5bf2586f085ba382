"""Scenario -> rosbag2 bag (MCAP) with PMU frames, network data, the islanding request and ground truth.

Bag layout (topics from controlled_islanding.wire.topics; times in the header are simulation time plus
START_TIME_UNIX_S, so the simulation start is 2026-01-01T00:00:00Z):

| topic | message | header.stamp | recorded at |
|---|---|---|---|
| /network/snapshot | NetworkSnapshot, pre-fault power flow | 0 s | 0 s |
| /pmu/frames | PmuFrame per time tag with a PMU's data in it | time tag | delivery time |
| /network/branch_status | BranchStatus per trip (in_service false) and per kept case event | event time | event time |
| /islanding/request | IslandingRequest | request time | request time |
| /truth/rotor_angles | RotorAngles, simulated delta at every time tag | time tag | time tag |
| /truth/coherent_groups | CoherentGroups, method "truth" (sim/truth.py) | last tag <= request | request time |

The truth groups are the final grouping of sim/truth.py (the clusters of the rotor angle deviations at the end of
the run), published at the request because that is what the nodes should find then; `distance` is the final
separation |d_p(T) - d_q(T)| (rad) and `window_s` the end time T.
PMU channels: `PMU_<bus>`, or `PMU_<bus>/<generator>` per machine where several share a bus (sim/pmu.py).
Every topic records the QoS the nodes use (wire/qos.py) as its offered QoS, so `ros2 bag play` offers
it again and the latched readers match.
The bag is written to a temporary directory beside the target and renamed into place only when complete.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controlled_islanding import atomic
from controlled_islanding.core.grid import Grid
from controlled_islanding.sim.andes_sim import Simulation, simulate
from controlled_islanding.sim.pmu import PmuData, measure
from controlled_islanding.sim.scenario import Scenario
from controlled_islanding.sim.truth import final_separation, truth_groups
from controlled_islanding.wire import topics
from controlled_islanding.wire.bagmeta import set_ros_distro
from controlled_islanding.wire.interfaces import msg_type_name, typestore
from controlled_islanding.wire.messages import (
    MONITOR_FIELDS,
    bus_voltage_angles,
    dynamic_data_fields,
    nominal_frequency_hz,
)
from controlled_islanding.wire.qos import bag_qos

log = logging.getLogger(__name__)

START_TIME_UNIX_S = 1_767_225_600
PDC_FRAME_ID = 'pdc'
_SIM_CACHE: dict[tuple[Any, ...], Simulation] = {}


class BagWriteError(RuntimeError):
    """The bag cannot be written (target exists, or the file system refused)."""


@dataclass(frozen=True)
class ScenarioResult:
    """What one scenario produced.

    Attributes:
        bag: The bag directory.
        n_frames: PMU frames recorded.
        groups: Generator name -> true group.
        simulation_wall_s: Wall time of the ANDES run, s (0 when reused from an earlier scenario).

    """

    bag: Path
    n_frames: int
    groups: dict[str, int]
    simulation_wall_s: float


def _ns(t_s: float) -> int:
    return START_TIME_UNIX_S * 1_000_000_000 + int(round(t_s * 1e9))


def _tag_ns(k: int, rate_fps: int) -> int:
    return START_TIME_UNIX_S * 1_000_000_000 + (2 * k * 1_000_000_000 + rate_fps) // (2 * rate_fps)


class _Messages:
    """Builds messages of our types from the typestore."""

    def __init__(self) -> None:
        self.store = typestore()
        self.types = self.store.types

    def new(self, name: str, **fields: Any) -> Any:
        full = name if '/' in name else msg_type_name(name)
        return self.types[full](**fields)

    def header(self, stamp_ns: int, frame_id: str = '') -> Any:
        stamp = self.types['builtin_interfaces/msg/Time'](sec=stamp_ns // 1_000_000_000,
                                                          nanosec=stamp_ns % 1_000_000_000)
        return self.types['std_msgs/msg/Header'](stamp=stamp, frame_id=frame_id)


def _snapshot_msg(m: _Messages, grid: Grid, stamp_ns: int) -> Any:
    gens, loads = grid.generators, grid.loads
    return m.new(
        'NetworkSnapshot', header=m.header(stamp_ns, 'andes_power_flow'), case_name=grid.name,
        base_mva=float(grid.base_mva), nominal_frequency_hz=nominal_frequency_hz(grid),
        bus_numbers=np.array(grid.buses, dtype=np.uint32),
        bus_voltage_angle_rad=np.array(bus_voltage_angles(grid), dtype=np.float64),
        branch_ids=[b.branch_id for b in grid.branches], branch_breaker_ids=[b.breaker for b in grid.branches],
        branch_from_bus=np.array([b.from_bus for b in grid.branches], dtype=np.uint32),
        branch_to_bus=np.array([b.to_bus for b in grid.branches], dtype=np.uint32),
        branch_in_service=np.array([b.in_service for b in grid.branches], dtype=bool),
        branch_p_from_mw=np.asarray(grid.p_from_mw, dtype=np.float64),
        branch_p_to_mw=np.asarray(grid.p_to_mw, dtype=np.float64),
        generator_names=[g.name for g in gens], generator_bus=np.array([g.bus for g in gens], dtype=np.uint32),
        generator_p_mw=np.array([g.p_mw for g in gens], dtype=np.float64),
        generator_p_max_mw=np.array([g.p_max_mw for g in gens], dtype=np.float64),
        generator_xq_pu=np.array([g.xq_pu for g in gens], dtype=np.float64),
        generator_ra_pu=np.array([g.ra_pu for g in gens], dtype=np.float64), **dynamic_data_fields(gens),
        load_bus=np.array([ld.bus for ld in loads], dtype=np.uint32),
        load_p_mw=np.array([ld.p_mw for ld in loads], dtype=np.float64),
        load_q_mvar=np.array([ld.q_mvar for ld in loads], dtype=np.float64))


def _frame_msgs(m: _Messages, pmu: PmuData, rate_fps: int) -> list[tuple[int, Any]]:
    out = []
    for k in np.flatnonzero(pmu.frame_present):
        measurements = [
            m.new('PmuMeasurement', station_id=pmu.station_ids[j], bus=int(pmu.buses[j]),
                  voltage_magnitude_pu=float(pmu.v_mag_pu[k, j]), voltage_angle_rad=float(pmu.v_angle_rad[k, j]),
                  current_magnitude_pu=float(pmu.i_mag_pu[k, j]), current_angle_rad=float(pmu.i_angle_rad[k, j]),
                  frequency_hz=float(pmu.frequency_hz[k, j]), rocof_hz_per_s=float(pmu.rocof_hz_per_s[k, j]),
                  stat=int(pmu.stat[k, j]))
            for j in range(len(pmu.buses))]
        msg = m.new('PmuFrame', header=m.header(_tag_ns(int(k), rate_fps), PDC_FRAME_ID), measurements=measurements)
        out.append((_ns(float(pmu.delivery_s[k])), msg))
    return out


def run_scenario(scenario: Scenario, out: Path, *, force: bool = False, progress: bool = True) -> ScenarioResult:
    """Simulate a scenario and write its bag.

    Args:
        scenario: The scenario.
        out: The bag directory to create.
        force: Replace an existing bag.
        progress: Report progress on stderr.

    Returns:
        A summary.

    Raises:
        BagWriteError: `out` exists and force is False.
        ScenarioError: The scenario names something the case lacks.
        SimulationError: ANDES failed.

    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    out = Path(out)
    if out.exists() and not force:
        raise BagWriteError(f'{out} exists; pass --force to replace it')
    key = scenario.simulation_key()
    wall = 0.0
    if key not in _SIM_CACHE:
        _SIM_CACHE.clear()  # one run held at a time: scenarios sharing a run are listed together
        _SIM_CACHE[key] = simulate(scenario, progress=progress)
        wall = _SIM_CACHE[key].wall_s
    elif progress:
        log.info('%s: reusing the ANDES run of an earlier scenario', scenario.name)
    sim = _SIM_CACHE[key]
    pmu = measure(sim, scenario)
    groups = truth_groups(pmu.tag_s, pmu.truth_delta_rad)
    group_of = dict(zip(sim.generator_names, (int(g) for g in groups), strict=True))

    m = _Messages()
    records: list[tuple[int, int, str, Any]] = []  # (timestamp, order, topic, msg)
    records.append((_ns(0.0), 0, topics.NETWORK_SNAPSHOT, _snapshot_msg(m, sim.grid, _ns(0.0))))
    changes = [(trip.t_s, bid, False) for trip, bid in zip(scenario.trips, sim.trip_branch_ids, strict=True)]
    changes += list(sim.case_branch_changes)
    for t_s, bid, in_service in changes:
        f, t = sim.branch_ends[bid]
        records.append((_ns(t_s), 1, topics.BRANCH_STATUS,
                        m.new('BranchStatus', header=m.header(_ns(t_s), 'andes'), branch_id=bid, from_bus=f,
                              to_bus=t, in_service=in_service)))
    request_id = f'{scenario.name}/request-1'
    records.append((_ns(scenario.request_s), 2, topics.ISLANDING_REQUEST,
                    m.new('IslandingRequest', header=m.header(_ns(scenario.request_s), 'scenario'),
                          request_id=request_id, reason=f'scenario {scenario.name}: islanding requested at '
                                                        f'{scenario.request_s:g} s',
                          branch_changes_before=len({(bid, t_s) for t_s, bid, _ in changes
                                                     if 0.0 < t_s <= scenario.request_s}),
                          generator_names=[], group=np.zeros(0, dtype=np.uint32),
                          predicted_first_slip=m.header(0).stamp, key_id='', signature=np.zeros(0, dtype=np.uint8))))
    for stamp, msg in _frame_msgs(m, pmu, scenario.rate_fps):
        records.append((stamp, 3, topics.PMU_FRAMES, msg))
    names = list(sim.generator_names)
    gen_buses = np.array(sim.generator_buses, dtype=np.uint32)
    for k in range(len(pmu.tag_s)):
        stamp = _tag_ns(k, scenario.rate_fps)
        records.append((stamp, 4, topics.TRUTH_ROTOR_ANGLES,
                        m.new('RotorAngles', header=m.header(stamp, 'andes'), generator_names=names,
                              generator_buses=gen_buses, angle_rad=pmu.truth_delta_rad[k].astype(np.float64),
                              valid=np.ones(len(names), dtype=bool), suspect_reason=[],
                              **{f: np.zeros(0, dtype=np.float64) for f in MONITOR_FIELDS})))
    last_tag = int(np.flatnonzero(pmu.tag_s <= scenario.request_s + 1e-9)[-1])
    sep = final_separation(pmu.tag_s, pmu.truth_delta_rad)
    records.append((_ns(scenario.request_s), 5, topics.TRUTH_COHERENT_GROUPS,
                    m.new('CoherentGroups', header=m.header(_tag_ns(last_tag, scenario.rate_fps), 'andes'),
                          generator_names=names, generator_buses=gen_buses, group=groups.astype(np.uint32),
                          k=int(groups.max()) + 1, method='truth', distance=sep.ravel().astype(np.float64),
                          window_s=float(pmu.tag_s[-1]), unobserved_generator_names=[], request_id='',
                          suspect_generator_names=[], suspect_reasons=[])))
    records.sort(key=lambda r: (r[0], r[1]))

    # rosbags names the .mcap after the bag directory, so the partial bag gets the final name in a scratch dir.
    scratch = out.parent / f'.{out.name}.partial'
    if scratch.exists():
        shutil.rmtree(scratch)
    scratch.mkdir(parents=True)
    tmp = scratch / out.name
    try:
        with Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conns: dict[str, Any] = {}
            for stamp, _, topic, msg in records:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=m.store,
                                                         offered_qos_profiles=[bag_qos(topic)])
                writer.write(conns[topic], stamp, m.store.serialize_cdr(msg, msg.__msgtype__))
        set_ros_distro(tmp)
        if out.exists():
            shutil.rmtree(out)
        atomic.replace(tmp, out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return ScenarioResult(bag=out, n_frames=int(pmu.frame_present.sum()), groups=group_of, simulation_wall_s=wall)


# ANDES' floating point differs in the last bits between CPUs (OpenBLAS and libm pick kernels per processor): the
# committed PJM 5-bus bag, regenerated on an AMD EPYC, differed in 13 of 366 messages by at most 8e-10 relative,
# around its grid collapse. Numbers within this of each other are the same message; anything else must be equal.
_RELATIVE_TOLERANCE = 1e-8


def message_difference(bag: Path, other: Path) -> str | None:
    """Return where two bags' messages first differ, or None if they agree.

    Topics, log times and every non-numeric field must be equal; numbers agree within a relative 1e-8 (of the
    larger magnitude, and at least 1e-8 absolute), the processor-dependent rounding of the simulation.
    """
    from rosbags.highlevel import AnyReader

    def messages(path: Path) -> list[tuple[str, int, bytes, object]]:
        with AnyReader([path], default_typestore=typestore()) as reader:
            return [(conn.topic, t_ns, bytes(raw), reader.deserialize(raw, conn.msgtype))
                    for conn, t_ns, raw in reader.messages()]

    ours, theirs = messages(bag), messages(other)
    for k, (a, b) in enumerate(zip(ours, theirs, strict=False)):
        if a[:2] != b[:2] or (a[2] != b[2] and not _same_fields(a[3], b[3])):
            return f'message {k}: {a[0]} at {a[1]} ns differs from {b[0]} at {b[1]} ns'
    if len(ours) != len(theirs):
        return f'{len(ours)} messages against {len(theirs)}'
    return None


def _same_fields(a: object, b: object) -> bool:
    """Return whether two decoded message values agree: numbers within _RELATIVE_TOLERANCE, the rest exactly."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape or a.dtype.kind != b.dtype.kind:
            return False
        if a.dtype.kind != 'f':
            return bool(np.array_equal(a, b))
        return bool(np.allclose(a, b, rtol=_RELATIVE_TOLERANCE, atol=_RELATIVE_TOLERANCE, equal_nan=True))
    if isinstance(a, float) and isinstance(b, float):
        return bool(np.isclose(a, b, rtol=_RELATIVE_TOLERANCE, atol=_RELATIVE_TOLERANCE, equal_nan=True))
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same_fields(x, y) for x, y in zip(a, b, strict=True))
    if hasattr(a, '__dataclass_fields__') and getattr(a, '__msgtype__', a) == getattr(b, '__msgtype__', b):
        return all(_same_fields(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__)
    return a == b
