"""Fuzz soak: malformed and adversarial messages into a live node graph, then a good replay through it.

The four pipeline nodes run as their own processes (supervised, on sim time driven by this harness), the
breaker node armed by a signed operator request. Each input topic in turn gets N seeded messages, each with
at least one defect (non-finite or negative values, arrays at and beyond the nodes' caps, parallel arrays of
unequal length, empty, unknown, duplicate or renamed ids, zero, far-past and far-future stamps, unset enums,
unsigned and forged decisions, decisions whose remedial actions are no amounts, name no bus or machine, or exceed
the caps). The receiving nodes' /diagnostics counters (`rejected.*`, `error.*`) are
read before and after each topic. Then the default bag is played, as fast as possible in lockstep, through
the SAME processes, and its decision is compared with the manifest's.

Safety of the harness itself: no fuzz request is both well-formed and fresh (the breaker's freshness rule
judges the request stamp), and no fuzz decision carries a signature by the partitioning key, so a breaker
command during the fuzz means a rule was broken, never that the graph obeyed plausible input.

No CLI here: `controlled_islanding.commands.fuzz` parses arguments and prints.
"""

from __future__ import annotations

import json
import os
import random
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from controlled_islanding.core.grid import DYNAMIC_FIELDS
from controlled_islanding.graph.processes import rss_kb
from controlled_islanding.wire import topics
from controlled_islanding.wire.messages import MAX_MODEL_NAME, MAX_REQUEST_ID

# Nodes under test and the input topics each one subscribes to.
RECEIVERS: dict[str, tuple[str, ...]] = {
    topics.PMU_FRAMES: ('pmu_ingestion',),
    topics.NETWORK_SNAPSHOT: ('pmu_ingestion', 'coherency', 'partitioning', 'breaker_command'),
    topics.BRANCH_STATUS: ('partitioning', 'breaker_command'),
    topics.ISLANDING_REQUEST: ('coherency', 'partitioning'),
    topics.ROTOR_ANGLES: ('coherency',),
    topics.COHERENT_GROUPS: ('partitioning',),
    topics.ISLANDING_DECISION: ('breaker_command',),
}
FUZZ_TOPICS: tuple[str, ...] = tuple(RECEIVERS)
# The receiver whose `received` (and, where it counts them, `lost.<topic>`) diagnostics pace the publisher.
PACER: dict[str, str] = {
    topics.PMU_FRAMES: 'pmu_ingestion', topics.NETWORK_SNAPSHOT: 'coherency',
    topics.BRANCH_STATUS: 'partitioning', topics.ISLANDING_REQUEST: 'partitioning',
    topics.ROTOR_ANGLES: 'coherency', topics.COHERENT_GROUPS: 'partitioning',
    topics.ISLANDING_DECISION: 'breaker_command',
}
# Messages published ahead of what the pacing node has reported received; the diagnostics it paces on come at
# up to 10 Hz, so this bounds the backlog without stalling on every message.
PACE_WINDOW = 60
# Topics whose readers keep only the latest message or a few (keep last 1 and 16): one message per gap of wall
# time, at least LATEST_ONLY_GAP_S (about the time a node takes to decode an IEEE 39 snapshot). The gap doubles
# whenever a receiver counts a loss (`lost.<topic>`, at most MAX_GAP_S) and halves again after QUIET_MESSAGES
# without one: it settles where about one message in QUIET_MESSAGES is lost, and every loss is counted. (Shrunk
# by only 0.8, a gap pushed to MAX_GAP_S by the losses around the messages at the caps never came down, and
# 10,000 snapshots took 30 min.) A message at or beyond the caps is followed by a wait until every receiver has
# taken it (BIG_WAIT_S at most): its decode takes long enough for a keep-last-1 reader to lose the next ones.
LATEST_ONLY = (topics.NETWORK_SNAPSHOT, topics.COHERENT_GROUPS)
LATEST_ONLY_GAP_S = 0.004
MAX_GAP_S = 0.25
QUIET_MESSAGES = 100
BIG_WAIT_S = 20.0
# A pacer that neither takes nor counts as lost what was sent for this long (s) has dropped it uncounted (a
# loss is counted only when the writer's next sample arrives); those messages are written off so that pacing
# never waits on them again. After a message at the caps the allowance is BIG_STALL_S: decoding one shows no
# progress until it is done.
STALL_S = 0.5
BIG_STALL_S = 5.0
# The fuzz runs on a sim clock that starts this far (s) before the bag's first message and stands still
# FUZZ_CLOCK_MARGIN_S before it, so nothing the fuzz leaves behind is newer than the bag's data. Before the
# replay it is brought up to HANDOVER_GAP_S before the bag's start in steps of CATCH_UP_STEP_S: the nodes bound
# their sim clock (wire/timebounds.SimClockGuard: at most 10 s at once, 1000 x wall time by default), and a
# clock that leapt to the bag would be refused as forged for the rest of the graph's life. Each step waits
# (at most CATCH_UP_WAIT_S) for a heartbeat from every node after it: a node busy with a backlog takes only the
# newest /clock when it is free again, and in a 10,000-message soak partitioning, still answering fuzz requests,
# next read the clock 42 s on (2 s steps every 25 ms), refused it as a jump and never trusted it again. The
# lead is short so that the catch-up, about a second a step, stays a few steps.
FUZZ_CLOCK_LEAD_S = 90.0
FUZZ_CLOCK_MARGIN_S = 60.0
HANDOVER_GAP_S = 5.0
CATCH_UP_STEP_S = 8.0
CATCH_UP_WAIT_S = 30.0
RSS_LIMIT_MB = 20.0
# Wall time the nodes get to publish their first diagnostics, s (also the supervisor's start-up grace in the soak):
# coherency imports scipy and loads numba's DTW engine, which took over 20 s on the shared 2-core machine under a
# load average of 15.
STARTUP_S = 90.0
# The kinds of each topic that are as large as the nodes' caps admit, or one element larger. Decoding one takes
# tens of MB of small objects and buffers; freed, most of it stays with the allocator (glibc heap, Python's
# object arenas) for reuse, and how much stays grows with the first few such messages until it covers them:
# a node given only these messages grew 79.0 -> 91.1 -> 92.5 MB after 1, 10 and 20 of them, then stayed at
# 92.5 MB to 150. So before the RSS baseline, each node gets every one of these kinds, round after round, until
# two rounds running raise no node's RSS above its high so far by WARM_PLATEAU_KB (at most WARM_ROUNDS): the
# warm baseline is a node that has already held the largest messages its caps admit. The growth over the fuzz is
# measured from there and judged; the cold growth is printed beside it. docs/nodes.md, "Fuzz soak", has the
# diagnosis.
LARGEST_KINDS: dict[str, tuple[str, ...]] = {
    topics.PMU_FRAMES: ('over_cap', 'at_cap_unknown'), topics.NETWORK_SNAPSHOT: ('over_cap', 'at_cap_nan'),
    topics.ROTOR_ANGLES: ('over_cap', 'at_cap_renamed'), topics.COHERENT_GROUPS: ('over_cap',),
    topics.ISLANDING_DECISION: ('over_cap', 'over_cap_actions'),
}
WARM_PLATEAU_KB = 1024
WARM_ROUNDS = 12
# Caps of the nodes as configured in config/*.yaml (messages.Limits and the per-node parameters).
MAX_PMUS_PER_FRAME = 10_000
MAX_BUSES = 50_000
MAX_BRANCHES = 100_000
MAX_GENERATORS = 10_000
MAX_STATION_ID_CHARS = 256
YEAR_S = 365.25 * 86_400.0


@dataclass
class TopicResult:
    """What one topic's fuzz did and what the receiving nodes counted.

    Attributes:
        topic: The input topic.
        sent: Messages published.
        received: Arrivals the pacing node counted in this phase (its `received` diagnostics delta).
        lost: Sum over the receiving nodes of the growth of `lost.<topic>` (from publication sequence numbers;
            only nodes that count losses, see docs/nodes.md).
        unaccounted: Messages the pacing node neither received nor counted as lost by the end of the phase.
        rejected: Sum over the receiving nodes of the growth of `rejected.*` and `error.*` in this phase.
        errors: The part of `rejected` that is `error.*` (an exception escaped a callback).
        by_node: Receiving node -> counter name -> growth in this phase.
        kinds: Defect kind -> messages sent with it.
        wall_s: Wall time of the phase, s.
        rss_kb: Pipeline node -> VmRSS after the phase settled, kB: which topic grew which node.

    """

    topic: str
    sent: int = 0
    received: int = 0
    lost: int = 0
    unaccounted: int = 0
    rejected: int = 0
    errors: int = 0
    by_node: dict[str, dict[str, int]] = field(default_factory=dict)
    kinds: dict[str, int] = field(default_factory=dict)
    wall_s: float = 0.0
    rss_kb: dict[str, int | None] = field(default_factory=dict)


