"""`hauwm shards inspect|preview|sample-data` through the command line entry point."""

import errno
import io
import json
import re
import shutil
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import cv2
import pytest

from data_pipeline.cli import main
from data_pipeline.sample_data import HEIGHT, split_sizes


def test_inspect_reports_counts_and_verify_catches_a_damaged_shard(built_shards, tmp_path, capsys):
    assert main(["inspect", str(built_shards), "--verify"]) == 0
    out = capsys.readouterr().out
    assert "train" in out and "validation" in out and "all match the manifest" in out
    manifest = json.loads((built_shards / "manifest.json").read_text())
    assert f"{manifest['splits']['train']['frames']:>10}" in out

    damaged = tmp_path / "damaged"
    shutil.copytree(built_shards, damaged)
    shard = damaged / "train-000002.tar"
    data = bytearray(shard.read_bytes())
    data[700] ^= 0xFF  # inside the first frames member
    shard.write_bytes(bytes(data))
    assert main(["inspect", str(damaged), "--verify"]) == 1
    out = capsys.readouterr().out
    assert "FAILED train-000002.tar: SHA-256 differs from the manifest" in out

    (damaged / "train-000001.tar").unlink()  # a shard gone since the build
    relabelled = damaged / "train-000003.tar"  # a clip whose JSON no longer counts its frames
    with tarfile.open(relabelled) as tar:
        members = [(member, tar.extractfile(member).read()) for member in tar.getmembers()]
    clip = None
    with tarfile.open(relabelled, "w") as tar:
        for member, data in members:
            if clip is None and member.name.endswith(".json"):  # the first clip's
                metadata = json.loads(data)
                metadata["num_frames"] += 1
                data, clip = json.dumps(metadata).encode(), member.name.split(".")[0]
                member.size = len(data)
            tar.addfile(member, io.BytesIO(data))
    assert main(["inspect", str(damaged), "--verify"]) == 1
    out = capsys.readouterr().out
    assert "FAILED train-000001.tar: missing" in out
    assert re.search(rf"FAILED train-000003.tar: clip {clip} stores \d+ frames, its JSON says \d+", out), out


@pytest.mark.parametrize(("edit", "problem"), [  # manifests edited by hand that verify used to call a match
    (lambda m: m["settings"].update(size=32), "train-000000.tar: clip .* stores 64×64 frames, the manifest says 32×32"),
    (lambda m: m["settings"].update(encoding="raw"), "train-000000.tar: clip .* stores .jpgs frames, the manifest's "
                                                     "encoding raw .npy"),
    (lambda m: m["splits"]["train"]["shards"][0].update(frame_counts={"100": m["splits"]["train"]["shards"][0]["clips"]}),
     "train-000000.tar: the clips' frame counts differ from the manifest's frame_counts"),
    (lambda m: m["splits"]["train"].update(clips=m["splits"]["train"]["clips"] + 1),
     "manifest.json: split train has [0-9]+ clips, its shards [0-9]+"),
    (lambda m: m["splits"]["train"]["shards"].pop(), "train-00000[0-9].tar: in .* but not in the manifest"),
])
def test_verify_catches_a_manifest_edited_by_hand(built_shards, tmp_path, capsys, edit, problem):
    shards = shutil.copytree(built_shards, tmp_path / "shards")
    manifest = json.loads((shards / "manifest.json").read_text())
    edit(manifest)
    (shards / "manifest.json").write_text(json.dumps(manifest))
    assert main(["inspect", str(shards), "--verify"]) == 1
    assert re.search(f"FAILED {problem}", capsys.readouterr().out)


def test_inspect_without_manifest_says_how_to_build(tmp_path, capsys):
    assert main(["inspect", str(tmp_path)]) == 2
    assert f"manifest.json not found: {tmp_path} is not a finished shard directory; build it with `hauwm shards build" \
        in capsys.readouterr().err
    (tmp_path / "a-file").write_text("")
    assert main(["inspect", str(tmp_path / "a-file")]) == 2
    assert f"shard directory {tmp_path / 'a-file'} is a file, not a directory" in capsys.readouterr().err
    assert main(["preview", str(tmp_path / "a-file"), "--out", str(tmp_path / "p.png")]) == 2


