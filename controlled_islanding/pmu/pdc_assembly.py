"""The PDC end of a C37.118.2 stream, without rclpy: channel map, DATA frames -> PmuMeasurement values, alignment.

Which phasor is the terminal voltage and which the current of which generator bus is never guessed: a channel
map file names, for each PMU station of the CFG-2 frame, the bus, the two channel names (CHNAM) and the base
voltage that turns volts and amperes back into per unit:

```yaml
# pdc_client channel map
base_mva: 100.0              # system MVA base: currents become pu on it
pmus:
  - station: PMU_30          # STN in the CFG-2 frame (or idcode: 7 to match the PMU's IDCODE instead)
    bus: 30                  # bus number in the network snapshot
    base_kv: 345.0           # bus base voltage, kV line to line
    voltage_channel: VPOS    # CHNAM of the positive-sequence terminal voltage phasor
    current_channel: IPOS    # CHNAM of the positive-sequence generator terminal current phasor
    current_direction: out   # 'out' of the generator into the grid (default) or 'in'
    station_id: PMU_30       # name on /pmu/frames (default: the station)
```

Quality (PmuMeasurement.stat is the PMU's STAT word, passed on, plus):
- a mapped phasor that is absent (NaN, or 0x8000 in an integer field) sets bits 15-14 to 10 ("do not use");
- a PMU whose time cannot be trusted within `max_time_error_s` sets bit 13 (sync error): the frame's message
  time quality (FRACSEC), the PMU's own time quality (STAT bits 8-6) or a lost lock (STAT bits 5-4) says so.
Data sorting (bit 12), trigger and configuration change bits are passed on as they came.

Angles arrive wrapped to +-pi; PmuMeasurement's are unwrapped, so each station's angles are unwrapped from
frame to frame (at 60 frames/s a phasor turns far less than pi between frames, even during a pole slip).
"""

from __future__ import annotations

import cmath
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from controlled_islanding.pmu import c37118

SQRT3 = math.sqrt(3.0)


class PdcAssemblyError(ValueError):
    """A channel map or a CFG-2 frame that cannot be used; the message names the file, station or channel."""


@dataclass(frozen=True)
class ChannelMapEntry:
    """Where one generator terminal's PMU data is in the stream, and how to turn it into per unit.

    Attributes:
        station: STN of the PMU in the CFG-2 frame ('' when matched by idcode).
        bus: Bus number of the generator terminal.
        base_kv: Bus base voltage, kV line to line.
        voltage_channel: CHNAM of the positive-sequence voltage phasor.
        current_channel: CHNAM of the positive-sequence current phasor.
        station_id: Name of the PMU on /pmu/frames.
        current_out: True when the current is measured out of the generator into the grid.
        idcode: Match the PMU block by IDCODE instead of STN (None: by STN).

    """

    station: str
    bus: int
    base_kv: float
    voltage_channel: str
    current_channel: str
    station_id: str
    current_out: bool = True
    idcode: int | None = None

    def matches(self, pmu: c37118.PmuConfig) -> bool:
        """Return True if this entry describes that PMU block of a CFG-2 frame."""
        return pmu.idcode == self.idcode if self.idcode is not None else pmu.station == self.station


@dataclass(frozen=True)
class ChannelMap:
    """The channel map file: the system MVA base and one entry per PMU."""

    base_mva: float
    pmus: tuple[ChannelMapEntry, ...]

    def to_yaml(self) -> str:
        """Return the map as the YAML that load_channel_map reads."""
        rows = []
        for e in self.pmus:
            row = {'station': e.station} if e.idcode is None else {'idcode': e.idcode}
            row.update({'bus': e.bus, 'base_kv': e.base_kv, 'voltage_channel': e.voltage_channel,
                        'current_channel': e.current_channel, 'current_direction': 'out' if e.current_out else 'in',
                        'station_id': e.station_id})
            rows.append(row)
        head = ('# pdc_client channel map (controlled_islanding/pmu/pdc_assembly.py): C37.118 channels -> generator '
                'buses\n')
        return head + yaml.safe_dump({'base_mva': self.base_mva, 'pmus': rows}, sort_keys=False)


