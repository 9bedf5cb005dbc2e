"""Shared fixtures: a small SSv2-format sample tree and shards built from it (session-scoped, a few seconds).

- `sample_ssv2`: `Path` to a `hauwm shards sample-data --clips 24 --with-broken` tree
  (`annotations/`, `videos/`, `broken.json` listing the broken entries: id → kind).
- `built_shards`: `Path` to a shard directory built from the clean entries of that tree (broken entries
  removed from the label files), train and validation, `--clips-per-shard 4`: train has 5 shards of
  4, 4, 4, 4, 2 clips, validation one shard of 3 clips. Clips have 24–60 frames at 64×64.
- `as_v1_export(export, out)`: a copy of a model export with config.json in the old schema_version 1 layout.
- `damaged_in_place(checkpoint, out)`: a copy of a torch checkpoint with 8 bytes changed inside its largest record
  (a disk or copy error: torch.load reads it without a word); → the record's name.
"""

from __future__ import annotations

import json
import logging
import shutil
import signal
import sys
import zipfile
from pathlib import Path

import pytest

from data_pipeline.build import BuildConfig, build
from data_pipeline.sample_data import make_sample_data
from data_pipeline.ssv2 import annotation_path


def pytest_configure(config) -> None:
    """Ctrl-C handled as in a terminal, however the suite was started: one started with `&` in a script (CI's, `make
    test &`) inherits SIGINT ignored (POSIX, without job control), Python then installs no handler, and every process
    a test starts would inherit it too; the tests of what Ctrl-C does found it ignored (and those of workers that
    ignore it passed without testing anything)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(autouse=True)
def lightning_logs_to_stderr_after_each_test():
    """Lightning's log handlers keep the sys.stderr of the moment lightning was first imported. When that was a
    test's capsys stream, it is closed after the test, and every later Lightning message would print a 'Logging
    error' traceback into whatever the next test captures; after each test they write to the process's stderr."""
    yield
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        for handler in logging.getLogger(name).handlers if "lightning" in sys.modules else []:
            if type(handler) is logging.StreamHandler:
                handler.stream = sys.__stderr__  # not setStream: it would flush the closed stream first


@pytest.fixture(scope="session")
def sample_ssv2(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ssv2")
    make_sample_data(root, clips=24, with_broken=True, seed=0, workers=2)
    return root


@pytest.fixture(scope="session")
def clean_annotations(sample_ssv2, tmp_path_factory) -> Path:
    """The sample tree's label files without the broken entries (videos stay in `sample_ssv2/videos`)."""
    broken = json.loads((sample_ssv2 / "broken.json").read_text())
    clean = tmp_path_factory.mktemp("clean-annotations")
    for name in ("train", "validation", "test", "labels"):
        entries = json.loads(annotation_path(sample_ssv2 / "annotations", name).read_text())
        if name != "labels":
            entries = [entry for entry in entries if entry["id"] not in broken]
        annotation_path(clean, name).write_text(json.dumps(entries))
    return clean


@pytest.fixture(scope="session")
def built_shards(sample_ssv2, clean_annotations, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("shards")
    config = BuildConfig(annotations=clean_annotations, videos=sample_ssv2 / "videos", out=out,
                         splits=["train", "validation"], clips_per_shard=4, workers=2, max_error_rate=0.0)
    manifest, status = build(config, log=lambda message: None)
    assert status == 0 and manifest is not None
    return out


@pytest.fixture
def as_v1_export():
    """Copy an export and rewrite its config.json the way `hauwm pretrain export` wrote schema_version 1
    (before WorldModelConfig): the world_model keys flat at the top level."""

    def rewrite(export: Path, out: Path) -> Path:
        shutil.copytree(export, out)
        config = json.loads((out / "config.json").read_text())
        v1 = {"schema_version": 1, "kind": config["kind"], **config["world_model"]}
        v1 |= {key: config[key] for key in ("feature_dim", "image_shape", "normalisation", "provenance")}
        (out / "config.json").write_text(json.dumps(v1, indent=2) + "\n")
        return out

    return rewrite


@pytest.fixture
def damaged_in_place():
    def damage(checkpoint: Path, out: Path) -> str:
        data = bytearray(checkpoint.read_bytes())
        with zipfile.ZipFile(checkpoint) as archive:
            record = max(archive.infolist(), key=lambda info: info.file_size)
        header = record.header_offset  # a local file header: 30 bytes, then the name and the extra field
        start = header + 30 + int.from_bytes(data[header + 26:header + 28], "little") + \
            int.from_bytes(data[header + 28:header + 30], "little") + record.file_size // 2
        data[start:start + 8] = bytes.fromhex("0000803f0000803f")  # two float32 ones: finite, plausible
        out.write_bytes(bytes(data))
        return record.filename

    return damage
