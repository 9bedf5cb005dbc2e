"""A loader worker that fails stops the run with a `LoaderError` naming the worker, the shard it was reading and
the likely cause — never a hang, never torch's bare traceback — and the checkpoints written before stay loadable."""

import json
import multiprocessing
import os
import shutil
import signal
import tarfile
import threading
import time
from pathlib import Path

import lightning
import pytest
import torch

from data_pipeline import SetEpoch, ShardDataModule
from data_pipeline.dataloader import make_dataloader
from data_pipeline.dataset import LoaderError, SequenceDataset, shard_set
from data_pipeline.shard_format import add_clip, open_writer

from test_loader import RecordingModel  # noqa: I001 (tests/data_pipeline/test_loader.py)

pytestmark = pytest.mark.timeout(180)
TINY_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "pretrain" / "tiny.yaml"


def copy_with_broken_shard(built_shards, tmp_path, break_shard) -> tuple:
    """A copy of the shard directory whose train-000001.tar `break_shard(path)` rewrites, its manifest listing the
    new file's size (as if damaged where its size does not show: what the loader finds only when it reads it)."""
    copy = tmp_path / "shards"
    shutil.copytree(built_shards, copy)
    broken = copy / "train-000001.tar"
    broken.chmod(0o644)
    break_shard(broken)
    edit_manifest_entry(copy, broken.name, bytes=broken.stat().st_size if broken.exists() else 0)
    return copy, broken


def edit_manifest_entry(shards: Path, name: str, **changes) -> None:
    """Change the manifest's entry of shard `name`."""
    manifest = json.loads((shards / "manifest.json").read_text())
    for split in manifest["splits"].values():
        for entry in split["shards"]:
            if entry["name"] == name:
                entry.update(changes)
    (shards / "manifest.json").write_text(json.dumps(manifest))


def truncate(shard) -> None:
    shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 3])  # cut inside a member


def rewrite_clips(shard, change) -> None:
    """Rewrite the shard with `change(index, metadata, frames) -> (metadata, frames)` applied to each clip."""
    with tarfile.open(shard) as tar:
        members = [tar.extractfile(member).read() for member in tar]  # per clip: <id>.jpgs, then <id>.json
    with open(shard, "wb") as file, open_writer(file) as tar:
        for index, (frames, metadata) in enumerate(zip(members[0::2], members[1::2])):
            add_clip(tar, *change(index, json.loads(metadata), frames), "jpgs")


def garble_frames(shard) -> None:
    """Replace the JPEGs of every clip of the shard by zeros, keeping each frames member's table of lengths."""
    def zeroed(index, metadata, frames):
        table = 4 * (int.from_bytes(frames[:4], "little") + 1)
        return metadata, frames[:table] + bytes(len(frames) - table)

    rewrite_clips(shard, zeroed)


@pytest.mark.parametrize("workers", [2, 0])
def test_an_unreadable_shard_is_named_with_the_worker(built_shards, tmp_path, workers):
    shards, broken = copy_with_broken_shard(built_shards, tmp_path, truncate)
    dataset = SequenceDataset(shard_set(shards, "train"), batch_size=2, seq_len=8, num_workers=workers)
    with pytest.raises(LoaderError) as failure:
        list(make_dataloader(dataset))
    message = str(failure.value)
    who = r"DataLoader worker [01] \(train split, pid \d+\)" if workers else "the loader"
    assert failure.match(rf"^{who}, reading shard {broken}: {broken} is not a readable shard .*--verify")
    assert "Traceback" not in message


def test_frames_that_do_not_decode_name_the_clip_and_its_shard(built_shards, tmp_path):
    shards, broken = copy_with_broken_shard(built_shards, tmp_path, garble_frames)
    dataset = SequenceDataset(shard_set(shards, "train"), batch_size=2, seq_len=8, num_workers=2)
    loader = make_dataloader(dataset)
    with pytest.raises(LoaderError, match=rf"DataLoader worker [01] \(train split, pid \d+\), reading shard .*: clip \S+ of shard "
                                          rf"{broken}: its frames do not decode \(ValueError: .*--verify"):
        for epoch in range(3):  # an epoch may leave out the shard's clips
            dataset.set_epoch(epoch)
            list(loader)


