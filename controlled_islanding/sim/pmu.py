"""PMU measurements from a simulation: resampling, C37.118-style noise, and impairments.

Measurement model (all seeded, independent streams per quantity so that turning an impairment on
changes nothing else):
- Time tags k / rate_fps from 0 to end_s. Simulated quantities are linearly interpolated from ANDES'
  non-uniform grid; angles are continuous and the current angle is unwrapped.
- Channels: a PMU at a bus with at most one generator has one channel, station id `PMU_<bus>`, whose current
  is that generator's, I = conj((P + jQ) / V), pu on the system base (zero at a bus with no generator). At a
  bus with several generators the PMU has one channel per generator, station id `PMU_<bus>/<generator name>`,
  each with the current that generator injects: a bus total belongs to none of them, and the rotor angle
  estimate V + (ra + j xq) I needs the machine's own current.
- The voltage phasor is the bus voltage, one measurement per bus shared by its channels (one PMU, one PT),
  its magnitude never negative (where ANDES' is, the angle is turned by pi instead, as a PMU's phasor turns).
- Each phasor is multiplied by (1 + e) with e complex Gaussian, |e| clipped to noise_tve, so the total
  vector error never exceeds noise_tve (<= 1 %).
- Frequency is f0 + (d angle / dt) / (2 pi) of the noise-free voltage angle plus 1 mHz rms noise;
  ROCOF is its time derivative plus 10 mHz/s rms noise.

Impairments and how lost data appears (loss, silence and voltage noise are per PMU, so per bus; current noise
is per channel):
- A lost measurement stays in its frame with STAT = STAT_DATA_INVALID and NaN values.
- A frame in which every PMU's data is lost (for example during the initial gap) is absent from the bag.
- Delivery time = time tag + max(0, N(delay_mean_s, delay_jitter_s)); frames are recorded in delivery
  order, so jitter above one frame period reorders them. Without delay, delivery time = time tag.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from controlled_islanding.sim.andes_sim import Simulation
from controlled_islanding.sim.scenario import Scenario
from controlled_islanding.wire.bagdata import PmuChannels

if TYPE_CHECKING:
    from controlled_islanding.sim.closed_loop import Sample

STAT_DATA_INVALID = 0x8000
FREQUENCY_NOISE_HZ = 0.001
ROCOF_NOISE_HZ_PER_S = 0.01


Frame = PmuChannels  # one frame of the closed loop's stream


@dataclass(frozen=True)
class PmuData(PmuChannels):
    """Every PMU's measurements on the time-tag grid of a whole run (PmuChannels with a leading time axis).

    Attributes:
        frame_present: Whether the frame is recorded at all, shape (n,).
        truth_delta_rad: Simulated rotor angles at the time tags, rad, shape (n, n_gen).

    """

    frame_present: np.ndarray
    truth_delta_rad: np.ndarray


def time_tags(end_s: float, rate_fps: int) -> np.ndarray:
    """Return the time tags k / rate_fps, s, from 0 up to and including end_s."""
    return np.arange(int(np.floor(end_s * rate_fps + 1e-9)) + 1) / rate_fps


def _interp(t_new: np.ndarray, t: np.ndarray, values: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(t_new, t, values[:, j]) for j in range(values.shape[1])])


def _as_measured(v: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ANDES' signed voltage and continuous angle as a PMU reports the same phasor: |V|, the angle turned by pi.

    Why: past a pole slip's electrical centre ANDES may carry a bus at V < 0 (IEEE 39 G3's bus 32 down to -1.6
    pu for seconds); a PMU's magnitude is never negative, and a bag that said otherwise differed from the same
    frames sent over C37.118.
    """
    return np.abs(v), np.where(v < 0, a + np.pi, a)


def _noisy(rng: np.random.Generator, mag: np.ndarray, ang: np.ndarray, tve: float) -> tuple[np.ndarray, np.ndarray]:
    e = (rng.standard_normal(mag.shape) + 1j * rng.standard_normal(mag.shape)) * (tve / 3.0)
    size = np.abs(e)
    e = np.where(size > tve, e * (tve / np.maximum(size, 1e-300)), e)
    factor = 1.0 + e
    return mag * np.abs(factor), ang + np.angle(factor)


