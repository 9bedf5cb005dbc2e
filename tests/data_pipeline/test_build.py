"""`hauwm shards build`: broken entries, faithful frames, reproducibility, resume after SIGKILL, refusals."""

import contextlib
import dataclasses
import functools
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from data_pipeline import decode, workers
from data_pipeline.build import BuildConfig, BuildError, build, id_fault, plan_shards
from data_pipeline.sample_data import BROKEN_KINDS
from data_pipeline.shard_format import decode_frames
from data_pipeline.ssv2 import AnnotationError, annotation_path
from hauwm.pid_lock import pid_lock


def quiet(message):
    pass


def tar_members(path):
    with tarfile.open(path) as tar:
        return {member.name: tar.extractfile(member).read() for member in tar}


def directory_bytes(path):
    return {p.name: p.read_bytes() for p in sorted(path.iterdir())}


def build_cli(*args):
    return [sys.executable, "-m", "hauwm.cli", "shards", "build", *map(str, args)]


@pytest.fixture(scope="module")
def broken_build(sample_ssv2, tmp_path_factory):
    out = tmp_path_factory.mktemp("broken-build")
    config = BuildConfig(annotations=sample_ssv2 / "annotations", videos=sample_ssv2 / "videos", out=out,
                         splits=["train", "validation", "test"], clips_per_shard=8, workers=2, max_error_rate=0.5)
    manifest, status = build(config, log=quiet)
    return config, manifest, status


def test_every_broken_entry_is_recorded_with_its_reason_and_kept_out_of_the_tars(sample_ssv2, broken_build):
    config, manifest, status = broken_build
    assert status == 0
    broken = json.loads((sample_ssv2 / "broken.json").read_text())
    errors = [json.loads(line) for line in (config.out / "errors.jsonl").read_text().splitlines()]
    assert {e["id"]: e["reason"] for e in errors} == {i: BROKEN_KINDS[kind] for i, kind in broken.items()}
    assert all(os.path.isabs(e["path"]) and e["path"].endswith(f"{e['id']}.webm") and e["detail"] for e in errors)
    assert manifest["errors"]["total"] == len(broken)
    stored = set()
    for split, counts in manifest["splits"].items():
        for shard in counts["shards"]:
            members = tar_members(config.out / shard["name"])
            ids = {name.split(".")[0] for name in members}
            assert len(ids) == shard["clips"] and set(members) == {f"{i}.{e}" for i in ids for e in ("jpgs", "json")}
            for name, data in members.items():
                if name.endswith(".json"):
                    metadata = json.loads(data)
                    assert (metadata["class_index"] == -1) == (split == "test")
            stored |= ids
    assert not stored & set(broken)
    assert sum(c["clips"] for c in manifest["splits"].values()) == 24


def test_error_rate_above_the_limit_fails_but_keeps_the_shards(broken_build):
    config, _, _ = broken_build
    config.max_error_rate = 0.01
    lines = []
    manifest, status = build(config, log=lines.append)  # a resume: every shard verified and kept
    assert status == 1 and manifest is not None
    assert any("0 to build" in line for line in lines)
    assert any("more than --max-error-rate 0.01" in line for line in lines)


def test_a_hanging_decoder_is_killed_and_the_build_goes_on(sample_ssv2, clean_annotations, tmp_path, monkeypatch):
    real = workers.process_clip
    hang_id = json.loads((clean_annotations / "something-something-v2-validation.json").read_text())[1]["id"]

    def hangs_on_one_clip(path, settings):
        if path.stem == hang_id:
            time.sleep(3600)
        return real(path, settings)

    monkeypatch.setattr(workers, "process_clip", hangs_on_one_clip)  # the forked workers inherit it
    config = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=tmp_path,
                         splits=["validation"], workers=2, timeout=1.0, max_error_rate=0.5)
    manifest, status = build(config, log=quiet)
    errors = [json.loads(line) for line in (tmp_path / "errors.jsonl").read_text().splitlines()]
    assert [(e["id"], e["reason"]) for e in errors] == [(hang_id, "timeout")]
    assert manifest["splits"]["validation"]["clips"] == 2 and status == 0


