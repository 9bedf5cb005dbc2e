"""`hauwm shards preview DIR --out preview.png`: a grid of sampled sequences, one clip per row,
its L frames (sampled with gaps k ~ U{1..K_max}, as the loader does) along the row, each labelled
with its frame index and gap; the row's caption (clip id, [class index], label) sits above it."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from hauwm.atomic import written_whole

from .sampling import gaps_of, sample_indices
from .shard_format import (MANIFEST_FILE, ShardDirError, UnreadableShard, decode_frames, frames_member, read_manifest,
                           read_samples)

SCALE, LABEL_HEIGHT, CAPTION_HEIGHT = 2, 14, 16
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")  # what cv2.imencode writes here


def _clips(directory: Path, shards: list[dict]) -> Iterator[dict]:
    """The clips of `shards` in order, as read_samples gives them (a damaged shard: ValueError naming it)."""
    for shard in shards:
        path = directory / shard["name"]
        with path.open("rb") as stream:
            yield from read_samples(stream, str(path))


def _text(canvas: np.ndarray, text: str, x: int, y: int, scale: float = 0.35) -> None:
    """`text` drawn in OpenCV's Hershey font, which has ASCII only: other characters are drawn as '?' (half a UTF-16
    pair, in a caption of shards built before such text was refused, made putText crash the process)."""
    text = text.encode("ascii", "replace").decode("ascii")
    cv2.putText(canvas, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


def write_preview(directory: Path, out: Path, split: str | None = None, clips: int = 8, length: int = 8,
                  k_max: int = 5, seed: int = 0) -> None:
    directory, out = Path(directory), Path(out)
    if out.suffix.lower() not in IMAGE_SUFFIXES:
        raise ShardDirError(f"--out {out}: name an image file ending in {', '.join(IMAGE_SUFFIXES)}")
    if out.is_dir():
        raise ShardDirError(f"--out {out} is a directory: name an image file, e.g. {out / 'preview.png'}")
    manifest = read_manifest(directory)
    split = split or next(iter(manifest["splits"]))
    if split not in manifest["splits"]:
        raise ShardDirError(f"{directory / MANIFEST_FILE} has no split {split!r} (it has {', '.join(manifest['splits'])})")
    rng = np.random.default_rng(seed)
    rows = []
    try:
        for files in _clips(directory, manifest["splits"][split]["shards"]):
            metadata = json.loads(files["json"])
            indices = sample_indices(metadata["num_frames"], length, k_max, rng)
            if indices is None:
                continue
            extension, member = frames_member(files)
            rows.append((metadata, indices, decode_frames(member, extension, indices)))
            if len(rows) == clips:
                break
    except UnreadableShard as error:  # its message says what to do
        raise ShardDirError(f"split {split!r} in {directory}: {error}") from None
    except (KeyError, ValueError) as error:  # a clip frames_member or decode_frames cannot read
        what = f"no {error} member" if isinstance(error, KeyError) else error
        raise ShardDirError(f"split {split!r} in {directory}: {what}; check the shards with `hauwm shards inspect "
                            f"{directory} --verify`") from None
    if not rows:
        raise ShardDirError(f"split {split!r} in {directory} has no clip with at least {length} frames")
    side = rows[0][2].shape[1] * SCALE
    row_height = CAPTION_HEIGHT + side + LABEL_HEIGHT
    canvas = np.zeros((row_height * len(rows), side * length, 3), np.uint8)
    for r, (metadata, indices, frames) in enumerate(rows):
        top = r * row_height
        _text(canvas, f"{metadata['id']}  [{metadata['class_index']}] {metadata['caption']}"[:90], 4, top + 12, 0.4)
        for j, (frame, index, gap) in enumerate(zip(frames, indices, gaps_of(indices))):
            image = cv2.resize(frame, (side, side), interpolation=cv2.INTER_NEAREST)
            canvas[top + CAPTION_HEIGHT: top + CAPTION_HEIGHT + side, j * side:(j + 1) * side] = image
            _text(canvas, f"t={index}" + (f" k={gap}" if j else ""), j * side + 3, top + row_height - 3)
    encoded, image = cv2.imencode(out.suffix, canvas[:, :, ::-1])
    if not encoded:
        raise ShardDirError(f"--out {out}: OpenCV cannot write {out.suffix} images; name a .png or .jpg file")
    out.parent.mkdir(parents=True, exist_ok=True)
    with written_whole(out) as partial:  # a full disk leaves an earlier preview there as it was
        partial.write_bytes(image.tobytes())
