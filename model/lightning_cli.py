"""The LightningCLI behind `hauwm pretrain fit | validate`: PretrainModule and ShardDataModule, with HAUWM's checks.

LightningCLI turns --config files and flags into the module (model.*), the data module (data.*) and the Trainer
(trainer.*). PretrainCLI adds what a user needs before anything is built, each step a function below:
  resume            `--ckpt_path last`, and a checkpoint of another model or with changed settings refused by name
  trainer settings  the ones the step cannot honour (precision, accumulation, clipping, no GPU) refused by flag
  one fit at a time a second fit (or DDP job) into a checkpoint directory in use refused (`FIT_LOCK`), by every
                    rank of a job that srun or torchrun started (`RankZeroRefusal`)
  wrong values      a value of the wrong type named with the --config file or flag that gave it (`wrong_value`)
  engineering       atomic checkpoints, a checkpoint at the last step and on SIGTERM (on every DDP rank after the
                    same step), the step progress bar, the resume notice (model/checkpointing.py, model/sigterm.py,
                    model/interrupt.py, model/progress.py)
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import difflib
import logging
import os
import pydoc
import re
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.plugins.environments import LightningEnvironment
from lightning.pytorch.callbacks import Callback, ModelCheckpoint, RichProgressBar, TQDMProgressBar
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.plugins.io import TorchCheckpointIO
from lightning.pytorch.plugins.precision import Precision
from lightning.pytorch.utilities.rank_zero import rank_zero_only

from data_pipeline.datamodule import ShardDataModule
from hauwm.arguments import MAX_SEED
from hauwm.memory import PARAMETER_BYTES, beyond_memory, parameter_count, training_memory
from hauwm.pid_lock import locked
from model.checkpointing import AtomicCheckpointIO, LastStepCheckpoint
from model.cli import refuse_other_frame_size
from model.config import ConfigError, WorldModelConfig, read_config_file
from model.export import checkpoint_world_model, newest_checkpoint, read_checkpoint
from model.interrupt import FitInterrupted, ResumeNotice
from model.module import PretrainModule, refuse_other_size
from model.networks import IMAGE_SHAPE
from model.progress import StepProgressBar
from model.rendezvous import RendezvousWatch
from model.rssm import RSSMState
from model.sigterm import AgreedSigterm
from model.world_model import WorldModel

PRECISIONS = ("32-true", "32", "16-mixed", "16", "bf16-mixed", "bf16")  # each with Lightning's other name for it
DATA_STREAM = ("train_split", "batch_size", "seq_len", "shuffle_buffer", "seed")  # the data settings that shape the
#                                                                               batches a resumed epoch goes on with
OPTIMIZER_KEYS = ("optimizer", "lr_scheduler")  # LightningCLI's, left out: the module configures its own


# -- where a fit keeps its checkpoints ----------------------------------------------------------------


def checkpoint_dir(root_dir: str | None) -> Path:
    """Where a fit in `trainer.default_root_dir` keeps its checkpoints (last.ckpt among them); `~` expanded, as
    Lightning does."""
    return Path(root_dir or ".").expanduser() / "checkpoints"


def names_a(class_path: str, kind: type) -> bool:
    """Whether a config's class path names `kind` or a subclass of it."""
    named = pydoc.locate(class_path)
    return isinstance(named, type) and issubclass(named, kind)


def names_a_model_checkpoint(callback: object) -> bool:
    """Whether a config's callback entry (a class_path and its init_args) is a ModelCheckpoint or a subclass of it."""
    return names_a(str(getattr(callback, "class_path", "")), ModelCheckpoint)


def last_checkpoint(trainer_config) -> Path:
    """Where a fit's last.ckpt is: in the directory its config's save-last ModelCheckpoint names (`dirpath`), or in
    checkpoint_dir(trainer.default_root_dir), where the fit puts it otherwise."""
    for callback in trainer_config.get("callbacks") or []:
        init_args = getattr(callback, "init_args", None)
        if init_args is None or not names_a_model_checkpoint(callback) or not init_args.get("save_last"):
            continue
        if init_args.get("dirpath"):
            return Path(init_args["dirpath"]).expanduser() / "last.ckpt"
    return checkpoint_dir(trainer_config["default_root_dir"]) / "last.ckpt"


# -- checks of the arguments, the resume and the trainer, before anything is built ----------------------


# setting groups a config file may hold; one written with no settings under it (its lines commented out) reads as
# null, which the parser takes as "every setting of the group at its default", undoing the configs before it
GROUPS = (("model",), ("data",), ("trainer",), ("model", "world_model"))


def setting_names(parser) -> set[str]:
    """Every setting a subcommand's parser takes, dotted (`model.world_model.deter`). A setting whose value may be a
    mapping (`trainer.callbacks`, `trainer.logger`) is one name: what is under it is its value."""
    names: set[str] = set()

    def add(settings: dict, prefix: str) -> None:
        for key, value in settings.items():
            if isinstance(value, dict) and value:
                add(value, f"{prefix}{key}.")
            else:
                names.add(prefix + key)

    add(parser.get_defaults().as_dict(), "")
    return names


