"""Rotor angles by the Kalman filter as the graph runs it: frames as delivered, machine data from the snapshot.

On the committed delay bag (IEEE 39, frames delayed 0.1 s with 0.03 s jitter, so they overtake each other):
core.dse.StreamingDSE fed in delivery order beats the steady-state estimate against /truth/rotor_angles after
the fault, and the real pmu_ingestion node with estimator=dse publishes what the core gives, falling back to the
steady-state estimate for a generator whose dynamic data the snapshot leaves out. Short: 2.5 s of one bag.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from controlled_islanding.core.dse import MachineData, StreamingDSE
from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad
from controlled_islanding.wire.bagdata import load_bag

BAG = Path(__file__).resolve().parents[1] / 'bags' / 'ieee39_g6g7_delay'


@pytest.fixture(scope='module')
def bag():
    return load_bag(BAG)


def around_fault(bag, before_s: float, after_s: float) -> tuple[float, slice]:
    """(fault start s, frame rows from before_s ahead of it to after_s past it)."""
    from controlled_islanding.sim.scenario import load_scenario

    start = load_scenario(BAG.with_suffix('.yaml')).faults[0].start_s
    rows = np.flatnonzero((bag.tag_s >= start - before_s) & (bag.tag_s < start + after_s))
    return start, slice(int(rows[0]), int(rows[-1]) + 1)


def phasors(bag, generators):
    cols = [bag.pmu_column(g.name, g.bus) for g in generators]
    return [x[:, cols] for x in (bag.v_mag_pu, bag.v_angle_rad, bag.i_mag_pu, bag.i_angle_rad)]


def delivered(bag, frames=slice(None)):
    """Present frame rows in the order the PDC delivered them."""
    rows = np.flatnonzero(bag.frame_present)
    rows = rows[(rows >= (frames.start or 0)) & (rows < (frames.stop or len(bag.tag_s)))]
    return rows[np.argsort(bag.delivery_s[rows], kind='stable')]


def truth_at_frames(bag) -> np.ndarray:
    rows = np.searchsorted(bag.truth_t_s, bag.tag_s - 1e-6)
    assert np.allclose(bag.truth_t_s[rows], bag.tag_s, atol=1e-6)
    return bag.truth_angles_rad[rows]


def error_deg(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.degrees(np.abs(np.angle(np.exp(1j * (estimate - truth)))))


def stream(bag, generators, reorder_s: float, frames=slice(None)) -> tuple[StreamingDSE, np.ndarray]:
    v, va, i, ia = phasors(bag, generators)
    dse = StreamingDSE(MachineData.of_generators(generators), bag.rate_fps, reorder_s, history_s=1.0)
    out = np.full(v.shape, np.nan)
    for k in delivered(bag, frames):
        out[k] = dse.offer(bag.t0_s + bag.tag_s[k], v[k], va[k], i[k], ia[k], np.isfinite(v[k]))
    return dse, out


def test_the_filter_fed_as_delivered_beats_the_steady_state_estimate_after_the_fault(bag):
    gens = bag.grid.generators
    assert set(MachineData.of_generators(gens).richest_model()) == {'genrou'}, 'the snapshot carries GENROU data'
    fault_s, frames = around_fault(bag, 0.5, 2.0)  # the fault, its clearing by a trip and the swing after
    dse, est = stream(bag, gens, reorder_s=0.1, frames=frames)
    v, va, i, ia = phasors(bag, gens)
    steady = estimate_rotor_angle_rad(v, va, i, ia, np.array([g.xq_pu for g in gens]),
                                      np.array([g.ra_pu for g in gens]))
    truth = truth_at_frames(bag)
    after = bag.frame_present & (bag.tag_s >= fault_s)
    after[frames.stop:] = False
    dse_p99 = np.nanpercentile(error_deg(est, truth)[after], 99)
    steady_p99 = np.nanpercentile(error_deg(steady, truth)[after], 99)
    assert dse_p99 < 2.0 and dse_p99 < steady_p99 / 4, (dse_p99, steady_p99)
    # Frames overtake each other all the time here; waiting 0.1 s, the filter itself loses almost none.
    assert dse.ahead_frames > 30 and dse.lost_frames <= 1


def test_without_waiting_late_frames_are_interpolated_and_lost_to_the_filter(bag):
    dse, est = stream(bag, bag.grid.generators, reorder_s=0.0, frames=slice(0, 120))
    assert dse.late_frames > 10 and dse.lost_frames >= dse.late_frames and dse.ahead_frames == 0
    assert np.isfinite(est[bag.frame_present[:120].nonzero()[0][5:]]).all()


@pytest.mark.ros
def test_pmu_ingestion_with_dse_publishes_the_filter_and_falls_back_where_data_are_missing(bag, rclpy_context):
    import rclpy
    from controlled_islanding_msgs.msg import RotorAngles
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from controlled_islanding.nodes.grid_sim import frame_msg, snapshot_msg
    from controlled_islanding.nodes.pmu_ingestion import PmuIngestionNode
    from controlled_islanding.ros.endpoints import qos_for
    from controlled_islanding.sim.pmu import Frame
    from controlled_islanding.wire import topics

    bare = bag.grid.generators[3].name
    gens = tuple(dataclasses.replace(g, m_s=float('nan')) if g.name == bare else g for g in bag.grid.generators)
    grid = dataclasses.replace(bag.grid, generators=gens)
    node = PmuIngestionNode(context=rclpy_context, parameter_overrides=[Parameter('estimator', value='dse')])
    listener = rclpy.create_node('listener', context=rclpy_context)
    got: dict[int, RotorAngles] = {}
    listener.create_subscription(RotorAngles, topics.relative(topics.ROTOR_ANGLES),
                                 lambda m: got.setdefault(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, m),
                                 qos_for(topics.ROTOR_ANGLES))
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    executor.add_node(listener)
    try:
        node.on_snapshot(snapshot_msg(grid))
        assert node.diag.values['dse_fallback'] == bare
        _, frames = around_fault(bag, 0.25, 0.75)  # the fault and its clearing
        for k in delivered(bag, frames):
            node.on_frame(frame_msg(Frame(
                tag_s=float(bag.tag_s[k]), delivery_s=float(bag.delivery_s[k]),
                station_ids=bag.station_ids, buses=bag.buses, v_mag_pu=bag.v_mag_pu[k],
                v_angle_rad=bag.v_angle_rad[k], i_mag_pu=bag.i_mag_pu[k], i_angle_rad=bag.i_angle_rad[k],
                frequency_hz=bag.frequency_hz[k], rocof_hz_per_s=bag.rocof_hz_per_s[k], stat=bag.stat[k])))
        expected = int(bag.frame_present[frames].sum())
        end = time.monotonic() + 20.0
        while len(got) < expected and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
        node.destroy_node()
        listener.destroy_node()
    _, core = stream(bag, gens, reorder_s=0.1, frames=frames)
    v, va, i, ia = phasors(bag, gens)
    steady = estimate_rotor_angle_rad(v, va, i, ia, np.array([g.xq_pu for g in gens]),
                                      np.array([g.ra_pu for g in gens]))
    column = [g.name for g in gens].index(bare)
    assert len(got) == expected, 'every frame answered on arrival'
    for stamp_ns, msg in got.items():
        k = int(round((stamp_ns * 1e-9 - bag.t0_s) * bag.rate_fps))
        angles = np.array(msg.angle_rad)
        assert list(msg.generator_names) == [g.name for g in gens]
        # Frames that came before the first one the filter took have no estimate: valid false.
        known = np.isfinite(core[k])
        assert np.allclose(angles[known], core[k][known], atol=1e-9) and not np.array(msg.valid)[~known].any(), k
        if known[column]:
            assert np.angle(np.exp(1j * (angles[column] - steady[k, column]))) == pytest.approx(0.0, abs=1e-9)
    assert sum(np.isfinite(core[k]).all() for k in range(frames.start, frames.stop)) > expected - 6


def test_coherency_finds_the_groups_on_the_filter_angles_exactly_when_on_andes_own(bag):
    # Why DSE angles find the G6/G7 split 0.15 s after steady-state ones (docs/benchmarks.md): not filter lag, the
    # windows that find it are those that find it on ANDES' own rotor angles; the steady-state estimate finds it
    # earlier through its own error during the fault.
    from controlled_islanding.evaluation import coherency_rules as study
    from controlled_islanding.evaluation.cases import coherency_node_parameters as _coherency_node_parameters

    params = _coherency_node_parameters()
    settings = {'rule': str(params['k_rule']), 'window_s': float(params['window_s']),
                'max_groups': int(params['max_groups']), 'dtw_band': int(params['dtw_band_samples'])}
    entry = study.manifest_entries(BAG.parent / 'index.yaml')[BAG.name]
    steady = study.scenario_from_bag(bag, entry)
    _, est = stream(bag, bag.grid.generators, reorder_s=0.1)
    rows = (bag.tag_s >= steady.t_s[0] - 1e-9) & (bag.tag_s <= steady.t_s[-1] + 1e-9)
    col = {n: j for j, n in enumerate(bag.truth_generator_names)}
    andes = np.array([np.interp(steady.t_s, bag.truth_t_s, bag.truth_angles_rad[:, col[n]])
                      for n in steady.generator_names])
    seen = np.isfinite(est[rows].T)
    filtered = dataclasses.replace(steady, angles_rad=est[rows].T)
    exact = dataclasses.replace(steady, angles_rad=np.where(seen, andes, np.nan))
    truth = study.blocks(steady.truth)
    found = {}
    for name, scenario in (('dse', filtered), ('andes', exact)):
        found[name] = [study.blocks(study.groups_at(scenario, end, **settings)) == truth
                       for end in np.arange(5.4, 5.91, 0.05)]
    assert found['dse'] == found['andes']
    assert any(found['dse']) and not all(found['dse'])  # the sweep spans the moment the groups are first found


def test_a_stream_at_a_divisor_of_rate_fps_has_no_missing_tags_until_it_shows_the_finer_grid(bag):
    # pmu_ingestion's rate_fps (60) is the finest grid; a 30 frames/s stream on it used to have every odd tag
    # "missing": stepped as lost, its answers from copies of the filter (the closed-loop testbed's 30 fps runs).
    gens = bag.grid.generators
    v, va, i, ia = phasors(bag, gens)
    keys = np.flatnonzero(bag.frame_present[:150])
    assert np.array_equal(keys, np.arange(150)), 'the first 2.5 s of the bag are complete'
    even = keys[keys % 2 == 0][:40]  # 1.33 s at 30 frames/s
    later = keys[(keys > even[-1]) & (keys != 101)]  # then every tag at 60 frames/s, but one lost
    on_60 = StreamingDSE(MachineData.of_generators(gens), 60.0, 0.1)
    on_30 = StreamingDSE(MachineData.of_generators(gens), 30.0, 0.1)
    for k in even:
        t = bag.t0_s + bag.tag_s[k]
        a60 = on_60.offer(t, v[k], va[k], i[k], ia[k], np.isfinite(v[k]))
        a30 = on_30.offer(t, v[k], va[k], i[k], ia[k], np.isfinite(v[k]))
        assert np.array_equal(a60, a30, equal_nan=True), k
    assert on_60.lost_frames == 0 and on_60.ahead_frames == 0
    for k in later:  # in tag order: the tag after the lost one is ahead of it until reorder_s has passed
        on_60.offer(bag.t0_s + bag.tag_s[k], v[k], va[k], i[k], ia[k], np.isfinite(v[k]))
    assert on_60.lost_frames == 1 and on_60.ahead_frames == 6


@pytest.mark.ros
def test_pmu_ingestion_counts_missing_frames_on_the_streams_own_tag_grid(rclpy_context):
    # Kundur's PMUs report 30 frames/s; under the default rate_fps of 60 every odd tag used to count as missing.
    from rclpy.parameter import Parameter

    from controlled_islanding.nodes.grid_sim import frame_msg, snapshot_msg
    from controlled_islanding.nodes.pmu_ingestion import PmuIngestionNode
    from controlled_islanding.sim.pmu import Frame

    kundur = load_bag(BAG.parent / 'kundur_bus9_unstable')
    assert kundur.rate_fps == 30
    node = PmuIngestionNode(context=rclpy_context, parameter_overrides=[Parameter('estimator', value='steady_state')])
    try:
        assert node.rate_fps == 60
        node.on_snapshot(snapshot_msg(kundur.grid))
        rows = np.flatnonzero(kundur.frame_present)[:40]
        for k in np.delete(rows, 20):
            node.on_frame(frame_msg(Frame(
                tag_s=float(kundur.tag_s[k]), delivery_s=float(kundur.tag_s[k]),
                station_ids=kundur.station_ids, buses=kundur.buses, v_mag_pu=kundur.v_mag_pu[k],
                v_angle_rad=kundur.v_angle_rad[k], i_mag_pu=kundur.i_mag_pu[k], i_angle_rad=kundur.i_angle_rad[k],
                frequency_hz=kundur.frequency_hz[k], rocof_hz_per_s=kundur.rocof_hz_per_s[k], stat=kundur.stat[k])))
            if k == rows[19]:
                assert node.diag.values['missing_frames'] == '0'
        assert node.diag.values['missing_frames'] == '1'  # the one left out, not 40 more
    finally:
        node.destroy_node()


def test_every_answer_carries_the_speeds_and_torques_it_was_found_with(bag):
    # A stability monitor reads them beside the angles (core/stability.py): the filter's own at an in-order
    # frame, a copy's ahead of a missing tag, interpolated for a late frame.
    gens = bag.grid.generators
    v, va, i, ia = phasors(bag, gens)
    _, frames = around_fault(bag, 0.5, 0.5)
    rows = list(range(len(bag.tag_s)))[frames]
    dse = StreamingDSE(MachineData.of_generators(gens), bag.rate_fps, reorder_s=0.1, history_s=1.0)

    def offer(k):
        return dse.offer(bag.t0_s + bag.tag_s[k], v[k], va[k], i[k], ia[k], np.isfinite(v[k]))

    for k in rows[:20]:
        offer(k)
        assert np.array_equal(dse.omega_pu_, dse.dse.omega_pu_) and np.array_equal(dse.tm_pu_, dse.dse.tm_pu_)
    speeds = {}
    for k in rows[20:24]:
        offer(k)
        speeds[k] = (dse.omega_pu_.copy(), dse.tm_pu_.copy())
    offer(rows[25])  # ahead of the missing rows[24]: a copy of the filter answers, the filter itself waits
    assert dse.ahead_frames == 1 and np.isfinite(dse.omega_pu_).all()
    assert not np.array_equal(dse.omega_pu_, dse.dse.omega_pu_)
    offer(rows[22])  # again, late: the filter's answer at that tag, from its history
    assert dse.late_frames == 1
    assert np.allclose(dse.omega_pu_, speeds[rows[22]][0]) and np.allclose(dse.tm_pu_, speeds[rows[22]][1])
