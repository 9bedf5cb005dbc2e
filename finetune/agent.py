"""The fine-tuning agent: world model + actor-critic, one gradient update and one action at a time.

One update (paper Algorithm 1, lines 18–20): fit the new world-model parts on a replay batch, imagine
H = 15 steps from every posterior state of that batch, and take one actor and one critic step on the
imagined trajectories. Acting filters each real frame through both streams and samples the actor
(its mode in evaluation episodes).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from finetune.behavior import ActorCritic
from finetune.config import FinetuneConfig
from finetune.world_model import Latent, RewardFn, WorldModel


class Agent(nn.Module):
    def __init__(self, cfg: FinetuneConfig, action_dim: int, frozen: nn.Module | None = None,
                 k1_embedding: torch.Tensor | None = None):
        super().__init__()
        self.world_model = WorldModel(cfg, action_dim, frozen, k1_embedding)
        self.behavior = ActorCritic(
            self.world_model.feature_dim, action_dim, cfg.units, cfg.horizon, cfg.gamma, cfg.lam, cfg.actor_lr,
            cfg.critic_lr, cfg.entropy_scale, cfg.target_fraction, cfg.grad_clip, layer_norm=cfg.layer_norm)
        self.action_dim = action_dim

    @property
    def device(self) -> torch.device:
        return self.world_model.reward[0].weight.device

    def update(self, batch: dict[str, np.ndarray]) -> dict[str, float]:
        tensors = {key: torch.as_tensor(value, device=self.device) for key, value in batch.items()}
        start, metrics = self.world_model.update(tensors)
        metrics.update(self.behavior.update(self.world_model.imagine, start, self.imagined_reward(tensors, start)))
        return metrics

    def imagined_reward(self, batch: dict[str, torch.Tensor], start: Latent) -> RewardFn | None:
        """The reward imagination trains the actor-critic on, for this batch: None, the reward head (online RL).
        Offline RL (eq. 6) and imitation (eq. 5) override it (finetune/offline.py, finetune/imitation.py)."""
        return None

    def initial(self) -> tuple[Latent, torch.Tensor]:
        """The latent and the zero 'previous action' at the start of an episode (batch of one)."""
        return self.world_model.initial(1, self.device), torch.zeros(1, self.action_dim, device=self.device)

    @torch.no_grad()
    def act(self, obs: np.ndarray, latent: Latent, prev_action: torch.Tensor, explore: bool) -> tuple[np.ndarray, Latent, torch.Tensor]:
        """obs uint8 [3, 64, 64] → (action [A] in [−1, 1], the new latent, the action as a [1, A] tensor)."""
        obs_t = torch.as_tensor(obs, device=self.device).unsqueeze(0)
        latent = self.world_model.observe_step(latent, prev_action, obs_t)
        dist = self.behavior.actor(self.world_model.feature(latent))
        action = dist.sample() if explore else dist.mode
        return action[0].cpu().numpy(), latent, action

    def trainable_state_dict(self) -> dict[str, torch.Tensor]:
        """Everything but the frozen export (which comes back from --pretrained on resume)."""
        return {k: v for k, v in self.state_dict().items() if not k.startswith("world_model.frozen.")}

    def optimizer_state_dicts(self) -> dict[str, dict]:
        return {"model": self.world_model.optimizer.state_dict(), "actor": self.behavior.actor_opt.state_dict(),
                "critic": self.behavior.critic_opt.state_dict()}

    def load_optimizer_state_dicts(self, states: dict[str, dict]) -> None:
        self.world_model.optimizer.load_state_dict(states["model"])
        self.behavior.actor_opt.load_state_dict(states["actor"])
        self.behavior.critic_opt.load_state_dict(states["critic"])
