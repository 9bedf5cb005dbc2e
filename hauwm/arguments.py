"""argparse types and limits the stages' command lines share."""

from __future__ import annotations

import argparse
from pathlib import Path

MAX_SEED = 2**32 - 1  # the largest seed numpy takes (and Lightning's seed_everything, which seeds it)
MAX_TIMEOUT = 86_400.0  # a --timeout of a day at most: a wait the OS can represent (1e300 s overflows, inf never ends)


def path(text: str) -> Path:
    """A path flag's value: not empty (an unset shell variable would otherwise name the current directory, and an
    output would be written there)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path (an unset shell variable?): name a file or directory")
    return Path(text)
