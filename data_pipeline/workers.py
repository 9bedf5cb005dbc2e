"""Decode clips in worker processes that can be killed and replaced, with a per-clip timeout.

decord can hang on a bad file, and a hung C call cannot be interrupted from Python, so each clip is
decoded (and its frames encoded) in one of N forked worker processes. A worker that overruns the
timeout is killed and replaced; a worker that dies is replaced too. Results come back in job order
whatever the number of workers or their timing, so the shards do not depend on `--workers`.
Memory stays flat: at most `workers + lookahead` clips are in flight or waiting to be written. Workers end with
the build process, however it ends (`_end_with`).
"""

from __future__ import annotations

import ctypes
import os
import re
import signal
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from multiprocessing import get_context
from multiprocessing.connection import Connection, wait
from pathlib import Path

from .decode import ClipError, decode_clip
from .shard_format import encode_frames

PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when its parent ends
_LOG_PREFIX = re.compile(r"\[\d\d:\d\d:\d\d\] \S+:\d+: ")  # decord's "[time] file.cc:line: " prefixes


@dataclass(frozen=True)
class DecodeSettings:
    size: int
    resize: str
    min_frames: int
    encoding: str
    quality: int


@dataclass
class ClipResult:
    """`frames_member` and the source facts for a good clip; `reason`/`detail` for a failed one."""
    frames_member: bytes = b""
    num_frames: int = 0
    source_width: int = 0
    source_height: int = 0
    fps: float = 0.0
    decoder: str = ""  # decode.DecodedClip.decoder
    reason: str = ""
    detail: str = ""


def process_clip(path: Path, settings: DecodeSettings) -> ClipResult:
    """Decode, check and encode one clip (in a worker process)."""
    try:
        clip = decode_clip(path, settings.size, settings.resize, settings.min_frames)
    except ClipError as error:
        return ClipResult(reason=error.reason, detail=_LOG_PREFIX.sub("", error.detail))
    return ClipResult(encode_frames(clip.frames, settings.encoding, settings.quality), len(clip.frames),
                      clip.source_width, clip.source_height, round(clip.fps, 3), clip.decoder)


def _end_with(build_process: int) -> None:
    """Have Linux SIGKILL this worker when the build process ends, however it ends: killed with SIGKILL alone (by
    the OOM killer, or a user), it cannot tell its workers, which then waited for their next clip for good, adopted
    by init (and one that hangs in decord would never read anything again)."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != build_process:  # it ended before the signal was asked for
        os._exit(0)


def _serve(connection: Connection, settings: DecodeSettings, build_process: int) -> None:
    _end_with(build_process)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)  # FFmpeg's log lines about broken files; failures come back as ClipResults
    import cv2

    cv2.setNumThreads(1)
    while True:
        job = connection.recv()
        if job is None:
            return
        index, path = job
        connection.send((index, process_clip(path, settings)))


class _Worker:
    def __init__(self, settings: DecodeSettings):
        self.connection, child = get_context("fork").Pipe()
        self.process = get_context("fork").Process(target=_serve, args=(child, settings, os.getpid()), daemon=True)
        self.process.start()
        child.close()
        self.job: tuple[int, Path] | None = None
        self.deadline = 0.0

    def submit(self, index: int, path: Path, timeout: float) -> None:
        self.job, self.deadline = (index, path), time.monotonic() + timeout
        self.connection.send((index, path))

    def stop(self, kill: bool = False) -> None:
        if kill:
            self.process.kill()
        else:
            try:
                self.connection.send(None)
            except (BrokenPipeError, OSError):
                pass
        self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.connection.close()


class DecodePool:
    """`imap(paths)` yields one `ClipResult` per path, in order."""

    def __init__(self, workers: int, settings: DecodeSettings, timeout: float):
        self.settings, self.timeout = settings, timeout
        self.workers = [_Worker(settings) for _ in range(max(1, workers))]
        self.lookahead = 2 * len(self.workers)  # clips decoded ahead of the one written next

    def __enter__(self) -> "DecodePool":
        return self

    def __exit__(self, *exc) -> None:
        for worker in self.workers:
            worker.stop(kill=exc[0] is not None)

    def _replace(self, worker: _Worker) -> _Worker:
        worker.stop(kill=True)
        fresh = _Worker(self.settings)
        self.workers[self.workers.index(worker)] = fresh
        return fresh

    def imap(self, paths: Iterable[Path]) -> Iterator[ClipResult]:
        jobs = enumerate(paths)
        upcoming = next(jobs, None)
        done: dict[int, ClipResult] = {}
        next_out = 0
        window = len(self.workers) + self.lookahead
        while True:
            for worker in self.workers:  # keep idle workers busy, within the window after next_out
                if worker.job is None and upcoming is not None and upcoming[0] < next_out + window:
                    try:
                        worker.submit(*upcoming, self.timeout)
                    except OSError:  # it died while idle (the OOM killer, a user): the clip goes to a fresh one
                        self._replace(worker).submit(*upcoming, self.timeout)
                    upcoming = next(jobs, None)
            while next_out in done:
                yield done.pop(next_out)
                next_out += 1
            busy = [worker for worker in self.workers if worker.job is not None]
            if not busy:
                if upcoming is None:
                    return
                continue
            ready = wait([w.connection for w in busy],
                         timeout=max(0.0, min(w.deadline for w in busy) - time.monotonic()))
            for worker in busy:
                if worker.connection in ready:
                    try:
                        index, result = worker.connection.recv()
                        worker.job = None
                    except (EOFError, OSError):  # the worker died (segfault, out of memory)
                        index, result = worker.job[0], ClipResult(reason="crashed", detail="the decoder process died")
                        self._replace(worker)
                    done[index] = result
                elif time.monotonic() >= worker.deadline:
                    done[worker.job[0]] = ClipResult(reason="timeout", detail=f"no result within {self.timeout:g} s")
                    self._replace(worker)
