"""The diagnostic_updater-style topic status (ros.diagnostics.TopicStatus) on a driven clock, without processes."""

from __future__ import annotations

import pytest
from diagnostic_msgs.msg import DiagnosticStatus

from controlled_islanding.ros.diagnostics import TopicStatus

T0_S = 1_767_225_600.0  # a node clock that runs (sim or wall time), s


def run(status: TopicStatus, seconds: int, rate_hz: float, start_s: float = T0_S, lag_s: float = 0.01) -> float:
    """Deliver rate_hz messages per second for `seconds` one-second publishes; return the clock at the end."""
    clock_s = start_s
    for _ in range(seconds):
        n = int(round(rate_hz))
        for i in range(n):
            stamp = clock_s + i / max(n, 1)
            status.arrived(stamp + lag_s, stamp)
        clock_s += 1.0
        status.update(clock_s)
    return clock_s


def test_the_rate_is_judged_within_ten_percent_over_the_window():
    status = TopicStatus('x: /pmu/frames topic status', 60.0, (-1.0, 1.0))
    clock_s = run(status, 6, 60.0)
    assert (status.level, status.message) == (DiagnosticStatus.OK, 'Desired frequency met')
    assert float(status.values['Actual frequency (Hz)']) == 60.0
    assert status.values['Minimum acceptable frequency (Hz)'].startswith('54.0')
    clock_s = run(status, 6, 50.0, clock_s)
    assert (status.level, status.message) == (DiagnosticStatus.WARN, 'Frequency too low.')
    clock_s = run(status, 6, 70.0, clock_s)
    assert (status.level, status.message) == (DiagnosticStatus.WARN, 'Frequency too high.')
    clock_s = run(status, 6, 60.0, clock_s)
    assert status.level == DiagnosticStatus.OK, 'the status returns once the rate is back'
    run(status, 6, 0.0, clock_s)
    assert status.level == DiagnosticStatus.ERROR and status.message.startswith('No events recorded.')


def test_a_standing_clock_measures_no_rate_and_blames_nothing():
    status = TopicStatus('x', 60.0, (-1.0, 1.0))
    status.update(0.0)  # sim time before the first /clock
    assert status.level == DiagnosticStatus.OK and 'not running' in status.message
    clock_s = run(status, 6, 60.0)
    for _ in range(6):  # the bag ended: the clock stands and nothing comes
        status.update(clock_s)
    assert status.level == DiagnosticStatus.OK and 'not running' in status.message


def test_stamps_outside_the_bounds_are_errors():
    status = TopicStatus('x', 60.0, (-1.0, 1.0))
    run(status, 6, 60.0, lag_s=2.0)
    assert (status.level, status.message) == (DiagnosticStatus.ERROR, 'Timestamps too far in past seen.')
    run(status, 1, 60.0, start_s=T0_S + 6, lag_s=-3.0)
    assert status.message == 'Timestamps too far in future seen.'
    assert float(status.values['Earliest timestamp delay:']) < -2.9


@pytest.mark.ros
def test_a_fault_and_a_warning_both_log_and_hold_in_one_node(rclpy_context):
    # rclpy raises when one call site logs at two severities: a breaker node with a fault once lost its
    # control_centre_silent warning (and counted a callback error) that way.
    import rclpy

    from controlled_islanding.ros.diagnostics import Diagnostics

    node = rclpy.create_node('diagnostics_levels', context=rclpy_context)
    try:
        diag = Diagnostics(node)
        diag.fault('clock_inconsistent', 'sim clock jumped back')
        diag.warn('control_centre_silent', 'no live decision writer')
        diag.fault('clock_inconsistent', None)
        diag.warn('control_centre_silent', 'still none')
        assert diag.warnings == {'control_centre_silent': 'still none'} and diag.faults == {}
        assert diag.level()[0] == DiagnosticStatus.WARN
    finally:
        node.destroy_node()
