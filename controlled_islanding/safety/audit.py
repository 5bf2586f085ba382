"""The breaker audit log: append-only JSON lines, fsync'ed per record, and the state a restart rebuilds from it.

The log is the breaker node's memory. Every record is on disk before the command it describes is published,
so after a crash the log holds every command that can have reached the field, and a restarted node reads it
back to never command a decision or a breaker twice. A log that cannot be read or written makes the node
refuse to act (fail safe) rather than act without memory.
"""

from __future__ import annotations

import json
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path


class AuditError(OSError):
    """The audit log cannot be read or written; the node must not command."""


@dataclass
class AuditState:
    """What the log says has happened.

    Attributes:
        decisions: Decision id -> request stamp (s, node clock) of every authenticated decision handled,
            commanded or refused.
        commanded: Breaker id -> (decision id, node clock s) of every open command issued and not reported
            closed again since (a branch status 'in service' stamped after the command).
        nonces: Arm/disarm nonce -> request stamp (s, wall clock) of every authenticated arm request.
        shed_mw: Load bus -> load commanded shed there so far, MW (every decision's sheds added up).
        tripped: Machine -> the decision id that commanded it tripped.
        records: Number of records read.
        repaired_tail: A torn last line (a crash mid-write) was cut off; it described nothing published.

    """

    decisions: dict[str, float] = field(default_factory=dict)
    commanded: dict[str, tuple[str, float]] = field(default_factory=dict)
    nonces: dict[str, float] = field(default_factory=dict)
    shed_mw: dict[int, float] = field(default_factory=dict)
    tripped: dict[str, str] = field(default_factory=dict)
    records: int = 0
    repaired_tail: bool = False

    def apply(self, record: dict) -> None:
        """Update the state with one record, as written by the breaker node."""
        self.records += 1
        event = record.get('event')
        decision_id = record.get('decision_id')
        if decision_id and record.get('authenticated'):
            self.decisions[str(decision_id)] = float(record.get('request_stamp_s', 0.0))
        if event == 'command':
            for command in record['commands']:
                action = command.get('action', 'open')
                if action == 'shed':
                    bus = int(command['bus'])
                    self.shed_mw[bus] = self.shed_mw.get(bus, 0.0) + float(command['amount_mw'])
                elif action == 'trip':
                    self.tripped[str(command['generator'])] = str(decision_id)
                else:
                    self.commanded[str(command['breaker_id'])] = (str(decision_id),
                                                                  float(record.get('ros_time_s', 0.0)))
        if event == 'reclosed':
            self.commanded.pop(str(record['breaker_id']), None)
        if event in ('armed', 'disarmed') and record.get('nonce'):
            self.nonces[str(record['nonce'])] = float(record.get('stamp_s', 0.0))


def read_state(path: Path) -> AuditState:
    """Rebuild the state from an existing log (a missing log is an empty one).

    A last line without its newline is a record torn by a crash before its fsync returned, so the command it
    described was never published: it is cut off. Any other unreadable line means the log cannot be trusted.

    Raises:
        AuditError: The path is not a regular file, cannot be read, or holds a corrupt record.

    """
    state = AuditState()
    try:
        info = path.stat()
    except FileNotFoundError:
        return state
    except OSError as exc:
        raise AuditError(f'audit log {path}: {exc.strerror or exc}') from exc
    if not stat.S_ISREG(info.st_mode):
        raise AuditError(f'audit log {path} is not a regular file; its history cannot be read back')
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise AuditError(f'audit log {path}: {exc.strerror or exc}') from exc
    complete, _, tail = data.rpartition(b'\n')
    if tail:
        try:
            os.truncate(path, len(complete) + 1 if complete else 0)
        except OSError as exc:
            raise AuditError(f'audit log {path}: cannot cut off a torn last record: {exc.strerror or exc}') from exc
        state.repaired_tail = True
    for number, line in enumerate(complete.split(b'\n') if complete else [], start=1):
        try:
            record = json.loads(line)
            if not isinstance(record, dict):
                raise ValueError('not a JSON object')
            state.apply(record)
        except (ValueError, KeyError, TypeError) as exc:
            raise AuditError(f'audit log {path} line {number} is corrupt ({exc}); refusing to act without a '
                             f'trustworthy history') from exc
    return state


class AuditLog:
    """Append-only JSON-lines file; every record is fsync'ed before `append` returns.

    Args:
        path: The log file; created (with its directory) if missing.

    Raises:
        AuditError: The log exists but cannot be read back, or cannot be opened for appending.

    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fd: int | None = None
        self.state = read_state(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        except OSError as exc:
            raise AuditError(f'audit log {self.path}: {exc.strerror or exc}') from exc

    def append(self, record: dict) -> None:
        """Write one record as a JSON line, fsync it, and apply it to the state.

        Raises:
            AuditError: The write or the fsync failed (disk full, I/O error); the record may be torn.

        """
        if self._fd is None:
            raise AuditError(f'audit log {self.path} is closed')
        line = (json.dumps(record, sort_keys=True) + '\n').encode()
        try:
            written = os.write(self._fd, line)
            if written != len(line):
                raise OSError(f'short write: {written} of {len(line)} bytes')
            os.fsync(self._fd)
        except OSError as exc:
            raise AuditError(f'audit log {self.path}: {getattr(exc, "strerror", None) or exc}') from exc
        self.state.apply(record)

    def close(self) -> None:
        """Close the file."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> AuditLog:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
