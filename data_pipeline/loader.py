"""The training loader: WebDataset shards → batches of variable-gap sequences (docs/architecture.md §2).

Per epoch, the shard list is shuffled globally with `seed + epoch`, then split by node (rank) and by
DataLoader worker (`webdataset.split_by_node`, `split_by_worker`). Each worker cycles over its shards
pass after pass and stops after exactly
`batches_per_worker` batches, computed up front from the manifest's per-shard frame counts:

    batches_per_worker = ⌊ clips with at least L frames / (world_size · workers · batch_size) ⌋

so every rank runs the same number of steps (DDP would hang otherwise) however uneven the shards.
A worker whose shards hold fewer clips than its share sees some clips twice; one with more sees some
not at all this epoch (a new shuffle next epoch). Lightning does not call `set_epoch` on an
IterableDataset: `data_pipeline.SetEpoch` (a callback) does it, before the workers are started.

The stages of one worker, a webdataset pipeline (the per-sequence cost at L = 16 is in bench/README.md):

    shard URLs → `shard_samples` (tar → samples) → shuffle buffer within the pass
      → `to_sequence` (JSON, L frame indices; too-short clips dropped) → groups of batch_size
      → `collate` (only the L sampled frames of each clip decoded, straight into the batch array)
"""

from __future__ import annotations

import json
import random
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from itertools import islice
from pathlib import Path

import numpy as np
import torch
import webdataset as wds
from torch.utils.data import DataLoader, IterableDataset
from webdataset.utils import pytorch_worker_info

from .sampling import gaps_of, sample_indices
from .shard_format import decode_frames, read_samples

MANIFEST_FILE = "manifest.json"
BUILD_HINT = ("build it with `hauwm shards build --annotations DIR --videos DIR --out {dir}` "
              "(or `hauwm shards sample-data` first for the built-in data)")


class LoaderError(ValueError):
    """A shard directory or loader setting that cannot work; the message says what to do."""


@dataclass(frozen=True)
class ShardSet:
    """The shards of one split: their URLs and, per shard, how many clips have each frame count."""
    split: str
    urls: list[str]
    frame_counts: list[dict[int, int]]

    def eligible(self, seq_len: int) -> list[int]:
        """Per shard, the number of clips with at least `seq_len` frames (the others are skipped)."""
        return [sum(n for frames, n in counts.items() if frames >= seq_len) for counts in self.frame_counts]


def read_manifest(directory: str | Path) -> dict:
    directory = Path(directory)
    path = directory / MANIFEST_FILE
    if not directory.is_dir():
        raise LoaderError(f"shard directory {directory} does not exist; {BUILD_HINT.format(dir=directory)}")
    if not path.is_file():
        raise LoaderError(f"{path} not found: {directory} is not a finished shard directory; "
                          f"{BUILD_HINT.format(dir=directory)} (a build in parts writes it when all parts are done)")
    return json.loads(path.read_text())


def shard_set(directory: str | Path, split: str, shard_url: str | None = None) -> ShardSet:
    """The shards of `split` listed in `directory/manifest.json`. `shard_url` (e.g.
    `"pipe:aws s3 cp s3://bucket/shards/{name} -"`) fetches each tar from elsewhere; default: the local file."""
    manifest = read_manifest(directory)
    if split not in manifest["splits"]:
        raise LoaderError(f"{Path(directory) / MANIFEST_FILE} has no split {split!r} (it has "
                          f"{', '.join(manifest['splits'])}); build it with `hauwm shards build ... --split {split}`")
    shards = manifest["splits"][split]["shards"]
    urls = [shard_url.format(name=s["name"]) if shard_url else str(Path(directory) / s["name"]) for s in shards]
    counts = [{int(frames): n for frames, n in s["frame_counts"].items()} for s in shards]
    return ShardSet(split, urls, counts)


def shard_samples(sources: Iterator[dict]) -> Iterator[dict]:
    """webdataset stage: `{"url": ...}` (a path or a `pipe:` command, opened by webdataset's `gopen`) → the
    shard's tar samples `{"__key__", "json", "jpgs" | "npy"}`, in clip order."""
    for source in sources:
        stream = wds.gopen(source["url"])
        yield from read_samples(stream, source["url"])
        stream.read()  # the tar's trailing zero blocks: a `pipe:` command finishes before it is closed
        stream.close()


