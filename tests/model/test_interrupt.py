"""Ctrl-C during `hauwm pretrain fit`: Lightning stops the fit with sys.exit(1) and no checkpoint of its own; the
last line names the step reached and the checkpoint to resume from, with or without a progress bar, and the
command exits with 130. SIGTERM (a cluster's preemption): the fit writes last.ckpt at the step it stopped at (after
that step's validation, if it has one) and exits with 143. Checkpoints are written whole even where $TMPDIR is another filesystem."""

from __future__ import annotations

import errno
import multiprocessing
import os
import signal
import subprocess
import sys

import lightning
import pytest
import torch

from data_pipeline.dataset import LoaderError
from model.interrupt import ResumeNotice
from model.progress import StepProgressBar

from conftest import fit  # noqa: I001 (tests/model/conftest.py)
from test_progress import Regression


class CtrlC(lightning.Callback):
    """Ctrl-C before optimizer step 3 (as the Trainer's callback `test_interrupt.CtrlC`)."""

    def on_train_batch_start(self, trainer: lightning.Trainer, *_) -> None:
        if trainer.global_step == 3:
            raise KeyboardInterrupt


class DeadWorker(lightning.Callback):
    """A loader failure before optimizer step 3 (as the Trainer's callback `test_interrupt.DeadWorker`)."""

    def on_train_batch_start(self, trainer: lightning.Trainer, *_) -> None:
        if trainer.global_step == 3:
            raise LoaderError("DataLoader worker 0 (train split, pid 1) died while reading shard x.tar: killed")


class Sigterm(lightning.Callback):
    """SIGTERM to this process during optimizer step 3 (as the Trainer's callback `test_interrupt.Sigterm`)."""

    def on_train_batch_start(self, trainer: lightning.Trainer, *_) -> None:
        if trainer.global_step == 3:
            os.kill(os.getpid(), signal.SIGTERM)


class SigtermInAnEpochsLastStep(lightning.Callback):
    """SIGTERM to this process during optimizer step 6, the last of the first epoch in these tests (18 training clips,
    batches of 3; as the Trainer's callback `test_interrupt.SigtermInAnEpochsLastStep`)."""

    def on_train_batch_start(self, trainer: lightning.Trainer, *_) -> None:
        if trainer.global_step == 5:
            assert trainer.num_training_batches == 6
            os.kill(os.getpid(), signal.SIGTERM)


class SigtermToTheJob(lightning.Callback):
    """SIGTERM to this process and to every loader worker, from another process, as SLURM's `scancel` or a job's time
    limit sends it to each process of the job, at the first batch of step 4's validation (as the Trainer's callback
    `test_interrupt.SigtermToTheJob`)."""

    def on_validation_batch_start(self, trainer: lightning.Trainer, pl_module, batch, batch_idx: int, *_) -> None:
        if trainer.global_step == 4 and batch_idx == 0 and not trainer.sanity_checking:
            workers = [str(child.pid) for child in multiprocessing.active_children()]
            assert len(workers) == 3  # 2 train workers and 1 for the validation split (one shard)
            send = "import os, signal, sys; [os.kill(int(pid), signal.SIGTERM) for pid in sys.argv[1:]]"
            subprocess.run([sys.executable, "-c", send, *workers, str(os.getpid())], check=True)


@pytest.mark.parametrize("bar", [True, False], ids=["bar", "no-bar"])
def test_ctrl_c_names_the_checkpoint_to_resume_from(tmp_path, capsys, bar):
    checkpoints = lightning.pytorch.callbacks.ModelCheckpoint(tmp_path / "checkpoints", save_last=True,
                                                              every_n_train_steps=2)
    notice = ResumeNotice()
    trainer = lightning.Trainer(max_steps=10, accelerator="cpu", logger=False, enable_model_summary=False,
                                enable_progress_bar=bar, callbacks=[CtrlC(), checkpoints, notice]
                                + ([StepProgressBar()] if bar else []))
    with pytest.raises(SystemExit):
        trainer.fit(Regression())
    assert notice.exit_code == 130
    last = tmp_path / "checkpoints" / "last.ckpt"
    assert f"hauwm pretrain fit: interrupted at step 3; resume with --ckpt_path {last} (step 2, written " in \
        capsys.readouterr().err
    assert torch.load(last, weights_only=False)["global_step"] == 2


