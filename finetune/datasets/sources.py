"""Where dataset episodes come from: scripted experts, random actions, a trained agent, a run's replay.

- `ExpertPolicy`: Meta-World's scripted policy of the task (`metaworld.policies`), acting on the env's
  39-dim state (`MetaWorldEnv.state`), optionally with clipped Gaussian action noise for medium data;
- `RandomPolicy`: uniform actions in [-1, 1];
- `load_agent_policy`: a `hauwm finetune` run's agent from its checkpoint, acting with its mode or a sample;
- `replay_episodes`: the episodes a `hauwm finetune` run kept in RUNDIR/replay ("medium replay").

Policies play through `finetune.rollout.play_episode`, the same episode player as the agent's evaluation.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from finetune.datasets.minari_io import DatasetError
from finetune.rollout import AgentPolicy, Policy, play_episode


class RandomPolicy:
    """Uniform random actions from the env's (seeded) action space."""

    def __init__(self, action_space) -> None:
        self.action_space = action_space

    def reset(self) -> None:
        pass

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.action_space.sample()


class ExpertPolicy:
    """Meta-World's scripted policy for the env's task, plus N(0, noise^2) per action dimension, clipped to [-1, 1]."""

    def __init__(self, env, noise: float, seed: int) -> None:  # env: finetune.envs.metaworld_env.MetaWorldEnv
        from metaworld.policies import ENV_POLICY_MAP

        from finetune.envs.base import action_seed
        from finetune.envs.metaworld_env import tasks

        if not env.name.startswith("metaworld_"):
            raise DatasetError(f"task {env.name} has no scripted expert (only Meta-World tasks have one); collect "
                               "with a trained agent instead: --policy agent --checkpoint RUNDIR")
        env_id = tasks()[env.name]
        if env_id not in ENV_POLICY_MAP:
            raise DatasetError(f"Meta-World has no scripted policy for {env_id}; use --policy agent --checkpoint RUNDIR")
        if noise < 0:
            raise DatasetError(f"--action-noise must be >= 0, got {noise}")
        self.env = env
        self.expert = ENV_POLICY_MAP[env_id]()
        self.noise = noise
        self.rng = np.random.default_rng(action_seed(seed))

    def reset(self) -> None:
        pass

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        with warnings.catch_warnings():  # the policies' "Constant(s) may be too high": their actions are clipped
            warnings.simplefilter("ignore", UserWarning)
            action = self.expert.get_action(self.env.state)  # [4] in Meta-World's bounds, which are [-1, 1]
        if self.noise > 0:
            action = action + self.rng.normal(0.0, self.noise, action.shape)
        return np.clip(action, -1.0, 1.0).astype(np.float32)


def load_agent_policy(rundir: str | Path, pretrained: str | Path | None, device: str, explore: bool,
                      action_dim: int, checkpoint: str | None = None) -> AgentPolicy:
    """The agent of a `hauwm finetune` run (RUNDIR/config.yaml + RUNDIR/`checkpoint`: its last checkpoint by
    default, or best.pt) as a policy."""
    from finetune.config import FinetuneError
    from finetune.run_dir import CHECKPOINT, load_trained
    from finetune.train import resolve_device

    try:
        torch_device = resolve_device(device)
    except FinetuneError as error:  # --device's, not the run's
        raise DatasetError(str(error)) from None
    try:
        _, agent, _ = load_trained(Path(rundir), pretrained, action_dim, torch_device, checkpoint or CHECKPOINT)
    except FinetuneError as error:
        raise DatasetError(f"--checkpoint {rundir}: {error}") from None
    return AgentPolicy(agent, explore)


def run_config(rundir: str | Path):
    """The FinetuneConfig a `hauwm finetune` run wrote to RUNDIR/config.yaml (finetune.run_dir.run_config)."""
    from finetune.config import FinetuneError
    from finetune.run_dir import run_config as read_run_config

    try:
        return read_run_config(rundir)
    except FinetuneError as error:
        raise DatasetError(str(error)) from None


def policy_episodes(env, policy: Policy, episodes: int) -> Iterator[dict[str, np.ndarray]]:
    """`episodes` episodes of `policy` on `env`, one at a time (replay layout, see finetune/rollout.py)."""
    for _ in range(episodes):
        yield play_episode(env, policy)


def replay_episodes(rundir: str | Path, limit: int | None = None) -> tuple[dict[str, Any], int, Iterator[dict[str, np.ndarray]]]:
    """The run's settings, the number of episodes and the replay's episodes, oldest first (at most `limit`).

    The replay keeps obs, action and reward only: no success flags, and every episode is taken to end
    at a time limit (none of the paper's tasks has terminal states).
    """
    from finetune.envs.registry import episode_time_limit
    from finetune.replay import episode_files

    cfg = run_config(rundir)
    paths = episode_files(Path(rundir) / "replay")
    if not paths:
        why = ("an offline run never acts, so it keeps no replay" if cfg.paradigm == "offline" else
               "the run has not finished an episode yet")
        raise DatasetError(f"{rundir}/replay holds no episodes: {why}; to record the run's agent instead, use "
                           f"--policy agent --checkpoint {rundir}")
    paths = paths[:limit] if limit is not None else paths
    settings = {"task": cfg.task, "action_repeat": cfg.action_repeat,
                "time_limit": episode_time_limit(cfg.task, cfg.action_repeat, cfg.time_limit),
                "fast_render": cfg.fast_render, "seed": cfg.seed, "agent": cfg.agent, "run": str(rundir)}
    return settings, len(paths), consistent_episodes(paths)


def consistent_episodes(paths: list[Path]) -> Iterator[dict[str, np.ndarray]]:
    """The replay episodes in `paths`, each of the world model's frame size and the first one's action width
    (ReplayError if not: a dataset's episodes must fit its one action space)."""
    from finetune.replay import read_episode

    action_dim = None
    for path in paths:
        episode = read_episode(path, action_dim)
        action_dim = episode["action"].shape[1]
        yield episode
