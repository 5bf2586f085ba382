"""pdc_client: live C37.118.2 input. Connects to PMUs or a PDC over TCP and publishes time-aligned PmuFrames.

For each server in `servers` ('host:port' or 'host:port:idcode'; IDCODE 1 when not given) a thread connects,
asks for the CFG-2 frame, sends START and reads frames; a lost connection is retried every `reconnect_s`.
The CFG-2 frame gives the channel names, PHUNIT scaling and nominal frequency; `channel_map_file` says which
channels are the terminal voltage and current of which bus, and the base values back to per unit
(controlled_islanding/pmu/pdc_assembly.py). A STAT configuration-change bit, or a DATA frame that no longer
matches the configuration, makes it ask for the CFG-2 frame again.

Each DATA frame's PMUs are gathered with the other servers' data of the same time tag (at most `align_wait_s`
of wall time) and published on /pmu/frames as one PmuFrame stamped with the time tag (SOC + FRACSEC), so
the clock of the rest of the graph is the PMUs' own UTC. STAT is passed on; absent data and PMUs whose time
error may exceed `max_time_error_s` are flagged in it (pdc_assembly). The socket threads only parse; every
ROS call happens in the executor, woken by a guard condition.
"""

from __future__ import annotations

import queue
import socket
import sys
import threading
import time
from dataclasses import dataclass

from controlled_islanding_msgs.msg import PmuFrame, PmuMeasurement
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from controlled_islanding.pmu import c37118
from controlled_islanding.pmu.pdc_assembly import PdcAssembler, PdcAssemblyError, TimeAligner, load_channel_map
from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.params import NodeSetupError, declare_bounded
from controlled_islanding.ros.spin import spin_node
from controlled_islanding.wire import topics

_CONFIG_WAIT_S = 5.0  # ask again for CFG-2 after this long without one
_MAX_EVENTS = 10_000  # events waiting for the executor; beyond, the socket thread drops DATA frames


@dataclass(frozen=True)
class Server:
    """One TCP source: a PMU or a PDC."""

    host: str
    port: int
    idcode: int

    @property
    def name(self) -> str:
        """Return 'host:port', the source name in logs and diagnostics."""
        return f'{self.host}:{self.port}'


def parse_server(text: str) -> Server:
    """Parse 'host:port' or 'host:port:idcode'.

    Raises:
        NodeSetupError: Names the entry and what is wrong.

    """
    parts = text.strip().split(':')
    try:
        if len(parts) not in (2, 3) or not parts[0]:
            raise ValueError('expected host:port or host:port:idcode')
        port, idcode = int(parts[1]), int(parts[2]) if len(parts) == 3 else 1
        if not 0 < port <= 65535 or not 0 <= idcode <= 0xFFFF:
            raise ValueError('port must be 1-65535 and idcode 0-65535')
    except ValueError as exc:
        raise NodeSetupError(f'servers entry {text!r}: {exc}') from exc
    return Server(parts[0], port, idcode)


class _Connection(threading.Thread):
    """Reads one server's frames into the node's event queue; reconnects until stopped."""

    def __init__(self, server: Server, events: queue.Queue, wake, reconnect_s: float, timeout_s: float) -> None:
        super().__init__(name=f'c37118 {server.name}', daemon=True)
        self.server, self.events, self.wake = server, events, wake
        self.reconnect_s, self.timeout_s = reconnect_s, timeout_s
        self.stopping = threading.Event()
        self.sock: socket.socket | None = None
        self.dropped = 0

    def post(self, *event: object) -> None:
        if event[0] == 'data' and self.events.qsize() >= _MAX_EVENTS:
            self.dropped += 1  # the executor is far behind; a late frame is useless live
            return
        self.events.put(event)
        self.wake()

    def command(self, code: int) -> None:
        assert self.sock is not None
        self.sock.sendall(c37118.encode_command(c37118.Command(
            self.server.idcode, c37118.TimeTag.from_ns(time.time_ns(), 1_000_000), code)))

    def run(self) -> None:
        while not self.stopping.is_set():
            try:
                self._session()
            except (OSError, c37118.C37118Error) as exc:
                self.post('down', self.server.name, f'{type(exc).__name__}: {exc}')
            finally:
                if self.sock is not None:
                    self.sock.close()
                    self.sock = None
            self.stopping.wait(self.reconnect_s)

    def _session(self) -> None:
        self.sock = socket.create_connection((self.server.host, self.server.port), timeout=self.timeout_s)
        self.sock.settimeout(0.2)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        splitter = c37118.FrameSplitter()
        config: c37118.Config | None = None
        self.command(c37118.CMD_CFG2)
        asked_s = time.monotonic()
        while not self.stopping.is_set():
            if config is None and time.monotonic() - asked_s > _CONFIG_WAIT_S:
                self.command(c37118.CMD_CFG2)
                asked_s = time.monotonic()
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            if not data:
                raise OSError('the server closed the connection')
            arrived_s = time.monotonic()
            for raw in splitter.feed(data):
                config = self._frame(raw, config, arrived_s)
                if config is None:
                    asked_s = time.monotonic()
            if splitter.skipped_bytes:
                self.post('skipped', self.server.name, splitter.skipped_bytes)
                splitter.skipped_bytes = 0

    def _frame(self, raw: bytes, config: c37118.Config | None, arrived_s: float) -> c37118.Config | None:
        try:
            kind = c37118.check_frame(raw)[0]
            if kind in (c37118.FRAME_CFG2, c37118.FRAME_CFG1):
                fresh = c37118.decode_config(raw)
                self.post('config', self.server.name, fresh)
                if config is None:
                    self.command(c37118.CMD_START)
                return fresh
            if kind != c37118.FRAME_DATA:
                return config
            if config is None:
                self.post('bad', self.server.name, 'DATA frame before the CFG-2 frame; dropped')
                return config
            frame = c37118.decode_data(raw, config)
        except c37118.C37118Error as exc:
            self.post('bad', self.server.name, str(exc))
            if config is not None and 'new configuration' in str(exc):
                self.command(c37118.CMD_CFG2)
                return None
            return config
        self.post('data', self.server.name, frame, arrived_s)
        if any(p.stat & c37118.STAT_CONFIG_CHANGE for p in frame.pmus):
            self.command(c37118.CMD_CFG2)  # the configuration changes within a minute: fetch it again
        return config