def unknown_setting(config: dict, names: set[str], prefix: str = "") -> tuple[str, object] | None:
    """The first key of a config file's mapping (dotted) that is no setting in `names`, and its value; or None."""
    for key, value in config.items():
        name = f"{prefix}{key}"
        if name in names:
            continue
        if not (isinstance(value, dict) and any(known.startswith(name + ".") for known in names)):
            return name, value
        if unknown := unknown_setting(value, names, name + "."):
            return unknown
    return None


def given_flags(args: list[str]) -> Iterator[tuple[str, str]]:
    """(flag, its value) for each argument, in order: `--flag=value`, or `--flag value` (the next argument)."""
    for index, arg in enumerate(args):
        flag, equals, value = arg.partition("=")
        yield flag, value if equals else (args[index + 1] if index + 1 < len(args) else "")


def refuse_bad_configs(args: list[str], names: set[str], command: str) -> None:
    """What the parser would take silently, or report without naming the --config file (it says "<unicode
    string>", whichever file it was, or no file at all): a file that is not YAML (named with its line), a key set
    twice, a file with no settings, a group with none (null: it reset that group's settings), model.k_max (the
    parser ignored it: it is data.k_max's), the sizes moved under model.world_model (an old-style flag or key named
    with its new place), and a key that is no setting in `names` (a misspelling, named with the setting meant)."""
    sizes = {field.name for field in dataclasses.fields(WorldModelConfig)}
    for flag, value in given_flags(args):
        if flag.startswith("--model.") and flag.removeprefix("--model.") in sizes:
            raise ConfigError(f"{flag} is now --model.world_model.{flag.removeprefix('--model.')} (model/config.py)")
        if flag not in ("--config", "-c"):
            continue
        path = Path(value)
        if not path.is_file():
            continue  # the parser names it
        config = read_config_file(path, "model:, data:, trainer:; give it some, or drop --config")
        for group in GROUPS:
            parent = config
            for key in group[:-1]:
                parent = parent.get(key) if isinstance(parent, dict) else None
            if isinstance(parent, dict) and group[-1] in parent and parent[group[-1]] is None:
                name = ".".join(group)
                raise ConfigError(f"config file {path}: `{group[-1]}:` ({name}) holds no settings (YAML reads it as "
                                  f"null, which resets every {name} setting the configs before it made): delete that "
                                  "line, or give it a setting")
        model = config.get("model")
        if isinstance(model, dict) and "k_max" in model:
            raise ConfigError(f"config file {path}: model.k_max is data.k_max's (the sampler's largest gap, which the "
                              f"model reads): write `data: {{k_max: {model['k_max']}}}` instead")
        flat = sorted(sizes & set(model)) if isinstance(model, dict) else []
        if flat:
            raise ConfigError(f"{path}: model.{flat[0]} (like every size) now belongs under model.world_model, "
                              f"e.g. `model: {{world_model: {{{flat[0]}: {model[flat[0]]}}}}}` (model/config.py)")
        if found := unknown_setting(config, names):
            unknown, value = found
            if children := sorted(name for name in names if name.startswith(unknown + ".")):
                raise ConfigError(f"config file {path}: {unknown} is a group of settings, not {value!r}: write them "
                                  f"under it, e.g. `{unknown.split('.')[-1]}: {{{children[0].split('.')[-1]}: ...}}`")
            meant = difflib.get_close_matches(unknown, names, n=1)
            raise ConfigError(f"config file {path}: {unknown} is no setting of `{command}`"
                              + (f" (did you mean {meant[0]}?)" if meant else "")
                              + f"; `{command} --help` lists them")


# jsonargparse's words for a setting of one type, or of a few words (a Literal), given a value of another (a union's
# words are longer, and said whole)
WRONG_TYPE = re.compile(r"Parser key \"([^\"]+)\":\s*Expected a (?:<class '(\w+)'>|typing\.Literal\[(.+)\])\. "
                        r"Got value: (.+)")
# YAML 1.1 reads these bare words as true or false: a setting of words gets a bool
YAML_BOOLEANS = "off, on, no, yes, false or true"


