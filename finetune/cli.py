"""`hauwm finetune`: train an agent on one control task from the frozen pre-trained export.

    hauwm finetune --config configs/finetune/dmc_cheetah_run.yaml --pretrained exports/hauwm
    hauwm finetune --config configs/finetune/demo.yaml --pretrained DIR --steps 2000 --logdir runs/demo
    hauwm finetune --config configs/finetune/dmc_cheetah_run.yaml --set agent=scratch --logdir runs/scratch/cheetah
    hauwm finetune offline --config configs/offline/metaworld_drawer_close.yaml --pretrained DIR --dataset ID
    hauwm finetune imitate --config configs/imitation/metaworld_drawer_close.yaml --pretrained DIR --demos ID
    hauwm finetune evaluate RUNDIR --pretrained DIR [--best] [--episodes 50]

Without a subcommand it runs online RL; `offline` learns from a fixed dataset (no environment step but
evaluation; --steps counts updates there) and `imitate` from expert demonstrations without the
environment's reward (docs/downstream.md). Running again with the same --logdir resumes from its checkpoint.
`evaluate` plays a run's last checkpoint (or with --best its best.pt) for --episodes episodes.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import os
import sys
import time
from pathlib import Path

from hauwm.termination import interrupted_once, sigterm_as_interrupt, stopped_by

# subcommand -> (paradigm, its data flag, the config setting that flag fills, help)
SUBCOMMANDS = {
    "offline": ("offline", "--dataset", "dataset", "offline RL from a fixed dataset (LOMPO-style, eq. 6)"),
    "imitate": ("imitation", "--demos", "demos", "imitation of expert demonstrations (VMAIL-style, eq. 5)"),
}

COMMANDS = {"online": "hauwm finetune", "offline": "hauwm finetune offline", "imitation": "hauwm finetune imitate"}
CONFIG_DIRS = {"online": "configs/finetune", "offline": "configs/offline", "imitation": "configs/imitation"}


def parser(subcommand: str | None = None) -> argparse.ArgumentParser:
    """The arguments of `hauwm finetune` (online RL) or of its `offline` / `imitate` subcommand."""
    from finetune.config import step_unit  # here, as every import of torch: `hauwm finetune` takes SIGTERM first

    prog = "hauwm finetune" + (f" {subcommand}" if subcommand else "")
    paradigm = SUBCOMMANDS[subcommand][0] if subcommand else "online"
    unit, _ = step_unit(paradigm)
    description = __doc__
    if subcommand is not None:  # its line of the module's overview: what it does, its example, where to read on
        example = "\n".join(line for line in __doc__.splitlines() if f"hauwm finetune {subcommand} " in line)
        description = (f"{SUBCOMMANDS[subcommand][3]} (docs/downstream.md)\n\n{example}\n\n--steps counts {unit}s; "
                       "running again with the same --logdir resumes from its checkpoint.")
    p = argparse.ArgumentParser(allow_abbrev=False,
                                prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, help=f"YAML settings, e.g. {CONFIG_DIRS[paradigm]}/dmc_cheetah_run.yaml")
    p.add_argument("--pretrained", help="directory written by `hauwm pretrain export` (weights.safetensors + "
                                        "config.json); not needed with agent=scratch")
    if subcommand is not None:
        _, flag, setting, _ = SUBCOMMANDS[subcommand]
        p.add_argument(flag, dest=setting, metavar="ID", help="dataset id for finetune.datasets (a dataset written by "
                                                               f"`hauwm datasets collect`); overrides the config's {setting}")
    p.add_argument("--steps", type=int, help=f"{unit} budget (overrides the config)")
    kept = "logs, checkpoint.pt, best.pt" + ("" if paradigm == "offline" else ", replay/")
    p.add_argument("--logdir", help=f"run directory: {kept} (overrides the config)")
    p.add_argument("--seed", type=int, help="the run's seed: weights, envs, sampling (overrides the config)")
    p.add_argument("--device", help="auto, cpu, cuda or cuda:N")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config setting, e.g. --set agent=scratch --set batch_size=16")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (for logs)")
    return p


def evaluate_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hauwm finetune evaluate", allow_abbrev=False,
                                description="Play a `hauwm finetune` run's agent (the actor's mode) on its task and print "
                                            "its mean return, normalised return and success rate.")
    p.add_argument("rundir", type=Path, metavar="RUNDIR", help="the run directory (--logdir of the run)")
    p.add_argument("--pretrained", help="the export the run was trained on (not needed for agent=scratch runs)")
    p.add_argument("--best", action="store_true", help="play best.pt (the run's best evaluation) instead of its last checkpoint")
    p.add_argument("--episodes", type=int, help="episodes to play (default: the run's eval_episodes)")
    p.add_argument("--seed", type=int, help="env seed of the first episode (default: the run's seed + 10^9, apart from "
                                             "the seeds of the run's training episodes and evaluations)")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (for logs)")
    return p


def evaluate_run(argv: list[str]) -> int:
    """`hauwm finetune evaluate`: one line with the run's agent's returns over --episodes fresh episodes."""
    from finetune.agent import DivergedError
    from finetune.pretrained import PretrainedError
    from finetune.config import FinetuneError, step_unit
    from finetune.run_dir import BEST, CHECKPOINT, load_trained, run_config
    from finetune.train import HELD_OUT_SEED, evaluate, resolve_device, task_env

    args = evaluate_parser().parse_args(argv)
    try:
        cfg = run_config(args.rundir)
        episodes = cfg.eval_episodes if args.episodes is None else args.episodes
        seed = cfg.seed + HELD_OUT_SEED if args.seed is None else args.seed
        if episodes < 1:
            raise FinetuneError(f"--episodes must be >= 1, got {episodes}")
        if not 0 <= seed < 2**32:
            raise FinetuneError(f"the env seed must lie in 0..2^32-1, got {seed}: pass --seed")
        checkpoint = BEST if args.best else CHECKPOINT
        pretrained = args.pretrained if cfg.agent == "hauwm" else None
        with contextlib.closing(task_env(cfg, seed)) as env:
            cfg, agent, counters = load_trained(args.rundir, pretrained, env.action_space.shape[0],
                                                resolve_device(args.device), checkpoint)
            result = evaluate(agent, env, episodes, cfg.task, seed=seed, progress=not args.no_progress)
    except (DivergedError, FinetuneError, PretrainedError) as error:
        print(f"hauwm finetune evaluate: error: {error}", file=sys.stderr)
        return 2
    unit, key = step_unit(cfg.paradigm)
    print(f"{cfg.task} ({cfg.agent}, {cfg.paradigm}) {args.rundir / checkpoint} at {unit} {counters[key]}, {episodes} "
          f"episodes from env seed {seed}: " + ", ".join(f"{k} {v:.4g}" for k, v in result.items()))
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "evaluate":
        return evaluate_run(argv[1:])
    with interrupted_once(), sigterm_as_interrupt() as terminated:  # the run's own SIGTERM handling comes later
        try:
            return train_command(argv, terminated)
        except KeyboardInterrupt:  # while it imported what it runs (torch: seconds): before anything began
            stopped, status = stopped_by(terminated)
            print(f"hauwm finetune: {stopped}, before the run started", file=sys.stderr)
            return status


def train_command(argv: list[str], terminated: list[int]) -> int:
    """`hauwm finetune [offline|imitate] ...`: read the settings, run (or resume) the run, say how it ended."""
    from finetune.agent import DivergedError
    from finetune.config import FinetuneConfig, FinetuneError, load_config, others_settings, parse_override, step_unit
    from finetune.pretrained import PretrainedError
    from finetune.replay import ReplayError
    from finetune.run_dir import CHECKPOINT, saved_agents
    from hauwm.termination import Terminated
    from model.config import ConfigError

    subcommand = argv[0] if argv and argv[0] in SUBCOMMANDS else None
    args = parser(subcommand).parse_args(argv[1:] if subcommand else argv)
    paradigm = SUBCOMMANDS[subcommand][0] if subcommand else "online"
    stopped, status, cfg = "", 0, None
    try:
        overrides = dict(parse_override(text) for text in args.set)
        if "paradigm" in overrides:
            commands = ", ".join(f"`{command}`" for command in COMMANDS.values())
            raise ConfigError(f"the paradigm is chosen by the command ({commands}), not by a setting: drop --set "
                              f"paradigm={overrides['paradigm']}")
        for key in ("steps", "logdir", "seed", "device", "dataset", "demos"):
            if (flag := getattr(args, key, None)) is not None:
                if key in overrides and not same_value(key, overrides[key], flag):
                    raise ConfigError(f"--{key} {flag} and --set {key}={overrides[key]} disagree: give one")
                overrides[key] = flag
        cfg = load_config(args.config, overrides)
        if cfg.paradigm != paradigm:
            raise ConfigError(f"{args.config} is a config for {cfg.paradigm} training (paradigm: {cfg.paradigm}): run "
                              f"`{COMMANDS[cfg.paradigm]} --config {args.config} …`, or give `{COMMANDS[paradigm]}` "
                              f"a config from {CONFIG_DIRS[paradigm]}/")
        defaults = FinetuneConfig(action_repeat=cfg.action_repeat)  # train_every's default follows it
        for key, owners in others_settings(paradigm).items():  # set (file, --set) for a run that would ignore it
            if getattr(cfg, key) != getattr(defaults, key):
                readers = " and ".join(f"`{COMMANDS[owner]}`" for owner in owners)
                raise ConfigError(f"setting {key} belongs to {readers}, not to `{COMMANDS[paradigm]}`: drop it")
        pretrained = args.pretrained
        if cfg.paradigm == "offline" and cfg.num_envs != 1:  # it steps no training env; a user would expect speed
            print(f"{parser(subcommand).prog}: note: offline RL steps no training env (evaluation plays one), so "
                  f"num_envs {cfg.num_envs} is not used", file=sys.stderr)
        if cfg.agent == "scratch" and pretrained is not None:  # the run ignores it (start_run); say so, pass none
            print(f"{parser(subcommand).prog}: note: the scratch agent does not use --pretrained {pretrained}",
                  file=sys.stderr)
            pretrained = None
        result = _runner(paradigm)(cfg, pretrained, progress=not args.no_progress)
    except DivergedError as error:
        print(f"{parser(subcommand).prog}: error: {error} ({saved_agents(Path(cfg.logdir))})", file=sys.stderr)
        return 2
    except (ConfigError, PretrainedError, FinetuneError, ReplayError) as error:
        print(f"{parser(subcommand).prog}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM before the run's own handling; said below, once the run's frames
        stopped, status = stopped_by(terminated)  # (and its progress bar) are gone
    except Terminated as where:  # SIGTERM: the run wrote its checkpoint of this moment (hauwm/termination.py)
        stopped, status = f"terminated (SIGTERM) at {where}", 143
    if stopped and cfg is None:  # while the settings were read: nothing had started
        print(f"{parser(subcommand).prog}: {stopped}, before the run started", file=sys.stderr)
        return status
    if stopped:
        checkpoint = Path(cfg.logdir) / CHECKPOINT
        written = time.strftime("%H:%M:%S", time.localtime(checkpoint.stat().st_mtime)) if checkpoint.is_file() else ""
        kept = (f"its last checkpoint, {checkpoint} (written {written}), is kept: the same command goes on from there"
                if written else "no checkpoint was written yet: the same command starts it again")
        print(f"{parser(subcommand).prog}: {stopped}; {kept}", file=sys.stderr)
        return status
    kind = cfg.agent if paradigm == "online" else f"{cfg.agent}, {paradigm}"
    unit, _ = step_unit(paradigm)
    if result:
        print(f"finished {cfg.task} ({kind}) in {cfg.logdir}: " + ", ".join(f"{k} {v:.4g}" for k, v in result.items()))
    else:  # every run ends with an evaluation, so this one had nothing left to do
        print(f"nothing to train: {cfg.logdir} has already run its budget of {cfg.steps} {unit}s (a larger --steps "
              f"goes on from its checkpoint); {last_evaluation(Path(cfg.logdir))}")
    print(best_kept(Path(cfg.logdir), unit))
    return 0


def same_value(key: str, setting: object, flag: object) -> bool:
    """Whether a --set value (read as YAML: `2024` is a number) and a flag's say the same (a path: the same path)."""
    if key == "logdir":
        return os.path.normpath(str(setting)) == os.path.normpath(str(flag))
    return str(setting) == str(flag)


