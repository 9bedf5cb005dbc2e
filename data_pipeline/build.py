"""`hauwm shards build`: SSv2 (label files + webm) → WebDataset shards, resumable and reproducible.

Each split's clip list (in the label file's order, cut to `--max-clips`) is cut into shards of
`--clips-per-shard` entries, so shard `{split}-{NNNNNN}` always covers the same clips whatever fails,
whatever `--workers`, and whichever `--part` builds it. Clips that fail go to the shard's error list,
never into the tar, which is why shards are uneven. A shard is written to `.NAME.tar.partial`,
renamed to `NAME.tar` when complete, and its stats file `NAME.stats.json` is written last; so after a
SIGKILL at any moment, a re-run keeps the shards whose stats and tar check out (size and SHA-256)
and rebuilds the rest, byte-identically. When every shard of every part is present, the build writes
`errors.jsonl` and then `manifest.json` (settings, counts, per-shard checksums, version).
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import importlib.util
import itertools
import json
import os
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from hauwm.arguments import MAX_TIMEOUT
from hauwm.atomic import written_whole
from hauwm.memory import DECODER_BYTES, beyond_memory
from hauwm.pid_lock import lock_holder, locked

from .shard_format import ENCODINGS, ERRORS_FILE, FORMAT_VERSION, MANIFEST_FILE, add_clip, open_writer
from .ssv2 import AnnotationError, ClipRecord, annotation_path, load_labels, load_split
from .workers import ClipResult, DecodePool, DecodeSettings

SETTINGS_FILE = "build.json"
RETRYABLE = ("missing", "unreadable", "timeout", "crashed")  # failures of the moment: the file may arrive or be
#                                                               readable, the machine be less busy
MAX_MEMBER_NAME = 100  # bytes of a tar member's name in the USTAR format the shards are written in
MAX_SIZE = 512  # --size: the world model reads 64×64; SSv2's clips are 240 pixels high


class BuildError(Exception):
    """A problem with the build's inputs or output directory; the message says what to do."""


@dataclass
class BuildConfig:
    annotations: Path
    videos: Path
    out: Path
    splits: list[str] = field(default_factory=lambda: ["train", "validation"])
    size: int = 64
    resize: str = "squash"
    encoding: str = "jpeg"
    quality: int = 90
    clips_per_shard: int = 256
    min_frames: int = 8
    max_clips: int | None = None
    workers: int = 1
    part: int = 0
    num_parts: int = 1
    max_error_rate: float = 0.01
    timeout: float = 30.0
    retry_failed: bool = False  # rebuild the shards whose clips failed for a reason a later run may not repeat


@dataclass
class ShardPlan:
    split: str
    index: int
    records: list[ClipRecord]

    @property
    def name(self) -> str:
        return f"{self.split}-{self.index:06d}"


def _sha256(path: Path) -> str:
    with open(path, "rb") as file:
        return hashlib.file_digest(file, "sha256").hexdigest()


def _write_json_atomic(path: Path, data, lines: list[dict] | None = None, writer: int = 0) -> None:
    """Write to a temporary name, then rename; `writer` (the part) keeps parts that run at once apart."""
    text = json.dumps(data, indent=1, sort_keys=True) + "\n" if lines is None else \
        "".join(json.dumps(line, sort_keys=True) + "\n" for line in lines)
    with written_whole(path, f".{path.name}.partial{writer}") as partial:
        partial.write_text(text)


def settings_of(config: BuildConfig) -> dict:
    """Everything the shards' bytes depend on; a resume must match it exactly."""
    return {
        "format_version": FORMAT_VERSION, "splits": list(config.splits), "size": config.size,
        "resize": config.resize, "encoding": config.encoding, "quality": config.quality,
        "clips_per_shard": config.clips_per_shard, "min_frames": config.min_frames, "max_clips": config.max_clips,
        "annotations_sha256": {name: _sha256(annotation_path(config.annotations, name))
                               for name in annotation_files(config.splits)},
    }


def annotation_files(splits: list[str]) -> list[str]:
    """The label files a build of `splits` reads (the test split needs no labels)."""
    return (["labels"] if set(splits) - {"test"} else []) + list(splits)


