"""IEEE C37.118.2-2011 synchrophasor frames: parse and build CFG-2, DATA, COMMAND and HEADER frames.

Pure bytes in, plain dataclasses out (no sockets, no rclpy), so every rule is testable in milliseconds and
the same code serves both ends: `controlled-islanding serve-pmu` builds frames, the pdc_client node parses
them. test/test_c37118.py checks both directions against pyc37, an independent implementation.

Why our own: pyc37 1.0.2 (the maintained fork of pypmu) was evaluated first; its decoder raises on any
non-zero PMU time quality in STAT, reads 23 of the 24 FRACSEC fraction bits, needs `collections.abc`
imported by someone else, and cannot put an actual frequency in a float FREQ field; its PMU server
sends at most ~9 frames/s whatever the configured rate (README, "Libraries").

Wire facts used here (C37.118.2-2011, big endian throughout):
- Every frame: SYNC (0xAA, then frame type in bits 6-4 and version in bits 3-0), FRAMESIZE (bytes, CHK
  included), IDCODE, SOC (s since 1970-01-01 UTC, leap seconds not counted), FRACSEC, body, CHK
  (CRC-CCITT: polynomial 0x1021, initial value 0xFFFF, no reflection, no final XOR).
- FRACSEC: bits 31-24 message time quality (bit 30 leap direction, 29 leap occurred, 28 leap pending,
  27-24 a code for the worst-case clock error), bits 23-0 the fraction of a second in 1/TIME_BASE.
- Phasors are volts and amperes. Integer phasors are scaled by PHUNIT (1e-5 V or A per bit); float
  phasors are in V and A as they are. Integer FREQ is the deviation from nominal in mHz and integer DFREQ
  is ROCOF x 100; float FREQ is the actual frequency in Hz and float DFREQ the ROCOF in Hz/s.
- Absent data: NaN in float fields, 0x8000 in 16-bit integer ones.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

SYNC_BYTE = 0xAA
VERSION_2005 = 1
VERSION_2011 = 2

FRAME_DATA = 0
FRAME_HEADER = 1
FRAME_CFG1 = 2
FRAME_CFG2 = 3
FRAME_COMMAND = 4
FRAME_CFG3 = 5
FRAME_NAMES = {FRAME_DATA: 'DATA', FRAME_HEADER: 'HEADER', FRAME_CFG1: 'CFG-1', FRAME_CFG2: 'CFG-2',
               FRAME_COMMAND: 'COMMAND', FRAME_CFG3: 'CFG-3'}

CMD_STOP = 1  # turn off transmission of data frames
CMD_START = 2  # turn on transmission of data frames
CMD_HEADER = 3
CMD_CFG1 = 4
CMD_CFG2 = 5
CMD_CFG3 = 6
CMD_EXTENDED = 8

# STAT word of one PMU block (2011).
STAT_DATA_ERROR_MASK = 0xC000  # bits 15-14: 00 good, 01 PMU error (data may be fine), 10 test mode/absent, 11 error
STAT_DO_NOT_USE = 0x8000  # bit 15: 10 and 11 both say "do not use the values"
STAT_SYNC_ERROR = 0x2000  # bit 13: not in sync with a UTC-traceable time source
STAT_SORT_BY_ARRIVAL = 0x1000  # bit 12: the PDC placed this block by arrival, not by its time tag
STAT_TRIGGER = 0x0800
STAT_CONFIG_CHANGE = 0x0400  # bit 10: a new configuration is coming within a minute
STAT_DATA_MODIFIED = 0x0200
STAT_TIME_QUALITY_SHIFT = 6  # bits 8-6: PMU time quality (PMU_TIME_QUALITY_MAX_ERROR_S)
STAT_UNLOCKED_SHIFT = 4  # bits 5-4: how long sync has been lost: 00 < 10 s, 01 < 100 s, 10 < 1000 s, 11 more

# Worst-case time error, s, of each code. Message time quality (FRACSEC bits 27-24): 0 = locked to UTC,
# 1..11 = within 10^(code - 10) s, 15 = clock failure; 12-14 are undefined and taken as failure.
MESSAGE_TIME_QUALITY_MAX_ERROR_S = {0: 0.0, **{c: 10.0 ** (c - 10) for c in range(1, 12)}}
# PMU time quality (STAT bits 8-6): 0 = not used (a 2005 device; no information), 1 = < 100 ns ... 6 = < 10 ms,
# 7 = > 10 ms or unknown.
PMU_TIME_QUALITY_MAX_ERROR_S = {0: None, 1: 1e-7, 2: 1e-6, 3: 1e-5, 4: 1e-4, 5: 1e-3, 6: 1e-2, 7: math.inf}

PHUNIT_SCALE = 1e-5  # V or A per bit for each unit of PHUNIT's 24-bit factor
ABSENT_INT16 = -0x8000  # 16-bit integer marker of absent data
_STATION_CHARS = 16
_HEADER_BYTES = 14  # SYNC, FRAMESIZE, IDCODE, SOC, FRACSEC
_MAX_FRAME_BYTES = 0xFFFF


class C37118Error(ValueError):
    """A frame is malformed (names what and where), or a value cannot be represented in the chosen format."""


def crc_ccitt(data: bytes) -> int:
    """Return the CRC-CCITT of data as C37.118 computes CHK (poly 0x1021, init 0xFFFF, no reflection)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