def test_a_decoder_that_died_between_clips_is_replaced_and_its_next_clip_decoded(sample_ssv2, clean_annotations):
    """A decoder killed while idle (the OOM killer, a user) made the next clip's send raise BrokenPipeError, which
    ended the build with exit status 141 and no word, as if its stdout had been closed."""
    entries = json.loads((clean_annotations / "something-something-v2-validation.json").read_text())
    paths = [next((sample_ssv2 / "videos").glob(f"{entry['id']}.*")) for entry in entries]
    settings = workers.DecodeSettings(size=64, resize="squash", min_frames=8, encoding="jpeg", quality=90)
    with workers.DecodePool(2, settings, timeout=60.0) as pool:
        idle = pool.workers[1].process
        idle.kill()
        idle.join()
        results = list(pool.imap(paths))
    assert [result.reason for result in results] == [""] * len(paths) and all(r.num_frames for r in results)


def test_clips_that_decord_cannot_open_are_decoded_by_opencv_and_counted(sample_ssv2, clean_annotations, tmp_path,
                                                                        monkeypatch):
    real = decode._decode_decord
    refused = json.loads((clean_annotations / "something-something-v2-validation.json").read_text())[1]["id"]

    def refuses_one_clip(path):
        if path.stem == refused:
            raise RuntimeError("cannot open")
        return real(path)

    monkeypatch.setattr(decode, "_decode_decord", refuses_one_clip)  # the forked workers inherit it
    config = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=tmp_path,
                         splits=["validation"], workers=2)
    lines = []
    manifest, status = build(config, log=lines.append)
    assert status == 0 and manifest["splits"]["validation"]["clips"] == 3
    assert ("1 of the clips in shards were decoded by OpenCV (decord could not open them or would decode them "
            "wrong), the rest by decord") in lines
    assert sum(json.loads(path.read_text())["decoded_by_opencv"] for path in tmp_path.glob("*.stats.json")) == 1


def decode_with_opencv(path, size, crop=False):
    """An independent decode: OpenCV, every frame, its centre square cut out where `crop`, resized with INTER_AREA."""
    capture, frames = cv2.VideoCapture(str(path)), []
    while True:
        ok, frame = capture.read()
        if not ok:
            return np.stack(frames)
        if crop:
            height, width = frame.shape[:2]
            side = min(height, width)
            frame = frame[(height - side) // 2:(height + side) // 2, (width - side) // 2:(width + side) // 2]
        frames.append(cv2.resize(frame[:, :, ::-1], (size, size), interpolation=cv2.INTER_AREA))


@pytest.mark.parametrize("resize", ["squash", "center-crop"])
def test_stored_frames_equal_an_independent_decode(sample_ssv2, clean_annotations, built_shards, tmp_path, resize):
    raw = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=tmp_path,
                      splits=["validation"], encoding="raw", max_error_rate=0.0, resize=resize)
    build(raw, log=quiet)
    built = [(tmp_path, "npy")] + ([(built_shards, "jpgs")] if resize == "squash" else [])  # the demo's: squashed
    for directory, extension in built:
        members = tar_members(directory / "validation-000000.tar")
        ids = sorted({name.split(".")[0] for name in members})
        assert len(ids) == 3
        for clip_id in ids:
            stored = decode_frames(members[f"{clip_id}.{extension}"], extension)
            metadata = json.loads(members[f"{clip_id}.json"])
            source = decode_with_opencv(sample_ssv2 / "videos" / f"{clip_id}.webm", 64, crop=resize == "center-crop")
            assert stored.shape == source.shape == (metadata["num_frames"], 64, 64, 3)
            assert metadata["source_height"] == 240 and metadata["fps"] == 12.0
            if extension == "npy":
                np.testing.assert_array_equal(stored, source)
            else:  # JPEG q90 4:4:4: close (about 42 dB PSNR), not equal
                mse = np.mean((stored.astype(float) - source) ** 2)
                assert 10 * np.log10(255**2 / mse) > 38