def measure(sim: Simulation, scenario: Scenario) -> PmuData:
    """Turn a simulation into the scenario's PMU data.

    Args:
        sim: The ANDES results.
        scenario: Gives the PMU rate and buses, noise, seed and impairments.

    Returns:
        The PMU data.

    """
    tags = time_tags(scenario.end_s, scenario.rate_fps)
    if scenario.pmu_buses is None:
        buses = tuple(dict.fromkeys(sim.generator_buses))
    else:
        buses = scenario.pmu_buses
    columns = [sim.bus_numbers.index(b) for b in buses]
    v = _interp(tags, sim.t_s, sim.bus_v_pu[:, columns])
    a = _interp(tags, sim.t_s, sim.bus_angle_rad[:, columns])
    p = _interp(tags, sim.t_s, sim.p_pu)
    q = _interp(tags, sim.t_s, sim.q_pu)
    stations, channel_bus, channel_gens = [], [], []  # channel_bus indexes `buses`
    for j, bus in enumerate(buses):
        gens = [g for g, gb in enumerate(sim.generator_buses) if gb == bus]
        for group in ([gens] if len(gens) <= 1 else [[g] for g in gens]):
            stations.append(f'PMU_{bus}' if len(gens) <= 1 else f'PMU_{bus}/{sim.generator_names[group[0]]}')
            channel_bus.append(j)
            channel_gens.append(group)
    current = np.zeros((len(tags), len(stations)), dtype=complex)
    for c, (j, gens) in enumerate(zip(channel_bus, channel_gens, strict=True)):
        for g in gens:
            current[:, c] += np.conj((p[:, g] + 1j * q[:, g]) / (v[:, j] * np.exp(1j * a[:, j])))
    i_mag = np.abs(current)
    i_ang = np.unwrap(np.angle(current), axis=0)

    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(scenario.seed).spawn(6)]
    v_mag, v_ang = _noisy(streams[0], *_as_measured(v, a), scenario.noise_tve)
    i_mag, i_ang = _noisy(streams[1], i_mag, i_ang, scenario.noise_tve)
    f_clean = sim.freq_hz + np.gradient(a, tags, axis=0) / (2 * np.pi)
    freq = f_clean + streams[2].normal(0.0, FREQUENCY_NOISE_HZ, f_clean.shape)
    rocof = np.gradient(f_clean, tags, axis=0) + streams[3].normal(0.0, ROCOF_NOISE_HZ_PER_S, f_clean.shape)

    imp = scenario.impairments
    lost = streams[4].random(v.shape) < imp.frame_loss_rate
    lost[tags < imp.initial_gap_s, :] = True
    if imp.silent_pmu_bus is not None:
        lost[tags >= imp.silent_from_s, buses.index(imp.silent_pmu_bus)] = True
    delay = np.maximum(0.0, streams[5].normal(imp.delay_mean_s, imp.delay_jitter_s, tags.shape)) \
        if imp.delay_mean_s > 0 or imp.delay_jitter_s > 0 else np.zeros_like(tags)
    # Per-bus quantities spread over the bus's channels.
    v_mag, v_ang, freq, rocof, lost = (x[:, channel_bus] for x in (v_mag, v_ang, freq, rocof, lost))
    stat = np.where(lost, STAT_DATA_INVALID, 0).astype(np.uint16)
    out = []
    for arr in (v_mag, v_ang, i_mag, i_ang, freq, rocof):
        arr = arr.copy()
        arr[lost] = np.nan
        out.append(arr)
    return PmuData(
        tag_s=tags, delivery_s=tags + delay, station_ids=tuple(stations), buses=tuple(buses[j] for j in channel_bus),
        v_mag_pu=out[0], v_angle_rad=out[1], i_mag_pu=out[2], i_angle_rad=out[3], frequency_hz=out[4],
        rocof_hz_per_s=out[5], stat=stat, frame_present=~lost.all(axis=1),
        truth_delta_rad=_interp(tags, sim.t_s, sim.delta_rad))