def empty(shard) -> None:
    with open(shard, "wb") as file, open_writer(file):
        pass


def drop_num_frames(shard) -> None:
    """Rewrite the shard with its first clip's metadata lacking `num_frames`."""
    def without(index, metadata, frames):
        return ({key: value for key, value in metadata.items() if index or key != "num_frames"}, frames)

    rewrite_clips(shard, without)


@pytest.mark.parametrize("workers", [0, 2])
def test_a_shard_with_fewer_clips_than_the_manifest_says_is_an_error_not_a_hang(built_shards, tmp_path, workers):
    shards, broken = copy_with_broken_shard(built_shards, tmp_path, empty)
    dataset = SequenceDataset(shard_set(shards, "train"), batch_size=2, seq_len=8, num_workers=workers)
    with pytest.raises(LoaderError, match=rf"shards are not the ones manifest.json describes .* clips of at least "
                                          rf"seq_len=8 frames: {broken} gave 0 where the manifest counts [1-9]; check .*--verify"):
        for epoch in range(4):  # every epoch that needs a second pass over the emptied shard's stream finds out
            dataset.set_epoch(epoch)
            list(make_dataloader(dataset))


@pytest.mark.parametrize("damage", ["another shard in its place", "a partial copy"])
def test_a_shard_of_another_size_than_the_manifest_lists_is_named_before_any_worker_starts(built_shards, tmp_path,
                                                                                           damage):
    """A train shard copied over a validation one (more clips than the manifest counts) was read as validation data
    without a word; a partial copy was met by a worker, possibly hours into the fit."""
    shards = shutil.copytree(built_shards, tmp_path / "shards")
    shard = shards / "validation-000000.tar"
    shard.chmod(0o644)
    listed = shard.stat().st_size
    if damage == "a partial copy":
        shard.write_bytes(shard.read_bytes()[: listed // 2])
    else:
        largest = max(shards.glob("train-*.tar"), key=lambda train: train.stat().st_size)
        shard.write_bytes(largest.read_bytes())
        assert shard.stat().st_size != listed
    with pytest.raises(LoaderError, match=rf"^1 of the \d+ validation shards listed in {shards / 'manifest.json'} are "
                                          rf"not the files it lists, e.g. {shard}: {shard.stat().st_size} bytes, listed "
                                          rf"as {listed} \(a partial copy, or another shard in its place\); check"):
        shard_set(shards, "validation")


def test_a_shard_with_more_clips_than_the_manifest_says_is_an_error(built_shards, tmp_path):
    """A shard of the size listed (a tar's size steps by 10 KiB) but other clips, more of them: read without a word.
    Found at the end of a pass over the stream's shards (with 2 streams, within the first epochs)."""
    shards = shutil.copytree(built_shards, tmp_path / "shards")
    name = "train-000001.tar"
    entry = next(entry for entry in json.loads((shards / "manifest.json").read_text())["splits"]["train"]["shards"]
                 if entry["name"] == name)
    frames, clips = max(entry["frame_counts"].items())
    counts = {**entry["frame_counts"], frames: clips - 1, "3": 1}  # one clip listed as too short for seq_len 8
    edit_manifest_entry(shards, name, frame_counts={key: n for key, n in counts.items() if n})
    dataset = SequenceDataset(shard_set(shards, "train"), batch_size=2, seq_len=8, num_workers=2)
    with pytest.raises(LoaderError, match=rf"shards are not the ones manifest.json describes .* clips of at least "
                                          rf"seq_len=8 frames: {shards / name} gave (\d+) where the manifest counts "
                                          rf"(?!\1)\d+; check .*--verify"):
        for epoch in range(4):
            dataset.set_epoch(epoch)
            list(make_dataloader(dataset))


def test_a_clip_without_its_metadata_is_named_with_its_own_shard(built_shards, tmp_path):
    shards, broken = copy_with_broken_shard(built_shards, tmp_path, drop_num_frames)
    dataset = SequenceDataset(shard_set(shards, "train"), batch_size=2, seq_len=8, num_workers=0)
    with pytest.raises(LoaderError, match=rf"clip \S+ of shard {broken}: not a HAUWM clip \(KeyError: 'num_frames'\)"):
        for epoch in range(3):
            dataset.set_epoch(epoch)
            list(dataset)


def test_a_worker_that_stalls_is_reported_after_the_timeout(built_shards):
    slow = shard_set(built_shards, "train", shard_url=f"pipe:sleep 4; cat {built_shards}/{{name}}")
    dataset = SequenceDataset(slow, batch_size=2, seq_len=8, num_workers=2)
    batches = iter(make_dataloader(dataset, timeout=1))
    deadline = time.monotonic() + 60  # on a busy machine a worker may take over a second to start
    while dataset.reading(0) == "(none yet)" and time.monotonic() < deadline:
        time.sleep(0.05)
    with pytest.raises(LoaderError, match=r"no batch came from the DataLoader workers for 1 s \(worker 0 reading "
                                          r"shard pipe:sleep 4; .*--data.timeout.*--ckpt_path"):
        next(batches)


def test_a_worker_killed_between_epochs_is_named_when_the_next_epoch_starts(built_shards):
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=2)
    loader = make_dataloader(dataset)
    before = {process.pid for process in multiprocessing.active_children()}
    list(loader)
    victim = min({process.pid for process in multiprocessing.active_children()} - before)
    os.kill(victim, signal.SIGKILL)
    dataset.set_epoch(1)
    with pytest.raises(LoaderError, match=rf"^DataLoader worker [01] \(train split, pid {victim}\) died while reading shard "):
        list(loader)


def test_a_killed_validation_worker_is_named_with_its_split(built_shards):
    dataset = SequenceDataset(shard_set(built_shards, "validation"), batch_size=2, seq_len=8, num_workers=1,
                              shuffle=False, batches_per_worker=2)
    loader = make_dataloader(dataset)
    before = {process.pid for process in multiprocessing.active_children()}
    list(loader)
    victim = min({process.pid for process in multiprocessing.active_children()} - before)
    os.kill(victim, signal.SIGKILL)
    with pytest.raises(LoaderError, match=rf"^DataLoader worker 0 \(validation split, pid {victim}\) died while "
                                          r"reading shard \S+validation-\d+\.tar"):
        list(loader)


def test_a_worker_killed_while_the_trainer_waits_for_it_is_named_at_once(built_shards):
    """Not after the loader's 600 s timeout: the death itself interrupts the wait."""
    slow = shard_set(built_shards, "train", shard_url=f"pipe:sleep 3; cat {built_shards}/{{name}}")
    dataset = SequenceDataset(slow, batch_size=2, seq_len=8, num_workers=2)
    before = {process.pid for process in multiprocessing.active_children()}
    batches = iter(make_dataloader(dataset))
    victim = min({process.pid for process in multiprocessing.active_children()} - before)
    threading.Timer(0.5, os.kill, (victim, signal.SIGKILL)).start()
    started = time.monotonic()
    with pytest.raises(LoaderError, match=rf"^DataLoader worker [01] \(train split, pid {victim}\) died .*killed by SIGKILL"):
        next(batches)
    assert time.monotonic() - started < 60


def close_files_then_die() -> None:
    os.closerange(3, 65536)  # the sentinel's write end too: the process reads "ended" while it still runs
    time.sleep(1.0)
    os.kill(os.getpid(), signal.SIGKILL)


def test_a_worker_whose_files_closed_before_it_ended_is_named(built_shards):
    """A killed process closes its files (the batch connections, its sentinel) before it becomes a zombie that
    `is_alive()` sees. Receiving a batch then fails with a reset connection while the worker still counts as
    alive: the loader waits for the end, and reports the death, not the bare ConnectionResetError."""
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=1)
    loader = make_dataloader(dataset)
    dying = multiprocessing.get_context("fork").Process(target=close_files_then_die)
    dying.start()
    loader._worker_processes = lambda: [dying]  # as if it were the iterator's worker 0
    report = loader._failure_report(ConnectionResetError(104, "Connection reset by peer"))
    assert report is not None and report.startswith(f"DataLoader worker 0 (train split, pid {dying.pid}) died while reading "
                                                    f"shard (none yet): killed by SIGKILL")