def plan_shards(config: BuildConfig) -> list[ShardPlan]:
    labels = load_labels(config.annotations) if set(config.splits) - {"test"} else {}
    plans, split_of = [], {}  # clip id -> the split it is planned in
    for split in config.splits:
        records = load_split(config.annotations, split, labels)[: config.max_clips]
        for record in records:  # one clip in two splits would put validation clips into training
            if split_of.setdefault(record.id, split) != split:
                raise AnnotationError(f"clip {record.id!r} is listed in {annotation_path(config.annotations, split)} "
                                      f"and in {annotation_path(config.annotations, split_of[record.id])}: a clip "
                                      "belongs to one split; remove it from one of them")
        if not records:  # the loader would name this split missing, though it was built
            raise AnnotationError(f"{annotation_path(config.annotations, split)} lists no clips: drop --split {split}, "
                                  "or point --annotations at the label files of a dataset that has them")
        starts = range(0, len(records), config.clips_per_shard)
        plans += [ShardPlan(split, i, records[start:start + config.clips_per_shard]) for i, start in enumerate(starts)]
    return plans


def check_settings(out: Path, settings: dict, digest: str, part: int) -> None:
    """Record the settings in a fresh directory, or in one holding only shards built with them (parts built on other
    machines and copied there: their stats files carry the settings' digest); refuse a resume whose settings differ
    and a directory holding other files of a build. `digest`: settings_digest(settings)."""
    path, tars = out / SETTINGS_FILE, sorted(out.glob("*.tar"))
    if path.is_file():
        try:
            previous = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise BuildError(f"{path} is damaged ({err}), so the settings of the shards in {out} are unknown; build into "
                             "a new --out directory") from None
        if previous != settings:
            details = "; ".join(f"{key}: was {was}, now {now}" for key, was, now in _differences(previous, settings))
            raise BuildError(f"{out} holds shards built with other settings ({details}). Re-run with the "
                             f"original settings to resume, or build into a new --out directory.")
    elif foreign := [tar.name for tar in tars if not built_with(tar, digest)]:
        raise BuildError(f"{out} holds shards that were not built with these settings, and no {SETTINGS_FILE} (e.g. "
                         f"{foreign[0]}): build into a new --out directory")
    elif not tars and (present := [name for name in (MANIFEST_FILE, ERRORS_FILE) if (out / name).exists()]):
        raise BuildError(f"{out} holds a {present[0]} but no {SETTINGS_FILE}: not a build of `hauwm shards build`, "
                         "whose files would be replaced; build into a new --out directory")
    else:
        _write_json_atomic(path, settings, writer=part)


def built_with(tar: Path, digest: str) -> bool:
    """Whether the shard `tar` has a stats file that records a build with the settings of `digest`."""
    try:
        return json.loads(tar.with_suffix(".stats.json").read_text()).get("settings_digest") == digest
    except (OSError, ValueError, AttributeError):  # missing, not JSON, not an object
        return False


def _differences(previous: dict, current: dict, prefix: str = "") -> list[tuple[str, str, str]]:
    """(key, old, new) for every setting that differs; nested dicts (the label files' hashes) key by key."""
    differences = []
    for key in sorted(previous.keys() | current.keys()):
        was, now = previous.get(key), current.get(key)
        if isinstance(was, dict) and isinstance(now, dict):
            differences += _differences(was, now, prefix=f"{prefix}{key}.")
        elif was != now:
            differences.append((prefix + key, _show(previous, key), _show(current, key)))
    return differences


def _show(settings: dict, key: str) -> str:
    if key not in settings:
        return "absent"
    text = repr(settings[key])
    return text if len(text) <= 40 else text[:37] + "..."


