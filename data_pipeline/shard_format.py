"""The on-disk shard format: how a clip's frames and metadata become tar members, and back; and the
directory's `manifest.json` (settings, per-split counts, per-shard checksums), read by `read_manifest` alone.

A shard `{split}-{NNNNNN}.tar` holds, per clip, two members named by the SSv2 id (which has no dots):

- `{id}.jpgs` (encoding `jpeg`, the default): every frame as its own JPEG (quality 90 by default, no
  chroma subsampling: 4:2:0 smears small coloured objects at 64×64, about 34 dB against 42 dB PSNR),
  packed as `uint32 N`, `N × uint32 byte length`, then the N JPEG files back to back (little endian).
  A reader decodes only the frames it samples. About 2–3 KB per 64×64 frame.
- or `{id}.npy` (encoding `raw`): the frames as one `uint8 [T, H, W, 3]` NumPy array (12.3 KB/frame).
- `{id}.json`: `id`, `caption`, `template`, `class_index` (−1 for test clips), `num_frames`,
  `source_width`, `source_height`, `fps`.

Frames are RGB. Tars are written byte-for-byte reproducibly: USTAR format, members in clip order,
mtime 0, owner 0:0 without names, mode 0444. `read_samples` reads them back as a stream, a clip at a
time, with `tarfile`'s stream mode (about 90 µs per clip; webdataset's own reader adds about 50 µs more),
and JPEG frames are decoded with simplejpeg (libjpeg-turbo; about 25 µs per 64×64 frame against about
40 µs through OpenCV, the loader's main cost at a thousand sequences per second).
"""

from __future__ import annotations

import io
import json
import tarfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np
import simplejpeg

from hauwm.json_kinds import is_count

ENCODINGS = {"jpeg": "jpgs", "raw": "npy"}  # encoding → member extension
FORMAT_VERSION = 1
MANIFEST_FILE = "manifest.json"  # a finished shard directory's index: settings, counts, per-shard checksums
ERRORS_FILE = "errors.jsonl"  # one JSON line per clip that could not be decoded (split, id, reason)
BUILD_HINT = ("build it with `hauwm shards build --annotations DIR --videos DIR --out {dir}` "
              "(or `hauwm shards sample-data` first for the built-in data)")
REBUILD_MANIFEST = ("re-run the `hauwm shards build` command that made the directory: it keeps the finished shards "
                    "and writes manifest.json and errors.jsonl again")
# the header readers of the .npy versions numpy writes, by (major, minor) version
NPY_HEADER_READERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}


class ShardDirError(ValueError):
    """Not a finished shard directory, or a damaged one; the message says how to make or mend it."""


def read_manifest(directory: str | Path) -> dict:
    """`directory/manifest.json`, checked: the directory and the file exist, and it is a manifest of this format."""
    directory = Path(directory)
    path = directory / MANIFEST_FILE
    if not directory.is_dir():
        what = "is a file, not a directory" if directory.exists() else "does not exist"
        raise ShardDirError(f"shard directory {directory} {what}; {BUILD_HINT.format(dir=directory)}")
    if not path.is_file():
        raise ShardDirError(f"{path} not found: {directory} is not a finished shard directory; "
                            f"{BUILD_HINT.format(dir=directory)} (a build in parts writes it when all parts are done)")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ShardDirError(f"{path} is damaged (not JSON: {err}); {REBUILD_MANIFEST}") from None
    missing = [key for key in ("format_version", "settings", "splits", "errors")
               if not isinstance(manifest, dict) or key not in manifest]
    if missing:
        raise ShardDirError(f"{path} is not a shard manifest (it has no {', '.join(missing)}); {REBUILD_MANIFEST}")
    if manifest["format_version"] != FORMAT_VERSION:
        raise ShardDirError(f"{path} is of shard format {manifest['format_version']!r}; this HAUWM reads format "
                            f"{FORMAT_VERSION}: build the shards again with it")
    if problem := faulty_entry(manifest):  # valid JSON, but cut short or edited: a KeyError deep in a reader
        raise ShardDirError(f"{path} is damaged ({problem}); {REBUILD_MANIFEST}")
    if not manifest["splits"]:
        raise ShardDirError(f"{path} lists no split: its build found no clip; build again with label files that list "
                            "clips (`hauwm shards build --split ...`)")
    names = [shard["name"] for split in manifest["splits"].values() for shard in split["shards"]]
    if len(set(names)) < len(names):  # written by a build given one --split twice: its clips would train twice
        raise ShardDirError(f"{path} lists shard {next(n for n in names if names.count(n) > 1)} more than once; "
                            "build the shards again, naming each --split once")
    return manifest


