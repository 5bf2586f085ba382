"""The committed scenario bags: two readers, manifest, scenario conformance, DTW recovery, regeneration.

Each bag must open with rosbags and with the mcap package, match the manifest and its scenario, have its
true groups recovered by DTW coherency; a sample covering every input format and impairment regenerates with the
same messages from its YAML file (`controlled-islanding simulate --all bags --check` checks every bag).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controlled_islanding.sim.manifest import build_manifest, manifest_entries, scenario_files
from controlled_islanding.sim.scenario import load_scenario
from controlled_islanding.wire import topics
from controlled_islanding.wire.bagdata import BagData, load_bag
from controlled_islanding.wire.interfaces import msg_type_name

BAGS = Path(__file__).resolve().parents[1] / 'bags'
MANIFEST = manifest_entries(BAGS / 'index.yaml')
NAMES = [entry['name'] for entry in MANIFEST]
MAX_BAG_BYTES = 5 * 1024 * 1024


def _entry(name: str) -> dict:
    return next(e for e in MANIFEST if e['name'] == name)


def _raw_messages(bag: Path) -> list[tuple[str, int, bytes]]:
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        return [(conn.topic, timestamp, bytes(raw)) for conn, timestamp, raw in reader.messages()]


def test_every_scenario_has_a_manifest_entry_and_a_bag() -> None:
    assert sorted(p.stem for p in scenario_files(BAGS)) == sorted(NAMES)
    assert any(not e['synchronous'] for e in MANIFEST) and any(e['synchronous'] for e in MANIFEST)


@pytest.mark.parametrize('name', NAMES)
def test_bag_opens_with_rosbags_and_with_the_mcap_package(name: str) -> None:
    from mcap.reader import make_reader

    bag = BAGS / name
    files = list(bag.glob('*.mcap'))
    assert len(files) == 1
    assert sum(f.stat().st_size for f in bag.iterdir()) < MAX_BAG_BYTES
    via_rosbags = _raw_messages(bag)
    with files[0].open('rb') as handle:
        via_mcap = [(channel.topic, message.log_time, bytes(message.data), schema.name)
                    for schema, channel, message in make_reader(handle).iter_messages(log_time_order=True)]
    assert len(via_mcap) == len(via_rosbags)
    assert sorted(m[:3] for m in via_mcap) == sorted(via_rosbags)
    schemas = {m[0]: m[3] for m in via_mcap}
    assert schemas[topics.PMU_FRAMES] == msg_type_name('PmuFrame')
    assert schemas[topics.TRUTH_COHERENT_GROUPS] == msg_type_name('CoherentGroups')


def test_manifest_matches_what_the_bags_hold() -> None:
    assert build_manifest(BAGS)['bags'] == MANIFEST


@pytest.mark.parametrize('name', NAMES)
def test_the_bags_truth_groups_are_the_manifests_final_grouping(name: str) -> None:
    data = load_bag(BAGS / name)
    assert data.truth_groups is not None
    entry = _entry(name)
    assert [[n for n in data.truth_generator_names if data.truth_groups[n] == g] for g in range(entry['truth_k'])] \
        == entry['truth_groups']
    if entry['first_pole_slip_s'] is not None:
        assert 0.0 < entry['first_pole_slip_s'] <= entry['end_s']
    # No bus holds machines of two true groups: one bus cannot be in two islands, so no islanding could follow them.
    groups_at: dict[int, set[int]] = {}
    for g in data.grid.generators:
        groups_at.setdefault(g.bus, set()).add(data.truth_groups[g.name])
    assert {bus: groups for bus, groups in groups_at.items() if len(groups) > 1} == {}


# Scenarios made before the request rule of bags/README.md (90 deg between final groups, outside any fault); every
# scenario added since must ask at that moment, so its request is a design, not a setting that makes a method pass.
REQUEST_BEFORE_THE_RULE = {'ieee14_g1_unstable', 'ieee14_psse_g1_borderline',
                           'ieee39_case2_g3_unstable', 'ieee39_g3_multitrip', 'ieee39_g6g7_delay',
                           'ieee39_g6g7_initial_gap', 'ieee39_g6g7_loss', 'ieee39_g6g7_silent_pmu',
                           'ieee39_g6g7_unstable', 'ieee39_paper_case1', 'ieee39_paper_case1_matpower',
                           'ieee39_paper_case2'}


@pytest.mark.parametrize('name', [n for n in NAMES if n not in REQUEST_BEFORE_THE_RULE])
def test_new_scenarios_ask_when_the_final_groups_are_90_deg_apart(name: str) -> None:
    entry = _entry(name)
    assert entry['separation_visible_s'] is not None, 'a scenario that stays one group needs its own request rule'
    assert entry['request_s'] == pytest.approx(entry['separation_visible_s'], abs=1e-3)
    assert 90.0 < entry['max_angle_between_groups_at_request_deg'] < 180.0


@pytest.mark.parametrize('name', NAMES)
def test_bag_follows_its_scenario(name: str) -> None:
    scenario = load_scenario(BAGS / _entry(name)['scenario'])
    data = load_bag(BAGS / name)
    imp = scenario.impairments
    assert data.rate_fps == scenario.rate_fps
    assert data.tag_s[-1] == pytest.approx(scenario.end_s)
    assert len(data.tag_s) == int(round(scenario.end_s * scenario.rate_fps)) + 1
    assert set(data.buses) == {g.bus for g in data.grid.generators}
    # Trips are the scenario's; any other branch change is a case event the scenario keeps.
    # Stamps are integer ns in the bag: 7.6 s comes back as 7.6000000000000005.
    trips = [e for e in data.branch_events if any(abs(e.t_s - t.t_s) < 1e-9 and not e.in_service
                                                  for t in scenario.trips)]
    assert [e.t_s for e in trips] == pytest.approx([t.t_s for t in scenario.trips], abs=1e-9)
    if scenario.case_events != 'keep':
        assert len(data.branch_events) == len(scenario.trips)
    assert data.request_t_s.tolist() == pytest.approx([scenario.request_s])
    assert data.grid.has_flows and sum(g.p_mw for g in data.grid.generators) > sum(ld.p_mw for ld in data.grid.loads)
    assert np.isfinite([g.xq_pu for g in data.grid.generators]).all()
    # Every machine's dynamic data ride in the snapshot, enough for pmu_ingestion's filter (estimator dse).
    from controlled_islanding.core.dse import MachineData

    assert set(MachineData.of_generators(data.grid.generators).richest_model()) <= {'classical', 'genrou'}
    assert list(data.truth_generator_names) == [g.name for g in data.grid.generators]

    delay = data.delivery_s - data.tag_s
    present = data.frame_present
    if imp.delay_mean_s > 0:
        assert (delay[present] > 0).all()
        arrival_order = np.argsort(data.delivery_s[present], kind='stable')
        assert (np.diff(data.tag_s[present][arrival_order]) < 0).any()
    else:
        assert np.allclose(delay[present], 0.0, atol=1e-9)
    assert not present[data.tag_s < imp.initial_gap_s - 1e-9].any()
    assert present[data.tag_s >= imp.initial_gap_s - 1e-9].all()
    invalid = np.isnan(data.v_mag_pu[present])
    if imp.frame_loss_rate > 0:
        assert invalid.mean() == pytest.approx(imp.frame_loss_rate, abs=0.03)
    if imp.silent_pmu_bus is not None:
        column = list(data.buses).index(imp.silent_pmu_bus)
        silent = data.tag_s >= imp.silent_from_s - 1e-9
        assert np.isnan(data.v_mag_pu[silent, column]).all()
        assert not np.isnan(data.v_mag_pu[~silent & present, column]).any()
    if imp.frame_loss_rate == 0 and imp.silent_pmu_bus is None:
        assert not invalid.any()


def _rotor_angle_series(data: BagData) -> list[np.ndarray]:
    """Return what an online estimator holds at the request: frames delivered by then, tagged up to then."""
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad

    request = float(data.request_t_s[0])
    seen = (data.tag_s <= request + 1e-9) & (data.delivery_s <= request + 1e-9)
    series = []
    for gen in data.grid.generators:
        j = data.pmu_column(gen.name, gen.bus)
        columns = [a[seen, j] for a in (data.v_mag_pu, data.v_angle_rad, data.i_mag_pu, data.i_angle_rad)]
        series.append(estimate_rotor_angle_rad(*columns, xq_pu=gen.xq_pu, ra_pu=gen.ra_pu))
    return series


# Bags whose final groups the k rule misses at the request, with why (docs/coherency_rules.md). Strict: once the
# rule finds them, the test fails until the name is taken out.
MISSED_BY_THE_K_RULE = {
    'pjm5bus_bus3_unstable': 'at the request, 47 ms after the clearing, the bus-3 machine is 122 deg from the others '
                             '(PMU estimate) and has moved away for 3 frames only; the rule finds the final groups '
                             'from 1.233 s, 4 frames later and 2 before the first slip (measured frame by frame)',
    'nordic44_bus6000_three_groups': 'the bus 5300 and 6100 machines are 20 to 30 deg from their pre-fault angles at '
                                     'the request, where the same fault cleared 30 ms earlier (one group for 5 s, '
                                     'a slip into other groups at 6.9 s) gives angles within 2 deg; found 0.3 s later',
}


@pytest.mark.parametrize('name', [pytest.param(n, marks=pytest.mark.xfail(
    strict=True, reason=MISSED_BY_THE_K_RULE[n])) if n in MISSED_BY_THE_K_RULE else n for n in NAMES])
def test_dtw_coherency_recovers_the_truth_groups(name: str) -> None:
    from controlled_islanding.core.coherency import DTWCoherency

    data = load_bag(BAGS / name)
    assert data.truth_groups is not None
    estimator = DTWCoherency().fit(_rotor_angle_series(data))
    truth = [data.truth_groups[g.name] for g in data.grid.generators]
    # Both number groups by first generator, so equal partitions give equal label lists.
    assert estimator.labels_.tolist() == truth, (
        f'{name}: DTW groups {estimator.labels_.tolist()} (k = {estimator.n_groups_}) != truth {truth}')


def regeneration_sample() -> list:
    """Return the scenarios the suite regenerates: every input format and every impairment kind once, cheapest first.

    Regenerating every bag takes about 13 minutes on this machine kind (EI 33 alone about 3), too long for the
    suite; `controlled-islanding simulate --all bags --check` does it. Cost is taken as buses x simulated seconds.
    """
    chosen: dict[tuple, object] = {}
    for path in scenario_files(BAGS):
        scenario = load_scenario(path)
        entry = _entry(scenario.name)
        cost = len(load_bag(BAGS / scenario.name).grid.buses) * scenario.end_s
        for key in [('format', scenario.case.suffix), *(('impairment', k) for k in entry['impairments'])]:
            if key not in chosen or cost < chosen[key][0]:
                chosen[key] = (cost, scenario)
    unique = {s.name: s for _cost, s in chosen.values()}
    # Scenarios sharing one ANDES run are simulated once when they follow each other.
    return sorted(unique.values(), key=lambda s: (repr(s.simulation_key()), s.name))


@pytest.mark.slow
def test_a_sample_of_bags_regenerates_with_the_same_messages(tmp_path: Path) -> None:
    from controlled_islanding.sim.bag import message_difference, run_scenario

    sample = regeneration_sample()
    assert len(sample) >= 2
    for scenario in sample:
        out = run_scenario(scenario, tmp_path / scenario.name, progress=False).bag
        assert message_difference(out, BAGS / scenario.name) is None, scenario.name


@pytest.mark.parametrize('case,richest', [('ieee14/ieee14_full.xlsx', 'genrou'), ('5bus/pjm5bus.xlsx', 'classical')])
def test_the_snapshot_carries_each_machines_dynamic_data_from_andes_through_the_bag_format(case, richest) -> None:
    from controlled_islanding.core.dse import MachineData
    from controlled_islanding.sim.andes_sim import power_flow_grid
    from controlled_islanding.sim.bag import _Messages, _snapshot_msg
    from controlled_islanding.wire.bagdata import _grid_from_snapshot
    from controlled_islanding.wire.interfaces import typestore
    from controlled_islanding.wire.messages import grid_from_snapshot

    grid = power_flow_grid(case)
    sent = MachineData.of_generators(grid.generators)
    assert sent.richest_model().tolist() == [richest] * len(grid.generators)
    store, name = typestore(), msg_type_name('NetworkSnapshot')
    msg = store.deserialize_cdr(store.serialize_cdr(_snapshot_msg(_Messages(), grid, 10**9), name), name)
    for decoded in (grid_from_snapshot(msg), _grid_from_snapshot(msg)):
        got = MachineData.of_generators(decoded.generators)
        assert got.model == sent.model
        for column in ('m_s', 'd_pu', 'xd1_pu', 'xd2_pu', 'td20_s', 's10', 's12', 'xq_pu'):
            assert np.array_equal(getattr(got, column), getattr(sent, column), equal_nan=True), column


def test_message_comparison_forgives_rounding_only() -> None:
    """Regenerated bags may differ in the last bits across processors (sim.bag._RELATIVE_TOLERANCE), nothing more."""
    import copy

    from rosbags.highlevel import AnyReader

    from controlled_islanding.sim.bag import _same_fields
    from controlled_islanding.wire.interfaces import typestore

    with AnyReader([BAGS / 'pjm5bus_bus3_unstable'], default_typestore=typestore()) as reader:
        frame = next(reader.deserialize(raw, c.msgtype) for c, _t, raw in reader.messages()
                     if c.topic == '/pmu/frames')
    for scale, same in ((1 + 1e-12, True), (1 + 1e-6, False)):
        other = copy.deepcopy(frame)
        other.measurements[0].current_angle_rad = frame.measurements[0].current_angle_rad * scale + 1e-12
        assert _same_fields(frame, other) is same
    other = copy.deepcopy(frame)
    other.measurements[0].station_id += 'x'
    assert not _same_fields(frame, other)
