"""`hauwm shards {build,inspect,preview,sample-data}`: the data pipeline's command line."""

from __future__ import annotations

import argparse
import shutil
import sys

from hauwm.arguments import at_least, path
from hauwm.termination import interrupted_once, sigterm_as_interrupt, stopped_by

from .decode import RESIZE_MODES
from .shard_format import ENCODINGS, MANIFEST_FILE
from .ssv2 import SPLITS, AnnotationError


MAX_SAMPLE_CLIPS = 200_000  # sample-data: its ids come from 1..219,999 (sample_data.ID_RANGE), the broken ones too


def _build(args: argparse.Namespace) -> int:
    from .build import BuildConfig, BuildError, build

    config = BuildConfig(
        annotations=args.annotations, videos=args.videos, out=args.out, splits=args.split or ["train", "validation"],
        size=args.size, resize=args.resize, encoding=args.encoding, quality=args.quality,
        clips_per_shard=args.clips_per_shard, min_frames=args.min_frames, max_clips=args.max_clips,
        workers=args.workers, part=args.part, num_parts=args.num_parts, max_error_rate=args.max_error_rate,
        timeout=args.timeout, retry_failed=args.retry_failed)
    try:
        _, status = build(config)
    except (BuildError, AnnotationError) as error:
        print(f"hauwm shards build: {error}", file=sys.stderr)
        return 2
    return status


def _inspect(args: argparse.Namespace) -> int:
    from .inspect_shards import inspect_shards
    from .shard_format import ShardDirError

    try:
        return inspect_shards(args.dir, verify=args.verify)
    except ShardDirError as error:
        print(f"hauwm shards inspect: {error}", file=sys.stderr)
        return 2


