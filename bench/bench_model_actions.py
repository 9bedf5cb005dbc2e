"""Does the fine-tuning world model know what actions do? A probe of the dynamics-backprop signal.

    python bench/bench_model_actions.py                               # cartpole balance, 8 episodes, 2,000 updates
    python bench/bench_model_actions.py --task dmc_cartpole_swingup --updates 1000

The actor learns by following the gradient of imagined returns through the world model, so it can only
improve where the model ranks actions the way the environment does. This script plays `--episodes`
random episodes, then trains the scratch agent's world model on them (the learning check's CPU sizes)
and, every `--every` updates, imagines 15 steps from posterior states with each constant action in
{−1, −0.5, 0, 0.5, 1} and prints the mean imagined reward per step. For comparison it plays one real
episode per constant action: on cartpole balance holding still (0) scores far more than pushing (±1).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.bench_learning import CPU_SETTINGS, UniformOrConstant  # noqa: E402
from bench.machine import describe_machine  # noqa: E402
from finetune.rollout import play_episode  # noqa: E402
from finetune.agent import Agent  # noqa: E402
from finetune.behavior import TruncatedNormal  # noqa: E402
from finetune.config import load_config  # noqa: E402
from finetune.envs import make_env  # noqa: E402
from finetune.replay import Replay  # noqa: E402

CONSTANT_ACTIONS = (-1.0, -0.5, 0.0, 0.5, 1.0)


def constant_policy(value: float, action_dim: int = 1):
    """A policy for DualStreamWorldModel.imagine that always takes `value` in each of `action_dim` dimensions."""
    def policy(feat: torch.Tensor) -> TruncatedNormal:
        shape = (*feat.shape[:-1], action_dim)
        return TruncatedNormal(torch.full(shape, value), torch.full(shape, 1e-3))
    return policy


@torch.no_grad()
def imagined_rewards(agent: Agent, batch: dict[str, torch.Tensor]) -> list[float]:
    latent, _ = agent.world_model.observe(batch["obs"], batch["action"])  # posterior states, no decoder
    rewards = []
    for value in CONSTANT_ACTIONS:
        torch.manual_seed(1)  # the same prior samples for every action
        rewards.append(agent.world_model.imagine(latent, constant_policy(value), 15)[1].mean().item())
    return rewards


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="dmc_cartpole_balance")
    parser.add_argument("--episodes", type=int, default=8, help="random episodes to train the model on")
    parser.add_argument("--updates", type=int, default=2000)
    parser.add_argument("--every", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    cfg = load_config(None, {**CPU_SETTINGS, "task": args.task, "agent": "scratch", "seed": args.seed})
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(args.seed)
    print(f"machine: {describe_machine()}")
    print(f"settings: 1 torch thread, task {args.task}, action repeat {cfg.action_repeat}, {args.episodes} random "
          f"episodes, batch {cfg.batch_size} × {cfg.seq_len}, deter {cfg.deter}, stoch {cfg.stoch}, encoder width "
          f"{cfg.encoder_width}")
    env = make_env(args.task, seed=args.seed, action_repeat=cfg.action_repeat, fast_render=True)
    if env.action_space.shape != (1,):
        raise SystemExit(f"{args.task} has actions of shape {env.action_space.shape}; this probe needs one action dim")
    rng = np.random.default_rng(args.seed)
    replay = Replay(None, cfg.replay_capacity, rng)
    for _ in range(args.episodes):
        replay.add(play_episode(env, UniformOrConstant(env.action_space.shape, rng)))
    real = [float(play_episode(env, UniformOrConstant(env.action_space.shape, rng, value))["reward"][1:].mean())
            for value in CONSTANT_ACTIONS]
    data_reward = np.mean([ep["reward"][1:].mean() for ep in replay.episodes])
    print(f"reward per agent step, real episode of each constant action {CONSTANT_ACTIONS}: "
          f"{[round(r, 2) for r in real]} (random-action data: {data_reward:.2f})")

    agent = Agent(cfg, action_dim=1)
    probe = {key: torch.as_tensor(value) for key, value in replay.sample(32, cfg.seq_len).items()}
    start = time.perf_counter()
    for update in range(args.updates + 1):
        if update % args.every == 0:
            imagined = imagined_rewards(agent, probe)
            print(f"{update:>6} updates ({time.perf_counter() - start:5.0f} s): imagined reward per step "
                  f"{[round(r, 2) for r in imagined]}", flush=True)
        if update < args.updates:
            batch = {key: torch.as_tensor(value) for key, value in replay.sample(cfg.batch_size, cfg.seq_len).items()}
            agent.world_model.step(*agent.world_model.loss(batch))


if __name__ == "__main__":
    main()