def to_sequence(sample: dict, seq_len: int, k_max: int, rng: np.random.Generator) -> dict | None:
    """A tar sample → its sequence (the L frame indices, the facts, the still-encoded frames member);
    None for a clip shorter than L frames."""
    metadata = json.loads(sample["json"])
    indices = sample_indices(metadata["num_frames"], seq_len, k_max, rng)  # int64 [L]
    if indices is None:
        return None
    extension = "jpgs" if "jpgs" in sample else "npy"
    return {"frames_member": sample[extension], "extension": extension, "indices": indices,
            "num_frames": metadata["num_frames"], "label": metadata["class_index"], "id": metadata["id"]}


def collate(sequences: list[dict]) -> dict:
    """Sequences → the batch of docs/architecture.md §2, decoding only the L sampled frames of each clip."""
    height, width = decode_frames(sequences[0]["frames_member"], sequences[0]["extension"], [0]).shape[1:3]
    frames = torch.empty((len(sequences), len(sequences[0]["indices"]), 3, height, width), dtype=torch.uint8)
    for slot, sequence in zip(frames.numpy(), sequences):  # slot: [L, 3, H, W]
        # the decoded [L, H, W, 3] frames are written transposed straight into their slot (no second pass)
        decode_frames(sequence["frames_member"], sequence["extension"], sequence["indices"],
                      out=slot.transpose(0, 2, 3, 1))
    indices = np.stack([s["indices"] for s in sequences])  # [B, L]
    return {
        "frames": frames,  # uint8 [B, L, 3, H, W]
        "gaps": torch.from_numpy(gaps_of(indices)),  # int64 [B, L], gaps[:, 0] == 0
        "indices": torch.from_numpy(indices),  # int64 [B, L]
        "num_frames": torch.tensor([s["num_frames"] for s in sequences], dtype=torch.int64),  # [B]
        "label": torch.tensor([s["label"] for s in sequences], dtype=torch.int64),  # [B]
        "id": [s["id"] for s in sequences],
    }


