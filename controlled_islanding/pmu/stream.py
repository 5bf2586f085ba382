"""A bag's PMU frames as a C37.118.2 PMU/PDC TCP server (no rclpy): the logic behind `controlled-islanding serve-pmu`.

The stream is one PDC data stream: one PMU block per station of the bag (in order of first appearance), each
with two phasors, VPOS (terminal voltage, volts line to neutral) and IPOS (generator current out of the
machine, amperes), FREQ and DFREQ. The bag's per-unit values become volts and amperes with `base_kv` and the
snapshot's MVA base; `ChannelMap` (pdc_assembly) written beside it tells a PDC which channel is which.

Time: every DATA frame carries the bag frame's own time tag (header.stamp) as SOC and FRACSEC, rounded to
1/TIME_BASE s, and is sent at the bag frame's log time (its arrival in the recording) divided by `rate`,
counted from the client's START command. A station absent from a bag frame is sent with STAT 0x8000 (absent
data inserted) and NaN (float) or 0x8000 (integer) values; a frame absent from the bag is never sent.

Protocol: a client sends COMMAND frames; CFG-2 (and CFG-1) gets the configuration, HEADER a text, START
starts this connection's playback from the bag's first frame, STOP pauses it (the playback clock runs on,
frames due meanwhile are skipped, as a live PMU's would be). Each connection has its own playback. Commands
addressed to another IDCODE are ignored.
"""

from __future__ import annotations

import math
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from controlled_islanding.pmu import c37118
from controlled_islanding.pmu.pdc_assembly import ChannelMap, ChannelMapEntry, amperes_per_pu, volts_per_pu
from controlled_islanding.wire import topics
from controlled_islanding.wire.bagmeta import unreadable

VOLTAGE_CHANNEL = 'VPOS'
CURRENT_CHANNEL = 'IPOS'
_INT_HEADROOM = 1.25  # integer full scale = this x the largest magnitude in the bag
_RECV_BYTES = 65536
_INT_FREQ_SPAN_HZ = 32.767  # 16-bit FREQ: +-32767 mHz off nominal
_INT_ROCOF_SPAN_HZ_PER_S = 327.67  # 16-bit DFREQ: +-32767 x 0.01 Hz/s


class PmuStreamError(RuntimeError):
    """The bag cannot be served (unreadable, no PMU frames, names too long) or the server cannot listen."""


@dataclass(frozen=True)
class BagStream:
    """Everything the server sends, encoded once.

    Attributes:
        config: The CFG-2 configuration.
        config_bytes: Its frame.
        frames: (send offset from START, s of bag log time; DATA frame bytes), in log time order.
        channel_map: What a PDC needs to map the stream back to buses and per unit.
        header_text: The HEADER frame's text.

    """

    config: c37118.Config
    config_bytes: bytes
    frames: tuple[tuple[float, bytes], ...]
    channel_map: ChannelMap
    header_text: str


