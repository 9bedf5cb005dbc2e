"""`hauwm shards inspect DIR [--verify]`: what a shard directory holds, and whether it is intact.

Prints, per split, clips, frames, shards, bytes and bytes per frame, and the failed clips by reason
(from manifest.json and errors.jsonl). `--verify` re-reads every shard: it must exist with the
manifest's size and SHA-256, and hold exactly the manifest's clips, frames and frame-count histogram, each clip
with its frames member (of the manifest's encoding and frame size) and a JSON member whose `num_frames` matches
the frames stored; each split's totals must be its shards' sums, and no tar may lie there unlisted.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections import Counter
from pathlib import Path

from tqdm import tqdm

from .shard_format import (ENCODINGS, ERRORS_FILE, MANIFEST_FILE, REBUILD_MANIFEST, decode_frames, frames_member,
                           UnreadableShard, read_manifest, read_samples)


def check_shard(path: Path, expected: dict, settings: dict) -> list[str]:
    """Problems with one shard (empty when it matches its manifest entry and the build's settings)."""
    if not path.is_file():
        return [f"{path.name}: missing"]
    problems = []
    data = path.read_bytes()
    if len(data) != expected["bytes"]:
        problems.append(f"{path.name}: {len(data)} bytes, manifest says {expected['bytes']}")
    if hashlib.sha256(data).hexdigest() != expected["sha256"]:
        problems.append(f"{path.name}: SHA-256 differs from the manifest")
    histogram = Counter()
    try:
        for sample in read_samples(io.BytesIO(data), path.name):
            clip = sample["__key__"]
            metadata = json.loads(sample["json"])
            extension, member = frames_member(sample)
            if extension != ENCODINGS[settings["encoding"]]:
                problems.append(f"{path.name}: clip {clip} stores .{extension} frames, the manifest's encoding "
                                f"{settings['encoding']} .{ENCODINGS[settings['encoding']]}")
            try:
                stored = decode_frames(member, extension)  # [T, H, W, 3]
            except ValueError as error:
                problems.append(f"{path.name}: clip {clip}: its frames do not decode ({error})")
                continue
            if stored.shape[1:3] != (settings["size"],) * 2:
                problems.append(f"{path.name}: clip {clip} stores {stored.shape[2]}×{stored.shape[1]} frames, the "
                                f"manifest says {settings['size']}×{settings['size']}")
            if len(stored) != metadata["num_frames"]:
                problems.append(f"{path.name}: clip {clip} stores {len(stored)} frames, "
                                f"its JSON says {metadata['num_frames']}")
            histogram[str(len(stored))] += 1
    except UnreadableShard as error:  # a broken tar
        return problems + [f"{path.name}: unreadable ({error.reason})"]
    except (KeyError, ValueError) as error:  # a clip without its members, or with a damaged JSON
        return problems + [f"{path.name}: unreadable ({type(error).__name__}: {error})"]
    clips, frames = histogram.total(), sum(int(length) * n for length, n in histogram.items())
    if clips != expected["clips"] or frames != expected["frames"]:
        problems.append(f"{path.name}: {clips} clips and {frames} frames, manifest says "
                        f"{expected['clips']} and {expected['frames']}")
    elif histogram != Counter(expected["frame_counts"]):  # what the loader sizes its epochs from
        problems.append(f"{path.name}: the clips' frame counts differ from the manifest's frame_counts")
    return problems


def check_totals(directory: Path, manifest: dict) -> list[str]:
    """Problems with the manifest's split totals (each the sum over its shards) and tars it does not list."""
    problems = []
    for split, counts in manifest["splits"].items():
        for key in ("clips", "frames", "bytes"):
            if (total := sum(shard[key] for shard in counts["shards"])) != counts[key]:
                problems.append(f"{MANIFEST_FILE}: split {split} has {counts[key]} {key}, its shards {total}")
    listed = {shard["name"] for counts in manifest["splits"].values() for shard in counts["shards"]}
    problems += [f"{tar.name}: in {directory} but not in the manifest" for tar in sorted(directory.glob("*.tar"))
                 if tar.name not in listed]
    return problems


def read_errors(path: Path) -> tuple[list[dict], int]:
    """The clip failures recorded in errors.jsonl (none if it is missing), and how many of its lines are not one."""
    records, damaged = [], 0
    for line in path.read_text(errors="replace").splitlines() if path.is_file() else []:
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            record = None
        if isinstance(record, dict) and {"split", "reason"} <= record.keys():
            records.append(record)
        else:
            damaged += 1
    return records, damaged


def inspect_shards(directory: Path, verify: bool = False) -> int:
    directory = Path(directory)
    manifest = read_manifest(directory)
    errors, damaged = read_errors(directory / ERRORS_FILE)
    settings = manifest["settings"]
    print(f"{directory}: format {manifest['format_version']}, {settings['size']}×{settings['size']} "
          f"{settings['resize']}, encoding {settings['encoding']}" +
          (f" (quality {settings['quality']})" if settings["encoding"] == "jpeg" else ""))
    print(f"{'split':<12}{'clips':>8}{'frames':>10}{'shards':>8}{'MB':>9}{'B/frame':>9}{'errors':>8}")
    for split, counts in manifest["splits"].items():
        print(f"{split:<12}{counts['clips']:>8}{counts['frames']:>10}{len(counts['shards']):>8}"
              f"{counts['bytes'] / 1e6:>9.1f}{counts['bytes'] / max(counts['frames'], 1):>9.0f}{counts['errors']:>8}")
    by_reason = Counter((error["split"], error["reason"]) for error in errors)
    for (split, reason), count in sorted(by_reason.items()):
        print(f"  {split} errors: {reason}: {count}")
    if damaged:
        print(f"  {ERRORS_FILE}: {damaged} lines are not clip failures (the file is damaged); {REBUILD_MANIFEST}")
    if not verify:
        return 0
    shards = [(split, shard) for split, counts in manifest["splits"].items() for shard in counts["shards"]]
    problems = []
    for split, shard in tqdm(shards, desc="verify", unit="shard", disable=None):
        problems += check_shard(directory / shard["name"], shard, settings)
    problems += check_totals(directory, manifest)
    if len(errors) != manifest["errors"]["total"] or damaged:
        problems.append(f"{ERRORS_FILE}: {len(errors)} clip failures and {damaged} damaged lines, manifest says "
                        f"{manifest['errors']['total']} failures")
    for problem in problems:
        print(f"  FAILED {problem}")
    print(f"verify: {len(shards)} shards, " + (f"{len(problems)} problems" if problems else "all match the manifest"))
    return 1 if problems else 0
