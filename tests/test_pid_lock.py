"""hauwm.pid_lock: one holder at a time, named by its pid."""

from __future__ import annotations

import os

import pytest

from hauwm.pid_lock import LockHeld, lock_holder, locked, pid_lock


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


def test_a_lock_whose_file_its_last_holder_deleted_meanwhile_is_taken_on_the_new_file(tmp_path, monkeypatch):
    """The holder before deleted the file between this process's open and its lock: the lock taken on the deleted
    file would be held by nobody else's reckoning, and a third process would lock the new file beside it."""
    import hauwm.pid_lock

    path, opened = tmp_path / ".lock", []
    flock_soon = hauwm.pid_lock._flock_soon

    def deleted_first(lock):
        if not opened:  # the first file opened: its holder deletes it now and lets go
            opened.append(lock)
            path.unlink()
        return flock_soon(lock)

    monkeypatch.setattr(hauwm.pid_lock, "_flock_soon", deleted_first)
    path.write_text("")
    with pid_lock(path):
        assert len(opened) == 1 and path.is_file() and lock_holder(path) == os.getpid()  # the file at `path`


def test_a_lock_whose_holder_removed_its_directory_meanwhile_is_taken_in_the_directory_made_again(tmp_path,
                                                                                                   monkeypatch):
    """Two runs on one new --logdir: the first, refused, removed the directory it had made as it let go; the second,
    waiting on the deleted file, then failed to open the lock again (FileNotFoundError; found by a review)."""
    import shutil

    import hauwm.pid_lock

    path, opened = tmp_path / "new" / "run" / ".lock", []
    flock_soon = hauwm.pid_lock._flock_soon

    def removed_first(lock):
        if not opened:  # the holder lets go: it deletes the file and the directories it made
            opened.append(lock)
            shutil.rmtree(tmp_path / "new")
        return flock_soon(lock)

    monkeypatch.setattr(hauwm.pid_lock, "_flock_soon", removed_first)
    with pid_lock(path):
        assert len(opened) == 1 and path.read_text() == str(os.getpid())


def test_a_lock_asked_for_while_lock_holder_looks_is_not_refused(tmp_path):
    """lock_holder holds a shared lock for an instant; a process asking for the lock then was told it was held."""
    import fcntl
    import threading

    path = tmp_path / ".lock"
    path.write_text("")
    looking = open(path)
    fcntl.flock(looking, fcntl.LOCK_SH)  # as lock_holder does, from another open file
    threading.Timer(0.05, looking.close).start()  # and lets go an instant later
    with pid_lock(path):  # LockHeld('?') before
        assert path.read_text() == str(os.getpid())


def test_locked_raises_the_callers_error_and_deletes_its_file(tmp_path):
    path = tmp_path / "made" / ".lock"

    def busy(pid: str) -> ValueError:
        return ValueError(f"busy: {pid}")

    with locked(path, busy):
        assert lock_holder(path) == os.getpid()
        with pytest.raises(ValueError, match=f"^busy: {os.getpid()}$"), locked(path, busy):
            pass
        assert path.exists()  # the refused one leaves the holder's file
    assert not path.exists() and path.parent.is_dir()


def test_a_lock_held_before_its_holder_wrote_its_pid_is_held(tmp_path):
    """Between the flock and the pid's write, lock_holder said the lock was free (a build of another --num-parts then
    went on beside it)."""
    import fcntl

    path = tmp_path / ".lock"
    with open(path, "w") as holder:
        fcntl.flock(holder, fcntl.LOCK_EX)
        assert lock_holder(path) == "?"
        holder.write("garbage")
        holder.flush()
        assert lock_holder(path) == "?"
    assert lock_holder(path) is None
