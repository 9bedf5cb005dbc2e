"""hauwm.termination: a SIGTERM is never lost between a command's handler and a run's `terminable()` block."""

from __future__ import annotations

import contextlib
import signal

import pytest

from hauwm import termination
from hauwm.termination import sigterm_as_interrupt, terminable


@pytest.mark.parametrize("moment", ["as the block's handler goes in", "as it goes out"])
def test_a_sigterm_as_a_terminable_block_starts_or_ends_is_not_lost(monkeypatch, moment):
    """The block was counted before its handler went in and after it went out: a SIGTERM in either gap met the
    command's handler, which saw a block and left the signal to it, so nobody took it (found by a review)."""
    real = termination.handling_sigterm

    @contextlib.contextmanager
    def sigterm_at_the_edge(handler):
        if moment == "as the block's handler goes in":
            signal.raise_signal(signal.SIGTERM)
        with real(handler):
            yield
        if moment == "as it goes out":
            signal.raise_signal(signal.SIGTERM)

    with sigterm_as_interrupt() as terminated:
        monkeypatch.setattr(termination, "handling_sigterm", sigterm_at_the_edge)
        with pytest.raises(KeyboardInterrupt), terminable():
            pass
    assert terminated == [signal.SIGTERM]