@dataclass
class NodeResult:
    """Health of one pipeline node over the fuzz.

    Attributes:
        name: The node.
        deaths: Exits and hangs the supervisor saw from the first fuzz message on (each followed by a restart).
        startup_restarts: Restarts before any fuzz message was sent (a node that took longer than the
            supervisor's heartbeat allowance to start, on a loaded machine): reported, not judged, since no
            input can have caused them.
        rss_before_kb: VmRSS before the warm-up, kB.
        rss_warm_kb: VmRSS after the warm-up (the largest messages of every kind, until RSS levels off), kB.
        rss_after_fuzz_kb: VmRSS after the last topic settled, kB (None if the process changed).
        rss_growth_mb: rss_after_fuzz_kb - rss_warm_kb, MB (1 MB = 1024 kB): what the fuzz added to a node
            that has already held the largest messages its caps admit. The judged figure.
        rss_cold_growth_mb: rss_after_fuzz_kb - rss_before_kb, MB: the same with the warm-up included.

    """

    name: str
    deaths: int = 0
    startup_restarts: int = 0
    rss_before_kb: int | None = None
    rss_warm_kb: int | None = None
    rss_after_fuzz_kb: int | None = None
    rss_growth_mb: float | None = None
    rss_cold_growth_mb: float | None = None


@dataclass
class ReplayResult:
    """The good replay after the fuzz, through the same node processes.

    Attributes:
        bag: Bag name from bags/index.yaml.
        graph: 'same': the processes that took the fuzz.
        expected_split: The manifest's expected split.
        expected_cut: The manifest's expected cut branches, sorted.
        status: Decision status (IslandingDecision.STATUS_*), None if no decision came.
        split: The decision's split flag.
        cut: The decision's cut branches, sorted.
        breaker_commands: Breaker ids commanded for that decision.
        agrees: Split and cut equal the manifest's.

    """

    bag: str
    graph: str = 'same'
    expected_split: bool | None = None
    expected_cut: list[str] = field(default_factory=list)
    status: int | None = None
    split: bool | None = None
    cut: list[str] = field(default_factory=list)
    breaker_commands: list[str] = field(default_factory=list)
    agrees: bool = False


@dataclass
class FuzzReport:
    """Everything the soak measured, and the verdict.

    Attributes:
        seed: Random seed of the message generator.
        per_topic: Messages per topic asked for.
        topics: One result per fuzzed topic, in order.
        nodes: One result per pipeline node.
        commands_during_fuzz: Breaker commands seen on /breaker/commands before the replay (0 required).
        replay: The replay afterwards.
        warm_rounds: Rounds of the largest messages sent before the RSS baseline (see LARGEST_KINDS).
        warm_rss_kb: Pipeline node -> VmRSS after each of those rounds, kB.
        failures: One line per check that did not hold; empty = pass.
        results_dir: Node logs, the breaker audit log and report.json.
        wall_s: Wall time of the whole run, s.
        namespace: The graph's ROS namespace ('' = the root one).
        graph_topics: Every topic name in the graph once it was wired, sorted.

    """

    seed: int
    per_topic: int
    topics: list[TopicResult] = field(default_factory=list)
    nodes: list[NodeResult] = field(default_factory=list)
    commands_during_fuzz: int = 0
    replay: ReplayResult | None = None
    warm_rounds: int = 0
    warm_rss_kb: list[dict[str, int | None]] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    results_dir: str = ''
    wall_s: float = 0.0
    namespace: str = ''
    graph_topics: list[str] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        """Whether every check held."""
        return not self.failures

    def as_dict(self) -> dict:
        """Return the report as plain JSON-able data."""
        return {**asdict(self), 'passed': self.passed}


class FuzzError(RuntimeError):
    """The soak could not run (graph did not come up, bag unreadable); not a failed check."""


# ---------------------------------------------------------------------------------------------- messages

@dataclass
class Seeds:
    """Well-formed messages from the default bag, the raw material every fuzz message is a defect of."""

    snapshot: object
    frames: list
    status: object
    request: object
    bag_start_s: float
    generator_names: list[str]
    generator_buses: list[int]
    expected_islands: list[list[int]]
    expected_cut: list[str]


def load_seeds(bag: Path, entry: dict) -> Seeds:
    """Read the first snapshot, frames, status and request of a bag into rclpy messages.

    Raises:
        FuzzError: The bag lacks one of them.

    """
    from controlled_islanding_msgs.msg import BranchStatus, IslandingRequest, NetworkSnapshot, PmuFrame
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader

    from controlled_islanding.wire.interfaces import typestore

    classes = {topics.NETWORK_SNAPSHOT: NetworkSnapshot, topics.PMU_FRAMES: PmuFrame,
               topics.BRANCH_STATUS: BranchStatus, topics.ISLANDING_REQUEST: IslandingRequest}
    found: dict[str, list] = {t: [] for t in classes}
    with AnyReader([bag], default_typestore=typestore()) as reader:
        start_s = reader.start_time * 1e-9
        conns = [c for c in reader.connections if c.topic in classes]
        for conn, _, raw in reader.messages(connections=conns):
            if len(found[conn.topic]) < 20:
                found[conn.topic].append(deserialize_message(bytes(raw), classes[conn.topic]))
    missing = [t for t, v in found.items() if not v]
    if missing:
        raise FuzzError(f'bag {bag} has no message on {", ".join(missing)}; it cannot seed the fuzz')
    snap = found[topics.NETWORK_SNAPSHOT][0]
    expected = entry.get('expected_decision', {})
    return Seeds(snapshot=snap, frames=found[topics.PMU_FRAMES], status=found[topics.BRANCH_STATUS][0],
                 request=found[topics.ISLANDING_REQUEST][0], bag_start_s=start_s,
                 generator_names=list(snap.generator_names), generator_buses=[int(b) for b in snap.generator_bus],
                 expected_islands=[list(map(int, isl)) for isl in expected.get('islands', [])],
                 expected_cut=sorted(expected.get('cut_branches', [])))


def _copy(msg: object) -> object:
    from rclpy.serialization import deserialize_message, serialize_message

    return deserialize_message(serialize_message(msg), type(msg))


