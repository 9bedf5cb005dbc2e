"""hauwm.atomic.written_whole: a file replaced whole, or left as it was."""

from __future__ import annotations

import pytest

from hauwm.atomic import written_whole


def test_the_new_contents_replace_the_file_only_when_the_block_ends(tmp_path):
    path = tmp_path / "stats.json"
    path.write_text("old")
    with written_whole(path) as partial:
        partial.write_text("new")
        assert path.read_text() == "old" and partial.name == ".stats.json.partial"
    assert path.read_text() == "new" and list(tmp_path.iterdir()) == [path]


@pytest.mark.parametrize("error", [KeyboardInterrupt, OSError])
def test_a_block_that_fails_leaves_the_file_as_it_was_and_nothing_beside_it(tmp_path, error):
    path = tmp_path / "checkpoint.pt"
    path.write_text("old")
    with pytest.raises(error), written_whole(path, "checkpoint.pt.tmp") as partial:
        partial.write_text("half of the n")
        raise error
    assert path.read_text() == "old" and list(tmp_path.iterdir()) == [path]


def test_the_new_contents_and_the_rename_are_flushed_to_the_disk(tmp_path, monkeypatch):
    """Without fsync, a power loss or a node's crash after the rename could leave an empty or cut-off checkpoint in
    place of the old and the new one (found by a review)."""
    import os

    flushed, renamed = [], []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (flushed.append(os.readlink(f"/proc/self/fd/{fd}")), real_fsync(fd)))
    monkeypatch.setattr(os, "replace", lambda a, b: (renamed.append(len(flushed)), real_replace(a, b)))
    path = tmp_path / "checkpoint.pt"
    with written_whole(path) as partial:
        partial.write_text("new")
    assert flushed == [str(partial), str(tmp_path)] and renamed == [1]  # the contents before the rename, then it


def test_a_flush_that_fails_leaves_the_file_as_it_was_and_nothing_beside_it(tmp_path, monkeypatch):
    """A full quota of network storage shows at fsync: the partial file stayed, on a disk the user was just told to
    free (found by a review)."""
    import errno
    import os

    def full(fd):
        raise OSError(errno.EDQUOT, "Disk quota exceeded")

    monkeypatch.setattr(os, "fsync", full)
    path = tmp_path / "checkpoint.pt"
    path.write_text("old")
    with pytest.raises(OSError, match="quota"), written_whole(path) as partial:
        partial.write_text("new")
    assert path.read_text() == "old" and list(tmp_path.iterdir()) == [path]
