"""`hauwm pretrain …`: fit (LightningCLI), export, analyze.

    hauwm pretrain fit --config configs/pretrain/ssv2.yaml [--data.shards DIR] [--trainer.max_steps N] ...
    hauwm pretrain fit --config configs/pretrain/ssv2.yaml --ckpt_path RUN/checkpoints/last.ckpt   (resume)
    hauwm pretrain validate --config ... --ckpt_path CKPT
    hauwm pretrain export CKPT --out DIR
    hauwm pretrain analyze --model DIR [--model DIR2] --shards DIR --out DIR

Every setting of the module (model.*), the data module (data.*) and the Trainer (trainer.*) can be
overridden on the command line after --config; `hauwm pretrain fit --help` lists them. Checkpoints go to
`<trainer.default_root_dir>/checkpoints/` (last.ckpt is always the newest), TensorBoard logs and the
resolved config.yaml to `<trainer.default_root_dir>/lightning_logs/version_N/`.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import pydoc
import sys
import warnings
from pathlib import Path

import torch

USAGE = __doc__.split("\n\n")[1]
LIGHTNING_COMMANDS = ("fit", "validate")
PRECISIONS = ("32-true", "32", "16-mixed", "16", "bf16-mixed", "bf16")  # each with Lightning's other name for it


def refuse_flat_sizes(args: list[str]) -> None:
    """The sizes moved under model.world_model: name an old-style flag or config key and its new place
    (the parser alone would only say that `model` does not accept it)."""
    import yaml

    from model.config import ConfigError, WorldModelConfig

    sizes = {field.name for field in dataclasses.fields(WorldModelConfig)}
    for index, arg in enumerate(args):
        flag, _, value = arg.partition("=")
        if flag.startswith("--model.") and flag.removeprefix("--model.") in sizes:
            raise ConfigError(f"{flag} is now --model.world_model.{flag.removeprefix('--model.')} (model/config.py)")
        if flag not in ("--config", "-c"):
            continue
        path = Path(value or (args[index + 1] if index + 1 < len(args) else ""))
        try:
            config = yaml.safe_load(path.read_text()) if path.is_file() else None
        except yaml.YAMLError:
            continue  # the parser reports it
        model = config.get("model") if isinstance(config, dict) else None
        flat = sorted(sizes & set(model)) if isinstance(model, dict) else []
        if flat:
            raise ConfigError(f"{path}: model.{flat[0]} (like every size) now belongs under model.world_model, "
                              f"e.g. `model: {{world_model: {{{flat[0]}: {model[flat[0]]}}}}}` (model/config.py)")


def refuse_other_frame_size(shards: str | Path, flag: str) -> None:
    """Refuse (ConfigError) a shard directory whose frames are not the 64×64 the world model's CNNs read."""
    from data_pipeline.shard_format import read_manifest
    from model.config import ConfigError
    from model.networks import IMAGE_SHAPE

    size, side = read_manifest(shards)["settings"]["size"], IMAGE_SHAPE[-1]
    if size != side:
        raise ConfigError(f"{flag} {shards} holds {size}×{size} frames; the world model reads {side}×{side}: build "
                          f"the shards with `hauwm shards build ... --size {side}`")


def not_an_advert(record: logging.LogRecord) -> bool:
    """A logging filter: Lightning 2.6 advertises its cloud logger at every Trainer start; a run's output is for the run."""
    return "litlogger" not in str(record.msg)


def checkpoint_dir(root_dir: str | None) -> Path:
    """Where a fit in `trainer.default_root_dir` keeps its checkpoints (last.ckpt among them); `~` expanded, as
    Lightning does."""
    return Path(root_dir or ".").expanduser() / "checkpoints"


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


def flat_settings(namespace) -> dict[str, object]:
    """A jsonargparse Namespace's settings by dotted key (`world_model.deter`: 200, ...)."""
    return {key: namespace[key] for key in namespace.keys() if not hasattr(namespace[key], "keys")}


