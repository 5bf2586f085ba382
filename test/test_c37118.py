"""controlled_islanding.pmu.c37118 against pyc37, an independent C37.118.2 implementation, in both directions.

pyc37 builds CFG-2 and DATA frames in all four phasor formats and our parser must read back what was put in;
our frames must parse in pyc37 with the same values. Our own round trips cover what pyc37 cannot express
(non-zero PMU time quality, FRACSEC fractions above 2^23, float FREQ of the actual frequency).
"""

from __future__ import annotations

import collections.abc  # noqa: F401  pyc37.frame uses collections.abc without importing it
import math
import random

import pytest

from controlled_islanding.pmu import c37118 as c

pyc37_frame = pytest.importorskip('pyc37.frame')
pyc37_utils = pytest.importorskip('pyc37.utils')

SOC = 1_767_225_608  # 2026-01-01 00:00:08 UTC


def pyc37_cfg(fmt: tuple[bool, bool, bool, bool], time_base: int = 1_000_000, fnom: int = 60,
              units=((915527, 'v'), (45776, 'i'))):
    """Return one PMU: phasors V and I, one analog, one digital word; fmt: polar, phasor/analog/freq float."""
    names = ['VA', 'I1', 'ANALOG1'] + [f'BRK{k}' for k in range(16)]
    return pyc37_frame.ConfigFrame2(7734, time_base, 1, 'Station A', 7734, fmt, 2, 1, 1, names, list(units),
                                    [(1, 'pow')], [(0x0000, 0xFFFF)], fnom, 22, 30, soc=SOC, frasec=123456)


def test_crc_is_ccitt_false_and_equals_pyc37():
    assert c.crc_ccitt(b'123456789') == 0x29B1  # the published check value of CRC-16/CCITT-FALSE
    rng = random.Random(1)
    for n in (0, 1, 16, 100, 1000):
        data = bytes(rng.randrange(256) for _ in range(n))
        assert c.crc_ccitt(data) == pyc37_utils.crc16xmodem(data, 0xFFFF)


@pytest.mark.parametrize('fmt', [(True, True, True, True), (False, True, True, True), (True, False, False, False),
                                 (False, False, False, False)], ids=['polar-float', 'rect-float', 'polar-int',
                                                                     'rect-int'])
def test_pyc37_frames_parse_to_what_was_put_in(fmt):
    cfg_frame = pyc37_cfg(fmt)
    cfg = c.decode_config(cfg_frame.convert2bytes())
    assert cfg.idcode == 7734 and cfg.time_base == 1_000_000 and cfg.data_rate == 30
    (pmu,) = cfg.pmus
    assert pmu.station == 'Station A' and pmu.idcode == 7734 and pmu.nominal_hz == 60 and pmu.cfg_count == 22
    assert (pmu.polar, pmu.phasor_float, pmu.analog_float, pmu.freq_float) == fmt
    assert pmu.phasor_names == ('VA', 'I1') and pmu.analog_names == ('ANALOG1',) and len(pmu.digital_names) == 16
    assert not pmu.is_current(0) and pmu.is_current(1)
    assert pmu.phasor_scale(0) == pytest.approx(9.15527) and pmu.phasor_scale(1) == pytest.approx(0.45776)

    polar, ph_float, an_float, fr_float = fmt
    if ph_float:
        phasors = [(14635.5, 0.25), (1092.25, -2.5)] if polar else [(14635.5, -120.25), (-1092.25, 400.5)]
    else:
        phasors = [(14635, 2500), (1092, -25000)] if polar else [(14635, -1200), (-1092, 4005)]
    freq, dfreq = (0.015, -0.25) if fr_float else (15, -25)  # pyc37: float FREQ is the deviation, not the value
    analog = [2.5] if an_float else [250]
    stat = 0x2000 | 0x1000  # sync error, sorted by arrival; PMU time quality 0: pyc37 cannot decode others
    frame = pyc37_frame.DataFrame(7734, stat, phasors, freq, dfreq, analog, [0x3C12], cfg_frame, soc=SOC,
                                  frasec=(654321, '+', False, True, 6))
    got = c.decode_data(frame.convert2bytes(), cfg)
    assert got.time == c.TimeTag(SOC, 654321, time_quality=6, leap_pending=True)
    assert got.time.ns(cfg.time_base) == SOC * 1_000_000_000 + 654_321_000
    (block,) = got.pmus
    assert block.stat == stat and block.digitals == (0x3C12,)
    for k, (a, b) in enumerate(phasors):
        scale = 1.0 if ph_float else pmu.phasor_scale(k)
        want = a * scale * complex(math.cos(b * (1 if ph_float else 1e-4)), math.sin(b * (1 if ph_float else 1e-4))) \
            if polar else complex(a * scale, b * scale)
        assert block.phasors[k] == pytest.approx(want, rel=1e-6)
    if fr_float:
        assert block.freq_hz == pytest.approx(0.015) and block.rocof_hz_per_s == pytest.approx(-0.25)
    else:
        assert block.freq_hz == pytest.approx(60.015) and block.rocof_hz_per_s == pytest.approx(-0.25)
    assert block.analogs[0] == pytest.approx(2.5 if an_float else 250.0)


