"""Loader throughput: sequences/s per core at L = 16 (aim: at least 1,000), in-process and with 2 workers,
and over many short epochs with the workers started once against workers restarted every epoch.

Builds shards from the built-in sample data (`--encoding jpeg` or `raw`; or uses `--shards DIR`), then
times `SequenceDataset` (tar reading, shuffle buffer, gap sampling, decoding only the L sampled frames,
collation into the batch) in the main process (torch and OpenCV limited to one thread) and through a
DataLoader with 2 workers, first over one long epoch, then over `--epochs` epochs of `--epoch-batches`
batches (a small dataset, or many GPUs: issue 12 had 7 steps an epoch) with `make_dataloader`'s persistent
workers and with a DataLoader that starts its workers every epoch (the loader before issue 12). Reports
wall-clock rates and rates per CPU second (CPU time of the process and its workers, counted once the
workers have exited), which stay meaningful on a machine shared with other jobs. Also what receiving one
batch from a worker costs the training process's main thread (on a GPU, the thread that pins the batches):
the hand-over (what crosses from the worker: a slot's place, data_pipeline/batch_slots.py) and the copy out of
the slot (on a GPU, the copy into pinned memory that pinning makes in any case).

    python bench/bench_loader.py [--shards DIR | --encoding jpeg|raw] [--seq-len 16] [--batch-size 32]
                                 [--batches 150] [--epochs 40] [--epoch-batches 4]
"""

from __future__ import annotations

import argparse
import atexit
import functools
import gc
import os
import resource
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import torch  # noqa: E402
from torch.utils.data import DataLoader  # noqa: E402

from bench.machine import describe_machine  # noqa: E402
from data_pipeline.build import BuildConfig, build  # noqa: E402
from data_pipeline.batch_slots import SlotBatch  # noqa: E402
from data_pipeline.dataloader import init_worker, make_dataloader  # noqa: E402
from data_pipeline.dataset import SequenceDataset, shard_set  # noqa: E402
from data_pipeline.sample_data import make_sample_data  # noqa: E402
from data_pipeline.shard_format import read_manifest  # noqa: E402


def cpu_seconds() -> float:
    """CPU time of this process and of its finished children (DataLoader workers)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def time_epochs(dataset: SequenceDataset, make_batches, epochs: int = 1) -> tuple[float, float, int]:
    """Wall seconds, CPU seconds and sequences of `epochs` passes over `make_batches(dataset)` (start-up
    included: workers, first shards; and the workers' shut-down, so that their CPU time is counted)."""
    started, cpu_started, sequences = time.perf_counter(), cpu_seconds(), 0
    batches = make_batches(dataset)
    for epoch in range(epochs):
        dataset.set_epoch(epoch)
        for batch in batches:
            sequences += len(batch["id"])
    del batches
    gc.collect()  # persistent workers exit with their loader
    return time.perf_counter() - started, cpu_seconds() - cpu_started, sequences


def restarting_workers(dataset: SequenceDataset) -> DataLoader:
    """A DataLoader that starts its workers at every epoch, as `make_dataloader` did before issue 12: also with torch's
    own hand-over of a batch (no shared-memory slots) and no pinning, as then."""
    return DataLoader(dataset, batch_size=None, num_workers=dataset.num_workers, persistent_workers=False,
                      worker_init_fn=functools.partial(init_worker, "normal", os.getpid()))


def receive_cost(dataset: SequenceDataset, batches: int) -> tuple[float, float, float]:
    """The training process's own CPU time to take one batch from a worker → median ms over `batches` of (the
    hand-over, the copy out of its slot), both its main thread's, and the mean ms of the whole process (every
    intra-op thread, one per core as in a fit: threads left spinning after a copy count too). Each `next()` comes
    after a pause long enough for a worker to have the batch ready, so the time is the hand-over, not the waiting."""
    threads = torch.get_num_threads()
    torch.set_num_threads(os.cpu_count() or 1)
    items, hand_over, copy_out = DataLoader.__iter__(make_dataloader(dataset)), [], []
    process_started = time.process_time()
    for _ in range(batches):
        time.sleep(0.1)
        started = time.thread_time()
        item = next(items)
        received = time.thread_time()
        if isinstance(item, SlotBatch):
            item.take()
        hand_over.append(received - started)
        copy_out.append(time.thread_time() - received)
    process = (time.process_time() - process_started) / batches
    torch.set_num_threads(threads)
    return 1000 * statistics.median(hand_over), 1000 * statistics.median(copy_out), 1000 * process


def report(label: str, seconds: float, cpu: float, sequences: int, seq_len: int) -> None:
    print(f"{label}: {sequences / seconds:.0f} sequences/s wall, {sequences / cpu:.0f} sequences "
          f"({sequences * seq_len / cpu:.0f} frames) per CPU second")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shards", type=Path, default=None, help="a shard directory (default: build sample shards)")
    parser.add_argument("--encoding", choices=["jpeg", "raw"], default="jpeg", help="of the built sample shards")
    parser.add_argument("--seq-len", type=int, default=16)
    parser.add_argument("--k-max", type=int, default=5)
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--batches", type=int, default=150, help="batches to time per setting")
    parser.add_argument("--epochs", type=int, default=40, help="short epochs to time with 2 workers")
    parser.add_argument("--epoch-batches", type=int, default=4, help="batches per short epoch")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    shards = args.shards
    if shards is None:
        work = Path(tempfile.mkdtemp(prefix="bench-loader-"))
        atexit.register(shutil.rmtree, work, ignore_errors=True)
        make_sample_data(work / "ssv2", 64, workers=2)
        shards = work / "shards"
        build(BuildConfig(annotations=work / "ssv2" / "annotations", videos=work / "ssv2" / "videos", out=shards,
                          splits=["train"], clips_per_shard=8, encoding=args.encoding, workers=2),
              log=lambda message: None)
    print(f"machine: {describe_machine()}")
    encoding = read_manifest(shards)["settings"]["encoding"]
    print(f"settings: L={args.seq_len}, K_max={args.k_max}, batch {args.batch_size}, shuffle buffer 256, "
          f"{encoding} shards {shards}")
    settings = dict(batch_size=args.batch_size, seq_len=args.seq_len, k_max=args.k_max)
    for workers in (0, 2):
        dataset = SequenceDataset(shard_set(shards, "train"), num_workers=workers,
                                  batches_per_worker=args.batches // max(1, workers), **settings)
        timing = time_epochs(dataset, (lambda d: d) if workers == 0 else make_dataloader)
        report("main process" if workers == 0 else f"DataLoader, {workers} workers", *timing, args.seq_len)
    dataset = SequenceDataset(shard_set(shards, "train"), num_workers=2, batches_per_worker=21, **settings)
    hand_over, copy_out, process = receive_cost(dataset, 40)
    print(f"receiving a batch from a worker: {hand_over + copy_out:.2f} ms of the main thread's CPU (median of 40: "
          f"hand-over {hand_over:.2f} ms, copy out of the slot {copy_out:.2f} ms); {process:.2f} ms of the "
          f"process's, all {os.cpu_count()} intra-op threads")
    for label, make_batches in (("workers started once", make_dataloader),
                                ("the loader before issue 12 (workers restarted every epoch, torch's hand-over)",
                                 restarting_workers)):
        dataset = SequenceDataset(shard_set(shards, "train"), num_workers=2,
                                  batches_per_worker=args.epoch_batches // 2, **settings)
        timing = time_epochs(dataset, make_batches, args.epochs)
        report(f"2 workers, {args.epochs} epochs of {args.epoch_batches} batches, {label}", *timing, args.seq_len)


if __name__ == "__main__":
    main()
