"""One process at a time: an exclusive lock on a file that holds its holder's pid (the kernel releases the lock of
a process that dies, killed or not), for a fine-tuning run's directory, a dataset being written and a fit's
checkpoint directory.

    with pid_lock(path):      # LockHeld(pid) where another process holds it
        ...
    with locked(path, refused):  # the same, `refused(pid)` raised instead, and the file deleted when the block ends
        ...
    lock_holder(path)         # the pid holding it now ('?' before it is written), None where none does

A holder may delete the file before it lets go; a process that opened the old file meanwhile locks the new one.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

PROBE_S = 0.2  # longer than any lock_holder holds its shared lock, far shorter than any holder holds the lock


class LockHeld(Exception):
    """Another process holds the lock; `pid` is what its file says ('?' where it says nothing yet)."""

    def __init__(self, pid: str) -> None:
        super().__init__(pid)
        self.pid = pid


@contextlib.contextmanager
def pid_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on `path` (made, and its directory, where they do not exist), with this process's pid
    written in it."""
    while True:
        path.parent.mkdir(parents=True, exist_ok=True)  # again after a holder that made it removed it on letting go
        lock = open(path, "a+")
        if not _flock_soon(lock):
            lock.seek(0)
            pid = lock.read().strip() or "?"
            lock.close()
            raise LockHeld(pid)
        with contextlib.suppress(FileNotFoundError):
            if os.stat(path).st_ino == os.fstat(lock.fileno()).st_ino:
                break
        lock.close()  # the holder before deleted the file between our open and our lock: lock the new one
    with lock:
        lock.truncate(0)
        lock.write(str(os.getpid()))
        lock.flush()
        yield


@contextlib.contextmanager
def locked(path: Path, refused: Callable[[str], Exception]) -> Iterator[None]:
    """Hold `pid_lock(path)` (its directory made where needed) while the block runs, and delete the file before
    letting go; where another process holds it, raise `refused(its pid)`: the caller's error, naming what to do."""
    with contextlib.ExitStack() as held:
        try:
            held.enter_context(pid_lock(path))
        except LockHeld as other:
            raise refused(other.pid) from None
        try:
            yield
        finally:
            path.unlink(missing_ok=True)


def _flock_soon(lock: IO) -> bool:
    """Whether the exclusive lock on `lock` is ours within PROBE_S: `lock_holder` holds a shared lock for an instant,
    and a process asking then would otherwise be told that the lock is held."""
    deadline = time.monotonic() + PROBE_S
    while True:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.005)


def lock_holder(path: Path) -> int | str | None:
    """The pid of the process holding the lock on `path` now ('?' where it has not written it yet), None where none
    does."""
    try:
        with open(path) as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                text = lock.read().strip()
                return int(text) if text.isdigit() else "?"
    except OSError:
        pass
    return None
