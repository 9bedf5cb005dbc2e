"""Kinds of JSON values, for every reader of a file that another program or version may have written (an export's
config.json, a shard directory's manifest, a Minari dataset's metadata.json): JSON's true is a Python int too, so a
count is checked to be an int and not a bool."""

from __future__ import annotations


def is_integer(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_count(value: object) -> bool:
    """A whole number ≥ 0 (not a bool, not a float): a count of clips, frames, bytes, episodes or steps."""
    return is_integer(value) and value >= 0


def is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)
