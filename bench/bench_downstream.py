"""Learning checks of offline RL and imitation on a CPU: Meta-World drawer close from 64×64 pixels.

    python bench/bench_downstream.py --pretrained DIR                          # everything, hours on a CPU
    python bench/bench_downstream.py --pretrained DIR --only offline --updates 600
    python bench/bench_downstream.py --pretrained DIR --report                 # the table of finished runs
    python bench/bench_downstream.py --pretrained DIR --report --runs offline_lam0 offline_lam50 --final-episodes 50

One command, in LOGDIR (default runs/bench_downstream), each step skipped when its output is there:

1. datasets (Minari, under LOGDIR/minari unless MINARI_DATASETS_PATH is set): clean scripted-expert
   episodes, noisy ones (the expert with N(0, σ²) action noise: the "medium" part), their merge (medexp;
   with --random-episodes, random-policy episodes too), and ≤ 10 separate expert demonstrations;
2. the random policy's and the expert's returns at the same env settings (10 episodes each);
3. offline RL on medexp with the penalty u of --penalty (default loglik_std), one run per λ of --lams
   (default 5 and 0), and the same at the first λ with the frozen stream's disagreement added (one run per
   --frozen-weights w > 0);
4. imitation from the demonstrations;
5. a table: return over the last evaluation's 10 episodes (mean ± std), normalised between the random
   policy (0) and the scripted expert (1) measured here at the same settings (short episodes, so Table 4's
   500-step references do not apply), and the success rate; u on dataset vs imagined states;
6. with --final-episodes N: every run's last checkpoint, its best evaluation's (best.pt) and both
   references played again for N episodes, all from the same env seed (the same goal placements), since
   10 episodes tell 30% from 40% success poorly (a binomial standard error of 15 points).

On a GPU, the repeat on a DMC task (no scripted expert there): an online run first, whose replay is the
medium part and whose best agent (best.pt) plays the expert part and the demonstrations (`--from-run`), then the same
runs at Table 3 sizes (`--gpu`; several calls of under 10 minutes each, as every step resumes):

    python bench/bench_learning.py --gpu --agent hauwm --pretrained DIR --logdir runs/cheetah
    python bench/bench_downstream.py --gpu --from-run runs/cheetah --pretrained DIR --lams 50 0 \
        --updates 1500 --imitation-steps 20000 --logdir runs/bench_downstream_dmc --final-episodes 20

Runs resume from their checkpoints (a --logdir that holds a run goes on). Small networks for the CPU
(CPU_SETTINGS below), fast rendering, action repeat 2, 100-step episodes (200 simulator steps). Other
settings of `hauwm finetune` go to every run with --set KEY=VALUE; --tag names such a variant's runs
(`offline_lam5-TAG`), so that they sit beside the default ones in the same --logdir.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import describe_machine  # noqa: E402
from hauwm.arguments import at_least  # noqa: E402
from finetune.config import PENALTIES  # noqa: E402
from hauwm.termination import Terminated  # noqa: E402

TASK = "metaworld_drawer_close"  # without --from-run: Meta-World's scripted expert makes the data free
ENV = dict(action_repeat=2, time_limit=100, fast_render=True)
CPU_SETTINGS = dict(batch_size=16, seq_len=16, units=200, hidden=100, log_every=50, device="cpu", threads=1)
GPU_SETTINGS = dict(device="cuda", log_every=250)  # Table 3 sizes (FinetuneConfig's defaults), compiled updates
OFFLINE = dict(paradigm="offline", model_heads=7, horizon=5)
IMITATION = dict(paradigm="imitation", horizon=15, prefill=1000, train_every=8, demo_fraction=0.5)


def noise_tag(args: argparse.Namespace) -> str:
    """'' for the default σ 0.5 of the noisy part, else σ (e.g. '1')."""
    return "" if args.noise == 0.5 else f"{args.noise:g}"


def variant(args: argparse.Namespace) -> str:
    """What sets this invocation's medexp apart from the default one (σ 0.5, no random episodes): '' or
    e.g. '1r20' (σ 1, 20 random episodes)."""
    return noise_tag(args) + (f"r{args.random_episodes}" if args.random_episodes else "")


def dataset_ids(args: argparse.Namespace) -> dict[str, str]:
    """The datasets' ids; the noisy part names its σ, and medexp its variant, when they are not the default.
    With --from-run the medium part is the run's replay and the expert its best evaluation's agent (best.pt)."""
    name = args.task.split("_", 1)[1]  # drawer_close, cheetah_run
    medium = "replay" if args.from_run else f"noisy{noise_tag(args)}"
    expert = "agent" if args.from_run else "expert"
    return {"expert": f"bench/{name}-{expert}-v0", "medium": f"bench/{name}-{medium}-v0",
            "random": f"bench/{name}-random-v0", "medexp": f"bench/{name}-medexp{variant(args)}-v0",
            "demos": f"bench/{name}-{'agentdemos' if args.from_run else 'demos'}-v0"}


def datasets(args: argparse.Namespace) -> dict[str, str]:
    """Collect (or find) the datasets (expert, noisy, demos, random with --random-episodes) and merge medexp;
    returns their ids."""
    from finetune.datasets import list_datasets
    from finetune.datasets.cli import main as datasets_cli

    ids = dataset_ids(args)
    task = ["--task", args.task, *[item for key, value in args.env.items() if value is not None
                                   for item in ("--set", f"{key}={value}")]]
    if args.from_run:  # the run's replay, and its agent's episodes (the run's env settings come with it)
        agent = ["--policy", "agent", "--checkpoint", str(args.from_run), "--best", "--pretrained", str(args.pretrained),
                 "--device", args.sizes["device"]]
        plans = {"expert": [*agent, "--episodes", str(args.expert_episodes), "--seed", "0"],
                 "medium": ["--from-run", str(args.from_run)],
                 "demos": [*agent, "--episodes", str(args.demos), "--seed", "2"]}
    else:
        plans = {"expert": [*task, "--policy", "expert", "--episodes", str(args.expert_episodes), "--seed", "0"],
                 "medium": [*task, "--policy", "expert", "--action-noise", str(args.noise), "--episodes",
                            str(args.noisy_episodes), "--seed", "1"],
                 "demos": [*task, "--policy", "expert", "--episodes", str(args.demos), "--seed", "2"]}
    if args.random_episodes:
        plans["random"] = [*task, "--policy", "random", "--episodes", str(args.random_episodes), "--seed", "3"]
    have = set(list_datasets())
    for name, plan in plans.items():
        if ids[name] not in have:
            if datasets_cli(["collect", "--dataset-id", ids[name], *plan, "--no-progress"]) != 0:
                sys.exit(f"collecting {ids[name]} failed")
    parts = [ids["medium"], ids["expert"]] + ([ids["random"]] if args.random_episodes else [])
    if ids["medexp"] not in have and datasets_cli(["merge", *parts, "--out", ids["medexp"], "--no-progress"]) != 0:
        sys.exit("merging medexp failed")
    return ids


def references(args: argparse.Namespace, episodes: int, seed: int) -> dict[str, tuple[float, float, float]]:
    """(mean return, its std, success rate) of the random policy and the expert (Meta-World's scripted one, or
    with --from-run the run's best evaluation's agent), `episodes` each."""
    from finetune.datasets.sources import ExpertPolicy, RandomPolicy, load_agent_policy
    from finetune.envs import make_env
    from finetune.rollout import play_episode
    from finetune.run_dir import BEST

    result = {}
    for name in ("random", "expert"):
        env = make_env(args.task, seed=seed, **args.env)
        env.action_space.seed(seed)
        if name == "random":
            policy = RandomPolicy(env.action_space)
        elif args.from_run:
            policy = load_agent_policy(args.from_run, args.pretrained, args.sizes["device"], False,
                                       env.action_space.shape[0], BEST)
        else:
            policy = ExpertPolicy(env, 0.0, seed)
        played = [play_episode(env, policy, seed=seed if i == 0 else None) for i in range(episodes)]
        returns = [float(p["reward"].sum(dtype=np.float64)) for p in played]
        successes = [p["success"].any() for p in played if "success" in p] or [float("nan")]  # DMC: no success
        result[name] = (float(np.mean(returns)), float(np.std(returns)), float(np.mean(successes)))
        env.close()
    return result


def run(name: str, settings: dict, args: argparse.Namespace) -> None:
    from finetune.config import load_config
    from finetune.imitation import train_imitation
    from finetune.offline import train_offline

    cfg = load_config(None, {**args.sizes, **args.env, "task": args.task, "seed": args.seed,
                             "logdir": str(args.logdir / name), "eval_episodes": args.eval_episodes, **settings})
    started = time.perf_counter()
    print(f"== {name}: {cfg.steps} {'updates' if cfg.paradigm == 'offline' else 'env steps'}", flush=True)
    (train_offline if cfg.paradigm == "offline" else train_imitation)(cfg, args.pretrained, progress=not args.no_progress)
    print(f"   {name} done in {(time.perf_counter() - started) / 60:.1f} min", flush=True)


def read_rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open() as f:
        return list(csv.DictReader(f))


def percent(rate: float) -> str:
    """A success rate as a percentage; "—" where the suite has none (DMC: NaN)."""
    return "—" if math.isnan(rate) else f"{rate:.0%}"


def report(args: argparse.Namespace, names: list[str], refs: dict[str, tuple[float, float, float]]) -> None:
    low, high = refs["random"][0], refs["expert"][0]
    print(f"\nmachine: {describe_machine(args.sizes['device'])}")
    from finetune.train import EVAL_SEED

    print(f"settings: task {args.task}, {args.env}, seed {args.seed} (the references below play env seed "
          f"{args.seed} + {EVAL_SEED}; each evaluation of a run, seed + {EVAL_SEED} + its step: other placements, a "
          "rough comparison; the replay after, with --final-episodes, plays all on one env seed)")
    print(f"{'run':<28} {'at':>8} {f'return ({args.eval_episodes} episodes)':>22} {'normalised':>11} {'success':>8} "
          f"{'u dataset':>10} {'u imagined':>11}")
    for name, (mean, std, success) in refs.items():
        print(f"{name + ' policy':<28} {'':>8} {mean:>12.1f} ± {std:<7.1f} {(mean - low) / (high - low):>11.2f} "
              f"{percent(success):>8}")
    curves = []
    for name in names:
        evaluations = read_rows(args.logdir / name / "eval.csv")
        if not evaluations:
            print(f"{name:<28} (no evaluation yet)")
            continue
        evaluation, step_key = evaluations[-1], "update" if "update" in evaluations[-1] else "env_step"
        train = (read_rows(args.logdir / name / "train.csv") or [{}])[-1]
        mean, std = float(evaluation["return"]), float(evaluation["return_std"])
        u = [f"{float(train[key]):>10.3g}" if train.get(key) else f"{'':>10}"
             for key in ("penalty_u_dataset", "penalty_u_imagined")]
        print(f"{name:<28} {step_key[0] + evaluation[step_key]:>8} {mean:>12.1f} ± {std:<7.1f} "
              f"{(mean - low) / (high - low):>11.2f} {percent(float(evaluation.get('success_rate', 'nan'))):>8} {u[0]} "
              f"{u[1]}")
        curves.append(f"{name}: " + ", ".join(
            f"{row[step_key]}: {float(row['return']):.0f} ({percent(float(row.get('success_rate', 'nan')))})"
            for row in evaluations))
    print("\nevery evaluation, as updates (offline) or env steps (imitation): return (success rate)")
    print("\n".join(curves))


def final_report(args: argparse.Namespace, names: list[str]) -> None:
    """Each run's last and best checkpoints and both references, --final-episodes episodes each from one env seed."""
    from finetune.config import step_unit
    from finetune.envs import make_env
    from finetune.run_dir import BEST, CHECKPOINT, load_trained
    from finetune.train import evaluate, resolve_device

    episodes, seed = args.final_episodes, args.seed + 20_000
    refs = references(args, episodes, seed)
    low, high = refs["random"][0], refs["expert"][0]
    print(f"\nlast checkpoints and the best evaluations' (best.pt, marked *) played again: {episodes} episodes each, "
          f"env seed {seed} for all")
    print(f"{'run':<28} {'at':>8} {'return':>20} {'normalised':>11} {'success':>8} {'± s.e.':>7}")

    def row(name: str, at: str, mean: float, std: float, success: float) -> None:
        stderr = (success * (1 - success) / episodes) ** 0.5
        print(f"{name:<28} {at:>8} {mean:>10.1f} ± {std:<7.1f} {(mean - low) / (high - low):>11.2f} "
              f"{percent(success):>8} {percent(stderr):>7}", flush=True)

    for name, (mean, std, success) in refs.items():
        row(name + " policy", "", mean, std, success)
    for name in names:
        logdir = args.logdir / name
        if not (logdir / CHECKPOINT).exists():
            print(f"{name:<28} (no checkpoint yet)")
            continue
        played = set()
        for checkpoint in (CHECKPOINT, BEST):
            if not (logdir / checkpoint).exists():  # a run from before best.pt existed
                continue
            env = make_env(args.task, seed=seed, **args.env)
            cfg, agent, counters = load_trained(logdir, args.pretrained, env.action_space.shape[0],
                                                resolve_device(args.sizes["device"]), checkpoint=checkpoint)
            unit, key = step_unit(cfg.paradigm)
            at = f"{unit[0]}{counters[key]}"  # u750: update 750, e12000: env step 12,000
            if at not in played:  # best.pt of the last evaluation is the last checkpoint
                result = evaluate(agent, env, episodes, args.task, seed=seed)
                row(name + ("*" if checkpoint == BEST else ""), at, result["return"], result["return_std"],
                    result.get("success_rate", float("nan")))
            played.add(at)
            env.close()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pretrained", required=True, help="export of `hauwm pretrain export` (e.g. make demo's)")
    p.add_argument("--logdir", type=Path, default=Path("runs/bench_downstream"))
    p.add_argument("--only", choices=["offline", "imitation"], help="run one paradigm only")
    p.add_argument("--updates", type=at_least(1), default=1500, help="offline updates per run")
    p.add_argument("--imitation-steps", type=at_least(1), default=20_000, help="imitation env steps")
    p.add_argument("--lams", type=float, nargs="+", default=[5.0, 0.0],
                   help="λ of eq. 6: one offline run per value (a sweep; LOMPO's default is 5)")
    p.add_argument("--penalty", default="loglik_std", choices=PENALTIES,
                   help="u of eq. 6 for the offline runs (finetune/penalty.py); runs of another than loglik_std are "
                        "named offline_PENALTY_lamλ")
    p.add_argument("--frozen-weights", type=float, nargs="*", default=[],
                   help="extra offline runs at the first of --lams with the frozen disagreement's weight w > 0")
    p.add_argument("--expert-episodes", type=at_least(1), default=20)
    p.add_argument("--noisy-episodes", type=at_least(1), default=40)
    p.add_argument("--noise", type=float, default=0.5,
                   help="σ of the noisy expert's action noise; another than 0.5 makes its own datasets and offline "
                        "runs (-medexpσ)")
    p.add_argument("--random-episodes", type=at_least(0), default=0,
                   help="random-policy episodes added to medexp (its own datasets and runs, -medexp…rN)")
    p.add_argument("--demos", type=at_least(1), default=10, help="expert demonstrations for imitation (≤ 10)")
    p.add_argument("--eval-episodes", type=at_least(1), default=10, help="episodes per evaluation (and per reference)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting of hauwm finetune for every run (e.g. --set entropy_scale=1e-3); use with --tag")
    p.add_argument("--tag", default="", help="suffix of this invocation's run names (a variant made with --set)")
    p.add_argument("--report", action="store_true", help="only print the table of what has run")
    p.add_argument("--runs", nargs="+", help="with --report: these run directories of LOGDIR instead of the planned ones")
    p.add_argument("--final-episodes", type=at_least(0), default=0,
                   help="play every run's last checkpoint, its best.pt and the references again for this many episodes")
    p.add_argument("--from-run", type=Path, metavar="RUNDIR",
                   help="a `hauwm finetune` run (e.g. bench_learning.py --gpu's) whose task, replay (the medium part) "
                        "and agent (the expert part and the demonstrations) make the datasets, for DMC and RoboDesk")
    p.add_argument("--gpu", action="store_true", help="Table 3 sizes on a CUDA device (GPU_SETTINGS) instead of the CPU's")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args()
    from finetune.config import parse_override
    from finetune.datasets import DatasetError
    from finetune.datasets.sources import run_config
    from finetune.pretrained import PretrainedError, load_pretrained

    if args.demos > 10:
        p.error(f"argument --demos: issue 13's check imitates from at most 10 demonstrations, got {args.demos}")
    try:  # before minutes of collecting datasets
        load_pretrained(args.pretrained)
    except PretrainedError as error:
        p.error(f"argument --pretrained: {error}")

    args.sizes = GPU_SETTINGS if args.gpu else CPU_SETTINGS
    args.task, args.env = TASK, ENV
    if args.from_run:
        try:
            source = run_config(args.from_run)
        except DatasetError as error:
            p.error(f"argument --from-run: {error}")
        args.task, args.env = source.task, source.env_settings

    args.logdir.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("MINARI_DATASETS_PATH", str((args.logdir / "minari").resolve()))
    import torch

    torch.set_num_threads(1)
    ids = datasets(args) if not args.report else dataset_ids(args)
    every = max(1, args.updates // 4)
    overrides = dict(parse_override(text) for text in args.set)
    user_tag = f"-{args.tag}" if args.tag else ""
    tag = (f"-medexp{variant(args)}" if variant(args) else "") + user_tag  # offline runs: their dataset too
    kind = "" if args.penalty == "loglik_std" else f"_{args.penalty}"
    offline = {f"offline{kind}_lam{lam:g}{tag}": dict(penalty_scale=lam) for lam in args.lams}
    offline.update({f"offline{kind}_lam{args.lams[0]:g}_frozen{w:g}{tag}": dict(penalty_scale=args.lams[0],
                                                                                penalty_frozen_weight=w)
                    for w in args.frozen_weights if w > 0})
    plans = {} if args.only == "imitation" else {
        name: {**OFFLINE, **extra, "penalty": args.penalty, "dataset": ids["medexp"], "steps": args.updates,
               "eval_every": every, "checkpoint_every": every, **overrides} for name, extra in offline.items()}
    if args.only != "offline":
        plans[f"imitation{user_tag}"] = {**IMITATION, "demos": ids["demos"], "steps": args.imitation_steps,
                                    "eval_every": max(2000, args.imitation_steps // 5), "checkpoint_every": 2000,
                                    **overrides}
    status = 0
    try:
        for name, settings in ({} if args.report else plans).items():
            run(name, settings, args)
    except Terminated as where:  # e.g. a `timeout` around the call: the runs so far are still reported
        print(f"bench_downstream: {name} terminated (SIGTERM) at {where}; {args.logdir / name} keeps its checkpoint "
              "of that moment: the same command goes on from there", flush=True)
        status = 143
    names = args.runs if args.report and args.runs else list(plans)
    from finetune.train import EVAL_SEED

    # the references play env seed + EVAL_SEED; each evaluation of a run plays seed + EVAL_SEED + its step, so the
    # table's last evaluations met other placements than the references did: --final-episodes plays all on one seed
    report(args, names, references(args, args.eval_episodes, args.seed + EVAL_SEED))
    if args.final_episodes and not status:
        final_report(args, names)
    return status


if __name__ == "__main__":
    sys.exit(main())
