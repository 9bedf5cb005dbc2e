"""argparse types and limits the stages' command lines share."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

MAX_SEED = 2**32 - 1  # the largest seed numpy takes (and Lightning's seed_everything, which seeds it)
MAX_TIMEOUT = 86_400.0  # a --timeout of a day at most: a wait the OS can represent (1e300 s overflows, inf never ends)


def at_least(least: int, most: int | None = None) -> Callable[[str], int]:
    """An argparse type for counts and seeds: a whole number >= `least` (and <= `most`)."""
    def whole_number(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = least - 1
        if value < least or most is not None and value > most:
            within = f">= {least}" if most is None else f"from {least} to {most}"
            raise argparse.ArgumentTypeError(f"must be a whole number {within}, got {text!r}")
        return value
    return whole_number


def path(text: str) -> Path:
    """A path flag's value: not empty (an unset shell variable would otherwise name the current directory, and an
    output would be written there)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path (an unset shell variable?): name a file or directory")
    return Path(text)