def settings_digest(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def verified_stats(out: Path, plan: ShardPlan, digest: str, check_hash: bool = True) -> dict | None:
    """The shard's stats if its stats file and tar check out, else None (the shard must be built)."""
    stats_path, tar_path = out / f"{plan.name}.stats.json", out / f"{plan.name}.tar"
    try:
        stats = json.loads(stats_path.read_text())
    except (OSError, ValueError):  # missing, not JSON, not UTF-8 text (a disk's damage): the shard is built again
        return None
    if (not isinstance(stats, dict) or stats.get("settings_digest") != digest
            or stats.get("planned") != [r.id for r in plan.records]
            or not tar_path.is_file() or tar_path.stat().st_size != stats.get("bytes")):
        return None
    if check_hash and _sha256(tar_path) != stats.get("sha256"):
        return None
    return stats


def id_fault(clip_id: str) -> str | None:
    """Why `clip_id` cannot key a clip's tar members (`<id>.json`, `<id>.jpgs`), or None when it can."""
    if not clip_id or any(c in clip_id for c in "./\\"):
        return "tar keys must not be empty nor contain '.', '/' or '\\'"
    if any(ord(c) < 32 or c == "\x7f" for c in clip_id):  # a NUL no file name can hold: it was `missing`, "retry"
        return "ids must not hold control characters (no video file can be named so)"
    if len(f"{clip_id}.jpgs".encode()) > MAX_MEMBER_NAME:
        return f"the tar format's member names hold at most {MAX_MEMBER_NAME} bytes, so an id at most {MAX_MEMBER_NAME - 5}"
    return None


def retryable(errors: list[dict]) -> list[dict]:
    """The failures among `errors` (entries of errors.jsonl) that a later run may not repeat."""
    return [error for error in errors if error["reason"] in RETRYABLE]


def _error_entry(config: BuildConfig, record: ClipRecord, reason: str, detail: str) -> dict:
    # absolute: a resumed build whose --videos is spelled otherwise (relative, absolute) writes the same bytes
    return {"id": record.id, "split": record.split, "path": os.path.abspath(config.videos / f"{record.id}.webm"),
            "reason": reason, "detail": detail}


def _metadata(record: ClipRecord, result: ClipResult) -> dict:
    return {"id": record.id, "caption": record.caption, "template": record.template,
            "class_index": record.class_index, "num_frames": result.num_frames,
            "source_width": result.source_width, "source_height": result.source_height, "fps": result.fps}


def clips_held(stats: dict) -> set[str]:
    """The ids of the clips a shard (its stats) holds: those planned that did not fail."""
    failed = {error["id"] for error in stats["errors"]}
    return {clip for clip in stats["planned"] if clip not in failed}


@contextlib.contextmanager
def part_lock(config: BuildConfig) -> Iterator[None]:
    """Hold the lock of this --part of --num-parts into --out (hauwm.pid_lock) while the block runs, refusing a build
    whose shards another running build writes: two builds of one part (a job submitted twice, a requeue) wrote the
    same .partial files, and one committed a shard whose recorded SHA-256 was taken while the other still wrote it;
    builds of another --num-parts have parts that overlap this one's."""
    with locked(config.out / f".build.part-{config.part}-of-{config.num_parts}.lock", lambda pid: BuildError(
            f"{config.out} is being built by another `hauwm shards build` of part {config.part} (pid {pid}): wait for "
            "it to end, or build into another --out")):
        for lock in config.out.glob(".build.part-*-of-*.lock"):
            num_parts = lock.name.removesuffix(".lock").rpartition("-of-")[2]
            if num_parts != str(config.num_parts) and (pid := lock_holder(lock)) is not None:
                raise BuildError(f"{config.out} is being built by a `hauwm shards build` of --num-parts {num_parts} "
                                 f"(pid {pid}), whose parts overlap those of --num-parts {config.num_parts}: wait for "
                                 f"it to end, or build with --num-parts {num_parts}")
        yield


def partial_tar(out: Path, name: str) -> Path:
    """Where shard `name` is written before it is complete (renamed to `name`.tar then)."""
    return out / f".{name}.tar.partial"


def write_shard(config: BuildConfig, plan: ShardPlan, results, digest: str, progress: tqdm) -> dict:
    """Write one shard from the results of its valid clips, in order, to its .partial file; returns its stats.
    `commit_shard` then puts it in place."""
    extension = ENCODINGS[config.encoding]
    partial = partial_tar(config.out, plan.name)
    errors, frame_counts, clips, frames, by_opencv = [], Counter(), 0, 0, 0
    with open(partial, "wb") as file, open_writer(file) as tar:
        for record in plan.records:
            if fault := id_fault(record.id):
                errors.append(_error_entry(config, record, "invalid-id", fault))
                continue
            result = next(results)
            progress.update(1)
            if result.reason:
                errors.append(_error_entry(config, record, result.reason, result.detail))
                continue
            add_clip(tar, _metadata(record, result), result.frames_member, extension)
            clips, frames = clips + 1, frames + result.num_frames
            by_opencv += result.decoder == "opencv"
            frame_counts[str(result.num_frames)] += 1
    stats = {"name": plan.name, "split": plan.split, "index": plan.index, "settings_digest": digest,
             "planned": [r.id for r in plan.records], "clips": clips, "frames": frames,
             "bytes": partial.stat().st_size, "sha256": _sha256(partial),
             "frame_counts": dict(sorted(frame_counts.items(), key=lambda kv: int(kv[0]))), "errors": errors,
             "decoded_by_opencv": by_opencv}
    return stats


def commit_shard(config: BuildConfig, stats: dict) -> None:
    """Put the shard `write_shard` wrote in place of the .partial file; its stats file last: it marks it complete."""
    os.replace(partial_tar(config.out, stats["name"]), config.out / f"{stats['name']}.tar")
    _write_json_atomic(config.out / f"{stats['name']}.stats.json", stats)


def discard_shard(config: BuildConfig, stats: dict) -> None:
    """Remove the .partial file of a shard that `write_shard` wrote and that is not to replace the one in place."""
    partial_tar(config.out, stats["name"]).unlink()


def assemble_manifest(config: BuildConfig, settings: dict, all_stats: list[dict]) -> dict:
    """Write errors.jsonl and manifest.json from the stats of every shard of every part."""
    splits: dict[str, dict] = {}
    errors = []
    for stats in all_stats:
        split = splits.setdefault(stats["split"], {"clips": 0, "frames": 0, "bytes": 0, "errors": 0, "shards": []})
        split["clips"] += stats["clips"]
        split["frames"] += stats["frames"]
        split["bytes"] += stats["bytes"]
        split["errors"] += len(stats["errors"])
        split["shards"].append({key: stats[key] for key in ("clips", "frames", "bytes", "sha256", "frame_counts")}
                               | {"name": f"{stats['name']}.tar"})
        errors += stats["errors"]
    by_reason = dict(sorted(Counter(e["reason"] for e in errors).items()))
    manifest = {"format_version": FORMAT_VERSION, "settings": settings, "splits": splits,
                "errors": {"total": len(errors), "by_reason": by_reason}}
    _write_json_atomic(config.out / ERRORS_FILE, None, lines=errors, writer=config.part)
    _write_json_atomic(config.out / MANIFEST_FILE, manifest, writer=config.part)
    return manifest


def validate(config: BuildConfig) -> None:
    repeated = sorted({split for split in config.splits if config.splits.count(split) > 1})
    if repeated:  # each of its shards would be built and listed twice, so its clips would train twice an epoch
        raise BuildError(f"--split {repeated[0]} is given more than once: name each split once")
    for name in annotation_files(config.splits):
        if not annotation_path(config.annotations, name).is_file():
            raise BuildError(f"{annotation_path(config.annotations, name)}: file not found; --annotations must be "
                             "the directory holding the something-something-v2-*.json files")
    if config.num_parts < 1:
        raise BuildError(f"--num-parts must be at least 1, got {config.num_parts}")
    if not 0 <= config.part < config.num_parts:
        raise BuildError(f"--part {config.part} must lie in 0..{config.num_parts - 1} (--num-parts {config.num_parts})")
    for flag, value in (("--size", config.size), ("--clips-per-shard", config.clips_per_shard),
                        ("--workers", config.workers), ("--min-frames", config.min_frames)):
        if value < 1:
            raise BuildError(f"{flag} must be at least 1, got {value}")
    decoders = min(config.workers, (config.max_clips or config.workers) * len(config.splits))  # one a clip at most
    if problem := beyond_memory({f"--workers {decoders} decoder processes": decoders * DECODER_BYTES},
                                f"lower --workers (this machine has {os.cpu_count()} CPUs: decoders beyond them decode "
                                "no faster)"):
        raise BuildError(problem)
    if config.max_clips is not None and config.max_clips < 1:
        raise BuildError(f"--max-clips must be at least 1, got {config.max_clips}")
    if config.size > MAX_SIZE:
        raise BuildError(f"--size {config.size}: frames are at most {MAX_SIZE} pixels a side (SSv2's clips are 240 high; "
                         "larger frames only upsample them, and cost memory in every decoder process)")
    if not 1 <= config.quality <= 100:
        raise BuildError(f"--quality must lie in 1..100, got {config.quality}")
    if not 0 <= config.max_error_rate <= 1:
        raise BuildError(f"--max-error-rate is a fraction of the clips and must lie in 0..1, got {config.max_error_rate}")
    if not 0 < config.timeout <= MAX_TIMEOUT:
        raise BuildError(f"--timeout (seconds one clip may take to decode) must be positive and at most {MAX_TIMEOUT:g} "
                         f"(a day), got {config.timeout}")


def build(config: BuildConfig, log=print) -> tuple[dict | None, int]:
    """Build (or resume) this part's shards; returns the manifest (None until all parts are done) and
    the exit status (1 when this part's error rate exceeds --max-error-rate)."""
    validate(config)
    plans = plan_shards(config)
    mine = [plan for i, plan in enumerate(plans) if i % config.num_parts == config.part]
    settings = settings_of(config)
    digest = settings_digest(settings)
    complete = {plan.name: stats for plan in mine if (stats := verified_stats(config.out, plan, digest)) is not None}
    kept = {name: stats for name, stats in complete.items() if not (config.retry_failed and retryable(stats["errors"]))}
    todo = [plan for plan in mine if plan.name not in kept]
    valid = [r for plan in todo for r in plan.records if not id_fault(r.id)]
    videos = Path(os.path.abspath(config.videos))  # errors.jsonl's details name it: the same however it is spelled
    # the videos are needed only for clips left to decode: shards copied from other machines assemble without them.
    # A wrong --videos holds none of the build's clips (those left may all be missing: the tail of a download)
    if valid and not videos.is_dir():
        raise BuildError(f"--videos {config.videos}: not a directory (it should hold <id>.webm files)")
    planned = (r for plan in plans for r in plan.records if not id_fault(r.id))
    if valid and not any((videos / f"{record.id}.webm").is_file() for record in itertools.chain(valid, planned)):
        other = sorted(path.name for path in videos.glob(f"{glob.escape(valid[0].id)}.*"))
        found = (f"; {other[0]} is there, but clips are read from <id>.webm files: convert them to WebM, or rename "
                 "them if they are WebM" if other else ": point --videos at the directory of SSv2's <id>.webm files")
        raise BuildError(f"--videos {config.videos} holds none of the build's {sum(len(p.records) for p in plans)} "
                         f"clips (e.g. no {valid[0].id}.webm){found}")
    config.out.mkdir(parents=True, exist_ok=True)
    with part_lock(config):  # one build of a part at a time: they would write the same .partial files
        check_settings(config.out, settings, digest, config.part)
        if todo:  # they describe the shards as they were: gone until this build writes them again (a kill meanwhile
            #       left a manifest that the loader took for finished, of shards since replaced)
            for name in (MANIFEST_FILE, ERRORS_FILE):
                (config.out / name).unlink(missing_ok=True)
        workers = min(config.workers, len(valid))  # a worker each clip at most: one without a clip only costs memory
        log(f"shards: {len(plans)} in all, {len(mine)} in part {config.part}/{config.num_parts}, "
            f"{len(kept)} already complete, {len(todo)} to build ({len(valid)} clips, {workers} workers)")
        started = time.monotonic()
        built, unchanged = [], []  # unchanged: a message for each shard --retry-failed left as it was
        decode = DecodeSettings(config.size, config.resize, config.min_frames, config.encoding, config.quality)
        with DecodePool(workers, decode, config.timeout) as pool, \
                tqdm(total=len(valid), desc="build", unit="clip", disable=None) as progress:
            results = pool.imap(videos / f"{record.id}.webm" for record in valid)
            for plan in todo:
                stats = write_shard(config, plan, results, digest, progress)
                before = complete.get(plan.name)  # a shard that --retry-failed rebuilds must not lose a clip it holds
                if before is not None and (lost := sorted(clips_held(before) - clips_held(stats))):
                    discard_shard(config, stats)
                    reasons = Counter(e["reason"] for e in stats["errors"] if e["id"] in lost)
                    unchanged.append(f"kept {plan.name}.tar as it was: rebuilt, it would lose {len(lost)} of the clips "
                                     f"it holds ({', '.join(f'{r}: {n}' for r, n in sorted(reasons.items()))}; e.g. "
                                     f"{lost[0]}). --retry-failed rebuilds whole shards from --videos, which must hold "
                                     "every clip's video, not only the late ones")
                    kept[plan.name] = before
                else:
                    commit_shard(config, stats)
                    built.append(stats)
                progress.set_postfix(errors=sum(len(stats["errors"]) for stats in built))
        elapsed = time.monotonic() - started
        for message in unchanged:
            log(message)
        part_stats = list(kept.values()) + built
        total = sum(len(stats["planned"]) for stats in part_stats)
        failed = [e for stats in part_stats for e in stats["errors"]]
        new_frames = sum(stats["frames"] for stats in built)
        if built:
            log(f"built {len(built)} shards in {elapsed:.1f} s: {len(valid) / elapsed:.1f} clips/s, "
                f"{new_frames / elapsed:.0f} frames/s")
        log(f"part {config.part}: {total - len(failed)} clips in shards, {len(failed)} failed "
            f"({', '.join(f'{r}: {n}' for r, n in sorted(Counter(e['reason'] for e in failed).items())) or 'none'})")
        if by_opencv := sum(stats.get("decoded_by_opencv", 0) for stats in part_stats):  # stats of older builds: none
            missing = importlib.util.find_spec("decord") is None
            cause = "decord is not installed" if missing else "decord could not open them or would decode them wrong"
            log(f"{by_opencv} of the clips in shards were decoded by OpenCV ({cause}), the rest by decord")
        if (again := retryable(failed)) and not config.retry_failed:
            reasons = ", ".join(sorted(set(e["reason"] for e in again)))
            log(f"{len(again)} of the failures may not happen again ({reasons}): once their files are there, re-run "
                "with --retry-failed to rebuild the shards they are in")
        all_stats = [verified_stats(config.out, plan, digest, check_hash=False) for plan in plans]  # every part's
        absent = [(i, plan.name) for i, (plan, stats) in enumerate(zip(plans, all_stats)) if stats is None]
        manifest = None if absent else assemble_manifest(config, settings, all_stats)
        if absent:
            parts = sorted({i % config.num_parts for i, _ in absent})
            log(f"other parts are not done yet: {len(absent)} shards are missing (e.g. {absent[0][1]}.tar), which "
                f"--part {', '.join(map(str, parts))} of --num-parts {config.num_parts} build; re-run any part after "
                f"they finish to write {MANIFEST_FILE}")
        else:
            for split, counts in manifest["splits"].items():
                log(f"{split}: {counts['clips']} clips, {counts['frames']} frames, {len(counts['shards'])} shards, "
                    f"{counts['bytes'] / 1e6:.1f} MB, {counts['errors']} errors")
            log(f"wrote {config.out / MANIFEST_FILE} and {config.out / ERRORS_FILE}")
        rate = len(failed) / max(total, 1)
        if rate > config.max_error_rate:
            where = config.out / ERRORS_FILE if manifest else "the shards' .stats.json (other parts are unfinished)"
            log(f"error: {len(failed)} of {total} clips failed ({rate:.1%}), more than --max-error-rate "
                f"{config.max_error_rate:g}; see {where}")
            return manifest, 1
        return manifest, 0
