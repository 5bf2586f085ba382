"""One fault in a closed-loop run, at a seeded time near the islanding request: which fault, and doing it.

`plan_fault(seed, hosts)` draws the fault from the seed alone, so one seed is the same fault on every system:
- `kill`: SIGKILL of one pipeline node; the supervisor restarts it (graph/watchdog.py, PIPELINE_POLICY).
- `stop`: SIGSTOP of one pipeline node, SIGCONT after a seeded pause. A pause past the watchdog's hang_timeout_s
  (10 s) ends in the supervisor killing the stopped node and starting it again, before the SIGCONT would come.
- `partition` (emulated hosts only): the WAN between the control-centre host and the substation host is cut both
  ways for a seeded time, then healed (graph/wan.py set_partitions).
- `clock_step`: one node's sim clock (on emulated hosts: the clock of every node of one host) steps by a seeded
  amount, back or ahead, and stays stepped: those nodes hear /clock through a relay in the observer's process
  that adds the step from the fault on (before it, the relay passes /clock through unchanged).

The fault fires when the graph's /clock, as the observer hears it, reaches the request's time plus a seeded offset
within +-1 s. In lockstep (testbed's default) sim time stands at the request while the graph works, so a fault
with a positive offset lands after the decision and its commands; with --rate it lands while the graph works.

Only processes this run started are signalled, by the PID the supervisor holds.
"""

from __future__ import annotations

import os
import random
import signal
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from controlled_islanding.graph import GraphError, wan
from controlled_islanding.graph.supervisor import GRAPH, PIPELINE_POLICY

KINDS = ('kill', 'stop', 'clock_step', 'partition')
TARGETS = tuple(spec.executable for spec in GRAPH)
OFFSET_S = 1.0
# Both span the limit that changes what follows: the watchdog's hang timeout for a pause, the decision topic's
# liveliness lease (3 s) and the hang timeout for a partition.
STOP_PAUSE_S = (0.5, 2.0 * PIPELINE_POLICY.hang_timeout_s)
PARTITION_S = (0.5, 20.0)
# Small steps pass the sim clock guard's credit (sim_clock_max_jump_s, 10 s ahead) and test the freshness rules;
# large ones, and any step back, are clock jumps the guard must refuse.
CLOCK_STEPS_S = (-86400.0, -30.0, -2.0, -0.2, 0.2, 0.8, 2.0, 30.0, 86400.0)
CHAOS_CLOCK = '/chaos/clock'
PARTITIONED_ROLES = ('control', 'substation')


@dataclass(frozen=True)
class Fault:
    """One seeded fault.

    Attributes:
        seed: The seed it was drawn from.
        kind: One of KINDS.
        offset_s: When, against the request's time, s of sim time (within +-OFFSET_S).
        target: kill, stop: the node; clock_step: the node, or with hosts the host; partition: the two hosts, 'a|b'.
        duration_s: stop: SIGSTOP to SIGCONT; partition: cut to heal; wall s (0 otherwise).
        step_s: clock_step: the step of the target's sim clock, s (negative: back).

    """

    seed: int
    kind: str
    offset_s: float
    target: str
    duration_s: float = 0.0
    step_s: float = 0.0

    def describe(self) -> str:
        """Return the fault in a few words, e.g. 'kill -9 partitioning at request -0.31 s'."""
        at = f'at request {self.offset_s:+.2f} s'
        if self.kind == 'kill':
            return f'kill -9 {self.target} {at}'
        if self.kind == 'stop':
            return f'SIGSTOP {self.target} for {self.duration_s:.1f} s {at}'
        if self.kind == 'partition':
            return f'WAN partition {self.target.replace("|", " / ")} for {self.duration_s:.1f} s {at}'
        return f'{self.target} clock stepped {self.step_s:+g} s {at}'


def partition_hosts(hosts: dict[str, tuple[str, ...]] | None) -> tuple[str, str] | None:
    """Return the control-centre host and the substation host, or None when there are no two such hosts."""
    if not hosts:
        return None
    ends = [next(h for h, roles in hosts.items() if role in roles) for role in PARTITIONED_ROLES]
    return None if ends[0] == ends[1] else (ends[0], ends[1])


