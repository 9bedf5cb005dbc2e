"""Learning check on a cheap DMC pixel task: does the evaluation return rise well above a random policy's?

    python bench/bench_learning.py                                   # scratch agent, cartpole swing-up, 25 min
    python bench/bench_learning.py --agent hauwm --pretrained DIR --minutes 60
    python bench/bench_learning.py --minutes 2 --logdir /tmp/quick   # a smoke run
    python bench/bench_learning.py --set model_lr=6e-4 --set actor_lr=2e-4 --set critic_lr=2e-4
    python bench/bench_learning.py --plot runs/a runs/b --out curve.png  # redraw finished runs together
    python bench/bench_learning.py --gpu --agent hauwm --pretrained DIR  # cheetah run, Table 3 sizes, 10 GPU min
    python bench/bench_learning.py --gpu --agent hauwm --make-export 300 --chunk 20000  # on a bare GPU machine

Runs `finetune.train.train` in chunks of `--chunk` env steps (each chunk resumes the last from its
checkpoint; a --logdir that holds a run goes on from it) until the wall-clock budget is spent, with small
networks that fit a CPU. Then it plays random-policy episodes for the baseline, prints a table of eval
returns, a summary per run (best, last, the evals from 20k env steps against the random policy) and the
critic's loss every 10k env steps, and draws eval return against env steps (`learning_curve.png` in the
log directory; `--plot` draws several finished runs of one task in one figure). Settings and machine are
printed with the figures. `--gpu`: the paper's sizes on one CUDA device instead (compiled updates, four
envs in worker processes, cheetah run by default), in one chunk of 50,000 env steps (each chunk would
compile the update anew).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import describe_machine  # noqa: E402
from finetune.config import load_config, parse_override  # noqa: E402
from hauwm.termination import Terminated  # noqa: E402
from finetune.run_dir import run_config  # noqa: E402
from finetune.train import train  # noqa: E402

# small enough for a shared CPU: ~1 update/s on one loaded core
CPU_SETTINGS = dict(
    action_repeat=8, prefill=2000, train_every=8, batch_size=16, seq_len=16, units=200, hidden=100, deter=100,
    stoch=20, encoder_width=8, eval_every=2000, eval_episodes=3, log_every=500, checkpoint_every=2000,
    fast_render=True, device="cpu", threads=1,
)
# Table 3's sizes and schedule (finetune/config.py defaults) on one GPU: CUDA graphs, envs rendered with EGL
GPU_SETTINGS = dict(device="cuda", compile="auto", num_envs=4, eval_every=10_000, eval_episodes=5, log_every=1000,
                    checkpoint_every=10_000)


class UniformOrConstant:
    """A finetune.rollout policy: uniform random actions drawn from `rng` (constant None) or one constant action."""

    def __init__(self, shape: tuple[int, ...], rng: np.random.Generator, constant: float | None = None) -> None:
        self.shape, self.rng, self.constant = shape, rng, constant

    def reset(self) -> None:
        pass

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        if self.constant is None:
            return self.rng.uniform(-1, 1, self.shape).astype(np.float32)
        return np.full(self.shape, self.constant, np.float32)


def random_returns(task: str, action_repeat: int, time_limit: int | None, episodes: int, seed: int = 123) -> list[float]:
    from finetune.envs import make_env
    from finetune.rollout import play_episode

    env = make_env(task, seed=seed, action_repeat=action_repeat, time_limit=time_limit, fast_render=True)
    policy = UniformOrConstant(env.action_space.shape, np.random.default_rng(seed))
    return [float(play_episode(env, policy)["reward"].sum()) for _ in range(episodes)]


def plot_curves(curves: dict[str, list[tuple[int, float]]], baseline: list[float], title: str, path: Path) -> None:
    """Eval return against env steps, one line per run, and the random policy's mean ± std."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.5))
    for label, points in curves.items():
        ax.plot(*zip(*points), marker="o", label=label)
    mean, std = np.mean(baseline), np.std(baseline)
    ax.axhline(mean, color="gray", linestyle="--", label="random policy (mean ± std)")
    ax.axhspan(mean - std, mean + std, color="gray", alpha=0.15)
    ax.set_xlabel("env steps (frames)")
    ax.set_ylabel("episode return")
    ax.set_title(title)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1))  # outside: runs overlap late
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def read_evals(logdir: Path) -> list[tuple[int, float]]:
    with open(logdir / "eval.csv") as f:
        return [(int(r["env_step"]), float(r["return"])) for r in csv.DictReader(f)]


