"""Decode one SSv2 clip once, check it for faults, and resize its frames to `size × size`.

decord (one thread: VP9 WebM fails with its default of 0 threads) reads the clip frame by frame until
the stream ends, so the frame count is the number of frames actually decoded (WebM stores none).
Where decord cannot open a file (or is not installed), or gives frames that are not RGB (decord 0.6
mis-shapes those of some narrow videos), OpenCV decodes the clip; `DecodedClip.decoder` says which
decoded it, and the shard builder counts OpenCV's. `fault_tol=0` makes decord raise instead of silently
repeating frames on corrupt input; a clip that decodes to fewer frames than its container's duration
declares is corrupt too (truncated, or garbage in the stream). Faults raise `ClipError(reason, detail)`,
which the shard builder records in `errors.jsonl`; the per-clip timeout lives in `workers.py`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

RESIZE_MODES = ("squash", "center-crop")
DECLARED_SLACK = 2  # frames a container's declared duration may exceed the decoded count by


class ClipError(Exception):
    """A clip that cannot go into a shard; `reason` is `missing`, `empty`, `undecodable`, `corrupt` or `too-short`."""

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


def declared_frame_count(path: Path) -> int:
    """The frame count the container's duration implies (0 when it declares none)."""
    capture = cv2.VideoCapture(str(path))
    try:
        return max(0, int(round(capture.get(cv2.CAP_PROP_FRAME_COUNT)))) if capture.isOpened() else 0
    finally:
        capture.release()


def _decode_decord(path: Path):
    import decord

    reader = decord.VideoReader(str(path), num_threads=1, fault_tol=0)
    fps = float(reader.get_avg_fps())
    while True:
        try:
            yield reader.next().asnumpy(), fps
        except StopIteration:
            return


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
            yield frame[:, :, ::-1], fps  # BGR → RGB
    finally:
        capture.release()


def _open(path: Path):
    """(decoder name, its (frame, fps) iterator, the first (frame, fps) or None): decord where it opens the file
    and gives RGB frames, else OpenCV."""
    try:
        frames_iter = _decode_decord(path)
        first = next(frames_iter, None)
        if first is None or first[0].shape[2:] == (3,):
            return "decord", frames_iter, first
        # decord 0.6 mis-shapes the frames of some narrow videos (16, 24, 48 or 72 px wide: [H, W, 4] or [H, W, 6]
        # of shifted rows), which would go into the shard as garbage colours
    except Exception:  # decord raises bare RuntimeError/DECORDError on files it cannot open
        pass
    frames_iter = _decode_opencv(path)
    return "opencv", frames_iter, next(frames_iter, None)


def decode_clip(path: Path, size: int, resize: str = "squash", min_frames: int = 1) -> DecodedClip:
    """Decode every frame of `path`, resized; raise `ClipError` for any fault."""
    path = Path(path)
    if not path.is_file():  # nothing there, or no regular file (a directory, a device, a pipe: reading could hang)
        what = "a directory" if path.is_dir() else "not a regular file" if path.exists() else None
        raise ClipError("missing", f"{path} is {what}, not a video file" if what else f"no file at {path}")
    if os.path.getsize(path) == 0:
        raise ClipError("empty", "the file has 0 bytes")
    backend, frames_iter, first = _open(path)
    if first is None:
        raise ClipError("empty", f"{backend} decoded no frames")
    source_height, source_width = first[0].shape[:2]
    fps = first[1]
    resized = [resize_frame(first[0], size, resize)]
    decoder_error = None
    try:
        for frame, _ in frames_iter:
            resized.append(resize_frame(frame, size, resize))
    except Exception as error:  # DECORDLimitReachedError (frames recovered from corrupt data), a failed decoder check
        decoder_error = f"{backend}: {str(error).strip().splitlines()[0][:200]}"
    declared = declared_frame_count(path)
    if declared and len(resized) + DECLARED_SLACK < declared:
        # no count of the frames decoded, and the same words whether the decoder stopped at the damage or raised
        # there: decord does either, after a varying number of frames, from run to run on the same file, and a
        # resumed build's errors.jsonl must be byte-identical to an unbroken one's
        raise ClipError("corrupt", f"the stream breaks off: fewer frames decode than the {declared} its container "
                                   "declares (truncated or damaged)")
    if decoder_error is not None:
        raise ClipError("corrupt", decoder_error)
    if len(resized) < min_frames:
        raise ClipError("too-short", f"{len(resized)} frames, fewer than --min-frames {min_frames}")
    return DecodedClip(np.stack(resized), int(source_width), int(source_height), fps, backend)
