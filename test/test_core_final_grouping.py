"""The predicted final grouping (core/final_grouping.py), the rule the stability monitor and coherency share.

On the machine against an infinite bus of test_core_stability.py, whose answer the equal-area criterion gives in
closed form: cleared after the critical angle, the watch raises one alarm, once, and remembers it by time tag;
cleared before it, nothing is raised and the DTW rule's split of the machine from the bus is predicted to come
back, so the final grouping is one group.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_core_stability import DELTA_S, FAULT_S, T_CR_S, first_slip_s, machines, smib

from controlled_islanding.core.final_grouping import SwingWatch, final_groups


def feed(watch: SwingWatch, frames) -> list:
    """Feed every frame; return the alarms raised, with the frame time each came with."""
    raised = []
    for t, d, w, pe, v in frames:
        alarm = watch.update(t, np.array(d), np.array(w), np.array(pe), np.array(v))
        if alarm is not None:
            raised.append((t, alarm))
    return raised


def test_a_separating_swing_raises_one_alarm_remembered_by_time_tag() -> None:
    frames = smib(1.1 * T_CR_S)
    watch = SwingWatch(machines())
    raised = feed(watch, frames)
    assert len(raised) == 1, 'once per swing, however long the swing keeps separating'
    t, alarm = raised[0]
    assert alarm.t_s == t == alarm.raised_s
    assert FAULT_S + 1.1 * T_CR_S < t < first_slip_s(frames)
    assert alarm.groups.tolist() == [0, 1] and alarm.k == 2
    assert alarm.first_slip_s == pytest.approx(first_slip_s(frames), abs=0.1)
    assert watch.at(t - 1e-3) is None, 'no alarm stood before the frame that raised it'
    assert watch.at(t).raised_s == t
    # The rule's split stands at the alarm: the OMIB accelerates away, nothing says it returns.
    assert final_groups(watch.at(t), [0, 0]).tolist() == [0, 1], 'the prediction wins over the rule'


def test_a_returning_swing_raises_nothing_and_its_split_comes_back() -> None:
    frames = smib(0.9 * T_CR_S)
    watch = SwingWatch(machines())
    heading_back = []
    for t, d, w, pe, v in frames:
        assert watch.update(t, np.array(d), np.array(w), np.array(pe), np.array(v)) is None
        if t > FAULT_S + 0.9 * T_CR_S and w[0] < 1.0 and d[0] - DELTA_S > 0.1:
            heading_back.append(bool(watch.returning(np.array([0, 1]))[0, 1]))
    assert watch.alarm_ is None and watch.at(frames[-1][0]) is None
    assert heading_back and all(heading_back), 'a pair coming back towards its rest is no separation'
    # A split the DTW rule made there is merged: the final grouping is one group.
    assert final_groups(None, [0, 1], watch.returning(np.array([0, 1]))).tolist() == [0, 0]


def test_while_the_machine_runs_away_its_split_is_not_said_to_return() -> None:
    frames = smib(1.1 * T_CR_S)
    watch = SwingWatch(machines())
    after_clearing = [f for f in frames if f[0] > FAULT_S + 1.1 * T_CR_S + 0.1]
    feed(watch, [f for f in frames if f[0] <= FAULT_S + 1.1 * T_CR_S + 0.1])
    for t, d, w, pe, v in after_clearing:  # on to the pole slips: a slipped pole is a measured separation
        watch.update(t, np.array(d), np.array(w), np.array(pe), np.array(v))
        assert not watch.returning(np.array([0, 1]))[0, 1], t


def test_final_groups_merge_only_where_every_split_between_them_returns() -> None:
    rule = np.array([0, 0, 1, 2, 2])
    returning = np.zeros((3, 3), dtype=bool)
    assert final_groups(None, rule, returning).tolist() == [0, 0, 1, 2, 2]
    returning[0, 1] = returning[1, 0] = True
    assert final_groups(None, rule, returning).tolist() == [0, 0, 0, 1, 1]
    # 0-1 and 1-2 come back, 0-2 does not: 1 joins one of them, never both into one group with 0-2 split.
    returning[1, 2] = returning[2, 1] = True
    labels = final_groups(None, rule, returning)
    assert labels[0] != labels[3] and labels.max() == 1
    assert final_groups(None, [2, 2, 0], None).tolist() == [0, 0, 1], 'numbered by first member'


def test_a_late_or_incomplete_frame_is_skipped_not_fatal() -> None:
    frames = smib(0.9 * T_CR_S, end_s=1.0)
    watch = SwingWatch(machines())
    feed(watch, frames)
    t, d, w, pe, v = frames[-1]
    assert watch.update(t - 0.5, np.array(d), np.array(w), np.array(pe), np.array(v)) is None
    assert watch.update(t + 0.1, np.array([d[0], math.nan]), np.array(w), np.array(pe), np.array(v)) is None
    assert watch.skipped_ == 2 and watch.frames_ == len(frames)


def test_a_new_swing_asks_again_only_for_a_separation_inside_a_group_already_asked_for() -> None:
    """After the islanding (a switching) the islands drift apart along the cut asked for: no second request."""
    frames = smib(1.1 * T_CR_S, end_s=2.5)
    watch = SwingWatch(machines())
    t_first, _ = feed(watch, [f for f in frames if f[0] <= 1.9])[0]
    # The cut opens: every terminal voltage steps, a switching no measurement error explains.
    opened = [(t, d, w, pe, [x * 0.9 for x in v]) for t, d, w, pe, v in frames if t > 1.9]
    assert feed(watch, opened) == []
    assert watch.alarm_ is not None and watch.alarm_.raised_s > t_first, 'the new swing did predict the separation'
    assert watch.raised_groups_.tolist() == [0, 1]


def test_a_request_stamped_at_the_alarm_frame_finds_the_alarm_through_stamp_rounding() -> None:
    from controlled_islanding.wire.messages import split_stamp

    start = 1_767_225_600.0  # POSIX stamps, as in the bags: a float keeps about 0.2 us of them
    frames = [(start + t, *rest) for t, *rest in smib(1.1 * T_CR_S)]
    watch = SwingWatch(machines())
    ((t, alarm),) = feed(watch, frames)
    assert watch.at(t - 1e-3) is None
    rounded_down = 0
    for tag in list(watch._times):  # noqa: SLF001  every remembered frame, as a request stamped at it
        sec, nanosec = split_stamp(tag)
        stamped = sec + nanosec * 1e-9
        rounded_down += stamped < tag
        assert watch.at(stamped) is watch.at(tag), tag
    assert rounded_down, 'some stamps come back a hair early, which the test is about'
