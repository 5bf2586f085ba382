"""pdc_assembly without ROS: the channel map, per-unit conversion, STAT and time-quality flags, alignment."""

from __future__ import annotations

import cmath
import math

import pytest

from controlled_islanding.pmu import c37118 as c
from controlled_islanding.pmu.pdc_assembly import (
    ChannelMap,
    PdcAssembler,
    PdcAssemblyError,
    TimeAligner,
    amperes_per_pu,
    parse_channel_map,
    volts_per_pu,
)

SOC = 1_767_225_600
MAP = {'base_mva': 100.0, 'pmus': [
    {'station': 'GEN A', 'bus': 30, 'base_kv': 20.0, 'voltage_channel': 'VT', 'current_channel': 'IT'},
    {'idcode': 12, 'bus': 31, 'base_kv': 345.0, 'voltage_channel': 'V1', 'current_channel': 'I1',
     'current_direction': 'in', 'station_id': 'PMU_31'}]}


def config() -> c.Config:
    a = c.PmuConfig('GEN A', 11, phasor_names=('IT', 'VT', 'VBUS'),
                    phasor_units=(c.phunit(0, True), c.phunit(0, False), c.phunit(0, False)))
    b = c.PmuConfig('somewhere', 12, phasor_names=('V1', 'I1'), phasor_units=(c.phunit(0, False), c.phunit(0, True)))
    other = c.PmuConfig('unmapped', 13, phasor_names=('V',), phasor_units=(c.phunit(0, False),))
    return c.Config(1, c.TimeTag(SOC), 1_000_000, (a, other, b), 60)


def block(v_pu: complex, i_pu: complex, kv: float, stat: int = 0) -> tuple[complex, complex]:
    return v_pu * volts_per_pu(kv), i_pu * amperes_per_pu(100.0, kv)


def frame(tag: c.TimeTag, angle: float, stat_a: int = 0, v_b: complex | None = None) -> c.DataFrame:
    va, ia = block(cmath.rect(1.02, angle), cmath.rect(5.0, angle - 0.3), 20.0)
    vb, ib = block(cmath.rect(0.98, -0.1), cmath.rect(2.0, 2.9), 345.0)
    return c.DataFrame(1, tag, (
        c.PmuData(stat_a, (ia, va, va), 60.01, 0.1), c.PmuData(0, (1 + 0j,), 60.0, 0.0),
        c.PmuData(0, (vb if v_b is None else v_b, ib), 59.99, -0.2)))


def test_channels_come_from_the_map_and_values_return_to_per_unit():
    asm = PdcAssembler(parse_channel_map(MAP), max_time_error_s=1e-4)
    layout = asm.configure('pdc', config())
    assert layout.unmapped == ('unmapped',) and asm.missing_stations() == []
    t_ns, (a, b) = asm.measurements('pdc', frame(c.TimeTag(SOC, 500_000), 0.5))
    assert t_ns == SOC * 1_000_000_000 + 500_000_000
    assert (a.station_id, a.bus, b.station_id, b.bus) == ('GEN A', 30, 'PMU_31', 31)
    assert a.voltage_magnitude_pu == pytest.approx(1.02) and a.voltage_angle_rad == pytest.approx(0.5)
    assert a.current_magnitude_pu == pytest.approx(5.0) and a.current_angle_rad == pytest.approx(0.2)
    assert b.current_magnitude_pu == pytest.approx(2.0)
    assert b.current_angle_rad == pytest.approx(2.9 - math.pi)  # measured into the machine: turned around
    assert a.stat == 0 and a.frequency_hz == pytest.approx(60.01)


def test_angles_are_unwrapped_frame_to_frame():
    asm = PdcAssembler(parse_channel_map(MAP), 1e-4)
    asm.configure('pdc', config())
    angles = [asm.measurements('pdc', frame(c.TimeTag(SOC, k), 3.0 + 0.2 * k))[1][0].voltage_angle_rad
              for k in range(10)]
    assert angles == pytest.approx([3.0 + 0.2 * k for k in range(10)])  # past pi, not wrapped back