def _preview(args: argparse.Namespace) -> int:
    from .shard_format import ShardDirError
    from .preview import write_preview

    try:
        write_preview(args.dir, args.out, split=args.split, clips=args.clips, length=args.length,
                      k_max=args.k_max, seed=args.seed)
    except ShardDirError as error:
        print(f"hauwm shards preview: {error}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


def _sample_data(args: argparse.Namespace) -> int:
    from .sample_data import make_sample_data

    taken = [f"{entry.name}/" if entry.is_dir() else entry.name
             for entry in (args.out / "annotations", args.out / "videos", args.out / "broken.json")
             if entry.is_file() or (entry.is_dir() and any(entry.iterdir()))]
    if taken:  # a dataset of its own, or an earlier sample: its annotations would be replaced, its videos orphaned
        print(f"hauwm shards sample-data: {args.out} already holds a dataset ({', '.join(taken)}): "
              "pass another --out, or delete it first", file=sys.stderr)
        return 2
    if (args.out / MANIFEST_FILE).exists():
        print(f"hauwm shards sample-data: {args.out} is a shard directory ({MANIFEST_FILE}): pass another --out",
              file=sys.stderr)
        return 2
    existed = {entry: entry.exists() for entry in (args.out, args.out / "annotations", args.out / "videos")}
    try:
        broken = make_sample_data(args.out, args.clips, with_broken=args.with_broken, seed=args.seed,
                                  workers=args.workers)
    except BaseException:  # Ctrl-C, SIGTERM, a full disk: what it wrote goes, so that the same command can start again
        for entry in (args.out / "annotations", args.out / "videos"):  # empty or absent before (checked above)
            shutil.rmtree(entry, ignore_errors=True)
            if existed[entry]:
                entry.mkdir()
        (args.out / "broken.json").unlink(missing_ok=True)
        if not existed[args.out]:
            shutil.rmtree(args.out, ignore_errors=True)
        raise
    print(f"wrote {args.clips} clips" + (f" and {len(broken)} broken entries" if broken else "") +
          f" to {args.out} (annotations/ and videos/)")
    return 0


def parser() -> argparse.ArgumentParser:
    root = argparse.ArgumentParser(allow_abbrev=False,
                                   prog="hauwm shards", description="SSv2 → WebDataset shards, and tools for them.")
    commands = root.add_subparsers(dest="command", required=True)

    build = commands.add_parser("build", allow_abbrev=False,
                                help="decode an SSv2 tree into 64×64 WebDataset shards (resumable)")
    flag = build.add_argument
    flag("--annotations", metavar="DIR", type=path, required=True, help="directory with something-something-v2-*.json")
    flag("--videos", metavar="DIR", type=path, required=True, help="directory with <id>.webm")
    flag("--split", action="append", choices=SPLITS, help="split to build; repeatable (default: train and validation)")
    flag("--out", metavar="DIR", type=path, required=True, help="output directory for shards, manifest, errors")
    flag("--size", metavar="N", type=int, default=64, help="frame side in pixels, at most 512 (default 64)")
    flag("--resize", choices=RESIZE_MODES, default="squash",
         help="squash the whole frame to a square, or crop the centre square first (default squash)")
    flag("--encoding", choices=list(ENCODINGS), default="jpeg",
         help="frames as per-frame JPEGs (default) or one raw uint8 array per clip")
    flag("--quality", metavar="Q", type=int, default=90, help="JPEG quality for --encoding jpeg (default 90)")
    flag("--clips-per-shard", metavar="N", type=int, default=256, help="label-file entries per shard (default 256)")
    flag("--min-frames", metavar="N", type=int, default=8, help="clips with fewer frames are errors (default 8)")
    flag("--max-clips", metavar="N", type=int, default=None, help="use only the first N entries of each split")
    flag("--workers", metavar="N", type=int, default=1, help="decoder processes (default 1)")
    flag("--part", metavar="I", type=int, default=0, help="build only part I of the shards (0-based)")
    flag("--num-parts", metavar="N", type=int, default=1, help="number of parts the shards are split into")
    flag("--max-error-rate", metavar="F", type=float, default=0.01,
         help="exit non-zero when more than this fraction of clips fail (default 0.01)")
    flag("--timeout", metavar="S", type=float, default=30.0, help="seconds one clip may take to decode (default 30)")
    flag("--retry-failed", action="store_true",
         help="rebuild the shards holding clips that failed as missing, unreadable, timed out or crashed (e.g. once the "
              "missing videos are there); other failures are facts of the files and stay")
    build.set_defaults(run=_build)

    inspect = commands.add_parser("inspect", allow_abbrev=False,
                                  help="counts per split, frames, bytes, errors by reason")
    inspect.add_argument("dir", type=path, help="shard directory (with manifest.json)")
    inspect.add_argument("--verify", action="store_true", help="re-check every shard against the manifest")
    inspect.set_defaults(run=_inspect)

    preview = commands.add_parser("preview", allow_abbrev=False,
                                  help="a PNG grid of sampled sequences, frames along the rows")
    flag = preview.add_argument
    flag("dir", type=path, help="shard directory (with manifest.json)")
    flag("--out", metavar="PNG", type=path, required=True, help="image file to write")
    flag("--split", default=None, help="split to show (default: the first in the manifest)")
    flag("--clips", metavar="N", type=at_least(1), default=8, help="rows (default 8)")
    flag("--length", metavar="L", type=at_least(1), default=8, help="frames per row (default 8)")
    flag("--k-max", metavar="K", type=at_least(1), default=5, help="largest gap K_max (default 5)")
    flag("--seed", metavar="N", type=at_least(0), default=0, help="seed of the gap draws (default 0)")
    preview.set_defaults(run=_preview)

    sample = commands.add_parser("sample-data", allow_abbrev=False,
                                 help="write the built-in stochastic-scene dataset in SSv2's format")
    flag = sample.add_argument
    flag("--out", metavar="DIR", type=path, required=True, help="output directory (annotations/, videos/)")
    flag("--clips", metavar="N", type=at_least(3, MAX_SAMPLE_CLIPS), default=96,
         help=f"good clips over all splits, from 3 (one each for validation and test) to {MAX_SAMPLE_CLIPS} (default 96)")
    flag("--with-broken", action="store_true",
         help="add corrupt, truncated, empty, missing, too-short and non-video entries")
    flag("--seed", metavar="N", type=at_least(0), default=0, help="seed of the scenes (default 0)")
    flag("--workers", metavar="N", type=at_least(1), default=2, help="processes rendering and encoding clips (default 2)")
    sample.set_defaults(run=_sample_data)
    return root


# what a command stopped by Ctrl-C or SIGTERM leaves, said after how it stopped
LEFT_BEHIND = {"build": "; run the same command again to resume",
               "sample-data": "; what it wrote was deleted: run the same command again"}


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(sys.argv[1:] if argv is None else argv)
    with interrupted_once(), sigterm_as_interrupt() as terminated:  # SIGTERM (scancel, timeout) as Ctrl-C
        try:
            return args.run(args)
        except KeyboardInterrupt:  # after each command's own clean-up
            stopped, status = stopped_by(terminated)
            print(f"\nhauwm shards {args.command}: {stopped}{LEFT_BEHIND.get(args.command, '')}", file=sys.stderr)
            return status
