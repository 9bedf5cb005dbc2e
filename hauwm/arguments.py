"""argparse types the stages' command lines share."""

from __future__ import annotations

import argparse
from pathlib import Path


def path(text: str) -> Path:
    """A path flag's value: not empty (an unset shell variable would otherwise name the current directory, and an
    output would be written there)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path (an unset shell variable?): name a file or directory")
    return Path(text)