class PdcClientNode(Node):
    """Reads C37.118.2 streams and publishes PmuFrames."""

    def __init__(self) -> None:
        super().__init__('pdc_client')
        self.declare_parameter('servers', [''])
        self.declare_parameter('channel_map_file', '')
        self.declare_parameter('frame_id', 'pdc_client')
        servers = [parse_server(s) for s in self.get_parameter('servers').value if s.strip()]
        if not servers:
            raise NodeSetupError("parameter servers is empty; give ['host:port'] or ['host:port:idcode', ...]")
        map_file = self.get_parameter('channel_map_file').value
        if not map_file:
            raise NodeSetupError('parameter channel_map_file is empty: it must name the YAML file that maps PMU '
                                 'channels to generator buses (see controlled_islanding/pmu/pdc_assembly.py)')
        try:
            channel_map = load_channel_map(map_file)
        except PdcAssemblyError as exc:
            raise NodeSetupError(str(exc)) from exc
        self.frame_id = str(self.get_parameter('frame_id').value)
        max_time_error_s = float(declare_bounded(
            self, 'max_time_error_s', 1e-4, 0.0, 10.0,
            'a PMU whose time may be off by more than this, s (FRACSEC or STAT time quality, lost lock), gets '
            'STAT bit 13 (sync error) on /pmu/frames; 1e-4 s is 2.2 degrees at 60 Hz'))
        align_wait_s = float(declare_bounded(
            self, 'align_wait_s', 0.1, 0.0, 10.0,
            'wall time to wait for the other servers data of a time tag before publishing without it, s'))
        reconnect_s = float(declare_bounded(self, 'reconnect_s', 1.0, 0.05, 600.0,
                                            'wait before reconnecting to a server, s'))
        connect_timeout_s = float(declare_bounded(self, 'connect_timeout_s', 2.0, 0.1, 60.0,
                                                  'TCP connect timeout, s'))
        self.assembler = PdcAssembler(channel_map, max_time_error_s)
        self.aligner = TimeAligner(align_wait_s)
        self.diag = Diagnostics(self)
        self.pub = self.create_publisher(PmuFrame, topics.relative(topics.PMU_FRAMES), qos_for(topics.PMU_FRAMES))
        self.events: queue.Queue = queue.Queue()
        self.published = 0
        self.newest_ns = 0
        self.connected: set[str] = set()
        self.wake = self.create_guard_condition(self.diag.guard(self.drain))
        # Parts waiting for other servers are published when their wait runs out, even if no frame comes.
        self.create_timer(max(align_wait_s / 2, 0.01), self.diag.guard(self._flush),
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.connections = [_Connection(s, self.events, self.wake.trigger, reconnect_s, connect_timeout_s)
                            for s in servers]
        # Frames published before DDS has matched a reader are lost to it (the topic is volatile): connecting,
        # and so START, can wait for the readers a replay or test expects. Live, nothing waits by default.
        self.min_readers = int(declare_bounded(
            self, 'wait_for_subscribers', 0, 0, 1000,
            'connect only once /pmu/frames has this many readers (or wait_for_subscribers_s has passed)'))
        self.start_deadline_s = time.monotonic() + float(declare_bounded(
            self, 'wait_for_subscribers_s', 10.0, 0.0, 3600.0, 'longest wait for those readers, s'))
        self.starter = self.create_timer(0.05, self.diag.guard(self._start_when_read),
                                         clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f'reading {", ".join(s.name for s in servers)}; {len(channel_map.pmus)} PMUs mapped '
                               f'by {map_file}')

    def _start_when_read(self) -> None:
        readers = self.pub.get_subscription_count()
        if readers < self.min_readers and time.monotonic() < self.start_deadline_s:
            return
        self.starter.cancel()
        if readers < self.min_readers:
            self.get_logger().warning(f'connecting with {readers} of {self.min_readers} readers of /pmu/frames')
        for c in self.connections:
            c.start()

    def drain(self) -> None:
        """Handle every event the socket threads queued: configurations, frames, errors."""
        while True:
            try:
                event = self.events.get_nowait()
            except queue.Empty:
                break
            kind, source = event[0], event[1]
            if kind == 'config':
                self._configure(source, event[2])
            elif kind == 'data':
                self.diag.arrived()
                self._data(source, event[2], event[3])
            elif kind == 'bad':
                self.diag.reject('bad_frame', f'{source}: {event[2]}')
            elif kind == 'skipped':
                self.diag.reject('bad_frame', f'{source}: {event[2]} bytes that start no frame were skipped')
            elif kind == 'down':
                self.connected.discard(source)
                self.aligner.expected.discard(source)
                self.diag.fault(f'connection.{source}', event[2])
        self._values()

    def _configure(self, source: str, cfg: c37118.Config) -> None:
        try:
            layout = self.assembler.configure(source, cfg)
        except PdcAssemblyError as exc:
            self.diag.fault(f'config.{source}', str(exc))
            self.assembler.layouts.pop(source, None)
            return
        self.diag.fault(f'config.{source}', None)
        self.diag.fault(f'connection.{source}', None)
        self.connected.add(source)
        self.aligner.expected.add(source)
        pmus = len(cfg.pmus)
        self.get_logger().info(
            f'{source}: CFG-2 IDCODE {cfg.idcode}, {pmus} PMUs, {cfg.frames_per_s:g} frames/s, nominal '
            f'{sorted({p.nominal_hz for p in cfg.pmus})} Hz; {len(layout.slots)} mapped'
            + (f', not in the channel map: {", ".join(layout.unmapped)}' if layout.unmapped else ''))

    def _data(self, source: str, frame: c37118.DataFrame, arrived_s: float) -> None:
        t0 = time.perf_counter()
        if source not in self.assembler.layouts:
            self.diag.reject('no_config', f'{source}: DATA frame while its CFG-2 frame is unusable')
            return
        t_ns, measurements = self.assembler.measurements(source, frame)
        if frame.time.leap_pending or frame.time.leap_occurred:
            self.diag.values['leap_second'] = 'pending' if frame.time.leap_pending else 'occurred in the last 24 h'
        late = self.aligner.late
        for stamp_ns, parts in self.aligner.add(source, t_ns, measurements, arrived_s):
            self._publish(stamp_ns, parts)
        if self.aligner.late > late:
            self.diag.reject('late', f'{source}: data for time tag {t_ns * 1e-9:.6f} s came after that time tag '
                                     'was published (or repeats it)')
        self.diag.computed(time.perf_counter() - t0)

    def _flush(self) -> None:
        for stamp_ns, parts in self.aligner.due(time.monotonic()):
            self._publish(stamp_ns, parts)

    def _publish(self, stamp_ns: int, parts: list) -> None:
        msg = PmuFrame()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        msg.header.frame_id = self.frame_id
        msg.measurements = [PmuMeasurement(
            station_id=m.station_id, bus=m.bus, voltage_magnitude_pu=m.voltage_magnitude_pu,
            voltage_angle_rad=m.voltage_angle_rad, current_magnitude_pu=m.current_magnitude_pu,
            current_angle_rad=m.current_angle_rad, frequency_hz=float(m.frequency_hz),
            rocof_hz_per_s=float(m.rocof_hz_per_s), stat=m.stat) for m in parts]
        self.pub.publish(msg)
        self.published += 1
        self.newest_ns = max(self.newest_ns, stamp_ns)

    def _values(self) -> None:
        v = self.diag.values
        v['servers_connected'] = str(len(self.connected))
        v['frames_published'] = str(self.published)
        v['newest_time_tag_s'] = f'{self.newest_ns * 1e-9:.6f}'
        v['incomplete_frames'] = str(self.aligner.incomplete)
        v['time_quality_flagged'] = str(self.assembler.time_flagged)
        v['dropped_overloaded'] = str(sum(c.dropped for c in self.connections))
        missing = self.assembler.missing_stations()
        v['stations_missing'] = ','.join(missing) if len(missing) <= 50 else f'{len(missing)} stations'

    def close(self) -> None:
        """Stop the socket threads (spin_node calls this on shutdown)."""
        for c in self.connections:
            c.stopping.set()
            try:
                if c.sock is not None:
                    c.command(c37118.CMD_STOP)
            except OSError:
                pass
        for c in self.connections:
            if c.is_alive():
                c.join(timeout=1.0)


def main(args: list[str] | None = None) -> int:
    """Run the pdc_client node."""
    return spin_node(PdcClientNode, args)


if __name__ == '__main__':
    sys.exit(main())
