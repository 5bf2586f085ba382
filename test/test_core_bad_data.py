"""core/bad_data on manifest bags of four ANDES systems, alone and through the filter as the graph runs it.

Clean and noisy bags flag nothing; each attack of sim/attacks is flagged before the request, by the test that can
see it; the blind spot (a ramp through a bolted fault on the station's own bus) is an xfail naming it.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from controlled_islanding.core.bad_data import BadDataDetector
from controlled_islanding.sim.attacks import AttackError, attack, with_tve_noise
from controlled_islanding.wire.bagdata import load_bag

BAGS = Path(__file__).resolve().parents[1] / 'bags'
# (bag, fault start s, a station of each true group)
CASES = {'ieee39_g6g7_unstable': (5.0, ('PMU_30', 'PMU_36')), 'ieee14_g1_unstable': (1.0, ('PMU_1', 'PMU_3')),
         'kundur_bus9_unstable': (None, None)}
_LOADED: dict = {}


def _bag(name: str):
    if name not in _LOADED:
        _LOADED[name] = load_bag(BAGS / name)
    return _LOADED[name]


def first_flags(channels, detector: BadDataDetector | None = None) -> dict[str, tuple[str, float]]:
    """Station -> (reason, first time tag flagged, s), frame by frame over the whole bag."""
    det = detector or BadDataDetector()
    first: dict[str, tuple[str, float]] = {}
    buses = np.asarray(channels.buses)
    at_rest = channels.grid.bus_angles_at(buses) if hasattr(channels, 'grid') else None
    for k in range(len(channels.tag_s)):
        idx = np.flatnonzero(np.isfinite(channels.v_mag_pu[k]) & np.isfinite(channels.i_mag_pu[k]))
        if not idx.size:
            continue
        suspects = det.judge(channels.tag_s[k], [channels.station_ids[j] for j in idx], *(
            a[k, idx] for a in (channels.v_mag_pu, channels.v_angle_rad, channels.i_mag_pu, channels.i_angle_rad,
                                channels.frequency_hz, channels.rocof_hz_per_s)), buses=buses[idx],
            bus_angle_rad=None if at_rest is None else at_rest[idx])
        for sid, why in suspects.items():
            first.setdefault(sid, (why, float(channels.tag_s[k])))
    return first


@pytest.mark.parametrize('name', sorted(CASES))
@pytest.mark.parametrize('noise_tve', [0.0, 0.01])
def test_clean_bags_flag_no_station_with_and_without_noise(name, noise_tve):
    bag = _bag(name)
    channels = with_tve_noise(bag, noise_tve, seed=3) if noise_tve else bag
    assert first_flags(channels) == {}


@pytest.mark.parametrize('name', ['ieee39_g6g7_unstable', 'ieee14_g1_unstable'])
@pytest.mark.parametrize('kind,expected', [('ramp', 'frequency_mismatch'), ('replay', 'replayed'),
                                           ('frozen', 'frozen'), ('step', 'frequency_mismatch'),
                                           ('ramp_back', 'frequency_mismatch')])
def test_each_attack_is_flagged_before_the_request_naming_the_station(name, kind, expected):
    bag = _bag(name)
    start_s, stations = CASES[name]
    request_s = float(bag.request_t_s[0])
    station = stations[0]
    flags = first_flags(attack(bag, kind, [station], start_s))
    assert set(flags) == {station}
    why, at_s = flags[station]
    assert why == expected and start_s - 1e-9 <= at_s < request_s


@pytest.mark.parametrize('name', ['ieee39_g6g7_unstable', 'ieee14_g1_unstable'])
def test_the_two_station_ramp_flags_both(name):
    bag = _bag(name)
    start_s, stations = CASES[name]
    flags = first_flags(attack(bag, 'ramp2', list(stations), start_s))
    assert set(flags) == set(stations)
    assert all(at < float(bag.request_t_s[0]) for _, at in flags.values())


@pytest.mark.parametrize('kind', ['ramp', 'ramp_back'])
def test_a_ramp_on_the_faulted_bus_station_is_flagged_in_the_few_frames_between_its_clearing_and_the_request(kind):
    """A spoofed speed on the few frames a cleared fault leaves before the request is flagged.

    EI 33: bus 101048's voltage is below the floor from 1.033 to 1.133 s and the request comes at 1.3 s, 5 frames
    after it recovers: a full window (15 frames) never forms before the request; the frames at hand do.
    """
    bag = _bag('ei33_bus101048_pair_unstable')
    request_s = float(bag.request_t_s[0])
    flags = first_flags(attack(bag, kind, ['PMU_101048'], 1.0))
    assert set(flags) == {'PMU_101048'}
    why, at_s = flags['PMU_101048']
    assert why == 'frequency_mismatch' and 1.15 < at_s <= request_s + 1e-9


def test_a_suspect_station_returns_only_after_clean_s_of_clean_data():
    bag = _bag('ieee14_g1_unstable')
    # A step on both angles, before the fault, leaves the frequency window after window_s: from then on the data
    # are clean again.
    det = BadDataDetector(clean_s=1.0)
    channels = attack(bag, 'step', ['PMU_1'], 0.4)
    back_s = math.nan
    flagged_s = math.nan
    for k in range(len(channels.tag_s)):
        idx = np.flatnonzero(np.isfinite(channels.v_mag_pu[k]))
        suspects = det.judge(channels.tag_s[k], [channels.station_ids[j] for j in idx], *(
            a[k, idx] for a in (channels.v_mag_pu, channels.v_angle_rad, channels.i_mag_pu, channels.i_angle_rad,
                                channels.frequency_hz, channels.rocof_hz_per_s)))
        if 'PMU_1' in suspects and math.isnan(flagged_s):
            flagged_s = float(channels.tag_s[k])
        if math.isfinite(flagged_s) and 'PMU_1' not in suspects and math.isnan(back_s):
            back_s = float(channels.tag_s[k])
    assert math.isfinite(flagged_s) and math.isfinite(back_s)
    assert back_s - 0.4 >= det.window_s + det.clean_s - 2 / bag.rate_fps


def _judge_bus(v_pu, angle_rad, buses=None) -> dict[str, str]:
    """One frame of stations S0.., all on bus 7 unless told, each voltage given: only the bus test can flag."""
    n = len(v_pu)
    return BadDataDetector().judge(0.0, [f'S{j}' for j in range(n)], v_pu, angle_rad, [0.5] * n, [0.0] * n,
                                   [60.0] * n, [0.0] * n, buses=[7] * n if buses is None else buses)


def test_the_bus_test_names_the_one_station_of_a_bus_that_disagrees_with_the_others():
    assert _judge_bus([1.0, 1.0, 1.0], [0.1, 0.1, 0.1]) == {}
    # Three stations each 1 % (the TVE bound) off the bus voltage in different directions: honest, never flagged.
    honest = 1.0 * np.exp(1j * 0.1) * (1 + 0.01 * np.exp(1j * np.array([0.0, 2.1, 4.2])))
    assert _judge_bus(np.abs(honest), np.angle(honest)) == {}
    # A GPS time shift of 1.5 deg on one of three: the two others agree, only it is named.
    assert _judge_bus([1.0, 1.0, 1.0], [0.1, 0.1, 0.1 + math.radians(1.5)]) == {'S2': 'bus_disagreement'}


def test_the_bus_test_flags_both_of_two_that_disagree_and_nothing_below_the_measuring_range():
    assert _judge_bus([0.09, 0.09], [0.1, 0.5]) == {}  # below 10 % of rated: the standard bounds nothing
    assert _judge_bus([0.5, 0.5], [0.1, 0.5]) == {'S0': 'bus_disagreement', 'S1': 'bus_disagreement'}
    assert _judge_bus([0.5, 0.5], [0.1, 0.5], buses=[1, 2]) == {}
    assert _judge_bus([0.5, 0.5], [0.1, 0.5], buses=[-1, -1]) == {}  # buses not known


@pytest.mark.parametrize('name', ['nordic44_bus6000_three_groups', 'gbnetwork_bus73_unstable'])
def test_clean_bags_with_several_machines_on_a_bus_flag_no_station_with_and_without_noise(name):
    bag = _bag(name)
    assert any(n > 1 for n in np.unique(np.asarray(bag.buses), return_counts=True)[1])
    assert first_flags(bag) == {}
    assert first_flags(with_tve_noise(bag, 0.01, seed=3)) == {}


def test_a_ramp_through_a_fault_on_a_bus_of_four_machines_is_flagged_once_its_voltage_is_back_in_range():
    """Nordic 44's bus 6000: nothing of the station's own tells the ramp in the fault; its three neighbours do."""
    bag = _bag('nordic44_bus6000_three_groups')
    flags = first_flags(attack(bag, 'ramp', ['PMU_6000/GENROU_34'], 1.0))
    assert flags == {'PMU_6000/GENROU_34': ('bus_disagreement', pytest.approx(1.0 + 10 / 30, abs=1e-6))}


def test_a_time_shift_present_from_the_first_frame_is_flagged_at_once_where_the_bus_has_other_stations():
    """GB bus 425 (four machines): a GPS offset that predates the stream shows in no station's own past.

    With the snapshot's angles the angle test names it at rest; without them (a snapshot that carries none) the
    other stations of its bus do, on every frame.
    """
    bag = _bag('gbnetwork_bus73_unstable')
    station = next(s for s, b in zip(bag.station_ids, bag.buses, strict=True) if b == 425)
    attacked = attack(bag, 'step', [station], 0.0)
    assert first_flags(attacked) == {station: ('angle_mismatch', pytest.approx(0.0))}
    blind = dataclasses.replace(attacked, grid=dataclasses.replace(bag.grid, bus_angle_rad=None))
    assert first_flags(blind) == {station: ('bus_disagreement', pytest.approx(0.0))}


def _judge_angles(angle_rad, snapshot_rad, v_pu=None) -> dict[str, str]:
    """One frame at rest of stations S0.. on buses 0.., against the snapshot's angles: only the angle test can flag."""
    n = len(angle_rad)
    return BadDataDetector().judge(0.0, [f'S{j}' for j in range(n)], v_pu or [1.0] * n, angle_rad, [0.5] * n,
                                   [0.0] * n, [60.0] * n, [0.0] * n, bus_angle_rad=snapshot_rad)


