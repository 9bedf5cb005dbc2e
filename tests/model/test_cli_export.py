"""`hauwm pretrain fit | export | analyze` on the built-in data: training lowers the loss, the export
reproduces the trained module without unpickling, bad settings fail with clear messages."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
import re
import shutil
import warnings
from pathlib import Path

import lightning
import pytest
import torch
import yaml
from safetensors.torch import load_file, save_file
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from hauwm.pid_lock import pid_lock
from model.cli import main
from model.export import ExportError, FrozenWorldModel, load_frozen
from model.module import PretrainModule
from model.rssm import RSSMState

from conftest import RUN_ARGS, RUN_STEPS, SMALL, TINY_CONFIG, TINY_SIZES, fit, make_batch  # noqa: I001 (tests/model/conftest.py)


def scalars(run, tag: str) -> list[float]:
    events = EventAccumulator(str(next((run / "lightning_logs").glob("version_*"))), size_guidance={"scalars": 0})
    events.Reload()
    return [event.value for event in events.Scalars(tag)]


def test_a_few_steps_of_tiny_lower_the_loss(tiny_run):
    losses = scalars(tiny_run, "train/loss")
    assert len(losses) == RUN_STEPS
    assert sum(losses[-5:]) / 5 < 0.7 * sum(losses[:5]) / 5


def test_every_loss_term_and_lambda_is_logged_every_step(tiny_run):
    for tag in ("recon_nll", "kl", "kl_balanced", "hcu", "disagreement", "lambda", "log_lambda", "grad_norm",
                "scaler_skips", "nonfinite_steps"):
        assert len(scalars(tiny_run, f"train/{tag}")) == RUN_STEPS, tag
    assert scalars(tiny_run, "train/scaler_skips")[-1] == scalars(tiny_run, "train/nonfinite_steps")[-1] == 0
    for k in range(1, 6):  # validation per gap k
        assert scalars(tiny_run, f"val/disagreement_k{k}")
    assert scalars(tiny_run, "val/spearman_k_disagreement")


def test_the_export_records_the_median_length_of_the_clips_trained_on(built_shards, tiny_export):
    """provenance.train_clip_length: the median frame count of the train clips with ≥ seq_len (8) frames, from the
    manifest's per-shard counts; fine-tuning's k = 1 embedding takes it as T."""
    shards = json.loads((built_shards / "manifest.json").read_text())["splits"]["train"]["shards"]
    lengths = sorted(int(frames) for shard in shards for frames, n in shard["frame_counts"].items()
                     for _ in range(n) if int(frames) >= 8)
    middle = len(lengths) // 2
    median = lengths[middle] if len(lengths) % 2 else (lengths[middle - 1] + lengths[middle]) / 2
    assert load_frozen(tiny_export).export_config["provenance"]["train_clip_length"] == median


def test_export_reproduces_the_trained_module(tiny_run, tiny_export, fake_batch):
    module = PretrainModule.load_from_checkpoint(tiny_run / "checkpoints" / "last.ckpt", map_location="cpu").eval()
    frozen = load_frozen(tiny_export)
    assert isinstance(frozen, FrozenWorldModel) and not frozen.training
    assert not any(p.requires_grad for p in frozen.parameters())
    config = frozen.export_config
    assert config["schema_version"] == 2 and config["world_model"] == frozen.config.to_dict() == module.world_model.config.to_dict()
    assert frozen.config.ensemble == 7 and frozen.config.temporal_mode == "relative"
    assert config["normalisation"]["offset"] == -0.5 and config["provenance"]["global_step"] == RUN_STEPS
    with torch.no_grad():
        outputs = []
        for world_model in (module.world_model, frozen):
            noise = world_model.rssm.draw_noise(*fake_batch["gaps"].shape, generator=torch.Generator().manual_seed(3))
            obs = world_model.observe(fake_batch["frames"], fake_batch["gaps"], fake_batch["num_frames"], noise)
            outputs.append((obs.prior_mean, obs.post_mean, world_model.decode(RSSMState(obs.deter, obs.stoch))))
    for trained, exported in zip(*outputs):
        assert torch.equal(trained, exported)


def test_export_loads_without_unpickling(tiny_export, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("load_frozen must not unpickle")

    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(pickle, "Unpickler", refuse)
    monkeypatch.setattr(torch, "load", refuse)
    assert load_frozen(tiny_export).rssm.ensemble == 7


def test_export_errors_are_clear(tiny_export, tmp_path):
    with pytest.raises(ExportError, match="not a HAUWM export.*hauwm pretrain export"):
        load_frozen(tmp_path)
    with pytest.raises(ExportError, match=rf"config.json is a file: an export is the directory .* \(e.g. "
                                          rf"{re.escape(str(tiny_export))}\)"):  # ".../config.json/config.json not found"
        load_frozen(tiny_export / "config.json")
    (tmp_path / "last.ckpt").write_bytes(b"a checkpoint")  # was told to pass its directory, RUN/checkpoints
    with pytest.raises(ExportError, match=rf"{re.escape(str(tmp_path / 'last.ckpt'))} is a checkpoint of `hauwm "
                                          r"pretrain fit`, not an export: make one with `hauwm pretrain export"):
        load_frozen(tmp_path / "last.ckpt")
    wrong_version = tmp_path / "v2"
    shutil.copytree(tiny_export, wrong_version)
    config = json.loads((wrong_version / "config.json").read_text())
    (wrong_version / "config.json").write_text(json.dumps({**config, "schema_version": 3}))
    with pytest.raises(ExportError, match=r"schema_version 3, this code reads versions \(1, 2\); re-export"):
        load_frozen(wrong_version)
    wrong_shape = tmp_path / "shape"
    shutil.copytree(tiny_export, wrong_shape)
    wider = {**config["world_model"], "deter": config["world_model"]["deter"] + 8}
    (wrong_shape / "config.json").write_text(json.dumps({**config, "world_model": wider}))
    with pytest.raises(ExportError, match=r"does not match .*config.json.*rssm\.cell"):
        load_frozen(wrong_shape)
    (wrong_shape / "weights.safetensors").unlink()
    with pytest.raises(ExportError, match="weights.safetensors not found"):
        load_frozen(wrong_shape)
    diverged = tmp_path / "diverged"
    shutil.copytree(tiny_export, diverged)
    tensors = load_file(diverged / "weights.safetensors")
    name = sorted(tensors)[0]
    tensors[name].view(-1)[0] = float("nan")
    save_file(tensors, diverged / "weights.safetensors")
    config = json.loads((diverged / "config.json").read_text())  # its checksum recorded with the NaN: found by value
    digest = hashlib.sha256((diverged / "weights.safetensors").read_bytes()).hexdigest()
    (diverged / "config.json").write_text(json.dumps({**config, "weights_sha256": digest}))
    with pytest.raises(ExportError, match=rf"weights.safetensors: {re.escape(name)} holds NaN or inf \(1 tensors do\): "
                                          "the checkpoint it was exported from had diverged"):
        load_frozen(diverged)
    edited = tmp_path / "edited"
    shutil.copytree(tiny_export, edited)
    for key, value, wanted in (("k_max", "5", "a whole number ≥ 1"), ("lambda_init", "1.0", "a number"),
                               ("hcu", 1, "true or false")):  # each was a TypeError or ValueError in `analyze`
        provenance = {**config["provenance"], key: value}
        (edited / "config.json").write_text(json.dumps({**config, "provenance": provenance}))
        with pytest.raises(ExportError, match=rf"config.json: provenance.{key} is {json.dumps(value)}, not {wanted}; "
                                              "re-export the checkpoint"):
            load_frozen(edited)


def test_a_version_1_export_still_loads(tiny_export, as_v1_export, tmp_path, fake_batch):
    old = as_v1_export(tiny_export, tmp_path / "v1")
    frozen, reference = load_frozen(old), load_frozen(tiny_export)
    assert frozen.export_config["schema_version"] == 1 and frozen.config == reference.config
    assert frozen.export_config["world_model"] == reference.export_config["world_model"]  # handed back as version 2
    with torch.no_grad():
        noise = reference.rssm.draw_noise(*fake_batch["gaps"].shape, generator=torch.Generator().manual_seed(3))
        means = [model.observe(fake_batch["frames"], fake_batch["gaps"], fake_batch["num_frames"], noise).prior_mean
                 for model in (frozen, reference)]
    assert torch.equal(*means)
    config = json.loads((old / "config.json").read_text())
    del config["temporal_dim"]
    (old / "config.json").write_text(json.dumps(config))
    with pytest.raises(ExportError, match=r"v1/config.json: world_model lacks \['temporal_dim'\]; re-export"):
        load_frozen(old)


def test_checkpoint_hyper_parameters_are_plain_data(tiny_run):
    state = torch.load(tiny_run / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    assert state["hyper_parameters"]["world_model"] == TINY_SIZES.to_dict()


def flat_checkpoint(tiny_run, path):
    """tiny_run's last.ckpt with the hyper_parameters `hauwm pretrain fit` wrote before WorldModelConfig (flat)."""
    state = torch.load(tiny_run / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    hparams = dict(state["hyper_parameters"])
    state["hyper_parameters"] = {**hparams.pop("world_model"), **hparams}
    torch.save(state, path)
    return path


def test_an_old_checkpoint_with_flat_sizes_still_exports(tiny_run, tiny_export, tmp_path, capsys):
    old = flat_checkpoint(tiny_run, tmp_path / "flat.ckpt")
    assert main(["export", str(old), "--out", str(tmp_path / "export")]) == 0
    assert "M=7" in capsys.readouterr().out
    exported, reference = load_frozen(tmp_path / "export"), load_frozen(tiny_export)
    assert exported.config == reference.config
    assert all(torch.equal(exported.state_dict()[name], t) for name, t in reference.state_dict().items())


def test_an_old_checkpoint_with_flat_sizes_is_not_resumed_silently(built_shards, tiny_run, tmp_path, capsys):
    old = flat_checkpoint(tiny_run, tmp_path / "flat.ckpt")
    assert fit(built_shards, tmp_path / "run", "--ckpt_path", str(old)) == 2
    err = capsys.readouterr().err
    assert "keeps the model sizes flat" in err and "hauwm pretrain export" in err and "Traceback" not in err
    assert fit(built_shards, tmp_path / "run", "--model.world_model.deter", "48", "--ckpt_path", str(old)) == 2
    assert "different model size (deter: checkpoint 64 vs this run 48)" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--model.world_model.ensemble", "1"], "HCU needs an ensemble of at least 2 heads"),
        (["--model.world_model.temporal_dim", "7"], "world_model.temporal_dim must be even"),
        (["--data.k_max", "0"], "k_max (the largest frame gap) must be ≥ 1, got 0"),
        (["--data.seq_len", "1"], "--data.seq_len must be at least 2"),
        (["--model.lr", "-1"], "model.lr must be positive"),
        (["--trainer.max_steps", "1", "--data.shards", "/nonexistent/shards"], "/nonexistent/shards does not exist"),
        (["--trainer.precision", "bf16-true"], "--trainer.precision bf16-true: a fit runs in 32-true, 16-mixed, bf16-mixed"),
        # no precision is Lightning's 32-true
        (["--trainer.precision", "null", "--data.k_max", "0"], "k_max (the largest frame gap) must be ≥ 1, got 0"),
        (["--trainer.accumulate_grad_batches", "2"], "accumulate_grad_batches 2: the step optimises by itself"),
        (["--trainer.gradient_clip_val", "1"], "the step clips its own gradients: set --model.grad_clip"),
        # Lightning refused it beside the precision in a traceback ("Received both `precision=32-true` and `plugins=")
        (["--trainer.plugins", "MixedPrecision", "--trainer.plugins.precision", "16-mixed", "--trainer.plugins.device",
          "cpu"], "--trainer.plugins MixedPrecision: a fit's precision plugin is the one --trainer.precision makes"),
        # Lightning divides by these after the first step (ZeroDivisionError), or refuses them in a traceback
        (["--trainer.val_check_interval", "0"], "--trainer.val_check_interval 0: validate every N >= 1 training steps"),
        (["--trainer.check_val_every_n_epoch", "0"], "--trainer.check_val_every_n_epoch 0: validate every N >= 1"),
        (["--trainer.max_steps", "-5"], "a --trainer setting Lightning refuses: `max_steps` must be a non-negative"),
        (["--trainer.devices", "0"], "a --trainer setting Lightning refuses: `Trainer(devices='0')` value is not"),
        (["--ckpt_path", "/"], "--ckpt_path / is a directory: pass a checkpoint file"),
        (["--trainer.limit_train_batches", "0"], "--trainer.limit_train_batches 0: the fit would train nothing"),
        (["--trainer.max_epochs", "0"], "--trainer.max_epochs 0: the fit would train nothing"),  # it ended at once, 0
        (["--trainer.max_steps", "0"], "--trainer.max_steps 0: the fit would train nothing"),
        (["--ckpt_path", "/nonexistent/last.ckpt"], "--ckpt_path /nonexistent/last.ckpt does not exist: pass a"),
        # it trained, but a SIGTERM killed it without last.ckpt, and Ctrl-C's notice said "at step 0"
        (["--trainer.strategy", "ddp_spawn"], "--trainer.strategy ddp_spawn: ranks started by Python's multiprocessing"),
        # Lightning's seed_everything raised numpy's ValueError in a traceback
        (["--seed_everything", "4294967296"], "seed_everything 4294967296: a seed is a whole number from 0 to 4294967295"),
        (["--seed_everything", "-1"], "seed_everything -1: a seed is a whole number from 0 to 4294967295"),
        # the memory estimate ran these through the model first: a traceback from deep inside torch
        (["--data.seq_len", "0"], "--data.seq_len must be at least 2 (a sequence must hold a gap k"),
        (["--data.batch_size", "-1"], "--data.batch_size must be at least 1, got -1"),
        (["--model.world_model.deter", str(2**40)], "needs at least 2^63 bytes of memory"),  # torch's size overflowed
    ],
)
def test_bad_configurations_are_refused_before_training(built_shards, tmp_path, capsys, flags, message):
    assert fit(built_shards, tmp_path, *flags) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "checkpoints").exists()


