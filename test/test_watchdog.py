"""The watchdog's decisions, on made-up times: restart with backoff, a restart budget, hangs by heartbeat."""

from __future__ import annotations

import pytest

from controlled_islanding.watchdog import ActionKind, RestartPolicy, Watchdog, WatchdogError

POLICY = RestartPolicy(nodes=frozenset({'coherency', 'partitioning'}), backoff_initial_s=0.5, backoff_factor=2.0,
                       backoff_max_s=3.0, max_restarts=4, restart_window_s=60.0, hang_timeout_s=5.0,
                       startup_grace_s=20.0)
RUNNING = {'coherency': None, 'partitioning': None}


def kinds(actions):
    return [(a.kind, a.name) for a in actions]


def fail_and_restart(dog: Watchdog, name: str, t_s: float) -> float:
    """Let name exit at t_s and restart when told; return the backoff it waited, s."""
    down = dog.step(t_s, {**RUNNING, name: 1}, {})
    assert kinds(down) == [(ActionKind.DOWN, name)] and down[0].exit_status == 1
    assert dog.step(t_s + down[0].restart_in_s - 0.01, RUNNING, {}) == []
    assert kinds(dog.step(t_s + down[0].restart_in_s, RUNNING, {})) == [(ActionKind.RESTART, name)]
    dog.started(name, t_s + down[0].restart_in_s)
    return down[0].restart_in_s


def test_a_dead_node_is_restarted_after_a_backoff_that_doubles_up_to_its_cap():
    dog = Watchdog(POLICY)
    dog.started('coherency', 0.0)
    assert [fail_and_restart(dog, 'coherency', t) for t in (10.0, 20.0, 30.0, 40.0)] == [0.5, 1.0, 2.0, 3.0]


def test_one_failure_more_than_the_budget_gives_up_and_old_restarts_stop_counting():
    dog = Watchdog(POLICY)
    dog.started('coherency', 0.0)
    for t in (1.0, 5.0, 9.0, 13.0):
        fail_and_restart(dog, 'coherency', t)
    last = dog.step(17.0, {**RUNNING, 'coherency': -11}, {})
    assert kinds(last) == [(ActionKind.DOWN, 'coherency')] and last[0].gave_up and last[0].restart_in_s is None
    assert 'giving up' in last[0].reason and dog.gave_up_on() == ['coherency']
    assert dog.step(100.0, {**RUNNING, 'coherency': -11}, {}) == []

    spaced = Watchdog(POLICY)
    spaced.started('coherency', 0.0)
    # One failure a minute and a bit: each is the first in its window, so the backoff never grows.
    assert [fail_and_restart(spaced, 'coherency', 70.0 * i) for i in range(1, 8)] == [0.5] * 7


def test_a_node_outside_the_policy_is_never_restarted_nor_judged():
    dog = Watchdog(POLICY)
    dog.started('bag_player', 0.0)
    assert dog.step(100.0, {'bag_player': 0}, {}) == []


def test_a_node_stopped_on_purpose_is_forgotten():
    dog = Watchdog(POLICY)
    dog.started('coherency', 0.0)
    dog.stopped('coherency')
    assert dog.step(100.0, {'coherency': 0}, {}) == []


def test_a_silent_node_is_hung_after_its_heartbeat_timeout_and_restarted_under_the_same_backoff():
    dog = Watchdog(POLICY)
    dog.started('coherency', 0.0)
    dog.started('partitioning', 0.0)
    beats = {'coherency': 3.0, 'partitioning': 3.0}
    assert dog.step(8.0, RUNNING, beats) == []
    beats['partitioning'] = 7.5
    hung = dog.step(8.1, RUNNING, beats)
    assert kinds(hung) == [(ActionKind.KILL, 'coherency')]
    assert hung[0].silent_s == pytest.approx(5.1) and hung[0].restart_in_s == 0.5 and 'hung' in hung[0].reason
    # Killed, it is down: its exit is not a second failure, and no second kill follows.
    assert dog.step(8.2, {**RUNNING, 'coherency': -9}, beats) == []
    assert kinds(dog.step(8.6, {**RUNNING, 'coherency': -9}, beats)) == [(ActionKind.RESTART, 'coherency')]
    dog.started('coherency', 8.6)
    # The old heartbeat (3.0) belongs to the killed process: the new one gets the start-up grace.
    assert dog.step(8.6 + 19.9, RUNNING, {**beats, 'partitioning': 28.0}) == []
    again = dog.step(8.6 + 20.1, RUNNING, {**beats, 'partitioning': 28.0})
    assert kinds(again) == [(ActionKind.KILL, 'coherency')] and again[0].restart_in_s == 1.0
    assert 'no heartbeat' in again[0].reason


def test_a_hung_node_over_its_budget_is_still_killed_but_not_restarted():
    dog = Watchdog(RestartPolicy(nodes=frozenset({'coherency'}), max_restarts=0, hang_timeout_s=2.0,
                                 startup_grace_s=1.0))
    dog.started('coherency', 0.0)
    hung = dog.step(1.5, {'coherency': None}, {})
    assert kinds(hung) == [(ActionKind.KILL, 'coherency')] and hung[0].gave_up
    assert dog.step(10.0, {'coherency': -9}, {}) == []


@pytest.mark.parametrize('bad', [{'backoff_initial_s': 0.0}, {'backoff_factor': 0.5}, {'max_restarts': -1},
                                 {'hang_timeout_s': 1.0}, {'startup_grace_s': -1.0}, {'restart_window_s': 0.0}])
def test_a_policy_that_cannot_work_is_refused(bad):
    with pytest.raises(WatchdogError):
        RestartPolicy(nodes=frozenset({'coherency'}), **bad)