def test_the_angle_test_at_rest_names_a_station_offset_from_the_snapshot_against_the_others():
    snapshot = [0.0, -0.2, 0.3, 0.1]
    # The PMUs' reference is not the snapshot's: one angle for all is no offset.
    assert _judge_angles([a + 2.0 for a in snapshot], snapshot) == {}
    shifted = [a + 2.0 for a in snapshot]
    shifted[2] += math.radians(20.0)  # a GPS time shift of 0.9 ms at 60 Hz
    assert _judge_angles(shifted, snapshot) == {'S2': 'angle_mismatch'}
    # Within the deployment's tolerance (0.1 rad), and unknown or out-of-range buses, nothing.
    shifted[2] = snapshot[2] + 2.0 + 0.09
    assert _judge_angles(shifted, snapshot) == {}
    assert _judge_angles([0.0, 0.5], [0.0, math.nan]) == {}
    assert _judge_angles([0.0, 0.5], [0.0, 0.0], v_pu=[1.0, 0.05]) == {}
    assert _judge_angles([0.0, 0.5], [0.0, 0.0]) == {'S0': 'angle_mismatch', 'S1': 'angle_mismatch'}


def test_the_angle_test_ends_with_the_rest():
    det = BadDataDetector()
    args = (['A', 'B', 'C'], [1.0, 1.0, 1.0])
    assert det.judge(0.0, *args, [0.0, 0.0, 0.0], [0.5] * 3, [0.0] * 3, [60.0] * 3, [0.0] * 3,
                     bus_angle_rad=[0.0, 0.0, 0.0]) == {}
    # A fault moves the voltages: from then on angles stand where the swing takes them.
    assert det.judge(1 / 30, args[0], [0.5, 0.6, 0.7], [0.0, 0.3, 0.6], [2.0] * 3, [0.0] * 3, [60.0] * 3,
                     [0.0] * 3, bus_angle_rad=[0.0, 0.0, 0.0]) == {}