def our_config(fmt: tuple[bool, bool, bool, bool], n_pmu: int = 1) -> c.Config:
    polar, ph_float, an_float, fr_float = fmt
    pmus = tuple(c.PmuConfig(
        station=f'PMU_{30 + k}', idcode=k + 1, polar=polar, phasor_float=ph_float, analog_float=an_float,
        freq_float=fr_float, phasor_names=(f'V_{30 + k}', f'I_{30 + k}'),
        phasor_units=(c.phunit(10.0, False), c.phunit(0.1, True)), analog_names=('P_MW',), analog_units=(1,),
        digital_names=tuple(f'B{b}' for b in range(16)), digital_units=(0xFFFF,), nominal_hz=50 if k else 60,
        cfg_count=3) for k in range(n_pmu))
    return c.Config(idcode=99, time=c.TimeTag(SOC, 0), time_base=1_000_000, pmus=pmus, data_rate=60)


# Float FREQ is left out: the standard puts the frequency itself there (60.012), which pyc37 refuses to decode.
@pytest.mark.parametrize('fmt', [(True, True, True, False), (False, False, False, False)], ids=['float', 'int'])
def test_our_frames_parse_in_pyc37(fmt):
    cfg = our_config(fmt)
    theirs = pyc37_frame.CommonFrame.convert2frame(c.encode_config(cfg))
    assert type(theirs).__name__ == 'ConfigFrame2'
    assert theirs.get_id_code() == 99 and theirs.get_time_base() == 1_000_000 and theirs.get_data_rate() == 60
    assert theirs.get_station_name().strip() == 'PMU_30' and theirs.get_fnom() == 60
    assert [n.strip() for n in theirs.get_channel_names()[:3]] == ['V_30', 'I_30', 'P_MW']
    assert theirs.get_ph_units() == [(1000000, 'v'), (10000, 'i')]
    assert theirs.get_data_format() == fmt

    v, i = 199_000 * complex(math.cos(0.3), math.sin(0.3)), 700 * complex(math.cos(-0.4), math.sin(-0.4))
    data = c.DataFrame(99, c.TimeTag(SOC, 500_000, time_quality=5), (c.PmuData(
        stat=0x2000, phasors=(v, i), freq_hz=60.012, rocof_hz_per_s=0.5, analogs=(120.0,), digitals=(0x0003,)),))
    frame = pyc37_frame.CommonFrame.convert2frame(c.encode_data(data, cfg), theirs)
    assert frame.get_soc() == SOC and frame.get_frasec() == (500_000, '+', False, False, 5)
    got = frame.get_phasors()  # pyc37 converts to polar and applies PHUNIT
    assert got[0][0] == pytest.approx(abs(v), rel=1e-4) and got[0][1] == pytest.approx(0.3, abs=1e-4)
    assert got[1][0] == pytest.approx(abs(i), rel=1e-3) and got[1][1] == pytest.approx(-0.4, abs=1e-4)
    assert frame.get_digital() == [0x0003]
    assert frame.get_freq() == 12 and frame.get_dfreq() == 50  # mHz deviation, ROCOF x 100


