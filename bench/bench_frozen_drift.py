"""Does the frozen stream stay near its own posterior states when it imagines on a task's frames?

    python bench/bench_frozen_drift.py --pretrained runs/export_cartpole_sizes
    python bench/bench_frozen_drift.py --pretrained DIR --task dmc_cheetah_run --action-repeat 2

In imagination the frozen stream runs open-loop on its ensemble-mean prior (it ignores actions and never
sees the imagined frames), and its features ŝ_t are half of what the actor and critic read. The export
never saw the task's frames, so that prior can carry ŝ_t away from the states its posterior gives on
real frames. This script plays `--episodes` random episodes, filters windows of them with the frozen
stream exactly as the agent does (k = 1 embedding plus noise), imagines `--horizon` steps from every
posterior state, and prints the mean |z-score| of ŝ_t's deter and stoch parts at each step, measured
against the posterior states' per-dimension mean and std. Posterior states themselves read ≈ 0.8 (the
mean of |N(0, 1)|); a value that keeps growing with the step means the critic is asked to value states
unlike any it starts from (see "Learning check" in bench/README.md for what that did to the critic).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.bench_learning import UniformOrConstant  # noqa: E402
from bench.machine import describe_machine  # noqa: E402
from finetune.rollout import play_episode  # noqa: E402
from bench.bench_model_actions import constant_policy  # noqa: E402
from finetune.config import FinetuneError, load_config  # noqa: E402
from finetune.envs import make_env  # noqa: E402
from finetune.pretrained import PretrainedError  # noqa: E402
from finetune.replay import Replay  # noqa: E402
from finetune.train import build_agent  # noqa: E402


def drift_table(features: torch.Tensor, deter: int) -> list[tuple[float, float]]:
    """features [H+1, N, F] of the frozen stream (step 0: posterior) → (deter, stoch) mean |z| per step."""
    mean, std = features[0].mean(0), features[0].std(0) + 1e-6
    z = ((features - mean) / std).abs()  # [H+1, N, F]
    return [(z[t, :, :deter].mean().item(), z[t, :, deter:].mean().item()) for t in range(len(features))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pretrained", required=True, help="export directory (hauwm pretrain export)")
    parser.add_argument("--task", default="dmc_cartpole_swingup")
    parser.add_argument("--action-repeat", type=int, default=8)
    parser.add_argument("--episodes", type=int, default=4, help="random episodes to take windows from")
    parser.add_argument("--windows", type=int, default=64, help="windows of 16 steps (posterior states: 16 × this)")
    parser.add_argument("--horizon", type=int, default=15)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(min(4, os.cpu_count() or 1))

    env = make_env(args.task, seed=args.seed, action_repeat=args.action_repeat, fast_render=True)
    cfg = load_config(None, dict(task=args.task, agent="hauwm", action_repeat=args.action_repeat, device="cpu"))
    try:  # before the episodes, so that a bad export fails at once
        agent = build_agent(cfg, env.action_space.shape[0], args.pretrained, torch.device("cpu"))
    except (PretrainedError, FinetuneError) as error:
        sys.exit(f"error: {error}")
    frozen = agent.world_model.frozen.rssm
    print(f"machine: {describe_machine()}")
    print(f"settings: export {args.pretrained} (deter {frozen.deter_dim}, stoch {frozen.stoch_dim}, M = "
          f"{frozen.ensemble}), task {args.task}, action repeat {args.action_repeat}, {args.episodes} random episodes, "
          f"{args.windows} windows of 16 posterior states, ensemble-mean imagination over {args.horizon} steps",
          flush=True)
    replay = Replay(None, capacity=10**6, rng=np.random.default_rng(args.seed))
    rng = np.random.default_rng(args.seed)
    for _ in range(args.episodes):
        replay.add(play_episode(env, UniformOrConstant(env.action_space.shape, rng)))
    batch = {key: torch.as_tensor(value) for key, value in replay.sample(args.windows, 16).items()}
    with torch.no_grad():
        latent, _ = agent.world_model.observe(batch["obs"], batch["action"])
        feats = agent.world_model.imagine(latent, constant_policy(0.0, agent.action_dim), args.horizon)[0]  # [H+1, N, F]
    table = drift_table(feats[..., :frozen.feature_dim], frozen.deter_dim)
    print(f"{'step':>5} {'deter |z|':>10} {'stoch |z|':>10}")
    for step, (deter_z, stoch_z) in enumerate(table):
        print(f"{step:>5} {deter_z:>10.2f} {stoch_z:>10.2f}")


if __name__ == "__main__":
    main()