@pytest.mark.parametrize('name,station', [('ieee39_g6g7_initial_gap', 'PMU_39'), ('ieee39_g6g7_initial_gap', 'PMU_35'),
                                          ('kundur_bus9_unstable', 'PMU_2'), ('ieee14_g1_unstable', 'PMU_3')])
def test_a_time_shift_from_a_streams_first_frame_is_flagged_against_the_snapshot(name, station):
    """The step (20 deg) from the first frame: no past of the station's own to tell it from (the initial gap's 5 s)."""
    bag = _bag(name)
    first = float(bag.tag_s[np.flatnonzero(bag.frame_present)[0]])
    flags = first_flags(attack(bag, 'step', [station], first))
    assert flags == {station: ('angle_mismatch', pytest.approx(first))}


def test_a_network_at_rest_is_not_frozen():
    det = BadDataDetector()
    for k in range(30):
        assert det.judge(k / 30, ['A', 'B'], [1.0, 1.0], [0.1, 0.2], [0.5, 0.5], [0.0, 0.1], [60.0, 60.0],
                         [0.0, 0.0]) == {}


@pytest.mark.parametrize('station', ['PMU_39', 'PMU_35'])
def test_a_station_frozen_from_its_first_frame_after_an_initial_gap_sends_values_and_is_flagged(station):
    """No frame before the fault: frozen at the empty frame before it, the attack was a silent station, not frozen.

    The sweep counted it "not flagged before the request" (docs/attacks.md, ieee39_g6g7_initial_gap); held at the
    station's first frame it repeats, and is flagged.
    """
    bag = _bag('ieee39_g6g7_initial_gap')
    frozen = attack(bag, 'frozen', [station], 5.0)
    j = bag.station_ids.index(station)
    sent = frozen.v_mag_pu[bag.tag_s >= 5.0 - 1e-9, j]
    assert np.isfinite(sent).all() and np.all(sent == sent[0])
    flags = first_flags(frozen)
    assert set(flags) == {station} and flags[station][1] < float(bag.request_t_s[0])


def test_an_attack_needs_a_known_station():
    with pytest.raises(AttackError):
        attack(_bag('kundur_bus9_unstable'), 'ramp', ['PMU_999'], 1.0)


@pytest.mark.parametrize('name', ['ieee39_case2_g3_unstable', 'pjm5bus_bus3_unstable'])
@pytest.mark.parametrize('integer', [False, True], ids=['float', 'int16'])
def test_a_clean_bag_over_c37118_flags_no_station(name, integer):
    """A clean bag as a PDC receives it flags nothing.

    Over C37.118 angles are wrapped and magnitudes never negative, so a pole slip's voltage passing through zero
    turns the phasor by pi between two frames (PMU_32 at 6.717 s and PMU_4 at 1.117 s, before angle_floor_pu).
    """
    from controlled_islanding.pmu import c37118
    from controlled_islanding.pmu.pdc_assembly import PdcAssembler
    from controlled_islanding.pmu.stream import load_bag_stream

    served = load_bag_stream(BAGS / name, integer=integer)
    cfg = c37118.decode_config(served.config_bytes)
    pdc = PdcAssembler(served.channel_map, 1.0)
    pdc.configure('pmu', cfg)
    det, flagged = BadDataDetector(), {}
    for _, raw in served.frames:
        t_ns, ms = pdc.measurements('pmu', c37118.decode_data(raw, cfg))
        ms = [m for m in ms if m.stat & c37118.STAT_DATA_ERROR_MASK == 0]
        flagged.update(det.judge(t_ns * 1e-9, [m.station_id for m in ms], *(
            [getattr(m, f) for m in ms] for f in ('voltage_magnitude_pu', 'voltage_angle_rad', 'current_magnitude_pu',
                                                   'current_angle_rad', 'frequency_hz', 'rocof_hz_per_s'))))
    assert flagged == {}