def test_resume_after_sigkill_is_byte_identical(sample_ssv2, clean_annotations, tmp_path):
    common = ["--annotations", clean_annotations, "--videos", sample_ssv2 / "videos", "--split", "train",
              "--split", "validation", "--clips-per-shard", "2", "--max-error-rate", "0"]
    reference = tmp_path / "reference"
    subprocess.run(build_cli(*common, "--out", reference, "--workers", "2"), check=True, capture_output=True)
    for kill_after_stats in (0, 4):  # kill while the first shard is written, and later on
        out = tmp_path / f"killed-{kill_after_stats}"
        process = subprocess.Popen(build_cli(*common, "--out", out, "--workers", "1"), start_new_session=True,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if kill_after_stats == 0 and out.is_dir() and any(out.glob(".*.partial")):
                break
            if kill_after_stats and out.is_dir() and len(list(out.glob("*.stats.json"))) >= kill_after_stats:
                break
            time.sleep(0.002)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)  # the build and its decoder processes
        process.wait()
        assert not (out / "manifest.json").exists(), "the build finished before it could be killed"
        finished = subprocess.run(build_cli(*common, "--out", out, "--workers", "2"), capture_output=True, text=True)
        assert finished.returncode == 0, finished.stderr
        assert directory_bytes(out) == directory_bytes(reference)