def file_name(value: object) -> bool:
    """A shard's file name in its directory (no path: a name with one would read a file elsewhere)."""
    return isinstance(value, str) and value.endswith(".tar") and "/" not in value and "\\" not in value


def frame_histogram(value: object) -> bool:
    """A shard's frame-count histogram: {"<frames>": clips}."""
    return isinstance(value, dict) and all(key.isdigit() and is_count(n) for key, n in value.items())


# the entries of a manifest its readers use (inspect, preview, the loader, `hauwm pretrain`), part by part, as a
# build writes them: (key, test, what the test wants)
SETTINGS_KINDS = (("size", lambda v: is_count(v) and v > 0, "a positive whole number"),
                  ("resize", lambda v: isinstance(v, str), "a string"),
                  ("encoding", lambda v: v in ENCODINGS, f"one of {', '.join(ENCODINGS)}"),
                  ("quality", is_count, "a whole number"))
SPLIT_KINDS = (*((key, is_count, "a whole number ≥ 0") for key in ("clips", "frames", "bytes", "errors")),
               ("shards", lambda v: isinstance(v, list), "a list of shards"))
SHARD_KINDS = (("name", file_name, "the file name of a .tar in the directory"),
               *((key, is_count, "a whole number ≥ 0") for key in ("clips", "frames", "bytes")),
               ("sha256", lambda v: isinstance(v, str), "a string"),
               ("frame_counts", frame_histogram, 'a mapping {"<frames>": clips}'))


def faulty_entry(manifest: dict) -> str | None:
    """The first entry a manifest lacks or holds as something else than a build writes, named by its path, e.g.
    `it has no splits.train.shards[0].sha256` or `its settings.size is null, not a positive whole number`; None when
    every entry is as a build writes it."""
    def fault(where: str, part: object, kinds: tuple) -> str | None:
        if not isinstance(part, dict):
            return f"it has no {where} (a mapping)"
        for key, test, wanted in kinds:
            if key not in part:
                return f"it has no {where}.{key}"
            if not test(part[key]):
                return f"its {where}.{key} is {json.dumps(part[key])[:40]}, not {wanted}"
        return None

    if problem := fault("settings", manifest["settings"], SETTINGS_KINDS) or fault("errors", manifest["errors"],
                                                                                   (("total", is_count, "a whole number"),)):
        return problem
    if not isinstance(manifest["splits"], dict):
        return "it has no splits (a mapping of split names)"
    for split, counts in manifest["splits"].items():
        if problem := fault(f"splits.{split}", counts, SPLIT_KINDS):
            return problem
        for i, shard in enumerate(counts["shards"]):
            if problem := fault(f"splits.{split}.shards[{i}]", shard, SHARD_KINDS):
                return problem
    return None


