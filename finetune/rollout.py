"""Play one episode with any policy, recorded in the replay's layout (finetune/replay.py).

A policy is anything with `reset()` (called when an episode starts) and `__call__(obs) -> action`
(obs uint8 [3, H, W] -> action [A] in [-1, 1]): the fine-tuned agent (`AgentPolicy`, used by
`evaluate` in finetune/train.py) or the dataset sources of finetune/datasets/sources.py (Meta-World's
scripted experts, uniform random actions). The episode is aligned as in Dreamer: entry t holds the
observation o_t, the action a_{t-1} that led to it and the reward r_t that came with it.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class Policy(Protocol):
    def reset(self) -> None: ...

    def __call__(self, obs: np.ndarray) -> np.ndarray: ...


class AgentPolicy:
    """The agent's actor as a policy: its mode (`explore=False`) or a sample, filtering frames through the world model."""

    def __init__(self, agent, explore: bool) -> None:  # agent: finetune.agent.Agent
        self.agent = agent
        self.explore = explore
        self.reset()

    def reset(self) -> None:
        self.latent, self.prev_action = self.agent.initial()

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        action, self.latent, self.prev_action = self.agent.act(obs[None], self.latent, self.prev_action, self.explore)
        return action[0]


def play_episode(env, policy: Policy, seed: int | None = None) -> dict[str, np.ndarray]:
    """Reset `env` (reseeded with `seed` if given), act with `policy` until the episode ends; returns the
    episode of T agent steps:

    obs uint8 [T+1, 3, H, W], action float32 [T+1, A] (entry 0 zeros; the clipped action the env applied),
    reward float32 [T+1] (entry 0 zero), terminal float32 [T+1] (1 at the last entry if it is a terminal
    state, 0 after a time limit) and, where the suite reports success, success float32 [T+1] (entry 0 zero).
    """
    obs, _ = env.reset(seed=seed)
    policy.reset()
    episode = {"obs": [obs], "action": [np.zeros(env.action_space.shape, np.float32)], "reward": [0.0], "success": [0.0]}
    reports_success = False
    terminated = truncated = False
    while not (terminated or truncated):
        action = np.clip(np.asarray(policy(obs), np.float32), -1.0, 1.0)
        obs, reward, terminated, truncated, info = env.step(action)
        reports_success = reports_success or "success" in info
        for key, value in (("obs", obs), ("action", action), ("reward", reward), ("success", info.get("success", 0.0))):
            episode[key].append(value)
    result = {"obs": np.stack(episode["obs"]), "action": np.stack(episode["action"]),
              "reward": np.asarray(episode["reward"], np.float32), "terminal": np.zeros(len(episode["reward"]), np.float32)}
    result["terminal"][-1] = float(terminated)
    if reports_success:
        result["success"] = np.asarray(episode["success"], np.float32)
    return result