class Adversary:
    """Seeded generator of defective messages, one topic at a time.

    Every message it makes carries at least one defect the receiving node is documented to refuse, or a stamp
    that cannot lead to a command (see the module docstring). `kind` names the defect, for the report.

    Args:
        seeds: Well-formed messages to corrupt.
        seed: Random seed; the same seed gives the same sequence of kinds and values.
        now_s: The fuzz sim clock, s.
        partitioning_key_id: Fingerprint of the trusted decision key, claimed by forged signatures.

    """

    def __init__(self, seeds: Seeds, seed: int, now_s: Callable[[], float], partitioning_key_id: str = '') -> None:
        self.s = seeds
        self.partitioning_key_id = partitioning_key_id
        self.rng = random.Random(seed)
        self.now_s = now_s
        self.n = 0
        self.forced: str | None = None
        self._big: dict[str, object] = {}
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

        self.attacker_key = Ed25519PrivateKey.generate()
        self.sent_ids: list[str] = []

    # -- stamps
    def _stamp(self, msg_stamp: object, kind: str) -> None:
        """Set a stamp: fresh (within the last 0.5 s of the clock) unless the kind says otherwise."""
        now = self.now_s()
        rng = self.rng
        if kind == 'zero_stamp':
            t = 0.0
        elif kind == 'future_stamp':
            t = now + rng.choice([1.5, 60.0, 3600.0, 86_400.0, YEAR_S, 50 * YEAR_S])
        elif kind == 'past_stamp':
            t = max(1.0, now - rng.choice([12.0, 3600.0, 86_400.0, YEAR_S, now - 1.0]))
        else:
            t = now - rng.uniform(0.0, 0.5)
        sec = min(int(t), 2**31 - 1)
        msg_stamp.sec = sec
        msg_stamp.nanosec = 0 if kind == 'zero_stamp' else int((t - int(t)) * 1e9)
        if kind == 'bad_nanosec':
            msg_stamp.nanosec = rng.choice([1_000_000_000, 2**32 - 1])

    def _bad_float(self) -> float:
        return self.rng.choice([float('nan'), float('inf'), float('-inf')])

    def _name(self) -> str:
        return self.rng.choice(['', 'GENROU_999', 'G\x00', 'x' * 300, 'GENROU_1 ', 'генератор', f'odd-{self.n}'])

    def _choose(self, kinds: list[tuple[str, float]]) -> str:
        names, weights = zip(*kinds, strict=True)
        if self.forced in names:
            return self.forced
        return self.rng.choices(names, weights)[0]

    def largest(self, topic: str) -> list[tuple[str, object]]:
        """Return one message of each at-cap and over-cap kind of a topic (the warm-up)."""
        out = []
        for kind in LARGEST_KINDS.get(topic, ()):
            self.forced = kind
            try:
                out.append(self.make(topic))
            finally:
                self.forced = None
        return out

    def make(self, topic: str) -> tuple[str, object]:
        """Return (defect kind, message) for a topic."""
        self.n += 1
        return {topics.PMU_FRAMES: self.frame, topics.NETWORK_SNAPSHOT: self.snapshot,
                topics.BRANCH_STATUS: self.branch_status, topics.ISLANDING_REQUEST: self.request,
                topics.ROTOR_ANGLES: self.rotor_angles, topics.COHERENT_GROUPS: self.groups,
                topics.ISLANDING_DECISION: self.decision}[topic]()

    # -- /pmu/frames
    def frame(self) -> tuple[str, object]:
        """Return a defective PmuFrame."""
        from controlled_islanding_msgs.msg import PmuFrame, PmuMeasurement

        kind = self._choose([('nan_phasor', 10), ('negative_values', 6), ('unknown_bus', 8), ('duplicate_station', 8),
                             ('empty_station_id', 5), ('odd_station_ids', 8), ('long_station_id', 3),
                             ('empty_frame', 5), ('zero_stamp', 8), ('future_stamp', 10), ('past_stamp', 8),
                             ('bad_nanosec', 3), ('all_unusable', 5), ('over_cap', 0.3), ('at_cap_unknown', 0.3)])
        rng = self.rng
        key = f'frame:{kind}'
        if kind in ('over_cap', 'at_cap_unknown'):
            n = MAX_PMUS_PER_FRAME + (1 if kind == 'over_cap' else 0)
            if key not in self._big:
                m = PmuMeasurement(station_id='PMU-X', bus=999_999, voltage_magnitude_pu=1.0, current_magnitude_pu=1.0,
                                   frequency_hz=60.0)
                big = PmuFrame()
                big.measurements = [m] * n
                self._big[key] = big
            msg = self._big[key]
            self._stamp(msg.header.stamp, 'fresh')
            return kind, msg
        msg = _copy(rng.choice(self.s.frames))
        stamp_kind = kind if kind in ('zero_stamp', 'future_stamp', 'past_stamp', 'bad_nanosec') else 'fresh'
        self._stamp(msg.header.stamp, stamp_kind)
        ms = list(msg.measurements)
        i = rng.randrange(len(ms))
        if kind == 'nan_phasor':
            setattr(ms[i], rng.choice(['voltage_magnitude_pu', 'voltage_angle_rad', 'current_magnitude_pu',
                                       'current_angle_rad', 'frequency_hz']), self._bad_float())
        elif kind == 'negative_values':
            ms[i].voltage_magnitude_pu = -abs(ms[i].voltage_magnitude_pu) - 1.0
            ms[i].frequency_hz = -60.0
            ms[i].current_angle_rad = rng.choice([-1e300, 1e300])
        elif kind == 'machine_data':
            self._bad_machine_data(msg)
        elif kind == 'unknown_bus':
            ms[i].bus = rng.choice([0, 999_999, 2**32 - 1])
        elif kind == 'duplicate_station':
            ms.append(_copy_measurement(ms[i]))
        elif kind == 'empty_station_id':
            for m in ms:
                m.station_id = ''
        elif kind == 'odd_station_ids':
            for m in ms:
                m.station_id = f'{m.station_id}-{self.n}-{rng.randrange(10**9)}'
        elif kind == 'long_station_id':
            ms[i].station_id = 'P' * (MAX_STATION_ID_CHARS + rng.randrange(1, 10_000))
        elif kind == 'empty_frame':
            ms = []
        elif kind == 'all_unusable':
            for m in ms:
                m.stat = rng.choice([PmuMeasurement.STAT_DATA_INVALID, PmuMeasurement.STAT_PMU_ERROR, 0xFFFF])
                m.voltage_magnitude_pu = self._bad_float()
        msg.measurements = ms
        return kind, msg

    # -- /network/snapshot
    def snapshot(self) -> tuple[str, object]:
        """Return a defective NetworkSnapshot (never a well-formed one with a fresh stamp)."""
        rng = self.rng
        kind = self._choose([('nan_value', 10), ('negative_reactance', 6), ('bad_base', 4), ('array_length', 10),
                             ('breaker_ids_length', 4), ('empty', 5), ('duplicate_bus', 6), ('duplicate_branch', 6),
                             ('unknown_bus', 8), ('zero_stamp', 8), ('future_stamp', 10), ('past_stamp', 8),
                             ('machine_data', 8), ('over_cap', 0.3), ('at_cap_nan', 0.3)])
        key = f'snapshot:{kind}'
        if kind in ('over_cap', 'at_cap_nan'):
            if key not in self._big:
                big = _copy(self.s.snapshot)
                extra = MAX_BUSES + (1 if kind == 'over_cap' else 0) - len(big.bus_numbers)
                big.bus_numbers = list(big.bus_numbers) + list(range(100_000, 100_000 + extra))
                if kind == 'at_cap_nan':
                    n = MAX_BRANCHES
                    big.branch_ids = [f'B{i}' for i in range(n)]
                    big.branch_from_bus = [100_000 + (i % 40_000) for i in range(n)]
                    big.branch_to_bus = [100_001 + (i % 40_000) for i in range(n)]
                    big.branch_in_service = [True] * n
                    big.branch_p_from_mw = [float('nan')] * n
                    big.branch_p_to_mw = [0.0] * n
                    big.branch_breaker_ids = []
                self._big[key] = big
            msg = self._big[key]
            self._stamp(msg.header.stamp, 'fresh')
            return kind, msg
        msg = _copy(self.s.snapshot)
        self._stamp(msg.header.stamp, kind if kind in ('zero_stamp', 'future_stamp', 'past_stamp') else 'fresh')
        if kind == 'nan_value':
            name = rng.choice(['branch_p_from_mw', 'branch_p_to_mw', 'generator_p_mw', 'generator_p_max_mw',
                               'generator_xq_pu', 'generator_ra_pu', 'load_p_mw', 'load_q_mvar'])
            values = list(getattr(msg, name))
            values[rng.randrange(len(values))] = self._bad_float()
            setattr(msg, name, values)
        elif kind == 'negative_reactance':
            name = rng.choice(['generator_xq_pu', 'generator_ra_pu'])
            values = list(getattr(msg, name))
            values[rng.randrange(len(values))] = -rng.uniform(1e-6, 10.0)
            setattr(msg, name, values)
        elif kind == 'bad_base':
            msg.base_mva = rng.choice([0.0, -100.0, float('nan'), float('-inf')])
        elif kind == 'array_length':
            name = rng.choice(['branch_from_bus', 'branch_to_bus', 'branch_in_service', 'branch_p_from_mw',
                               'generator_bus', 'generator_xq_pu', 'generator_p_mw', 'load_bus', 'load_q_mvar'])
            values = list(getattr(msg, name))
            setattr(msg, name, values[:-1] if rng.random() < 0.5 else values + values[:1])
        elif kind == 'breaker_ids_length':
            msg.branch_breaker_ids = ['CB-x'] * (len(msg.branch_ids) + rng.choice([-1, 1]))
        elif kind == 'empty':
            setattr(msg, rng.choice(['bus_numbers', 'branch_ids', 'generator_names']), [])
        elif kind == 'duplicate_bus':
            buses = list(msg.bus_numbers)
            buses[rng.randrange(1, len(buses))] = buses[0]
            msg.bus_numbers = buses
        elif kind == 'duplicate_branch':
            ids = list(msg.branch_ids)
            ids[rng.randrange(1, len(ids))] = ids[0]
            msg.branch_ids = ids
        elif kind == 'machine_data':
            self._bad_machine_data(msg)
        elif kind == 'unknown_bus':
            name = rng.choice(['branch_from_bus', 'branch_to_bus', 'generator_bus', 'load_bus'])
            values = list(getattr(msg, name))
            values[rng.randrange(len(values))] = rng.choice([0, 999_999, 2**32 - 1])
            setattr(msg, name, values)
        return kind, msg

    def _bad_machine_data(self, msg: object) -> None:
        """Spoil the optional machine dynamic data the decoder must still reject (NaN alone means unknown)."""
        rng = self.rng
        n = len(msg.generator_names)
        field = rng.choice([f'generator_{name}' for name in DYNAMIC_FIELDS] + ['generator_model'])
        if field == 'generator_model':
            models = list(msg.generator_model) or [''] * n
            if rng.random() < 0.5:
                models[rng.randrange(n)] = 'X' * (MAX_MODEL_NAME + 1 + rng.randrange(1000))
            else:
                models = models[:-1] if n > 1 and rng.random() < 0.5 else models + models[:1]
            msg.generator_model = models
            return
        values = list(getattr(msg, field)) or [float('nan')] * n
        how = rng.choice(['inf', 'negative', 'length'])
        if how == 'length':
            values = values[:-1] if n > 1 and rng.random() < 0.5 else values + values[:1]
        else:
            values[rng.randrange(n)] = (rng.choice([float('inf'), float('-inf')]) if how == 'inf'
                                        else -rng.uniform(1e-9, 1e6))
        setattr(msg, field, values)

    # -- /network/branch_status
    def branch_status(self) -> tuple[str, object]:
        """Return an adversarial BranchStatus (only ever stamped before the bag's snapshot)."""
        rng = self.rng
        kind = self._choose([('unknown_branch', 12), ('empty_id', 8), ('long_id', 4), ('mismatched_buses', 8),
                             ('zero_stamp', 10), ('future_stamp', 12), ('past_stamp', 8), ('bad_nanosec', 4),
                             ('duplicate', 8), ('flapping_real_branch', 8)])
        msg = _copy(self.s.status)
        ids = list(self.s.snapshot.branch_ids)
        self._stamp(msg.header.stamp, kind if kind in ('zero_stamp', 'future_stamp', 'past_stamp', 'bad_nanosec')
                    else 'fresh')
        if kind == 'unknown_branch':
            msg.branch_id = rng.choice(['99-100', 'CB-6-11', '6-11 ', '11-6x', f'odd-{self.n}'])
        elif kind == 'empty_id':
            msg.branch_id = ''
        elif kind == 'long_id':
            msg.branch_id = 'B' * rng.randrange(129, 100_000)
        elif kind == 'mismatched_buses':
            msg.branch_id = rng.choice(ids)
            msg.from_bus, msg.to_bus = rng.choice([(0, 0), (999_999, 1), (2**32 - 1, 2**32 - 1)])
        elif kind == 'duplicate':
            msg.in_service = False
        elif kind == 'flapping_real_branch':
            i = rng.randrange(len(ids))
            msg.branch_id = ids[i]
            msg.from_bus, msg.to_bus = self.s.snapshot.branch_from_bus[i], self.s.snapshot.branch_to_bus[i]
            msg.in_service = rng.random() < 0.5
        return kind, msg

    # -- /islanding/request
    def request(self) -> tuple[str, object]:
        """Return an adversarial IslandingRequest: never both well-formed and fresh."""
        from controlled_islanding_msgs.msg import IslandingRequest

        rng = self.rng
        kind = self._choose([('empty_id', 12), ('long_id', 8), ('zero_stamp', 12), ('future_stamp', 15),
                             ('past_stamp', 10), ('duplicate_id', 10), ('bad_nanosec_future', 4)])
        msg = IslandingRequest(reason=rng.choice(['', 'fuzz', 'x' * 10_000]))
        msg.request_id = f'fuzz-{self.n}'
        if kind == 'empty_id':
            msg.request_id = ''
            self._stamp(msg.header.stamp, 'fresh')
        elif kind == 'long_id':
            msg.request_id = 'R' * rng.randrange(129, 50_000)
            self._stamp(msg.header.stamp, 'fresh')
        elif kind == 'duplicate_id':
            msg.request_id = rng.choice(self.sent_ids) if self.sent_ids else 'fuzz-dup'
            self._stamp(msg.header.stamp, 'past_stamp')
        elif kind == 'bad_nanosec_future':
            self._stamp(msg.header.stamp, 'future_stamp')
            msg.header.stamp.nanosec = 2**32 - 1
        else:
            self._stamp(msg.header.stamp, kind)
        if kind in ('past_stamp', 'duplicate_id') and msg.header.stamp.sec > self.now_s() - 5.0:
            msg.header.stamp.sec = int(self.now_s() - 12.0)  # old enough for the breaker's freshness rule
        if msg.request_id.startswith('fuzz-'):
            self.sent_ids.append(msg.request_id)
            del self.sent_ids[:-100]
        return kind, msg

    # -- /rotor_angles
    def rotor_angles(self) -> tuple[str, object]:
        """Return a defective RotorAngles sample."""
        from controlled_islanding_msgs.msg import RotorAngles

        rng = self.rng
        kind = self._choose([('nan_valid', 12), ('array_length', 10), ('empty', 6), ('renamed_generators', 10),
                             ('unknown_ids', 8), ('duplicate_ids', 8), ('zero_stamp', 10), ('future_stamp', 12),
                             ('past_stamp', 8), ('bad_nanosec', 3), ('over_cap', 0.5), ('at_cap_renamed', 0.5)])
        names, buses = list(self.s.generator_names), list(self.s.generator_buses)
        key = f'rotor_angles:{kind}'
        if kind in ('over_cap', 'at_cap_renamed'):
            n = MAX_GENERATORS + (1 if kind == 'over_cap' else 0)
            if key not in self._big:
                self._big[key] = RotorAngles(generator_names=[f'G{i}' for i in range(n)], generator_buses=[1] * n,
                                              angle_rad=[0.0] * n, valid=[True] * n)
            msg = self._big[key]
            self._stamp(msg.header.stamp, 'fresh')
            return kind, msg
        angles = [rng.uniform(-3.0, 3.0) for _ in names]
        msg = RotorAngles(generator_names=names, generator_buses=buses, angle_rad=angles, valid=[True] * len(names))
        self._stamp(msg.header.stamp, kind if kind in ('zero_stamp', 'future_stamp', 'past_stamp', 'bad_nanosec')
                    else 'fresh')
        i = rng.randrange(len(names))
        if kind == 'nan_valid':
            angles[i] = self._bad_float()
            msg.angle_rad = angles
        elif kind == 'array_length':
            name = rng.choice(['generator_buses', 'angle_rad', 'valid'])
            values = list(getattr(msg, name))
            setattr(msg, name, values[:-1] if rng.random() < 0.5 else values + values[:1])
        elif kind == 'empty':
            msg.generator_names, msg.generator_buses, msg.angle_rad, msg.valid = [], [], [], []
        elif kind == 'renamed_generators':
            msg.generator_names = [f'G{j + 1}' for j in range(len(names))]
        elif kind == 'unknown_ids':
            names[i] = self._name() or 'GENROU_999'
            msg.generator_names = names
        elif kind == 'duplicate_ids':
            names[i] = names[(i + 1) % len(names)]
            msg.generator_names = names
        return kind, msg

    # -- /coherent_groups
    def groups(self) -> tuple[str, object]:
        """Return defective CoherentGroups (well-formed ones only with a past stamp)."""
        from controlled_islanding_msgs.msg import CoherentGroups

        rng = self.rng
        kind = self._choose([('k_mismatch', 10), ('duplicate_names', 8), ('renamed_generators', 10),
                             ('unknown_ids', 8), ('empty', 6), ('array_length', 10), ('distance_length', 6),
                             ('negative_distance', 6), ('nan_distance', 6), ('zero_stamp', 8), ('future_stamp', 12),
                             ('wrong_method', 6), ('long_request_id', 4), ('past_stamp', 4), ('over_cap', 0.5)])
        names, buses = list(self.s.generator_names), list(self.s.generator_buses)
        n = len(names)
        group = [0] * n
        group[rng.randrange(n)] = 1
        msg = CoherentGroups(generator_names=names, generator_buses=buses, group=group, k=2, method='dtw',
                             distance=[rng.uniform(0.0, 5.0) for _ in range(n * n)], window_s=3.0)
        self._stamp(msg.header.stamp, kind if kind in ('zero_stamp', 'future_stamp', 'past_stamp') else 'fresh')
        if kind == 'past_stamp' and msg.header.stamp.sec > self.now_s() - 5.0:
            msg.header.stamp.sec = int(self.now_s() - 12.0)
        if kind == 'k_mismatch':
            msg.k = rng.choice([0, 1, 3, 2**32 - 1])
        elif kind == 'duplicate_names':
            names[0] = names[1]
            msg.generator_names = names
        elif kind == 'renamed_generators':
            msg.generator_names = [f'G{j + 1}' for j in range(n)]
        elif kind == 'unknown_ids':
            names[rng.randrange(n)] = self._name() or 'GENROU_999'
            msg.generator_names = names
        elif kind == 'empty':
            msg.generator_names, msg.generator_buses, msg.group, msg.distance = [], [], [], []
        elif kind == 'array_length':
            msg.group = group[:-1]
        elif kind == 'distance_length':
            msg.distance = list(msg.distance)[: n * n - rng.randrange(1, n * n)]
        elif kind == 'negative_distance':
            d = list(msg.distance)
            d[rng.randrange(len(d))] = -1.0
            msg.distance = d
        elif kind == 'nan_distance':
            d = list(msg.distance)
            d[rng.randrange(len(d))] = self._bad_float()
            msg.distance = d
        elif kind == 'wrong_method':
            msg.method = rng.choice(['', 'truth', 'correlation', 'DTW'])
        elif kind == 'long_request_id':
            msg.request_id = 'R' * (MAX_REQUEST_ID + 1 + rng.randrange(1000))
        elif kind == 'over_cap':
            key = f'groups:{kind}'
            if key not in self._big:
                m = MAX_GENERATORS + 1
                self._big[key] = CoherentGroups(generator_names=[f'G{i}' for i in range(m)], generator_buses=[1] * m,
                                                 group=[0] * m, k=1, method='dtw')
            big = self._big[key]
            self._stamp(big.header.stamp, 'fresh')
            return kind, big
        return kind, msg

    # -- /islanding/decision
    def decision(self) -> tuple[str, object]:
        """Return an unsigned or forged IslandingDecision for the manifest's cut (a command if it were signed)."""
        from controlled_islanding_msgs.msg import IslandingDecision

        from controlled_islanding.safety import signing

        rng = self.rng
        kind = self._choose([('unsigned', 12), ('random_signature', 10), ('short_signature', 6),
                             ('attacker_key', 12), ('attacker_key_claiming_partitioning', 8), ('unset_status', 8),
                             ('inconsistent_status', 6), ('zero_stamp', 6), ('future_stamp', 8),
                             ('past_stamp', 6), ('empty_ids', 6), ('array_length', 6), ('duplicate_id', 6),
                             ('garbage_actions', 10), ('actions_array_length', 6), ('over_cap', 0.5),
                             ('over_cap_actions', 0.5)])
        buses, islands = [], []
        for k, members in enumerate(self.s.expected_islands or [[int(b) for b in self.s.snapshot.bus_numbers]]):
            buses += members
            islands += [k] * len(members)
        cut = list(self.s.expected_cut)
        by_id = dict(zip(self.s.snapshot.branch_ids, zip(self.s.snapshot.branch_from_bus,
                                                          self.s.snapshot.branch_to_bus, strict=True), strict=True))
        msg = IslandingDecision(decision_id=f'fuzz-decision-{self.n}', request_id=f'fuzz-request-{self.n}',
                                method='dtw', status=IslandingDecision.STATUS_SPLIT, split=True, bus_numbers=buses,
                                bus_island=islands, cut_branch_ids=cut,
                                cut_from_bus=[int(by_id.get(c, (0, 0))[0]) for c in cut],
                                cut_to_bus=[int(by_id.get(c, (0, 0))[1]) for c in cut])
        self._stamp(msg.request_stamp, kind if kind in ('zero_stamp', 'future_stamp', 'past_stamp') else 'fresh')
        self._stamp(msg.header.stamp, 'fresh')
        if kind == 'unset_status':
            msg.status = IslandingDecision.STATUS_UNSET
        elif kind == 'inconsistent_status':
            msg.status, msg.split = rng.choice([(IslandingDecision.STATUS_NO_SPLIT, True),
                                                (IslandingDecision.STATUS_SPLIT, False), (200, True)])
        elif kind == 'empty_ids':
            msg.decision_id, msg.request_id = '', ''
        elif kind == 'array_length':
            msg.bus_island = list(msg.bus_island)[:-1]
        elif kind == 'duplicate_id':
            msg.decision_id = f'fuzz-decision-{rng.randrange(max(1, self.n))}'
        elif kind == 'garbage_actions':
            # Sheds that are not amounts, at buses that do not exist or twice, trips of machines no case has.
            n = rng.randrange(1, 20)
            msg.shed_bus = [rng.choice([0, 2**32 - 1, *buses[:3]]) for _ in range(n)]
            msg.shed_mw = [rng.choice([float('nan'), float('inf'), -1.0, 0.0, 1e300, 5.0]) for _ in range(n)]
            msg.trip_generator_names = [rng.choice(['', 'GENROU_999', 'x' * 300, *self.s.snapshot.generator_names[:2]])
                                        for _ in range(rng.randrange(0, 5))]
        elif kind == 'actions_array_length':
            msg.shed_bus = list(buses[:2])
            msg.shed_mw = [1.0] * rng.choice([0, 1, 3])
        elif kind == 'over_cap_actions':
            key = f'decision:{kind}'
            if key not in self._big:
                m = MAX_BUSES + 1
                self._big[key] = IslandingDecision(
                    decision_id='fuzz-big-actions', request_id='fuzz-big-actions', method='dtw',
                    status=IslandingDecision.STATUS_SPLIT, split=True, bus_numbers=buses, bus_island=islands,
                    cut_branch_ids=msg.cut_branch_ids, cut_from_bus=msg.cut_from_bus, cut_to_bus=msg.cut_to_bus,
                    shed_bus=list(range(m)), shed_mw=[1.0] * m, trip_generator_names=['G'] * (MAX_GENERATORS + 1))
            big = self._big[key]
            big.decision_id = f'fuzz-big-actions-{self.n}'
            self._stamp(big.request_stamp, 'fresh')
            return kind, big
        elif kind == 'over_cap':
            key = f'decision:{kind}'
            if key not in self._big:
                big = IslandingDecision(decision_id='fuzz-big', request_id='fuzz-big', method='dtw',
                                        status=IslandingDecision.STATUS_SPLIT, split=True,
                                        bus_numbers=list(range(MAX_BUSES + 1)), bus_island=[0] * (MAX_BUSES + 1))
                self._big[key] = big
            big = self._big[key]
            big.decision_id = f'fuzz-big-{self.n}'
            self._stamp(big.request_stamp, 'fresh')
            return kind, big
        if kind == 'random_signature':
            msg.key_id = self.partitioning_key_id or 'partitioning-' + os.urandom(4).hex()
            msg.signature = list(os.urandom(64))
        elif kind == 'short_signature':
            msg.signature = list(os.urandom(rng.choice([1, 32, 63, 65, 4096])))
        elif kind in ('attacker_key', 'attacker_key_claiming_partitioning'):
            msg.key_id = signing.fingerprint(self.attacker_key)
            if kind == 'attacker_key_claiming_partitioning':
                msg.key_id = rng.choice([self.partitioning_key_id, 'partitioning', '', 'x' * 200])
            msg.signature = signing.sign(self.attacker_key, signing.decision_payload(msg))
        elif kind != 'unsigned':
            msg.signature = signing.sign(self.attacker_key, signing.decision_payload(msg))
        return kind, msg