def test_shared_memory_too_small_for_the_loader_is_refused_in_one_line(built_shards, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("data_pipeline.dataset.shared_memory_free", lambda: 2**19)
    assert fit(built_shards, tmp_path, "--data.num_workers", "1", "--trainer.max_steps", "1") == 2
    err = capsys.readouterr().err
    assert "/dev/shm has 0 MiB free: in Docker run with --shm-size" in err and "Traceback" not in err
    assert not (tmp_path / "checkpoints").exists()


def test_a_world_model_too_large_for_the_memory_is_refused_before_it_is_built(built_shards, tmp_path, capsys,
                                                                              monkeypatch):
    monkeypatch.setattr("hauwm.memory.memory_available", lambda: 2**30)  # the kernel's OOM killer ended it (exit 137)
    assert fit(built_shards, tmp_path, "--model.world_model.ensemble", "20000", "--trainer.max_steps", "1") == 2
    err = capsys.readouterr().err
    assert "more than the 1.0 GiB available: lower model.world_model's sizes (ensemble 20000;" in err
    assert "batch_size 3 × seq_len 8" in err and "Traceback" not in err
    assert not (tmp_path / "checkpoints").exists() and not (tmp_path / "lightning_logs").exists()
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "1") == 0  # tiny.yaml's sizes fit in it


def test_no_shard_directory_and_an_optimizer_flag_are_refused_in_one_line(capsys):
    assert main(["fit", "--config", str(TINY_CONFIG)]) == 2  # every config leaves data.shards to the command line
    err = capsys.readouterr().err
    assert "no shard directory: pass --data.shards DIR" in err and "Traceback" not in err
    # the module runs its own two Adams: LightningCLI's --optimizer / --lr_scheduler would crash the fit's first step
    assert main(["fit", "--config", str(TINY_CONFIG), "--optimizer", "torch.optim.SGD"]) == 2
    assert "optimizer: the module optimises with its own two Adams" in capsys.readouterr().err
    assert main(["fit", "--help"]) == 0
    assert "--data.shards" in (help_text := capsys.readouterr().out) and "--optimizer" not in help_text


