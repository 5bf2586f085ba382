"""The watchdog's decisions, on made-up times: restart with backoff, a restart budget, hangs by heartbeat."""

from __future__ import annotations

import pytest

from controlled_islanding.graph.watchdog import ActionKind, RestartPolicy, Watchdog, WatchdogError

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


def watch_over(dog: Watchdog, start_s: float, end_s: float, exits, beats, step_s: float = 0.1):
    """Step every step_s from start_s to end_s with beats(t) as the heartbeats; return (time, action) pairs."""
    seen = []
    for i in range(round((end_s - start_s) / step_s) + 1):
        t_s = start_s + i * step_s
        seen += [(t_s, a) for a in dog.step(t_s, exits, beats(t_s))]
    return seen


def test_a_silent_node_is_hung_after_its_heartbeat_timeout_and_restarted_under_the_same_backoff():
    dog = Watchdog(POLICY)
    dog.started('coherency', 0.0)
    dog.started('partitioning', 0.0)
    # coherency beats until 3 s and then falls silent; partitioning beats every second throughout.
    beats = lambda t_s: {'coherency': min(3.0, float(int(t_s))), 'partitioning': float(int(t_s))}  # noqa: E731
    seen = watch_over(dog, 0.0, 8.5, RUNNING, beats)
    assert [(t, a.kind, a.name) for t, a in seen] == [(pytest.approx(8.1), ActionKind.KILL, 'coherency')]
    hung = seen[0][1]
    assert hung.silent_s == pytest.approx(5.1) and hung.restart_in_s == 0.5 and 'hung' in hung.reason
    # Killed, it is down: its exit is not a second failure, and no second kill follows.
    assert watch_over(dog, 8.2, 8.5, {**RUNNING, 'coherency': -9}, beats) == []
    assert kinds(dog.step(8.61, {**RUNNING, 'coherency': -9}, beats(8.61))) == [(ActionKind.RESTART, 'coherency')]
    dog.started('coherency', 8.6)
    # The old heartbeat (3 s) belongs to the killed process: the new one gets the start-up grace.
    seen = watch_over(dog, 9.0, 29.0, RUNNING, beats)
    assert [(t, a.kind, a.name) for t, a in seen] == [(pytest.approx(28.7), ActionKind.KILL, 'coherency')]
    assert seen[0][1].restart_in_s == 1.0 and 'no heartbeat' in seen[0][1].reason


def test_a_stalled_supervisor_does_not_take_its_own_silence_for_hung_nodes():
    dog = Watchdog(POLICY)
    dog.started('coherency', 0.0)
    beats = lambda t_s: {'coherency': 1.0}  # noqa: E731  the heartbeats stop coming, as if the nodes hung
    assert watch_over(dog, 0.0, 2.0, RUNNING, beats) == []
    # Ten seconds without a step: the supervisor could not have heard anything, and must watch again first.
    assert dog.step(12.0, RUNNING, beats(12.0)) == []
    seen = watch_over(dog, 12.1, 17.5, RUNNING, beats)
    assert [(t, a.kind) for t, a in seen] == [(pytest.approx(17.1), ActionKind.KILL)]
    assert seen[0][1].silent_s == pytest.approx(16.1)


def test_a_hung_node_over_its_budget_is_still_killed_but_not_restarted():
    dog = Watchdog(RestartPolicy(nodes=frozenset({'coherency'}), max_restarts=0, hang_timeout_s=2.0,
                                 startup_grace_s=1.0))
    dog.started('coherency', 0.0)
    seen = watch_over(dog, 0.0, 3.0, {'coherency': None}, lambda t_s: {})
    assert [(t, a.kind) for t, a in seen] == [(pytest.approx(2.1), ActionKind.KILL)] and seen[0][1].gave_up
    assert watch_over(dog, 3.0, 10.0, {'coherency': -9}, lambda t_s: {}) == []


@pytest.mark.parametrize('bad', [{'backoff_initial_s': 0.0}, {'backoff_factor': 0.5}, {'max_restarts': -1},
                                 {'hang_timeout_s': 1.0}, {'startup_grace_s': -1.0}, {'restart_window_s': 0.0},
                                 {'max_step_gap_s': 0.0}])
def test_a_policy_that_cannot_work_is_refused(bad):
    with pytest.raises(WatchdogError):
        RestartPolicy(nodes=frozenset({'coherency'}), **bad)