def critic_losses(logdir: Path, every: int = 10_000) -> str:
    """The critic's loss from train.csv at every `every` env steps: a loss that keeps doubling is a critic
    diverging (the plain-MLP critic of the HAUWM agent did; see layer_norm in finetune/behavior.py)."""
    if not (logdir / "train.csv").exists():
        return "— (no updates yet)"
    with open(logdir / "train.csv") as f:
        rows = [(int(r["env_step"]), float(r["critic_loss"])) for r in csv.DictReader(f)]
    marks = range(every, rows[-1][0] + 1, every)  # the first row logged at or after each mark
    losses = [f"{mark // 1000}k: {next(loss for step, loss in rows if step >= mark):.3g}" for mark in marks]
    return ", ".join(losses) or f"— (under {every // 1000}k env steps)"


def summarize(name: str, points: list[tuple[int, float]], baseline: list[float], late: int = 20_000) -> str:
    """One line per run: best and last eval, and how the evals from `late` env steps on compare with the
    random policy (their mean, and how many lie above its mean + 1 std)."""
    mean, bar = np.mean(baseline), np.mean(baseline) + np.std(baseline)
    best = max(ret for _, ret in points)
    line = f"{name}: best {best:.1f} = {best / max(mean, 1e-9):.1f}× random mean; last {points[-1][1]:.1f} at {points[-1][0]}"
    later = [ret for step, ret in points if step >= late]
    if later:
        above = sum(ret > bar for ret in later)
        line += f"; evals from {late}: mean {np.mean(later):.1f}, {above} of {len(later)} above random mean + std ({bar:.1f})"
    return line


def report(logdirs: list[Path], out: Path, minutes: float | None = None) -> None:
    """Random-policy baseline, a table of eval returns (one column per run) and the curve PNG."""
    configs = [run_config(logdir) for logdir in logdirs]
    task, action_repeat, time_limit = configs[0].task, configs[0].action_repeat, configs[0].time_limit
    baseline = random_returns(task, action_repeat, time_limit, episodes=10)  # episodes as long as the runs' own
    curves = {f"{d.name}: {c.agent} agent, seed {c.seed}": read_evals(d) for c, d in zip(configs, logdirs)}
    print(f"\nrandom policy: {np.mean(baseline):.1f} ± {np.std(baseline):.1f} (10 episodes, action repeat {action_repeat})")
    steps = sorted({step for points in curves.values() for step, _ in points})
    print(f"{'env steps':>10} " + " ".join(f"{d.name:>20}" for d in logdirs))
    for step in steps:
        row = [dict(points).get(step) for points in curves.values()]
        print(f"{step:>10} " + " ".join(f"{'—' if r is None else f'{r:.1f}':>20}" for r in row))
    for d, points in zip(logdirs, curves.values()):
        print(summarize(d.name, points, baseline))
        print(f"  critic loss (train.csv) {critic_losses(d)}")
    budget = f", {minutes:.0f} min" if minutes is not None else ""
    where = "one GPU" if configs[0].device.startswith("cuda") else "shared CPU"
    plot_curves(curves, baseline, f"{task}, {where}{budget}", out)
    print(f"curve: {out}")


