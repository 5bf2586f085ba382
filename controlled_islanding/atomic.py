"""Replace a file or folder whole: a reader finds the old content or the new, never a part of it.

The new content is written beside the target under a hidden temporary name, fsynced, renamed over the target
(os.replace), and the folder fsynced, so that the rename outlives a crash too. On any failure the temporary is
removed and the target is left as it was. This is the package's one os.replace.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path


def _fsync(path: Path) -> None:
    """Fsync one file, or one folder's entries (not what they name)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_tree(path: Path) -> None:
    """Fsync a file, or a folder with everything in it, deepest first."""
    if path.is_dir() and not path.is_symlink():
        for child in sorted(path.rglob('*'), key=lambda c: len(c.parts), reverse=True):
            if not child.is_symlink() and (child.is_file() or child.is_dir()):  # no fifo: opening one blocks
                _fsync(child)
    _fsync(path)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def temporary(path: str | Path) -> Path:
    """Return a fresh hidden name beside `path`, for a file or folder that will replace it."""
    target = Path(path)
    return target.with_name(f'.{target.name}.{uuid.uuid4().hex[:12]}.tmp')


def replace(tmp: str | Path, path: str | Path) -> Path:
    """Make the finished `tmp` (a file or a folder) `path`: fsync it, rename it over `path`, fsync the folder."""
    tmp, target = Path(tmp), Path(path)
    try:
        _fsync_tree(tmp)
        os.replace(tmp, target)
    except BaseException:
        _remove(tmp)
        raise
    _fsync(target.parent)
    return target


@contextlib.contextmanager
def replacing(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path` for the block to create (by any means); it becomes `path` at the end.

    When the block raises, or creates nothing, the temporary is removed and `path` is left untouched.
    """
    tmp = temporary(path)
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f'{tmp}: nothing was written to replace {path} with')
    except BaseException:
        _remove(tmp)
        raise
    replace(tmp, path)


def write_bytes(path: str | Path, data: bytes, mode: int | None = None) -> Path:
    """Replace `path` with `data`; return the path.

    mode: The new file's permissions, exactly, from its creation on (0o600 for a private key); None: as a plain
    open() makes it (0o666 less the umask).
    """
    with replacing(path) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666 if mode is None else mode)
        with os.fdopen(fd, 'wb') as handle:
            if mode is not None:
                os.fchmod(handle.fileno(), mode)
            handle.write(data)
    return Path(path)


def write_text(path: str | Path, text: str, mode: int | None = None) -> Path:
    """Replace `path` with `text` (UTF-8); see write_bytes. Return the path."""
    return write_bytes(path, text.encode(), mode)