def processes_of_group(group: int) -> list[int]:
    """The pids of the processes still in process group `group` (zombies left out), from /proc."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            fields = stat.read_text().rsplit(")", 1)[1].split()  # after "pid (comm)": state, ppid, pgrp, ...
            if int(fields[2]) == group and fields[0] != "Z":
                pids.append(int(stat.parent.name))
    return pids


def test_the_decoders_of_a_build_killed_alone_end_with_it(sample_ssv2, clean_annotations, tmp_path):
    """kill -9 of the build process alone (the OOM killer's way, or a user's): its decoder processes, adopted by
    init, waited for their next clip for good."""
    out = tmp_path / "killed"
    process = subprocess.Popen(build_cli("--annotations", clean_annotations, "--videos", sample_ssv2 / "videos",
                                         "--split", "train", "--clips-per-shard", "2", "--out", out, "--workers", "2"),
                               start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while not (out.is_dir() and any(out.glob(".*.partial"))) and time.monotonic() < deadline:
            time.sleep(0.002)  # until the decoders work
        assert len(processes_of_group(process.pid)) == 3, "the build and its 2 decoders"
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
        deadline = time.monotonic() + 10
        while processes_of_group(process.pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not processes_of_group(process.pid)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)


def test_a_damaged_shard_is_rebuilt_on_resume(sample_ssv2, clean_annotations, tmp_path):
    config = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=tmp_path,
                         splits=["validation"], max_error_rate=0.0)
    build(config, log=quiet)
    before = directory_bytes(tmp_path)
    shard = tmp_path / "validation-000000.tar"
    shard.write_bytes(shard.read_bytes()[:-2000] + b"\0" * 2000)  # same size, different bytes
    lines = []
    build(config, log=lines.append)
    assert any("1 to build" in line for line in lines)
    assert directory_bytes(tmp_path) == before


def test_changed_settings_are_refused(sample_ssv2, clean_annotations, tmp_path):
    common = ["--annotations", clean_annotations, "--videos", sample_ssv2 / "videos", "--split", "validation",
              "--out", tmp_path]
    subprocess.run(build_cli(*common), check=True, capture_output=True)
    refused = subprocess.run(build_cli(*common, "--size", "32"), capture_output=True, text=True)
    assert refused.returncode == 2
    assert "size: was 64, now 32" in refused.stderr and "new --out" in refused.stderr
    assert "Traceback" not in refused.stderr


def two_parts(sample_ssv2, annotations, out: Path, part: int) -> BuildConfig:
    """Part `part` of a build of train and validation in two parts, 4 clips a shard."""
    return BuildConfig(annotations=annotations, videos=sample_ssv2 / "videos", out=out, splits=["train", "validation"],
                       clips_per_shard=4, part=part, num_parts=2, max_error_rate=0.0)


def test_parts_build_the_same_shards_and_the_last_writes_the_manifest(sample_ssv2, clean_annotations, built_shards,
                                                                      tmp_path):
    config = functools.partial(two_parts, sample_ssv2, clean_annotations, tmp_path)  # config(part)
    lines = []
    manifest, status = build(config(1), log=lines.append)
    assert manifest is None and status == 0 and not (tmp_path / "manifest.json").exists()
    assert sorted(p.name for p in tmp_path.glob("*.tar")) == ["train-000001.tar", "train-000003.tar",
                                                              "validation-000000.tar"]  # every 2nd of 6
    assert ("other parts are not done yet: 3 shards are missing (e.g. train-000000.tar), which --part 0 of --num-parts "
            "2 build; re-run any part after they finish to write manifest.json") in lines
    manifest, status = build(config(0), log=quiet)
    assert manifest is not None
    assert directory_bytes(tmp_path) == directory_bytes(built_shards)


def test_a_second_build_of_a_part_while_it_runs_is_refused_and_other_parts_go_on(sample_ssv2, clean_annotations,
                                                                                 tmp_path):
    """Two builds of one part (a job submitted twice, a requeue) wrote the same .partial files: one failed, and the
    other recorded a SHA-256 taken while the first still wrote the shard (`inspect --verify` then failed)."""
    config = functools.partial(two_parts, sample_ssv2, clean_annotations, tmp_path)  # config(part)
    with pid_lock(tmp_path / ".build.part-0-of-2.lock"):  # a build of part 0, as far as the lock goes
        with pytest.raises(BuildError, match=rf"{tmp_path} is being built by another `hauwm shards build` of part 0 "
                                             rf"\(pid {os.getpid()}\): wait for it to end, or build into another --out"):
            build(config(0), log=quiet)
        assert not list(tmp_path.glob("*.tar")) and not list(tmp_path.glob(".*.partial"))
        assert build(config(1), log=quiet) == (None, 0)  # another part goes on
    manifest, status = build(config(0), log=quiet)  # once the other build has ended
    assert manifest is not None and status == 0 and not list(tmp_path.glob(".build.part-*.lock"))


def test_a_build_of_another_num_parts_while_one_runs_is_refused(sample_ssv2, clean_annotations, tmp_path):
    """Their parts overlap: part 0 of 1 writes every shard part 1 of 2 writes, through the same .partial files."""
    config = functools.partial(two_parts, sample_ssv2, clean_annotations, tmp_path)  # config(part), of 2 parts
    with pid_lock(tmp_path / ".build.part-1-of-2.lock"):  # a build of part 1 of 2, as far as the lock goes
        with pytest.raises(BuildError, match=rf"{tmp_path} is being built by a `hauwm shards build` of --num-parts 2 "
                                             rf"\(pid {os.getpid()}\), whose parts overlap those of --num-parts 1: wait "
                                             "for it to end, or build with --num-parts 2"):
            build(dataclasses.replace(config(0), num_parts=1), log=quiet)
        assert not list(tmp_path.glob("*.tar")) and not list(tmp_path.glob(".*.partial"))
        assert build(config(0), log=quiet) == (None, 0)  # a part of the same --num-parts goes on
    (tmp_path / ".build.part-0-of-3.lock").write_text("123\n")  # left by a build killed with -9: no one holds it
    manifest, status = build(dataclasses.replace(config(0), num_parts=1), log=quiet)  # once the other has ended
    assert manifest is not None and status == 0


def test_parts_built_on_machines_without_a_shared_disk_assemble_where_their_files_are_copied(
        sample_ssv2, clean_annotations, built_shards, tmp_path):
    def config(part, out):
        return BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=out,
                           splits=["train", "validation"], clips_per_shard=4, part=part, num_parts=2,
                           max_error_rate=0.0)
    for part in (0, 1):
        build(config(part, tmp_path / f"machine-{part}"), log=quiet)
    gathered = tmp_path / "gathered"
    gathered.mkdir()
    for path in [*tmp_path.glob("machine-*/*.tar"), *tmp_path.glob("machine-*/*.stats.json")]:  # docs/data_pipeline.md
        shutil.copy(path, gathered)
    # on a machine without the videos: nothing is left to decode (refused for --videos before)
    manifest, status = build(dataclasses.replace(config(0, gathered), videos=tmp_path / "no-videos-here"), log=quiet)
    assert manifest is not None and status == 0
    assert directory_bytes(gathered) == directory_bytes(built_shards)
    other = config(0, tmp_path / "machine-1")
    (other.out / "build.json").unlink()
    with pytest.raises(BuildError, match=r"holds shards that were not built with these settings, and no build.json "
                                         r"\(e.g. train-000001.tar\)"):
        build(dataclasses.replace(other, size=32), log=quiet)


def test_a_directory_holding_a_manifest_or_errors_file_of_something_else_is_refused(sample_ssv2, clean_annotations,
                                                                                    tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "manifest.json").write_text('{"my": "precious manifest"}')
    config = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=out, splits=["validation"])
    with pytest.raises(BuildError, match=r"mine holds a manifest.json but no build.json: not a build of `hauwm shards "
                                         r"build`, whose files would be replaced; build into a new --out directory"):
        build(config, log=quiet)
    assert [path.name for path in out.iterdir()] == ["manifest.json"]
    assert (out / "manifest.json").read_text() == '{"my": "precious manifest"}'


def test_bad_inputs_give_clear_errors(sample_ssv2, tmp_path, monkeypatch):
    config = BuildConfig(annotations=tmp_path / "nowhere", videos=sample_ssv2 / "videos", out=tmp_path / "out")
    result = subprocess.run(build_cli("--annotations", tmp_path / "nowhere", "--videos", sample_ssv2 / "videos",
                                      "--out", tmp_path / "out"), capture_output=True, text=True)
    assert result.returncode == 2 and "labels.json: file not found" in result.stderr
    config.annotations, config.videos = sample_ssv2 / "annotations", tmp_path / "no-videos"
    with pytest.raises(BuildError, match="--videos .*no-videos: not a directory"):
        build(config, log=quiet)
    config.videos = sample_ssv2 / "annotations"  # a directory, but not of the clips' videos
    with pytest.raises(BuildError, match=r"--videos .*annotations holds none of the build's \d+ clips \(e.g. no "):
        build(config, log=quiet)
    assert not config.out.exists()  # refused before anything was written
    mp4 = shutil.copytree(sample_ssv2 / "videos", tmp_path / "mp4")  # the videos, named otherwise: said so
    for video in mp4.glob("*.webm"):
        video.rename(video.with_suffix(".mp4"))
    config.videos = mp4
    with pytest.raises(BuildError, match=r"holds none of .* \(e.g. no (\d+).webm\); \1.mp4 is there, but clips are "
                                         r"read from <id>.webm files"):
        build(config, log=quiet)
    config.videos = sample_ssv2 / "videos"
    monkeypatch.setattr("hauwm.memory.memory_available", lambda: 16 * 2**30)
    for setting, value, message in (("max_error_rate", 1.5, "--max-error-rate .* 0..1, got 1.5"),
                                    ("timeout", 0.0, "--timeout .* must be positive and at most 86400 .*, got 0.0"),
                                    ("timeout", math.inf, "--timeout .* at most 86400 .*, got inf"),
                                    ("timeout", 1e300, "--timeout .* at most 86400 .*, got 1e[+]300"),
                                    ("num_parts", 0, "--num-parts must be at least 1, got 0"),
                                    ("size", 100_000, "--size 100000: frames are at most 512 pixels a side"),
                                    # 100,000 forked decoders ran the machine out of memory
                                    ("workers", 100_000, r"this run needs at least 781.2 GiB of memory \(--workers 100000 "
                                                         r"decoder processes 781.2 GiB\), more than the 16.0 GiB "
                                                         r"available: lower --workers \(this machine has \d+ CPUs"),
                                    ("max_clips", 0, "--max-clips must be at least 1, got 0")):
        with pytest.raises(BuildError, match=message):
            build(dataclasses.replace(config, **{setting: value}), log=quiet)
    assert not config.out.exists()  # refused before anything was written


def test_a_build_starts_no_more_decoders_than_it_has_clips(sample_ssv2, clean_annotations, tmp_path, monkeypatch):
    started = []
    monkeypatch.setattr(workers.DecodePool, "__enter__", lambda pool: started.append(len(pool.workers)) or pool)
    config = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=tmp_path / "out",
                         splits=["validation"], workers=64)
    build(config, log=quiet)
    clips = json.loads((tmp_path / "out" / "manifest.json").read_text())["splits"]["validation"]["clips"]
    assert started == [clips] and clips < 64


@pytest.mark.slow
def test_repeated_random_sigkills_with_broken_entries_still_end_byte_identical(sample_ssv2, tmp_path):
    common = ["--annotations", sample_ssv2 / "annotations", "--videos", sample_ssv2 / "videos", "--split", "train",
              "--split", "validation", "--split", "test", "--clips-per-shard", "3", "--max-error-rate", "0.5"]
    reference = tmp_path / "reference"
    subprocess.run(build_cli(*common, "--out", reference, "--workers", "1"), check=True, capture_output=True)
    out, rng = tmp_path / "killed", np.random.default_rng(0)
    for _ in range(6):  # kill at random moments, several times over, with 2 decoder processes
        process = subprocess.Popen(build_cli(*common, "--out", out, "--workers", "2"), start_new_session=True,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(0.05, 1.0))
        with contextlib.suppress(ProcessLookupError):  # it may have finished already
            os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    subprocess.run(build_cli(*common, "--out", out, "--workers", "2"), check=True, capture_output=True)
    assert directory_bytes(out) == directory_bytes(reference)


def test_a_clip_listed_in_two_splits_is_refused_before_anything_is_built(sample_ssv2, clean_annotations, tmp_path):
    annotations = shutil.copytree(clean_annotations, tmp_path / "annotations")
    leaked = json.loads(annotation_path(annotations, "train").read_text())[0]
    validation = annotation_path(annotations, "validation")
    validation.write_text(json.dumps(json.loads(validation.read_text()) + [leaked]))
    config = BuildConfig(annotations=annotations, videos=sample_ssv2 / "videos", out=tmp_path / "shards")
    with pytest.raises(AnnotationError, match=rf"clip '{leaked['id']}' is listed in \S+validation.json and in "
                                              r"\S+train.json: a clip belongs to one split"):
        plan_shards(config)


def test_a_repeated_or_empty_split_is_refused_before_anything_is_written(sample_ssv2, clean_annotations, tmp_path):
    config = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=tmp_path / "shards",
                         splits=["validation", "validation"])
    with pytest.raises(BuildError, match="--split validation is given more than once"):
        build(config, log=quiet)
    annotations = shutil.copytree(clean_annotations, tmp_path / "annotations")
    annotation_path(annotations, "validation").write_text("[]")
    config = dataclasses.replace(config, annotations=annotations, splits=["train", "validation"])
    with pytest.raises(AnnotationError, match=r"validation.json lists no clips: drop --split validation"):
        build(config, log=quiet)
    assert not config.out.exists()


def test_an_id_too_long_for_a_tar_member_is_recorded_not_fatal(sample_ssv2, clean_annotations, tmp_path):
    annotations = shutil.copytree(clean_annotations, tmp_path / "annotations")
    validation = annotation_path(annotations, "validation")
    entries = json.loads(validation.read_text())
    long_id = "7" * 96  # 96 + ".jpgs" = 101 bytes: one more than a USTAR member name holds
    validation.write_text(json.dumps([entries[0] | {"id": long_id}] + entries[1:]))
    config = BuildConfig(annotations=annotations, videos=sample_ssv2 / "videos", out=tmp_path / "shards",
                         splits=["validation"], max_error_rate=0.5)
    manifest, status = build(config, log=quiet)
    errors = [json.loads(line) for line in (config.out / "errors.jsonl").read_text().splitlines()]
    assert [(e["id"], e["reason"]) for e in errors] == [(long_id, "invalid-id")] and "at most 95" in errors[0]["detail"]
    assert manifest["splits"]["validation"]["clips"] == len(entries) - 1 and status == 0
    assert "control characters" in id_fault("a\x00b") and "control characters" in id_fault("a\tb")  # "missing" before


def test_retry_failed_rebuilds_the_shard_of_a_clip_that_was_missing(sample_ssv2, clean_annotations, tmp_path):
    videos = shutil.copytree(sample_ssv2 / "videos", tmp_path / "videos")
    late = json.loads(annotation_path(clean_annotations, "validation").read_text())[1]["id"]
    (videos / f"{late}.webm").rename(tmp_path / "late.webm")  # not downloaded yet
    config = BuildConfig(annotations=clean_annotations, videos=videos, out=tmp_path / "shards", splits=["validation"],
                         max_error_rate=0.5)
    manifest, _ = build(config, log=quiet)
    assert manifest["errors"]["by_reason"] == {"missing": 1}
    (tmp_path / "late.webm").rename(videos / f"{late}.webm")  # the download finished
    lines = []
    manifest, _ = build(config, log=lines.append)  # a plain re-run keeps the shard, and says how to retry
    assert manifest["errors"]["by_reason"] == {"missing": 1}
    assert any("1 of the failures may not happen again (missing)" in line and "--retry-failed" in line for line in lines)
    manifest, status = build(dataclasses.replace(config, retry_failed=True), log=quiet)
    assert manifest["errors"]["total"] == 0 and manifest["splits"]["validation"]["clips"] == 3 and status == 0
    assert (config.out / "errors.jsonl").read_text() == ""


def test_a_rebuild_killed_before_its_manifest_leaves_none_of_the_shards_as_they_were(sample_ssv2, clean_annotations,
                                                                                     tmp_path, monkeypatch):
    """--retry-failed replaced a shard and was killed before it wrote manifest.json: the old manifest stayed, with
    the old shard's size, checksum and clips, and the loader took the directory for finished (found by a review)."""
    videos = shutil.copytree(sample_ssv2 / "videos", tmp_path / "videos")
    late = json.loads(annotation_path(clean_annotations, "validation").read_text())[1]["id"]
    (videos / f"{late}.webm").rename(tmp_path / "late.webm")
    config = BuildConfig(annotations=clean_annotations, videos=videos, out=tmp_path / "shards", splits=["validation"],
                         max_error_rate=0.5)
    build(config, log=quiet)
    (tmp_path / "late.webm").rename(videos / f"{late}.webm")

    def killed(*args, **kwargs):
        raise KeyboardInterrupt  # as a kill between the last shard and the manifest

    monkeypatch.setattr("data_pipeline.build.assemble_manifest", killed)
    with pytest.raises(KeyboardInterrupt):
        build(dataclasses.replace(config, retry_failed=True), log=quiet)
    assert not (config.out / "manifest.json").exists() and not (config.out / "errors.jsonl").exists()
    monkeypatch.undo()
    manifest, status = build(config, log=quiet)  # the re-run writes them, of the shards as they are now
    assert status == 0 and manifest["splits"]["validation"]["clips"] == 3 and manifest["errors"]["total"] == 0


