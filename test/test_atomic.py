"""atomic.py: what a replace fsyncs, and what it leaves when the block fails."""

from __future__ import annotations

import os

import pytest

from controlled_islanding import atomic


@pytest.fixture
def fsynced(monkeypatch) -> list[str]:
    """Record the path of every descriptor os.fsync is called on."""
    seen: list[str] = []
    real = os.fsync

    def spy(fd: int) -> None:
        seen.append(os.readlink(f'/proc/self/fd/{fd}'))
        real(fd)

    monkeypatch.setattr(os, 'fsync', spy)
    return seen


def test_a_file_written_beside_a_big_folder_fsyncs_itself_and_its_folder_only(tmp_path, fsynced):
    """A results folder beside it (a bag, logs) is not the write's business: it used to be fsynced file by file."""
    beside = tmp_path / 'output_bag'
    beside.mkdir()
    for k in range(40):
        (beside / f'part{k}.db3').write_bytes(b'x')
    atomic.write_text(tmp_path / 'summary.json', '{}')
    assert (tmp_path / 'summary.json').read_text() == '{}'
    assert len(fsynced) == 2 and fsynced[1] == str(tmp_path), fsynced
    assert fsynced[0].startswith(str(tmp_path / '.summary.json.')), fsynced  # the temporary, before its rename


def test_a_folder_replaced_whole_has_every_file_and_folder_in_it_fsynced_before_its_rename(tmp_path, fsynced):
    target = tmp_path / 'bag'  # a new bag: os.replace takes no folder's place but an empty one's
    with atomic.replacing(target) as tmp:
        (tmp / 'sub').mkdir(parents=True)
        (tmp / 'sub' / 'a.db3').write_bytes(b'a')
        (tmp / 'metadata.yaml').write_text('m')
        os.mkfifo(tmp / 'pipe')  # a fifo is skipped: opening one to fsync it would block
    assert sorted(p.name for p in target.iterdir()) == ['metadata.yaml', 'pipe', 'sub']
    names = [p.rsplit('/', 1)[-1] for p in fsynced]
    assert sorted(names[:3]) == ['a.db3', 'metadata.yaml', 'sub'] and names.index('a.db3') < names.index('sub')
    assert names[3].startswith('.bag.') and fsynced[4] == str(tmp_path) and len(fsynced) == 5, fsynced


def test_a_failed_block_leaves_the_target_as_it_was_and_no_temporary(tmp_path):
    target = atomic.write_text(tmp_path / 'a.json', 'old')
    with pytest.raises(RuntimeError), atomic.replacing(target) as tmp:
        tmp.write_text('half')
        raise RuntimeError('interrupted')
    assert target.read_text() == 'old' and sorted(p.name for p in tmp_path.iterdir()) == ['a.json']