def test_a_config_yaml_saved_by_an_earlier_fit_with_null_optimizer_keys_still_fits(built_shards, tmp_path):
    saved = tmp_path / "config.yaml"  # what LightningCLI wrote before the module opted out of --optimizer
    saved.write_text("optimizer: null\nlr_scheduler: null\n")
    assert fit(built_shards, tmp_path / "run", "--config", str(saved), "--trainer.max_steps", "1",
               "--trainer.limit_val_batches", "0") == 0


def test_an_unknown_flag_names_the_help_command_that_exists(capsys):
    assert main(["fit", "--model.nonsense", "1"]) == 2
    err = capsys.readouterr().err
    assert "run: hauwm pretrain fit --help" in err and "usage: hauwm pretrain [options] fit" in err


def test_the_config_yaml_a_fit_saved_is_taken_whole_as_a_config(tiny_run, capsys):
    saved = tiny_run / "lightning_logs" / "version_0" / "config.yaml"  # its callbacks' init_args, its null keys
    assert main(["fit", "--config", str(saved), "--print_config"]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["trainer"]["max_steps"] == RUN_STEPS


def test_a_checkpoint_of_another_model_size_is_refused(built_shards, tiny_run, tmp_path, capsys):
    code = fit(built_shards, tmp_path, "--model.world_model.deter", "48", "--ckpt_path", str(tiny_run / "checkpoints" / "last.ckpt"))
    assert code == 2
    assert "different model size (deter: checkpoint 64 vs this run 48)" in capsys.readouterr().err


def test_a_resume_keeps_this_runs_compile_setting(built_shards, tiny_run, tmp_path):
    """A resume goes on with the checkpoint's settings, except model.compile (how the step runs), which may change."""
    checkpoint = tiny_run / "checkpoints" / "last.ckpt"
    assert torch.load(checkpoint, weights_only=True)["hyper_parameters"]["compile"] == "off"
    # max_steps already reached: the resumed fit ends at once, after writing its resolved config.yaml
    assert fit(built_shards, tmp_path, "--model.compile", "default", "--ckpt_path", str(checkpoint),
               "--trainer.max_steps", str(RUN_STEPS)) == 0
    config = yaml.safe_load(next((tmp_path / "lightning_logs").glob("version_*/config.yaml")).read_text())
    assert config["model"]["compile"] == "default" and config["model"]["lr"] == 1e-3


def test_ckpt_path_last_resumes_the_runs_newest_checkpoint_or_starts_afresh(built_shards, tiny_run, tmp_path, capsys):
    shutil.copytree(tiny_run / "checkpoints", tmp_path / "run" / "checkpoints")
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert fit(built_shards, tmp_path / "run", "--ckpt_path", "last", "--trainer.max_steps", str(RUN_STEPS)) == 0
    said = capsys.readouterr().err
    assert f"--ckpt_path last: resuming from {last}" in said  # at max_steps already: ends at once, and says so
    assert f"{last} is at step {RUN_STEPS}, and --trainer.max_steps is {RUN_STEPS}: nothing to train" in said
    assert fit(built_shards, tmp_path / "run", "--ckpt_path", "last", "--trainer.max_steps", "0") == 0  # the same
    assert "--trainer.max_steps is 0: nothing to train" in capsys.readouterr().err  # (refused for a fresh fit)
    assert fit(built_shards, tmp_path / "fresh", "--ckpt_path", "last", "--trainer.max_steps", "1") == 0
    assert f"--ckpt_path last: no {tmp_path / 'fresh' / 'checkpoints' / 'last.ckpt'} yet, starting at step 0" in \
        capsys.readouterr().err


def test_a_resume_that_changes_how_batches_are_drawn_says_so(built_shards, tiny_run, tmp_path, capsys):
    """Allowed (another number of GPUs changes the per-GPU batch size), but the epoch under way is not exact."""
    shutil.copytree(tiny_run / "checkpoints", tmp_path / "checkpoints")
    assert fit(built_shards, tmp_path, "--ckpt_path", "last", "--trainer.max_steps", str(RUN_STEPS + 1),
               "--data.batch_size", "2") == 0
    assert ("last.ckpt was trained with data.batch_size 3 (asked: 2): the rest of its epoch is not what an unbroken "
            "run would have read") in capsys.readouterr().err


class RecordBatches(lightning.Callback):
    """Records (Lightning's epoch, the train dataset's epoch, the batch's clip ids) of every training step (as the
    Trainer's callback `test_cli_export.RecordBatches`)."""

    steps: list[tuple[int, int, list[str]]] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self.steps.append((trainer.current_epoch, trainer.train_dataloader.dataset.epoch, list(batch["id"])))


def test_a_resume_whose_epochs_got_shorter_than_its_checkpoints_position_reads_each_epoch_once(built_shards, tiny_run,
                                                                                                 tmp_path):
    """tiny_run stopped at batch 4 of a 6-batch epoch; at batch size 6 an epoch is 3 batches. Lightning ran that
    epoch again from its first batch while the loader had moved on to the next epoch's data, which the next epoch
    then read once more: every batch of it trained twice."""
    shutil.copytree(tiny_run / "checkpoints", tmp_path / "checkpoints")
    RecordBatches.steps.clear()
    assert fit(built_shards, tmp_path, "--ckpt_path", "last", "--trainer.max_steps", str(RUN_STEPS + 6),
               "--data.batch_size", "6", "--trainer.callbacks+=test_cli_export.RecordBatches") == 0
    epochs = [(lightning_epoch, data_epoch) for lightning_epoch, data_epoch, _ in RecordBatches.steps]
    assert epochs == [(7, 7)] * 3 + [(8, 8)] * 3  # the checkpoint's epoch 6 ended; each epoch reads its own data
    batches = [tuple(ids) for *_, ids in RecordBatches.steps]
    assert len(set(batches)) == 6


def test_a_resume_whose_batch_limit_is_below_its_checkpoints_position_reads_each_epoch_once(built_shards, tiny_run,
                                                                                           tmp_path):
    """tiny_run stopped at batch 4 of a 6-batch epoch; `--trainer.limit_train_batches 3` ends every epoch at batch 3.
    Lightning took the checkpoint's epoch as ended (SetEpoch), but the loader resumed inside it: the next epoch trained
    on the rest of the old epoch's data (2 batches, an epoch cut short), and the data epoch lagged Lightning's."""
    shutil.copytree(tiny_run / "checkpoints", tmp_path / "checkpoints")
    RecordBatches.steps.clear()
    assert fit(built_shards, tmp_path, "--ckpt_path", "last", "--trainer.max_steps", str(RUN_STEPS + 6),
               "--trainer.limit_train_batches", "3", "--trainer.callbacks+=test_cli_export.RecordBatches") == 0
    epochs = [(lightning_epoch, data_epoch) for lightning_epoch, data_epoch, _ in RecordBatches.steps]
    assert epochs == [(7, 7)] * 3 + [(8, 8)] * 3
    assert len({tuple(ids) for *_, ids in RecordBatches.steps}) == 6


def test_a_resume_that_changes_a_model_setting_is_refused(built_shards, tiny_run, tmp_path, capsys):
    shutil.copytree(tiny_run / "checkpoints", tmp_path / "checkpoints")
    for flags, said in ((["--model.lr", "0.5"], "model.lr 0.001 (asked: 0.5)"),
                        (["--data.k_max", "3"], "data.k_max 5 (asked: 3)")):
        assert fit(built_shards, tmp_path, "--ckpt_path", "last", "--trainer.max_steps", str(RUN_STEPS + 2), *flags) == 2
        err = capsys.readouterr().err
        assert f"last.ckpt was trained with {said}: a resume goes on with the settings the fit began with" in err
    assert (tmp_path / "checkpoints" / "last.ckpt").read_bytes() == (tiny_run / "checkpoints" / "last.ckpt").read_bytes()


def test_ckpt_path_last_reads_the_directory_the_configs_model_checkpoint_names(built_shards, tmp_path, capsys,
                                                                              monkeypatch):
    """The save-last ModelCheckpoint's dirpath (`~` expanded, as Lightning does), not another checkpoint's."""
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    elsewhere = tmp_path / "home" / "ckpts"
    overlay = tmp_path / "dirpath.yaml"
    overlay.write_text(yaml.safe_dump({"trainer": {"callbacks": [
        {"class_path": "data_pipeline.SetEpoch"},
        {"class_path": "lightning.pytorch.callbacks.ModelCheckpoint",  # snapshots, no last.ckpt
         "init_args": {"dirpath": str(tmp_path / "snapshots"), "every_n_train_steps": 1}},
        {"class_path": "lightning.pytorch.callbacks.ModelCheckpoint",
         "init_args": {"dirpath": "~/ckpts", "save_last": True, "enable_version_counter": False}}]}}))
    assert fit(built_shards, tmp_path / "run", "--config", str(overlay), "--trainer.max_steps", "2", "--ckpt_path",
               "last") == 0
    assert f"no {elsewhere / 'last.ckpt'} yet, starting at step 0" in capsys.readouterr().err
    assert fit(built_shards, tmp_path / "run", "--config", str(overlay), "--trainer.max_steps", "3", "--ckpt_path",
               "last") == 0
    assert f"--ckpt_path last: resuming from {elsewhere / 'last.ckpt'}" in capsys.readouterr().err
    assert torch.load(elsewhere / "last.ckpt", weights_only=False)["global_step"] == 3


def test_a_config_whose_callbacks_write_no_last_ckpt_is_named_and_its_checkpoints_not_restarted(built_shards,
                                                                                                tmp_path, capsys):
    """An overlay that sets trainer.callbacks replaces the whole list; without a save-last ModelCheckpoint in it,
    `--ckpt_path last` used to start at step 0 again, silently, beside the run's own checkpoints."""
    overlay = tmp_path / "callbacks.yaml"
    overlay.write_text(yaml.safe_dump({"trainer": {"callbacks": [{"class_path": "data_pipeline.SetEpoch"}]}}))
    # Lightning's own ModelCheckpoint then keeps one, after the validation of step 6
    assert fit(built_shards, tmp_path / "run", "--config", str(overlay), "--trainer.max_steps", "7",
               "--trainer.val_check_interval", "3") == 0
    assert "no ModelCheckpoint with save_last: true among trainer.callbacks" in capsys.readouterr().err
    assert fit(built_shards, tmp_path / "run", "--config", str(overlay), "--trainer.max_steps", "8", "--ckpt_path",
               "last") == 2
    newest = tmp_path / "run" / "checkpoints" / "epoch=0-step=6.ckpt"
    assert (f"--ckpt_path last: {newest.parent} holds checkpoints but no last.ckpt (the config's trainer.callbacks "
            f"have no ModelCheckpoint with save_last: true); go on from the newest with --ckpt_path {newest}") in \
        capsys.readouterr().err


def test_a_fresh_fit_where_an_earlier_fit_left_last_ckpt_is_refused(built_shards, tiny_run, tmp_path, capsys):
    """It would write last-v1.ckpt beside the old last.ckpt, which `--ckpt_path last` would later resume."""
    shutil.copytree(tiny_run / "checkpoints", tmp_path / "checkpoints")
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "1") == 2
    assert (f"{tmp_path / 'checkpoints'} holds the checkpoints of an earlier fit (last.ckpt): go on from it with "
            "--ckpt_path last") in capsys.readouterr().err
    assert sorted(path.name for path in (tmp_path / "checkpoints").iterdir()) == \
        sorted(path.name for path in (tiny_run / "checkpoints").iterdir())