def parse_channel_map(data: object, source: str = 'channel map') -> ChannelMap:
    """Check and return a channel map from parsed YAML.

    Raises:
        PdcAssemblyError: Names the source, the entry and the field that is wrong.

    """
    if not isinstance(data, Mapping) or not isinstance(data.get('pmus'), list) or not data['pmus']:
        raise PdcAssemblyError(f'{source}: needs base_mva and a non-empty list pmus (see pdc_assembly.py)')
    base_mva = _positive(data.get('base_mva'), f'{source}: base_mva')
    entries, seen_ids, seen_keys = [], set(), set()
    for k, row in enumerate(data['pmus']):
        where = f'{source}: pmus[{k}]'
        if not isinstance(row, Mapping):
            raise PdcAssemblyError(f'{where} is not a mapping')
        unknown = set(row) - {'station', 'idcode', 'bus', 'base_kv', 'voltage_channel', 'current_channel',
                              'current_direction', 'station_id'}
        if unknown:
            raise PdcAssemblyError(f'{where}: unknown keys {sorted(unknown)}')
        station, idcode = str(row.get('station', '')), row.get('idcode')
        if bool(station) == (idcode is not None):
            raise PdcAssemblyError(f'{where}: give exactly one of station (STN) or idcode')
        if idcode is not None and (not isinstance(idcode, int) or not 0 <= idcode <= 0xFFFF):
            raise PdcAssemblyError(f'{where}: idcode {idcode!r} is not a 16-bit integer')
        bus = row.get('bus')
        if not isinstance(bus, int) or bus <= 0:
            raise PdcAssemblyError(f'{where}: bus {bus!r} must be a positive integer bus number')
        channels = []
        for key in ('voltage_channel', 'current_channel'):
            if not isinstance(row.get(key), str) or not row[key]:
                raise PdcAssemblyError(f'{where}: {key} must name a CHNAM of the CFG-2 frame')
            channels.append(row[key])
        direction = row.get('current_direction', 'out')
        if direction not in ('out', 'in'):
            raise PdcAssemblyError(f'{where}: current_direction {direction!r} must be out or in')
        station_id = str(row.get('station_id') or station or f'idcode_{idcode}')
        key = station or idcode
        if station_id in seen_ids or key in seen_keys:
            raise PdcAssemblyError(f'{where}: station {key} / station_id {station_id} appears twice')
        seen_ids.add(station_id)
        seen_keys.add(key)
        entries.append(ChannelMapEntry(station, bus, _positive(row.get('base_kv'), f'{where}: base_kv'),
                                       channels[0], channels[1], station_id, direction == 'out', idcode))
    return ChannelMap(base_mva, tuple(entries))


def load_channel_map(path: str | Path) -> ChannelMap:
    """Read a channel map file.

    Raises:
        PdcAssemblyError: The file is missing, not YAML, or not a valid map.

    """
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise PdcAssemblyError(f'channel map {path}: cannot read it: {exc}') from exc
    return parse_channel_map(data, f'channel map {path}')