def make_export(logdir: Path, steps: int, gpu: bool) -> Path:
    """An export to fine-tune from, made here (LOGDIR-export; kept, and reused by a later call): the built-in
    sample data and its shards (bench_gpu's), `steps` eager steps of configs/pretrain/ssv2.yaml on one device
    (--gpu; tiny.yaml on the CPU) without validation, exported. A GPU machine starts bare, and a Table 3-size
    export (37.5 MB) is too large to carry there."""
    from bench.bench_gpu import sample_shards
    from model.cli import main as pretrain

    export, work = logdir.with_name(logdir.name + "-export"), logdir.with_name(logdir.name + "-pretrain")
    if (export / "config.json").exists():
        return export
    started = time.perf_counter()
    shards = work / "shards" if (work / "shards" / "manifest.json").exists() else sample_shards(work)
    fit = ["fit", "--config", f"configs/pretrain/{'ssv2' if gpu else 'tiny'}.yaml", "--data.shards", str(shards),
           "--model.compile", "off", "--trainer.max_steps", str(steps), "--trainer.limit_val_batches", "0",
           "--trainer.default_root_dir", str(work / "run"), "--trainer.enable_progress_bar", "false",
           "--ckpt_path", "last"] + (["--trainer.devices", "1", "--trainer.strategy", "auto"] if gpu else [])
    if pretrain(fit) != 0 or pretrain(["export", str(work / "run" / "checkpoints" / "last.ckpt"), "--out",
                                       str(export)]) != 0:
        raise SystemExit("bench_learning: making the export failed (above)")
    print(f"export: {export} ({steps} pre-training steps, {(time.perf_counter() - started) / 60:.1f} min)", flush=True)
    return export


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gpu", action="store_true", help="Table 3 sizes on a CUDA device (GPU_SETTINGS)")
    parser.add_argument("--task", help="default: dmc_cartpole_swingup (CPU), dmc_cheetah_run (--gpu)")
    parser.add_argument("--agent", default="scratch", choices=["scratch", "hauwm"])
    parser.add_argument("--pretrained", help="export directory (agent hauwm)")
    parser.add_argument("--make-export", type=int, metavar="STEPS",
                        help="agent hauwm without --pretrained: pre-train STEPS steps on the built-in sample data "
                             "first and fine-tune from that export (for a GPU machine that starts bare)")
    parser.add_argument("--minutes", type=float, help="wall-clock budget for training (default 25; --gpu 10)")
    parser.add_argument("--chunk", type=int, help="env steps per resumed chunk (default 2000; --gpu 50000)")
    parser.add_argument("--logdir", default="runs/bench_learning")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a setting")
    parser.add_argument("--plot", nargs="+", type=Path, metavar="LOGDIR", help="only redraw these finished runs")
    parser.add_argument("--out", type=Path, help="PNG path (default: LOGDIR/learning_curve.png)")
    args = parser.parse_args()
    if args.plot:
        report(args.plot, args.out or args.plot[0] / "learning_curve.png")
        return 0

    if args.make_export is not None:
        if args.agent != "hauwm" or args.pretrained:
            parser.error("--make-export makes the export of agent hauwm: use it with --agent hauwm, without --pretrained")
        args.pretrained = make_export(Path(args.logdir), args.make_export, args.gpu)
    args.task = args.task or ("dmc_cheetah_run" if args.gpu else "dmc_cartpole_swingup")
    args.minutes = args.minutes or (10.0 if args.gpu else 25.0)
    args.chunk = args.chunk or (50_000 if args.gpu else 2000)
    settings = {**(GPU_SETTINGS if args.gpu else CPU_SETTINGS), **dict(parse_override(text) for text in args.set)}
    logdir = Path(args.logdir)
    done = run_config(logdir).steps if (logdir / "config.yaml").exists() else 0  # a run to go on with
    cfg = load_config(None, dict(task=args.task, agent=args.agent, seed=args.seed, logdir=args.logdir,
                                 steps=done + args.chunk, **settings))
    if args.agent == "hauwm":  # the new stream takes the export's sizes
        cfg = dataclasses.replace(cfg, deter=None, stoch=None)
    print(f"machine: {describe_machine(cfg.device)}")
    print(f"settings: task {args.task}, agent {args.agent}, budget {args.minutes} min, "
          f"config { {key: getattr(cfg, key) for key in (*settings, 'layer_norm')} }", flush=True)
    start, status = time.perf_counter(), 0
    try:
        while time.perf_counter() - start < args.minutes * 60:
            train(cfg, args.pretrained, progress=False)
            print(f"{(time.perf_counter() - start) / 60:.1f} min: {cfg.steps} env steps", flush=True)
            cfg = dataclasses.replace(cfg, steps=cfg.steps + args.chunk)
    except Terminated as where:  # e.g. a `timeout` around the call: the evaluations so far are still reported
        print(f"bench_learning: terminated (SIGTERM) at {where}; {logdir} keeps the run's checkpoint of that moment: "
              "the same command goes on from there", flush=True)
        status = 143
    report([logdir], args.out or logdir / "learning_curve.png", (time.perf_counter() - start) / 60)
    return status


if __name__ == "__main__":
    sys.exit(main())