class KillWorker(lightning.Callback):
    """Kills one of the fit's loader workers with `signum` after training step `step`."""

    def __init__(self, step: int, signum: int):
        self.step, self.signum, self.pid = step, signum, None

    def on_fit_start(self, trainer, pl_module):
        self.before = {process.pid for process in multiprocessing.active_children()}  # left by earlier tests

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == self.step and self.pid is None:
            self.pid = min({process.pid for process in multiprocessing.active_children()} - self.before)
            os.kill(self.pid, self.signum)


@pytest.mark.parametrize("signum, cause", [(signal.SIGKILL, "SIGKILL, most likely by the kernel's out-of-memory"),
                                           (signal.SIGBUS, "SIGBUS: the shared memory .* \\(/dev/shm\\) is full")])
def test_a_killed_worker_stops_the_fit_with_its_shard_and_cause_and_the_checkpoint_loads(
        built_shards, tmp_path, signum, cause):
    data = ShardDataModule(str(built_shards), batch_size=2, seq_len=8, num_workers=2, seed=1)
    kill = KillWorker(step=3, signum=signum)
    checkpoint = lightning.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path, save_last=True, every_n_train_steps=2)
    trainer = lightning.Trainer(max_steps=200, accelerator="cpu", devices=1, logger=False, enable_progress_bar=False,
                                callbacks=[SetEpoch(), kill, checkpoint], limit_val_batches=0,
                                num_sanity_val_steps=0, enable_model_summary=False)
    with pytest.raises(LoaderError) as failure:
        trainer.fit(RecordingModel(), datamodule=data)
    urls = "|".join(shard_set(built_shards, "train").urls)
    assert failure.match(rf"^DataLoader worker [01] \(train split, pid {kill.pid}\) died while reading shard ({urls}): killed by "
                         rf"{cause}.*resume with `--ckpt_path")
    assert "Traceback" not in str(failure.value)
    saved = torch.load(tmp_path / "last.ckpt", weights_only=False)
    assert saved["global_step"] >= 2 and saved["global_step"] % 2 == 0
    assert trainer.global_step < 200