def test_a_second_fit_into_a_checkpoint_directory_in_use_is_refused(built_shards, tmp_path, capsys):
    """Two fits into one directory both ran: they wrote last.ckpt through the same partial file (one then failed)
    or the one that ended last left its own, the other's steps lost without a word."""
    checkpoints = tmp_path / "run" / "checkpoints"
    checkpoints.mkdir(parents=True)
    with pid_lock(checkpoints / ".fit.lock"):  # a fit of another process, as far as the lock goes
        assert fit(built_shards, tmp_path / "run", "--trainer.max_steps", "2") == 2
    assert (f"{checkpoints} is in use by another fit (pid {os.getpid()}): wait for it to end, or give this one "
            "another --trainer.default_root_dir") in capsys.readouterr().err
    assert not list(checkpoints.glob("*.ckpt"))
    assert fit(built_shards, tmp_path / "run", "--trainer.max_steps", "2") == 0  # once it has ended
    assert sorted(path.name for path in checkpoints.iterdir()) == ["last.ckpt"]  # the lock goes with the fit


def test_a_fresh_fit_is_not_warned_that_its_checkpoint_directory_is_not_empty(built_shards, tmp_path, recwarn):
    """The fit's own lock file, made first, had Lightning warn at every fresh fit that the checkpoint directory
    "exists and is not empty", as if it were about to write over a run."""
    assert fit(built_shards, tmp_path / "run", "--trainer.max_steps", "1") == 0
    assert not [str(w.message) for w in recwarn if "exists and is not empty" in str(w.message)]


def test_a_ddp_job_into_a_checkpoint_directory_in_use_is_refused(built_shards, tmp_path, capsys):
    """Its rank 0 takes the lock before it starts the other ranks: a DDP job took none, and wrote over the other fit."""
    checkpoints = tmp_path / "run" / "checkpoints"
    checkpoints.mkdir(parents=True)
    with pid_lock(checkpoints / ".fit.lock"):
        assert fit(built_shards, tmp_path / "run", "--trainer.max_steps", "2", "--trainer.devices", "2",
                   "--trainer.strategy", "ddp") == 2
    assert f"{checkpoints} is in use by another fit (pid {os.getpid()})" in capsys.readouterr().err
    assert not list(checkpoints.glob("*.ckpt"))


@pytest.mark.timeout(120)  # the old code waited until DDP's timeout
def test_several_nodes_without_a_cluster_are_refused_instead_of_waiting(built_shards, tiny_run, tmp_path, capsys,
                                                                        monkeypatch):
    """Rank 0 waited at 127.0.0.1 for nodes that could not reach it, without a word, until DDP's timeout."""
    for name in ("MASTER_ADDR", "SLURM_NTASKS", "SLURM_JOB_NAME", "TORCHELASTIC_RUN_ID"):  # as on a plain shell
        monkeypatch.delenv(name, raising=False)
    nodes = ("--trainer.num_nodes", "2", "--trainer.strategy", "ddp")
    assert fit(built_shards, tmp_path / "run", *nodes, "--trainer.max_steps", "2") == 2
    refused = ("--trainer.num_nodes 2, and no cluster started this process (no SLURM job, no torchrun, no MASTER_ADDR): "
               "start it with srun or torchrun on every node")
    assert refused in capsys.readouterr().err
    assert not (tmp_path / "run").exists()
    assert main(["validate", "--config", str(TINY_CONFIG), "--data.shards", str(built_shards), *nodes, "--ckpt_path",
                 str(tiny_run / "checkpoints" / "last.ckpt"), *RUN_ARGS]) == 2
    assert refused in capsys.readouterr().err


def test_resuming_another_runs_checkpoint_over_a_runs_own_last_ckpt_is_refused(built_shards, tiny_run, tmp_path,
                                                                                 capsys):
    """Its last.ckpt replaced this directory's without a word, and `--ckpt_path last` then went on with the other run."""
    shutil.copytree(tiny_run / "checkpoints", tmp_path / "run" / "checkpoints")
    other = tmp_path / "other.ckpt"
    shutil.copy(tiny_run / "checkpoints" / "last.ckpt", other)
    before = (tmp_path / "run" / "checkpoints" / "last.ckpt").read_bytes()
    assert fit(built_shards, tmp_path / "run", "--ckpt_path", str(other), "--trainer.max_steps", "30") == 2
    assert (f"{tmp_path / 'run' / 'checkpoints'} holds the checkpoints of an earlier fit (last.ckpt), which resuming "
            f"{other} there would replace") in capsys.readouterr().err
    assert (tmp_path / "run" / "checkpoints" / "last.ckpt").read_bytes() == before