def wrong_value(message: str, args: list[str]) -> str | None:
    """A parser message about one setting of the wrong type (`Parser key "trainer.max_steps": Expected a <class
    'int'>. Got value: abc`, after a page of usage) in one line, with the --config file or flag in `args` that gives
    that value, where one gives it as written; None for any other message (which is then said as the parser says it)."""
    if not (match := WRONG_TYPE.fullmatch(message.strip())):
        return None
    key, type_name, words, given = match.groups()
    wanted = type_name or f"one of {words}"
    for flag, value in given_flags(args):  # in the order the parser reads them: it stops at the first wrong value
        if flag in ("--config", "-c") and Path(value).is_file():
            setting = read_config_file(Path(value), "")
            for part in key.split("."):
                setting = setting.get(part) if isinstance(setting, dict) else None
            if setting is not None and str(setting) == given:
                quote = f" (YAML reads a bare {YAML_BOOLEANS} as a boolean: put the word in quotes)" if \
                    words and isinstance(setting, bool) else ""
                return f"config file {value}: {key} expects {wanted}, got {given!r}{quote}"
        elif flag == f"--{key}" and value == given:
            return f"{flag} expects {wanted}, got {given!r}"
    return f"{key} expects {wanted}, got {given!r}"


def checkpoint_to_resume(config, subcommand: str) -> str | None:
    """The --ckpt_path a run resumes from, with `last` (Lightning's word for the newest) read as this run's
    last.ckpt, if it has one yet; a fresh fit where an earlier fit left its last.ckpt is refused (it would write
    last-v1.ckpt beside it, and `--ckpt_path last` would then resume the old run), and so is a fit resuming another
    directory's checkpoint there (its last.ckpt would replace the earlier fit's)."""
    for flag, value in (("--ckpt_path", config.get("ckpt_path")),
                        ("--trainer.default_root_dir", config["trainer"].get("default_root_dir"))):
        if value is not None and not str(value).strip():  # "" would resume nothing, or write into the current directory
            raise ConfigError(f"{flag} is empty (an unset shell variable?): pass a path" +
                              (", or `last` for the run's newest checkpoint" if flag == "--ckpt_path" else ""))
    ckpt_path, last = config.get("ckpt_path"), last_checkpoint(config["trainer"])
    if ckpt_path == "last":
        if not last.is_file():
            # written by a config without a save-last ModelCheckpoint (none where there is no directory)
            if newest := newest_checkpoint(last.parent):
                raise ConfigError(f"--ckpt_path last: {last.parent} holds checkpoints but no last.ckpt (the config's "
                                  "trainer.callbacks have no ModelCheckpoint with save_last: true); go on from the "
                                  f"newest with --ckpt_path {newest}, and add such a ModelCheckpoint to the config")
            if subcommand == "validate":  # it would score a freshly initialised model
                raise ConfigError(f"--ckpt_path last: no {last}: nothing to validate; pass the run's "
                                  "--trainer.default_root_dir, or a checkpoint file as --ckpt_path")
        ckpt_path = config["ckpt_path"] = str(last) if last.is_file() else None
        rank_zero_only(print)(f"hauwm pretrain {subcommand}: --ckpt_path last: " + (
            f"resuming from {last}" if ckpt_path else f"no {last} yet, starting at step 0"), file=sys.stderr)
    elif subcommand == "fit" and ckpt_path is None and last.is_file():
        raise ConfigError(f"{last.parent} holds the checkpoints of an earlier fit (last.ckpt): go on from it with "
                          "--ckpt_path last, or start afresh with another --trainer.default_root_dir")
    elif subcommand == "fit" and last.is_file() and Path(ckpt_path).resolve().parent != last.parent.resolve():
        raise ConfigError(f"{last.parent} holds the checkpoints of an earlier fit (last.ckpt), which resuming "
                          f"{ckpt_path} there would replace: resume it with its own run's --trainer.default_root_dir, "
                          "or in a new one")
    return ckpt_path


def refuse_other_model(ckpt_path: str, config, subcommand: str) -> dict:
    """Refuse a checkpoint whose weights or sizes are not the model asked for (rather than silently training
    another size), and one a fit cannot go on from (weights only); say when it is already at max_steps, and when a
    fit resumes with other batch-drawing data settings (DATA_STREAM). -> its hyper_parameters."""
    checkpoint, saved_sizes = read_checkpoint(ckpt_path)
    checkpoint_world_model(checkpoint, saved_sizes, Path(ckpt_path))  # weights of another layout: refused
    if subcommand == "fit" and "optimizer_states" not in checkpoint:  # Lightning: a KeyError when it restores them
        raise ConfigError(f"{ckpt_path} holds the weights only (a ModelCheckpoint with save_weights_only: true): a fit "
                          "cannot go on from it without its optimizers' state; export or validate it, or resume from "
                          "a full checkpoint")
    max_steps, step = config["trainer"]["max_steps"], checkpoint.get("global_step", 0)
    if subcommand == "fit" and 0 <= max_steps <= step:
        rank_zero_only(print)(f"hauwm pretrain fit: {ckpt_path} is at step {step}, and --trainer.max_steps is "
                              f"{max_steps}: nothing to train (raise max_steps to go on)", file=sys.stderr)
    data_saved, data_asked = checkpoint.get("datamodule_hyper_parameters") or {}, config["data"]
    changed = [f"data.{key} {data_saved[key]!r} (asked: {data_asked[key]!r})" for key in DATA_STREAM
               if key in data_saved and data_saved[key] != data_asked[key]]
    if subcommand == "fit" and changed:  # allowed (a resume on another number of GPUs changes the batch size)
        rank_zero_only(print)(f"hauwm pretrain fit: {ckpt_path} was trained with {', '.join(changed)}: the rest of its "
                              "epoch is not what an unbroken run would have read (clips may repeat or be left out), "
                              "later epochs follow the new settings", file=sys.stderr)
    saved = checkpoint["hyper_parameters"]
    refuse_other_size(saved, WorldModelConfig(**config["model"]["world_model"].as_dict()), str(ckpt_path))
    if "world_model" not in saved:  # read_checkpoint found the sizes, flat at the top level
        raise ConfigError(
            f"{ckpt_path} keeps the model sizes flat in its hyper_parameters (written before they moved "
            "under model.world_model), so this version cannot resume it; `hauwm pretrain export` still "
            "exports it, or resume it with the hauwm version that wrote it"
        )
    return saved


