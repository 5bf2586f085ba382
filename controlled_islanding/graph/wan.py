"""An emulated wide-area network between the hosts of the node graph, built in user space.

Each host is a Linux network namespace of its own whose only interfaces are `lo` and a TUN device `wan0`. The
other end of every `wan0` is one emulator process (`python -m controlled_islanding.graph.wan`, `run_emulator`), which
reads each IPv4 packet a host sends and writes it into the destination host's `wan0` after a one-way delay with
jitter, or drops it (seeded Bernoulli loss per packet and destination). A packet to a multicast or broadcast
address (DDS discovery uses 239.255.0.1) is copied to every other host. This replaces `tc netem` on veth links,
which the kernel here does not offer (no sch_netem: "Specified qdisc kind is unknown"). A partition
(`set_partitions`, from any process: a file the emulator watches) drops every packet between two hosts, both
ways, until it is healed.

One host, `operator`, holds the replay's observer and recorder. What it sends (arming, probe requests) crosses the
WAN like any host's traffic, but what it receives is a monitoring tap: no delay and no loss, so that the latency
it measures from a request to a breaker command is the time between the two leaving their senders.

Addresses are from TEST-NET-1 (192.0.2.0/24, RFC 5737), which no real network routes, and no namespace has a
default route or any interface but its own two: nothing can leave the machine. Needs root (CAP_SYS_ADMIN and
CAP_NET_ADMIN), `ip` (iproute2) and /dev/net/tun; `unavailable_reason` says in one line what is missing.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import fcntl
import heapq
import json
import os
import random
import re
import select
import shutil
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from controlled_islanding import atomic
from controlled_islanding.graph import GraphError
from controlled_islanding.graph.processes import die_with_parent, sigterm_as_interrupt, status_field

# Which nodes run on which kind of host in a deployment: the PMU data concentrator's site, the control centre,
# and the substation that holds the breakers. The bag player stands in for the PDC's stream.
ROLES: dict[str, tuple[str, ...]] = {
    'pdc': ('pmu_ingestion', 'bag_player'),
    'control': ('coherency', 'partitioning', 'stability_monitor'),
    'substation': ('breaker_command',),
}
OPERATOR = 'operator'
SUBNET = '192.0.2'
DEVICE = 'wan0'
NAME_PREFIX = 'ciwan'  # namespaces are named ciwan<owner pid>-<host>
MTU = 1500
# What every DDS participant on an emulated host needs: discovery by multicast beyond loopback (the namespace has
# no interface outside the emulated WAN), and UDP only, so no two hosts can meet in shared memory.
DDS_ENVIRONMENT = {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET', 'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'}

_CLONE_NEWNET = 0x40000000
_TUNSETIFF = 0x400454CA
_IFF_TUN = 0x0001
_IFF_NO_PI = 0x1000
_CAP_NET_ADMIN = 12
_CAP_SYS_ADMIN = 21


class WanError(GraphError):
    """The emulated network could not be built or failed."""


@dataclass(frozen=True)
class LinkModel:
    """What the WAN does to each packet between two hosts, like netem's `delay D J loss L`.

    Attributes:
        delay_ms: One-way delay, ms.
        jitter_ms: Each packet's delay is uniform in delay_ms +- jitter_ms (at least 0), as netem's default;
            packets may therefore overtake each other, as under netem.
        loss_pct: Probability that a packet is dropped, % (independently per packet and destination).
        seed: Seed of the loss and jitter draws.

    """

    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss_pct: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.delay_ms < 0 or self.jitter_ms < 0 or not 0 <= self.loss_pct <= 100:
            raise ValueError(f'a link needs delay >= 0, jitter >= 0 and 0 <= loss <= 100 %, not {self}')


def parse_hosts(text: str) -> dict[str, tuple[str, ...]]:
    """Return host name -> roles from `--hosts`: comma-separated hosts, each one role or several joined by '+'.

    `pdc,control,substation` puts each role on a host of its own; `pdc+control,substation` puts the PDC beside the
    control centre. The host is named by its roles.

    Raises:
        ValueError: An unknown or repeated role, or one missing.

    """
    hosts: dict[str, tuple[str, ...]] = {}
    seen: list[str] = []
    for item in text.split(','):
        roles = tuple(r.strip() for r in item.split('+') if r.strip())
        if not roles:
            raise ValueError(f'--hosts {text!r}: an empty host')
        for role in roles:
            if role not in ROLES:
                raise ValueError(f'--hosts {text!r}: unknown role {role!r}; roles: {", ".join(ROLES)}')
            if role in seen:
                raise ValueError(f'--hosts {text!r}: role {role!r} is on two hosts')
            seen.append(role)
        hosts['+'.join(roles)] = roles
    missing = [r for r in ROLES if r not in seen]
    if missing:
        raise ValueError(f'--hosts {text!r}: no host runs {", ".join(missing)}')
    return hosts


def host_of(hosts: dict[str, tuple[str, ...]], executable: str) -> str:
    """Return the host that runs an executable; the operator's for any executable no role names (the recorder)."""
    for host, roles in hosts.items():
        if any(executable in ROLES[r] for r in roles):
            return host
    return OPERATOR