def names_a_model_checkpoint(callback: object) -> bool:
    """Whether a config's callback entry (a class_path and its init_args) is a ModelCheckpoint or a subclass of it."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    named = pydoc.locate(str(getattr(callback, "class_path", "")))
    return isinstance(named, type) and issubclass(named, ModelCheckpoint)


def lightning_cli(args: list[str]):
    """Run a LightningCLI subcommand over PretrainModule and the shard DataModule; -> the LightningCLI. Ctrl-C during
    or SIGTERM during a fit raises FitInterrupted, once ResumeNotice has said where to resume from."""
    refuse_flat_sizes(args)
    from lightning.pytorch.callbacks import ModelCheckpoint, RichProgressBar, TQDMProgressBar
    from lightning.pytorch.cli import LightningCLI
    from lightning.pytorch.plugins.io import TorchCheckpointIO
    from lightning.pytorch.utilities.rank_zero import rank_zero_only

    from data_pipeline.datamodule import ShardDataModule
    from model.config import WorldModelConfig
    from model.export import checkpoint_world_model, read_checkpoint
    from model.interrupt import FitInterrupted, ResumeNotice
    from model.config import ConfigError
    from model.module import PretrainModule, refuse_other_size
    from model.checkpointing import AtomicCheckpointIO, LastStepCheckpoint
    from model.progress import StepProgressBar

    notice = ResumeNotice()

    class PretrainCLI(LightningCLI):
        def add_arguments_to_parser(self, parser) -> None:
            parser.link_arguments("data.k_max", "model.k_max")  # one K_max for sampling and validation

        def _parse_ckpt_path(self) -> None:
            """LightningCLI replaces the model settings with the checkpoint's when resuming; refuse a checkpoint
            whose model size differs from the one asked for instead of silently training another size, and keep
            this run's model.compile (how the step runs on this machine, not what it trains)."""
            subcommand = self.config.get("subcommand") or ""
            config = self.config.get(subcommand, {})
            ckpt_path = config.get("ckpt_path") if config else None
            last = last_checkpoint(config["trainer"]) if config else None
            if ckpt_path == "last":  # Lightning's word for the newest checkpoint: this run's, if it has one yet
                ckpt_path = config["ckpt_path"] = str(last) if last.is_file() else None
                rank_zero_only(print)(f"hauwm pretrain {subcommand}: --ckpt_path last: " + (
                    f"resuming from {last}" if ckpt_path else f"no {last} yet, starting at step 0"), file=sys.stderr)
            elif subcommand == "fit" and ckpt_path is None and last.is_file():
                # a fresh fit there would write last-v1.ckpt beside it, and `--ckpt_path last` would then resume the old run
                raise ConfigError(f"{last.parent} holds the checkpoints of an earlier fit (last.ckpt): go on from it with "
                                  "--ckpt_path last, or start afresh with another --trainer.default_root_dir")
            if not (ckpt_path and Path(ckpt_path).is_file()):
                return super()._parse_ckpt_path()
            checkpoint, saved_sizes = read_checkpoint(ckpt_path)
            checkpoint_world_model(checkpoint, saved_sizes, Path(ckpt_path))  # weights of another layout: refused
            max_steps = config["trainer"]["max_steps"]
            step = checkpoint.get("global_step", 0)
            if subcommand == "fit" and 0 <= max_steps <= step:
                rank_zero_only(print)(f"hauwm pretrain fit: {ckpt_path} is at step {step}, and "
                                      f"--trainer.max_steps is {max_steps}: nothing to train (raise max_steps to go on)",
                                      file=sys.stderr)
            saved = checkpoint["hyper_parameters"]
            asked = WorldModelConfig(**config["model"]["world_model"].as_dict())
            refuse_other_size(saved, asked, str(ckpt_path))
            if "world_model" not in saved:  # read_checkpoint found the sizes, flat at the top level
                raise ConfigError(
                    f"{ckpt_path} keeps the model sizes flat in its hyper_parameters (written before they moved "
                    "under model.world_model), so this version cannot resume it; `hauwm pretrain export` still "
                    "exports it, or resume it with the hauwm version that wrote it"
                )
            asked_model, asked_k_max = config["model"].clone(), config["data"]["k_max"]
            super()._parse_ckpt_path()
            resumed, asked = self.config[subcommand]["model"], flat_settings(asked_model)
            changed = [f"model.{key} {value!r} (asked: {asked[key]!r})" for key, value in flat_settings(resumed).items()
                       if key != "compile" and key in asked and asked[key] != value]
            if saved.get("k_max", asked_k_max) != asked_k_max:  # data.k_max sets model.k_max, also over the checkpoint's
                changed.append(f"data.k_max {saved['k_max']!r} (asked: {asked_k_max!r})")
            if subcommand == "fit" and changed:
                raise ConfigError(f"{ckpt_path} was trained with {', '.join(changed[:3])}: a resume goes on with the "
                                  "settings the fit began with (only model.compile may change); drop the change, or "
                                  "start a new fit in another --trainer.default_root_dir")
            resumed["compile"] = asked_model["compile"]  # how a step runs on this machine, not what it trains

        def before_instantiate_classes(self) -> None:
            config = self.config[self.subcommand]
            if not config.data.shards:
                raise ConfigError("no shard directory: pass --data.shards DIR (built by `hauwm shards build`)")
            refuse_other_frame_size(config.data.shards, "--data.shards")  # and a missing or unfinished directory
            if config.ckpt_path and not Path(config.ckpt_path).is_file():
                raise ConfigError(f"--ckpt_path {config.ckpt_path} does not exist: pass a checkpoint file, or `last` "
                                  "for the run's newest (e.g. RUN/checkpoints/last.ckpt)")
            if self.subcommand == "validate" and not config.ckpt_path:
                print("hauwm pretrain validate: no --ckpt_path, so this scores a freshly initialised model",
                      file=sys.stderr)
            trainer = config.trainer
            if trainer.accelerator in ("gpu", "cuda") and not torch.cuda.is_available():
                raise ConfigError(f"trainer.accelerator is {trainer.accelerator} and no CUDA GPU is visible: for a (slow) "
                                  "CPU run add --trainer.accelerator cpu --trainer.devices 1 --trainer.strategy auto, or "
                                  "use configs/pretrain/tiny.yaml")
            no_cuda = trainer.accelerator == "cpu" or (trainer.accelerator == "auto" and not torch.cuda.is_available())
            if no_cuda and str(trainer.devices) == "-1":  # Lightning's "every GPU"; its CPU accelerator raises a TypeError
                raise ConfigError("trainer.devices -1 means every GPU, and this run is on the CPU: pass --trainer.devices "
                                  "1 (or N processes)")
            checkpointers = [callback for callback in trainer.callbacks or [] if names_a_model_checkpoint(callback)]
            if self.subcommand == "validate":  # writes no checkpoint; restoring one into it only warns of its dirpath
                trainer.enable_checkpointing = False
                trainer.callbacks = [callback for callback in trainer.callbacks or [] if callback not in checkpointers]
            elif trainer.enable_checkpointing is False and checkpointers:  # Lightning would refuse the pair
                print("hauwm pretrain: --trainer.enable_checkpointing false: the config's ModelCheckpoint is left "
                      "out, so this run writes no checkpoint and cannot be resumed", file=sys.stderr)
                trainer.callbacks = [callback for callback in trainer.callbacks if callback not in checkpointers]
            trainer.precision = trainer.precision or "32-true"  # None: Lightning's default
            if str(trainer.precision) not in PRECISIONS:  # half-precision weights: the step's float32 state breaks
                raise ConfigError(f"--trainer.precision {trainer.precision}: a fit runs in {', '.join(PRECISIONS[::2])} "
                                  "(float32 weights, autocast for the rest; 16-mixed is the paper's)")
            if trainer.accumulate_grad_batches != 1:  # Lightning refuses it under the step's manual optimisation
                raise ConfigError(f"--trainer.accumulate_grad_batches {trainer.accumulate_grad_batches}: the step "
                                  "optimises by itself (skipped steps, λ's dual step) and accumulates nothing: raise "
                                  "--data.batch_size instead")
            if trainer.gradient_clip_val is not None:
                raise ConfigError("--trainer.gradient_clip_val: the step clips its own gradients: set --model.grad_clip")
            if str(trainer.precision) in ("16-mixed", "16") and no_cuda:
                print("hauwm pretrain: float16 autocast needs a GPU; using bf16-mixed on CPU", file=sys.stderr)
                trainer.precision = "bf16-mixed"

        def before_fit(self) -> None:
            for callback in self.trainer.checkpoint_callbacks:
                if isinstance(callback, ModelCheckpoint) and callback.dirpath is None:
                    callback.dirpath = str(checkpoint_dir(self.trainer.default_root_dir))
            callbacks = self.trainer.callbacks
            for index, callback in enumerate(callbacks):  # Lightning's own default bar; a user's choice stays
                if type(callback) in (RichProgressBar, TQDMProgressBar):
                    callbacks[index] = StepProgressBar()
            # a fit stopped at max_steps, max_time or by SIGTERM resumes inside its epoch; before the notice, which
            # names the checkpoint it wrote
            callbacks.append(LastStepCheckpoint())
            callbacks.append(notice)  # with or without a progress bar
            if type(self.trainer.strategy.checkpoint_io) is TorchCheckpointIO:  # a user's own plugin stays
                self.trainer.strategy.checkpoint_io = AtomicCheckpointIO()

    # `hauwm` passes its own argv on purpose; Lightning would warn that sys.argv differs
    warnings.filterwarnings("ignore", message="LightningCLI's args parameter is intended")
    # checkpoints after the optimizer step are what resume needs; Lightning warns about it under manual optimisation
    warnings.filterwarnings("ignore", message="Using ModelCheckpoint with manual optimization")
    # training_step logs every log_every_n_steps *global* steps, across epochs (make demo: 30 logs in 300 steps of
    # 9-step epochs at 10); Lightning warns as if epochs shorter than the interval never logged
    warnings.filterwarnings("ignore", message="The number of training batches .* is smaller than the logging interval")
    # Lightning 2.6's own pytree helper uses a torch API that torch 2.14 deprecates (not this project's code)
    warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated")
    logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(not_an_advert)  # once, however often called
    try:
        return PretrainCLI(
            PretrainModule,
            ShardDataModule,
            args=args,
            save_config_kwargs={"overwrite": True},
            parser_kwargs={"prog": "hauwm pretrain",
                           "description": "Pre-train the HAUWM world model (ensemble RSSM + HCU loss) on video shards."},
        )
    except SystemExit:
        if notice.exit_code:  # Lightning's sys.exit(1) after Ctrl-C, or its SIGTERMException
            raise FitInterrupted(notice.exit_code) from None
        raise