def load_bag_stream(bag: str | Path, *, idcode: int = 1, base_kv: float = 345.0, integer: bool = False,
                    time_base: int = 1_000_000, stations: tuple[str, ...] = ()) -> BagStream:
    """Read a bag's /pmu/frames and /network/snapshot and encode the C37.118 stream.

    Args:
        bag: The rosbag2 bag.
        idcode: IDCODE of the data stream; PMU blocks get 1000 + their index.
        base_kv: Base voltage of every PMU bus, kV line to line (the bags hold per unit only).
        integer: 16-bit integer phasors (scaled by PHUNIT) and FREQ; else 32-bit floats.
        time_base: TIME_BASE, fractions of a second in FRACSEC.
        stations: Serve only these stations (all when empty), e.g. to play several PMUs from several servers.

    Raises:
        PmuStreamError: Names the bag and what is missing.

    """
    from rosbags.highlevel import AnyReader

    from controlled_islanding.wire.interfaces import typestore

    frames, base_mva = [], None
    try:
        with AnyReader([Path(bag)], default_typestore=typestore()) as reader:
            chosen = [c for c in reader.connections if c.topic in (topics.PMU_FRAMES, topics.NETWORK_SNAPSHOT)]
            for conn, log_ns, raw in reader.messages(connections=chosen):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == topics.NETWORK_SNAPSHOT:
                    base_mva = base_mva or float(msg.base_mva)
                else:
                    frames.append((log_ns, msg))
    except Exception as exc:  # rosbags raises many error types for an unreadable bag
        raise PmuStreamError(f'cannot read the bag: {unreadable(bag, exc)}') from exc
    if not frames:
        raise PmuStreamError(f'bag {bag}: no messages on {topics.PMU_FRAMES}')
    if not base_mva or base_mva <= 0:
        raise PmuStreamError(f'bag {bag}: no {topics.NETWORK_SNAPSHOT} with a positive base_mva; currents '
                             'cannot be turned into amperes')
    order: dict[str, int] = {}
    bus: dict[str, int] = {}
    peak_v, peak_i, freqs = {}, {}, []
    for _, msg in frames:
        for m in msg.measurements:
            if stations and m.station_id not in stations:
                continue
            order.setdefault(m.station_id, len(order))
            bus.setdefault(m.station_id, int(m.bus))
            if math.isfinite(m.voltage_magnitude_pu) and math.isfinite(m.current_magnitude_pu):
                # abs: bags simulated before sim/pmu.py turned the phasor carry ANDES' V < 0; the wire's is not.
                peak_v[m.station_id] = max(peak_v.get(m.station_id, 0.0), abs(m.voltage_magnitude_pu))
                peak_i[m.station_id] = max(peak_i.get(m.station_id, 0.0), abs(m.current_magnitude_pu))
            if math.isfinite(m.frequency_hz):
                freqs.append(m.frequency_hz)
    missing = set(stations) - set(order)
    if missing or not order:
        raise PmuStreamError(f'bag {bag}: no PMU station {sorted(missing) or ""} in {topics.PMU_FRAMES}')
    nominal = 50 if freqs and sorted(freqs)[len(freqs) // 2] < 55.0 else 60
    v_base, i_base = volts_per_pu(base_kv), amperes_per_pu(base_mva, base_kv)
    pmus = []
    for k, name in enumerate(order):
        if len(name.encode('ascii', errors='replace')) > 16:
            raise PmuStreamError(f'bag {bag}: station name {name!r} is longer than the 16 characters STN allows')
        # Integer phasors: PHUNIT chosen so the largest magnitude in the bag uses 80 % of the 16-bit range.
        v_scale = max(peak_v.get(name, 1.0), 1e-3) * v_base * _INT_HEADROOM / 0xFFFF
        i_scale = max(peak_i.get(name, 1.0), 1e-3) * i_base * _INT_HEADROOM / 0xFFFF
        pmus.append(c37118.PmuConfig(
            station=name, idcode=1000 + k, polar=True, phasor_float=not integer, analog_float=not integer,
            freq_float=not integer, phasor_names=(VOLTAGE_CHANNEL, CURRENT_CHANNEL),
            phasor_units=(c37118.phunit(v_scale if integer else 0.0, False),
                          c37118.phunit(i_scale if integer else 0.0, True)),
            nominal_hz=nominal, cfg_count=1))
    first_log_ns = frames[0][0]
    first_tag = c37118.TimeTag.from_ns(_stamp_ns(frames[0][1]), time_base)
    rate = _frames_per_s([_stamp_ns(m) for _, m in frames[:100]])
    config = c37118.Config(idcode, first_tag, time_base, tuple(pmus), rate)
    encoded = []
    for log_ns, msg in frames:
        by_station = {m.station_id: m for m in msg.measurements}
        blocks = []
        for p in pmus:
            m = by_station.get(p.station)
            if m is None:
                blocks.append(c37118.PmuData(c37118.STAT_DO_NOT_USE, (complex(math.nan, math.nan),) * 2, math.nan,
                                             math.nan))
                continue
            v = m.voltage_magnitude_pu * v_base * complex(math.cos(m.voltage_angle_rad), math.sin(m.voltage_angle_rad))
            i = m.current_magnitude_pu * i_base * complex(math.cos(m.current_angle_rad), math.sin(m.current_angle_rad))
            freq, rocof = m.frequency_hz, m.rocof_hz_per_s
            if integer:
                # 16-bit FREQ (mHz off nominal) and DFREQ (x100) saturate, as a device's would: a fault's
                # ROCOF of hundreds of Hz/s in a simulation is beyond +-327.67 Hz/s.
                freq = nominal + min(max(freq - nominal, -_INT_FREQ_SPAN_HZ), _INT_FREQ_SPAN_HZ)
                rocof = min(max(rocof, -_INT_ROCOF_SPAN_HZ_PER_S), _INT_ROCOF_SPAN_HZ_PER_S)
            blocks.append(c37118.PmuData(int(m.stat), (v, i), freq, rocof))
        frame = c37118.DataFrame(idcode, c37118.TimeTag.from_ns(_stamp_ns(msg), time_base), tuple(blocks))
        try:
            encoded.append(((log_ns - first_log_ns) * 1e-9, c37118.encode_data(frame, config)))
        except c37118.C37118Error as exc:
            raise PmuStreamError(f'bag {bag}: frame at {_stamp_ns(msg) * 1e-9:.3f} s: {exc}') from exc
    channel_map = ChannelMap(base_mva, tuple(
        ChannelMapEntry(p.station, bus[p.station], base_kv, VOLTAGE_CHANNEL, CURRENT_CHANNEL, p.station)
        for p in pmus))
    header = (f'controlled-islanding serve-pmu: bag {Path(bag).name}, {len(pmus)} PMUs, {len(encoded)} frames at '
              f'{rate} frames/s; phasors {"16-bit integer" if integer else "float"}, V line-to-neutral and A, '
              f'base {base_kv} kV, {base_mva} MVA')
    return BagStream(config, c37118.encode_config(config), tuple(encoded), channel_map, header)


def _stamp_ns(msg: object) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _frames_per_s(stamps_ns: list[int]) -> int:
    steps = sorted(b - a for a, b in zip(stamps_ns, stamps_ns[1:], strict=False) if b > a)
    if not steps:
        return 1
    return max(1, round(1e9 / steps[len(steps) // 2]))


class PmuServer:
    """Serves a BagStream to every client that connects; `with PmuServer(...) as s:` closes every socket.

    Args:
        stream: What to serve.
        host: Address to listen on (127.0.0.1 keeps it on this machine).
        port: TCP port; 0 picks a free one (see `port` after start).
        rate: Playback speed against the bag's timing (2.0 = twice as fast).
        log: Called with one line per event (connection, command, end of stream).

    """

    def __init__(self, stream: BagStream, host: str = '127.0.0.1', port: int = 4712, rate: float = 1.0,
                 log: Callable[[str], None] = print) -> None:
        if rate <= 0:
            raise PmuStreamError(f'rate {rate} must be positive')
        self.stream, self.rate, self.log = stream, rate, log
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self.streams_completed = 0
        try:
            self._listener = socket.create_server((host, port))
        except OSError as exc:
            raise PmuStreamError(f'cannot listen on {host}:{port}: {exc}') from exc
        self.host, self.port = self._listener.getsockname()[:2]

    def __enter__(self) -> PmuServer:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop accepting, end every connection, wait for their threads."""
        self._stop.set()
        self._listener.close()
        for thread in self._threads:
            thread.join(timeout=2.0)

    def serve(self, until: Callable[[], bool] = lambda: False) -> None:
        """Accept clients until close() or until() is true (checked every 0.2 s)."""
        self._listener.settimeout(0.2)
        while not self._stop.is_set() and not until():
            try:
                conn, peer = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            thread = threading.Thread(target=self._client, args=(conn, f'{peer[0]}:{peer[1]}'), daemon=True)
            self._threads = [t for t in self._threads if t.is_alive()] + [thread]
            thread.start()

    def _client(self, conn: socket.socket, peer: str) -> None:
        self.log(f'{peer}: connected')
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        splitter = c37118.FrameSplitter()
        frames = self.stream.frames
        start: float | None = None  # monotonic time of the START command; None: not streaming
        paused = False
        nxt = 0
        try:
            with conn:
                while not self._stop.is_set():
                    if start is not None and nxt < len(frames):
                        timeout = max(0.0, start + frames[nxt][0] / self.rate - time.monotonic())
                    else:
                        timeout = 0.2
                    readable, _, _ = select.select([conn], [], [], min(timeout, 0.2))
                    if readable:
                        data = conn.recv(_RECV_BYTES)
                        if not data:
                            self.log(f'{peer}: closed by the client')
                            return
                        for raw in splitter.feed(data):
                            start, paused = self._command(conn, peer, raw, start, paused)
                            if start is not None and not paused and nxt >= len(frames):
                                nxt = 0  # a START after the end plays the bag again
                    if start is None:
                        continue
                    now = time.monotonic()
                    while nxt < len(frames) and start + frames[nxt][0] / self.rate <= now:
                        if not paused:
                            conn.sendall(frames[nxt][1])
                        nxt += 1
                    if nxt >= len(frames) and start is not None:
                        self.log(f'{peer}: stream complete, {len(frames)} frames')
                        with self._lock:
                            self.streams_completed += 1
                        start = None
        except OSError as exc:
            self.log(f'{peer}: connection ended: {exc}')

    def _command(self, conn: socket.socket, peer: str, raw: bytes, start: float | None,
                 paused: bool) -> tuple[float | None, bool]:
        try:
            cmd = c37118.decode_command(raw)
        except c37118.C37118Error as exc:
            self.log(f'{peer}: ignored a frame that is not a valid command: {exc}')
            return start, paused
        if cmd.idcode != self.stream.config.idcode:
            self.log(f'{peer}: ignored a command for IDCODE {cmd.idcode}; this stream is {self.stream.config.idcode}')
            return start, paused
        if cmd.command in (c37118.CMD_CFG2, c37118.CMD_CFG1):
            conn.sendall(self.stream.config_bytes)
        elif cmd.command == c37118.CMD_HEADER:
            conn.sendall(c37118.encode_header(c37118.Header(self.stream.config.idcode, self.stream.config.time,
                                                            self.stream.header_text)))
        elif cmd.command == c37118.CMD_START:
            self.log(f'{peer}: START')
            return (time.monotonic() if start is None else start), False
        elif cmd.command == c37118.CMD_STOP:
            self.log(f'{peer}: STOP')
            return start, True
        else:
            self.log(f'{peer}: ignored command {cmd.command}')
        return start, paused