def unavailable_reason() -> str | None:
    """Return one line saying why the emulated WAN cannot be built here, or None if it can."""
    caps = int(status_field('self', 'CapEff') or '0', 16)
    if not (caps >> _CAP_SYS_ADMIN & 1 and caps >> _CAP_NET_ADMIN & 1):
        return ('the emulated WAN needs root (CAP_SYS_ADMIN and CAP_NET_ADMIN) for network namespaces and TUN '
                'devices; unprivileged user namespaces are not supported')
    if shutil.which('ip') is None:
        return 'the emulated WAN needs the ip command (iproute2) for network namespaces'
    if not Path('/dev/net/tun').exists():
        return 'the emulated WAN needs /dev/net/tun (the tun kernel module)'
    return None


def _setns(target: str | Path | int) -> None:
    """Move the calling thread into a network namespace, given by its file or an open descriptor of it."""
    fd = target if isinstance(target, int) else os.open(target, os.O_RDONLY)
    try:
        if ctypes.CDLL(None, use_errno=True).setns(fd, _CLONE_NEWNET) != 0:
            raise WanError(f'setns({target}): {os.strerror(ctypes.get_errno())}')
    finally:
        if fd is not target:
            os.close(fd)


def prefix(netns: str) -> list[str]:
    """Return the argv prefix that runs a command in a named network namespace."""
    return ['ip', 'netns', 'exec', netns]


def _ip(*args: str, netns: str | None = None, check: bool = True) -> str:
    argv = ['ip', *(['-n', netns] if netns else []), *args]
    done = subprocess.run(argv, capture_output=True, text=True, check=False)
    if check and done.returncode != 0:
        raise WanError(f'{" ".join(argv)}: {done.stderr.strip() or done.returncode}')
    return done.stdout


def our_namespaces() -> list[str]:
    """Return every network namespace this module made, by any process (named ciwan<pid>-<host>)."""
    return [n for n in (line.split()[0] for line in _ip('netns', 'list', check=False).splitlines() if line.strip())
            if re.fullmatch(rf'{NAME_PREFIX}\d+-[a-z+]+', n)]


def remove_namespace(netns: str) -> None:
    """Kill what still runs in one of our namespaces (only our processes can be there), then delete it."""
    for pid in _ip('netns', 'pids', netns, check=False).split():
        with contextlib.suppress(ProcessLookupError, ValueError):
            os.kill(int(pid), signal.SIGKILL)
    _ip('netns', 'delete', netns, check=False)


def sweep_stale() -> list[str]:
    """Delete namespaces left by a run of ours whose process is gone (it was SIGKILLed); return their names."""
    removed = []
    for netns in our_namespaces():
        owner = int(re.match(rf'{NAME_PREFIX}(\d+)-', netns).group(1))
        if not Path(f'/proc/{owner}').exists():
            remove_namespace(netns)
            removed.append(netns)
    return removed


def namespace_view(netns: str) -> dict[str, list[str]]:
    """Return a namespace's own interfaces and every route of every table, as `ip` prints them there."""
    links = [line.split(':')[1].strip().split('@')[0] for line in _ip('-o', 'link', 'show', netns=netns).splitlines()]
    routes = [line.strip() for line in _ip('route', 'show', 'table', 'all', netns=netns).splitlines() if line.strip()]
    routes6 = [line.strip() for line in _ip('-6', 'route', 'show', 'table', 'all', netns=netns).splitlines()
               if line.strip()]
    return {'interfaces': links, 'routes': routes, 'routes_ipv6': routes6}


def confined(view: dict[str, list[str]]) -> str | None:
    """Return why a namespace view could reach past the emulated WAN, or None if it cannot.

    Confined means: its interfaces are exactly lo and wan0, no IPv4 route names another device or a gateway, no
    default route, and no IPv6 route at all.
    """
    if sorted(view['interfaces']) != sorted(['lo', DEVICE]):
        return f'interfaces {view["interfaces"]}, not only lo and {DEVICE}'
    for route in view['routes']:
        words = route.split()
        dev = words[words.index('dev') + 1] if 'dev' in words else None
        if dev not in ('lo', DEVICE) or 'via' in words or words[0] == 'default':
            return f'route {route!r}'
    if view['routes_ipv6']:
        return f'IPv6 routes {view["routes_ipv6"]}'
    return None


