"""argparse types of the bench scripts: a bad duration or task name is a usage error naming its flag (argparse
prints it with the usage line), not a traceback minutes into a benchmark. Counts use hauwm.arguments.at_least."""

from __future__ import annotations

import argparse


def duration(text: str) -> float:
    """A duration in seconds, > 0."""
    try:
        value = float(text)
    except ValueError:
        value = 0.0
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a number of seconds > 0, got {text!r}")
    return value


def task_name(name: str) -> str:
    """A fine-tuning task that make_env knows (finetune/envs/registry.py)."""
    from finetune.envs.registry import check_task

    try:
        check_task(name)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return name
