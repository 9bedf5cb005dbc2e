"""Exceptions as one line of a message: every stage's errors are said in one line, not a traceback."""

from __future__ import annotations

import signal
from collections.abc import Mapping


def first_line(error: BaseException) -> str:
    """The first line of `error`'s message, or the name of its type where the message is empty (a bare
    MemoryError(), a library's RuntimeError(''))."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def killed_by(signum: int, advice: Mapping[int, str]) -> str:
    """How a process killed by signal `signum` ended: `advice` for the signals a stage knows the cause of (a SIGKILL:
    most likely the kernel's OOM killer), else the signal's name."""
    return advice.get(signum, f"killed by signal {signum} ({signal.strsignal(signum)})")
