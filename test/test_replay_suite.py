"""`replay BAG BAG ...`: the regression run's report, without starting a node graph."""

from __future__ import annotations

import argparse

import pytest

from controlled_islanding.commands import replay
from controlled_islanding.graph.suite import SuiteRun, render_suite, replay_suite
from controlled_islanding.graph.summary import phases


def test_phases_follow_the_marks_in_order_and_add_up_to_the_total():
    marks = {'begun': 100.0, 'nodes_started': 100.5, 'armed': 103.0, 'wired': 110.0, 'decided': 113.0,
             'stopped': 113.5}
    report = {'play_begun_unix': 110.25, 'play_ended_unix': 112.0}
    got = phases(marks, report)
    assert list(got.values()) == [0.5, 2.5, 7.0, 0.25, 1.75, 1.0, 0.5, 13.5]
    assert sum(list(got.values())[:-1]) == pytest.approx(got['total'])
    # A replay that failed before playing has no player marks: the phases it reached, no made-up ones.
    assert phases({'begun': 1.0, 'nodes_started': 2.0}, {}) == {'set-up and node processes spawned': 1.0,
                                                                'total': 1.0}


def test_a_bag_that_cannot_be_replayed_is_a_failed_row_and_two_bags_of_one_name_are_refused(tmp_path):
    not_a_bag = tmp_path / 'not_a_bag'
    not_a_bag.mkdir()
    (not_a_bag / 'metadata.yaml').write_text('this is not rosbag2 metadata\n')
    report = replay_suite([SuiteRun('broken', not_a_bag)], tmp_path / 'run', jobs=1)
    (row,) = report['rows']
    assert not row['ok'] and row['exit_status'] == 2 and 'cannot read' in row['error'], row
    assert report['overall']['ok'] == 0 and report['overall']['runs'] == 1
    assert 'FAILED' in render_suite(report).splitlines()[1]
    parser = argparse.ArgumentParser()
    replay.add_arguments(parser)
    args = parser.parse_args([str(not_a_bag), str(not_a_bag), '--results', str(tmp_path / 'cli')])
    with pytest.raises(replay.CliError, match='same name'):
        replay.run(args)