def test_ctrl_c_names_the_newest_checkpoint_of_several_model_checkpoints(tmp_path, capsys):
    """The notice read only the first ModelCheckpoint: with one that had written nothing yet before another that had,
    it said "no checkpoint was written yet" beside a last.ckpt to resume from."""
    rare = lightning.pytorch.callbacks.ModelCheckpoint(tmp_path / "rare", every_n_train_steps=100)
    frequent = lightning.pytorch.callbacks.ModelCheckpoint(tmp_path / "frequent", save_last=True, every_n_train_steps=2)
    trainer = lightning.Trainer(max_steps=10, accelerator="cpu", logger=False, enable_model_summary=False,
                                enable_progress_bar=False, callbacks=[CtrlC(), rare, frequent, ResumeNotice()])
    with pytest.raises(SystemExit):
        trainer.fit(Regression())
    last = tmp_path / "frequent" / "last.ckpt"
    assert f"interrupted at step 3; resume with --ckpt_path {last} (step 2, written " in capsys.readouterr().err


def test_the_cli_exits_130_and_says_so_before_any_checkpoint(built_shards, tmp_path, capsys):
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "10", "--trainer.callbacks+=test_interrupt.CtrlC") == 130
    assert capsys.readouterr().err.rstrip().endswith("interrupted at step 3; no checkpoint was written yet")


def test_a_fit_stopped_by_an_error_says_its_step_before_the_error(built_shards, tmp_path, capsys):
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "10", "--trainer.callbacks+=test_interrupt.DeadWorker") == 2
    lines = capsys.readouterr().err.rstrip().splitlines()
    assert lines[-2].endswith("hauwm pretrain fit: stopped by the error below at step 3; no checkpoint was written yet")
    assert lines[-1].startswith("hauwm pretrain fit: error: DataLoader worker 0 (train split, pid 1) died")


@pytest.mark.parametrize(("signal_at", "stop"), [("Sigterm", 4), ("SigtermInAnEpochsLastStep", 6)])
def test_sigterm_writes_the_checkpoint_of_the_step_it_stops_at_and_exits_143(built_shards, tmp_path, capsys,
                                                                              signal_at, stop):
    """Resumed, the fit goes on exactly as one never stopped: inside an epoch, and after an epoch's last step (where
    Lightning raises only after its end-of-epoch bookkeeping: a checkpoint written then skipped the next epoch)."""
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "10", f"--trainer.callbacks+=test_interrupt.{signal_at}") \
        == 143
    last = tmp_path / "checkpoints" / "last.ckpt"
    assert f"terminated (SIGTERM) at step {stop}; resume with --ckpt_path {last} (step {stop}, written " in \
        capsys.readouterr().err
    assert torch.load(last, weights_only=False)["global_step"] == stop
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "9", "--ckpt_path", "last") == 0  # and it resumes
    assert fit(built_shards, tmp_path / "unbroken", "--trainer.max_steps", "9") == 0  # as a fit never stopped
    resumed, unbroken = (torch.load(root / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
                         for root in (tmp_path, tmp_path / "unbroken"))
    assert resumed.keys() == unbroken.keys() and all(torch.equal(resumed[key], unbroken[key]) for key in resumed)


def test_a_sigterm_handler_the_process_had_before_the_fit_still_runs(built_shards, tmp_path, capsys):
    """A launcher's or a user's own SIGTERM handler (submitit requeues a job from one) is called too, as Lightning's
    handler calls it, and the fit still stops with its checkpoint."""
    calls = []

    def own_handler(signum, frame):
        calls.append(signum)

    before = signal.signal(signal.SIGTERM, own_handler)
    try:
        sigterm_at_step_3 = "--trainer.callbacks+=test_interrupt.Sigterm"
        assert fit(built_shards, tmp_path, "--trainer.max_steps", "10", sigterm_at_step_3) == 143
        assert signal.getsignal(signal.SIGTERM) is own_handler  # in place again after the fit
    finally:
        signal.signal(signal.SIGTERM, before)
    assert calls == [signal.SIGTERM]
    assert "terminated (SIGTERM) at step 4; resume with --ckpt_path " in capsys.readouterr().err


def test_sigterm_before_a_step_that_validates_lets_it_validate_and_writes_its_checkpoint(built_shards, tmp_path,
                                                                                        capsys):
    """Lightning's own handler raised inside the validation of step 4 (after its first of 2 batches), where no
    checkpoint is written; the checkpoint is step 4's, written at its end (before its validation)."""
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "10", "--trainer.val_check_interval", "4",
               "--data.val_batches", "2", "--trainer.callbacks+=test_interrupt.Sigterm") == 143
    last = tmp_path / "checkpoints" / "last.ckpt"
    assert f"terminated (SIGTERM) at step 4; resume with --ckpt_path {last} (step 4, written " in capsys.readouterr().err
    assert torch.load(last, weights_only=False)["global_step"] == 4