@pytest.mark.parametrize(("manifest", "message"), [
    ("{bad", "is damaged (not JSON: "),
    ('{"name": "something else"}', "is not a shard manifest (it has no format_version, settings, splits, errors)"),
    ('{"format_version": 99, "settings": {}, "splits": {}, "errors": {}}', "is of shard format 99; this HAUWM reads format 1"),
    ('{"format_version": 1, "settings": {}, "splits": {"train": {}}, "errors": {}}', "is damaged (it has no settings.size)"),
])
def test_a_damaged_or_foreign_manifest_is_named_by_every_reader(built_shards, tmp_path, capsys, manifest, message):
    shards = tmp_path / "shards"
    shutil.copytree(built_shards, shards)
    (shards / "manifest.json").write_text(manifest)
    assert main(["inspect", str(shards)]) == 2
    assert main(["preview", str(shards), "--out", str(tmp_path / "p.png")]) == 2
    from model.cli import main as pretrain
    assert pretrain(["fit", "--config", "configs/pretrain/tiny.yaml", "--data.shards", str(shards)]) == 2
    err = capsys.readouterr().err
    assert err.count(f"{shards / 'manifest.json'} {message}") == 3 and "Traceback" not in err


@pytest.mark.parametrize(("cut", "problem"), [
    (lambda m: m["settings"].pop("size"), "it has no settings.size"),
    (lambda m: m["splits"]["train"].pop("shards"), "it has no splits.train.shards"),
    (lambda m: m["splits"]["validation"]["shards"][0].pop("frame_counts"),
     "it has no splits.validation.shards[0].frame_counts"),
    (lambda m: m["splits"].update(train=[]), "it has no splits.train (a mapping)"),
    (lambda m: m.update(errors=None), "it has no errors (a mapping)"),
    # edited by hand: each of these was a TypeError or ValueError deep inside a reader
    (lambda m: m["splits"]["train"].update(clips=None), "its splits.train.clips is null, not a whole number ≥ 0"),
    (lambda m: m["splits"]["train"].update(bytes="big"), 'its splits.train.bytes is "big", not a whole number ≥ 0'),
    (lambda m: m["splits"]["train"]["shards"][0].update(name=5),
     "its splits.train.shards[0].name is 5, not the file name of a .tar in the directory"),
    (lambda m: m["splits"]["train"]["shards"][0].update(name="../elsewhere/train-000000.tar"),
     'its splits.train.shards[0].name is "../elsewhere/train-000000.tar", not the file name of a .tar'),
    (lambda m: m["splits"]["train"]["shards"][0].update(frame_counts={"abc": 1}),
     'its splits.train.shards[0].frame_counts is {"abc": 1}, not a mapping {"<frames>": clips}'),
    (lambda m: m["splits"]["train"]["shards"][0].update(frame_counts={"29": "1"}),
     'its splits.train.shards[0].frame_counts is {"29": "1"}, not a mapping'),
])
def test_a_manifest_that_lacks_an_entry_is_named_with_it_not_a_key_error(built_shards, tmp_path, capsys, cut, problem):
    shards = tmp_path / "shards"
    shutil.copytree(built_shards, shards)
    manifest = json.loads((shards / "manifest.json").read_text())
    cut(manifest)  # valid JSON still: edited by hand, or written by something else
    (shards / "manifest.json").write_text(json.dumps(manifest))
    assert main(["inspect", str(shards), "--verify"]) == 2
    assert main(["preview", str(shards), "--out", str(tmp_path / "p.png")]) == 2
    from model.cli import main as pretrain
    assert pretrain(["analyze", "--model", "nowhere", "--shards", str(shards), "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert err.count(f"{shards / 'manifest.json'} is damaged ({problem}") == 3
    assert err.count("re-run the `hauwm shards build`") == 3
    assert "Traceback" not in err


def test_a_damaged_errors_file_is_reported_and_fails_verify(built_shards, tmp_path, capsys):
    shards = tmp_path / "shards"
    shutil.copytree(built_shards, shards)
    with (shards / "errors.jsonl").open("a") as f:
        f.write("{half a rec\n")
    assert main(["inspect", str(shards), "--verify"]) == 1
    out = capsys.readouterr().out
    assert "errors.jsonl: 1 lines are not clip failures (the file is damaged)" in out
    assert "FAILED errors.jsonl:" in out and "1 damaged lines" in out


def test_preview_writes_a_grid_of_clips(built_shards, tmp_path):
    out = tmp_path / "preview.png"
    assert main(["preview", str(built_shards), "--out", str(out), "--clips", "3", "--length", "5"]) == 0
    image = cv2.imread(str(out))
    assert image.shape[1] == 5 * 128 and image.shape[0] > 3 * 128
    assert image.std() > 10  # not blank
    assert main(["preview", str(built_shards), "--out", str(tmp_path / "preview.txt")]) == 2
    assert not (tmp_path / "preview.txt").exists()


def test_a_caption_holding_half_a_utf16_pair_is_drawn_not_a_crash():
    """Shards built before such annotations were refused may hold one: OpenCV's putText died with SIGSEGV on it."""
    import subprocess
    import sys

    code = ("import numpy as np\nfrom data_pipeline.preview import _text\n"
            "_text(np.zeros((20, 200, 3), np.uint8), 'pushing \\ud83d ball', 2, 12)\nprint('drawn')")
    drawn = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                           cwd=Path(__file__).parents[2])
    assert drawn.returncode == 0 and drawn.stdout == "drawn\n", drawn.stderr


def test_a_preview_that_cannot_be_written_leaves_the_one_before(built_shards, tmp_path, monkeypatch, capsys):
    out = tmp_path / "preview.png"
    assert main(["preview", str(built_shards), "--out", str(out), "--clips", "2"]) == 0
    before = out.read_bytes()

    def full(self, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    monkeypatch.setattr(Path, "write_bytes", full)
    with pytest.raises(OSError):  # the hauwm command names it (hauwm/cli.py)
        main(["preview", str(built_shards), "--out", str(out), "--clips", "3"])
    assert out.read_bytes() == before and sorted(path.name for path in tmp_path.iterdir()) == ["preview.png"]
    monkeypatch.undo()  # the old one was deleted and the message blamed the directory's permissions
    (tmp_path / "dir.png").mkdir()
    assert main(["preview", str(built_shards), "--out", str(tmp_path / "dir.png")]) == 2
    assert f"--out {tmp_path / 'dir.png'} is a directory: name an image file" in capsys.readouterr().err


def test_preview_of_a_damaged_shard_names_it(built_shards, tmp_path, capsys):
    shards = tmp_path / "shards"
    shutil.copytree(built_shards, shards)
    damaged = sorted(shards.glob("train-*.tar"))[0]
    damaged.write_bytes(damaged.read_bytes()[: damaged.stat().st_size // 2])
    assert main(["preview", str(shards), "--out", str(tmp_path / "preview.png"), "--clips", "1000"]) == 2
    err = capsys.readouterr().err
    assert f"{damaged} is not a readable shard (unexpected end of data); check it with `hauwm shards inspect" in err
    assert err.count("--verify") == 1, err  # the hint twice before
    assert main(["inspect", str(shards), "--verify"]) == 1
    out = capsys.readouterr().out  # inspect --verify told the user to run inspect --verify
    assert f"FAILED {damaged.name}: unreadable (unexpected end of data)\n" in out and "--verify" not in out


def test_sample_data_writes_the_ssv2_layout(tmp_path, capsys):
    assert main(["sample-data", "--out", str(tmp_path), "--clips", "3", "--workers", "1"]) == 0
    annotations = tmp_path / "annotations"
    sizes = split_sizes(3)
    for split, size in sizes.items():
        entries = json.loads((annotations / f"something-something-v2-{split}.json").read_text())
        assert len(entries) == size
        for entry in entries:
            assert set(entry) == ({"id"} if split == "test" else {"id", "label", "template", "placeholders"})
            capture = cv2.VideoCapture(str(tmp_path / "videos" / f"{entry['id']}.webm"))
            assert capture.get(cv2.CAP_PROP_FRAME_HEIGHT) == HEIGHT and capture.get(cv2.CAP_PROP_FPS) == 12
            assert int(capture.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little") in (b"VP90", b"vp09")
    labels = json.loads((annotations / "something-something-v2-labels.json").read_text())
    assert all(isinstance(index, str) for index in labels.values())
    assert json.loads((tmp_path / "broken.json").read_text()) == {}
    written = {path: path.read_bytes() for path in annotations.iterdir()}
    assert main(["sample-data", "--out", str(tmp_path), "--clips", "3", "--workers", "1"]) == 2  # not over a dataset
    assert f"{tmp_path} already holds a dataset (annotations/, videos/, broken.json)" in capsys.readouterr().err
    assert {path: path.read_bytes() for path in annotations.iterdir()} == written
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "broken.json").write_text("my notes")  # a file of the user's own, under the name sample-data writes
    assert main(["sample-data", "--out", str(notes), "--clips", "3", "--workers", "1"]) == 2
    assert f"{notes} already holds a dataset (broken.json)" in capsys.readouterr().err
    assert (notes / "broken.json").read_text() == "my notes"


@pytest.mark.parametrize("stop", [KeyboardInterrupt(), OSError(errno.ENOSPC, "No space left on device")])
def test_sample_data_stopped_midway_leaves_nothing_so_the_same_command_starts_again(tmp_path, monkeypatch, stop):
    import data_pipeline.sample_data as sample_data

    made = []

    def stopped_after_two(job):
        if len(made) == 2:
            raise stop
        made.append(job)
        return real(job)

    real = sample_data._make_clip
    monkeypatch.setattr(sample_data, "_make_clip", stopped_after_two)
    out = tmp_path / "ssv2"

    def stopped_midway() -> None:  # Ctrl-C is said (exit 130), a full disk goes on to the `hauwm` dispatcher
        if isinstance(stop, KeyboardInterrupt):
            assert main(["sample-data", "--out", str(out), "--clips", "3", "--workers", "1"]) == 130
        else:
            with pytest.raises(OSError):
                main(["sample-data", "--out", str(out), "--clips", "3", "--workers", "1"])

    stopped_midway()
    assert not out.exists()  # half its videos, no annotations: "already holds a dataset" after
    (out / "videos").mkdir(parents=True)  # an empty directory of the user's stays
    stopped_midway()
    assert [path.name for path in out.iterdir()] == ["videos"] and not any((out / "videos").iterdir())
    monkeypatch.undo()
    assert main(["sample-data", "--out", str(out), "--clips", "3", "--workers", "1"]) == 0


def test_sigterm_while_sample_data_writes_leaves_nothing_and_says_so(tmp_path):
    """SIGTERM (scancel, timeout) killed it where Ctrl-C cleans up: 35 of 96 videos stayed, and the same command then
    refused the directory as "already holding a dataset"."""
    out = tmp_path / "ssv2"
    command = [sys.executable, "-m", "hauwm", "shards", "sample-data", "--out", str(out), "--clips", "60",
               "--workers", "1"]
    process = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out / "videos").is_dir() or len(list((out / "videos").iterdir())) < 2:
        assert process.poll() is None and time.monotonic() < deadline, "it ended before it could be stopped"
        time.sleep(0.01)
    process.terminate()
    assert process.wait(timeout=60) == 143
    assert "hauwm shards sample-data: terminated (SIGTERM); what it wrote was deleted" in process.stderr.read()
    assert not out.exists()


def test_more_sample_clips_than_ids_is_refused_as_a_flag(tmp_path, capsys):
    """--clips 220847 (SSv2's size) failed with numpy's "Cannot take a larger sample than population"."""
    with pytest.raises(SystemExit):
        main(["sample-data", "--out", str(tmp_path / "s"), "--clips", "220847"])
    assert "--clips: must be a whole number from 3 to 200000, got '220847'" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_sample_data_into_a_shard_directory_is_refused(built_shards, capsys):
    assert main(["sample-data", "--out", str(built_shards), "--clips", "3"]) == 2
    assert f"{built_shards} is a shard directory (manifest.json): pass another --out" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "message"), [
    (["build", "--annotations", "A", "--videos", "V", "--out", ""], "argument --out: an empty path (an unset shell"),
    (["inspect", " "], "argument dir: an empty path"),
    (["preview", "DIR", "--out", "p.png", "--clips", "0"], "argument --clips: must be a whole number >= 1, got '0'"),
    (["sample-data", "--out", "OUT", "--clips", "-3"], "argument --clips: must be a whole number from 3 to 200000"),
    (["preview", "DIR", "--out", "p.png", "--seed", "-1"], "argument --seed: must be a whole number >= 0, got '-1'"),
    (["sample-data", "--out", "OUT", "--seed", "x"], "argument --seed: must be a whole number >= 0, got 'x'"),
])
def test_bad_flag_values_are_refused_by_flag(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2 and message in capsys.readouterr().err