class EmulatedWan:
    """The namespaces of the hosts plus the operator's, and the emulator joining them; `with` removes them all.

    Args:
        hosts: Host names (from parse_hosts); OPERATOR is added.
        link: What the WAN does to the packets between hosts.
        work_dir: Where the emulator's log and statistics go.

    """

    def __init__(self, hosts: Sequence[str], link: LinkModel, work_dir: Path) -> None:
        self.hosts = [*hosts, OPERATOR]
        self.link = link
        self.work_dir = Path(work_dir)
        self.namespaces = {h: f'{NAME_PREFIX}{os.getpid()}-{h}' for h in self.hosts}
        self.addresses = {h: f'{SUBNET}.{i + 1}' for i, h in enumerate(self.hosts)}
        self.views: dict[str, dict[str, list[str]]] = {}
        self.stats: dict = {}
        self.control_file = self.work_dir / 'wan_partitions.json'
        self._emulator: subprocess.Popen | None = None
        self._made: list[str] = []
        self._sigterm: contextlib.AbstractContextManager | None = None

    def __enter__(self) -> EmulatedWan:
        why = unavailable_reason()
        if why:
            raise WanError(why)
        sweep_stale()
        self.work_dir.mkdir(parents=True, exist_ok=True)
        # SIGTERM would end us without unwinding, leaving the namespaces mounted until a later sweep.
        self._sigterm = sigterm_as_interrupt()
        self._sigterm.__enter__()
        try:
            for host in self.hosts:
                _ip('netns', 'add', self.namespaces[host])
                self._made.append(self.namespaces[host])
            self._start_emulator()
            for host in self.hosts:
                self.views[host] = namespace_view(self.namespaces[host])
                why = confined(self.views[host])
                if why:
                    raise WanError(f'namespace {self.namespaces[host]} is not confined to the emulated WAN: {why}')
        except BaseException:
            self.__exit__()
            raise
        return self

    def _start_emulator(self) -> None:
        config = {'hosts': [{'name': h, 'netns': self.namespaces[h], 'address': self.addresses[h],
                             'tap': h == OPERATOR} for h in self.hosts],
                  'link': asdict(self.link), 'stats_file': str(self.work_dir / 'wan_stats.json'),
                  'control_file': str(self.control_file)}
        set_partitions(self.control_file, [])
        log = open(self.work_dir / 'wan_emulator.log', 'ab')
        self._emulator = subprocess.Popen(
            [sys.executable, '-m', 'controlled_islanding.graph.wan', json.dumps(config)], stdout=subprocess.PIPE,
            stderr=log, stdin=subprocess.DEVNULL, preexec_fn=die_with_parent)
        log.close()
        ready, _, _ = select.select([self._emulator.stdout], [], [], 30.0)
        line = self._emulator.stdout.readline() if ready else b''
        if line.strip() != b'ready':
            self._emulator.kill()
            self._emulator.wait()
            tail = (self.work_dir / 'wan_emulator.log').read_text(errors='replace').strip().splitlines()[-5:]
            raise WanError(f'the WAN emulator did not start: {" / ".join(tail) or "no output within 30 s"}')

    def check_alive(self) -> None:
        """Raise if the emulator has ended."""
        if self._emulator is not None and self._emulator.poll() is not None:
            raise WanError(f'the WAN emulator exited with status {self._emulator.returncode}; '
                           f'log {self.work_dir / "wan_emulator.log"}')

    def prefix(self, host: str) -> list[str]:
        """Return the argv prefix that runs a command on a host (in its namespace)."""
        return prefix(self.namespaces[host])

    def run_on_operator(self, argv: Sequence[str]) -> int:
        """Run a command on the operator's host until it ends, the emulator fails, or we are interrupted.

        The command is a fresh process: a DDS participant takes its network from the process it lives in, and one
        made earlier in this process (a test suite's, or a loopback run's) left Fast DDS sending the new one's
        traffic to loopback only. Returns its exit status.

        Raises:
            WanError: The emulator ended first (the command is stopped).

        """
        child = subprocess.Popen([*self.prefix(OPERATOR), *argv], stdin=subprocess.DEVNULL)
        try:
            while child.poll() is None:
                self.check_alive()
                time.sleep(0.2)
            return child.returncode
        finally:
            # Interrupted: a terminal's Ctrl-C reached the child too, and a second SIGINT could cut its clean-up
            # short, so it gets a moment first; a SIGTERM or an emulator failure reached only us.
            for action in (None, signal.SIGINT, signal.SIGKILL):
                if child.poll() is not None:
                    break
                if action is not None:
                    child.send_signal(action)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    child.wait(timeout=2.0 if action is None else 20.0)

    def __exit__(self, *exc_info: object) -> None:
        if self._emulator is not None:
            if self._emulator.poll() is None:
                self._emulator.send_signal(signal.SIGTERM)
                try:
                    self._emulator.wait(timeout=5.0)
                except subprocess.TimeoutExpired:
                    self._emulator.kill()
                    self._emulator.wait()
            self._emulator.stdout.close()
            stats_file = self.work_dir / 'wan_stats.json'
            if stats_file.exists():
                self.stats.update(json.loads(stats_file.read_text()))
            self._emulator = None
        for netns in reversed(self._made):
            remove_namespace(netns)
        self._made.clear()
        if self._sigterm is not None:
            self._sigterm.__exit__(None, None, None)
            self._sigterm = None


