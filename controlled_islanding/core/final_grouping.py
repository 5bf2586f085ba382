"""The predicted final grouping: the one rule the stability monitor and the coherency node share.

Coherent groups are the groups the grid is predicted to END in (issue 30), not the ones it is in: a pair that is
drifting apart but slowing down, predicted to return, is not split. Both nodes feed a `SwingWatch` every
rotor-angle sample in time-tag order (what /rotor_angles carries: the filter's angle, speed and torque, and the
measured Re(V I*) and |V| of each machine), so both see the same predictions:

- the stability monitor asks for islanding when the watch raises a swing's alarm, with its groups and predicted
  first pole slip;
- the coherency node, asked for the groups of a request stamped T, takes `final_groups(watch.at(T), ...)`: the
  predicted groups when the watch has an alarm standing at T (so the monitor's request and the decision agree on
  k), else its DTW rule's groups (core/k_rules.py) less the splits the prediction says come back.

A swing is the predictor's (core/stability.py): the frames since the latest network switching it saw. Its alarm
is raised at the first frame at which the chosen predictor (SIME, docs/prediction.md) says with confidence that
the grid separates, once per swing; a later confident prediction in the same swing updates the groups that stand
(a later request is answered with what is known then) but raises nothing, and while the swing returns nothing is
raised at all. A new switching (a second fault, a trip, the islanding itself) starts a new swing, which must
alarm on its own; and its alarm is raised only when it splits a group of the last alarm raised further (a new
separation inside a group already asked for). After the islanding the islands drift apart, and the predictor
rightly sees them separate along the cut already asked for: asking again would only repeat the decision, its load
sheds included (a Kundur closed loop shed bus 8's 175 MW twice).

Which splits come back: the DTW rule splits pairs it sees heading for a pole slip, by their drift over the window
or their run from rest. The watch's own verdict on the same split (the OMIB of one group against the rest, on the
present swing) overrules it when it is confident that the split returns (z at or below -z_alarm: the equal-area
margin is positive by as many standard errors as an alarm needs, or no unstable equilibrium lies ahead), and so
does the measured motion when the pair is already heading back (the groups' inertia-weighted centres approach
each other, by the filter's speeds): a separation not under way is no separation. Neither overrules a pair that
has already slipped a pole (pi rad from where it rested): that separation is measured, not predicted.
A verdict in doubt leaves the rule's split standing: a split the rule sees and nothing contradicts is not
thrown away.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from controlled_islanding.core.stability import POLE_SLIP_RAD, MachineSet, SIMEPredictor, _chi2_bound

__all__ = ['STAMP_ROUNDING_S', 'Alarm', 'SwingWatch', 'final_groups', 'warm_up']

# A time tag's float seconds and its stamp's nanoseconds agree to within this, s (far below a frame period).
STAMP_ROUNDING_S = 1e-6


@dataclass(frozen=True)
class Alarm:
    """A confident prediction that the grid separates, standing for its swing.

    Attributes:
        t_s: Time tag of the frame it was made at (the first alarm of the swing: when it was raised), s.
        groups: Predicted final group per machine, 0-based, numbered by first member.
        first_slip_s: Predicted time of the first pole slip, s.
        confidence: The critical verdict's z over the alarm bar (>= 1).
        swing_start_s: First frame of the swing it belongs to, s.
        raised_s: Time tag of the frame the swing's first alarm was raised at, s.

    """

    t_s: float
    groups: np.ndarray
    first_slip_s: float
    confidence: float
    swing_start_s: float
    raised_s: float

    @property
    def k(self) -> int:
        """Return the number of predicted groups."""
        return int(self.groups.max()) + 1


class SwingWatch:
    """The chosen predictor over every frame, its alarms latched per swing and remembered by time tag.

    Args:
        machines: The machines (core.stability.MachineSet), in the frames' column order.
        keep_s: How long, s of time tags, the state after each frame is remembered for `at`.
        **settings: SIMEPredictor settings (noise_tve, z_alarm, history_s, max_groups, time_to_act_s).

    Attributes:
        predictor: The SIMEPredictor, as after the latest frame taken.
        alarm_: The alarm standing after the latest frame (None: none in the present swing).
        raised_groups_: The groups of the last alarm raised (None before the first).
        frames_: Frames taken (usable ones, in time-tag order).
        skipped_: Frames not taken: a time tag not after the latest one taken, or a machine without angle or speed.

    """

    def __init__(self, machines: MachineSet, keep_s: float = 6.0, **settings) -> None:
        self.machines = machines
        self.predictor = SIMEPredictor(machines, **settings)
        self.keep_s = float(keep_s)
        self.alarm_: Alarm | None = None
        self.raised_groups_: np.ndarray | None = None
        self.frames_ = 0
        self.skipped_ = 0
        self._times: deque[float] = deque()
        self._states: deque[Alarm | None] = deque()
        self._rest: np.ndarray | None = None
        self._last_s = -math.inf

    def update(self, t_s: float, delta_rad, omega_pu, pe_pu, v_pu=None, valid=None, pm_pu=None) -> Alarm | None:
        """Take one frame (SIMEPredictor.update's arguments); return the alarm it raised, if it raised one.

        A frame whose time tag is not after the latest one taken (a late frame) is skipped, as the predictor needs
        time-tag order; so is one with a machine's angle or speed unknown.
        """
        t = float(t_s)
        delta = np.asarray(delta_rad, dtype=float)
        omega = np.asarray(omega_pu, dtype=float)
        if not t > self._last_s or not (np.isfinite(delta).all() and np.isfinite(omega).all()):
            self.skipped_ += 1
            return None
        self._last_s = t
        self.frames_ += 1
        if self._rest is None:
            self._rest = delta.copy()
        p = self.predictor.update(t, delta, omega, pe_pu, v_pu, valid, pm_pu)
        swing = p.swing_start_s_
        if self.alarm_ is not None and not (math.isfinite(swing) and swing == self.alarm_.swing_start_s):
            self.alarm_ = None  # a new switching: a new swing, which must alarm on its own
        raised = None
        if p.separates_:
            first = self.alarm_ is None
            self.alarm_ = Alarm(t, p.groups_.copy(), float(p.first_slip_s_), float(p.confidence_), float(swing),
                                t if first else self.alarm_.raised_s)
            if first and _refines(self.alarm_.groups, self.raised_groups_):
                raised = self.alarm_
                self.raised_groups_ = self.alarm_.groups
        self._times.append(t)
        self._states.append(self.alarm_)
        while self._times and self._times[0] < t - self.keep_s:
            self._times.popleft()
            self._states.popleft()
        return raised

    @property
    def last_t_s(self) -> float:
        """Return the time tag of the latest frame taken, s (-inf before any)."""
        return self._last_s

    def at(self, t_s: float) -> Alarm | None:
        """Return the alarm that stood after the newest frame at or before t_s (None: none, or not remembered).

        A frame within STAMP_ROUNDING_S after t_s counts as at it: a request stamped at a frame's time tag goes
        through integer nanoseconds and back, and a POSIX time in float seconds keeps only about 0.2 us (a request
        of the monitor's, a hair before its own frame, found no alarm and was answered with one group).
        """
        i = bisect.bisect_right(self._times, float(t_s) + STAMP_ROUNDING_S)
        return self._states[i - 1] if i else None

    def returning(self, labels: np.ndarray) -> np.ndarray:
        """Return, for each two groups of labels, whether their split is predicted or seen to come back now.

        The split of groups a and b comes back when they are less than a pole slip (pi rad) from where they rested
        and the predictor's verdict on the OMIB of a against b (present swing) is confidently stable
        (z <= -z_alarm), or they are heading back towards each other by the filter's speeds. Judged on the latest
        frame taken.

        Returns:
            Symmetric (k, k) bool matrix; False on the diagonal and wherever nothing is known.

        """
        labels = np.asarray(labels, dtype=int)
        k = int(labels.max()) + 1 if labels.size else 0
        out = np.zeros((k, k), dtype=bool)
        frames = self.predictor._history.frames  # noqa: SLF001  the same frames the verdicts read
        if k < 2 or not frames or self._rest is None:
            return out
        _, delta, omega, _ = frames[-1]
        m = self.machines.m_s
        z_bar = self.predictor.z_alarm
        for a in range(k):
            for b in range(a + 1, k):
                lead, lag = np.flatnonzero(labels == a), np.flatnonzero(labels == b)
                sep = _centre(delta - self._rest, lead, m) - _centre(delta - self._rest, lag, m)
                speed = _centre(omega, lead, m) - _centre(omega, lag, m)
                if abs(sep) >= POLE_SLIP_RAD:
                    continue  # a pole already slipped: a separation measured, whatever comes next
                verdict = self.predictor.verdict(lead, lag)
                out[a, b] = out[b, a] = sep * speed < 0 or verdict.z <= -z_bar
        return out


def warm_up(z_alarm: float = 3.0) -> None:
    """Load what the predictor's first verdict needs (scipy.stats: 3.3 s at load 6 on the 2-core machine).

    A node calls it before spinning, within the supervisor's start-up grace: paid in the first verdict instead, it
    held the monitor's frames back 2.3 s behind real time on a Kundur replay, and its request reached
    breaker_command older than max_decision_age_s.
    """
    _chi2_bound(z_alarm, 10)


def _refines(groups: np.ndarray, before: np.ndarray | None) -> bool:
    """Whether groups split some group of `before` (always, when nothing was raised before)."""
    if before is None:
        return True
    return any(len(np.unique(groups[before == g])) > 1 for g in np.unique(before))


def _centre(x: np.ndarray, members: np.ndarray, m: np.ndarray) -> float:
    """Return the inertia-weighted mean of x over members."""
    return float(x[members] @ m[members] / m[members].sum())


def final_groups(alarm: Alarm | None, rule_labels, returning: np.ndarray | None = None) -> np.ndarray:
    """Return the predicted final grouping (the module docstring): 0-based per machine, numbered by first member.

    Args:
        alarm: The alarm standing at the request (SwingWatch.at); its groups win when there is one.
        rule_labels: The DTW rule's groups at the request (core/k_rules.py), per machine.
        returning: SwingWatch.returning(rule_labels): which of the rule's splits come back; None = none known.

    """
    if alarm is not None:
        return _canonical(alarm.groups)
    labels = np.asarray(rule_labels, dtype=int)
    if returning is None or not returning.any():
        return _canonical(labels)
    # Merge the rule's groups two clusters at a time, only where every split between them comes back: no final
    # group holds a pair that does not (a returning a-b and b-c never pull a separating a-c together).
    clusters = [{g} for g in range(int(labels.max()) + 1)]
    merged = True
    while merged:
        merged = False
        for i in range(len(clusters)):
            for j in range(i + 1, len(clusters)):
                if all(returning[a, b] for a in clusters[i] for b in clusters[j]):
                    clusters[i] |= clusters.pop(j)
                    merged = True
                    break
            if merged:
                break
    of = {g: c for c, members in enumerate(clusters) for g in members}
    return _canonical(np.array([of[int(g)] for g in labels]))


def _canonical(labels: np.ndarray) -> np.ndarray:
    order: dict[int, int] = {}
    return np.array([order.setdefault(int(g), len(order)) for g in labels], dtype=int)
