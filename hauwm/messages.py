"""Exceptions as one line of a message: every stage's errors are said in one line, not a traceback."""

from __future__ import annotations


def first_line(error: BaseException) -> str:
    """The first line of `error`'s message, or the name of its type where the message is empty (a bare
    MemoryError(), a library's RuntimeError(''))."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__