def set_partitions(control_file: Path, pairs: Sequence[tuple[str, str]]) -> None:
    """Cut the WAN between each pair of hosts (both ways), and heal every pair not named; [] heals them all.

    `control_file` is EmulatedWan.control_file; the emulator takes a change within about 50 ms.
    """
    atomic.write_text(Path(control_file), json.dumps({'partitions': [sorted(p) for p in pairs]}) + '\n')


# ----- the emulator process -----------------------------------------------------------------------------------


def _open_tun(netns: str, address: str) -> int:
    """Create wan0 inside a namespace, give it its address and routes, and return our end of it."""
    _setns(f'/run/netns/{netns}')
    fd = os.open('/dev/net/tun', os.O_RDWR | os.O_NONBLOCK)
    fcntl.ioctl(fd, _TUNSETIFF, struct.pack('16sH', DEVICE.encode(), _IFF_TUN | _IFF_NO_PI))
    # Commands started now run in this namespace too. IPv6 is switched off: its router and multicast listener
    # chatter is not part of the experiment, and DDS here speaks UDPv4.
    for argv in (['sysctl', '-qw', 'net.ipv6.conf.all.disable_ipv6=1'],
                 ['sysctl', '-qw', 'net.ipv6.conf.default.disable_ipv6=1'],
                 ['ip', 'link', 'set', 'lo', 'up'],
                 ['ip', 'link', 'set', DEVICE, 'mtu', str(MTU), 'multicast', 'on', 'up'],
                 ['ip', 'addr', 'add', f'{address}/24', 'dev', DEVICE],
                 ['ip', 'route', 'add', '224.0.0.0/4', 'dev', DEVICE]):
        subprocess.run(argv, check=True, capture_output=True)
    return fd