def best_kept(logdir: Path, unit: str) -> str:
    """Which evaluation the run's best.pt is of, e.g. 'best evaluation: return 1.3 at update 750, its agent in …'."""
    import torch

    from finetune.run_dir import BEST, CHECKPOINT
    from model.export import torch_load_failure

    if not (logdir / BEST).is_file():
        return "no evaluation has been kept (best.pt is written at evaluations)"
    try:
        counters = torch.load(logdir / BEST, map_location="cpu", weights_only=True, mmap=True)["counters"]
        best_return, best_at = counters["best_return"], counters["best_at"]
    except Exception as err:  # damaged or replaced since the run wrote it: say so; the run itself is done
        why = f"it lacks {err}" if isinstance(err, KeyError) else torch_load_failure(err)
        return f"{logdir / BEST} cannot be read ({why}); the run's {logdir / CHECKPOINT} is not affected"
    return f"best evaluation: return {best_return:.4g} at {unit} {best_at}, its agent in {logdir / BEST}"


def last_evaluation(logdir: Path) -> str:
    """The last row of a run's eval.csv, e.g. 'last evaluation at env_step 400: return 1.085, return_std 0'."""
    rows = []
    if (logdir / "eval.csv").is_file():
        with (logdir / "eval.csv").open(newline="") as f:
            rows = list(csv.DictReader(f))
    if not rows:
        return "no evaluation recorded"
    (step_name, step), *values = rows[-1].items()
    return f"last evaluation at {step_name} {step}: " + ", ".join(f"{k} {float(v):.4g}" for k, v in values if v)


def _runner(paradigm: str):
    """The entry point of a paradigm, imported only when asked for."""
    if paradigm == "offline":
        from finetune.offline import train_offline

        return train_offline
    if paradigm == "imitation":
        from finetune.imitation import train_imitation

        return train_imitation
    from finetune.train import train

    return train


if __name__ == "__main__":
    sys.exit(main())