def test_sigterm_to_the_whole_job_during_a_validation_lets_it_finish_with_its_workers(built_shards, tmp_path, capsys):
    """The workers got the job's SIGTERM too: they end only with the training process (a SIGTERM from it, or its
    death), so the validation under way still gets its batches, and the fit stops after the next step (the signal
    came after step 4's agreement). Before, they died of it, and the fit ended with exit status 2 ("DataLoader worker
    0 (validation split) died … killed by signal 15") and no checkpoint of the step it stopped at."""
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "10", "--trainer.val_check_interval", "4",
               "--data.num_workers", "2", "--data.val_batches", "8", "--data.batch_size", "2",
               "--trainer.callbacks+=test_interrupt.SigtermToTheJob") == 143
    last = tmp_path / "checkpoints" / "last.ckpt"
    assert f"terminated (SIGTERM) at step 5; resume with --ckpt_path {last} (step 5, written " in capsys.readouterr().err
    assert torch.load(last, weights_only=False)["global_step"] == 5
    assert not multiprocessing.active_children()  # every worker ended with the fit


def test_a_checkpoint_is_written_whole_beside_the_old_one_then_renamed(tmp_path, monkeypatch):
    from model.checkpointing import AtomicCheckpointIO

    path = tmp_path / "checkpoints" / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint({"global_step": 1}, path)
    seen = []

    def replace(source, target):  # the moment before the new checkpoint takes the old one's name
        seen.append((os.path.dirname(source), torch.load(target, weights_only=False)["global_step"]))
        os.rename(source, target)

    monkeypatch.setattr(os, "replace", replace)
    AtomicCheckpointIO().save_checkpoint({"global_step": 2}, path)
    assert seen == [(str(path.parent), 1)]  # written in the checkpoint's own directory; the old one whole till then
    assert torch.load(path, weights_only=False)["global_step"] == 2 and os.listdir(path.parent) == ["last.ckpt"]


def test_a_checkpoint_write_stopped_by_a_full_disk_says_so_in_one_line(tmp_path, monkeypatch, capsys):
    """torch's zip writer turns the OSError of a full disk into a RuntimeError ("unexpected pos"), which `hauwm` did
    not take for a full disk: a 70-line traceback and exit status 1."""
    from hauwm.cli import main
    from model.checkpointing import AtomicCheckpointIO

    path = tmp_path / "checkpoints" / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint({"global_step": 1}, path)

    def full_disk(obj, file):
        file.write(b"PK" * 50)
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError:
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 3629504 vs 3629396")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(OSError) as raised:
        AtomicCheckpointIO().save_checkpoint({"global_step": 2}, path)
    assert raised.value.errno == errno.ENOSPC and raised.value.filename == str(path)
    assert os.listdir(path.parent) == ["last.ckpt"] and torch.load(path, weights_only=False)["global_step"] == 1

    class Stage:  # a stage whose fit fails so
        @staticmethod
        def main(argv):
            AtomicCheckpointIO().save_checkpoint({"global_step": 2}, path)

    monkeypatch.setattr("importlib.import_module", lambda name: Stage)
    assert main(["pretrain", "fit"]) == 2
    assert capsys.readouterr().err.strip() == (f"hauwm pretrain: error: no space left on the device while writing {path}: "
                                               "free some space, then run the same command again (a fit goes on from "
                                               "its last checkpoint with --ckpt_path last; an export or analysis "
                                               "starts anew)")


def test_a_checkpoint_write_stopped_by_ctrl_c_leaves_the_old_one_and_nothing_beside_it(tmp_path, monkeypatch):
    """A Ctrl-C (or a full disk) in the middle of the write left `.last.ckpt.partial` in the checkpoint directory."""
    from model.checkpointing import AtomicCheckpointIO

    path = tmp_path / "checkpoints" / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint({"global_step": 1}, path)
    save = torch.save

    def interrupted(obj, file):
        save(obj, file)
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        AtomicCheckpointIO().save_checkpoint({"global_step": 2}, path)
    assert os.listdir(path.parent) == ["last.ckpt"] and torch.load(path, weights_only=False)["global_step"] == 1