def encode_frames(frames: np.ndarray, encoding: str, quality: int = 90) -> bytes:
    """`uint8 [T, H, W, 3]` RGB → the bytes of the frames member."""
    if encoding == "raw":
        buffer = io.BytesIO()
        np.save(buffer, np.ascontiguousarray(frames), allow_pickle=False)
        return buffer.getvalue()
    if encoding != "jpeg":
        raise ValueError(f"unknown encoding {encoding!r}; choose from {', '.join(ENCODINGS)}")
    params = [cv2.IMWRITE_JPEG_QUALITY, quality, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
    images = []
    for frame in frames:
        ok, data = cv2.imencode(".jpg", np.ascontiguousarray(frame[:, :, ::-1]), params)
        if not ok:
            raise RuntimeError("OpenCV failed to encode a JPEG frame")
        images.append(data.tobytes())
    header = np.array([len(images), *map(len, images)], dtype="<u4").tobytes()
    return header + b"".join(images)


def decode_frames(data: bytes, extension: str, indices=None, out: np.ndarray | None = None) -> np.ndarray:
    """The frames member → `uint8 [len(indices), H, W, 3]` RGB (all frames when `indices` is None),
    written into `out` when given (the loader passes one sequence's slot of its batch array)."""
    if extension == "npy":
        frames = _npy_view(data)  # [T, H, W, 3], a view of data
        images = [frames[i] for i in (range(len(frames)) if indices is None else indices)]
    elif extension == "jpgs":
        count = int(np.frombuffer(data, dtype="<u4", count=1)[0])
        lengths = np.frombuffer(data, dtype="<u4", count=count, offset=4)
        ends = (4 * (count + 1) + np.cumsum(lengths, dtype=np.int64)).tolist()
        starts = [4 * (count + 1), *ends[:-1]]
        frames = memoryview(data)
        images = [simplejpeg.decode_jpeg(frames[starts[i]:ends[i]], colorspace="RGB")
                  for i in (range(count) if indices is None else indices)]
    else:
        raise ValueError(f"unknown frames member extension {extension!r}")
    return np.stack(images, out=out)


def _npy_view(data: bytes) -> np.ndarray:
    """An `.npy` file's bytes → its array as a read-only view of `data` (np.load would copy every frame)."""
    stream = io.BytesIO(data)
    version = np.lib.format.read_magic(stream)
    shape, fortran_order, dtype = NPY_HEADER_READERS[version](stream)
    array = np.frombuffer(data, dtype, count=int(np.prod(shape)), offset=stream.tell())
    return array.reshape(shape, order="F" if fortran_order else "C")


def add_member(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode = len(data), 0, 0o444
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    tar.addfile(info, io.BytesIO(data))


def add_clip(tar: tarfile.TarFile, metadata: dict, frames_member: bytes, extension: str) -> None:
    clip_id = metadata["id"]
    add_member(tar, f"{clip_id}.{extension}", frames_member)
    add_member(tar, f"{clip_id}.json", json.dumps(metadata, sort_keys=True).encode())


def open_writer(fileobj: BinaryIO) -> tarfile.TarFile:
    return tarfile.open(fileobj=fileobj, mode="w", format=tarfile.USTAR_FORMAT)


def frames_member(sample: dict) -> tuple[str, bytes]:
    """A clip's frames member as read_samples gives it: (its extension, `jpgs` or `npy`, and its bytes); a
    ValueError if the sample has none."""
    for extension in ENCODINGS.values():
        if extension in sample:
            return extension, sample[extension]
    raise ValueError(f"clip {sample.get('__key__')!r} has no frames member (.{' or .'.join(ENCODINGS.values())})")


class UnreadableShard(ValueError):
    """A shard that is not a tar of clips; `reason` says why, the message also what to do."""

    def __init__(self, source: str, reason: str):
        super().__init__(f"{source} is not a readable shard ({reason}); check it with `hauwm shards inspect DIR "
                         "--verify` and rebuild it")
        self.reason = reason


def read_samples(stream: BinaryIO, source: str) -> Iterator[dict]:
    """A shard's clips in order, as webdataset samples: `{"__key__": id, "json": bytes, "jpgs" | "npy": bytes}`.
    Reads the tar as a stream (tarfile's "r|" mode: no seeking, so `pipe:` sources work); `source` names the
    shard in errors (UnreadableShard)."""
    sample: dict = {}
    try:
        with tarfile.open(fileobj=stream, mode="r|") as tar:
            for member in tar:
                if not member.isfile():
                    raise UnreadableShard(source, f"member {member.name!r} is not a plain file")
                if "." not in member.name:
                    raise UnreadableShard(source, f"member {member.name!r} has no extension: not a shard of clips")
                key, extension = member.name.split(".", 1)
                if sample and key != sample["__key__"]:
                    yield sample
                    sample = {}
                sample["__key__"], sample[extension] = key, tar.extractfile(member).read()
    except tarfile.TarError as error:
        raise UnreadableShard(source, str(error)) from None
    if sample:
        yield sample