def test_the_cli_prints_a_worker_failure_without_a_traceback(built_shards, tmp_path, capsys):
    from model.cli import main

    shards, broken = copy_with_broken_shard(built_shards, tmp_path, truncate)
    status = main(["fit", "--config", str(TINY_CONFIG), "--data.shards", str(shards), "--data.batch_size", "2",
                   "--data.seq_len", "8", "--data.num_workers", "2", "--trainer.max_steps", "4",
                   "--trainer.limit_val_batches", "0", "--trainer.enable_progress_bar", "false",
                   "--trainer.enable_model_summary", "false", "--trainer.default_root_dir", str(tmp_path / "run")])
    error = capsys.readouterr().err
    assert status == 2
    assert "hauwm pretrain fit: error: DataLoader worker" in error and f"reading shard {broken}" in error
    assert "Traceback" not in error


def test_a_shard_missing_from_the_directory_is_named_before_any_worker_starts(built_shards, tmp_path):
    """A deleted tar was met by a worker in the middle of an epoch, as a bare FileNotFoundError."""
    shards, broken = copy_with_broken_shard(built_shards, tmp_path, lambda shard: shard.unlink())
    with pytest.raises(LoaderError, match=rf"^1 of the \d+ train shards listed in {shards / 'manifest.json'} are "
                                          rf"missing, e.g. {broken}: copy them back, or check the shards with"):
        shard_set(shards, "train")