def flat_settings(namespace) -> dict[str, object]:
    """A jsonargparse Namespace's settings by dotted key (`world_model.deter`: 200, ...)."""
    return {key: namespace[key] for key in namespace.keys() if not hasattr(namespace[key], "keys")}


def changed_on_resume(saved: dict, resumed, asked_model, asked_k_max: int) -> list[str]:
    """The settings asked for that differ from the checkpoint's (LightningCLI would silently keep the checkpoint's),
    model.compile aside: how a step runs on this machine, not what it trains."""
    asked = flat_settings(asked_model)
    changed = [f"model.{key} {value!r} (asked: {asked[key]!r})" for key, value in flat_settings(resumed).items()
               if key != "compile" and key in asked and asked[key] != value]
    if saved.get("k_max", asked_k_max) != asked_k_max:  # data.k_max sets model.k_max, also over the checkpoint's
        changed.append(f"data.k_max {saved['k_max']!r} (asked: {asked_k_max!r})")
    return changed


# a fit that would train nothing (Lightning ends it at once, exit 0): the flag, and what to give instead
TRAINS_NOTHING = {
    "limit_train_batches": "leave it unset (a whole epoch), or cut the run with --trainer.max_steps",
    "max_epochs": "give N >= 1 (-1: no limit), or cut the run by steps with --trainer.max_steps",
    "max_steps": "give N >= 1 (-1: no limit); `hauwm pretrain validate` scores a checkpoint without training",
}


