"""`hauwm pretrain …`: fit and validate (LightningCLI, model/lightning_cli.py), export, analyze.

    hauwm pretrain fit --config configs/pretrain/ssv2.yaml --data.shards DIR [--trainer.max_steps N] ...
    hauwm pretrain fit --config configs/pretrain/ssv2.yaml --data.shards DIR --ckpt_path last        (resume)
    hauwm pretrain validate --config ... --data.shards DIR --ckpt_path CKPT
    hauwm pretrain fit --help                                          (every --model/--data/--trainer flag)
    hauwm pretrain export CKPT --out DIR
    hauwm pretrain analyze --model DIR [--model DIR2] --shards DIR --out DIR

Every setting of the module (model.*), the data module (data.*) and the Trainer (trainer.*) can be
overridden on the command line after --config; `hauwm pretrain fit --help` lists them. Checkpoints go to
`<trainer.default_root_dir>/checkpoints/` (last.ckpt is always the newest), TensorBoard logs and the
resolved config.yaml to `<trainer.default_root_dir>/lightning_logs/version_N/`.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

USAGE = __doc__.split("\n\n")[1]
LIGHTNING_COMMANDS = ("fit", "validate")


def refuse_other_frame_size(shards: str | Path, flag: str) -> None:
    """Refuse (ConfigError) a shard directory whose frames are not the 64×64 the world model's CNNs read."""
    from data_pipeline.shard_format import read_manifest
    from model.config import ConfigError
    from model.networks import IMAGE_SHAPE

    size, side = read_manifest(shards)["settings"]["size"], IMAGE_SHAPE[-1]
    if size != side:
        raise ConfigError(f"{flag} {shards} holds {size}×{size} frames; the world model reads {side}×{side}: build "
                          f"the shards with `hauwm shards build ... --size {side}`")


def export_command(argv: list[str]) -> int:
    from hauwm.arguments import path
    from model.export import CONFIG_FILE, WEIGHTS_FILE, ExportError, export_frozen, world_model_from_checkpoint

    parser = argparse.ArgumentParser(allow_abbrev=False,
                                     prog="hauwm pretrain export", description="Write the frozen export of a checkpoint.")
    parser.add_argument("checkpoint", type=path, help="a Lightning checkpoint of `hauwm pretrain fit` (e.g. RUN/checkpoints/last.ckpt)")
    parser.add_argument("--out", type=path, required=True, help="directory for weights.safetensors and config.json")
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
    from hauwm.arguments import MAX_SEED, path
    from model.analyze import analyze

    parser = argparse.ArgumentParser(
        prog="hauwm pretrain analyze", allow_abbrev=False,
        description="Disagreement against the horizon k (with/without HCU) and imagined rollouts per head (fig. 5).",
    )
    parser.add_argument("--model", type=path, action="append", required=True,
                        help="an export directory (`hauwm pretrain export`); give two to compare, e.g. with and without HCU")
    parser.add_argument("--shards", type=path, required=True, help="shard directory with a validation split")
    parser.add_argument("--out", type=path, required=True, help="directory for the PNG plots and figures.json")
    parser.add_argument("--overwrite", action="store_true", help="replace an analysis already in --out")
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
    if args.seed > MAX_SEED:  # torch's generator overflowed, after the batches were read
        parser.error(f"--seed must be at most {MAX_SEED}, got {args.seed}")
    refuse_other_frame_size(args.shards, "--shards")
    written = analyze(args.model, args.shards, args.out, split=args.split, batches=args.batches,
                      batch_size=args.batch_size, seq_len=args.seq_len, k_max=args.k_max, heads=args.heads, seed=args.seed,
                      overwrite=args.overwrite)
    for file in written:
        print(f"wrote {file}")
    return 0


def peer_lost(err: RuntimeError) -> str | None:
    """What to say when a collective failed because another rank of a DDP job stopped (its own error, or a kill),
    None for any other RuntimeError: gloo raises a bare RuntimeError from its transport, NCCL a DistBackendError."""
    import torch.distributed as dist

    from hauwm.messages import first_line

    if not (isinstance(err, dist.DistError) or "third_party/gloo" in str(err)):
        return None
    rank = dist.get_rank() if dist.is_initialized() else os.environ.get("RANK", "?")
    reason = first_line(err).split("] ", 1)[-1].split(". ", 1)[0][:160]
    return (f"rank {rank} lost the other ranks of the job ({reason}): a rank stopped first, and its own error, or the "
            "signal that killed it, says why (above, or in its node's log)")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(f"usage:\n{USAGE}")
        return 0
    from data_pipeline.dataset import LoaderError
    from data_pipeline.shard_format import ShardDirError
    from model.export import ExportError
    from model.interrupt import FitInterrupted
    from model.config import ConfigError

    command = argv[0]
    try:
        if command in LIGHTNING_COMMANDS:
            from lightning.fabric.utilities.exceptions import MisconfigurationException

            from model.lightning_cli import lightning_cli

            try:
                lightning_cli(argv)
            except MisconfigurationException as err:  # a --trainer value Lightning itself refuses (devices 0, max_steps -5)
                raise ConfigError(f"a --trainer setting Lightning refuses: {err}") from None
            except ValueError as err:  # one it refuses only once it knows an epoch's length, as a plain ValueError
                if "`val_check_interval`" not in str(err):
                    raise
                raise ConfigError(f"a --trainer setting Lightning refuses: {str(err).strip()}") from None
            return 0
        if command == "export":
            return export_command(argv[1:])
        if command == "analyze":
            return analyze_command(argv[1:])
    except (ConfigError, ExportError, LoaderError, ShardDirError) as err:
        print(f"hauwm pretrain {command}: error: {err}", file=sys.stderr)
        return 2
    except RuntimeError as err:
        if (lost := peer_lost(err)) is None:
            raise
        print(f"hauwm pretrain {command}: error: {lost}", file=sys.stderr)
        return 2
    except FitInterrupted as stop:  # ResumeNotice has said where the fit can resume from
        return stop.exit_code
    except SystemExit as done:  # --help, --print_config, or a flag the parser refused (it printed why)
        return done.code if isinstance(done.code, int) else 2
    print(f"hauwm pretrain: unknown command {command!r}\nusage:\n{USAGE}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
