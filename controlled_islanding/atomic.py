"""Replace a file or folder whole: a reader finds the old content or the new, never a part of it.

Written beside the target under a hidden temporary name, fsynced, renamed over the target (os.replace), then
the folder fsynced, so that the rename outlives a crash too. On any failure the temporary is removed and the
target is left as it was.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path


def _fsync(path: Path) -> None:
    if path.is_dir():
        for child in path.rglob('*'):
            if child.is_file():
                _fsync(child)
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


@contextlib.contextmanager
def replacing(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path` for the caller to create (a file or a folder); it becomes `path` at the end.

    The temporary does not exist yet: the block creates it, by any means (a library's writer, for instance).
    When the block raises, or creates nothing, the target is left untouched.
    """
    target = Path(path)
    tmp = target.with_name(f'.{target.name}.{uuid.uuid4().hex[:12]}.tmp')
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f'{tmp}: nothing was written to replace {target} with')
        _fsync(tmp)
        os.replace(tmp, target)
    except BaseException:
        _remove(tmp)
        raise
    _fsync(target.parent)


def write_bytes(path: str | Path, data: bytes, mode: int = 0o666) -> Path:
    """Replace `path` with `data`; a new file gets `mode` (less the umask) from its creation on. Return the path."""
    with replacing(path) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
        with os.fdopen(fd, 'wb') as handle:
            handle.write(data)
    return Path(path)


def write_text(path: str | Path, text: str, mode: int = 0o666) -> Path:
    """Replace `path` with `text` (UTF-8); see write_bytes. Return the path."""
    return write_bytes(path, text.encode(), mode)