def test_shards_left_whose_videos_are_all_missing_still_build(sample_ssv2, clean_annotations, tmp_path):
    """The check for a wrong --videos looked only at the clips left to build: when those were all missing (the tail of
    a download, or a part given only such shards), every re-run was refused and no manifest was ever written."""
    videos = shutil.copytree(sample_ssv2 / "videos", tmp_path / "videos")
    last = json.loads(annotation_path(clean_annotations, "validation").read_text())[-1]["id"]
    (videos / f"{last}.webm").unlink()  # never downloaded
    config = BuildConfig(annotations=clean_annotations, videos=videos, out=tmp_path / "shards", splits=["validation"],
                         clips_per_shard=1, max_error_rate=0.5)
    manifest, _ = build(config, log=quiet)
    last_shard = manifest["splits"]["validation"]["shards"][-1]["name"]  # its clip is the missing one
    for stale in (config.out / last_shard, config.out / last_shard.replace(".tar", ".stats.json"),
                  config.out / "manifest.json"):
        stale.unlink()  # as a build killed before its last shard leaves it
    manifest, status = build(config, log=quiet)
    assert status == 0 and manifest["errors"]["by_reason"] == {"missing": 1}


def test_errors_jsonl_is_the_same_however_videos_is_spelled(sample_ssv2, clean_annotations, tmp_path, monkeypatch):
    """The decoder got --videos as typed, and its details name the path: a resume from another directory, or with a
    relative path, wrote other bytes (found by a review)."""
    videos = shutil.copytree(sample_ssv2 / "videos", tmp_path / "videos")
    missing = json.loads(annotation_path(clean_annotations, "validation").read_text())[0]["id"]
    (videos / f"{missing}.webm").unlink()
    written = []
    for spelled in (videos, Path("videos")):
        monkeypatch.chdir(tmp_path)
        out = tmp_path / f"out-{len(written)}"
        build(BuildConfig(annotations=clean_annotations, videos=spelled, out=out, splits=["validation"],
                          max_error_rate=0.5), log=quiet)
        written.append((out / "errors.jsonl").read_text())
    assert written[0] == written[1] and f"no file at {videos / missing}.webm" in written[0]


