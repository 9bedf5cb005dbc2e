"""Replace a file whole or not at all: every stage's writer of a file that a kill or a full disk must not leave
half-written (checkpoints, the export, shard statistics, CSV logs, replay episodes).

    with written_whole(path) as partial:
        torch.save(state, partial)

The block writes `partial`, beside `path`; when it ends, `partial` is flushed to the disk (fsync) and renamed over
`path` (a rename within one directory is atomic on POSIX: a reader sees the old file or the new one), and the rename
itself is flushed (fsync of the directory): after a power loss or a node's crash the file is the old one or the
new one, not an empty or a cut-off one in place of both. When the block ends by an exception (Ctrl-C, a full disk),
`partial` is deleted and `path` stays as it was. A kill -9 can leave `partial` behind, hidden by its leading dot
unless `partial_name` says otherwise.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def written_whole(path: Path, partial_name: str | None = None) -> Iterator[Path]:
    """Yield the path to write `path`'s new contents to (`.NAME.partial` beside it, or `partial_name`)."""
    partial = path.with_name(partial_name or f".{path.name}.partial")
    try:
        yield partial
        flush_to_disk(partial)  # a full quota of network storage may show only here (EDQUOT)
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    flush_to_disk(path.parent)


def flush_to_disk(path: Path) -> None:
    """fsync a file's contents, or a directory's entries (a rename in it)."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)