def _copy_measurement(m: object) -> object:
    from controlled_islanding_msgs.msg import PmuMeasurement

    return PmuMeasurement(station_id=m.station_id, bus=m.bus, voltage_magnitude_pu=m.voltage_magnitude_pu,
                          voltage_angle_rad=m.voltage_angle_rad, current_magnitude_pu=m.current_magnitude_pu,
                          current_angle_rad=m.current_angle_rad, frequency_hz=m.frequency_hz,
                          rocof_hz_per_s=m.rocof_hz_per_s, stat=m.stat)


# ---------------------------------------------------------------------------------------------- the run

def _counters(diag: dict[str, str]) -> dict[str, int]:
    """Return the rejected.* and error.* counters of one node's diagnostics."""
    out = {}
    for key, value in diag.items():
        if key.startswith(('rejected.', 'error.')):
            try:
                out[key] = int(float(value))
            except ValueError:
                continue
    return out


def run_soak(per_topic: int, seed: int, bag: Path, entry: dict, results: Path, key_dir: Path,
             progress: Callable[[str], None] = lambda _line: None, topic_names: tuple[str, ...] = FUZZ_TOPICS,
             warm_rounds: int = WARM_ROUNDS, namespace: str = '') -> FuzzReport:
    """Start the graph, fuzz every topic, replay the bag through the same graph, and judge.

    Args:
        per_topic: Messages per input topic.
        seed: Random seed of the messages.
        bag: The bag to replay afterwards (and to take well-formed seed messages from).
        entry: Its bags/index.yaml entry (expected_decision).
        results: Folder for node logs, the breaker audit log and the player's report; created.
        key_dir: Signing keys (made if missing): partitioning signs, the operator arms.
        progress: Called with one line per step.
        topic_names: The topics to fuzz, in order.
        warm_rounds: Most rounds of the largest messages before the RSS baseline (see LARGEST_KINDS).
        namespace: The graph's ROS namespace, e.g. '/area1' ('' = the root one); its /clock is <namespace>/clock,
            as with `replay --namespace`.

    Raises:
        FuzzError: The graph or the bag could not be brought up.

    """
    import rclpy
    from controlled_islanding_msgs.msg import BreakerCommand, IslandingDecision
    from controlled_islanding_msgs.srv import SetArmed
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile
    from rclpy.signals import SignalHandlerOptions
    from rosgraph_msgs.msg import Clock

    from controlled_islanding.graph.rosenv import isolated_ros_environment
    from controlled_islanding.graph.supervisor import GRAPH, PIPELINE_POLICY, PLAYER, Supervisor, SupervisorError
    from controlled_islanding.ros.endpoints import qos_for
    from controlled_islanding.ros.params import message_class
    from controlled_islanding.safety import signing

    t_start = time.monotonic()
    results.mkdir(parents=True, exist_ok=True)
    signing.init_keys(key_dir)
    operator_key = signing.load_private_key(signing.key_paths(key_dir, 'operator').private)
    seeds = load_seeds(bag, entry)
    report = FuzzReport(seed=seed, per_topic=per_topic, results_dir=str(results), namespace=namespace)
    clock_topic = f'{namespace}{topics.CLOCK}'
    remaps = {topics.CLOCK: clock_topic} if namespace else {}
    names = [spec.executable for spec in GRAPH]
    fuzz_t0_s = seeds.bag_start_s - FUZZ_CLOCK_LEAD_S
    clock_origin = time.monotonic()
    catching_up_s: list[float | None] = [None]

    def sim_now_s() -> float:
        if catching_up_s[0] is not None:
            return catching_up_s[0]
        return min(fuzz_t0_s + (time.monotonic() - clock_origin), seeds.bag_start_s - FUZZ_CLOCK_MARGIN_S)

    diagnostics: dict[str, dict[str, str]] = {}
    heartbeats: dict[str, float] = {}
    commands: list = []
    decisions: dict[str, object] = {}
    replaying = [False]

    with isolated_ros_environment(results / 'ros_log') as env:
        env = {**env, 'CONTROLLED_ISLANDING_KEYS': str(key_dir)}
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=int(env['ROS_DOMAIN_ID']),
                   signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node('fuzz_soak', context=context, namespace=namespace or None)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)

        def on_diag(msg: DiagnosticArray) -> None:
            for status in msg.status:
                name = status.name.removeprefix(namespace).lstrip('/')
                diagnostics[name] = {kv.key: kv.value for kv in status.values}
                heartbeats[name] = time.monotonic()

        def on_command(msg: BreakerCommand) -> None:
            commands.append((replaying[0], msg))

        def on_decision(msg: IslandingDecision) -> None:
            decisions.setdefault(msg.request_id, msg)

        node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, on_diag, qos_for(topics.DIAGNOSTICS))
        node.create_subscription(BreakerCommand, topics.relative(topics.BREAKER_COMMANDS), on_command,
                                 qos_for(topics.BREAKER_COMMANDS))
        node.create_subscription(IslandingDecision, topics.relative(topics.ISLANDING_DECISION), on_decision,
                                 qos_for(topics.ISLANDING_DECISION))
        clock_pub = node.create_publisher(Clock, clock_topic, qos_for(topics.CLOCK))
        pubs = {}
        for topic in FUZZ_TOPICS:
            qos = qos_for(topic)
            # A deep writer history: the adversary's own backlog is never what limits what the nodes see. The rest
            # is the topic's own QoS: a writer offering less (e.g. no liveliness lease on /islanding/decision) is
            # not matched, and its messages test nothing.
            deep = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=max(qos.depth, 1000),
                              reliability=qos.reliability, durability=qos.durability, deadline=qos.deadline,
                              lifespan=qos.lifespan, liveliness=qos.liveliness,
                              liveliness_lease_duration=qos.liveliness_lease_duration)
            cls = {topics.PMU_FRAMES: 'PmuFrame', topics.NETWORK_SNAPSHOT: 'NetworkSnapshot',
                   topics.BRANCH_STATUS: 'BranchStatus', topics.ISLANDING_REQUEST: 'IslandingRequest',
                   topics.ROTOR_ANGLES: 'RotorAngles', topics.COHERENT_GROUPS: 'CoherentGroups',
                   topics.ISLANDING_DECISION: 'IslandingDecision'}[topic]
            pubs[topic] = node.create_publisher(message_class(f'controlled_islanding_msgs/msg/{cls}'),
                                                topics.relative(topic), deep)
        last_clock = [0.0]

        def tick(sup: Supervisor) -> None:
            if not replaying[0] and time.monotonic() - last_clock[0] >= 0.02:
                t = sim_now_s()
                clock_pub.publish(Clock(clock=_time(t)))
                last_clock[0] = time.monotonic()
            sup.supervise(heartbeats)

        def spin(sup: Supervisor, seconds: float, done: Callable[[], bool] = lambda: False) -> bool:
            end = time.monotonic() + seconds
            while not done() and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.01)
                tick(sup)
            return done()

        try:
            # The start-up grace of the soak's own machine, which other work may load: a node killed for a slow
            # start before any fuzz message only delays the run (and is reported, not judged).
            policy = replace(PIPELINE_POLICY, startup_grace_s=STARTUP_S)
            with Supervisor(env, results / 'logs', policy, namespace=namespace, remaps=remaps) as sup:
                extra = {'breaker_command': {'audit_log': results / 'breaker_audit.jsonl', 'key_dir': key_dir},
                         'partitioning': {'key_dir': key_dir}}
                for spec in GRAPH:
                    sup.start(spec, {'use_sim_time': True, **extra.get(spec.executable, {})})
                progress(f'fuzz: started {", ".join(names)} (logs in {results / "logs"})')
                if not spin(sup, STARTUP_S, lambda: all(n in heartbeats for n in names)):
                    sup.check_alive()
                    silent = [n for n in names if n not in heartbeats]
                    raise FuzzError(f'no diagnostics within {STARTUP_S:.0f} s from {silent}')
                arm_client = node.create_client(SetArmed, 'breaker_command/set_armed')
                if not arm_client.wait_for_service(timeout_sec=20.0):
                    raise FuzzError(f'breaker_command did not offer {namespace}/breaker_command/set_armed within 20 s')
                future = arm_client.call_async(signing.signed_arm_request(
                    SetArmed.Request(), operator_key, f'{namespace}/breaker_command', True, time.time()))
                if not spin(sup, 10.0, future.done) or not future.result().accepted:
                    why = future.result().message if future.done() else 'no answer within 10 s'
                    raise FuzzError(f'breaker_command refused to arm: {why}')
                for topic in FUZZ_TOPICS:
                    spin(sup, 20.0, lambda t=topic: pubs[t].get_subscription_count() >= len(RECEIVERS[t]))
                report.graph_topics = sorted(name for name, _ in node.get_topic_names_and_types())
                # One honest snapshot first: every later defect is judged against a network the nodes hold.
                good = _copy(seeds.snapshot)
                good.header.stamp = _time(sim_now_s())
                pubs[topics.NETWORK_SNAPSHOT].publish(good)
                spin(sup, 3.0)
                pids = {n: sup.children[n].pid for n in names}
                restarts_at_start = len(sup.restarts)
                rss_before = {n: rss_kb(pids[n]) for n in names}
                trusted = signing.fingerprint(
                    signing.load_public_key(signing.key_paths(key_dir, 'partitioning').public))
                adversary = Adversary(seeds, seed, sim_now_s, trusted)
                # RSS also falls now and then (the allocator gives back the top of a heap), so "levelled off" means
                # no new high by WARM_PLATEAU_KB, not no rise from the round before.
                high, flat = dict(rss_before), 0
                while report.warm_rounds < warm_rounds and flat < 2:
                    for topic in topic_names:
                        _warm_up(topic, adversary, pubs[topic], diagnostics, spin, sup)
                    spin(sup, 2.0)
                    rss_warm = {n: rss_kb(pids[n]) for n in names}
                    report.warm_rss_kb.append(rss_warm)
                    report.warm_rounds += 1
                    grew = any((rss_warm[n] or 0) - (high[n] or 0) >= WARM_PLATEAU_KB for n in names)
                    high = {n: max(high[n] or 0, rss_warm[n] or 0) for n in names}
                    flat = 0 if grew else flat + 1
                progress(f'fuzz: breaker_command armed; {per_topic} messages per topic, seed {seed}; RSS (MB) '
                         f'before / after {report.warm_rounds} warm-up rounds: ' + ', '.join(
                             f'{n} {(rss_before[n] or 0) / 1024:.1f} / {(rss_warm[n] or 0) / 1024:.1f}'
                             for n in names))
                for topic in topic_names:
                    result = _fuzz_topic(topic, per_topic, adversary, pubs[topic], diagnostics, spin, sup)
                    report.topics.append(result)
                    progress(f'fuzz: {topic:<24} sent {result.sent:>6}  received {result.received:>6}  '
                             f'lost {result.lost:>4}  rejected {result.rejected:>6}  errors {result.errors}  '
                             f'{result.wall_s:6.1f} s  RSS (MB) ' + ', '.join(
                                 f'{n} {(kb or 0) / 1024:.1f}' for n, kb in result.rss_kb.items()))
                spin(sup, 2.0)
                for n in names:
                    after = rss_kb(sup.children[n].pid) if sup.children[n].pid == pids[n] else None
                    nr = NodeResult(n, rss_before_kb=rss_before[n], rss_warm_kb=rss_warm[n], rss_after_fuzz_kb=after)
                    if after is not None and rss_before[n] is not None and rss_warm[n] is not None:
                        nr.rss_growth_mb = (after - rss_warm[n]) / 1024.0
                        nr.rss_cold_growth_mb = (after - rss_before[n]) / 1024.0
                    report.nodes.append(nr)
                report.commands_during_fuzz = sum(1 for during_replay, _ in commands if not during_replay)
                catching_up_s[0] = sim_now_s()
                while catching_up_s[0] < seeds.bag_start_s - HANDOVER_GAP_S:
                    catching_up_s[0] = min(catching_up_s[0] + CATCH_UP_STEP_S, seeds.bag_start_s - HANDOVER_GAP_S)
                    stepped = time.monotonic() + 0.05  # a heartbeat after the step's first publish
                    spin(sup, CATCH_UP_WAIT_S, lambda at=stepped: all(heartbeats.get(n, 0.0) > at for n in names))
                spin(sup, 0.1)
                report.replay = _replay(sup, node, spin, bag, entry, seeds, results, decisions, commands,
                                        replaying, PLAYER, progress, clock_topic)
                for nr in report.nodes:
                    nr.startup_restarts = sum(1 for r in sup.restarts[:restarts_at_start] if r.name == nr.name)
                    nr.deaths = sum(1 for r in sup.restarts[restarts_at_start:] if r.name == nr.name)
        except SupervisorError as exc:
            raise FuzzError(str(exc)) from exc
        finally:
            node.destroy_node()
            context.try_shutdown()
    report.wall_s = time.monotonic() - t_start
    report.failures = judge(report)
    (results / 'report.json').write_text(json.dumps(report.as_dict(), indent=2, default=str))
    return report


