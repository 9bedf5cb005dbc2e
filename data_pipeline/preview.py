"""`hauwm shards preview DIR --out preview.png`: a grid of sampled sequences, one clip per row,
its L frames (sampled with gaps k ~ U{1..K_max}, as the loader does) along the row, each labelled
with its frame index and gap; the row's caption (class index: caption) sits above it."""

from __future__ import annotations

import json
import tarfile
from pathlib import Path

import cv2
import numpy as np

from .sampling import gaps_of, sample_indices
from .shard_format import MANIFEST_FILE, ShardDirError, decode_frames, read_manifest

SCALE, LABEL_HEIGHT, CAPTION_HEIGHT = 2, 14, 16
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")  # what cv2.imwrite writes here


def _clips(directory: Path, shards: list[dict]):
    for shard in shards:
        with tarfile.open(directory / shard["name"]) as tar:
            members: dict[str, dict[str, bytes]] = {}
            for member in tar:
                key, extension = member.name.split(".", 1)
                members.setdefault(key, {})[extension] = tar.extractfile(member).read()
                if len(members[key]) == 2:
                    yield members.pop(key)


def _text(canvas: np.ndarray, text: str, x: int, y: int, scale: float = 0.35) -> None:
    cv2.putText(canvas, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


def write_preview(directory: Path, out: Path, split: str | None = None, clips: int = 8, length: int = 8,
                  k_max: int = 5, seed: int = 0) -> None:
    directory, out = Path(directory), Path(out)
    if out.suffix.lower() not in IMAGE_SUFFIXES:
        raise ShardDirError(f"--out {out}: name an image file ending in {', '.join(IMAGE_SUFFIXES)}")
    manifest = read_manifest(directory)
    split = split or next(iter(manifest["splits"]))
    if split not in manifest["splits"]:
        raise ShardDirError(f"{directory / MANIFEST_FILE} has no split {split!r} (it has {', '.join(manifest['splits'])})")
    rng = np.random.default_rng(seed)
    rows = []
    for files in _clips(directory, manifest["splits"][split]["shards"]):
        metadata = json.loads(files["json"])
        indices = sample_indices(metadata["num_frames"], length, k_max, rng)
        if indices is None:
            continue
        extension = next(e for e in files if e != "json")
        rows.append((metadata, indices, decode_frames(files[extension], extension, indices)))
        if len(rows) == clips:
            break
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
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), canvas[:, :, ::-1]):
        raise ShardDirError(f"cannot write {out} (is its directory writable?)")