def settle_trainer(trainer, subcommand: str, resuming: bool) -> None:
    """Refuse, by flag, the Trainer settings this step cannot honour; leave out checkpointing where nothing is
    saved; float16 autocast becomes bfloat16 on a CPU. (Every rank of a DDP job runs this; rank 0 alone says so.)"""
    if trainer.accelerator in ("gpu", "cuda") and not torch.cuda.is_available():
        raise ConfigError(f"trainer.accelerator is {trainer.accelerator} and no CUDA GPU is visible: for a (slow) "
                          "CPU run add --trainer.accelerator cpu --trainer.devices 1 --trainer.strategy auto, or "
                          "use configs/pretrain/tiny.yaml")
    no_cuda = trainer.accelerator == "cpu" or (trainer.accelerator == "auto" and not torch.cuda.is_available())
    if no_cuda and str(trainer.devices) == "-1":  # Lightning's "every GPU"; its CPU accelerator raises a TypeError
        raise ConfigError("trainer.devices -1 means every GPU, and this run is on the CPU: pass --trainer.devices "
                          "1 (or N processes)")
    if any(start in str(trainer.strategy) for start in ("spawn", "fork", "notebook")):
        raise ConfigError(f"--trainer.strategy {trainer.strategy}: ranks started by Python's multiprocessing do not get "
                          "the fit's SIGTERM handling (no last.ckpt, no exit 143) nor its stop notice; use "
                          "--trainer.strategy ddp (one process a device, as torchrun and SLURM start them)")
    checkpointers = [callback for callback in trainer.callbacks or [] if names_a_model_checkpoint(callback)]
    # validate writes no checkpoint (restoring one into it only warns of its dirpath); nor does a fast_dev_run, as
    # Lightning says, but its ModelCheckpoint wrote last.ckpt at the end (2.6), which the real fit then resumed
    if subcommand == "validate" or trainer.fast_dev_run:
        trainer.enable_checkpointing = False
        trainer.callbacks = [callback for callback in trainer.callbacks or [] if callback not in checkpointers]
    elif trainer.enable_checkpointing is False and checkpointers:  # Lightning would refuse the pair
        rank_zero_only(print)("hauwm pretrain: --trainer.enable_checkpointing false: the config's ModelCheckpoint is "
                              "left out, so this run writes no checkpoint and cannot be resumed", file=sys.stderr)
        trainer.callbacks = [callback for callback in trainer.callbacks if callback not in checkpointers]
    elif trainer.enable_checkpointing is not False and not any((getattr(callback, "init_args", None) or {}).get(
            "save_last") for callback in checkpointers):
        rank_zero_only(print)("hauwm pretrain: no ModelCheckpoint with save_last: true among trainer.callbacks (a "
                              "config that sets trainer.callbacks replaces the whole list), so this fit writes no "
                              "last.ckpt and `--ckpt_path last` cannot resume it: keep the ModelCheckpoint of "
                              "configs/pretrain/*.yaml in the list", file=sys.stderr)
    plugins = trainer.plugins if isinstance(trainer.plugins, list) else [trainer.plugins]
    for plugin in filter(None, plugins):  # Lightning refused the pair with a ValueError in a traceback
        if names_a(class_path := str(getattr(plugin, "class_path", plugin)), Precision):
            raise ConfigError(f"--trainer.plugins {class_path.rsplit('.', 1)[-1]}: a fit's precision plugin is the one "
                              f"--trainer.precision makes ({', '.join(PRECISIONS[::2])}); leave the plugin out")
    trainer.precision = trainer.precision or "32-true"  # None: Lightning's default
    if str(trainer.precision) not in PRECISIONS:  # half-precision weights: the step's float32 state breaks
        raise ConfigError(f"--trainer.precision {trainer.precision}: a fit runs in {', '.join(PRECISIONS[::2])} "
                          "(float32 weights, autocast for the rest; 16-mixed is the paper's)")
    if trainer.accumulate_grad_batches != 1:  # Lightning refuses it under the step's manual optimisation
        raise ConfigError(f"--trainer.accumulate_grad_batches {trainer.accumulate_grad_batches}: the step "
                          "optimises by itself (skipped steps, λ's dual step) and accumulates nothing: raise "
                          "--data.batch_size instead")
    # a resume at max_steps or beyond has been told so (`refuse_other_model`), and ends at once as it always did
    zero = [flag for flag in TRAINS_NOTHING if getattr(trainer, flag) == 0 and not (flag == "max_steps" and resuming)]
    if subcommand == "fit" and zero:
        raise ConfigError(f"--trainer.{zero[0]} 0: the fit would train nothing and end at once; "
                          f"{TRAINS_NOTHING[zero[0]]}")
    interval = trainer.val_check_interval  # steps (int), a fraction of an epoch (float), or a time
    if isinstance(interval, int | float) and not isinstance(interval, bool) and not interval > 0:  # Lightning divides by it
        raise ConfigError(f"--trainer.val_check_interval {interval}: validate every N >= 1 training steps, or a fraction "
                          "> 0 of an epoch (null: once an epoch)")
    if trainer.check_val_every_n_epoch is not None and trainer.check_val_every_n_epoch < 1:
        raise ConfigError(f"--trainer.check_val_every_n_epoch {trainer.check_val_every_n_epoch}: validate every N >= 1 "
                          "epochs, or null to validate by --trainer.val_check_interval steps alone")
    if trainer.gradient_clip_val is not None:
        raise ConfigError("--trainer.gradient_clip_val: the step clips its own gradients: set --model.grad_clip")
    if str(trainer.precision) in ("16-mixed", "16") and no_cuda:
        rank_zero_only(print)("hauwm pretrain: float16 autocast needs a GPU; using bf16-mixed on CPU", file=sys.stderr)
        trainer.precision = "bf16-mixed"


ESTIMATED_LENGTH = 32  # the longest sequence the memory estimate runs (~10 ms a step on fake tensors); longer ones
#                       are extrapolated from it and half of it: the saved activations grow linearly with the length