def _time(t_s: float) -> object:
    from builtin_interfaces.msg import Time

    from controlled_islanding.wire.messages import split_stamp

    sec, nanosec = split_stamp(t_s)
    return Time(sec=sec, nanosec=nanosec)


def _warm_up(topic: str, adversary: Adversary, pub: object, diagnostics: dict, spin: Callable, sup: object) -> None:
    """Publish the largest messages of a topic once each; wait (at most 20 s) until the pacer has taken them."""
    largest = adversary.largest(topic)
    if not largest:
        return
    pacer = PACER[topic]

    def taken() -> int:
        values = diagnostics.get(pacer, {})
        return int(float(values.get('received', '0'))) + int(float(values.get(f'lost.{topic}', '0')))

    start = taken()
    for _, msg in largest:
        pub.publish(msg)
        spin(sup, 20.0, lambda n=start + 1: taken() >= n)
        start = taken()
    spin(sup, 1.0)


@dataclass
class Gap:
    """Wall time between messages to keep-last readers: doubled on a loss, halved after QUIET_MESSAGES without.

    Attributes:
        s: The gap now, s.
        losses: Losses counted so far.
        quiet: Messages sent since the last loss or change.

    """

    s: float = LATEST_ONLY_GAP_S
    losses: int = 0
    quiet: int = 0

    def sent(self, losses: int) -> None:
        """Take the receivers' total count of losses after one more message was sent."""
        if losses > self.losses:
            self.s, self.losses, self.quiet = min(2.0 * self.s, MAX_GAP_S), losses, 0
            return
        self.quiet += 1
        if self.quiet >= QUIET_MESSAGES:
            self.s, self.quiet = max(0.5 * self.s, LATEST_ONLY_GAP_S), 0