def export_command(argv: list[str]) -> int:
    from model.export import CONFIG_FILE, WEIGHTS_FILE, ExportError, export_frozen, world_model_from_checkpoint

    parser = argparse.ArgumentParser(prog="hauwm pretrain export", description="Write the frozen export of a checkpoint.")
    parser.add_argument("checkpoint", type=Path, help="a Lightning checkpoint of `hauwm pretrain fit` (e.g. RUN/checkpoints/last.ckpt)")
    parser.add_argument("--out", type=Path, required=True, help="directory for weights.safetensors and config.json")
    parser.add_argument("--overwrite", action="store_true", help="replace an export already in --out")
    args = parser.parse_args(argv)
    model, provenance = world_model_from_checkpoint(args.checkpoint)
    if not args.overwrite and any((args.out / name).exists() for name in (WEIGHTS_FILE, CONFIG_FILE)):
        raise ExportError(f"--out {args.out} already holds an export; fine-tuning runs made on it check its weights "
                          "and would not resume on others: choose another --out, or pass --overwrite")
    out = export_frozen(model, args.out, provenance)
    print(f"exported {args.checkpoint} (step {provenance['global_step']}, M={model.config.ensemble}) to {out}")
    return 0


def analyze_command(argv: list[str]) -> int:
    from model.analyze import analyze

    parser = argparse.ArgumentParser(
        prog="hauwm pretrain analyze",
        description="Disagreement against the horizon k (with/without HCU) and imagined rollouts per head (fig. 5).",
    )
    parser.add_argument("--model", type=Path, action="append", required=True,
                        help="an export directory (`hauwm pretrain export`); give two to compare, e.g. with and without HCU")
    parser.add_argument("--shards", type=Path, required=True, help="shard directory with a validation split")
    parser.add_argument("--out", type=Path, required=True, help="directory for the PNG plots and figures.json")
    parser.add_argument("--split", default="validation", help="the shards' split to evaluate on (default validation)")
    parser.add_argument("--batches", type=int, default=8, help="held-out batches to average over (default 8)")
    parser.add_argument("--batch-size", type=int, default=8, help="sequences per batch (default 8)")
    parser.add_argument("--seq-len", type=int, default=12, help="frames per sampled sequence (default 12)")
    parser.add_argument("--k-max", type=int, default=None, help="largest gap k (default: the first model's training K_max)")
    parser.add_argument("--heads", type=int, default=4, help="ensemble heads shown side by side in the rollout figure (default 4)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sampled sequences and gaps (default 0)")
    args = parser.parse_args(argv)
    for flag, value, least in (("--batches", args.batches, 1), ("--heads", args.heads, 1), ("--batch-size", args.batch_size, 1),
                               ("--seq-len", args.seq_len, 2),  # a rollout needs a frame to see and one to imagine
                               ("--k-max", 1 if args.k_max is None else args.k_max, 1), ("--seed", args.seed, 0)):
        if value < least:
            parser.error(f"{flag} must be at least {least}, got {value}")
    refuse_other_frame_size(args.shards, "--shards")
    written = analyze(args.model, args.shards, args.out, split=args.split, batches=args.batches,
                      batch_size=args.batch_size, seq_len=args.seq_len, k_max=args.k_max, heads=args.heads, seed=args.seed)
    for path in written:
        print(f"wrote {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(f"usage:\n{USAGE}")
        return 0
    from data_pipeline.loader import LoaderError
    from data_pipeline.shard_format import ShardDirError
    from model.export import ExportError
    from model.interrupt import FitInterrupted
    from model.config import ConfigError

    command = argv[0]
    try:
        if command in LIGHTNING_COMMANDS:
            lightning_cli(argv)
            return 0
        if command == "export":
            return export_command(argv[1:])
        if command == "analyze":
            return analyze_command(argv[1:])
    except (ConfigError, ExportError, LoaderError, ShardDirError) as err:
        print(f"hauwm pretrain {command}: error: {err}", file=sys.stderr)
        return 2
    except FitInterrupted as stop:  # ResumeNotice has said where the fit can resume from
        return stop.exit_code
    except SystemExit as done:  # --help, --print_config, or a flag the parser refused (it printed why)
        return done.code if isinstance(done.code, int) else 2
    print(f"hauwm pretrain: unknown command {command!r}\nusage:\n{USAGE}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