@pytest.mark.parametrize('name', ['ieee39_case2_g3_unstable', 'ieee14_g1_unstable'])
def test_stray_frames_before_a_bag_neither_flag_it_nor_switch_the_frequency_test_off(name):
    """Frames of the bag's own content at random fresh tags (as the fuzz soak sends them) before the bag itself.

    Learnt as the smallest spacing, the period was a wire value: the clean bag after them had seven stations
    flagged, or the frequency test off for good; a ramp on the clean bag is still flagged after them.
    """
    import random

    data = _bag(name)
    fields = ('v_mag_pu', 'v_angle_rad', 'i_mag_pu', 'i_angle_rad', 'frequency_hz', 'rocof_hz_per_s')

    def feed(det, t_s, k):
        idx = np.flatnonzero(np.isfinite(data.v_mag_pu[k]) & np.isfinite(data.i_mag_pu[k]))
        return det.judge(t_s, [data.station_ids[j] for j in idx], *[getattr(data, f)[k, idx] for f in fields])

    def stray_frames(det, seed):
        rng, now_s = random.Random(seed), data.tag_s[0] - 60.0
        for n in range(rng.choice([30, 60, 120])):
            feed(det, now_s - rng.uniform(0.0, 0.5), rng.randrange(len(data.tag_s)))
            now_s += rng.choice([0.0, 0.1, 1.0]) if n % 10 == 0 else 0.0
        return det

    for seed in range(12):
        det, late = stray_frames(BadDataDetector(), seed), {}
        for k in range(len(data.tag_s)):
            # Suspicions raised by the stray frames themselves last until clean_s of clean data.
            late.update({s: r for s, r in feed(det, data.tag_s[k], k).items() if data.tag_s[k] > 1.5})
        assert late == {}, (seed, late)
        ramped = attack(data, 'ramp', [data.station_ids[0]], float(data.tag_s[len(data.tag_s) // 3]))
        assert data.station_ids[0] in first_flags(ramped, stray_frames(BadDataDetector(), seed)), \
            f'seed {seed}: the frequency test is off after the stray frames'


@pytest.mark.parametrize('name,garbage_hz', [('ieee39_case2_g3_unstable', -60.0),
                                             ('nordic44_bus6000_three_groups', 80.0)])
def test_one_garbage_frame_first_names_no_nominal_frequency(name, garbage_hz):
    """The stream's first frame has one station's values garbage (negative magnitude, a frequency no grid has).

    The nominal frequency was learnt per station from its first frame: -60 Hz read as a 50 Hz grid, 80 Hz as a
    60 Hz one, and the honest stream after it was flagged on every frame (the replay after the fuzz refused for
    suspect data). The grid's nominal now comes from the frames' median within C37.118.1's range.
    """
    data = _bag(name)
    fields = (data.v_mag_pu, data.v_angle_rad, data.i_mag_pu, data.i_angle_rad, data.frequency_hz, data.rocof_hz_per_s)

    def poisoned() -> BadDataDetector:
        det = BadDataDetector()
        idx = np.flatnonzero(np.isfinite(data.v_mag_pu[0]) & np.isfinite(data.i_mag_pu[0]))
        v, va, i, ia, f, r = (np.array(a[0, idx], dtype=float) for a in fields)
        v[0], ia[0], f[0] = -abs(v[0]) - 1.0, 1e300, garbage_hz
        det.judge(data.tag_s[0] - 10.0, [data.station_ids[j] for j in idx], v, va, i, ia, f, r)
        return det

    det = poisoned()
    assert first_flags(data, det) == {}
    assert det.f0_hz == data.grid.freq_hz
    station = data.station_ids[0]
    ramped = attack(data, 'ramp', [station], float(data.tag_s[len(data.tag_s) // 3]))
    assert first_flags(ramped, poisoned())[station][0] == 'frequency_mismatch'


# ---------------------------------------------------------------------------------- the filter's innovation test
def _screened(bag, channels, until_s: float = math.inf) -> dict[str, tuple[str, float]]:
    """Station -> (reason, first flag s) over the channels up to until_s, through the graph's screening."""
    from controlled_islanding.evaluation.attack_sweep import screen
    from controlled_islanding.evaluation.cases import coherency_node_parameters
    return screen(bag, channels, params=coherency_node_parameters(), until_s=until_s)[3]


def _screened_flags(name: str, kind: str, station: str, start_s: float):
    """Station -> (reason, first flag s) over the bag up to its request, through the graph's screening."""
    bag = _bag(name)
    channels = attack(bag, kind, [station], start_s) if kind else bag
    return _screened(bag, channels, until_s=float(bag.request_t_s[0]))


@pytest.mark.parametrize('name,kind,station,start_s', [
    # the faulted area's machine: its voltage below the frequency test's floor from the fault on; from the fault's
    # first frame (the frame at its time tag is still at rest, where the angle test against the snapshot sees it)
    ('ieee39_g6g7_unstable', 'step', 'PMU_35', 5.0 + 1 / 60), ('kundur_bus9_unstable', 'step', 'PMU_4', 1.0 + 1 / 30),
    # a CT ratio error from the fault's first frame on (at rest, the dispatch test sees it): x_s I moves the
    # machine's internal voltage
    ('ieee39_g6g7_unstable', 'current', 'PMU_35', 5.0 + 1 / 60),
    ('ieee14_g1_unstable', 'current', 'PMU_1', 1.0 + 1 / 60)])
def test_the_innovation_test_flags_what_the_frequency_test_cannot_see_before_the_request(name, kind, station,
                                                                                          start_s):
    assert station not in first_flags(attack(_bag(name), kind, [station], start_s))  # the frequency test's blind spot
    flags = _screened_flags(name, kind, station, start_s)
    assert set(flags) == {station}
    why, at_s = flags[station]
    assert why == 'innovation' and start_s - 1e-9 <= at_s < float(_bag(name).request_t_s[0])


def test_a_spoofed_speed_inside_a_bolted_fault_at_the_stations_own_terminal_is_flagged_on_its_first_frame():
    """GB bus 73: every frame before the request is inside the fault, the voltage at 0.003 pu (no angle to judge).

    The fault current still carries z = V + j x_s I, and the machine, with no electrical output, accelerates as its
    model says: 2 rad/s more stands out at once. (-2 rad/s does not: the first frame's honest innovation leads by
    about as much, the filter having taken the power's drop as linear over the frame, and the later frames of the
    fault turn the current against the voltage faster than the filter's chord follows, so are not judged.)
    """
    flags = _screened_flags('gbnetwork_bus73_unstable', 'ramp', 'PMU_73', 1.0)
    assert flags == {'PMU_73': ('innovation', pytest.approx(1.0 + 1 / 30, abs=1e-6))}


def _filter_on(bag):
    """Return the bag's generator channel columns and a filter fitted to its machines."""
    from controlled_islanding.core.dse import MachineData, RotorAngleDSE

    gens = bag.grid.generators
    return [bag.pmu_column(g.name, g.bus) for g in gens], RotorAngleDSE().fit(MachineData.of_generators(gens))


def _phasors(channels, k: int, cols) -> list[np.ndarray]:
    """Frame k's V and I magnitudes and angles on the given columns, as RotorAngleDSE.update takes them."""
    return [np.asarray(getattr(channels, f))[k][cols] for f in ('v_mag_pu', 'v_angle_rad', 'i_mag_pu',
                                                                 'i_angle_rad')]


@pytest.mark.parametrize('name', ['pjm5bus_bus3_unstable', 'nordic44_bus6000_three_groups',
                                  'ei33_bus101048_pair_unstable'])
@pytest.mark.parametrize('noise_tve', [0.0, 0.01])
def test_honest_frames_inside_bolted_faults_are_judged_and_pass(name, noise_tve):
    """Frames whose voltage is below the measuring range, where z is not, are judged; honest ones stay in bound."""
    bag = _bag(name)
    channels = with_tve_noise(bag, noise_tve, seed=3, present_tve=0.005) if noise_tve else bag
    cols, dse = _filter_on(bag)
    below = []
    for k in np.flatnonzero(np.asarray(bag.frame_present)):
        frame = _phasors(channels, k, cols)
        dse.update(float(bag.tag_s[k]), *frame)
        below += list(dse.nis_[(frame[0] < 0.1) & np.isfinite(dse.nis_)])
    assert len(below) >= 3
    assert max(below) < BadDataDetector().nis_bound


def test_a_dead_bus_is_not_judged():
    """V and I both near zero (a machine's breaker and its bus both open): z is out of range, no model to hold."""
    bag = _bag('kundur_bus9_unstable')
    cols, dse = _filter_on(bag)
    rows = np.flatnonzero(np.asarray(bag.frame_present) & (np.asarray(bag.tag_s) < 0.9))
    for k in rows:
        dse.update(float(bag.tag_s[k]), *_phasors(bag, k, cols))
    v, v_angle, i, i_angle = (a.copy() for a in _phasors(bag, rows[-1], cols))
    v[0], i[0] = 1e-3, 1e-3
    dse.update(float(bag.tag_s[rows[-1]]) + 1 / 30, v, v_angle, i, i_angle)
    assert math.isnan(dse.nis_[0]) and np.isfinite(dse.nis_[1:]).all()


@pytest.mark.parametrize('name', sorted(CASES))
@pytest.mark.parametrize('noise_tve', [0.0, 0.01])
def test_clean_bags_flag_no_station_with_the_filter_with_and_without_noise(name, noise_tve):
    """The innovation, schedule and new-station tests too, over the whole bag; noise brought up to C37.118.1's 1 %."""
    from controlled_islanding.evaluation.attack_sweep import screen
    from controlled_islanding.evaluation.cases import coherency_node_parameters

    bag = _bag(name)
    channels = with_tve_noise(bag, noise_tve, seed=3, present_tve=0.005) if noise_tve else bag
    assert screen(bag, channels, params=coherency_node_parameters())[3] == {}


@pytest.mark.parametrize('name,station', [('ieee14_g1_unstable', 'PMU_1'), ('kundur_bus9_unstable', 'PMU_2')])
def test_a_ct_ratio_error_present_at_rest_is_flagged_at_the_first_frame_against_the_dispatch(name, station):
    flags = _screened_flags(name, 'current', station, 0.0)
    assert flags == {station: ('schedule_mismatch', float(_bag(name).tag_s[0]))}


def test_the_schedule_test_ends_at_the_first_event():
    """A CT ratio error from the fault's first frame on is not the dispatch test's to see: the grid is not at rest."""
    flags = _screened_flags('kundur_bus9_unstable', 'current', 'PMU_2', 1.0 + 1 / 30)
    assert all(why != 'schedule_mismatch' for why, _ in flags.values())


def test_a_station_joining_a_running_stream_is_suspect_until_clean_s_of_clean_data():
    """The 1 s replay on a station that sent nothing for that second: its own tests cannot see a recording."""
    name = 'ieee39_g6g7_initial_gap'
    flags = _screened_flags(name, 'replay', 'PMU_35', 5.0)
    assert flags == {'PMU_35': ('new_station', 6.0)}
    # An honest station heard for the first time 2 s into the stream, at rest: suspect for clean_s, then used.
    tags, suspect, flags = _joining('ieee39_g6g7_unstable', 'PMU_39', 2.0)
    assert flags == {'PMU_39': ('new_station', pytest.approx(2.0, abs=1e-6))}
    assert suspect[(tags >= 2.0) & (tags < 2.0 + 1.0 - 1e-6)].all()
    assert not suspect[tags >= 2.0 + 1.0 + 1e-6].any()


def test_a_station_joining_during_an_event_is_held_until_the_grid_is_at_rest_again():
    """Only the snapshot can judge its offset: no test of its own past spans its first frame."""
    tags, suspect, flags = _joining('kundur_bus9_unstable', 'PMU_4', 1.2)
    assert flags == {'PMU_4': ('new_station', pytest.approx(1.2, abs=1e-6))}
    assert suspect[tags >= 1.2 - 1e-6].all()


def _joining(name: str, station: str, from_s: float):
    """Screen the bag with `station` silent until from_s; return tags, its machine's suspect flags, the flags."""
    from controlled_islanding.evaluation.attack_sweep import screen
    from controlled_islanding.evaluation.cases import coherency_node_parameters

    bag = _bag(name)
    j = bag.station_ids.index(station)
    silent = (bag.tag_s[:, None] < from_s) & (np.arange(len(bag.station_ids)) == j)
    joined = dataclasses.replace(bag, v_mag_pu=np.where(silent, np.nan, bag.v_mag_pu))
    tags, _, suspect, flags = screen(bag, joined, params=coherency_node_parameters())
    col = [bag.station_ids[bag.pmu_column(g.name, g.bus)] for g in bag.grid.generators].index(station)
    return tags, suspect[:, col], flags


@pytest.mark.xfail(strict=True, raises=AssertionError,
                   reason="open (issue 29): the request comes at the clearing of a bolted fault on the "
                   "station's own bus, whose every frame after the fault is below 0.01 pu: its voltage carries no "
                   "angle, and its current is the only evidence of its machine, which no other station sees while "
                   'its bus is shorted. -2 rad/s over the 0.3 s fault reads as the machine accelerating with 61 % of '
                   'its pre-fault accelerating power (GB bus 73: 77 % over 0.2 s), a turbine whose power fell that '
                   "much within the fault: the snapshot bounds no turbine's rate, and the filter's torque walk takes "
                   "it. Nordic 44's cut grows from 4 branches to 7 (docs/attacks.md, ramp_back); its three neighbours "
                   "on bus 6000 name it (bus_disagreement) only at 1.333 s, the first frame back in range. Refusing "
                   "whenever "
                   "such a station's data decide would refuse clean bags too: GB bus 73's clean decision changes "
                   'when that station is left unobserved')
def test_a_ramp_through_the_fault_on_the_faulted_bus_station_cannot_steer():
    assert _refused_or_as_clean('nordic44_bus6000_three_groups', 'ramp_back', 'PMU_6000/GENROU_34')


def test_gap_step_silences_the_station_for_gap_s_then_shifts_both_angles_by_half_a_cycle():
    from controlled_islanding.sim.attacks import GAP_S

    bag = _bag('ieee39_g6g7_unstable')
    j = bag.station_ids.index('PMU_35')
    attacked = attack(bag, 'gap_step', ['PMU_35'], 5.0)
    tags = np.asarray(bag.tag_s)
    silent, back = (tags >= 5.0) & (tags < 5.0 + GAP_S - 1e-9), tags >= 5.0 + GAP_S - 1e-9
    for f in ('v_mag_pu', 'v_angle_rad', 'i_mag_pu', 'i_angle_rad', 'frequency_hz', 'rocof_hz_per_s'):
        assert np.isnan(getattr(attacked, f)[silent, j]).all(), f
    for f in ('v_angle_rad', 'i_angle_rad'):
        moved = getattr(attacked, f)[back, j] - getattr(bag, f)[back, j]
        assert np.allclose(moved[np.isfinite(moved)], np.pi)
    others = np.arange(len(bag.station_ids)) != j
    assert np.array_equal(attacked.v_angle_rad[:, others], bag.v_angle_rad[:, others], equal_nan=True)
    assert np.array_equal(attacked.v_mag_pu[~silent, j], bag.v_mag_pu[~silent, j], equal_nan=True)


@pytest.mark.parametrize('name', ['ieee39_g6g7_unstable', 'ieee39_g6g7_initial_gap', 'ieee14_g1_unstable'])
def test_a_station_back_from_a_gap_half_a_cycle_off_cannot_steer(name):
    """Its phasors still fit its own machine; held until the snapshot can judge it, it decides nothing.

    On the initial-gap bag the stream itself starts at the event: the station is first heard inside it.
    """
    from controlled_islanding.evaluation.attack_sweep import attack_start_s
    from controlled_islanding.sim.attacks import GAP_S

    station = {'ieee14_g1_unstable': 'PMU_2'}.get(name, 'PMU_39')
    assert _refused_or_as_clean(name, 'gap_step', station)
    start_s = attack_start_s(_bag(name))
    flags = _screened_flags(name, 'gap_step', station, start_s)
    assert flags == {station: ('gap_in_event', pytest.approx(start_s + GAP_S, abs=1e-6))}


@pytest.mark.parametrize('name,start_s', [('ieee39_g6g7_unstable', 5.0), ('kundur_bus9_unstable', 1.0)])
def test_a_station_silent_alone_through_an_event_is_held_and_a_silent_stream_holds_none(name, start_s):
    """Honest data: one station's silence is held (its offset cannot be judged), the whole stream's is no one's."""
    bag = _bag(name)
    station = bag.station_ids[-1]
    j = bag.station_ids.index(station)
    quiet = (bag.tag_s >= start_s) & (bag.tag_s < start_s + 0.6 - 1e-9)
    alone = dataclasses.replace(bag, v_mag_pu=np.where(quiet[:, None] & (np.arange(len(bag.station_ids)) == j),
                                                       np.nan, bag.v_mag_pu))
    assert first_flags(alone) == {station: ('gap_in_event', pytest.approx(start_s + 0.6, abs=1e-6))}
    everyone = dataclasses.replace(bag, v_mag_pu=np.where(quiet[:, None], np.nan, bag.v_mag_pu))
    assert first_flags(everyone) == {}
    # Before the event the grid is at rest: the snapshot judges the returning station at once, nothing is held.
    before = dataclasses.replace(bag, v_mag_pu=np.where(((bag.tag_s >= start_s - 0.7) & (bag.tag_s < start_s - 0.1))[
        :, None] & (np.arange(len(bag.station_ids)) == j), np.nan, bag.v_mag_pu))
    assert first_flags(before) == {}


def _refused_or_as_clean(name: str, kind: str, station: str) -> bool:
    """Whether the pipeline, offline, refuses the attacked bag or decides on it as on the clean one."""
    from controlled_islanding.evaluation.attack_sweep import attack_start_s, run_pipeline
    from controlled_islanding.evaluation.cases import coherency_node_parameters

    bag = _bag(name)
    params = coherency_node_parameters()
    attacked = run_pipeline(bag, attack(bag, kind, [station], attack_start_s(bag)), params=params)
    return attacked.refused or attacked.key() == run_pipeline(bag, bag, params=params).key()


def _settling(det: BadDataDetector, t0: float, t1: float, c_angle: float, swing: float = 0.0,
              c_from_s: float = -math.inf) -> dict[str, str]:
    """Frames of three stations A, B, C at 30 frames/s from t0 to t1 at 0.9 pu after an event; return the suspects.

    C is silent until c_from_s and its angles carry c_angle (a time offset it came back with, past its own tests);
    swing, pu, moves every station's current magnitude along a 0.5 Hz swing.
    """
    out, rng = {}, np.random.default_rng(int(t0 * 1000))
    for t in np.arange(t0, t1, 1 / 30):
        ids = ['A', 'B'] + (['C'] if t >= c_from_s else [])
        n = len(ids)
        noise = 0.01 / 3 * rng.standard_normal((4, n))  # C37.118.1 TVE of 1 % at 3 sigma, as sim/pmu.py draws it
        i_mag = 0.5 * (1 + swing * math.sin(2 * math.pi * 0.5 * t)) * (1 + noise[0])
        angles = np.array([0.0, 0.0, c_angle][:n])
        out = det.judge(float(t), ids, 0.9 * (1 + noise[1]), angles + noise[2], i_mag, angles + noise[3],
                        [60.0] * n, [0.0] * n, [0.45] * n, bus_angle_rad=[0.0] * n)
    return out


def _after_an_event() -> BadDataDetector:
    """Return a detector that saw A, B and C at rest from 0 s to 1 s, at 1.0 pu (the event drops them to 0.9)."""
    det, rng = BadDataDetector(), np.random.default_rng(0)
    for t in np.arange(0.0, 1.0, 1 / 30):
        noise = 1e-3 * rng.standard_normal((4, 3))
        assert det.judge(float(t), ['A', 'B', 'C'], 1 + noise[0], noise[1], 0.45 * (1 + noise[2]), noise[3],
                         [60.0] * 3, [0.0] * 3, [0.45] * 3, bus_angle_rad=[0.0] * 3) == {}
    assert det.at_rest
    return det


def test_the_tests_at_rest_judge_again_once_the_grid_settled_under_a_newer_snapshot():
    """A station back from an outage 20 deg off is seen by the angle test once the grid rests under a new snapshot.

    Before, the tests against the snapshot ended for good at the first event: in a deployment that runs for days,
    after its first switching no station was ever compared with a snapshot again.
    """
    for c_off, at_end in ((math.radians(20.0), {'C': 'gap_in_event'}), (0.0, {})):
        det = _after_an_event()
        # The event at 1 s; C silent from then until 2 s, back 20 deg off: no test of its own past spans the
        # change, so it is held until the grid is at rest again.
        assert _settling(det, 1.0, 7.0, c_off, c_from_s=2.0) == {'C': 'gap_in_event'}
        assert not det.at_rest
        # A snapshot older than the event is no reference for the grid since.
        det.reference(0.0)
        assert _settling(det, 7.0, 8.0, c_off) == {'C': 'gap_in_event'}
        assert not det.at_rest
        # One stamped once the grid settled is: rest_s after the last station's steady start the angle test judges
        # C, which stays suspect 20 deg off and, honest, is used again after clean_s of clean data.
        det.reference(7.5)
        assert _settling(det, 8.0, 8.1, c_off) == {'C': 'gap_in_event'} and det.at_rest
        assert _settling(det, 8.1, 9.5, c_off) == at_end, c_off


def test_a_snapshot_stamped_within_a_swing_does_not_end_the_event():
    det = _after_an_event()
    # A swing of 10 % in every station's current: no station is steady, whatever snapshot comes.
    assert _settling(det, 1.0, 9.0, 0.0, swing=0.1) == {}
    det.reference(8.5)
    assert _settling(det, 9.0, 12.0, 0.0, swing=0.1) == {} and not det.at_rest
    # Stamped during the swing, which then dies out: its dispatch and angles are not the grid's at rest.
    det = _after_an_event()
    assert _settling(det, 1.0, 3.0, 0.0, swing=0.1) == {}
    det.reference(2.5)
    assert _settling(det, 3.0, 10.0, 0.0) == {} and not det.at_rest


def test_one_station_back_from_an_outage_at_another_voltage_does_not_end_the_rest():
    """Back half a cycle off and 3 % lower, at rest: the angle test names it on its return.

    Before, its own voltage step from before the outage counted as an event, which ended the tests against the
    snapshot for every station, and nothing ever flagged it (measured on this bag: no flag to the request).
    """
    from controlled_islanding.sim.attacks import GAP_S

    bag = _bag('ieee39_g6g7_unstable')
    j = bag.station_ids.index('PMU_39')
    shifted = attack(bag, 'gap_step', ['PMU_39'], 2.0)
    back = np.asarray(bag.tag_s) >= 2.0 + GAP_S - 1e-9
    v = shifted.v_mag_pu.copy()
    v[back, j] *= 0.97
    flags = first_flags(dataclasses.replace(shifted, v_mag_pu=v))
    assert flags == {'PMU_39': ('angle_mismatch', pytest.approx(2.0 + GAP_S, abs=1e-6))}


def _without(bag, rows: np.ndarray, cols: np.ndarray | None = None):
    """Return the bag with the data of `rows` (bool per frame) lost, at every station or at those of `cols`."""
    at = rows[:, None] & (np.ones(len(bag.station_ids), dtype=bool) if cols is None
                          else np.isin(np.arange(len(bag.station_ids)), cols))[None, :]
    return dataclasses.replace(bag, **{f: np.where(at, np.nan, getattr(bag, f)) for f in (
        'v_mag_pu', 'v_angle_rad', 'i_mag_pu', 'i_angle_rad', 'frequency_hz', 'rocof_hz_per_s')})


@pytest.mark.parametrize('name,tag_s', [('ieee14_g1_unstable', 1.0 + 1 / 60), ('kundur_bus9_unstable', 1.0 + 1 / 30),
                                        ('nordic44_bus6000_three_groups', 1.0 + 1 / 30),
                                        ('ieee39_paper_case2', 5.0 + 1 / 60), ('ieee39_case2_g3_unstable', 5.2),
                                        ('ieee39_g6g7_unstable', 5.25 + 1 / 60)])
def test_one_frame_lost_at_a_faults_inception_or_clearing_flags_no_station(name, tag_s):
    """One lost frame at an event is no evidence against any station.

    Before, the filter stepped the lost frame blind (no acceleration) and its next frames' innovations, honest,
    exceeded the bound at the faulted area's stations: a single lost frame at an event refused the split.
    """
    bag = _bag(name)
    lost = _without(bag, np.abs(np.asarray(bag.tag_s) - tag_s) < 1e-3)
    assert _screened(bag, lost) == {}


@pytest.mark.parametrize('name,station', [('kundur_bus9_unstable', 'PMU_4'), ('ieee14_g1_unstable', 'PMU_2')])
def test_an_honest_station_at_half_the_streams_rate_is_not_flagged(name, station):
    bag = _bag(name)
    odd = np.arange(len(bag.tag_s)) % 2 == 1
    half = _without(bag, odd, np.array([bag.station_ids.index(station)]))
    assert _screened(bag, half) == {}


@pytest.mark.parametrize('name,station', [('ieee39_g6g7_unstable', 'PMU_35'), ('ieee14_g1_unstable', 'PMU_2'),
                                          ('nordic44_bus6000_three_groups', 'PMU_8500/GENROU_80')])
def test_a_spoofed_speed_on_a_station_sending_every_other_frame_is_flagged_by_its_frequency(name, station):
    """A station that sends every other frame is judged by its frequency too.

    Before, the frequency test judged consecutive frames only: at half the stream's rate a station was never
    judged, and a +2 rad/s ramp on the G6-G7 bags' PMU_35 steered the cut (22-23 added), flagged by nothing.
    """
    from controlled_islanding.evaluation.attack_sweep import attack_start_s

    bag = _bag(name)
    odd = np.arange(len(bag.tag_s)) % 2 == 1
    half = _without(bag, odd, np.array([bag.station_ids.index(station)]))
    start_s = attack_start_s(bag)
    ramped = attack(half, 'ramp', [station], start_s)
    flags = _screened(bag, ramped, until_s=float(bag.request_t_s[0]))
    assert flags[station][0] == 'frequency_mismatch'


def test_a_stream_that_starts_in_an_event_holds_no_station_whose_first_frame_was_lost():
    """Silent for one frame from the stream's start is no silence the filter does not bridge."""
    bag = _bag('ieee39_g6g7_initial_gap')
    first = np.zeros(len(bag.tag_s), dtype=bool)
    first[np.flatnonzero(np.asarray(bag.frame_present))[0]] = True
    assert first_flags(_without(bag, first, np.array([bag.station_ids.index('PMU_37')]))) == {}


def _span(bag, from_s: float, span_s: float = 0.15) -> np.ndarray:
    """Frames from half a period after from_s on, for span_s: longer than the filter's resumed span (0.1 s)."""
    from controlled_islanding.core.coherency import frame_period_s
    tags = np.asarray(bag.tag_s)
    start = from_s + 0.5 * frame_period_s(tags)
    return (tags > start) & (tags < start + span_s)


@pytest.mark.parametrize('name,after_s', [('ieee14_g1_unstable', 0.0), ('kundur_bus9_unstable', 0.0),
                                          ('nordic44_bus6000_three_groups', 0.0), ('pjm5bus_bus3_unstable', 0.0),
                                          ('ieee39_g6g7_unstable', 0.25)])
def test_a_silence_of_the_whole_stream_through_an_event_flags_no_station(name, after_s):
    """0.15 s with no frame at all, from a fault's first frame or in its swing: a PDC or network outage.

    Before, the filters of the faulted area came back from it with innovations far above the bound and flagged
    their honest stations (every one of IEEE 14's): an outage at the event refused the split.
    """
    from controlled_islanding.evaluation.attack_sweep import attack_start_s

    bag = _bag(name)
    rows = _span(bag, attack_start_s(bag) + after_s)
    outage = dataclasses.replace(_without(bag, rows), frame_present=np.asarray(bag.frame_present) & ~rows)
    assert _screened(outage, outage) == {}


@pytest.mark.parametrize('name,station,after_s', [('ieee14_g1_unstable', 'PMU_2', 0.25),
                                                  ('kundur_bus9_unstable', 'PMU_3', 0.0),
                                                  ('ieee39_g6g7_unstable', 'PMU_35', 0.25),
                                                  ('ieee39_paper_case2', 'PMU_32', 0.0)])
def test_a_station_silent_for_longer_than_a_resumed_span_through_an_event_is_not_flagged(name, station, after_s):
    """0.15 s of one station's frames lost across a fault's inception or clearing, or in its swing.

    Before, the blind steps held its last inputs with no acceleration and a speed walk sized for a grid at rest:
    its filter came back off by more than its covariance allowed, and the honest station was flagged.
    """
    from controlled_islanding.evaluation.attack_sweep import attack_start_s

    bag = _bag(name)
    rows = _span(bag, attack_start_s(bag) + after_s)
    assert _screened(bag, _without(bag, rows, np.array([bag.station_ids.index(station)]))) == {}


@pytest.mark.parametrize('name,station', [('ieee14_g1_unstable', 'PMU_1'), ('kundur_bus9_unstable', 'PMU_4'),
                                          ('ieee39_g6g7_unstable', 'PMU_30')])
def test_a_station_back_half_a_cycle_off_from_a_short_silence_in_an_event_is_flagged(name, station):
    """The widening after a silence is what the unseen inputs allow, not a licence: gap_step with a 0.15 s gap."""
    from controlled_islanding.evaluation.attack_sweep import attack_start_s

    bag = _bag(name)
    j = bag.station_ids.index(station)
    start_s = attack_start_s(bag)
    tags = np.asarray(bag.tag_s)
    silent = _without(bag, (tags >= start_s) & (tags < start_s + 0.15), np.array([j]))
    back = tags >= start_s + 0.15
    shifted = dataclasses.replace(silent, **{f: np.where(back[:, None] & (np.arange(len(bag.station_ids)) == j),
                                                         getattr(silent, f) + np.pi, getattr(silent, f))
                                             for f in ('v_angle_rad', 'i_angle_rad')})
    flags = _screened(bag, shifted, until_s=float(bag.request_t_s[0]))
    assert flags[station][0] == 'innovation'


@pytest.mark.parametrize('station,lost_s', [('PMU_6000/GENROU_33', (3.967, 4.0)), ('PMU_5400/GENROU_24', (4.733,))])
def test_a_machine_slipping_poles_is_not_judged_on_the_frame_after_lost_ones(station, lost_s):
    """Nordic 44's machines slip at 6 Hz: no chord follows their phasors across a lost frame.

    Before, the first frame after one or two lost ones was judged as if it did, and honest stations were flagged.
    """
    bag = _bag('nordic44_bus6000_three_groups')
    tags = np.asarray(bag.tag_s)
    rows = np.any(np.abs(tags[:, None] - np.array(lost_s)[None, :]) < 0.006, axis=1)
    assert _screened(bag, _without(bag, rows, np.array([bag.station_ids.index(station)]))) == {}