def _fuzz_topic(topic: str, n: int, adversary: Adversary, pub: object, diagnostics: dict, spin: Callable,
                sup: object) -> TopicResult:
    """Publish n defective messages on one topic, paced by the receiving node; count what the receivers did."""
    receivers = RECEIVERS[topic]
    pacer = PACER[topic]
    lost_key = f'lost.{topic}'
    result = TopicResult(topic)
    t0 = time.monotonic()
    spin(sup, 0.5)
    before = {r: _counters(diagnostics.get(r, {})) for r in receivers}

    def count(node: str, key: str) -> int:
        try:
            return int(float(diagnostics.get(node, {}).get(key, '0')))
        except ValueError:
            return 0

    received0 = count(pacer, 'received')
    lost0 = {r: count(r, lost_key) for r in receivers}
    taken0 = {r: count(r, 'received') + count(r, lost_key) for r in receivers}

    def received() -> int:
        return count(pacer, 'received') - received0

    def lost(node: str) -> int:
        return count(node, lost_key) - lost0[node]

    written_off = 0
    owed_off = {r: 0 for r in receivers}

    def outstanding() -> int:
        return result.sent - received() - lost(pacer) - written_off

    def owed(node: str) -> int:
        """Messages of this phase a receiver has neither taken nor counted as lost (nor been written off for)."""
        return result.sent - (count(node, 'received') + count(node, lost_key) - taken0[node]) - owed_off[node]

    latest_only = topic in LATEST_ONLY
    gap = Gap()
    for _ in range(n):
        kind, msg = adversary.make(topic)
        result.kinds[kind] = result.kinds.get(kind, 0) + 1
        pub.publish(msg)
        result.sent += 1
        if latest_only:
            gap.sent(sum(lost(r) for r in receivers))
        big = latest_only and kind.startswith(('over_cap', 'at_cap'))
        if big:
            # Taken by every receiver: each has taken or counted as lost everything sent so far, or taken one more
            # message since this one was published (the loss of the last one is counted only at the next).
            at_publish = {r: count(r, 'received') for r in receivers}
            progress_at, seen = time.monotonic(), {r: owed(r) for r in receivers}

            def all_took(at_publish: dict[str, int] = at_publish) -> bool:
                nonlocal progress_at, seen
                now = {r: owed(r) for r in receivers}
                if now != seen:
                    progress_at, seen = time.monotonic(), now
                took = all(v <= 0 or count(r, 'received') > at_publish[r] for r, v in now.items())
                return took or time.monotonic() - progress_at > BIG_STALL_S

            spin(sup, BIG_WAIT_S, all_took)
            for r in receivers:
                owed_off[r] += max(0, owed(r))
            if outstanding() > 0:
                written_off += outstanding()
        elif outstanding() >= PACE_WINDOW:
            # Wait for the pacer to catch up, but only while it makes progress.
            target = PACE_WINDOW // 2
            progress_at, seen = time.monotonic(), outstanding()

            def caught_up(target: int = target) -> bool:
                nonlocal progress_at, seen
                if outstanding() != seen:
                    progress_at, seen = time.monotonic(), outstanding()
                return seen < target or time.monotonic() - progress_at > STALL_S

            if not spin(sup, 10.0, caught_up) or outstanding() >= target:
                written_off += max(0, outstanding() - (target - 1))
        else:
            spin(sup, gap.s if latest_only else 0.0)

    def snapshot() -> dict:
        return {r: _counters(diagnostics.get(r, {})) for r in receivers}

    # Settled: every message arrived, or the counters stood still for 2 s (at most 30 s: requests wait 2 s).
    last, since, end = snapshot(), time.monotonic(), time.monotonic() + 30.0
    while time.monotonic() < end:
        spin(sup, 0.25)
        now = snapshot()
        if now != last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= 2.0 and (outstanding() + written_off <= 0
                                                   or time.monotonic() - since >= 4.0):
            break
    for r in receivers:
        grown = {k: v - before[r].get(k, 0) for k, v in last[r].items() if v - before[r].get(k, 0) > 0}
        result.by_node[r] = grown
        result.rejected += sum(grown.values())
        result.errors += sum(v for k, v in grown.items() if k.startswith('error.'))
    result.received = received()
    result.lost = sum(lost(r) for r in receivers)
    result.unaccounted = max(0, result.sent - result.received - lost(pacer))
    result.wall_s = time.monotonic() - t0
    result.rss_kb = {name: rss_kb(child.pid) for name, child in sup.children.items()}
    return result