def test_round_trip_of_everything_pyc37_cannot_express():
    for fmt in [(True, True, True, True), (False, True, False, True), (True, False, False, False),
                (False, False, True, False)]:
        cfg = our_config(fmt, n_pmu=3)
        again = c.decode_config(c.encode_config(cfg))
        assert again == cfg
        tag = c.TimeTag(SOC, 999_999, time_quality=15, leap_delete=True, leap_occurred=True, leap_pending=True)
        blocks = tuple(c.PmuData(
            stat=0x8000 | 0x2000 | (7 << c.STAT_TIME_QUALITY_SHIFT) | (3 << c.STAT_UNLOCKED_SHIFT) | k,
            phasors=(150_000 * complex(math.cos(3.1), math.sin(3.1)), complex(math.nan, math.nan) if k == 1
                     else complex(-300.0, 200.0)),
            freq_hz=59.95 + k * 0.01, rocof_hz_per_s=-1.25, analogs=(1000.0,), digitals=(0xA5A5,)) for k in range(3))
        got = c.decode_data(c.encode_data(c.DataFrame(99, tag, blocks), cfg), cfg)
        assert got.time == tag and got.time.max_error_s == math.inf
        for want, block in zip(blocks, got.pmus, strict=True):
            assert block.stat == want.stat and block.digitals == want.digitals
            assert block.phasors[0] == pytest.approx(want.phasors[0], abs=5.0)
            if math.isnan(want.phasors[1].real):
                assert math.isnan(block.phasors[1].real) and math.isnan(block.phasors[1].imag)
            else:
                assert block.phasors[1] == pytest.approx(want.phasors[1], abs=0.1)
            assert block.freq_hz == pytest.approx(want.freq_hz, abs=1e-3)
            assert block.rocof_hz_per_s == pytest.approx(-1.25, abs=1e-2)


def test_time_tags_keep_24_bits_and_round_to_the_time_base():
    tag = c.TimeTag(SOC, 12_000_000)  # > 2^23: pyc37 reads 3611392 here
    assert c.TimeTag.from_word(SOC, tag.fracsec_word()) == tag
    # A bag time tag at 1/60 s, through TIME_BASE 1e6 and back: within half a microsecond.
    t_ns = SOC * 1_000_000_000 + 16_666_667
    back = c.TimeTag.from_ns(t_ns, 1_000_000).ns(1_000_000)
    assert abs(back - t_ns) <= 500
    assert c.TimeTag.from_ns(SOC * 1_000_000_000 + 999_999_999, 1_000_000) == c.TimeTag(SOC + 1, 0)
    assert c.TimeTag(SOC, 0, time_quality=6).max_error_s == pytest.approx(1e-4)
    assert c.TimeTag(SOC, 0, time_quality=0).max_error_s == 0.0


def test_commands_both_ways():
    for name, code in (('start', c.CMD_START), ('stop', c.CMD_STOP), ('cfg2', c.CMD_CFG2), ('header', c.CMD_HEADER)):
        theirs = pyc37_frame.CommandFrame(7, name, soc=SOC, frasec=1)
        ours = c.decode_command(theirs.convert2bytes())
        assert (ours.idcode, ours.command, ours.time.soc) == (7, code, SOC)
        back = pyc37_frame.CommonFrame.convert2frame(c.encode_command(c.Command(7, c.TimeTag(SOC, 1), code)))
        assert back.get_command() == name


def test_malformed_frames_are_named_and_the_splitter_resynchronises():
    cfg = our_config((True, True, True, True))
    good = c.encode_config(cfg)
    with pytest.raises(c.C37118Error, match='CHK'):
        c.decode_config(good[:-1] + bytes([good[-1] ^ 1]))
    with pytest.raises(c.C37118Error, match='FRAMESIZE'):
        c.decode_config(good[:-3] + good[-2:])
    with pytest.raises(c.C37118Error, match='expected a DATA frame'):
        c.decode_data(good, cfg)
    other = our_config((False, False, False, False))
    data = c.encode_data(c.DataFrame(99, c.TimeTag(SOC), (c.PmuData(0, (1 + 1j, 1j), 60.0, 0.0, (0.0,), (0,)),)), cfg)
    with pytest.raises(c.C37118Error, match='new configuration'):
        c.decode_data(data, other)
    with pytest.raises(c.C37118Error, match='full scale'):
        c.encode_data(c.DataFrame(99, c.TimeTag(SOC), (c.PmuData(0, (1e9 + 0j, 1j), 60.0, 0.0, (0.0,), (0,)),)),
                      our_config((True, False, False, False)))
    with pytest.raises(c.C37118Error, match='16-bit'):
        c.encode_data(c.DataFrame(99, c.TimeTag(SOC), (c.PmuData(0, (1e9 + 0j, 1j), 60.0, 0.0, (0.0,), (0,)),)),
                      other)
    with pytest.raises(c.C37118Error, match='longer than 16'):
        c.encode_config(c.Config(1, c.TimeTag(SOC), 1_000_000, (c.PmuConfig('a' * 17, 1),), 60))

    splitter = c.FrameSplitter()
    stream = b'\x00\x01garbage' + good + data + data[:10]
    frames = [f for k in range(0, len(stream), 7) for f in splitter.feed(stream[k:k + 7])]
    assert frames == [good, data] and splitter.skipped_bytes == 9
    assert splitter.feed(data[10:]) == [data]
