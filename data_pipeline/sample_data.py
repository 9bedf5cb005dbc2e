"""The built-in dataset: procedurally generated stochastic scenes in SSv2's exact on-disk format.

`hauwm shards sample-data --out DIR --clips N` writes `DIR/annotations/something-something-v2-{train,
validation,test,labels}.json` and `DIR/videos/<id>.webm` (real VP9 WebM written by OpenCV, 12 fps,
height 240, a width that varies per clip), so every later stage runs exactly as on SSv2.

Each clip shows one or two large, high-contrast shapes on a dark background. Every frame, each shape
changes course to a new random heading with probability `TURN_PROBABILITY` (and bounces off the walls),
so the next frame is nearly certain but a frame k steps ahead is uncertain, and more so the larger k:
the property the paper's horizon-calibrated uncertainty (eq. 3) is meant to capture. The caption and
class come from the SSv2-style templates below, chosen from the clip's actual net motion.

`--with-broken` adds the failure kinds the shard builder must survive (`BROKEN_KINDS`), listed in
`DIR/broken.json` (id → kind; empty without them) so tests can check that each one lands in `errors.jsonl`.
"""

from __future__ import annotations

import json
import math
import os
import signal
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from .ssv2 import annotation_path, class_name

FPS = 12
ID_RANGE = 220_000  # clip ids are drawn from 1..ID_RANGE - 1, as SSv2's run to 220,847
HEIGHT = 240
WIDTHS = (320, 352, 400, 427, 480)
MIN_FRAMES, MAX_FRAMES = 24, 60
TURN_PROBABILITY = 0.2  # per frame and shape: the scene's source of uncertainty
SPEED_RANGE = (14.0, 24.0)  # pixels per frame at height 240 (about 4–6 px at 64×64)
RADIUS_RANGE = (30, 46)  # pixels at height 240 (about 8–12 px at 64×64)

TEMPLATES = (
    "Pushing [something] from left to right",
    "Pushing [something] from right to left",
    "Moving [something] up",
    "Moving [something] down",
    "Moving [something] and [something] closer to each other",
    "Moving [something] and [something] away from each other",
    "Tipping [something] with [something in it] over, so [something in it] falls out",
    "Putting [something] onto [a slanted surface]",
)
COLORS = {"red": (230, 40, 40), "green": (40, 220, 60), "blue": (50, 90, 255), "yellow": (250, 230, 40),
          "white": (245, 245, 245), "magenta": (235, 50, 220), "cyan": (40, 230, 235), "orange": (255, 150, 20)}
SHAPES = ("ball", "box")
BROKEN_KINDS = {  # kind → the reason prefix `hauwm shards build` records for it
    "corrupt": "corrupt", "truncated": "corrupt", "empty": "empty", "missing": "missing",
    "too-short": "too-short", "not-a-video": "undecodable",
}


@dataclass(frozen=True)
class Shape:
    kind: str
    color_name: str
    radius: int


def render_scene(rng: np.random.Generator, num_frames: int, width: int,
                 height: int = HEIGHT) -> tuple[np.ndarray, list[Shape], np.ndarray]:
    """Frames `uint8 [T, H, W, 3]` (RGB), the shapes, and their centres `float [T, S, 2]`."""
    num_shapes = int(rng.integers(1, 3))
    names = rng.choice(list(COLORS), size=num_shapes, replace=False)
    shapes = [Shape(str(rng.choice(SHAPES)), str(name), int(rng.integers(*RADIUS_RANGE))) for name in names]
    position = np.stack([rng.uniform([s.radius, s.radius], [width - s.radius, height - s.radius])
                         for s in shapes])  # [S, 2] as (x, y)
    heading = rng.uniform(0, 2 * math.pi, num_shapes)
    speed = rng.uniform(*SPEED_RANGE, num_shapes)
    background = rng.integers(10, 70, 3)
    ramp = np.linspace(0.6, 1.0, width)[None, :, None]  # a faint horizontal gradient
    canvas = (background[None, None, :] * ramp).astype(np.uint8)
    canvas = np.repeat(canvas, height, axis=0)

    frames = np.empty((num_frames, height, width, 3), np.uint8)
    centres = np.empty((num_frames, num_shapes, 2))
    for t in range(num_frames):
        frame = canvas.copy()
        for index, shape in enumerate(shapes):
            x, y = position[index]
            color = COLORS[shape.color_name]
            if shape.kind == "ball":
                cv2.circle(frame, (int(x), int(y)), shape.radius, color, -1, cv2.LINE_AA)
            else:
                r = shape.radius
                cv2.rectangle(frame, (int(x - r), int(y - r)), (int(x + r), int(y + r)), color, -1)
        frames[t] = frame
        centres[t] = position
        turns = rng.random(num_shapes) < TURN_PROBABILITY
        heading = np.where(turns, rng.uniform(0, 2 * math.pi, num_shapes), heading)
        velocity = speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1)
        position = position + velocity
        for index, shape in enumerate(shapes):  # bounce off the walls: mirror the heading
            for axis, limit in ((0, width), (1, height)):
                low, high = shape.radius, limit - shape.radius
                if not low <= position[index, axis] <= high:
                    position[index, axis] = np.clip(position[index, axis], low, high)
                    heading[index] = (math.pi - heading[index]) if axis == 0 else -heading[index]
    return frames, shapes, centres