@pytest.mark.parametrize("flag", ["--ckpt_path", "--trainer.default_root_dir"])
def test_an_empty_path_flag_of_fit_is_refused(built_shards, tmp_path, flag, capsys, monkeypatch):
    """An unset shell variable: --ckpt_path "" ended in a traceback from Lightning; --trainer.default_root_dir ""
    wrote checkpoints/ and lightning_logs/ into the current directory."""
    monkeypatch.chdir(tmp_path)
    args = ["fit", "--config", str(TINY_CONFIG), "--data.shards", str(built_shards), "--trainer.max_steps", "1",
            "--trainer.default_root_dir", str(tmp_path / "run"), *RUN_ARGS, flag, ""]
    assert main(args) == 2
    assert f"{flag} is empty (an unset shell variable?): pass a path" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_an_export_is_not_replaced_without_overwrite(tiny_run, tiny_export, tmp_path, capsys):
    out = tmp_path / "export"
    shutil.copytree(tiny_export, out)
    weights = (out / "weights.safetensors").read_bytes()
    (out / "weights.safetensors").write_bytes(weights[:-4] + bytes(4))  # another model's, as far as a sha256 goes
    checkpoint = str(tiny_run / "checkpoints" / "last.ckpt")
    assert main(["export", checkpoint, "--out", str(out)]) == 2
    assert "already holds an export" in capsys.readouterr().err
    assert (out / "weights.safetensors").read_bytes() != weights  # untouched
    assert main(["export", checkpoint, "--out", str(out), "--overwrite"]) == 0
    assert (out / "weights.safetensors").read_bytes() == weights  # the same checkpoint gives the same bytes
    umask = os.umask(0o022)
    try:  # readable by others as the umask allows (on shared storage); safetensors' save_file gave 0600
        assert main(["export", checkpoint, "--out", str(out), "--overwrite"]) == 0
    finally:
        os.umask(umask)
    assert {path.name: path.stat().st_mode & 0o777 for path in out.iterdir()} == {
        "weights.safetensors": 0o644, "config.json": 0o644}


def test_an_export_stopped_while_writing_leaves_the_old_one_whole(tiny_run, tiny_export, tmp_path, monkeypatch):
    """A full disk (or a kill) while --overwrite writes the config: both old files stay as they were."""
    from model.export import export_frozen

    out = tmp_path / "export"
    shutil.copytree(tiny_export, out)
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    write_bytes = Path.write_bytes

    def disk_full_at_the_config(path: Path, data: bytes) -> int:
        if path.name == ".config.json.partial":
            raise OSError(28, "No space left on device")
        return write_bytes(path, data)

    monkeypatch.setattr(Path, "write_bytes", disk_full_at_the_config)
    model = load_frozen(tiny_export)
    with torch.no_grad():
        next(model.parameters()).add_(1.0)  # another model's weights
    with pytest.raises(OSError, match="No space left"):
        export_frozen(model, out)
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before  # and no partial file left


def test_a_checkpoint_damaged_in_place_is_refused_by_export_and_resume(built_shards, tiny_run, tmp_path, capsys,
                                                                        damaged_in_place):
    """Bytes changed inside a tensor's record (a disk or copy error) were exported and resumed without a word: torch
    does not check the zip's CRC-32s."""
    run = tmp_path / "run" / "checkpoints"
    shutil.copytree(tiny_run / "checkpoints", run)
    damaged = run / "damaged.ckpt"
    record = damaged_in_place(run / "last.ckpt", damaged)
    newest = max((path for path in run.glob("*.ckpt") if path != damaged), key=lambda path: path.stat().st_mtime)
    assert main(["export", str(damaged), "--out", str(tmp_path / "out")]) == 2
    assert (f"{damaged} is damaged: its record {record} fails its checksum (a disk or copy error); use "
            f"another one, e.g. {newest} (the newest whole one beside it)") in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    # the newest beside it damaged too (the disk or the copy that damaged one): the newest whole one is suggested
    whole = run / "older.ckpt"
    shutil.copy(newest, whole)
    os.utime(whole, (1, 1))
    damaged_in_place(newest, newest)
    assert main(["export", str(damaged), "--out", str(tmp_path / "out")]) == 2
    assert f"use another one, e.g. {whole} (the newest whole one beside it)" in capsys.readouterr().err
    whole.write_bytes(whole.read_bytes()[:5000])  # truncated
    others = len(list(run.glob("*.ckpt"))) - 1
    assert main(["export", str(damaged), "--out", str(tmp_path / "out")]) == 2
    assert (f"the {others} other checkpoint(s) beside it are damaged too: restore one from a copy, or start the fit "
            "afresh") in capsys.readouterr().err
    assert fit(built_shards, tmp_path / "run", "--ckpt_path", str(damaged), "--trainer.max_steps", "30") == 2
    assert f"{damaged} is damaged: its record {record} fails its checksum" in capsys.readouterr().err


