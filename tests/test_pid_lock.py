"""hauwm.pid_lock: one holder at a time, named by its pid."""

from __future__ import annotations

import os

import pytest

from hauwm.pid_lock import LockHeld, lock_holder, pid_lock


def test_a_second_holder_is_refused_with_the_first_ones_pid_and_the_lock_goes_with_its_holder(tmp_path):
    path = tmp_path / ".lock"
    assert lock_holder(path) is None
    with pid_lock(path):
        assert lock_holder(path) == os.getpid()
        with pytest.raises(LockHeld) as held, pid_lock(path):  # another open file: flock treats it as another holder
            pass
        assert held.value.pid == str(os.getpid())
    assert lock_holder(path) is None
    with pid_lock(path):  # free again
        path.unlink()  # a holder may delete its file before it lets go
    with pid_lock(path):
        assert path.read_text() == str(os.getpid())
