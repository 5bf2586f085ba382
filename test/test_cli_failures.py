"""Failed runs never block their retry, and unreadable bags are named with their fault (issue 31).

No node process starts here: every failure is met before the graph would be started, in graph/results.py alone,
or in a bag_player made in this process, which refuses before it plays.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
from pathlib import Path

import pytest

from controlled_islanding.cli import main
from controlled_islanding.graph import GraphError
from controlled_islanding.graph.processes import interrupted, sigterm_as_interrupt
from controlled_islanding.graph.results import FAILED, INTERRUPTED, claim, running
from controlled_islanding.sim.manifest import default_bag

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope='module')
def good_bag() -> Path:
    return REPO / 'bags' / default_bag()['bag']


def _not_a_bag(tmp_path: Path) -> Path:
    folder = tmp_path / 'not_a_bag'
    folder.mkdir()
    (folder / 'notes.txt').write_text('a folder, but no bag\n')
    return folder


def _truncated(tmp_path: Path, good: Path) -> tuple[Path, Path]:
    bag = tmp_path / 'truncated'
    bag.mkdir()
    shutil.copy(good / 'metadata.yaml', bag)
    mcap = next(good.glob('*.mcap'))
    (bag / mcap.name).write_bytes(mcap.read_bytes()[:20000])
    return bag, bag / mcap.name


@pytest.mark.parametrize('command', [['replay'], ['evaluate'], ['serve-pmu']])
def test_a_folder_without_metadata_yaml_is_named_as_not_a_bag(tmp_path, capsys, command):
    folder = _not_a_bag(tmp_path)
    argv = [*command, str(folder)] + (['--results', str(tmp_path / 'r')] if command == ['replay'] else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f'{folder} is not a rosbag2 bag: it holds no metadata.yaml' in err, err
    assert 'Expected metadata file' not in err
    assert not (tmp_path / 'r').exists()


@pytest.mark.parametrize('command', [['replay'], ['evaluate'], ['serve-pmu']])
def test_a_truncated_mcap_is_named_as_truncated_or_corrupt(tmp_path, capsys, good_bag, command):
    bag, mcap = _truncated(tmp_path, good_bag)
    argv = [*command, str(bag)] + (['--results', str(tmp_path / 'r')] if command == ['replay'] else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f'truncated or corrupt MCAP file {mcap}' in err, err
    assert not (tmp_path / 'r').exists()


def test_a_replay_that_fails_before_any_result_removes_its_folder_and_can_be_retried(tmp_path, capsys):
    results = tmp_path / 'r'
    bag = _not_a_bag(tmp_path)
    for _ in range(2):
        assert main(['replay', str(bag), '--results', str(results)]) == 2
        err = capsys.readouterr().err
        assert 'metadata.yaml' in err and 'exists' not in err, err
        assert not results.exists()


def test_a_failed_runs_folder_is_reused_and_a_finished_one_needs_force(tmp_path, capsys):
    results = tmp_path / 'r'
    (results / 'logs').mkdir(parents=True)
    (results / 'logs' / 'coherency.log').write_text('the failed run\n')
    (results / FAILED).write_text('{}')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('case: [\n')
    assert main(['testbed', str(bad), '--results', str(results), '--no-baselines']) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and 'exists' not in err, err
    assert not results.exists(), 'the retry failed before writing anything, so its folder went'

    results.mkdir()
    (results / 'summary.json').write_text('{}')
    assert main(['testbed', str(bad), '--results', str(results), '--no-baselines']) == 2
    err = capsys.readouterr().err
    assert 'holds a finished run' in err and '--force' in err, err
    assert (results / 'summary.json').exists(), 'a finished run is never replaced without --force'
    assert main(['testbed', str(bad), '--results', str(results), '--no-baselines', '--force']) == 2
    assert 'holds a finished run' not in capsys.readouterr().err


def test_running_removes_an_empty_folder_and_marks_one_with_files(tmp_path):
    with pytest.raises(GraphError), running(tmp_path / 'early'):
        raise GraphError('the bag is unreadable')
    assert not (tmp_path / 'early').exists()

    with pytest.raises(GraphError), running(tmp_path / 'late', bag='B') as folder:
        (folder / 'logs').mkdir()
        (folder / 'logs' / 'node.log').write_text('started\n')
        raise GraphError('partitioning died')
    marker = json.loads((tmp_path / 'late' / FAILED).read_text())
    assert marker['error'] == 'partitioning died' and marker['bag'] == 'B' and marker['failed_utc']
    assert (tmp_path / 'late' / 'logs' / 'node.log').exists(), 'the logs say why: they stay'

    with pytest.raises(KeyboardInterrupt), running(tmp_path / 'stopped', bag='B'):
        raise KeyboardInterrupt
    assert json.loads((tmp_path / 'stopped' / INTERRUPTED).read_text())['bag'] == 'B'

    assert claim(tmp_path / 'late') == (tmp_path / 'late').resolve()
    assert list((tmp_path / 'late').iterdir()) == [], 'a marked folder is claimed afresh'


@pytest.fixture
def python_signals():
    """Python's own SIGINT and SIGTERM handling, as a command line has it (a pytest-xdist worker ignores SIGINT)."""
    before = {s: signal.signal(s, h) for s, h in ((signal.SIGINT, signal.default_int_handler),
                                                  (signal.SIGTERM, signal.SIG_DFL))}
    yield
    for s, h in before.items():
        signal.signal(s, h)


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_a_signal_that_another_library_turns_into_its_own_error_still_marks_the_folder_interrupted(
        tmp_path, sig, python_signals):
    """pybind11 turns a KeyboardInterrupt raised while rclpy converts a message into a RuntimeError."""
    def convert():
        try:
            os.kill(os.getpid(), sig)
            time.sleep(1.0)
        except KeyboardInterrupt as exc:
            raise RuntimeError('Unable to convert call argument') from exc

    with pytest.raises(RuntimeError), sigterm_as_interrupt(), running(tmp_path / 'run', bag='B') as folder:
        (folder / 'logs').mkdir()
        (folder / 'logs' / 'node.log').write_text('started\n')
        convert()
    assert interrupted() == sig
    assert json.loads((tmp_path / 'run' / INTERRUPTED).read_text())['bag'] == 'B'
    assert not (tmp_path / 'run' / FAILED).exists()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler, 'Ctrl-C is given back as it was'

    with pytest.raises(GraphError), sigterm_as_interrupt(), running(tmp_path / 'later') as folder:
        (folder / 'log').write_text('x')
        raise GraphError('partitioning died')
    assert interrupted() is None and (tmp_path / 'later' / FAILED).exists(), 'a signal is forgotten by the next run'


