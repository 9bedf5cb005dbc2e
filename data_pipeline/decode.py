"""Decode one SSv2 clip once, check it for faults, and resize its frames to `size × size`.

decord (one thread: VP9 WebM fails with its default of 0 threads) reads the clip frame by frame until
the stream ends, so the frame count is the number of frames actually decoded (WebM stores none).
Where decord cannot open a file (or is not installed), or would decode it wrong (decord 0.6 mis-shapes
the frames of some narrow videos and misplaces the colour of odd heights: `decord_frame_trusted`), or
the container declares more than a million frames, OpenCV decodes the clip; `DecodedClip.decoder` says
which decoded it, and the shard builder counts OpenCV's. `fault_tol=0` makes decord raise instead of silently
repeating frames on corrupt input; a clip whose frames end before its container's duration declares is corrupt
too (truncated, or garbage at the end: `broken_off`), and so is one short of frames with a hole in the middle
(`holed`). Faults raise `ClipError(reason, detail)`, which the shard builder records in `errors.jsonl`; the
per-clip timeout lives in `workers.py`.
"""

from __future__ import annotations

import itertools
import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from hauwm.messages import first_line

RESIZE_MODES = ("squash", "center-crop")
DECLARED_SLACK = 2  # frames a container's declared duration may exceed the decoded count by
MAX_DROPPED_RUN = 5  # frames a camera may drop in a row; a longer run, in a clip short of frames, is a hole (damage)
MAX_DECLARED_FRAMES = 1_000_000  # more, and decord is not tried: a damaged duration of 1e15 ms made it abort
#                                  the process (std::bad_alloc); a day at 12 fps is about 1e6 frames


class ClipError(Exception):
    """A clip that cannot go into a shard; `reason` is `missing`, `unreadable`, `empty`, `undecodable`, `corrupt` or
    `too-short`."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason, self.detail = reason, detail


@dataclass
class DecodedClip:
    frames: np.ndarray  # uint8 [T, size, size, 3], RGB
    source_width: int
    source_height: int
    fps: float
    decoder: str  # "decord", or "opencv" where decord could not open the file (or is not installed)


def resize_frame(frame: np.ndarray, size: int, mode: str) -> np.ndarray:
    """`uint8 [H, W, 3]` → `uint8 [size, size, 3]`: squash the whole frame, or crop its centre square first."""
    if mode == "center-crop":
        height, width = frame.shape[:2]
        side = min(height, width)
        top, left = (height - side) // 2, (width - side) // 2
        frame = frame[top:top + side, left:left + side]
    elif mode != "squash":
        raise ValueError(f"unknown resize mode {mode!r}; choose from {', '.join(RESIZE_MODES)}")
    return cv2.resize(frame, (size, size), interpolation=cv2.INTER_AREA)


@dataclass(frozen=True)
class Container:
    """What a file's headers declare, as OpenCV reads them (all 0 where it cannot open the file)."""

    frame_count: int  # the frame count its duration implies (0: it declares none)
    fps: float  # the frame rate that count was computed with (duration = frame_count / fps)
    width: int
    height: int


