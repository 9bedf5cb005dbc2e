"""`hauwm finetune`: train an agent on one control task from the frozen pre-trained export.

    hauwm finetune --config configs/finetune/dmc_cheetah_run.yaml --pretrained exports/hauwm
    hauwm finetune --config configs/finetune/demo.yaml --pretrained DIR --steps 2000 --logdir runs/demo
    hauwm finetune --config configs/finetune/dmc_cheetah_run.yaml --set agent=scratch   # baseline

Running again with the same --logdir resumes from its checkpoint.
"""

from __future__ import annotations

import argparse
import sys


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hauwm finetune", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, help="YAML settings, e.g. configs/finetune/dmc_cheetah_run.yaml")
    p.add_argument("--pretrained", help="directory written by `hauwm pretrain export` (weights.safetensors + "
                                        "config.json); not needed with agent=scratch")
    p.add_argument("--steps", type=int, help="env-step budget (overrides the config)")
    p.add_argument("--logdir", help="run directory: logs, checkpoint, replay (overrides the config)")
    p.add_argument("--seed", type=int)
    p.add_argument("--device", help="auto, cpu or cuda")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config setting, e.g. --set agent=scratch --set batch_size=16")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (for logs)")
    return p


def main(argv: list[str] | None = None) -> int:
    from finetune.config import ConfigError, load_config, parse_override
    from finetune.pretrained import PretrainedError
    from finetune.train import FinetuneError, train

    args = parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        overrides = dict(parse_override(text) for text in args.set)
        for key in ("steps", "logdir", "seed", "device"):
            if getattr(args, key) is not None:
                overrides[key] = getattr(args, key)
        cfg = load_config(args.config, overrides)
        result = train(cfg, args.pretrained, progress=not args.no_progress)
    except (ConfigError, PretrainedError, FinetuneError) as error:
        print(f"hauwm finetune: error: {error}", file=sys.stderr)
        return 2
    summary = ", ".join(f"{k} {v:.4g}" for k, v in result.items())
    print(f"finished {cfg.task} ({cfg.agent}) in {cfg.logdir}: {summary or 'no evaluation yet'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