def choose_template(shapes: list[Shape], centres: np.ndarray) -> str:
    """The SSv2-style class that best describes the clip's net motion."""
    if len(shapes) == 2:
        start = np.linalg.norm(centres[0, 0] - centres[0, 1])
        end = np.linalg.norm(centres[-1, 0] - centres[-1, 1])
        if abs(end - start) < 20:
            return TEMPLATES[6]
        return TEMPLATES[4] if end < start else TEMPLATES[5]
    dx, dy = centres[-1, 0] - centres[0, 0]
    if max(abs(dx), abs(dy)) < 20:
        return TEMPLATES[7]
    if abs(dx) >= abs(dy):
        return TEMPLATES[0] if dx > 0 else TEMPLATES[1]
    return TEMPLATES[3] if dy > 0 else TEMPLATES[2]


def fill_template(template: str, shapes: list[Shape]) -> tuple[str, list[str]]:
    """The caption (brackets replaced by object names) and the placeholders, as in SSv2."""
    names = [f"{s.color_name} {s.kind}" for s in shapes]
    placeholders = [names[min(i, len(names) - 1)] for i in range(template.count("["))]
    caption = template
    for name in placeholders:
        start, end = caption.index("["), caption.index("]")
        caption = caption[:start] + name + caption[end + 1:]
    return caption, placeholders


def write_webm(path: Path, frames: np.ndarray) -> None:
    """Real VP9 WebM via OpenCV; `frames` is RGB `uint8 [T, H, W, 3]`."""
    height, width = frames.shape[1:3]
    saved = os.dup(2)  # OpenCV prints a harmless "tag 'VP90' is not supported ... fallback" line to stderr
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)
    try:
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"VP90"), FPS, (width, height))
    finally:
        os.dup2(saved, 2)
        os.close(saved)
    if not writer.isOpened():
        raise RuntimeError(f"{path}: OpenCV cannot write VP9 WebM here (its FFmpeg build lacks libvpx)")
    for frame in frames:
        writer.write(np.ascontiguousarray(frame[:, :, ::-1]))
    writer.release()


def _make_clip(job: tuple[int, str, Path, str]) -> dict:
    """Render and write one clip; returns its SSv2 annotation entry."""
    seed, clip_id, videos, kind = job
    rng = np.random.default_rng(seed)
    num_frames = 4 if kind == "too-short" else int(rng.integers(MIN_FRAMES, MAX_FRAMES + 1))
    frames, shapes, centres = render_scene(rng, num_frames, int(rng.choice(WIDTHS)))
    template = choose_template(shapes, centres)
    caption, placeholders = fill_template(template, shapes)
    path = videos / f"{clip_id}.webm"
    if kind in ("ok", "too-short", "truncated", "corrupt"):
        write_webm(path, frames)
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif kind == "corrupt":  # garbage in the middle of the stream: decoders drop or mangle frames
        data = path.read_bytes()
        start = len(data) // 3
        garbage = rng.integers(0, 256, min(len(data) // 3, 4096), dtype=np.uint8).tobytes()
        path.write_bytes(data[:start] + garbage + data[start + len(garbage):])
    elif kind == "not-a-video":
        path.write_bytes(rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
    return {"id": clip_id, "label": caption, "template": template, "placeholders": placeholders}


def split_sizes(clips: int) -> dict[str, int]:
    """About 3/4 train, 1/8 validation, 1/8 test (at least one each: `--clips` is at least 3)."""
    held_out = max(1, clips // 8)
    return {"train": clips - 2 * held_out, "validation": held_out, "test": held_out}


def make_sample_data(out: Path, clips: int, with_broken: bool = False, seed: int = 0,
                     workers: int = 1) -> dict[str, str]:
    """Write the dataset; returns the broken entries (id → kind)."""
    out = Path(out)
    annotations, videos = out / "annotations", out / "videos"
    annotations.mkdir(parents=True, exist_ok=True)
    videos.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    broken_plan = {"train": list(BROKEN_KINDS), "validation": ["missing", "too-short"], "test": []}
    sizes = split_sizes(clips)
    total = clips + (sum(len(kinds) for kinds in broken_plan.values()) if with_broken else 0)
    ids = [str(i) for i in rng.choice(np.arange(1, ID_RANGE), size=total, replace=False)]
    jobs: dict[str, list] = {}
    broken: dict[str, str] = {}
    for split, size in sizes.items():
        kinds = ["ok"] * size + (broken_plan[split] if with_broken else [])
        kinds = [kinds[i] for i in rng.permutation(len(kinds))]  # broken entries anywhere in the file
        jobs[split] = []
        for kind in kinds:
            clip_id = ids.pop()
            jobs[split].append((int(rng.integers(2**31)), clip_id, videos, kind))
            if kind != "ok":
                broken[clip_id] = kind
    everything = [job for split_jobs in jobs.values() for job in split_jobs]
    progress = dict(total=len(everything), desc="sample clips", unit="clip", disable=None)
    if workers > 1:
        # Ctrl-C is the main process's to handle (it stops the pool): a worker's own traceback was a stray
        # "Process ForkPoolWorker-2:" on the terminal
        with get_context("fork").Pool(workers, initializer=signal.signal, initargs=(signal.SIGINT, signal.SIG_IGN)) as pool:
            entries = list(tqdm(pool.imap(_make_clip, everything), **progress))
    else:
        entries = list(tqdm(map(_make_clip, everything), **progress))
    by_id = {entry["id"]: entry for entry in entries}
    for split, split_jobs in jobs.items():
        split_entries = [by_id[job[1]] for job in split_jobs]
        if split == "test":
            split_entries = [{"id": entry["id"]} for entry in split_entries]
        annotation_path(annotations, split).write_text(json.dumps(split_entries, indent=1))
    labels = {class_name(template): str(index) for index, template in enumerate(TEMPLATES)}
    annotation_path(annotations, "labels").write_text(json.dumps(labels, indent=1))
    (out / "broken.json").write_text(json.dumps(broken, indent=1, sort_keys=True))
    return broken