def read_container(path: Path) -> Container:
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            return Container(0, 0.0, 0, 0)
        count, fps = capture.get(cv2.CAP_PROP_FRAME_COUNT), capture.get(cv2.CAP_PROP_FPS)
        return Container(max(0, int(round(count))) if math.isfinite(count) else 0, fps if math.isfinite(fps) else 0.0,
                         int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    finally:
        capture.release()


def decord_frame_trusted(frame: np.ndarray, container: Container) -> bool:
    """Whether decord decodes this file right, judged by its first frame: RGB [H, W, 3] of the container's size, H
    even. decord 0.6 gives [H, W, 4] or [H, W, 6] frames of shifted rows for some narrow videos (16, 24, 48 or 72 px
    wide) and misplaces the colour rows of videos of odd height (by up to 11 grey levels); OpenCV decodes both right."""
    if frame.ndim != 3 or frame.shape[2] != 3:
        return False
    if container.height == 0:  # OpenCV cannot read the headers: decord is the only decoder there is
        return True
    return frame.shape[:2] == (container.height, container.width) and container.height % 2 == 0


# a decoder yields (frame uint8 [H, W, 3] RGB, the stream's fps, the second at which the frame ends)


def _decode_decord(path: Path):
    import decord

    reader = decord.VideoReader(str(path), num_threads=1, fault_tol=0)
    fps = float(reader.get_avg_fps())
    for index in itertools.count():
        try:
            frame = reader.next().asnumpy()
        except StopIteration:
            return
        yield frame, fps, float(reader.get_frame_timestamp(index)[1])


def _decode_opencv(path: Path):
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise ClipError("undecodable", "neither decord nor OpenCV can open the file")
    fps = float(capture.get(cv2.CAP_PROP_FPS))
    try:
        while True:
            ok, frame = capture.read()
            if not ok:
                return
            ends = capture.get(cv2.CAP_PROP_POS_MSEC) / 1000 + (1 / fps if fps > 0 else 0.0)  # POS_MSEC: its start
            yield frame[:, :, ::-1], fps, ends  # BGR → RGB
    finally:
        capture.release()


def _open(path: Path, container: Container):
    """(decoder name, its iterator, its first (frame, fps, end) or None): decord where it opens the file
    and decodes it right (`decord_frame_trusted`), else OpenCV. A container declaring more than MAX_DECLARED_FRAMES
    goes to OpenCV straight away: decord allocates for every frame declared."""
    if container.frame_count <= MAX_DECLARED_FRAMES:
        try:
            frames_iter = _decode_decord(path)
            first = next(frames_iter, None)
            if first is None or decord_frame_trusted(first[0], container):
                return "decord", frames_iter, first
        except Exception:  # decord raises bare RuntimeError/DECORDError on files it cannot open
            pass
    frames_iter = _decode_opencv(path)
    return "opencv", frames_iter, next(frames_iter, None)


def holed(decoded: int, longest_step: float, container: Container) -> bool:
    """Whether fewer frames decode than the container declares (by more than DECLARED_SLACK) and, somewhere in the
    stream, more than MAX_DROPPED_RUN frames in a row are missing (`longest_step`: the longest time between two
    decoded frames): garbage in the stream that the decoder skipped, after a mangled frame, though the last frame
    ends on time. A camera dropping frames drops a few at a time."""
    if container.fps <= 0 or decoded + DECLARED_SLACK >= container.frame_count:
        return False
    return longest_step * container.fps > MAX_DROPPED_RUN + 1 + 0.5  # a step of n + 1 frame times: n frames missing


def broken_off(decoded: int, decoded_until: float, container: Container) -> bool:
    """Whether the decoded stream ends before the duration its container declares, by more than DECLARED_SLACK
    frames: a truncated file, or garbage where the decoder stopped. Timed by the frames' timestamps (a stream whose
    timestamps skip frames reaches its duration with fewer frames) and, where those are missing, by the count."""
    if container.fps <= 0:
        return decoded + DECLARED_SLACK < container.frame_count
    until = max(decoded_until, decoded / container.fps)
    return until + DECLARED_SLACK / container.fps < container.frame_count / container.fps


def decode_clip(path: Path, size: int, resize: str = "squash", min_frames: int = 1) -> DecodedClip:
    """Decode every frame of `path`, resized; raise `ClipError` for any fault."""
    path = Path(path)
    if not path.is_file():  # nothing there, or no regular file (a directory, a device, a pipe: reading could hang)
        what = "a directory" if path.is_dir() else "not a regular file" if path.exists() else None
        raise ClipError("missing", f"{path} is {what}, not a video file" if what else f"no file at {path}")
    if os.path.getsize(path) == 0:
        raise ClipError("empty", "the file has 0 bytes")
    try:  # decord and OpenCV would say only that they cannot open it: `undecodable`, never retried
        with open(path, "rb") as file:
            file.read(1)
    except OSError as error:  # no permission, an I/O error of network storage: of the moment, retried
        raise ClipError("unreadable", f"{path}: {error.strerror or error}") from None
    container = read_container(path)
    backend, frames_iter, first = _open(path, container)
    if first is None:
        raise ClipError("empty", f"{backend} decoded no frames (a codec neither decord nor OpenCV decodes, e.g. AV1)")
    source_height, source_width = first[0].shape[:2]
    fps = first[1]
    resized, decoded_until = [resize_frame(first[0], size, resize)], first[2]
    longest_step, decoder_error = 0.0, None
    try:
        for frame, _, ends in frames_iter:
            resized.append(resize_frame(frame, size, resize))
            longest_step = max(longest_step, ends - decoded_until)
            decoded_until = max(decoded_until, ends)
    except Exception as error:  # DECORDLimitReachedError (frames recovered from corrupt data), a failed decoder check
        decoder_error = f"{backend}: {first_line(error)[:200]}"
    declared = container.frame_count
    if declared and broken_off(len(resized), decoded_until, container):
        # no count of the frames decoded, and the same words whether the decoder stopped at the damage or raised
        # there: decord does either, after a varying number of frames, from run to run on the same file, and a
        # resumed build's errors.jsonl must be byte-identical to an unbroken one's
        raise ClipError("corrupt", f"the stream breaks off: fewer frames decode than the {declared} its container "
                                   "declares (truncated or damaged; or a video whose audio outlasts its picture, or which "
                                   "starts late: docs/data_pipeline.md)")
    if declared and holed(len(resized), longest_step, container):
        raise ClipError("corrupt", f"the stream has a hole: more than {MAX_DROPPED_RUN} frames in a row are missing, "
                                   f"and fewer frames decode than the {declared} its container declares (damaged)")
    if decoder_error is not None:
        raise ClipError("corrupt", decoder_error)
    if len(resized) < min_frames:
        raise ClipError("too-short", f"{len(resized)} frames, fewer than --min-frames {min_frames}")
    return DecodedClip(np.stack(resized), int(source_width), int(source_height), fps, backend)
