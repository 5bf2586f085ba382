"""Child processes and signals: what /proc says of a process, SIGTERM unwound like Ctrl-C, children that die with us."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

_PR_SET_PDEATHSIG = 1


_interrupted_by: int | None = None


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """While open, SIGTERM raises KeyboardInterrupt in the main thread, as Ctrl-C does, and both are remembered.

    Python's default SIGTERM ends the process at once, skipping every `finally` and `__exit__`: a `kill PID` left
    the nodes' forked helpers running, network namespaces mounted, and a results folder that did not say it was
    unfinished. A handler the program set itself, or a call off the main thread, is left alone.

    A KeyboardInterrupt raised while rclpy converts a message comes out of pybind11 as a RuntimeError, so the
    exception alone cannot say a run was interrupted: `interrupted()` can, until the next outermost opening.
    """
    global _interrupted_by
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL):
        yield
        return
    _interrupted_by = None
    previous_int = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGTERM, _terminated)
    if previous_int is signal.default_int_handler:
        signal.signal(signal.SIGINT, _terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        if previous_int is signal.default_int_handler:
            signal.signal(signal.SIGINT, previous_int)


def interrupted() -> int | None:
    """Return the signal (SIGINT or SIGTERM) that interrupted the last `sigterm_as_interrupt` block, if one did."""
    return _interrupted_by


def _terminated(signum: int, _frame: object) -> None:
    global _interrupted_by
    _interrupted_by = signum
    raise KeyboardInterrupt(f'signal {signum}')


def die_with_parent() -> None:
    """Ask the kernel to send this process SIGTERM when its parent dies (a subprocess preexec_fn).

    A SIGKILLed parent cannot run its cleanup; the kernel then stops its children instead (only them: what a
    child forked is then the child's to end).
    """
    with contextlib.suppress(OSError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def _stat_fields(pid: int | str) -> list[str]:
    # The command name, in parentheses, may hold spaces and parentheses itself: the fields follow the last ')'.
    return Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()


def processes() -> list[tuple[int, str, int]]:
    """Return (pid, state, process group) of every process."""
    out = []
    for stat in Path('/proc').glob('[0-9]*/stat'):
        try:
            fields = _stat_fields(stat.parent.name)
            out.append((int(stat.parent.name), fields[0], int(fields[2])))
        except (OSError, IndexError, ValueError):
            continue
    return out


def cpu_s(pid: int) -> float:
    """Return a live process's CPU time so far (user + system), s; 0 if it cannot be read."""
    try:
        fields = _stat_fields(pid)
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, IndexError, ValueError):
        return 0.0


def status_field(pid: int | str, name: str) -> str | None:
    """Return one field of /proc/<pid>/status ('VmRSS', 'CapEff', ...) as written there, or None."""
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            key, _, value = line.partition(':')
            if key == name:
                return value.strip()
    except OSError:
        return None
    return None


def rss_kb(pid: int) -> int | None:
    """Return VmRSS of a process in kB, or None if it is gone."""
    value = status_field(pid, 'VmRSS')
    return int(value.split()[0]) if value else None
