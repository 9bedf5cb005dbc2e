"""The training data as a torch IterableDataset: WebDataset shards → batches of variable-gap sequences
(docs/architecture.md §2). `dataloader.py` runs it in DataLoader workers; `datamodule.py` hands both to Lightning.

Per epoch, the shard list is shuffled globally with `seed + epoch`, then split by rank (as `webdataset.split_by_node`
does, with the rank of the process that made the dataset: a worker may have no process group) and by DataLoader
worker (every `workers`-th shard: `SequenceDataset.stream_urls`). Each worker cycles over its shards pass after pass
and stops after exactly `batches_per_worker` batches, computed up front from the manifest's per-shard frame counts:

    batches_per_worker = ⌊ clips with at least L frames / (world_size · workers · batch_size) ⌋

so every rank runs the same number of steps (DDP would hang otherwise) however uneven the shards.
A worker whose shards hold fewer clips than its share sees some clips twice; one with more sees some
not at all this epoch (a new shuffle next epoch).

The data position — the epoch and the batches of it already trained on — lives in a shared-memory tensor that
the dataset creates before any worker starts. The main process writes it: `set_epoch` (the `SetEpoch` callback
calls it; Lightning does not call `set_epoch` on an IterableDataset) and `resume_at` (from
`ResumableDataLoader.load_state_dict`). Every `__iter__` reads it, in the main process or in a worker (how the
workers, started once, follow it: `dataloader.py`); a worker of a stream that a ResumableDataLoader began reads the
copy `begin_stream` made as the stream began, since it may start after the position moved on. The training set is
`continuous`: its workers' iterators go on into the next epoch by themselves.

An exception inside a worker (an unreadable shard, frames that do not decode) becomes a `LoaderError` naming
the worker and the shard it was reading (each worker notes it in a second shared tensor), handed to the main
process as the worker's last item.

The stages of one worker (the per-sequence cost at L = 16 is in bench/README.md):

    shard URLs → `shard_samples` (tar → samples) → shuffle buffer within the pass
      → `to_sequence` (JSON, L frame indices; too-short clips dropped) → groups of batch_size
      → `collate` (only the L sampled frames of each clip decoded, straight into the batch array, which in a
        DataLoader worker is its next shared-memory slot: batch_slots.py)
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import random
import string
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from itertools import islice
from multiprocessing.context import BaseContext
from pathlib import Path

import numpy as np
import torch
import webdataset as wds
from torch.utils.data import IterableDataset, get_worker_info
from webdataset.gopen import Pipe
from webdataset.utils import pytorch_worker_info

from .batch_slots import BatchSlots, SlotBatch, batch_views, block_bytes, shared_memory_free
from .sampling import gaps_of, sample_indices
from .shard_format import MANIFEST_FILE, UnreadableShard, decode_frames, frames_member, read_manifest, read_samples
from .ssv2 import SPLITS

VERIFY_HINT = "check the shards with `hauwm shards inspect DIR --verify` and rebuild the broken one"


class LoaderError(ValueError):
    """A shard directory, loader setting or loader worker that cannot work; the message says what to do."""


# what a worker hands over: a batch (a dict, or a SlotBatch naming its frames in shared memory), or its last item, the
# error that ended it
WorkerItem = dict | SlotBatch | LoaderError


@dataclass(frozen=True)
class ShardSet:
    """The shards of one split: their URLs and, per shard, how many clips have each frame count; their frames'
    height and width (the build's --size); their sha256s as the manifest lists them (what they hold, wherever they are)."""
    split: str
    urls: list[str]
    frame_counts: list[dict[int, int]]
    frame_size: int = 64
    checksums: tuple[str, ...] = ()

    def eligible(self, seq_len: int) -> list[int]:
        """Per shard, the number of clips with at least `seq_len` frames (the others are skipped)."""
        return [sum(n for frames, n in counts.items() if frames >= seq_len) for counts in self.frame_counts]

    def clip_lengths(self) -> dict[int, int]:
        """{frame count T: clips} over every shard of the split."""
        return dict(sum((Counter(counts) for counts in self.frame_counts), Counter()))

    def median_frames(self, seq_len: int) -> float | None:
        """The median frame count T of the clips with at least `seq_len` frames (None if there are none): the
        typical T of the relative temporal embedding's k / T, which fine-tuning's k = 1 embedding takes."""
        lengths = [(frames, n) for counts in self.frame_counts for frames, n in counts.items() if frames >= seq_len]
        if not lengths:
            return None
        frames, clips = np.array(lengths).T
        return float(np.median(np.repeat(frames, clips)))


def check_shard_url(template: str | None) -> None:
    """A `shard_url` names each tar through `{name}` and nothing else: without it every shard would be one tar (the
    validation split too), and another field would fail at the first shard."""
    if template is None:
        return
    try:
        fields = {field for _, field, _, _ in string.Formatter().parse(template) if field is not None}
    except ValueError as err:  # an unmatched brace
        raise LoaderError(f"--data.shard_url {template!r}: {err}; write {{name}} where each tar's file name goes, and "
                          "double any other brace ({{ }})") from None
    if fields != {"name"}:
        other = sorted(fields - {"name"})
        raise LoaderError(f"--data.shard_url {template!r} must name each tar through {{name}} (e.g. "
                          f"'pipe:aws s3 cp s3://bucket/shards/{{name}} -')" +
                          (f", and no other field ({{{other[0]}}})" if other else "; without it every shard would be "
                           "the same tar"))


def shard_set(directory: str | Path, split: str, shard_url: str | None = None) -> ShardSet:
    """The shards of `split` listed in `directory/manifest.json`. `shard_url` (e.g.
    `"pipe:aws s3 cp s3://bucket/shards/{name} -"`) fetches each tar from elsewhere; default: the local file."""
    manifest = read_manifest(directory)
    if split not in manifest["splits"]:
        remedy = f"build it with `hauwm shards build ... --split {split}`" if split in SPLITS else "name one of those"
        raise LoaderError(f"{Path(directory) / MANIFEST_FILE} has no split {split!r} (it has "
                          f"{', '.join(manifest['splits'])}); {remedy}")
    shards = manifest["splits"][split]["shards"]
    urls = [shard_url.format(name=s["name"]) if shard_url else str(Path(directory) / s["name"]) for s in shards]
    if not shard_url and (missing := [url for url in urls if not Path(url).is_file()]):  # met by a worker, mid-epoch
        raise LoaderError(f"{len(missing)} of the {len(urls)} {split} shards listed in "
                          f"{Path(directory) / MANIFEST_FILE} are missing, e.g. {missing[0]}: copy them back, or "
                          f"{VERIFY_HINT}")
    # a stat per shard, not a checksum (`inspect --verify`); a tar's size steps by 10 KiB, so a shard of other clips
    # may still pass, to be found by the worker that reads it (`SequenceDataset._passes`)
    sizes = [] if shard_url else [(url, Path(url).stat().st_size, s["bytes"]) for url, s in zip(urls, shards)]
    if other := [(url, size, listed) for url, size, listed in sizes if size != listed]:
        url, size, listed = other[0]
        raise LoaderError(f"{len(other)} of the {len(urls)} {split} shards listed in {Path(directory) / MANIFEST_FILE} "
                          f"are not the files it lists, e.g. {url}: {size} bytes, listed as {listed} (a partial copy, "
                          f"or another shard in its place); {VERIFY_HINT}")
    counts = [{int(frames): n for frames, n in s["frame_counts"].items()} for s in shards]
    return ShardSet(split, urls, counts, manifest["settings"]["size"],  # the size: the workers' batch slots'
                    tuple(s["sha256"] for s in shards))


def shard_samples(sources: Iterator[dict]) -> Iterator[dict]:
    """webdataset stage: `{"url": ...}` (a path or a `pipe:` command, opened by webdataset's `gopen`) → the
    shard's tar samples `{"__key__", "__url__", "json", "jpgs" | "npy"}`, in clip order."""
    for source in sources:
        stream = wds.gopen(source["url"])
        try:
            for sample in read_samples(stream, source["url"]):
                sample["__url__"] = source["url"]
                yield sample
            stream.read()  # the tar's trailing zero blocks: a `pipe:` command finishes before it is closed
        except BaseException:  # cut off (an epoch that ends inside the shard, an error): not waited for
            if isinstance(stream, Pipe):  # (webdataset's close waits for the command to end by itself)
                stream.stream.close()  # the command gets SIGPIPE at its next write (and the close at collection is
                stream.proc.kill()  # a no-op); its shell (`sh -c`), which may have forked it, ends now
                stream.proc.wait()
            else:
                stream.close()
            raise
        stream.close()  # a `pipe:` command's: waited for, and a failure (its exit status) raised


def to_sequence(sample: dict, seq_len: int, k_max: int, rng: np.random.Generator) -> dict | None:
    """A tar sample → its sequence (the L frame indices, the facts, the still-encoded frames member);
    None for a clip shorter than L frames."""
    try:
        metadata = json.loads(sample["json"])
        num_frames, label, clip_id = metadata["num_frames"], metadata["class_index"], metadata["id"]
        extension, member = frames_member(sample)
    except (KeyError, TypeError, ValueError) as error:
        raise LoaderError(f"clip {sample['__key__']} of shard {sample['__url__']}: not a HAUWM clip "
                          f"({type(error).__name__}: {error}); {VERIFY_HINT}") from None
    indices = sample_indices(num_frames, seq_len, k_max, rng)  # int64 [L]
    if indices is None:
        return None
    return {"frames_member": member, "extension": extension, "indices": indices,
            "num_frames": num_frames, "label": label, "id": clip_id, "url": sample["__url__"]}


def decode_sequence(sequence: dict, indices, out: np.ndarray | None = None) -> np.ndarray:
    """`decode_frames` for one sequence's frames member; frames that do not decode name the clip and its shard."""
    try:
        return decode_frames(sequence["frames_member"], sequence["extension"], indices, out=out)
    except Exception as error:
        raise LoaderError(f"clip {sequence['id']} of shard {sequence['url']}: its frames do not decode "
                          f"({type(error).__name__}: {error}); {VERIFY_HINT}") from error


def collate(sequences: list[dict], block: torch.Tensor | None = None) -> dict:
    """Sequences → the batch of docs/architecture.md §2, decoding only the L sampled frames of each clip, into
    `block` (uint8; a new one if None or too small): every tensor is a view of one block (batch_slots.py)."""
    height, width = decode_sequence(sequences[0], [0]).shape[1:3]
    shape = len(sequences), len(sequences[0]["indices"]), height, width
    _, size = block_bytes(*shape)
    if block is None or len(block) < size:
        block = torch.empty(size, dtype=torch.uint8)
    batch = batch_views(block, *shape)
    for slot, sequence in zip(batch["frames"].numpy(), sequences):  # slot: [L, 3, H, W]
        # the decoded [L, H, W, 3] frames are written transposed straight into their slot (no second pass)
        decode_sequence(sequence, sequence["indices"], out=slot.transpose(0, 2, 3, 1))
    indices = np.stack([s["indices"] for s in sequences])  # [B, L]
    batch["gaps"][:], batch["indices"][:] = torch.from_numpy(gaps_of(indices)), torch.from_numpy(indices)
    batch["num_frames"][:] = torch.tensor([s["num_frames"] for s in sequences])
    batch["label"][:] = torch.tensor([s["label"] for s in sequences])
    return {**batch, "id": [s["id"] for s in sequences]}  # frames uint8 [B, L, 3, H, W]; the rest int64


def usable_shards(shards: ShardSet, seq_len: int, world_size: int, workers: int) -> dict[str, int]:
    """url -> its clips of at least `seq_len` frames (as the manifest counts them), for each shard that holds any; a
    LoaderError when there is none, or fewer than the world_size · workers streams need (one shard each)."""
    usable = {url: n for url, n in zip(shards.urls, shards.eligible(seq_len)) if n > 0}
    streams = world_size * workers
    if not usable and not any(shards.frame_counts):  # every clip of the split failed to build, or it lists none
        raise LoaderError(f"split {shards.split!r} holds no clips (`hauwm shards inspect` shows why its clips failed "
                          "to build; `hauwm shards build --retry-failed` rebuilds those a missing or slow video "
                          "kept out)")
    if not usable:
        longest = max((frames for counts in shards.frame_counts for frames in counts), default=0)
        raise LoaderError(f"split {shards.split!r} has no clip of at least seq_len={seq_len} frames (the longest "
                          f"has {longest}): lower seq_len (--data.seq_len of a fit, --seq-len of analyze)")
    if len(usable) < streams:
        fewer = (["fewer workers (--data.num_workers)"] if workers > 1 else []) + (
            ["fewer devices (--trainer.devices)"] if world_size > 1 else [])
        raise LoaderError(
            f"split {shards.split!r} has {len(usable)} shards with clips of at least seq_len={seq_len} frames, "
            f"but {world_size} ranks × {workers} workers need at least {streams} (one each): rebuild with a "
            f"smaller --clips-per-shard" + "".join(f", or use {way}" for way in fewer))
    return usable


class SequenceDataset(IterableDataset):
    """Batches of variable-gap sequences from one split's shards; `len()` is the batches per rank."""

    def __init__(self, shards: ShardSet, batch_size: int = 32, seq_len: int = 16, k_max: int = 5,
                 num_workers: int = 0, shuffle: bool = True, shuffle_buffer: int = 256, seed: int = 0,
                 batches_per_worker: int | None = None, continuous: bool = False):
        """`continuous`: an iterator goes on from epoch to epoch by itself (training: the workers run into the next
        epoch while the last batches of this one train; `ResumableDataLoader` hands out one epoch per `iter()`);
        otherwise an iterator is one epoch (validation: the same batches at every evaluation)."""
        if seq_len < 1 or k_max < 1 or batch_size < 1:
            raise LoaderError(f"seq_len, k_max and batch_size must be at least 1 "
                              f"(got {seq_len}, {k_max}, {batch_size})")
        # this process's rank, kept for the DataLoader workers: one started by forkserver or spawn (Python 3.14's
        # default on Linux) has no process group, and Lightning sets no RANK, so it would read as rank 0 of 1
        self.rank, self.world_size, _, _ = pytorch_worker_info()
        self.num_workers, self.workers = num_workers, max(1, num_workers)  # DataLoader workers; streams per rank
        self.streams = self.world_size * self.workers  # what a resume position means depends on it
        self.clips_in = usable_shards(shards, seq_len, self.world_size, self.workers)  # url -> clips of ≥ seq_len frames
        self.urls = list(self.clips_in)
        # what the shards read hold, wherever they are: a resume from moved shards is exact, from others it is not
        self.content_id = hashlib.sha256(" ".join(checksum for url, checksum in zip(shards.urls, shards.checksums)
                                                  if url in self.clips_in).encode()).hexdigest()[:16]
        clips = sum(self.clips_in.values())
        self.batches_per_worker = batches_per_worker or clips // (self.streams * batch_size)
        if self.batches_per_worker < 1:
            raise LoaderError(f"split {shards.split!r} has {clips} clips of at least {seq_len} frames, fewer than one "
                              f"batch of {batch_size} for each of {self.streams} ranks × workers; lower "
                              "--data.batch_size")
        self.batch_size, self.seq_len, self.k_max = batch_size, seq_len, k_max
        self.shuffle, self.shuffle_buffer, self.seed, self.continuous = shuffle, shuffle_buffer, seed, continuous
        self.split = shards.split  # for error messages: a fit reads train and validation shards
        self.frame_size = shards.frame_size
        self._slots: BatchSlots | None = None  # where workers place their batches (share_slots)
        # shared with the DataLoader workers (created before they start): [epoch, batches of it already trained
        # on per rank (a resumed run)], written by the main process; and the position the workers' iterators start
        # from, copied from it by `begin_stream` as a ResumableDataLoader starts them (they may start after the
        # position moved on; −1: no stream begun, as under a plain DataLoader, whose workers read the position)
        self._position = torch.zeros(2, dtype=torch.int64).share_memory_()
        self._stream_start = torch.full((2,), -1, dtype=torch.int64).share_memory_()
        # per worker, the index in `urls` of the shard it is reading (-1: none yet), for error messages
        self._reading = torch.full((self.workers,), -1, dtype=torch.int64).share_memory_()

    @property
    def epoch(self) -> int:
        return int(self._position[0])

    @property
    def skip_batches(self) -> int:
        return int(self._position[1])

    def set_epoch(self, epoch: int) -> None:
        self.resume_at(epoch, 0)

    def resume_at(self, epoch: int, batches: int) -> None:
        """The next iterator continues epoch `epoch` after its first `batches` batches (per rank)."""
        self._position[0], self._position[1] = epoch, batches

    def begin_stream(self) -> None:
        """The workers' next iterators start from the position as it is now: a worker that starts after the
        position moved on (the first start of persistent workers is not waited for; a resumed epoch can end before
        a late worker has read the position, and SetEpoch then moves it to the next epoch) still plays its part of
        this stream."""
        self._stream_start.copy_(self._position)

    def reading(self, worker: int) -> str:
        """The shard worker `worker` of this rank is reading (or read last)."""
        index = int(self._reading[worker])
        return self.urls[index] if index >= 0 else "(none yet)"

    def __len__(self) -> int:
        return self.batches_per_worker * self.workers

    def stream_urls(self, stream: int, epoch: int | None = None) -> list[str]:
        """The shards stream `stream` of this rank reads in `epoch` (default: this one): the list shuffled with
        seed + epoch (the same order everywhere), every world_size-th from the rank on (webdataset's
        `split_by_node`, with the rank of the process that made the dataset), then every `workers`-th shard from
        `stream` on (what `split_by_worker` does, for a stream index that need not be the process's)."""
        urls = list(self.urls)
        if self.shuffle:
            random.Random(self.seed + (self.epoch if epoch is None else epoch)).shuffle(urls)
        return urls[self.rank :: self.world_size][stream :: self.workers]

    def _sources(self, urls: list[str], worker: int) -> Iterator[dict]:
        """webdataset shard sources `{"url"}`, noting in shared memory which shard `worker` opens."""
        for url in urls:
            self._reading[worker] = self.urls.index(url)
            yield {"url": url}

    def _passes(self, urls: list[str], rng: np.random.Generator, worker: int) -> Iterator[dict]:
        """Sequences from this stream's shards, pass after pass (the batch cap ends the epoch); each pass in a
        new shard order, shuffled through the buffer within the pass, so no clip repeats before every clip of
        the stream has come once. A pass that gives fewer sequences than the manifest promises for these shards
        is an error (they are not the shards it describes); without it, a stream of shards that give none would
        spin forever; one that gives more is another shard in its place (whose size `shard_set` could not tell).
        """
        while True:
            order = [urls[i] for i in rng.permutation(len(urls))] if self.shuffle else urls
            samples = shard_samples(self._sources(order, worker))
            if self.shuffle and self.shuffle_buffer > 1:
                samples = wds.shuffle(self.shuffle_buffer, initial=self.shuffle_buffer,
                                      rng=random.Random(int(rng.integers(2**63))))(samples)
            given: Counter[str] = Counter()  # url -> sequences it gave in this pass
            for sequence in filter(None, (to_sequence(sample, self.seq_len, self.k_max, rng) for sample in samples)):
                given[sequence["url"]] += 1
                yield sequence
            differing = [f"{url} gave {given[url]} where the manifest counts {self.clips_in[url]}"
                         for url in urls if given[url] != self.clips_in[url]]
            if differing:
                raise LoaderError(f"shards are not the ones manifest.json describes (replaced, truncated or copied from "
                                  f"another build); clips of at least seq_len={self.seq_len} frames: "
                                  f"{'; '.join(differing)}; {VERIFY_HINT}")

    def __iter__(self) -> Iterator[WorkerItem]:
        """This worker's batches of the epoch (and, `continuous`, of the epochs after it). A DataLoader takes
        batch i from worker i mod W, and after a resume it still asks worker 0 first: so worker p plays stream
        (p + skip) mod W, which skips the sequences its stream already gave (without decoding them), and the
        batches come in the same order as in an uninterrupted run. An epoch holds W · batches_per_worker
        batches, so in the epochs after, worker p is asked right after the stream before its own again: it
        keeps playing stream (p + skip) mod W, from the epoch's first batch."""
        _, _, process_worker, _ = pytorch_worker_info()
        begun = get_worker_info() is not None and int(self._stream_start[0]) >= 0  # a worker of a begun stream
        position = self._stream_start if begun else self._position
        first_epoch, skip = int(position[0]), int(position[1])
        stream = (process_worker + skip) % self.workers
        # batches this stream gave before the resume: of batches 0..skip−1, those i with i mod W == stream
        skipped = (skip - stream + self.workers - 1) // self.workers
        epochs = itertools.count(first_epoch) if self.continuous else [first_epoch]
        batches = (batch for epoch in epochs for batch in self._epoch_batches(
            epoch, stream, skipped if epoch == first_epoch else 0, process_worker))
        return self._naming_the_shard(batches, process_worker)

    def _epoch_batches(self, epoch: int, stream: int, skipped: int, worker: int) -> Iterator[dict | SlotBatch]:
        """Stream `stream`'s batches of `epoch`, after the first `skipped`, read by DataLoader worker `worker`."""
        rng = np.random.default_rng([self.seed, epoch, self.rank, stream])
        urls = self.stream_urls(stream, epoch)
        remaining = islice(self._passes(urls, rng, worker), skipped * self.batch_size, None)
        groups = wds.batched(self.batch_size, collation_fn=None, partial=False)(remaining)
        return map(self._handed_over, islice(groups, max(0, self.batches_per_worker - skipped)))

    def share_slots(self, per_worker: int, context: BaseContext) -> BatchSlots:
        """Give each DataLoader worker that starts next (with `context`) `per_worker` shared-memory slots to place
        its batches in (batch_slots.py); new ones for every loader, since batches that the workers of an earlier
        loader placed and nobody received (it ended with batches in flight) keep their slots taken. -> the slots, which
        the loader keeps alive in this process for its batches to be copied out. A LoaderError if the shared memory
        has no room for them."""
        _, slot_bytes = block_bytes(self.batch_size, self.seq_len, self.frame_size, self.frame_size)
        needed, room = self.workers * per_worker * slot_bytes, shared_memory_free()
        if room is not None and needed > room:
            raise LoaderError(f"the {self.split} loader's {self.workers} workers need {needed / 2**20:.0f} MiB of "
                              f"shared memory to hand batches over and /dev/shm has {room / 2**20:.0f} MiB free: in "
                              "Docker run with --shm-size 8g (or --ipc=host), or lower --data.num_workers or "
                              "--data.batch_size")
        self._slots = BatchSlots(self.workers, per_worker, slot_bytes, context)
        return self._slots

    def _handed_over(self, sequences: list[dict]) -> dict | SlotBatch:
        """In a DataLoader worker with slots, the batch written into the worker's next slot, to travel as a
        SlotBatch; otherwise (no slot free, a batch larger than a slot, the main process) the batch itself."""
        info = get_worker_info()
        if self._slots is None or info is None or (place := self._slots.place(info.id)) is None:
            return collate(sequences)
        slot, block = place
        try:
            batch = collate(sequences, block)
        except BaseException:
            self._slots.vacate(info.id, slot)
            raise
        if batch["frames"].data_ptr() != block.data_ptr():  # larger than the slot: collated elsewhere
            self._slots.vacate(info.id, slot)
            return batch
        size, length, _, height, width = batch["frames"].shape
        return SlotBatch(self._slots.key, info.id, slot, (size, length, height, width), batch["id"])

    def _naming_the_shard(self, batches: Iterator[dict | SlotBatch], worker: int) -> Iterator[WorkerItem]:
        """`batches`, with an error turned into a `LoaderError` naming the worker and the shard it was reading.
        A DataLoader worker hands it over as its last item, which `ResumableDataLoader` raises (torch would
        re-raise the exception with the worker's traceback pasted into its message); the main process raises it."""
        try:
            yield from batches
        except Exception as error:
            info = get_worker_info()
            who = "the loader" if info is None else f"DataLoader worker {info.id} ({self.split} split, pid {os.getpid()})"
            cause = error if isinstance(error, (LoaderError, UnreadableShard)) else f"{type(error).__name__}: {error}"
            failure = LoaderError(f"{who}, reading shard {self.reading(worker)}: {cause}")
            if info is None:
                raise failure from error
            yield failure