def _positive(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise PdcAssemblyError(f'{what} {value!r} must be a positive number')
    return float(value)


def volts_per_pu(base_kv: float) -> float:
    """Return the line-to-neutral volts of 1 pu on a bus of base_kv (line to line)."""
    return base_kv * 1e3 / SQRT3


def amperes_per_pu(base_mva: float, base_kv: float) -> float:
    """Return the amperes of 1 pu current on base_mva at base_kv."""
    return base_mva * 1e6 / (SQRT3 * base_kv * 1e3)


@dataclass
class Measurement:
    """One PMU's values as PmuMeasurement holds them (pu, rad unwrapped, Hz, Hz/s, STAT word)."""

    station_id: str
    bus: int
    voltage_magnitude_pu: float
    voltage_angle_rad: float
    current_magnitude_pu: float
    current_angle_rad: float
    frequency_hz: float
    rocof_hz_per_s: float
    stat: int


@dataclass(frozen=True)
class _Slot:
    block: int
    voltage: int
    current: int
    entry: ChannelMapEntry


@dataclass
class SourceLayout:
    """How one stream's CFG-2 maps onto the channel map."""

    config: c37118.Config
    slots: tuple[_Slot, ...]
    unmapped: tuple[str, ...]


class PdcAssembler:
    """Turns DATA frames of one or more streams into Measurements by the channel map.

    Args:
        channel_map: The map.
        max_time_error_s: A PMU whose claimed worst-case time error is larger is flagged STAT_SYNC_ERROR.

    """

    def __init__(self, channel_map: ChannelMap, max_time_error_s: float) -> None:
        self.map = channel_map
        self.max_time_error_s = max_time_error_s
        self.layouts: dict[str, SourceLayout] = {}
        self._last_angle: dict[tuple[str, int], float] = {}
        self.time_flagged = 0

    def configure(self, source: str, cfg: c37118.Config) -> SourceLayout:
        """Take a stream's CFG-2 frame; return what it maps.

        Raises:
            PdcAssemblyError: A mapped station names a channel the frame lacks, or a voltage channel whose
                PHUNIT says current (or the reverse).

        """
        slots, unmapped = [], []
        for b, pmu in enumerate(cfg.pmus):
            entry = next((e for e in self.map.pmus if e.matches(pmu)), None)
            if entry is None:
                unmapped.append(pmu.station)
                continue
            index = []
            for name, want_current in ((entry.voltage_channel, False), (entry.current_channel, True)):
                if name not in pmu.phasor_names:
                    raise PdcAssemblyError(f'{source}: PMU {pmu.station} (IDCODE {pmu.idcode}) has no phasor '
                                           f'channel {name!r}; its phasors are {list(pmu.phasor_names)}')
                i = pmu.phasor_names.index(name)
                if pmu.is_current(i) != want_current:
                    raise PdcAssemblyError(f'{source}: PMU {pmu.station} channel {name!r} is a '
                                           f'{"current" if pmu.is_current(i) else "voltage"} by its PHUNIT, but the '
                                           f'channel map names it as the {"current" if want_current else "voltage"}')
                index.append(i)
            slots.append(_Slot(b, index[0], index[1], entry))
        layout = SourceLayout(cfg, tuple(slots), tuple(unmapped))
        self.layouts[source] = layout
        return layout

    def missing_stations(self) -> list[str]:
        """Return the map's stations that no configured stream carries."""
        found = {s.entry.station_id for layout in self.layouts.values() for s in layout.slots}
        return [e.station_id for e in self.map.pmus if e.station_id not in found]

    def measurements(self, source: str, frame: c37118.DataFrame) -> tuple[int, list[Measurement]]:
        """Return (time tag, ns since the epoch; the mapped PMUs' measurements) of a DATA frame.

        Raises:
            PdcAssemblyError: The stream has not sent a CFG-2 frame yet.

        """
        layout = self.layouts.get(source)
        if layout is None:
            raise PdcAssemblyError(f'{source}: DATA frame before any CFG-2 frame')
        frame_error_s = frame.time.max_error_s
        out = []
        for slot in layout.slots:
            block = frame.pmus[slot.block]
            entry = slot.entry
            v = block.phasors[slot.voltage]
            i = block.phasors[slot.current] * (1 if entry.current_out else -1)
            stat = block.stat
            if not all(math.isfinite(x) for x in (v.real, v.imag, i.real, i.imag)) \
                    and stat & c37118.STAT_DATA_ERROR_MASK != c37118.STAT_DATA_ERROR_MASK:
                stat = (stat & ~c37118.STAT_DATA_ERROR_MASK) | c37118.STAT_DO_NOT_USE
            if self._time_untrusted(block.stat, frame_error_s):
                stat |= c37118.STAT_SYNC_ERROR
                self.time_flagged += 1
            out.append(Measurement(
                station_id=entry.station_id, bus=entry.bus,
                voltage_magnitude_pu=abs(v) / volts_per_pu(entry.base_kv),
                voltage_angle_rad=self._unwrap(entry.station_id, 0, v),
                current_magnitude_pu=abs(i) / amperes_per_pu(self.map.base_mva, entry.base_kv),
                current_angle_rad=self._unwrap(entry.station_id, 1, i),
                frequency_hz=block.freq_hz, rocof_hz_per_s=block.rocof_hz_per_s, stat=stat))
        return frame.time.ns(layout.config.time_base), out

    def _time_untrusted(self, stat: int, frame_error_s: float) -> bool:
        pmu_error_s = c37118.PMU_TIME_QUALITY_MAX_ERROR_S[(stat >> c37118.STAT_TIME_QUALITY_SHIFT) & 0x7]
        unlocked = (stat >> c37118.STAT_UNLOCKED_SHIFT) & 0x3
        return (frame_error_s > self.max_time_error_s or unlocked != 0
                or (pmu_error_s is not None and pmu_error_s > self.max_time_error_s))

    def _unwrap(self, station: str, which: int, phasor: complex) -> float:
        if not (math.isfinite(phasor.real) and math.isfinite(phasor.imag)):
            return math.nan
        raw = cmath.phase(phasor)
        last = self._last_angle.get((station, which))
        angle = raw if last is None else last + math.remainder(raw - last, 2 * math.pi)
        self._last_angle[(station, which)] = angle
        return angle


@dataclass
class _Pending:
    first_arrival_s: float
    sources: set[str] = field(default_factory=set)
    measurements: list[Measurement] = field(default_factory=list)


class TimeAligner:
    """Gathers the measurements of one time tag from several streams into one frame, as a PDC does.

    A time tag is emitted once every expected stream has sent it, or `wait_s` of wall time after its first
    part arrived, whichever comes first; older incomplete time tags are emitted before a newer one. A part that
    arrives for a time tag already emitted is late: counted and dropped (a repeated time tag, such as the
    repeated second of an inserted leap second, is also late).

    Args:
        wait_s: Longest wait for the other streams, s of wall time.

    """

    def __init__(self, wait_s: float) -> None:
        self.wait_s = wait_s
        self.expected: set[str] = set()
        self._pending: dict[int, _Pending] = {}
        self._newest_emitted_ns: int | None = None
        self._emitted_recent: set[int] = set()
        self.late = 0
        self.incomplete = 0

    def add(self, source: str, t_ns: int, measurements: Iterable[Measurement],
            now_s: float) -> list[tuple[int, list[Measurement]]]:
        """Add one stream's part of a time tag; return the frames now complete, oldest first."""
        if t_ns in self._emitted_recent or (self._newest_emitted_ns is not None and t_ns <= self._newest_emitted_ns
                                             and t_ns not in self._pending):
            self.late += 1
            return []
        pending = self._pending.setdefault(t_ns, _Pending(now_s))
        pending.sources.add(source)
        pending.measurements.extend(measurements)
        if self.expected <= pending.sources:
            return self._emit_through(t_ns)
        return self.due(now_s)

    def due(self, now_s: float) -> list[tuple[int, list[Measurement]]]:
        """Return the frames whose wait has run out (and any older ones), oldest first."""
        expired = [t for t, p in self._pending.items() if now_s - p.first_arrival_s >= self.wait_s]
        return self._emit_through(max(expired)) if expired else []

    def _emit_through(self, t_ns: int) -> list[tuple[int, list[Measurement]]]:
        out = []
        for t in sorted(t for t in self._pending if t <= t_ns):
            pending = self._pending.pop(t)
            if not self.expected <= pending.sources:
                self.incomplete += 1
            out.append((t, pending.measurements))
            self._emitted_recent.add(t)
            self._newest_emitted_ns = t if self._newest_emitted_ns is None else max(self._newest_emitted_ns, t)
        if len(self._emitted_recent) > 4096:  # memory stays bounded; older repeats are caught by the newest bound
            newest = sorted(self._emitted_recent)[-2048:]
            self._emitted_recent = set(newest)
        return out