class PmuStream:
    """Turns the run's samples into PMU frames as they come, with `measure`'s channels, noise and impairments.

    Differences from `measure`, which sees the whole run at once: frequency is the backward difference of the
    noise-free voltage angle between consecutive tags (not a central difference, which needs the next tag) and
    ROCOF the backward difference of that; noise draws come from the same seeded streams but in frame order.
    """

    def __init__(self, scenario: Scenario, generator_names: Sequence[str], generator_buses: Sequence[int],
                 bus_numbers: Sequence[int], f0_hz: float) -> None:

        self.scenario = scenario
        self.f0_hz = f0_hz
        buses = tuple(dict.fromkeys(generator_buses)) if scenario.pmu_buses is None else scenario.pmu_buses
        self.bus_cols = [list(bus_numbers).index(b) for b in buses]
        stations, channel_bus, channel_gens = [], [], []
        for j, bus in enumerate(buses):
            gens = [g for g, gb in enumerate(generator_buses) if gb == bus]
            for group in ([gens] if len(gens) <= 1 else [[g] for g in gens]):
                stations.append(f'PMU_{bus}' if len(gens) <= 1 else f'PMU_{bus}/{generator_names[group[0]]}')
                channel_bus.append(j)
                channel_gens.append(group)
        self.station_ids = tuple(stations)
        self.channel_bus = channel_bus
        self.channel_gens = channel_gens
        self.buses = tuple(buses[j] for j in channel_bus)
        self.pmu_buses = buses
        self.next_k = 0
        self.prev: Sample | None = None
        self.streams = [np.random.default_rng(s) for s in np.random.SeedSequence(scenario.seed).spawn(6)]
        self._last_angle: np.ndarray | None = None
        self._last_freq: np.ndarray | None = None
        self._last_i_angle: np.ndarray | None = None

    def feed(self, sample: Sample) -> list[Frame]:
        """Take the next step's state; return the frames whose tags it passed (possibly none)."""
        out = []
        rate = self.scenario.rate_fps
        while self.next_k / rate <= sample.t_s + 1e-9:
            tag = self.next_k / rate
            prev = self.prev if self.prev is not None and self.prev.t_s < sample.t_s else sample
            w = 0.0 if sample.t_s <= prev.t_s else (tag - prev.t_s) / (sample.t_s - prev.t_s)
            w = min(1.0, max(0.0, w))

            def at(name: str, p: Sample = prev, x: float = w) -> np.ndarray:
                return (1 - x) * getattr(p, name) + x * getattr(sample, name)

            v = at('bus_v_pu')[self.bus_cols]
            a = at('bus_angle_rad')[self.bus_cols]
            p, q = at('p_pu'), at('q_pu')
            current = np.zeros(len(self.station_ids), dtype=complex)
            for c, (j, gens) in enumerate(zip(self.channel_bus, self.channel_gens, strict=True)):
                for g in gens:
                    current[c] += np.conj((p[g] + 1j * q[g]) / (v[j] * np.exp(1j * a[j])))
            i_ang = np.angle(current)
            if self._last_i_angle is not None:  # keep the current angle continuous, as np.unwrap would
                i_ang = self._last_i_angle + np.angle(np.exp(1j * (i_ang - self._last_i_angle)))
            self._last_i_angle = i_ang
            s = self.streams
            v_mag, v_ang = _noisy(s[0], *_as_measured(v, a), self.scenario.noise_tve)
            i_mag, i_ang_n = _noisy(s[1], np.abs(current), i_ang, self.scenario.noise_tve)
            f_clean = (np.full(len(v), self.f0_hz) if self._last_angle is None else
                       self.f0_hz + (a - self._last_angle) * rate / (2 * np.pi))
            rocof_clean = np.zeros(len(v)) if self._last_freq is None else (f_clean - self._last_freq) * rate
            self._last_angle, self._last_freq = a, f_clean
            freq = f_clean + s[2].normal(0.0, FREQUENCY_NOISE_HZ, f_clean.shape)
            rocof = rocof_clean + s[3].normal(0.0, ROCOF_NOISE_HZ_PER_S, f_clean.shape)
            imp = self.scenario.impairments
            lost = s[4].random(len(v)) < imp.frame_loss_rate
            if tag < imp.initial_gap_s:
                lost[:] = True
            if imp.silent_pmu_bus is not None and tag >= imp.silent_from_s:
                lost[list(self.pmu_buses).index(imp.silent_pmu_bus)] = True
            delay = (max(0.0, float(s[5].normal(imp.delay_mean_s, imp.delay_jitter_s)))
                     if imp.delay_mean_s > 0 or imp.delay_jitter_s > 0 else 0.0)
            cb = self.channel_bus
            lost_c = lost[cb]
            arrays = [x.copy() for x in (v_mag[cb], v_ang[cb], i_mag, i_ang_n, freq[cb], rocof[cb])]
            for arr in arrays:
                arr[lost_c] = np.nan
            self.next_k += 1
            if lost_c.all():
                continue  # a frame in which every PMU's data is lost is not sent at all
            out.append(Frame(tag_s=tag, delivery_s=tag + delay, station_ids=self.station_ids, buses=self.buses,
                             v_mag_pu=arrays[0], v_angle_rad=arrays[1], i_mag_pu=arrays[2], i_angle_rad=arrays[3],
                             frequency_hz=arrays[4], rocof_hz_per_s=arrays[5],
                             stat=np.where(lost_c, STAT_DATA_INVALID, 0).astype(np.uint16)))
        self.prev = sample
        return out
