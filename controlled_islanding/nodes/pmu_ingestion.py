"""pmu_ingestion: the PDC end of the graph. PMU frames in, one rotor-angle sample per time tag out.

Frames are published as soon as they arrive, stamped with their time tag, so a frame never waits for a late
one; the coherency node orders its window by time tag. A frame repeating a time tag already seen is a
duplicate; one older than the newest by more than `max_delay_s` is too late. A PMU whose STAT says "do not
use", or that is absent from the frame, gives `valid = false` for its generator. Rotor angles come from the
core estimator with the generator reactances of the latest /network/snapshot.
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque

import numpy as np
from controlled_islanding_msgs.msg import NetworkSnapshot, PmuFrame, PmuMeasurement, RotorAngles
from rclpy.node import Node

from controlled_islanding import topics
from controlled_islanding.core.grid import Grid
from controlled_islanding.messages import MessageError, grid_from_snapshot, stamp_s
from controlled_islanding.node_common import Diagnostics, NodeSetupError, qos_for, spin_node

_UNUSABLE = 0x8000  # STAT bit 15: 10 = data invalid, 11 = PMU error
_FIELDS = ('voltage_magnitude_pu', 'voltage_angle_rad', 'current_magnitude_pu', 'current_angle_rad')


class PmuIngestionNode(Node):
    """Turns PMU frames into rotor angles."""

    def __init__(self) -> None:
        super().__init__('pmu_ingestion')
        self.declare_parameter('rate_fps', 60.0)
        self.declare_parameter('max_delay_s', 1.0)
        self.declare_parameter('stale_pmu_s', 0.5)
        self.rate_fps = float(self.get_parameter('rate_fps').value)
        self.max_delay_s = float(self.get_parameter('max_delay_s').value)
        self.stale_pmu_s = float(self.get_parameter('stale_pmu_s').value)
        if self.rate_fps <= 0:
            raise NodeSetupError(f'rate_fps={self.rate_fps} must be positive')
        self.grid: Grid | None = None
        # Topics are not ordered against each other: frames may overtake the snapshot. Hold them until it comes.
        self.early: deque[PmuFrame] = deque()
        self.seen: deque[int] = deque(maxlen=4096)
        self.seen_set: set[int] = set()
        self.unique_frames = 0
        self.first_s = math.inf
        self.newest_s = -math.inf
        self.last_valid_s: dict[str, float] = {}
        self.last_angle_rad: dict[str, float] = {}
        self.diag = Diagnostics(self)
        self.pub = self.create_publisher(RotorAngles, topics.ROTOR_ANGLES, qos_for(topics.ROTOR_ANGLES))
        self.create_subscription(NetworkSnapshot, topics.NETWORK_SNAPSHOT, self.on_snapshot,
                                 qos_for(topics.NETWORK_SNAPSHOT))
        self.create_subscription(PmuFrame, topics.PMU_FRAMES, self.on_frame, qos_for(topics.PMU_FRAMES))

    def on_snapshot(self, msg: NetworkSnapshot) -> None:
        """Take the generators (names, buses, reactances) from a snapshot."""
        try:
            self.grid = grid_from_snapshot(msg)
        except MessageError as exc:
            self.diag.reject(exc.reason, f'network snapshot: {exc}')
            return
        while self.early:
            self.on_frame(self.early.popleft(), counted=True)

    def _usable(self, m: PmuMeasurement, buses: set[int], stations: set[str]) -> bool:
        if m.station_id in stations:
            self.diag.reject('duplicate', f'PMU {m.station_id} appears twice in one frame')
            return False
        stations.add(m.station_id)
        if int(m.bus) not in buses:
            self.diag.reject('unknown_id', f'PMU {m.station_id} reports bus {m.bus}, not in the network')
            return False
        if m.stat & _UNUSABLE:
            return False
        if not all(math.isfinite(getattr(m, f)) for f in _FIELDS):
            self.diag.reject('nan_value', f'PMU {m.station_id}: NaN or inf phasor with a good STAT')
            return False
        return True

    def on_frame(self, frame: PmuFrame, counted: bool = False) -> None:
        """Check a frame, estimate each generator's rotor angle, publish."""
        if not counted:
            self.diag.arrived()
        t0 = time.perf_counter()
        t = stamp_s(frame.header.stamp)
        if t <= 0:
            self.diag.reject('missing_stamp', 'PMU frame header.stamp (time tag) is zero')
            return
        if not frame.measurements:
            self.diag.reject('empty_message', f'PMU frame at {t:.3f} s has no measurements')
            return
        if self.grid is None:
            self.early.append(frame)
            if stamp_s(self.early[-1].header.stamp) - stamp_s(self.early[0].header.stamp) > self.max_delay_s:
                self.early.popleft()
                self.diag.reject('no_data', f'PMU frames for more than max_delay_s={self.max_delay_s} before any '
                                            'network snapshot: generator reactances unknown')
            return
        key = int(round(t * self.rate_fps))
        if key in self.seen_set:
            self.diag.reject('duplicate', f'PMU frame time tag {t:.6f} s already seen')
            return
        if t < self.newest_s - self.max_delay_s:
            self.diag.reject('time_backwards', f'PMU frame at {t:.3f} s is {self.newest_s - t:.3f} s older than '
                                               f'the newest; more than max_delay_s={self.max_delay_s}')
            return
        if len(self.seen) == self.seen.maxlen:
            self.seen_set.discard(self.seen[0])
        self.seen.append(key)
        self.seen_set.add(key)
        self.unique_frames += 1
        self.first_s, self.newest_s = min(self.first_s, t), max(self.newest_s, t)
        buses, stations = set(self.grid.buses), set()
        by_bus = {}
        for m in frame.measurements:
            if self._usable(m, buses, stations):
                by_bus[int(m.bus)] = m
                self.last_valid_s[m.station_id] = max(self.last_valid_s.get(m.station_id, t), t)
            else:
                self.last_valid_s.setdefault(m.station_id, -math.inf)
        self.pub.publish(self._angles(frame, by_bus))
        self._account(t0)

    def _angles(self, frame: PmuFrame, by_bus: dict[int, PmuMeasurement]) -> RotorAngles:
        from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad

        assert self.grid is not None
        gens = self.grid.generators
        valid = np.array([g.bus in by_bus for g in gens])
        angles = np.zeros(len(gens))
        if valid.any():
            idx = np.flatnonzero(valid)
            cols = np.array([[getattr(by_bus[gens[i].bus], f) for f in _FIELDS] for i in idx])
            # One row = one time tag: the estimator unwraps along rows, never across generators.
            raw = estimate_rotor_angle_rad(
                cols[None, :, 0], cols[None, :, 1], cols[None, :, 2], cols[None, :, 3],
                np.array([gens[i].xq_pu for i in idx]), np.array([gens[i].ra_pu for i in idx]))[0]
            # Unwrap along time, frame by frame, against the last angle of each generator: at 60 frames/s a
            # rotor moves far less than pi between frames, even slipping poles.
            ref = np.array([self.last_angle_rad.get(gens[i].name, raw[j]) for j, i in enumerate(idx)])
            angles[idx] = ref + np.angle(np.exp(1j * (raw - ref)))
        valid &= np.isfinite(angles)
        for i in np.flatnonzero(valid):
            self.last_angle_rad[gens[i].name] = float(angles[i])
        return RotorAngles(header=frame.header, generator_names=[g.name for g in gens],
                           generator_buses=[g.bus for g in gens], angle_rad=np.where(valid, angles, 0.0).tolist(),
                           valid=valid.tolist())

    def _account(self, t0: float) -> None:
        self.diag.computed(time.perf_counter() - t0)
        expected = int(round((self.newest_s - self.first_s) * self.rate_fps)) + 1
        self.diag.values['missing_frames'] = str(max(0, expected - self.unique_frames))
        if self.unique_frames % 30:
            return  # stale PMUs change slowly; refreshing them twice a second at 60 frames/s is plenty
        stale = sorted(s for s, last in self.last_valid_s.items() if self.newest_s - last > self.stale_pmu_s)
        self.diag.values['stale_pmus'] = str(len(stale))
        self.diag.values['stale_pmu_ids'] = ','.join(stale)


def main(args: list[str] | None = None) -> int:
    """Run the pmu_ingestion node."""
    return spin_node(PmuIngestionNode, args)


if __name__ == '__main__':
    sys.exit(main())