def plan_fault(seed: int, hosts: dict[str, tuple[str, ...]] | None = None) -> Fault:
    """Return the fault of a seed; a WAN partition only among emulated hosts that separate control and substation."""
    rng = random.Random(seed)
    ends = partition_hosts(hosts)
    kind = rng.choice([k for k in KINDS if k != 'partition' or ends])
    offset_s = round(rng.uniform(-OFFSET_S, OFFSET_S), 3)
    if kind == 'partition':
        return Fault(seed, kind, offset_s, '|'.join(ends), duration_s=round(rng.uniform(*PARTITION_S), 2))
    if kind == 'clock_step':
        target = rng.choice(sorted(hosts)) if hosts else rng.choice(TARGETS)
        return Fault(seed, kind, offset_s, target, step_s=rng.choice(CLOCK_STEPS_S))
    target = rng.choice(TARGETS)
    return Fault(seed, kind, offset_s, target, duration_s=round(rng.uniform(*STOP_PAUSE_S), 2) if kind == 'stop'
                 else 0.0)


class FaultInjector:
    """Carries out one fault during run_closed_loop and records what happened and whether the graph recovered.

    Args:
        fault: The fault.
        request_s: The request's sim time (scenario seconds).
        start_unix_s: The unix time of sim time 0 (the stamps' origin, sim/bag.START_TIME_UNIX_S).
        hosts: With emulated hosts, host name -> roles (graph/wan.parse_hosts).
        control_file: With hosts, the WAN's partition file (EmulatedWan.control_file).

    """

    def __init__(self, fault: Fault, request_s: float, start_unix_s: float,
                 hosts: dict[str, tuple[str, ...]] | None = None, control_file: Path | None = None) -> None:
        if fault.kind == 'partition' and control_file is None:
            raise GraphError(f'{fault.describe()}: a WAN partition needs emulated hosts (--hosts)')
        self.fault, self.hosts, self.control_file = fault, hosts, control_file
        self.fire_at_s = request_s + fault.offset_s
        self.request_s, self.start_unix_s = request_s, start_unix_s
        self.sim_s: float | None = None
        self.fired: dict | None = None
        self.ended_wall: float | None = None  # SIGCONT sent, WAN healed, or the node found restarted
        self.restarted_wall: float | None = None
        self.recovered_wall: float | None = None
        self.notes: list[str] = []
        self._pid: int | None = None
        self._relay = None
        self._observer = self._sup = None

    # --- wiring ------------------------------------------------------------------------------------------------
    def stepped_nodes(self) -> list[str]:
        """Return the nodes whose clock the fault steps (they hear /clock through the relay from the start)."""
        if self.fault.kind != 'clock_step':
            return []
        if self.hosts:
            return [n for n in TARGETS if wan.host_of(self.hosts, n) == self.fault.target]
        return [self.fault.target]

    def remaps(self, namespace: str) -> dict[str, dict[str, str]]:
        """Return each stepped node's own remapping of /clock to the relay's topic in `namespace`."""
        return {n: {'/clock': f'{namespace}{CHAOS_CLOCK}'} for n in self.stepped_nodes()}

    def attach(self, observer: object, sup: object, clock_topic: str) -> None:
        """Listen to the graph's clock (`clock_topic`) on the observer's node, and relay it if a clock steps."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        from controlled_islanding.ros.endpoints import qos_for
        from controlled_islanding.wire import topics

        self._observer, self._sup = observer, sup
        node = observer.node
        if self.stepped_nodes():
            self._relay = node.create_publisher(Clock, f'{observer.namespace}{CHAOS_CLOCK}', qos_for(topics.CLOCK))
        # As rclpy's time source reads /clock: best effort, depth 1.
        node.create_subscription(Clock, clock_topic, self._on_clock,
                                 QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))

    def ready(self) -> bool:
        """Return whether every stepped node hears the relay (so the run may start)."""
        return self._relay is None or self._relay.get_subscription_count() >= len(self.stepped_nodes())

    # --- the fault ---------------------------------------------------------------------------------------------
    def _on_clock(self, msg: object) -> None:
        ns = msg.clock.sec * 1_000_000_000 + msg.clock.nanosec
        self.sim_s = ns * 1e-9 - self.start_unix_s
        if self.fired is None and self.sim_s >= self.fire_at_s - 1e-9:
            self._fire()
        if self._relay is not None:
            if self.fired is not None:
                ns = max(0, ns + int(round(self.fault.step_s * 1e9)))
                msg.clock.sec, msg.clock.nanosec = divmod(ns, 1_000_000_000)
            self._relay.publish(msg)

    def _child(self, name: str) -> object:
        return self._sup.children[name]

    def _fire(self) -> None:
        fault, now = self.fault, time.monotonic()
        self.fired = {'sim_s': self.sim_s, 'after_request_s': self.sim_s - self.request_s, 'wall': now}
        if fault.kind in ('kill', 'stop'):
            child = self._child(fault.target)
            if child.poll() is not None:
                self.notes.append(f'{fault.target} was not running at the fault (exit {child.returncode})')
                self._pid = None
                return
            self._pid = child.pid
            os.kill(child.pid, signal.SIGKILL if fault.kind == 'kill' else signal.SIGSTOP)
        elif fault.kind == 'partition':
            wan.set_partitions(self.control_file, [tuple(fault.target.split('|'))])

    def step(self) -> None:
        """End the fault when due (SIGCONT, heal) and follow the recovery; call this often."""
        if self.fired is None:
            return
        fault, now = self.fault, time.monotonic()
        if self.ended_wall is None and fault.kind == 'stop' and now >= self.fired['wall'] + fault.duration_s:
            child = self._child(fault.target)
            if child.pid == self._pid and child.poll() is None:
                os.kill(child.pid, signal.SIGCONT)
            else:
                self.notes.append(f'{fault.target} was killed as hung and restarted before its SIGCONT was due')
            self.ended_wall = now
        elif self.ended_wall is None and fault.kind == 'partition' and now >= self.fired['wall'] + fault.duration_s:
            wan.set_partitions(self.control_file, [])
            self.ended_wall = now
        if fault.kind in ('kill', 'stop') and self._pid is not None:
            child = self._child(fault.target)
            if self.restarted_wall is None and child.pid != self._pid:
                self.restarted_wall = now
        if self.recovered_wall is None and self._back(now):
            self.recovered_wall = now

    def _back(self, now: float) -> bool:
        fault, obs = self.fault, self._observer.obs
        if fault.kind in ('kill', 'stop'):
            if self._pid is None:
                return False
            since = self.restarted_wall or (self.ended_wall if fault.kind == 'stop' else None)
            return since is not None and obs.heartbeats_s.get(f'/{fault.target}', -1.0) > since
        if fault.kind == 'partition':
            # The substation hears the control centre again: its decision writer is alive in a status sent since.
            diag = obs.diagnostics.get('/breaker_command', {})
            return (self.ended_wall is not None and obs.heartbeats_s.get('/breaker_command', -1.0) > self.ended_wall
                    and int(diag.get('decision_writers_alive', '0')) > 0)
        return False

    def settled(self) -> bool:
        """Return whether nothing more is to come: the fault ended and the graph is back (or it never fired)."""
        if self.fired is None or self.fault.kind == 'clock_step' or (self.fault.kind in ('kill', 'stop')
                                                                     and self._pid is None):
            return True
        return self.recovered_wall is not None and (self.fault.kind == 'kill' or self.ended_wall is not None)

    def record(self) -> dict:
        """Return what was done and seen: the fault, when it fired, its end, the restart and the recovery."""
        fired = self.fired
        t0 = None if fired is None else fired['wall']

        def after(t: float | None) -> float | None:
            return None if t is None or t0 is None else round(t - t0, 3)

        if fired is None or self.fault.kind == 'clock_step':
            recovered = None  # nothing failed that could come back
        elif self.fault.kind in ('kill', 'stop') and self._pid is None:
            recovered = None
        else:
            recovered = self.recovered_wall is not None
        return {'fault': asdict(self.fault), 'describe': self.fault.describe(), 'fired': fired is not None,
                'fired_sim_s': None if fired is None else round(fired['sim_s'], 4),
                'fired_after_request_s': None if fired is None else round(fired['after_request_s'], 4),
                'pid': self._pid, 'ended_after_s': after(self.ended_wall),
                'restarted_after_s': after(self.restarted_wall), 'recovered': recovered,
                'recovered_after_s': after(self.recovered_wall), 'stepped_nodes': self.stepped_nodes(),
                'notes': list(self.notes)}

    def release(self) -> None:
        """Undo what could outlive the run: continue a node still stopped, heal the WAN."""
        if self.fired is None or self.ended_wall is not None:
            return
        if self.fault.kind == 'stop' and self._pid is not None:
            child = self._child(self.fault.target)
            if child.pid == self._pid and child.poll() is None:
                os.kill(child.pid, signal.SIGCONT)
        elif self.fault.kind == 'partition':
            wan.set_partitions(self.control_file, [])