def test_claim_never_removes_a_folder_that_is_not_a_runs(tmp_path):
    mine = tmp_path / 'my_documents'
    mine.mkdir()
    (mine / 'thesis.tex').write_text('years of work\n')
    for force in (False, True):
        with pytest.raises(GraphError, match='does not look like a results folder'):
            claim(mine, force=force)
    assert (mine / 'thesis.tex').exists()
    (tmp_path / 'a_file').write_text('x')
    with pytest.raises(GraphError, match='not a folder'):
        claim(tmp_path / 'a_file', force=True)


def _with_older_rotor_angles(tmp_path: Path, good: Path) -> Path:
    """Copy a bag, /truth/rotor_angles recorded as RotorAngles was before it gained suspect_reason."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_types_from_msg, get_typestore
    from rosbags.typesys.stores import Stores

    from controlled_islanding.wire import topics
    from controlled_islanding.wire.interfaces import msg_type_name, typestore

    name = msg_type_name('RotorAngles')
    old_text = '\n'.join(line for line in (REPO / 'msg_schemas/msg/RotorAngles.msg').read_text().splitlines()
                         if line.split('#')[0].strip() and 'suspect_reason' not in line)
    old = get_typestore(Stores.ROS2_JAZZY)
    old.register(get_types_from_msg(old_text, name))
    store, out = typestore(), tmp_path / 'older'
    with AnyReader([good], default_typestore=store) as reader, \
            Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}
        for c in reader.connections:
            older = c.topic == topics.TRUTH_ROTOR_ANGLES
            conns[c.id] = (writer.add_connection(c.topic, c.msgtype, typestore=old) if older
                           else writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest))
        for c, stamp, raw in reader.messages():
            if c.topic == topics.TRUTH_ROTOR_ANGLES:
                msg = reader.deserialize(raw, c.msgtype)
                raw = old.serialize_cdr(old.types[name](**{f: getattr(msg, f) for f, _ in old.fielddefs[name][1]}),
                                        name)
            writer.write(conns[c.id], stamp, raw)
    return out


@pytest.mark.ros
def test_bag_player_refuses_a_bag_recorded_with_another_definition_naming_the_topic(tmp_path, good_bag,
                                                                                    rclpy_context):
    """Published raw, such messages fail to decode in every subscriber: the player refuses before it plays."""
    from rclpy.parameter import Parameter

    from controlled_islanding.nodes.bag_player import BagPlayerNode
    from controlled_islanding.ros.params import NodeSetupError
    from controlled_islanding.wire.bagmeta import other_definitions

    bag = _with_older_rotor_angles(tmp_path, good_bag)
    with pytest.raises(NodeSetupError, match=r'/truth/rotor_angles \(controlled_islanding_msgs/msg/RotorAngles\) '
                                             'recorded with another definition'):
        BagPlayerNode(context=rclpy_context, parameter_overrides=[Parameter('bag', value=str(bag)),
                                                                  Parameter('publish_truth', value=True)])
    from rosbags.highlevel import AnyReader

    from controlled_islanding.wire.interfaces import typestore
    with AnyReader([good_bag], default_typestore=typestore()) as reader:
        assert other_definitions(reader.connections, typestore()) == []