def refuse_beyond_memory(config) -> None:
    """Refuse a fit whose world model (config.model.world_model) cannot fit in this machine's memory: on a
    CPU, its training at config.data's batch size and sequence length (weights, Adam state, activations); for a GPU,
    its weights while they are built on the host (hauwm/memory.py; a GPU's own memory running out is one line of
    `hauwm`'s). A batch size or length the loader refuses is left to it."""
    world_model = WorldModelConfig(**config.model.world_model.as_dict()).validate()  # named as the module names it
    accelerator, batch_size, seq_len = config.trainer.accelerator, config.data.batch_size, config.data.seq_len
    if not (isinstance(batch_size, int) and isinstance(seq_len, int) and batch_size >= 1 and seq_len >= 2):
        return

    def training(length: int) -> dict[str, int]:
        def forward() -> WorldModel:  # one training batch through the model, on fake tensors
            model = WorldModel(world_model)
            with torch.autocast("cpu", torch.bfloat16, enabled="16" in str(config.trainer.precision)):
                obs = model.observe(torch.zeros(batch_size, length, *IMAGE_SHAPE, dtype=torch.uint8),
                                    torch.ones(batch_size, length, dtype=torch.long), torch.full((batch_size,), length))
                model.decode(RSSMState(obs.deter, obs.stoch))
            return model

        return training_memory(forward)

    paper = WorldModelConfig()
    larger = [f"{name} {value}" for name, value in world_model.to_dict().items()
              if type(value) is int and value > getattr(paper, name)]
    sizes = "model.world_model's sizes" + (f" ({', '.join(larger)}; the paper's are in configs/pretrain/ssv2.yaml)"
                                           if larger else "")
    if accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available()):
        needs = training(min(seq_len, ESTIMATED_LENGTH))
        if seq_len > ESTIMATED_LENGTH:  # affine in the length: extrapolated from two lengths
            short = training(ESTIMATED_LENGTH // 2)
            needs = {what: size + (size - short[what]) * (seq_len - ESTIMATED_LENGTH) // (ESTIMATED_LENGTH // 2)
                     for what, size in needs.items()}
        what = f"model.world_model at batch_size {batch_size} × seq_len {seq_len}"
        batch = "--data.batch_size or --data.seq_len"
        weights_first = needs["weights and Adam state"] >= needs.get("saved activations or gradients", 0)
        fix = f"lower {sizes}, or {batch}" if weights_first else f"lower {batch}, or {sizes}"
    else:
        needs = {"weights built on the host": PARAMETER_BYTES * parameter_count(lambda: WorldModel(world_model))}
        what, fix = "model.world_model", f"lower {sizes}"
    if problem := beyond_memory(needs, fix):
        raise ConfigError(f"{what}: {problem}")


def refuse_nodes_without_a_cluster(trainer) -> None:
    """Several nodes and no SLURM, torchrun or MASTER_ADDR: rank 0 waited at 127.0.0.1, without a word, for nodes
    that could not reach it."""
    environment = getattr(trainer.strategy, "cluster_environment", None)
    if trainer.num_nodes > 1 and type(environment) is LightningEnvironment and "MASTER_ADDR" not in os.environ:
        raise ConfigError(f"--trainer.num_nodes {trainer.num_nodes}, and no cluster started this process (no SLURM "
                          "job, no torchrun, no MASTER_ADDR): start it with srun or torchrun on every node, or set "
                          "MASTER_ADDR (node 0's address), MASTER_PORT and NODE_RANK on each")


# -- the CLI ------------------------------------------------------------------------------------------


FIT_LOCK = ".fit.lock"  # in a fit's checkpoint directory while it runs: its pid (hauwm/pid_lock.py)


def starts_every_rank(trainer) -> bool:
    """Whether this process is the job's only one or starts its other ranks itself (Lightning's launcher on one
    machine, `--trainer.devices N`), rather than a launcher (srun, torchrun) or other nodes starting them."""
    environment = getattr(trainer.strategy, "cluster_environment", None)
    return environment is None or (trainer.num_nodes == 1 and not environment.creates_processes_externally)


class RankZeroRefusal(Callback):
    """Rank 0's refusal of a fit, said by every rank of a job whose ranks it did not start: they would otherwise
    wait for the refused rank 0 in DDP's set-up until its timeout (30 minutes). `setup` runs on every rank once the
    process group is up, before anything is trained or saved."""

    def __init__(self, refusal: str | None) -> None:
        self.refusal = refusal  # rank 0's; None on the other ranks and where rank 0 took the lock

    def setup(self, trainer, pl_module, stage: str) -> None:
        if (refusal := trainer.strategy.broadcast(self.refusal, src=0)) is not None:
            raise ConfigError(refusal)


class PretrainCLI(LightningCLI):
    def __init__(self, *args, notice: ResumeNotice, held: contextlib.ExitStack, **kwargs):
        self.notice = notice  # LightningCLI parses, builds and runs inside __init__
        self.held = held  # what the fit holds while it runs (its directory's lock), let go when the call ends
        super().__init__(*args, **kwargs)

    def parse_arguments(self, parser, args: list[str]) -> None:
        """The checks of `refuse_bad_configs` first, against the settings of the subcommand asked for; a value of the
        wrong type then said in one line (`wrong_value`), any other parser error as the parser says it."""
        subcommand = args[0] if args and args[0] in self.subcommands() else None
        if subcommand is None:  # the parser says what the subcommands are
            return super().parse_arguments(parser, args)
        subparser = self._subcommand_parsers[subcommand]  # LightningCLI's, one per subcommand
        refuse_bad_configs(args, setting_names(subparser), f"{parser.prog} {subcommand}")
        before = parser.exit_on_error, subparser.exit_on_error
        parser.exit_on_error = subparser.exit_on_error = False  # their errors come here, raised
        try:
            super().parse_arguments(parser, args)
        except argparse.ArgumentError as err:
            if said := wrong_value(str(err), args):
                raise ConfigError(said) from None
            subparser.exit_on_error = True
            subparser.error(str(err))  # what it says otherwise, with its usage
        finally:  # as Lightning expects them later (it parses a resumed checkpoint's settings, catching SystemExit)
            parser.exit_on_error, subparser.exit_on_error = before
        seed = self.config[subcommand].get("seed_everything")
        if type(seed) is int and not 0 <= seed <= MAX_SEED:  # Lightning's seed_everything raised it in a traceback
            raise ConfigError(f"seed_everything {seed}: a seed is a whole number from 0 to {MAX_SEED}")

    def add_arguments_to_parser(self, parser) -> None:
        parser.link_arguments("data.k_max", "model.k_max")  # one K_max for sampling and validation
        # the module runs its own two Adams, so LightningCLI adds no --optimizer / --lr_scheduler; the config.yaml an
        # earlier fit saved holds both as null, and stays usable as --config (a value is refused by name)
        for name in OPTIMIZER_KEYS:
            parser.add_argument(f"--{name}", type=Any, default=None, help=argparse.SUPPRESS)

    def _parse_ckpt_path(self) -> None:
        """LightningCLI replaces the model settings with the checkpoint's when resuming: refuse a checkpoint of
        another model or settings that changed instead of silently training something else, and keep this run's
        model.compile."""
        subcommand = self.config.get("subcommand") or ""
        config = self.config.get(subcommand, {})
        ckpt_path = checkpoint_to_resume(config, subcommand) if config else None
        if not (ckpt_path and Path(ckpt_path).is_file()):
            return super()._parse_ckpt_path()
        saved = refuse_other_model(ckpt_path, config, subcommand)
        asked_model, asked_k_max = config["model"].clone(), config["data"]["k_max"]
        super()._parse_ckpt_path()
        resumed = self.config[subcommand]["model"]
        changed = changed_on_resume(saved, resumed, asked_model, asked_k_max)
        if changed:  # validate would silently score with the checkpoint's settings, not the ones asked for
            remedy = ("a resume goes on with the settings the fit began with (only model.compile may change); drop the "
                      "change, or start a new fit in another --trainer.default_root_dir") if subcommand == "fit" else \
                     "validate scores it with the settings it was trained with; drop the change"
            raise ConfigError(f"{ckpt_path} was trained with {', '.join(changed[:3])}: {remedy}")
        resumed["compile"] = asked_model["compile"]

    def before_instantiate_classes(self) -> None:
        config = self.config[self.subcommand]
        for name in OPTIMIZER_KEYS:
            if config.get(name) is not None:
                raise ConfigError(f"{name}: the module optimises with its own two Adams (manual optimisation), so "
                                  f"no {name} can be set; --model.lr and --model.lambda_lr set their learning rates")
        if config.data.shards:  # none: ShardDataModule says what to pass
            refuse_other_frame_size(config.data.shards, "--data.shards")  # and a missing or unfinished directory
        if config.ckpt_path and not Path(config.ckpt_path).is_file():
            what = "is a directory" if Path(config.ckpt_path).is_dir() else "does not exist"
            raise ConfigError(f"--ckpt_path {config.ckpt_path} {what}: pass a checkpoint file, or `last` "
                              "for the run's newest (e.g. RUN/checkpoints/last.ckpt)")
        if self.subcommand == "validate" and not config.ckpt_path:
            print("hauwm pretrain validate: no --ckpt_path, so this scores a freshly initialised model", file=sys.stderr)
        if self.subcommand == "validate":  # settle_trainer leaves the checkpoint callbacks out, on purpose
            warnings.filterwarnings("ignore", message="Be aware that when using `ckpt_path`, callbacks used to create")
        if self.subcommand == "fit":
            refuse_beyond_memory(config)
        settle_trainer(config.trainer, self.subcommand, resuming=bool(config.ckpt_path))

    def before_validate(self) -> None:
        refuse_nodes_without_a_cluster(self.trainer)
        self.watch_rendezvous()

    def before_fit(self) -> None:
        refuse_nodes_without_a_cluster(self.trainer)
        for callback in self.trainer.checkpoint_callbacks:
            if isinstance(callback, ModelCheckpoint) and callback.dirpath is None:
                callback.dirpath = str(checkpoint_dir(self.trainer.default_root_dir))
        refusal = None
        if self.trainer.global_rank == 0:  # a fit's, or a DDP job's global rank 0's for the whole job
            try:
                self.lock_checkpoint_directory(last_checkpoint(self.config["fit"]["trainer"]).parent)
            except ConfigError as refused:
                if starts_every_rank(self.trainer):  # before the other ranks start
                    raise
                refusal = str(refused)
                self.trainer.loggers = []  # no lightning_logs/version_N of its own before the ranks learn it
        callbacks = self.trainer.callbacks
        callbacks.insert(0, RankZeroRefusal(refusal))  # first: before SaveConfigCallback writes config.yaml
        for index, callback in enumerate(callbacks):  # Lightning's own default bar; a user's choice stays
            if type(callback) in (RichProgressBar, TQDMProgressBar):
                callbacks[index] = StepProgressBar()
        # a fit stopped at max_steps, max_time or by SIGTERM resumes inside its epoch; before the notice, which
        # names the checkpoint it wrote
        callbacks.append(AgreedSigterm())  # SIGTERM: stop after the step (under DDP, the same one on all ranks)
        callbacks.append(LastStepCheckpoint())  # after AgreedSigterm: it saves at the end of the step agreed on
        callbacks.append(self.notice)  # with or without a progress bar
        if type(self.trainer.strategy.checkpoint_io) is TorchCheckpointIO:  # a user's own plugin stays
            self.trainer.strategy.checkpoint_io = AtomicCheckpointIO()
        self.watch_rendezvous()

    def watch_rendezvous(self) -> None:
        """A job of several ranks: say while this one waits for the others, and what to do if they never all come
        (model/rendezvous.py), until the call ends."""
        if self.trainer.world_size > 1:
            timeout = getattr(self.trainer.strategy, "_timeout", None)  # DDPStrategy's `timeout` argument
            self.held.enter_context(RendezvousWatch(f"hauwm pretrain {self.subcommand}", self.trainer.global_rank,
                                                    self.trainer.world_size, self.trainer.num_nodes, timeout))

    def lock_checkpoint_directory(self, directory: Path) -> None:
        """Refuse a fit into a checkpoint directory another fit is writing: both wrote last.ckpt through the same
        partial file, and the one that ended last left its own (the other's steps lost without a word)."""
        if not directory.is_dir():  # made for the lock: gone again if the fit wrote nothing into it

            def remove_if_empty() -> None:
                if not any(directory.iterdir()):
                    directory.rmdir()

            directory.mkdir(parents=True, exist_ok=True)  # another fit starting at once may have made it too
            self.held.callback(remove_if_empty)
        self.held.enter_context(locked(directory / FIT_LOCK, lambda pid: ConfigError(
            f"{directory} is in use by another fit (pid {pid}): wait for it to end, or give this one another "
            "--trainer.default_root_dir")))
        if [entry.name for entry in directory.iterdir()] == [FIT_LOCK]:  # Lightning would call it "not empty"
            warnings.filterwarnings("ignore", message=re.escape(f"Checkpoint directory {directory} exists and is not "
                                                                "empty"))


def not_an_advert(record: logging.LogRecord) -> bool:
    """A logging filter: Lightning 2.6 advertises its cloud logger at every Trainer start; a run's output is for the run."""
    return "litlogger" not in str(record.msg)


def lightning_cli(args: list[str]) -> PretrainCLI:
    """Run a LightningCLI subcommand (fit, validate) over PretrainModule and the shard DataModule. Ctrl-C or SIGTERM
    during a fit raises FitInterrupted, once ResumeNotice has said where to resume from."""
    # `hauwm` passes its own argv on purpose; Lightning would warn that sys.argv differs
    warnings.filterwarnings("ignore", message="LightningCLI's args parameter is intended")
    # checkpoints after the optimizer step are what resume needs; Lightning warns about it under manual optimisation
    warnings.filterwarnings("ignore", message="Using ModelCheckpoint with manual optimization")
    # training_step logs every log_every_n_steps *global* steps, across epochs (make demo: 30 logs in 300 steps of
    # 9-step epochs at 10); Lightning warns as if epochs shorter than the interval never logged
    warnings.filterwarnings("ignore", message="The number of training batches .* is smaller than the logging interval")
    # the weights stay float32 under 16-mixed and bf16-mixed (autocast): the summary's size in 32 bits is exact
    warnings.filterwarnings("ignore", message=r"Precision (16|bf16)-mixed is not supported by the model summary")
    # Lightning 2.6's own pytree helper uses a torch API that torch 2.14 deprecates (not this project's code)
    warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated")
    logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(not_an_advert)  # once, however often called
    notice = ResumeNotice()
    try:
        with contextlib.ExitStack() as held:
            return PretrainCLI(
                PretrainModule,
                ShardDataModule,
                notice=notice,
                held=held,
                args=args,
                save_config_kwargs={"overwrite": True},
                auto_configure_optimizers=False,  # the module's own two Adams (manual optimisation): no --optimizer
                parser_kwargs={"prog": "hauwm pretrain", "allow_abbrev": False,  # `--trainer.max_step` is no max_steps
                               "description": "Pre-train the HAUWM world model (ensemble RSSM + HCU loss) on video "
                                              "shards."},
            )
    except SystemExit:
        if notice.exit_code:  # Lightning's sys.exit(1) after Ctrl-C, or its SIGTERMException
            raise FitInterrupted(notice.exit_code) from None
        raise
