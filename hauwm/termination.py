"""SIGTERM and Ctrl-C for the `hauwm` commands: a run stops after its current iteration with a checkpoint, and a
command outside a run stops as Ctrl-C stops it, said as SIGTERM.

SLURM (`scancel`, a job's time limit, preemption) and Kubernetes send SIGTERM to every process of a job, and
SIGKILL some seconds later. A fine-tuning run of 1M env steps checkpoints every `checkpoint_every` steps; killed
outright it would lose what it did since its last checkpoint. Inside `terminable()` the signal only sets a flag; the
training loop reads it after each iteration (an env step and the updates due, or an update offline), writes its
checkpoint and raises `Terminated`, which `hauwm finetune` reports in one line with exit status 143. The same
command goes on from there (a checkpoint taken within an episode drops that episode's steps, as any other does). Env
workers that the job's SIGTERM ended before the learner saw its own (`EnvWorkerError.by_sigterm`) stop the run the
same way, with the checkpoint of the env steps completed (finetune/train.py `run`). Outside a run (while `hauwm
finetune` starts, in `hauwm datasets` and `hauwm shards`), `sigterm_as_interrupt()` makes SIGTERM do what Ctrl-C
does — a KeyboardInterrupt, whose clean-up runs — said as SIGTERM (143). (`hauwm pretrain` has Lightning's own
handling, model/sigterm.py.)
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from types import FrameType


class Terminated(Exception):
    """The run got SIGTERM and stopped after writing its checkpoint."""


class StopRequest:
    """Whether SIGTERM has come since `terminable()` began."""

    def __init__(self) -> None:
        self.requested = False

    def note(self, signum: int, frame: FrameType | None) -> None:
        self.requested = True


@contextlib.contextmanager
def handling_sigterm(handler: Callable[[int, FrameType | None], None]) -> Iterator[None]:
    """`handler` takes SIGTERM while the block runs (in the main thread: elsewhere Python cannot install a handler,
    and the signal keeps its default). A handler the process had before (a launcher's such as submitit's, a user's)
    is called after it, also when it raises, and comes back afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.getsignal(signal.SIGTERM)

    def handler_then_before(signum: int, frame: FrameType | None) -> None:
        try:
            handler(signum, frame)
        finally:
            if callable(before):
                before(signum, frame)

    signal.signal(signal.SIGTERM, handler_then_before)
    try:
        yield
    finally:
        if not _Stopping.stopped:  # else SIGTERM stays ignored until the `interrupted_once` block ends
            signal.signal(signal.SIGTERM, before)


class _Stopping:
    """The `interrupted_once` blocks running (in the main thread), and whether a signal has stopped them."""
    blocks = 0
    stopped = False


def stop_listening() -> None:
    """Inside an `interrupted_once` block, ignore SIGINT and SIGTERM until it ends: the process is stopping already,
    and its clean-up must not be cut short by a second Ctrl-C — a partial dataset half deleted, an env's OpenGL
    context half freed (which crashed the process when it was freed again). Outside one, nothing."""
    if _Stopping.blocks and threading.current_thread() is threading.main_thread():
        _Stopping.stopped = True
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, signal.SIG_IGN)


def interrupt_once(signum: int, frame: FrameType | None) -> None:
    """A SIGINT handler: KeyboardInterrupt, as Python's own, and every SIGINT and SIGTERM after it ignored."""
    stop_listening()
    raise KeyboardInterrupt


@contextlib.contextmanager
def interrupted_once() -> Iterator[None]:
    """The block runs with `interrupt_once` for SIGINT (in the main thread), unless the process was started with
    SIGINT ignored (`cmd &` in a script: immune to Ctrl-C, as POSIX has it); SIGINT's and SIGTERM's handlers come back
    as they were afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    if before[signal.SIGINT] is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, interrupt_once)
    _Stopping.blocks += 1
    try:
        yield
    finally:
        _Stopping.blocks -= 1
        _Stopping.stopped = _Stopping.stopped and _Stopping.blocks > 0
        for signum, handler in before.items():
            signal.signal(signum, handler)


class _Terminable:
    """How many `terminable()` blocks are running: SIGTERM is theirs while one is."""
    blocks = 0


@contextlib.contextmanager
def terminable() -> Iterator[StopRequest]:
    """SIGTERM sets the StopRequest's flag instead of killing the process (`handling_sigterm`)."""
    request = StopRequest()
    with handling_sigterm(request.note):  # installed before the count, restored after it: a SIGTERM at any moment
        _Terminable.blocks += 1           # meets this handler or an interrupt that counts no block (it was lost when
        try:                              # the interrupt saw a block counted before, or after, this handler was in)
            yield request
        finally:
            _Terminable.blocks -= 1


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[list[int]]:
    """SIGTERM (SLURM's scancel or time limit) does what Ctrl-C does — a KeyboardInterrupt, every SIGINT and SIGTERM
    after it ignored while the command stops (`stop_listening`) — except inside a `terminable()` block, whose own
    handler takes it (and calls this one after it, which then does nothing). The list yielded gets the signal, so that
    the exit status can say so (`stopped_by`)."""
    terminated: list[int] = []

    def interrupt(signum: int, frame: FrameType | None) -> None:
        if _Terminable.blocks:
            return
        terminated.append(signum)
        stop_listening()
        raise KeyboardInterrupt

    with handling_sigterm(interrupt):
        yield terminated


def stopped_by(terminated: list[int]) -> tuple[str, int]:
    """What stopped a command that raised KeyboardInterrupt, and its exit status: SIGTERM (143) or Ctrl-C (130)."""
    return ("terminated (SIGTERM)", 143) if terminated else ("interrupted", 130)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM wait until the block has run (a write that must not be cut short: a dataset's episode), then
    reach the handlers they would have reached, as if they came then. In the main thread only (see above)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []
    before = {signum: signal.signal(signum, lambda signum, frame: came.append(signum))
              for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for signum, handler in before.items():
            signal.signal(signum, handler)
    if came:
        handler = before[came[0]]
        if callable(handler):
            handler(came[0], None)
        elif handler == signal.SIG_DFL:  # its default action (ending the process), now that the block is done
            signal.raise_signal(came[0])
