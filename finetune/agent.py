"""The fine-tuning agent: world model + actor-critic, one gradient update and one batch of actions at a time.

One update (paper Algorithm 1, lines 18–20): fit the new world-model parts on a replay batch, imagine
H = 15 steps from every posterior state of that batch, and take one actor and one critic step on the
imagined trajectories. Acting filters each environment's real frame through both streams and samples
the actor (its mode in evaluation episodes); the envs of a run act as one batch.

Speed (`compile` setting, docs/finetuning.md): the three forward regions — the world-model loss, the
imagination with the actor and critic losses, and one acting step — can run through `torch.compile`
(on CUDA with CUDA graphs, mode "reduce-overhead": an update at Table 3 sizes is thousands of small
kernels, so its eager speed is bound by kernel launches). Backward passes run the compiled backward
graphs; gradient clipping and the Adam steps stay eager. Nothing inside the regions reads a value back
to the host: metrics come back as device tensors, read once per log window by the training loop.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import nn

from finetune.behavior import ActorCritic
from finetune.config import FinetuneConfig
from finetune.world_model import DualStreamWorldModel, Latent, RewardFn, no_param_grads
from model.export import FrozenWorldModel


class DivergedError(FloatingPointError):
    """The actor gave a non-finite action: the agent's weights (or the latents they make) went NaN or inf."""


class Agent(nn.Module):
    def __init__(self, cfg: FinetuneConfig, action_dim: int, frozen: FrozenWorldModel | None = None,
                 k1_embedding: torch.Tensor | None = None):
        super().__init__()
        self.world_model = DualStreamWorldModel(cfg, action_dim, frozen, k1_embedding)
        self.behavior = ActorCritic(
            self.world_model.feature_dim, action_dim, cfg.units, cfg.horizon, cfg.gamma, cfg.lam, cfg.actor_lr,
            cfg.critic_lr, cfg.entropy_scale, cfg.target_fraction, cfg.grad_clip, layer_norm=cfg.layer_norm)
        self.action_dim = action_dim
        self.compile_mode: str | None = None
        self._regions: dict[str, Callable] = self._eager_regions()

    @property
    def device(self) -> torch.device:
        return self.world_model.reward[0].weight.device

    # -- the forward regions an update and an action are made of ------------------------------------

    def _eager_regions(self) -> dict[str, Callable]:
        return {"model_loss": self.world_model.loss, "behavior_losses": self._behavior_losses,
                "policy_step": self._policy_step}

    def _behavior_losses(self, start: Latent, reward: RewardFn | None) -> tuple[torch.Tensor, ...]:
        return self.behavior.losses(self.world_model.imagine, start, reward)

    def _policy_step(self, obs: torch.Tensor, latent: Latent, prev_action: torch.Tensor,
                     explore: bool) -> tuple[Latent, torch.Tensor]:
        latent = self.world_model.observe_step(latent, prev_action, obs)
        dist = self.behavior.actor(self.world_model.feature(latent))
        return latent, dist.sample() if explore else dist.mode

    def set_compile(self, mode: str | None) -> None:
        """Run the forward regions through torch.compile with `mode` ("default", "reduce-overhead"), or eagerly (None).

        Compiling happens lazily, on the first update and the first action (a minute or more at Table 3 sizes).
        """
        if mode not in (None, "default", "reduce-overhead"):
            raise ValueError(f"compile mode must be default, reduce-overhead or None, got {mode!r}")
        self.compile_mode = mode
        eager = self._eager_regions()
        self._regions = eager if mode is None else {name: torch.compile(fn, mode=mode) for name, fn in eager.items()}

    def _new_step(self) -> None:
        if self.compile_mode == "reduce-overhead":  # a new iteration: earlier CUDA-graph outputs may be reused
            torch.compiler.cudagraph_mark_step_begin()

    # -- learning and acting --------------------------------------------------------------------------

    def update(self, batch: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        """One update on a replay batch; returns its metrics as 0-d tensors on the agent's device (no host sync)."""
        self._new_step()
        tensors = {key: torch.as_tensor(value, device=self.device) for key, value in batch.items()}
        start, metrics = self.world_model.step(*self._regions["model_loss"](tensors))
        reward = self.imagined_reward(tensors, start)
        # the world model's (and a reward function's) parameters record no gradient in imagination; switched
        # here, outside the compiled region (switching requires_grad inside it would break the graph)
        with no_param_grads(self.world_model, *self.reward_modules()):
            losses = self._regions["behavior_losses"](start, reward)
        metrics.update(self.behavior.step(*losses))
        metrics.update(self.finish_update())
        values = torch.stack(list(metrics.values()))  # a fresh tensor: a CUDA graph's outputs are overwritten by its next run
        return dict(zip(metrics, values.unbind()))

    def imagined_reward(self, batch: dict[str, torch.Tensor], start: Latent) -> RewardFn | None:
        """The reward imagination trains the actor-critic on, for this batch: None, the reward head (online RL).
        Offline RL (eq. 6) and imitation (eq. 5) override it (finetune/offline.py, finetune/imitation.py)."""
        return None

    def reward_modules(self) -> list[nn.Module]:
        """Modules of `imagined_reward`'s function that have their own parameters (imitation: the discriminator)."""
        return []

    def finish_update(self) -> dict[str, torch.Tensor]:
        """What a paradigm does after the actor-critic step (imitation: the discriminator's); its metrics."""
        return {}

    def initial(self, batch_size: int = 1) -> tuple[Latent, torch.Tensor]:
        """The latents and the zero 'previous actions' at the start of `batch_size` episodes."""
        return (self.world_model.initial(batch_size, self.device),
                torch.zeros(batch_size, self.action_dim, device=self.device))

    def restart(self, latent: Latent, prev_action: torch.Tensor, done: np.ndarray) -> tuple[Latent, torch.Tensor]:
        """Start new episodes where `done` [B] is true: those rows of the latents and previous actions become zeros."""
        mask = torch.as_tensor(done, device=self.device)[:, None]  # [B, 1]
        def keep(x: torch.Tensor) -> torch.Tensor:
            return torch.where(mask, torch.zeros_like(x), x)
        restarted = latent.map(keep)
        return restarted, keep(prev_action)

    @torch.no_grad()
    def act(self, obs: np.ndarray, latent: Latent, prev_action: torch.Tensor, explore: bool) -> tuple[np.ndarray, Latent, torch.Tensor]:
        """obs uint8 [B, 3, 64, 64] (one frame per env) → (actions [B, A] in [−1, 1], the new latents, the actions
        as a [B, A] tensor)."""
        self._new_step()
        obs_t = torch.as_tensor(obs, device=self.device)
        latent, action = self._regions["policy_step"](obs_t, latent, prev_action, explore)
        if self.compile_mode is not None:  # own copies: a CUDA graph's outputs are overwritten by its next run
            latent = latent.map(torch.Tensor.clone)
            action = action.clone()
        actions = action.cpu().numpy()
        if not np.isfinite(actions).all():  # an env would take it (Meta-World even scores it as solved)
            raise DivergedError("the actor gave a non-finite action (NaN or inf): the agent has diverged; lower "
                                "actor_lr or model_lr, or set layer_norm: true, and start a new run")
        return actions, latent, action

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