def test_absent_data_and_untrusted_time_are_flagged_in_stat():
    asm = PdcAssembler(parse_channel_map(MAP), 1e-4)
    asm.configure('pdc', config())
    nan = complex(math.nan, math.nan)
    _, (a, b) = asm.measurements('pdc', frame(c.TimeTag(SOC), 0.1, stat_a=c.STAT_SORT_BY_ARRIVAL, v_b=nan))
    assert a.stat == c.STAT_SORT_BY_ARRIVAL  # passed on
    assert b.stat & c.STAT_DATA_ERROR_MASK == c.STAT_DO_NOT_USE
    _, (a, b) = asm.measurements('pdc', frame(c.TimeTag(SOC, 1, time_quality=7), 0.1))  # frame clock: 1 ms
    assert a.stat & c.STAT_SYNC_ERROR and b.stat & c.STAT_SYNC_ERROR
    _, (a, b) = asm.measurements('pdc', frame(c.TimeTag(SOC, 2, time_quality=5), 0.1))  # 10 us: fine
    assert not a.stat & c.STAT_SYNC_ERROR
    _, (a, _b) = asm.measurements('pdc', frame(c.TimeTag(SOC, 3), 0.1, stat_a=5 << c.STAT_TIME_QUALITY_SHIFT))
    assert a.stat & c.STAT_SYNC_ERROR  # the PMU's own time quality: < 1 ms is not < 100 us
    _, (a, _b) = asm.measurements('pdc', frame(c.TimeTag(SOC, 4), 0.1, stat_a=1 << c.STAT_UNLOCKED_SHIFT))
    assert a.stat & c.STAT_SYNC_ERROR  # lost lock for more than 10 s


def test_a_map_that_does_not_fit_the_stream_names_the_channel():
    bad = {**MAP, 'pmus': [{**MAP['pmus'][0], 'voltage_channel': 'VX'}]}
    with pytest.raises(PdcAssemblyError, match="no phasor channel 'VX'.*'IT', 'VT', 'VBUS'"):
        PdcAssembler(parse_channel_map(bad), 1e-4).configure('pdc', config())
    swapped = {**MAP, 'pmus': [{**MAP['pmus'][0], 'voltage_channel': 'IT', 'current_channel': 'VT'}]}
    with pytest.raises(PdcAssemblyError, match='current by its PHUNIT'):
        PdcAssembler(parse_channel_map(swapped), 1e-4).configure('pdc', config())
    for broken, match in ((dict(MAP, base_mva=0), 'base_mva'), ({'pmus': []}, 'non-empty'),
                          ({**MAP, 'pmus': [{**MAP['pmus'][0], 'bus': 'thirty'}]}, 'bus'),
                          ({**MAP, 'pmus': [{**MAP['pmus'][0], 'idcode': 3}]}, 'exactly one'),
                          ({**MAP, 'pmus': [MAP['pmus'][0], MAP['pmus'][0]]}, 'twice')):
        with pytest.raises(PdcAssemblyError, match=match):
            parse_channel_map(broken, 'test map')
    assert parse_channel_map(__import__('yaml').safe_load(parse_channel_map(MAP).to_yaml())) == \
        parse_channel_map(MAP)
    assert isinstance(parse_channel_map(MAP), ChannelMap)


def test_alignment_waits_for_every_stream_then_gives_up_and_drops_late_parts():
    aligner = TimeAligner(wait_s=0.1)
    aligner.expected = {'a', 'b'}
    assert aligner.add('a', 100, ['a100'], now_s=0.0) == []
    assert aligner.add('b', 100, ['b100'], now_s=0.01) == [(100, ['a100', 'b100'])]
    assert aligner.add('a', 200, ['a200'], now_s=0.02) == []
    assert aligner.add('a', 300, ['a300'], now_s=0.03) == []
    assert aligner.due(now_s=0.125) == [(200, ['a200'])]  # b never sent 200: published without it
    assert aligner.add('b', 300, ['b300'], now_s=0.126) == [(300, ['a300', 'b300'])]
    assert aligner.add('b', 200, ['b200'], now_s=0.13) == []  # too late: 200 is out
    assert aligner.add('a', 300, ['again'], now_s=0.14) == []  # a repeated time tag (leap second) too
    assert (aligner.late, aligner.incomplete) == (2, 1)