class _Emulator:
    def __init__(self, config: dict) -> None:
        self.link = LinkModel(**config['link'])
        self.rng = random.Random(self.link.seed)
        self.names = [h['name'] for h in config['hosts']]
        self.tap = {h['name'] for h in config['hosts'] if h['tap']}
        self.by_address = {socket_aton(h['address']): h['name'] for h in config['hosts']}
        self.broadcast = socket_aton(f'{SUBNET}.255')
        self.stats_file = Path(config['stats_file'])
        home = os.open('/proc/thread-self/ns/net', os.O_RDONLY)
        try:
            self.fds = {h['name']: _open_tun(h['netns'], h['address']) for h in config['hosts']}
        finally:
            _setns(home)
            os.close(home)
        self.host_of_fd = {fd: name for name, fd in self.fds.items()}
        self.queue: list[tuple[float, int, str, str, bytes]] = []
        self.seq = 0
        self.pairs: dict[str, dict[str, int]] = {}
        self.other = {'not_ipv4': 0, 'unroutable': 0, 'write_failed': 0}
        self.control_file = Path(config['control_file']) if config.get('control_file') else None
        self.control_mtime_ns = -1
        self.control_read_s = -1.0
        self.partitioned: set[frozenset[str]] = set()
        self.late_ms: list[float] = []
        self.stop = False

    def _pair(self, src: str, dst: str) -> dict[str, int]:
        return self.pairs.setdefault(f'{src}->{dst}', {'packets': 0, 'bytes': 0, 'dropped': 0, 'partitioned': 0})

    def read_control(self) -> None:
        """Take the partitions of the control file if it changed (a file replaced whole: atomic.write_text)."""
        now = time.monotonic()
        if self.control_file is None or now - self.control_read_s < 0.02:
            return
        self.control_read_s = now
        try:
            mtime_ns = self.control_file.stat().st_mtime_ns
            if mtime_ns == self.control_mtime_ns:
                return
            pairs = json.loads(self.control_file.read_text())['partitions']
        except (OSError, ValueError, KeyError):
            return
        self.control_mtime_ns = mtime_ns
        self.partitioned = {frozenset(p) for p in pairs}

    def receive(self, src: str, packet: bytes, now: float) -> None:
        if len(packet) < 20 or packet[0] >> 4 != 4:
            self.other['not_ipv4'] += 1
            return
        dst_addr = packet[16:20]
        if 224 <= dst_addr[0] <= 239 or dst_addr in (self.broadcast, b'\xff\xff\xff\xff'):
            targets = [n for n in self.names if n != src]
        elif dst_addr in self.by_address and self.by_address[dst_addr] != src:
            targets = [self.by_address[dst_addr]]
        else:
            self.other['unroutable'] += 1
            return
        link = self.link
        for dst in targets:
            pair = self._pair(src, dst)
            if frozenset((src, dst)) in self.partitioned:
                pair['partitioned'] += 1
                continue
            if dst in self.tap:
                due = now  # the operator's tap sees a packet as it leaves its sender
            else:
                if link.loss_pct and self.rng.random() * 100.0 < link.loss_pct:
                    pair['dropped'] += 1
                    continue
                jitter = self.rng.uniform(-link.jitter_ms, link.jitter_ms) if link.jitter_ms else 0.0
                due = now + max(0.0, link.delay_ms + jitter) / 1e3
            self.seq += 1
            heapq.heappush(self.queue, (due, self.seq, src, dst, packet))

    def deliver(self, now: float) -> None:
        while self.queue and self.queue[0][0] <= now:
            due, _, src, dst, packet = heapq.heappop(self.queue)
            try:
                os.write(self.fds[dst], packet)
            except OSError:
                self.other['write_failed'] += 1
                continue
            if len(self.late_ms) < 1_000_000:
                self.late_ms.append((now - due) * 1e3)
            pair = self.pairs[f'{src}->{dst}']
            pair['packets'] += 1
            pair['bytes'] += len(packet)

    def run(self) -> None:
        fds = list(self.host_of_fd)
        while not self.stop:
            now = time.monotonic()
            timeout = 0.05 if not self.queue else min(0.05, max(0.0, self.queue[0][0] - now))
            try:
                readable, _, _ = select.select(fds, [], [], timeout)
            except InterruptedError:
                continue
            now = time.monotonic()
            self.read_control()
            for fd in readable:
                src = self.host_of_fd[fd]
                for _ in range(64):  # drain a burst without starving the other hosts
                    try:
                        packet = os.read(fd, 65536)
                    except BlockingIOError:
                        break
                    self.receive(src, packet, now)
            self.deliver(time.monotonic())

    def write_stats(self) -> None:
        late = sorted(self.late_ms)

        def pct(q: float) -> float | None:
            return late[min(len(late) - 1, int(q / 100 * len(late)))] if late else None

        stats = {'link': asdict(self.link), 'pairs': self.pairs, **self.other,
                 'lateness_ms': {'n': len(late), 'median': pct(50), 'p99': pct(99), 'max': late[-1] if late else None}}
        atomic.write_text(self.stats_file, json.dumps(stats, indent=1))


def socket_aton(address: str) -> bytes:
    """Return an IPv4 address as its 4 bytes."""
    return bytes(int(x) for x in address.split('.'))


def run_emulator(config: dict) -> int:
    """Build every host's wan0 and forward packets between them until SIGTERM; then write the statistics."""
    emulator = _Emulator(config)
    # The kernel's netem runs in softirq context; a user-space stand-in that waits behind the busy node processes
    # for a time slice adds its own delay (measured as lateness_ms), so it takes the lowest real-time priority (it
    # sleeps in select between packets; the kernel's RT throttling still bounds it), else a high nice value.
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, -10)

    def stop(signum: int, frame: object) -> None:
        emulator.stop = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    print('ready', flush=True)
    try:
        emulator.run()
    finally:
        emulator.write_stats()
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the emulator process (started by EmulatedWan)."""
    parser = argparse.ArgumentParser(description='the emulated WAN between the host namespaces (internal)')
    parser.add_argument('config', help='JSON: hosts [{name, netns, address, tap}], link, stats_file, control_file')
    return run_emulator(json.loads(parser.parse_args(argv).config))


if __name__ == '__main__':
    sys.exit(main())