def _replay(sup: object, node: object, spin: Callable, bag: Path, entry: dict, seeds: Seeds, results: Path,
            decisions: dict, commands: list, replaying: list, player_spec: object,
            progress: Callable[[str], None], clock_topic: str = topics.CLOCK) -> ReplayResult:
    """Play the bag as fast as possible (lockstep at the request) into the graph that took the fuzz."""
    expected = entry.get('expected_decision', {})
    out = ReplayResult(bag=entry.get('name', bag.name), expected_split=expected.get('split'),
                       expected_cut=sorted(expected.get('cut_branches', [])))
    replaying[0] = True  # the bag's /clock takes over; the fuzz clock stops
    played = [topics.NETWORK_SNAPSHOT, topics.PMU_FRAMES, topics.BRANCH_STATUS, topics.ISLANDING_REQUEST,
              topics.CLOCK]
    counts = {t: node.count_subscribers(clock_topic if t == topics.CLOCK else topics.relative(t)) for t in played}
    report_file = results / 'player_report.json'
    progress(f'fuzz: replaying {out.bag} as fast as possible through the same graph')
    player = sup.start(player_spec, {'bag': bag.resolve(), 'as_fast_as_possible': True,
                                     'report_file': report_file, 'clock_min_step_s': 0.05,
                                     'min_subscribers': str([f'{t}={n}' for t, n in counts.items()])},
                       name='bag_player')
    request_id = seeds.request.request_id
    spin(sup, 90.0, lambda: player.poll() is not None and request_id in decisions)
    spin(sup, 1.0)  # the command follows the decision
    decision = decisions.get(request_id)
    if decision is not None:
        out.status = int(decision.status)
        out.split = bool(decision.split)
        out.cut = sorted(str(c) for c in decision.cut_branch_ids)
        out.breaker_commands = [str(c.breaker_id) for during, c in commands
                                if during and c.decision_id == decision.decision_id]
    out.agrees = decision is not None and out.split == out.expected_split and out.cut == out.expected_cut
    return out