@dataclass(frozen=True)
class TimeTag:
    """SOC and FRACSEC of a frame.

    Attributes:
        soc: Seconds since 1970-01-01 00:00 UTC, leap seconds not counted (a leap second repeats a value).
        fraction: Fraction of the second, in 1/TIME_BASE of a second (24 bits).
        time_quality: Message time quality code (FRACSEC bits 27-24); see MESSAGE_TIME_QUALITY_MAX_ERROR_S.
        leap_delete: Leap second direction: False = add (insert), True = delete.
        leap_occurred: Set for 24 h after a leap second.
        leap_pending: Set up to 60 s before a leap second.

    """

    soc: int
    fraction: int = 0
    time_quality: int = 0
    leap_delete: bool = False
    leap_occurred: bool = False
    leap_pending: bool = False

    @classmethod
    def from_ns(cls, t_ns: int, time_base: int, **flags: object) -> TimeTag:
        """Return the time tag nearest to t_ns (ns since the epoch) in 1/time_base steps."""
        soc, rest_ns = divmod(int(t_ns), 1_000_000_000)
        fraction = (rest_ns * time_base + 500_000_000) // 1_000_000_000
        if fraction >= time_base:  # rounding reached the next second
            soc, fraction = soc + 1, 0
        return cls(soc, fraction, **flags)

    def fracsec_word(self) -> int:
        """Return the 32-bit FRACSEC word."""
        if not 0 <= self.fraction < 1 << 24:
            raise C37118Error(f'FRACSEC fraction {self.fraction} does not fit in 24 bits')
        if not 0 <= self.time_quality <= 15:
            raise C37118Error(f'message time quality code {self.time_quality} is not 0-15')
        flags = (self.leap_delete << 6) | (self.leap_occurred << 5) | (self.leap_pending << 4) | self.time_quality
        return (flags << 24) | self.fraction

    @classmethod
    def from_word(cls, soc: int, word: int) -> TimeTag:
        """Return the time tag of a SOC and a FRACSEC word."""
        flags = word >> 24
        return cls(soc, word & 0xFFFFFF, flags & 0x0F, bool(flags & 0x40), bool(flags & 0x20), bool(flags & 0x10))

    def ns(self, time_base: int) -> int:
        """Return the time tag in ns since the epoch (POSIX UTC, like ROS stamps)."""
        return self.soc * 1_000_000_000 + (self.fraction * 1_000_000_000 + time_base // 2) // time_base

    @property
    def max_error_s(self) -> float:
        """Worst-case clock error the message time quality claims, s (inf: clock failure or undefined code)."""
        return MESSAGE_TIME_QUALITY_MAX_ERROR_S.get(self.time_quality, math.inf)


@dataclass(frozen=True)
class PmuConfig:
    """One PMU block of a CFG-2 frame.

    Attributes:
        station: STN, at most 16 ASCII characters (trailing blanks are not part of the name).
        idcode: IDCODE of this PMU's data.
        polar: Phasors are magnitude and angle (else real and imaginary).
        phasor_float: Phasors are 32-bit floats (else 16-bit integers scaled by PHUNIT).
        analog_float: Analog values are 32-bit floats.
        freq_float: FREQ and DFREQ are 32-bit floats.
        phasor_names: CHNAM of each phasor.
        phasor_units: PHUNIT word of each phasor: bits 31-24 0 = voltage, 1 = current; bits 23-0 the scale in
            1e-5 V or A per bit (integer phasors only).
        analog_names: CHNAM of each analog value.
        analog_units: ANUNIT word of each analog value (bits 23-0 a signed scale factor for integer values).
        digital_names: CHNAM of each bit of each digital word, 16 per word.
        digital_units: DIGUNIT word of each digital word.
        nominal_hz: FNOM, 50 or 60.
        cfg_count: CFGCNT, incremented by the PMU at every configuration change.

    """

    station: str
    idcode: int
    polar: bool = True
    phasor_float: bool = True
    analog_float: bool = True
    freq_float: bool = True
    phasor_names: tuple[str, ...] = ()
    phasor_units: tuple[int, ...] = ()
    analog_names: tuple[str, ...] = ()
    analog_units: tuple[int, ...] = ()
    digital_names: tuple[str, ...] = ()
    digital_units: tuple[int, ...] = ()
    nominal_hz: int = 60
    cfg_count: int = 0

    def __post_init__(self) -> None:
        if len(self.phasor_names) != len(self.phasor_units):
            raise C37118Error(f'PMU {self.station}: {len(self.phasor_names)} phasor names but '
                              f'{len(self.phasor_units)} PHUNIT words')
        if len(self.analog_names) != len(self.analog_units):
            raise C37118Error(f'PMU {self.station}: {len(self.analog_names)} analog names but '
                              f'{len(self.analog_units)} ANUNIT words')
        if len(self.digital_names) != 16 * len(self.digital_units):
            raise C37118Error(f'PMU {self.station}: {len(self.digital_names)} digital names, not 16 per '
                              f'DIGUNIT word ({len(self.digital_units)})')
        if self.nominal_hz not in (50, 60):
            raise C37118Error(f'PMU {self.station}: nominal frequency {self.nominal_hz} Hz; FNOM allows 50 or 60')

    @property
    def format_word(self) -> int:
        """Return the FORMAT word."""
        return (self.freq_float << 3) | (self.analog_float << 2) | (self.phasor_float << 1) | int(self.polar)

    def is_current(self, phasor: int) -> bool:
        """Return True if PHUNIT says the phasor is a current."""
        return (self.phasor_units[phasor] >> 24) == 1

    def phasor_scale(self, phasor: int) -> float:
        """Return V or A per bit of an integer phasor."""
        return (self.phasor_units[phasor] & 0xFFFFFF) * PHUNIT_SCALE

    def analog_scale(self, analog: int) -> float:
        """Return the scale of an integer analog value (ANUNIT bits 23-0, signed)."""
        raw = self.analog_units[analog] & 0xFFFFFF
        return float(raw - (1 << 24) if raw & 0x800000 else raw)

    def data_bytes(self) -> int:
        """Return the size of this PMU's block in a DATA frame."""
        phasor = 8 if self.phasor_float else 4
        number = 4 if self.freq_float else 2
        analog = 4 if self.analog_float else 2
        return 2 + phasor * len(self.phasor_names) + 2 * number + analog * len(self.analog_names) \
            + 2 * len(self.digital_units)


def phunit(scale_v_or_a_per_bit: float, current: bool) -> int:
    """Return a PHUNIT word for a voltage or current channel with the given V or A per bit."""
    units = int(round(scale_v_or_a_per_bit / PHUNIT_SCALE))
    if not 0 <= units < 1 << 24:
        raise C37118Error(f'PHUNIT scale {scale_v_or_a_per_bit} V or A per bit does not fit in 24 bits of 1e-5')
    return (int(current) << 24) | units


@dataclass(frozen=True)
class Config:
    """A CFG-2 (or CFG-1) frame: the layout of every DATA frame of a stream.

    Attributes:
        idcode: IDCODE of the data stream (the PMU or PDC).
        time: Time tag of the configuration frame itself.
        time_base: TIME_BASE: FRACSEC fractions per second.
        pmus: One block per PMU, in DATA frame order.
        data_rate: DATA_RATE: frames per second if positive, seconds per frame if negative.
        frame_type: FRAME_CFG2 or FRAME_CFG1.
        version: SYNC version (VERSION_2011 or VERSION_2005).

    """

    idcode: int
    time: TimeTag
    time_base: int
    pmus: tuple[PmuConfig, ...]
    data_rate: int
    frame_type: int = FRAME_CFG2
    version: int = VERSION_2011

    @property
    def frames_per_s(self) -> float:
        """Return the reporting rate, frames/s."""
        if self.data_rate == 0:
            raise C37118Error('DATA_RATE is 0')
        return float(self.data_rate) if self.data_rate > 0 else -1.0 / self.data_rate

    def data_bytes(self) -> int:
        """Return the size of a DATA frame of this configuration."""
        return _HEADER_BYTES + sum(p.data_bytes() for p in self.pmus) + 2


@dataclass(frozen=True)
class PmuData:
    """One PMU block of a DATA frame, in engineering units.

    Attributes:
        stat: STAT word (STAT_* bits).
        phasors: Each phasor as a complex number, V or A (NaN when absent).
        freq_hz: Frequency, Hz (nominal + deviation for integer FREQ).
        rocof_hz_per_s: Rate of change of frequency, Hz/s.
        analogs: Analog values, scaled.
        digitals: Digital status words.

    """

    stat: int
    phasors: tuple[complex, ...]
    freq_hz: float
    rocof_hz_per_s: float
    analogs: tuple[float, ...] = ()
    digitals: tuple[int, ...] = ()


@dataclass(frozen=True)
class DataFrame:
    """A DATA frame: every PMU of the stream at one time tag."""

    idcode: int
    time: TimeTag
    pmus: tuple[PmuData, ...]


@dataclass(frozen=True)
class Command:
    """A COMMAND frame (CMD_*), sent by a PDC to a PMU or PDC."""

    idcode: int
    time: TimeTag
    command: int
    extended: bytes = field(default=b'')


@dataclass(frozen=True)
class Header:
    """A HEADER frame: free text about the stream."""

    idcode: int
    time: TimeTag
    text: str


# ---------------------------------------------------------------------------------------------------- framing


def _frame(frame_type: int, idcode: int, time: TimeTag, body: bytes, version: int = VERSION_2011) -> bytes:
    size = _HEADER_BYTES + len(body) + 2
    if size > _MAX_FRAME_BYTES:
        raise C37118Error(f'{FRAME_NAMES.get(frame_type, frame_type)} frame of {size} bytes exceeds 65535')
    if not 0 <= idcode <= 0xFFFF:
        raise C37118Error(f'IDCODE {idcode} does not fit in 16 bits')
    if not 0 <= time.soc <= 0xFFFFFFFF:
        raise C37118Error(f'SOC {time.soc} does not fit in 32 bits')
    head = struct.pack('>BBHHII', SYNC_BYTE, (frame_type << 4) | version, size, idcode, time.soc,
                       time.fracsec_word())
    without_chk = head + body
    return without_chk + struct.pack('>H', crc_ccitt(without_chk))


def check_frame(raw: bytes) -> tuple[int, int, int, TimeTag]:
    """Check SYNC, FRAMESIZE and CHK; return (frame type, version, IDCODE, time tag).

    Raises:
        C37118Error: Names what is wrong.

    """
    if len(raw) < _HEADER_BYTES + 2:
        raise C37118Error(f'frame of {len(raw)} bytes is shorter than the 16-byte minimum')
    sync, type_version, size, idcode, soc, fracsec = struct.unpack_from('>BBHHII', raw)
    if sync != SYNC_BYTE or type_version & 0x80:
        raise C37118Error(f'bad SYNC word 0x{sync:02x}{type_version:02x}')
    if size != len(raw):
        raise C37118Error(f'FRAMESIZE says {size} bytes, the frame has {len(raw)}')
    chk = struct.unpack_from('>H', raw, len(raw) - 2)[0]
    crc = crc_ccitt(raw[:-2])
    if chk != crc:
        raise C37118Error(f'CHK 0x{chk:04x} does not match the CRC-CCITT of the frame, 0x{crc:04x}')
    frame_type = (type_version >> 4) & 0x07
    if frame_type not in FRAME_NAMES:
        raise C37118Error(f'unknown frame type {frame_type}')
    return frame_type, type_version & 0x0F, idcode, TimeTag.from_word(soc, fracsec)


def frame_type_of(raw: bytes) -> int:
    """Return the frame type from the SYNC word (no checks; use check_frame first)."""
    return (raw[1] >> 4) & 0x07


class FrameSplitter:
    """Cuts a TCP byte stream into frames by SYNC and FRAMESIZE; skips garbage until the next SYNC byte.

    Attributes:
        skipped_bytes: Bytes thrown away while looking for a frame start.

    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.skipped_bytes = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return every complete frame now available (CHK not yet checked)."""
        self._buffer += data
        frames = []
        while True:
            start = self._buffer.find(SYNC_BYTE)
            if start < 0:
                self.skipped_bytes += len(self._buffer)
                self._buffer.clear()
                return frames
            if start:
                self.skipped_bytes += start
                del self._buffer[:start]
            if len(self._buffer) < 4:
                return frames
            size = struct.unpack_from('>H', self._buffer, 2)[0]
            if self._buffer[1] & 0x80 or size < _HEADER_BYTES + 2:
                # Not a frame start after all: drop this byte and look for the next SYNC.
                self.skipped_bytes += 1
                del self._buffer[:1]
                continue
            if len(self._buffer) < size:
                return frames
            frames.append(bytes(self._buffer[:size]))
            del self._buffer[:size]


# -------------------------------------------------------------------------------------------- configuration


def _name(text: str, what: str) -> bytes:
    try:
        raw = text.encode('ascii')
    except UnicodeEncodeError as exc:
        raise C37118Error(f'{what} {text!r} is not ASCII') from exc
    if len(raw) > _STATION_CHARS:
        raise C37118Error(f'{what} {text!r} is longer than 16 characters')
    return raw.ljust(_STATION_CHARS)


def encode_config(cfg: Config) -> bytes:
    """Return the bytes of a CFG-2 (or CFG-1) frame."""
    if not 0 < cfg.time_base < 1 << 24:
        raise C37118Error(f'TIME_BASE {cfg.time_base} must be 1 to 2^24 - 1')
    body = bytearray(struct.pack('>IH', cfg.time_base, len(cfg.pmus)))
    for p in cfg.pmus:
        body += _name(p.station, 'station name')
        body += struct.pack('>HHHHH', p.idcode, p.format_word, len(p.phasor_names), len(p.analog_names),
                            len(p.digital_units))
        for name in (*p.phasor_names, *p.analog_names, *p.digital_names):
            body += _name(name, f'PMU {p.station}: channel name')
        for word in (*p.phasor_units, *p.analog_units, *p.digital_units):
            body += struct.pack('>I', word)
        body += struct.pack('>HH', 1 if p.nominal_hz == 50 else 0, p.cfg_count)
    body += struct.pack('>h', cfg.data_rate)
    return _frame(cfg.frame_type, cfg.idcode, cfg.time, bytes(body), cfg.version)


def decode_config(raw: bytes) -> Config:
    """Parse a CFG-1 or CFG-2 frame.

    Raises:
        C37118Error: The frame is not a well-formed configuration frame; names the field.

    """
    frame_type, version, idcode, time = check_frame(raw)
    if frame_type not in (FRAME_CFG1, FRAME_CFG2):
        raise C37118Error(f'expected a CFG-2 frame, got {FRAME_NAMES[frame_type]}')
    end = len(raw) - 2
    pos = _HEADER_BYTES

    def take(n: int, what: str) -> bytes:
        nonlocal pos
        if pos + n > end:
            raise C37118Error(f'configuration frame ends inside {what} (byte {pos}, frame {len(raw)} bytes)')
        chunk = raw[pos:pos + n]
        pos += n
        return chunk

    time_base_word, num_pmu = struct.unpack('>IH', take(6, 'TIME_BASE/NUM_PMU'))
    time_base = time_base_word & 0xFFFFFF
    if time_base == 0:
        raise C37118Error('TIME_BASE is 0')
    pmus = []
    for k in range(num_pmu):
        station = _text(take(16, f'STN of PMU {k + 1}'))
        pmu_id, fmt, phnmr, annmr, dgnmr = struct.unpack('>HHHHH', take(10, f'PMU {station} counts'))
        names = [_text(take(16, f'PMU {station} channel names')) for _ in range(phnmr + annmr + 16 * dgnmr)]
        ph_units = struct.unpack(f'>{phnmr}I', take(4 * phnmr, f'PMU {station} PHUNIT'))
        an_units = struct.unpack(f'>{annmr}I', take(4 * annmr, f'PMU {station} ANUNIT'))
        dg_units = struct.unpack(f'>{dgnmr}I', take(4 * dgnmr, f'PMU {station} DIGUNIT'))
        fnom, cfg_count = struct.unpack('>HH', take(4, f'PMU {station} FNOM/CFGCNT'))
        pmus.append(PmuConfig(
            station=station, idcode=pmu_id, polar=bool(fmt & 1), phasor_float=bool(fmt & 2),
            analog_float=bool(fmt & 4), freq_float=bool(fmt & 8), phasor_names=tuple(names[:phnmr]),
            phasor_units=ph_units, analog_names=tuple(names[phnmr:phnmr + annmr]), analog_units=an_units,
            digital_names=tuple(names[phnmr + annmr:]), digital_units=dg_units,
            nominal_hz=50 if fnom & 1 else 60, cfg_count=cfg_count))
    (data_rate,) = struct.unpack('>h', take(2, 'DATA_RATE'))
    if pos != end:
        raise C37118Error(f'configuration frame has {end - pos} bytes after DATA_RATE')
    return Config(idcode, time, time_base, tuple(pmus), data_rate, frame_type, version)


def _text(raw: bytes) -> str:
    # Names are ASCII padded with blanks (some devices pad with NUL).
    return raw.decode('ascii', errors='replace').rstrip(' \x00')


# ------------------------------------------------------------------------------------------------------ data


def encode_data(frame: DataFrame, cfg: Config) -> bytes:
    """Return the bytes of a DATA frame laid out by cfg.

    Raises:
        C37118Error: The frame does not match cfg, or a value does not fit its integer field.

    """
    if len(frame.pmus) != len(cfg.pmus):
        raise C37118Error(f'DATA frame has {len(frame.pmus)} PMU blocks, the configuration {len(cfg.pmus)}')
    body = bytearray()
    for p, d in zip(cfg.pmus, frame.pmus, strict=True):
        if len(d.phasors) != len(p.phasor_names) or len(d.analogs) != len(p.analog_names) \
                or len(d.digitals) != len(p.digital_units):
            raise C37118Error(f'PMU {p.station}: DATA block does not match its configuration (phasors, analogs, '
                              'digital words)')
        body += struct.pack('>H', d.stat)
        for i, ph in enumerate(d.phasors):
            body += _encode_phasor(p, i, complex(ph))
        if p.freq_float:
            body += struct.pack('>ff', d.freq_hz, d.rocof_hz_per_s)
        else:
            body += struct.pack('>hh', _int16((d.freq_hz - p.nominal_hz) * 1000.0, p, 'FREQ'),
                                _int16(d.rocof_hz_per_s * 100.0, p, 'DFREQ'))
        for i, value in enumerate(d.analogs):
            body += struct.pack('>f', value) if p.analog_float else \
                struct.pack('>h', _int16(value / p.analog_scale(i), p, 'ANALOG'))
        for word in d.digitals:
            body += struct.pack('>H', word)
    return _frame(FRAME_DATA, cfg.idcode, frame.time, bytes(body), cfg.version)


def _int16(value: float, p: PmuConfig, what: str) -> int:
    """Round a value in field units to a 16-bit integer field; NaN or inf becomes the absent marker."""
    if not math.isfinite(value):
        return ABSENT_INT16
    counts = round(value)
    if not -0x7FFF <= counts <= 0x7FFF:
        raise C37118Error(f'PMU {p.station}: {what} {counts} does not fit a 16-bit integer field')
    return counts


def _encode_phasor(p: PmuConfig, i: int, ph: complex) -> bytes:
    absent = not (math.isfinite(ph.real) and math.isfinite(ph.imag))
    if p.phasor_float:
        if absent:
            return struct.pack('>ff', math.nan, math.nan)
        return struct.pack('>ff', abs(ph), math.atan2(ph.imag, ph.real)) if p.polar else \
            struct.pack('>ff', ph.real, ph.imag)
    scale = p.phasor_scale(i)
    if scale <= 0:
        raise C37118Error(f'PMU {p.station}: phasor {p.phasor_names[i]} is integer but its PHUNIT scale is 0')
    if p.polar:
        if absent:
            return struct.pack('>Hh', 0, ABSENT_INT16)
        magnitude = round(abs(ph) / scale)
        if magnitude > 0xFFFF:
            raise C37118Error(f'PMU {p.station}: phasor {p.phasor_names[i]} magnitude {abs(ph):.6g} exceeds the '
                              f'PHUNIT full scale {0xFFFF * scale:.6g}')
        return struct.pack('>Hh', magnitude, round(math.atan2(ph.imag, ph.real) * 1e4))
    if absent:
        return struct.pack('>hh', ABSENT_INT16, ABSENT_INT16)
    return struct.pack('>hh', _int16(ph.real / scale, p, f'phasor {p.phasor_names[i]} real part'),
                       _int16(ph.imag / scale, p, f'phasor {p.phasor_names[i]} imaginary part'))


def decode_data(raw: bytes, cfg: Config) -> DataFrame:
    """Parse a DATA frame laid out by cfg (the stream's latest CFG-2).

    Raises:
        C37118Error: Bad CHK, another frame type, or a size that does not match cfg.

    """
    frame_type, _version, idcode, time = check_frame(raw)
    if frame_type != FRAME_DATA:
        raise C37118Error(f'expected a DATA frame, got {FRAME_NAMES[frame_type]}')
    if len(raw) != cfg.data_bytes():
        raise C37118Error(f'DATA frame of {len(raw)} bytes; its configuration (CFGCNT '
                          f'{",".join(str(p.cfg_count) for p in cfg.pmus)}) makes {cfg.data_bytes()}: a new '
                          'configuration is needed')
    pos = _HEADER_BYTES
    blocks = []
    for p in cfg.pmus:
        (stat,) = struct.unpack_from('>H', raw, pos)
        pos += 2
        phasors = []
        for i in range(len(p.phasor_names)):
            if p.phasor_float:
                a, b = struct.unpack_from('>ff', raw, pos)
                pos += 8
                phasors.append(complex(a * math.cos(b), a * math.sin(b)) if p.polar else complex(a, b))
                continue
            scale = p.phasor_scale(i)
            if p.polar:
                magnitude, angle = struct.unpack_from('>Hh', raw, pos)
                value = complex(math.nan, math.nan) if angle == ABSENT_INT16 else \
                    magnitude * scale * complex(math.cos(angle * 1e-4), math.sin(angle * 1e-4))
            else:
                re, im = struct.unpack_from('>hh', raw, pos)
                value = complex(math.nan, math.nan) if ABSENT_INT16 in (re, im) else complex(re * scale, im * scale)
            pos += 4
            phasors.append(value)
        if p.freq_float:
            freq, dfreq = struct.unpack_from('>ff', raw, pos)
            pos += 8
        else:
            df_mhz, rocof_x100 = struct.unpack_from('>hh', raw, pos)
            pos += 4
            freq = math.nan if df_mhz == ABSENT_INT16 else p.nominal_hz + df_mhz * 1e-3
            dfreq = math.nan if rocof_x100 == ABSENT_INT16 else rocof_x100 * 1e-2
        analogs = []
        for i in range(len(p.analog_names)):
            if p.analog_float:
                analogs.append(struct.unpack_from('>f', raw, pos)[0])
                pos += 4
            else:
                (value,) = struct.unpack_from('>h', raw, pos)
                analogs.append(math.nan if value == ABSENT_INT16 else value * p.analog_scale(i))
                pos += 2
        digitals = struct.unpack_from(f'>{len(p.digital_units)}H', raw, pos)
        pos += 2 * len(p.digital_units)
        blocks.append(PmuData(stat, tuple(phasors), freq, dfreq, tuple(analogs), tuple(digitals)))
    return DataFrame(idcode, time, tuple(blocks))


# --------------------------------------------------------------------------------------- commands and header


def encode_command(cmd: Command, version: int = VERSION_2011) -> bytes:
    """Return the bytes of a COMMAND frame."""
    return _frame(FRAME_COMMAND, cmd.idcode, cmd.time, struct.pack('>H', cmd.command) + cmd.extended, version)


def decode_command(raw: bytes) -> Command:
    """Parse a COMMAND frame.

    Raises:
        C37118Error: Not a well-formed command frame.

    """
    frame_type, _version, idcode, time = check_frame(raw)
    if frame_type != FRAME_COMMAND:
        raise C37118Error(f'expected a COMMAND frame, got {FRAME_NAMES[frame_type]}')
    if len(raw) < _HEADER_BYTES + 4:
        raise C37118Error('COMMAND frame without a CMD word')
    (command,) = struct.unpack_from('>H', raw, _HEADER_BYTES)
    return Command(idcode, time, command, bytes(raw[_HEADER_BYTES + 2:-2]))


def encode_header(header: Header, version: int = VERSION_2011) -> bytes:
    """Return the bytes of a HEADER frame."""
    return _frame(FRAME_HEADER, header.idcode, header.time, header.text.encode('ascii', errors='replace'), version)


def decode_header(raw: bytes) -> Header:
    """Parse a HEADER frame."""
    frame_type, _version, idcode, time = check_frame(raw)
    if frame_type != FRAME_HEADER:
        raise C37118Error(f'expected a HEADER frame, got {FRAME_NAMES[frame_type]}')
    return Header(idcode, time, raw[_HEADER_BYTES:-2].decode('ascii', errors='replace'))
