"""Results folders that a failed run never blocks: replay's and the testbed's, claimed, then finished or marked.

A run claims a fresh folder. When it fails before writing anything, the folder goes again; when it fails later,
its logs stay for the reader and a marker says why (INTERRUPTED.json for Ctrl-C or SIGTERM, FAILED.json
otherwise). The same command can then be run again: a folder that holds a marker, or nothing, is replaced, and
`force` replaces a finished run's folder too. A folder that does not look like a run's is never removed.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

from controlled_islanding import atomic
from controlled_islanding.graph import GraphError
from controlled_islanding.graph.processes import interrupted as signalled

FAILED = 'FAILED.json'
INTERRUPTED = 'INTERRUPTED.json'
# What a run of ours writes at the top of its folder; a folder with none of them is not removed, even by force.
_RUN_FILES = (FAILED, INTERRUPTED, 'summary.json', 'suite.json', 'testbed.json', 'logs', 'player_go.json')

log = logging.getLogger(__name__)


def claim(path: Path, force: bool = False) -> Path:
    """Create `path` as an empty results folder, replacing a failed run's (or with `force`, any run's); return it.

    Raises:
        GraphError: `path` holds a finished run (and not `force`), or something that is not a run's folder.

    """
    path = Path(path).resolve()
    if path.exists() or path.is_symlink():
        if not path.is_dir() or path.is_symlink():
            raise GraphError(f'results folder {path} exists and is not a folder; name a new one')
        names = {p.name for p in path.iterdir()}
        marker = next((m for m in (FAILED, INTERRUPTED) if m in names), None)
        if names and not names & set(_RUN_FILES):
            raise GraphError(f'results folder {path} exists and does not look like a results folder (none of '
                             f'{", ".join(_RUN_FILES)} in it); name a new one')
        if names and marker is None and not force:
            raise GraphError(f'results folder {path} holds a finished run; name a new one, or --force to replace it')
        if names:
            log.info('replacing %s (%s)', path, f'its {marker}' if marker else '--force')
        shutil.rmtree(path)
    path.mkdir(parents=True)
    return path


@contextlib.contextmanager
def running(path: Path, force: bool = False, **about: object) -> Iterator[Path]:
    """Claim `path` for the block, and on failure remove it (nothing written yet) or mark it (`about` in the marker).

    A marker the block wrote itself (a richer INTERRUPTED.json) is kept as it is.
    """
    path = claim(path, force)
    try:
        yield path
    except BaseException as exc:
        interrupted = isinstance(exc, KeyboardInterrupt) or signalled() is not None
        if not interrupted and not any(p.is_file() for p in path.rglob('*')):
            shutil.rmtree(path, ignore_errors=True)
        elif not (path / FAILED).exists() and not (path / INTERRUPTED).exists():
            now = datetime.now(UTC).isoformat(timespec='seconds')
            fields = {'interrupted_utc': now} if interrupted else {'failed_utc': now, 'error': str(exc)}
            with contextlib.suppress(OSError):
                atomic.write_text(path / (INTERRUPTED if interrupted else FAILED),
                                  json.dumps({**fields, **about}, indent=1, default=str) + '\n')
        raise