def judge(report: FuzzReport) -> list[str]:
    """Return one line per check that failed."""
    failures = []
    for t in report.topics:
        if t.rejected <= 0:
            failures.append(f'{t.topic}: no rejection counted by {", ".join(RECEIVERS[t.topic])} for {t.sent} messages')
        if t.errors:
            failures.append(f'{t.topic}: {t.errors} exceptions escaped callbacks (error.* in /diagnostics)')
    for n in report.nodes:
        if n.deaths:
            failures.append(f'{n.name}: died or hung {n.deaths} time(s)')
        if n.rss_growth_mb is None:
            failures.append(f'{n.name}: RSS not measured (process gone)')
        elif n.rss_growth_mb >= RSS_LIMIT_MB:
            failures.append(f'{n.name}: RSS grew {n.rss_growth_mb:.1f} MB (limit {RSS_LIMIT_MB:.0f} MB)')
    if report.commands_during_fuzz:
        failures.append(f'{report.commands_during_fuzz} breaker command(s) issued during the fuzz')
    r = report.replay
    if r is None or r.status is None:
        failures.append('the replay after the fuzz got no decision')
    elif not r.agrees:
        failures.append(f'the replay after the fuzz decided split={r.split} cut={r.cut}; the manifest expects '
                        f'split={r.expected_split} cut={r.expected_cut}')
    return failures


def render(report: FuzzReport) -> str:
    """Return the report as tables."""
    lines = [f'fuzz soak: {report.per_topic} messages per topic, seed {report.seed}, {report.wall_s:.0f} s',
             '',
             f'{"topic":<24} {"sent":>7} {"received":>9} {"lost":>6} {"rejected":>9} {"errors":>7} {"wall s":>7}  '
             'top rejection reasons']
    for t in report.topics:
        merged: dict[str, int] = {}
        for node_name, counters in t.by_node.items():
            for key, value in counters.items():
                merged[f'{node_name}:{key.split(".", 1)[1]}'] = value
        top = ', '.join(f'{k}={v}' for k, v in sorted(merged.items(), key=lambda kv: -kv[1])[:4])
        lines.append(f'{t.topic:<24} {t.sent:>7} {t.received:>9} {t.lost:>6} {t.rejected:>9} {t.errors:>7} '
                     f'{t.wall_s:>7.0f}  {top}')
    lines += ['', f'{"node":<16} {"deaths":>6} {"RSS cold MB":>12} {"warm MB":>8} {"after MB":>9} '
                  f'{"growth MB":>10} {"(from cold)":>12}']

    def mb(kb: int | None) -> str:
        return f'{kb / 1024:.1f}' if kb else '-'

    for n in report.nodes:
        growth = f'{n.rss_growth_mb:+.1f}' if n.rss_growth_mb is not None else '-'
        cold = f'({n.rss_cold_growth_mb:+.1f})' if n.rss_cold_growth_mb is not None else '-'
        lines.append(f'{n.name:<16} {n.deaths:>6} {mb(n.rss_before_kb):>12} {mb(n.rss_warm_kb):>8} '
                     f'{mb(n.rss_after_fuzz_kb):>9} {growth:>10} {cold:>12}')
    lines.append(f'growth MB = after - warm: the warm-up sent each node the largest message of every kind, '
                 f'{report.warm_rounds} rounds, until its RSS levelled off (limit {RSS_LIMIT_MB:.0f} MB)')
    slow = [f'{n.name} {n.startup_restarts}' for n in report.nodes if n.startup_restarts]
    if slow:
        lines.append(f'restarted before the first fuzz message (no heartbeat in time at start-up; not judged): '
                     f'{", ".join(slow)}')
    lines += ['', f'breaker commands during the fuzz: {report.commands_during_fuzz}']
    r = report.replay
    if r is not None:
        got = 'no decision' if r.status is None else f'split={r.split} cut {", ".join(r.cut) or "nothing"}'
        lines.append(f'replay of {r.bag} afterwards ({r.graph} graph): {got}; manifest expects cut '
                     f'{", ".join(r.expected_cut) or "nothing"} -> {"agrees" if r.agrees else "DIFFERS"}'
                     + (f'; commanded {", ".join(r.breaker_commands)}' if r.breaker_commands else ''))
    lines.append(f'results: {report.results_dir}')
    lines.append('PASS' if report.passed else 'FAIL:\n  ' + '\n  '.join(report.failures))
    return '\n'.join(lines)
