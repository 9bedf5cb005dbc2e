"""Loader throughput: sequences/s per core at L = 16 (aim: at least 1,000), in-process and with 2 workers.

Builds shards from the built-in sample data (`--encoding jpeg` or `raw`; or uses `--shards DIR`), then
times `SequenceDataset` (tar reading, shuffle buffer, gap sampling, decoding only the L sampled frames,
collation into the batch) in the main process (torch and OpenCV limited to one thread) and through a
DataLoader with 2 workers. Reports wall-clock rates and rates per CPU second (CPU time of the process and
its workers), which stay meaningful on a machine shared with other jobs.

    python bench/bench_loader.py [--shards DIR | --encoding jpeg|raw] [--seq-len 16] [--batch-size 32]
                                 [--batches 150]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import torch  # noqa: E402

from data_pipeline.build import BuildConfig, build  # noqa: E402
from data_pipeline.loader import SequenceDataset, make_dataloader, read_manifest, shard_set  # noqa: E402
from data_pipeline.sample_data import make_sample_data  # noqa: E402


def machine() -> str:
    model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor())
    return f"{model}, {len(os.sched_getaffinity(0))} cores available, torch {torch.__version__}"


def cpu_seconds() -> float:
    """CPU time of this process and of its finished children (DataLoader workers)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def time_batches(batches) -> tuple[float, float, int]:
    """Wall seconds, CPU seconds and sequences of one pass (start-up included: workers, first shards)."""
    started, cpu_started, sequences = time.perf_counter(), cpu_seconds(), 0
    for batch in batches:
        sequences += len(batch["id"])
    return time.perf_counter() - started, cpu_seconds() - cpu_started, sequences


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shards", type=Path, default=None, help="a shard directory (default: build sample shards)")
    parser.add_argument("--encoding", choices=["jpeg", "raw"], default="jpeg", help="of the built sample shards")
    parser.add_argument("--seq-len", type=int, default=16)
    parser.add_argument("--k-max", type=int, default=5)
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--batches", type=int, default=150, help="batches to time per setting")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    shards = args.shards
    if shards is None:
        work = Path(tempfile.mkdtemp(prefix="bench-loader-"))
        make_sample_data(work / "ssv2", 64, workers=2)
        shards = work / "shards"
        build(BuildConfig(annotations=work / "ssv2" / "annotations", videos=work / "ssv2" / "videos", out=shards,
                          splits=["train"], clips_per_shard=8, encoding=args.encoding, workers=2),
              log=lambda message: None)
    print(f"machine: {machine()}, load average {os.getloadavg()[0]:.1f} at the start")
    encoding = read_manifest(shards)["settings"]["encoding"]
    print(f"settings: L={args.seq_len}, K_max={args.k_max}, batch {args.batch_size}, shuffle buffer 256, "
          f"{encoding} shards {shards}")
    for workers in (0, 2):
        dataset = SequenceDataset(shard_set(shards, "train"), batch_size=args.batch_size, seq_len=args.seq_len,
                                  k_max=args.k_max, num_workers=workers,
                                  batches_per_worker=args.batches // max(1, workers))
        seconds, cpu, sequences = time_batches(dataset if workers == 0 else make_dataloader(dataset))
        label = "main process" if workers == 0 else f"DataLoader, {workers} workers"
        print(f"{label}: {sequences / seconds:.0f} sequences/s wall, {sequences / cpu:.0f} sequences "
              f"({sequences * args.seq_len / cpu:.0f} frames) per CPU second")

if __name__ == "__main__":
    main()
