"""Shard-build throughput against a bare decode-and-resize loop over the same clips.

Prints, for the built-in sample data (`hauwm shards sample-data`): the bare loop's clips/s and frames/s
(decord, one thread, resize to 64×64, in one process), the build's clips/s and frames/s with 1 and 2
workers (decode + JPEG encode + tar writing + hashing; wall clock, and per CPU second of the workers),
its ratio to the bare loop, the peak memory of the build's main process and of its largest worker for two dataset sizes
(it should stay flat as the dataset grows), and the bytes per frame of each encoding.

    python bench/bench_shards.py [--clips 64] [--keep DIR]
"""

from __future__ import annotations

import argparse
import atexit
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import describe_machine  # noqa: E402
from hauwm.arguments import at_least  # noqa: E402
from data_pipeline.decode import decode_clip  # noqa: E402
from data_pipeline.sample_data import make_sample_data  # noqa: E402
from data_pipeline.ssv2 import load_split  # noqa: E402

MEASURE_BUILD = """
import json, resource, sys, time
from pathlib import Path
from data_pipeline.build import BuildConfig, build
args = json.loads(sys.argv[1])
config = BuildConfig(annotations=Path(args["annotations"]), videos=Path(args["videos"]), out=Path(args["out"]),
                     splits=["train"], workers=args["workers"], max_clips=args["max_clips"], encoding=args["encoding"],
                     clips_per_shard=16, max_error_rate=1.0)
started = time.perf_counter()
manifest, _ = build(config, log=lambda message: None)
elapsed = time.perf_counter() - started
split = manifest["splits"]["train"]
own, workers = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"seconds": elapsed, "clips": split["clips"], "frames": split["frames"], "bytes": split["bytes"],
                  "main_cpu": own.ru_utime + own.ru_stime, "worker_cpu": workers.ru_utime + workers.ru_stime,
                  "main_rss_mb": own.ru_maxrss / 1024, "worker_rss_mb": workers.ru_maxrss / 1024}))
"""


def run_build(data: Path, out: Path, workers: int, max_clips: int | None, encoding: str = "jpeg") -> dict:
    shutil.rmtree(out, ignore_errors=True)  # a fresh build, not a resume
    args = {"annotations": str(data / "annotations"), "videos": str(data / "videos"), "out": str(out),
            "workers": workers, "max_clips": max_clips, "encoding": encoding}
    result = subprocess.run([sys.executable, "-c", MEASURE_BUILD, json.dumps(args)], capture_output=True, text=True,
                            cwd=ROOT, check=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def bare_loop(data: Path) -> tuple[float, float, int, int]:
    """Wall and CPU seconds, clips and frames of decoding and resizing every train clip in this process."""
    records = load_split(data / "annotations", "train")
    started, cpu_started, frames = time.perf_counter(), time.process_time(), 0
    for record in records:
        frames += len(decode_clip(data / "videos" / f"{record.id}.webm", 64).frames)
    return time.perf_counter() - started, time.process_time() - cpu_started, len(records), frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=at_least(8), default=64,
                        help="sample clips to generate (3/4 go to train; a quarter of those is the smaller build)")
    parser.add_argument("--keep", type=Path, default=None, help="keep the sample data and shards here")
    args = parser.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="bench-shards-"))
    if args.keep is None:
        atexit.register(shutil.rmtree, work, ignore_errors=True)
    data = work / "ssv2"
    if not (data / "annotations").is_dir():
        make_sample_data(data, args.clips, workers=2)
    print(f"machine: {describe_machine()}")
    print(f"settings: --clips {args.clips} of the built-in sample data; builds at the build's defaults (64×64, "
          "squash, JPEG) with --workers 1 and 2, and with raw frames", flush=True)
    seconds, cpu, clips, frames = bare_loop(data)
    bare_fps = frames / cpu
    print(f"data: {clips} train clips, {frames} frames (sample data, 240 px high VP9, 24–60 frames per clip)")
    print(f"bare decode+resize loop (1 process): {frames / seconds:.0f} frames/s wall, "
          f"{bare_fps:.0f} frames per CPU second")
    for workers in (1, 2):
        result = run_build(data, work / f"shards-w{workers}", workers, None)
        per_worker = result["frames"] / result["worker_cpu"]
        print(f"build --workers {workers}: {result['clips'] / result['seconds']:.1f} clips/s and "
              f"{result['frames'] / result['seconds']:.0f} frames/s wall; per worker "
              f"{result['clips'] / result['worker_cpu']:.1f} clips and {per_worker:.0f} frames per CPU second "
              f"({per_worker / bare_fps:.0%} of the bare loop); main process {result['main_cpu']:.1f} CPU s")
    for max_clips in (clips // 4, clips):
        result = run_build(data, work / f"shards-mem-{max_clips}", 1, max_clips)
        print(f"peak memory, {max_clips} clips: main process {result['main_rss_mb']:.0f} MB, "
              f"largest worker {result['worker_rss_mb']:.0f} MB")
    for encoding in ("jpeg", "raw"):
        result = run_build(data, work / f"shards-{encoding}", 1, None, encoding)
        print(f"--encoding {encoding}: {result['bytes'] / result['frames']:.0f} bytes per 64×64 frame "
              "(tar overhead included)")


if __name__ == "__main__":
    main()