@pytest.mark.parametrize("damage", [b"\xff\xfe", b"[]", b"null"])
def test_a_damaged_stats_file_has_its_shard_built_again(sample_ssv2, clean_annotations, tmp_path, damage):
    """Bytes that are not UTF-8 (a disk's damage) raised UnicodeDecodeError, JSON that is not an object
    AttributeError, both as tracebacks; the docs promise the shard is built again."""
    config = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=tmp_path, splits=["validation"])
    build(config, log=quiet)
    before = directory_bytes(tmp_path)
    (tmp_path / "validation-000000.stats.json").write_bytes(damage)
    lines = []
    build(config, log=lines.append)
    assert any("1 to build" in line for line in lines)
    assert directory_bytes(tmp_path) == before


def test_retry_failed_never_loses_a_clip_a_shard_holds(sample_ssv2, clean_annotations, tmp_path):
    videos = shutil.copytree(sample_ssv2 / "videos", tmp_path / "videos")
    clips = [entry["id"] for entry in json.loads(annotation_path(clean_annotations, "validation").read_text())]
    (videos / f"{clips[1]}.webm").rename(tmp_path / "late.webm")  # not downloaded yet
    config = BuildConfig(annotations=clean_annotations, videos=videos, out=tmp_path / "shards", splits=["validation"],
                         max_error_rate=0.5)
    build(config, log=quiet)
    before = directory_bytes(config.out)
    late = tmp_path / "late-videos"  # the natural retry: a directory holding only the late download
    late.mkdir()
    (tmp_path / "late.webm").rename(late / f"{clips[1]}.webm")
    lines = []
    manifest, status = build(dataclasses.replace(config, videos=late, retry_failed=True), log=lines.append)
    assert directory_bytes(config.out) == before  # the shard as it was: its other clips' videos are not in late/
    assert manifest["splits"]["validation"]["clips"] == 2 and manifest["errors"]["by_reason"] == {"missing": 1}
    assert any(line.startswith("kept validation-000000.tar as it was: rebuilt, it would lose 2 of the clips it holds "
                               "(missing: 2; e.g. ") and "must hold every clip's video" in line for line in lines)
    assert not list(config.out.glob(".*.partial"))


def test_workers_beyond_the_clips_are_not_counted_against_the_memory(sample_ssv2, clean_annotations, tmp_path,
                                                                    monkeypatch):
    """A build starts a decoder a clip at most: --workers 100000 --max-clips 2 starts 2 (one split)."""
    monkeypatch.setattr("hauwm.memory.memory_available", lambda: 2**30)
    config = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=tmp_path / "out",
                         splits=["validation"], workers=100_000, max_clips=2)
    manifest, status = build(config, log=quiet)
    assert status == 0 and manifest["splits"]["validation"]["clips"] == 2