class SequenceDataset(IterableDataset):
    """Batches of variable-gap sequences from one split's shards; `len()` is the batches per rank."""

    def __init__(self, shards: ShardSet, batch_size: int = 32, seq_len: int = 16, k_max: int = 5,
                 num_workers: int = 0, shuffle: bool = True, shuffle_buffer: int = 256, seed: int = 0,
                 batches_per_worker: int | None = None):
        if seq_len < 1 or k_max < 1 or batch_size < 1:
            raise LoaderError(f"seq_len, k_max and batch_size must be at least 1 "
                              f"(got {seq_len}, {k_max}, {batch_size})")
        _, world_size, _, _ = pytorch_worker_info()
        self.num_workers, self.workers = num_workers, max(1, num_workers)  # DataLoader workers; streams per rank
        eligible = shards.eligible(seq_len)
        usable = [(url, n) for url, n in zip(shards.urls, eligible) if n > 0]
        streams = world_size * self.workers
        if len(usable) < streams:
            raise LoaderError(
                f"split {shards.split!r} has {len(usable)} shards with clips of at least seq_len={seq_len} frames, "
                f"but {world_size} ranks × {self.workers} workers need at least {streams}: rebuild with a smaller "
                f"--clips-per-shard, or use fewer workers")
        clips = sum(n for _, n in usable)
        self.batches_per_worker = batches_per_worker or clips // (streams * batch_size)
        if self.batches_per_worker < 1:
            raise LoaderError(f"split {shards.split!r} has {clips} clips of at least {seq_len} frames, fewer than "
                              f"one batch of {batch_size} for each of {streams} ranks × workers; lower batch_size")
        self.urls = [url for url, _ in usable]
        self.batch_size, self.seq_len, self.k_max = batch_size, seq_len, k_max
        self.shuffle, self.shuffle_buffer, self.seed = shuffle, shuffle_buffer, seed
        self.epoch = 0
        self.skip_batches = 0  # batches of this epoch already trained on (a resumed run), per rank

    def set_epoch(self, epoch: int) -> None:
        self.epoch, self.skip_batches = epoch, 0

    def resume_at(self, epoch: int, batches: int) -> None:
        """The next iterator continues epoch `epoch` after its first `batches` batches (per rank)."""
        self.epoch, self.skip_batches = epoch, batches

    def __len__(self) -> int:
        return self.batches_per_worker * self.workers

    def stream_urls(self, worker: int) -> list[str]:
        """The shards stream `worker` of this rank reads this epoch: the list shuffled with seed + epoch (the
        same order everywhere), split by node (webdataset's `split_by_node`), then every `workers`-th shard
        from `worker` on (what `split_by_worker` does, for a stream index that need not be the process's)."""
        urls = list(self.urls)
        if self.shuffle:
            random.Random(self.seed + self.epoch).shuffle(urls)
        return list(wds.split_by_node(urls))[worker :: self.workers]

    def _passes(self, urls: list[str], rng: np.random.Generator) -> Iterator[dict]:
        """Tar samples from this stream's shards, pass after pass (the batch cap ends the epoch); each
        pass in a new shard order, shuffled through the buffer within the pass, so no clip repeats
        before every clip of the stream has come once."""
        while True:
            stages = [wds.SimpleShardList([urls[i] for i in rng.permutation(len(urls))] if self.shuffle else urls),
                      shard_samples]
            if self.shuffle and self.shuffle_buffer > 1:
                stages.append(wds.shuffle(self.shuffle_buffer, initial=self.shuffle_buffer,
                                          rng=random.Random(int(rng.integers(2**63)))))
            yield from wds.DataPipeline(*stages)

    def __iter__(self) -> Iterator[dict]:
        """This worker's batches of the epoch. A DataLoader takes batch i from worker i mod W, and after a
        resume it still asks worker 0 first: so worker p plays stream (p + skip) mod W, which skips the
        sequences its stream already gave (without decoding them), and the batches come in the same order as
        in an uninterrupted run."""
        rank, _, process_worker, _ = pytorch_worker_info()
        stream = (process_worker + self.skip_batches) % self.workers
        skipped = (self.skip_batches - stream + self.workers - 1) // self.workers  # batches this stream gave
        rng = np.random.default_rng([self.seed, self.epoch, rank, stream])
        urls = self.stream_urls(stream)
        sequences = (to_sequence(sample, self.seq_len, self.k_max, rng) for sample in self._passes(urls, rng))
        remaining = islice(filter(None, sequences), skipped * self.batch_size, None)
        batches = wds.batched(self.batch_size, collation_fn=collate, partial=False)(remaining)
        return islice(batches, max(0, self.batches_per_worker - skipped))


def _init_worker(_: int) -> None:
    import cv2

    cv2.setNumThreads(1)
    torch.set_num_threads(1)


class ResumableDataLoader(DataLoader):
    """A DataLoader that Lightning resumes inside an epoch. Lightning stores `state_dict()` in every
    checkpoint and, on resume, calls `load_state_dict()` right before it creates the resumed epoch's
    iterator (before any epoch hook could set the epoch). `batches_done` reports how many batches of the
    current epoch the training loop has consumed (the data module points it at the Trainer's progress)."""

    batches_done: Callable[[], int] = staticmethod(lambda: 0)

    def state_dict(self) -> dict:
        return {"epoch": self.dataset.epoch, "batches": int(self.batches_done())}

    def load_state_dict(self, state: dict) -> None:
        self.dataset.resume_at(state["epoch"], state["batches"])


def make_dataloader(dataset: SequenceDataset) -> ResumableDataLoader:
    """Batches come collated from the dataset, so `batch_size=None`; workers restart every epoch
    (`persistent_workers=False`) so they see the epoch `SetEpoch` set."""
    return ResumableDataLoader(dataset, batch_size=None, num_workers=dataset.num_workers,
                               worker_init_fn=_init_worker, persistent_workers=False,
                               pin_memory=torch.cuda.is_available())