def test_export_of_a_missing_or_damaged_checkpoint_is_refused(built_shards, tiny_run, tmp_path, capsys):
    assert main(["export", str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "out")]) == 2
    assert "none.ckpt not found" in capsys.readouterr().err
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes((tiny_run / "checkpoints" / "last.ckpt").read_bytes()[:5000])
    not_a_checkpoint = tmp_path / "frames.npy"
    not_a_checkpoint.write_bytes(b"\x93NUMPY" + bytes(100))
    for path, reason in [(truncated, "it is truncated or not a checkpoint"), (not_a_checkpoint, "it is not a checkpoint")]:
        assert main(["export", str(path), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert f"{path} cannot be read as a Lightning checkpoint" in err and reason in err
        assert "weights_only" not in err and "Traceback" not in err  # not torch's advice to unpickle it unsafely
    assert main(["export", str(tiny_run), "--out", str(tmp_path / "out")]) == 2
    assert f"{tiny_run} is a directory (an export?), not a checkpoint" in capsys.readouterr().err
    state = torch.load(tiny_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    state["state_dict"] = {name.replace("rssm.", "dynamics."): t for name, t in state["state_dict"].items()}
    torch.save(state, tmp_path / "renamed.ckpt")  # an older layout's names
    assert main(["export", str(tmp_path / "renamed.ckpt"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "renamed.ckpt: its weights do not fit its own world_model settings (Error(s) in loading" in err
    assert "Traceback" not in err
    assert fit(built_shards, tmp_path / "run", "--ckpt_path", str(tmp_path / "renamed.ckpt")) == 2  # nor resumed
    assert "renamed.ckpt: its weights do not fit its own world_model settings" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_checkpoint_of_something_else_is_refused_by_export_and_by_a_resumed_fit(built_shards, tmp_path, capsys):
    cases = {"list.ckpt": [1, 2], "plain.ckpt": {"weights": torch.zeros(2)},
             "foreign.ckpt": {"state_dict": {}, "hyper_parameters": {"lr": 0.1}, "pytorch-lightning_version": "2.6.0"}}
    for name, content in cases.items():
        torch.save(content, tmp_path / name)
        assert main(["export", str(tmp_path / name), "--out", str(tmp_path / "out")]) == 2
        assert fit(built_shards, tmp_path / "run", "--ckpt_path", str(tmp_path / name)) == 2
        err = capsys.readouterr().err
        reason = "is not a `hauwm pretrain fit` checkpoint" if name == "foreign.ckpt" else "is not a Lightning checkpoint"
        assert err.count(f"{tmp_path / name} {reason}") == 2 and "Traceback" not in err, name
    assert not (tmp_path / "out").exists() and not (tmp_path / "run" / "checkpoints").exists()


def test_shards_of_another_frame_size_are_refused_by_fit_and_analyze(built_shards, tiny_export, tmp_path, capsys):
    shards = tmp_path / "shards-32"
    shutil.copytree(built_shards, shards)
    manifest = json.loads((shards / "manifest.json").read_text())
    manifest["settings"]["size"] = 32  # as `hauwm shards build --size 32` records it
    (shards / "manifest.json").write_text(json.dumps(manifest))
    assert fit(shards, tmp_path / "run") == 2
    assert main(["analyze", "--model", str(tiny_export), "--shards", str(shards), "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert err.count(f"{shards} holds 32×32 frames; the world model reads 64×64") == 2 and "Traceback" not in err


@pytest.mark.parametrize("field, value, message", [
    ("normalisation", {"formula": "x / 255", "scale": 1 / 255, "offset": 0.0}, "image normalisation .* differs from"),
    ("image_shape", [3, 96, 96], r"image_shape \[3, 96, 96\] differs from the \[3, 64, 64\]"),
    ("kind", "some-other-model", "kind 'some-other-model', not a hauwm-pretrained-world-model"),
])
def test_analyze_refuses_an_export_made_for_other_frames(built_shards, tiny_export, tmp_path, capsys, field, value,
                                                          message):
    """The frames analyze feeds in are pre-training's (64×64, x / 255 − 0.5); an export that says it reads others
    was evaluated as if it did not, and its figures were silently wrong."""
    export = shutil.copytree(tiny_export, tmp_path / "export")
    config = json.loads((export / "config.json").read_text())
    (export / "config.json").write_text(json.dumps({**config, field: value}))
    assert main(["analyze", "--model", str(export), "--shards", str(built_shards), "--out", str(tmp_path / "a"),
                 "--batches", "1", "--batch-size", "2", "--seq-len", "8"]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and str(export / "config.json") in err and "Traceback" not in err
    assert not (tmp_path / "a").exists()


def test_analyze_writes_plots_and_figures(built_shards, tiny_export, tmp_path, capsys):
    out = tmp_path / "analysis"
    args = ["analyze", "--model", str(tiny_export), "--model", str(tiny_export), "--shards", str(built_shards),
            "--out", str(out), "--batches", "2", "--batch-size", "3", "--seq-len", "8", "--heads", "3"]
    assert main(args) == 0
    figures = json.loads((out / "figures.json").read_text())
    assert len(figures["models"]) == 2
    horizon = figures["models"][0]["horizon"]
    assert horizon["k"] == [1, 2, 3, 4, 5] and sum(horizon["count"]) == 2 * 3 * 7
    assert len(figures["models"][0]["rollout"]["disagreement"]) == 4
    for png in ["disagreement_vs_k.png", *(f"rollouts_{i}-{tiny_export.name}.png" for i in range(2))]:
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    assert main([*args, "--k-max", "20", "--batches", "1", "--out", str(tmp_path / "k20")]) == 0
    assert "note: --k-max 20 with --seq-len 8: a sequence spans up to 141 frames, but 3 of the 3 clips are shorter" \
        in capsys.readouterr().err


def test_analyze_replaces_an_earlier_analysis_only_when_asked_and_then_whole(built_shards, tiny_export, tmp_path,
                                                                             capsys):
    out = tmp_path / "analysis"
    args = ["analyze", "--shards", str(built_shards), "--out", str(out), "--batches", "1", "--batch-size", "2",
            "--seq-len", "8"]
    assert main([*args, "--model", str(tiny_export), "--model", str(tiny_export)]) == 0
    first = (out / "figures.json").read_text()
    assert main([*args, "--model", str(tiny_export)]) == 2  # replaced without a word before
    assert f"--out {out} holds an analysis already (figures.json): choose another --out, or pass --overwrite" \
        in capsys.readouterr().err
    assert (out / "figures.json").read_text() == first
    assert main([*args, "--model", str(tiny_export), "--overwrite"]) == 0
    assert len(json.loads((out / "figures.json").read_text())["models"]) == 1
    assert sorted(path.name for path in out.iterdir()) == [  # the first analysis's two rollouts are gone
        "disagreement_vs_k.png", "figures.json", f"rollouts_{tiny_export.name}.png"]
    (out / "figures.json").unlink()  # an analysis stopped before its figures.json: its rollouts were deleted
    (out / "rollouts_run_a.png").write_bytes(b"a user's plot")
    assert main([*args, "--model", str(tiny_export)]) == 2
    assert (f"--out {out} holds plots of an analysis already (disagreement_vs_k.png, rollouts_run_a.png, "
            f"rollouts_{tiny_export.name}.png; one stopped before it wrote figures.json?)") in capsys.readouterr().err
    assert (out / "rollouts_run_a.png").read_bytes() == b"a user's plot"
    (tmp_path / "file").write_text("a user's")
    assert main([*args[:-6], "--out", str(tmp_path / "file"), "--model", str(tiny_export)]) == 2
    assert "is a file: analyze writes a directory of plots" in capsys.readouterr().err
    # an unset shell variable: the files went into the current directory
    assert main(["analyze", "--shards", str(built_shards), "--out", "", "--model", str(tiny_export)]) == 2
    assert "--out: an empty path (an unset shell variable?)" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "last.ckpt"), "--out", ""]) == 2
    assert "--out: an empty path (an unset shell variable?)" in capsys.readouterr().err


def test_logging_every_n_steps_logs_every_term_and_counter_at_those_steps(built_shards, tmp_path):
    root = tmp_path / "every3"
    assert fit(built_shards, root, "--trainer.log_every_n_steps", "3", "--trainer.max_steps", "7",
               "--trainer.val_check_interval", "7") == 0
    events = EventAccumulator(str(next((root / "lightning_logs").glob("version_*"))), size_guidance={"scalars": 0})
    events.Reload()
    for tag in ("train/loss", "train/lambda", "train/scaler_skips", "train/nonfinite_steps"):
        assert [event.step for event in events.Scalars(tag)] == [2, 5], tag  # steps 3 and 6, counted from 0
    assert scalars(root, "train/nonfinite_steps")[-1] == 0


def test_checkpointing_turned_off_drops_the_configs_checkpoint_callback(built_shards, tmp_path, capsys):
    """Lightning refuses enable_checkpointing=False beside the config's ModelCheckpoint (a traceback); the CLI leaves
    the callback out and says what that costs."""
    root = tmp_path / "no-checkpoints"
    assert fit(built_shards, root, "--trainer.enable_checkpointing", "false", "--trainer.max_steps", "2",
               "--trainer.limit_val_batches", "0") == 0
    assert "writes no checkpoint and cannot be resumed" in capsys.readouterr().err
    assert not (root / "checkpoints").exists()


def test_16_mixed_asked_on_a_cpu_trains_in_bf16_mixed_with_float32_distributions(built_shards, tmp_path, capsys):
    """The GPU's 16-mixed path has a CPU equivalent: the CLI switches to bf16-mixed, says so, and training
    stays finite with the distribution parameters in float32 under autocast."""
    root = tmp_path / "bf16"
    with warnings.catch_warnings(record=True) as caught:
        assert fit(built_shards, root, "--trainer.precision", "16-mixed", "--trainer.max_steps", "3",
                   "--trainer.val_check_interval", "3", "--trainer.enable_model_summary", "true") == 0
    assert "using bf16-mixed on CPU" in capsys.readouterr().err
    # Lightning's summary calls its size in 32 bits an estimate under mixed precision; the weights are float32
    assert not [str(w.message) for w in caught if "not supported by the model summary" in str(w.message)]
    losses = scalars(root, "train/loss")
    assert len(losses) == 3 and all(torch.isfinite(torch.tensor(losses)))
    assert scalars(root, "train/scaler_skips")[-1] == scalars(root, "train/nonfinite_steps")[-1] == 0
    module = PretrainModule.load_from_checkpoint(root / "checkpoints" / "last.ckpt", map_location="cpu")
    batch = make_batch()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        obs = module.world_model.observe(batch["frames"], batch["gaps"], batch["num_frames"])
    assert obs.prior_mean.dtype == obs.prior_std.dtype == obs.post_std.dtype == torch.float32


@pytest.mark.parametrize(("flags", "message"), [(["--seq-len", "1"], "--seq-len must be at least 2, got 1"),
                                                (["--batches", "0"], "--batches must be at least 1, got 0"),
                                                (["--k-max", "0"], "--k-max must be at least 1, got 0"),
                                                (["--seed", "-1"], "--seed must be at least 0, got -1"),
                                                # torch's generator overflowed (a traceback), after the batches were read
                                                (["--seed", str(2**64)], "--seed must be at most 4294967295"),
                                                # ran for hours in the gap tables and the per-k evaluation
                                                (["--k-max", "10000000"], "--k-max 10000000 with sequences of 12 "
                                                 "frames: the longest clip has"),
                                                # kept every batch in memory until the machine ran out of it
                                                (["--batches", "1000000000"], "lower --batches or --batch-size")])
def test_analyze_refuses_settings_that_leave_nothing_to_measure(built_shards, tiny_export, tmp_path, capsys, flags,
                                                                  message):
    args = ["analyze", "--model", str(tiny_export), "--shards", str(built_shards), "--out", str(tmp_path / "a"), *flags]
    assert main(args) == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "a").exists()


def test_a_fit_prints_lightnings_messages_and_its_notes_but_not_the_cloud_logger_advert(built_shards, tmp_path):
    messages: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: messages.append(record.getMessage())
    logging.getLogger("lightning.pytorch").addHandler(handler)
    try:
        assert fit(built_shards, tmp_path / "run", "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0",
                   "--data.k_max", "20") == 0
    finally:
        logging.getLogger("lightning.pytorch").removeHandler(handler)
    assert any("GPU available" in message for message in messages)  # Lightning's own start-up lines still print
    assert not any("litlogger" in message for message in messages)
    # the sample clips (24-60 frames) hold few spans of 7 gaps up to 20: the long gaps are rare, and it says so
    assert any(message.startswith("note: --data.k_max 20 with --data.seq_len 8: a sequence spans up to 141 frames, "
                                  "but 18 of the 18 clips are shorter") for message in messages), messages


def test_validate_scores_a_checkpoint_and_writes_no_checkpoint(built_shards, tiny_run, tmp_path, capsys, recwarn):
    checkpoint = tiny_run / "checkpoints" / "last.ckpt"
    assert main(["validate", "--config", str(TINY_CONFIG), "--data.shards", str(built_shards), "--trainer.default_root_dir",
                 str(tmp_path), *RUN_ARGS, "--ckpt_path", str(checkpoint)]) == 0
    assert "val/loss" in capsys.readouterr().out
    assert not (tmp_path / "checkpoints").exists() and list((tmp_path / "lightning_logs").glob("version_0"))
    assert not [w for w in recwarn if "dirpath has changed" in str(w.message)]
    # the checkpoint callbacks are left out on purpose; Lightning's advice to add them back is not shown
    assert not [w for w in recwarn if "callbacks used to create the checkpoint" in str(w.message)]


def test_validate_refuses_settings_it_would_ignore_and_a_missing_last_checkpoint(built_shards, tiny_run, tmp_path,
                                                                               capsys):
    """LightningCLI scores a checkpoint with the settings it was trained with: a changed one was silently dropped,
    and `--ckpt_path last` without a checkpoint scored a freshly initialised model, exit status 0."""
    validate = ["validate", "--config", str(TINY_CONFIG), "--data.shards", str(built_shards), *RUN_ARGS]
    checkpoint = tiny_run / "checkpoints" / "last.ckpt"
    assert main([*validate, "--trainer.default_root_dir", str(tmp_path), "--ckpt_path", str(checkpoint),
                 "--model.kl_scale", "0"]) == 2
    assert (f"{checkpoint} was trained with model.kl_scale 1.0 (asked: 0.0): validate scores it with the settings it "
            "was trained with") in capsys.readouterr().err
    assert main([*validate, "--trainer.default_root_dir", str(tmp_path / "typo"), "--ckpt_path", "last"]) == 2
    assert f"--ckpt_path last: no {tmp_path / 'typo' / 'checkpoints' / 'last.ckpt'}: nothing to validate" in \
        capsys.readouterr().err


def test_a_fit_refuses_to_resume_a_weights_only_checkpoint(built_shards, tiny_run, tmp_path, capsys):
    checkpoint = torch.load(tiny_run / "checkpoints" / "last.ckpt", weights_only=False)
    for key in ("optimizer_states", "lr_schedulers"):  # what a ModelCheckpoint(save_weights_only=True) leaves out
        checkpoint.pop(key, None)
    (tmp_path / "checkpoints").mkdir()
    torch.save(checkpoint, tmp_path / "checkpoints" / "last.ckpt")
    assert fit(built_shards, tmp_path, "--ckpt_path", "last", "--trainer.max_steps", str(RUN_STEPS + 1)) == 2
    err = capsys.readouterr().err
    assert "last.ckpt holds the weights only (a ModelCheckpoint with save_weights_only: true): a fit cannot go on" in err
    assert "Traceback" not in err


def test_validation_by_epoch_with_an_interval_longer_than_an_epoch_is_an_error_not_a_traceback(built_shards, tmp_path,
                                                                                              capsys):
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "2", "--trainer.check_val_every_n_epoch", "1") == 2
    err = capsys.readouterr().err
    assert "error: a --trainer setting Lightning refuses: `val_check_interval` (100) must be less than or equal to " \
           "the number of the training batches (6)" in err and "Traceback" not in err


def test_an_export_into_something_that_is_not_a_directory_of_files_is_refused(tiny_run, tmp_path, capsys):
    """A directory at --out/weights.safetensors made the last rename fail with a traceback and left a .partial file
    beside it; a file at --out gave FileExistsError from deep inside pathlib."""
    checkpoint = str(tiny_run / "checkpoints" / "last.ckpt")
    out = tmp_path / "export"
    (out / "weights.safetensors").mkdir(parents=True)
    assert main(["export", checkpoint, "--out", str(out), "--overwrite"]) == 2
    assert f"{out / 'weights.safetensors'} is a directory: an export writes a file there" in capsys.readouterr().err
    assert sorted(path.name for path in out.iterdir()) == ["weights.safetensors"]  # nothing written beside it
    (tmp_path / "file").write_text("a user's")
    assert main(["export", checkpoint, "--out", str(tmp_path / "file")]) == 2
    assert f"--out {tmp_path / 'file'} is a file, not a directory" in capsys.readouterr().err
    assert (tmp_path / "file").read_text() == "a user's"


@pytest.mark.parametrize(("text", "message"), [
    # an overlay whose group's settings are all commented out reads as null: the fit trained the paper-size model
    ("model:\n  # lr: 0.01\n", "`model:` (model) holds no settings (YAML reads it as null, which resets every model "
                               "setting the configs before it made): delete that line"),
    ("trainer:\n", "`trainer:` (trainer) holds no settings"),  # it dropped the config's ModelCheckpoint: no last.ckpt
    ("model:\n  world_model:\n    # deter: 8\n", "`world_model:` (model.world_model) holds no settings"),  # traceback
    ("model:\n  k_max: 7\n", "model.k_max is data.k_max's (the sampler's largest gap, which the model reads): write "
                             "`data: {k_max: 7}` instead"),  # ignored: the fit trained with k_max 5
    ("model:\n  lr: 0.001\n  lr: 0.5\n", "is not valid YAML: 'lr' is set twice: keep one at line 3"),  # 0.5 won
    ("# nothing yet\n", "holds no settings, not a mapping of settings"),  # "Unexpected config: "
    ("42\n", "holds 42, not a mapping of settings"),
    # a misspelt key: the parser named the key after its whole usage text, not the file
    ("trainer:\n  max_step: 4\n", "trainer.max_step is no setting of `hauwm pretrain fit` (did you mean "
                                  "trainer.max_steps?); `hauwm pretrain fit --help` lists them"),
    ("model:\n  world_model:\n    detr: 48\n", "model.world_model.detr is no setting of `hauwm pretrain fit` (did "
                                              "you mean model.world_model.deter?)"),
    # non-finite values passed the range checks: weights went NaN, HCU was off, or every step was skipped
    ("model:\n  lambda_init: .nan\n", "model.lambda_init must be a finite number, got nan"),
    ("model:\n  hcu_target: .inf\n", "model.hcu_target must be a finite number, got inf"),
    ("model:\n  lr: 1e999\n", "model.lr must be a finite number, got inf"),
    ("model:\n  world_model:\n    reference_length: .nan\n", "world_model.reference_length must be a finite number"),
    # a value of the wrong type: the parser named the key after its whole usage text, not the file
    ("trainer:\n  max_steps: many\n", "trainer.max_steps expects int, got 'many'"),
    ("model:\n  world_model:\n    deter: wide\n", "model.world_model.deter expects int, got 'wide'"),
    # YAML's bare `off` is false: the parser's whole usage page, naming neither the file nor the quotes
    ("model:\n  compile: off\n", "model.compile expects one of 'auto', 'off', 'default', 'reduce-overhead', got "
                                  "'False' (YAML reads a bare off, on, no, yes, false or true as a boolean: put the word "
                                  "in quotes)"),
    ("model:\n  world_model: 5\n", "model.world_model is a group of settings, not 5: write them under it, e.g. "
                                    "`world_model: {cnn_width: ...}`"),  # was: "is no setting (did you mean ...?)"
])
def test_a_config_file_that_would_train_other_settings_without_a_word_is_refused(built_shards, tmp_path, capsys, text,
                                                                                  message):
    overlay = tmp_path / "overlay.yaml"
    overlay.write_text(text)
    assert fit(built_shards, tmp_path, "--config", str(overlay)) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and "usage:" not in err, err[-1500:]
    assert f"config file {overlay}" in err or "must be a finite number" in err
    assert not (tmp_path / "checkpoints").exists()


def test_a_flag_of_the_wrong_type_is_named_in_one_line_and_other_parser_errors_keep_their_usage(built_shards, tmp_path,
                                                                                               capsys):
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "lots") == 2
    err = capsys.readouterr().err
    assert err.strip().endswith("hauwm pretrain fit: error: --trainer.max_steps expects int, got 'lots'"), err[-500:]
    assert "usage:" not in err
    assert fit(built_shards, tmp_path, "--model.compile", "fast") == 2  # one of a few words
    assert capsys.readouterr().err.strip().endswith(
        "error: --model.compile expects one of 'auto', 'off', 'default', 'reduce-overhead', got 'fast'")
    assert fit(built_shards, tmp_path, "--data.pin_memory", "maybe") == 2  # a union's words are the parser's, whole
    err = capsys.readouterr().err
    assert "usage:" in err and "Does not validate against any of the Union subtypes" in err and "Given value: maybe" in err
    overlay = tmp_path / "overlay.yaml"
    overlay.write_text("trainer:\n  max_steps: many\n")  # the parser stops at the first bad value it reads
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "lots", "--config", str(overlay)) == 2
    assert "error: --trainer.max_steps expects int, got 'lots'" in capsys.readouterr().err
    assert fit(built_shards, tmp_path, "--trainer.max_steps", "") == 2  # an unset shell variable: blamed on no file
    err = capsys.readouterr().err
    assert "usage:" in err and 'Parser key "trainer.max_steps"' in err and "config file" not in err
    assert fit(built_shards, tmp_path, "--trainer.max_stepz", "3") == 2
    err = capsys.readouterr().err
    assert "usage:" in err and "unrecognized arguments: --trainer.max_stepz 3" in err
    assert not (tmp_path / "checkpoints").exists()


def test_a_checkpoint_whose_settings_the_parser_refuses_is_refused_without_a_traceback(built_shards, tiny_run,
                                                                                      tmp_path, capsys):
    """A setting since removed (or of another type) in a checkpoint's hyper_parameters: Lightning parses them when it
    resumes, catching the parser's exit; a parser left raising its errors made that a traceback."""
    state = torch.load(tiny_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    state["hyper_parameters"]["a_removed_setting"] = 1
    torch.save(state, tmp_path / "old.ckpt")
    assert fit(built_shards, tmp_path / "run", "--ckpt_path", str(tmp_path / "old.ckpt")) == 2
    err = capsys.readouterr().err
    assert "Parsing of ckpt_path hyperparameters failed" in err and "Traceback" not in err


def test_a_diverged_checkpoint_is_not_exported_and_leaves_the_export_there_whole(tiny_run, tiny_export, tmp_path,
                                                                                capsys):
    """`export bad.ckpt --out E --overwrite` replaced a good export with NaN weights; only a later run refused them."""
    state = torch.load(tiny_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    name = next(name for name, tensor in state["state_dict"].items() if tensor.is_floating_point() and "decoder" in name)
    state["state_dict"][name] = torch.full_like(state["state_dict"][name], float("nan"))
    torch.save(state, tmp_path / "diverged.ckpt")
    out = tmp_path / "export"
    shutil.copytree(tiny_export, out)
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    assert main(["export", str(tmp_path / "diverged.ckpt"), "--out", str(out), "--overwrite"]) == 2
    assert (f"the model's weights are not finite ({name.removeprefix('world_model.')} holds NaN or inf; 1 tensors do): "
            f"it diverged; nothing was written to {out}") in capsys.readouterr().err
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before


def test_fast_dev_run_writes_no_checkpoint(built_shards, tmp_path):
    """Lightning's fast_dev_run promises no checkpoint; the fit wrote last.ckpt of step 1, which the real fit in the
    same directory then refused to start beside (or `--ckpt_path last` carried on from)."""
    assert fit(built_shards, tmp_path, "--trainer.fast_dev_run", "true") == 0
    assert not list(tmp_path.rglob("*.ckpt"))


def test_a_stopped_fit_of_a_moved_run_names_the_checkpoint_it_resumed_from(built_shards, tiny_run, tmp_path, capsys,
                                                                          monkeypatch):
    """A run copied elsewhere and resumed: its ModelCheckpoint knew of no checkpoint (Lightning restores its state only
    for the same directory), and a stop before its first save said "no checkpoint was written yet"."""
    from model.module import PretrainModule

    shutil.copytree(tiny_run / "checkpoints", tmp_path / "checkpoints")
    step = PretrainModule.training_step

    def interrupted(module, batch, batch_idx):
        raise KeyboardInterrupt

    monkeypatch.setattr(PretrainModule, "training_step", interrupted)
    assert fit(built_shards, tmp_path, "--ckpt_path", str(tmp_path / "checkpoints" / "last.ckpt"),
               "--trainer.max_steps", str(RUN_STEPS + 5)) == 130
    assert (f"interrupted at step {RUN_STEPS}; resume with --ckpt_path {tmp_path / 'checkpoints' / 'last.ckpt'} (step "
            f"{RUN_STEPS}, written") in capsys.readouterr().err and step


def test_the_memory_estimate_of_a_long_sequence_is_extrapolated_exactly(monkeypatch):
    """Sequences longer than ESTIMATED_LENGTH are not run through the model (a step costs ~10 ms on fake tensors:
    --data.seq_len 100000 stalled for minutes); the saved activations grow linearly with the length."""
    from jsonargparse import Namespace

    from hauwm.memory import training_memory
    from model import lightning_cli
    from model.networks import IMAGE_SHAPE
    from model.rssm import RSSMState
    from model.world_model import WorldModel

    length = 3 * lightning_cli.ESTIMATED_LENGTH + 5
    estimated = {}
    monkeypatch.setattr(lightning_cli, "beyond_memory", lambda needs, fix: estimated.update(needs))
    config = Namespace(model=Namespace(world_model=Namespace(**SMALL.to_dict())), data=Namespace(batch_size=2,
                       seq_len=length), trainer=Namespace(accelerator="cpu", precision="32-true"))
    lightning_cli.refuse_beyond_memory(config)

    def forward():
        model = WorldModel(SMALL)
        obs = model.observe(torch.zeros(2, length, *IMAGE_SHAPE, dtype=torch.uint8), torch.ones(2, length,
                            dtype=torch.long), torch.full((2,), length))
        model.decode(RSSMState(obs.deter, obs.stoch))
        return model

    assert estimated == training_memory(forward)
