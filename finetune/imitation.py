"""Imitation from expert demonstrations on the frozen export (paper §5.5, eq. 5, appendix F.1; VMAIL-style):
`hauwm finetune imitate`.

The online loop of finetune/train.py runs unchanged but for three hooks (`LoopHooks`): the agent, the
replay, and per-episode reseeding. Every update:

1. the world model (new stream with its decoder) is fitted on a batch whose last `demo_fraction` of
   windows are expert demonstrations and the rest the agent's own episodes, with no reward loss: the
   environment's reward is never learned from (it is still logged: episodes.csv, eval.csv);
2. the expert pairs (z_t, a_t): the actions the expert took, with the latents z_t = [ŝ_t; s̃_t] that the world
   model imagines along them for H steps from the posterior states of the demonstration windows (the frozen
   encoder and streams, through the world model's observe), `expert_latents: imagined`; or, as VMAIL, the
   demonstrations' posterior latents themselves (`expert_latents: posterior`);
3. the actor-critic learns in imagination from every posterior state of the batch, as online, with the
   discriminator's logit ℓ(z_t, a_t) as the reward (finetune/discriminator.py says why that form);
4. the discriminator takes one step on those expert pairs against the imagined policy pairs.

Why imagined expert latents: the policy's pairs can only be imagined ones, and imagined latents differ from
posterior ones whatever the actions (no frame corrects them; the frozen stream rolls its ensemble mean).
Trained on posterior expert pairs, the discriminator learned that difference, not the expert's behaviour:
on drawer close it called the expert's own actions, imagined from the expert's states, "policy" from the
first imagined step on (logit +2.5 on the posterior, −1.1 one step later, −5.3 ten steps later), and gave
the actor's actions there the same logits within 0.25 (bench/bench_imitation_diagnosis.py). Imagined
along the demonstrations, from every window position with H actions after it, both sides of D carry the same
imagination drift over the same depths (0..H−1), and what tells them apart is the actions and where they
lead. A checkpoint from before this setting resumes only with `expert_latents: posterior`.

Evaluation, logs, checkpoints (which hold the discriminator and its optimiser) and resume are the online
loop's; a run resumed from a checkpoint taken at an episode's end continues exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from finetune.agent import Agent
from finetune.config import FinetuneConfig, FinetuneError
from finetune.discriminator import Discriminator
from finetune.replay import Replay
from finetune.run_dir import exclusive
from finetune.train import LoopHooks, dataset_replay, run
from finetune.world_model import Latent, RewardFn, Rollout
from model.export import FrozenWorldModel


class MixedReplay:
    """The agent's own episodes (a Replay on disk) plus the demonstrations (in memory, never written): each
    batch holds `batch_size − demos_per_batch` windows of the first, then `demos_per_batch` of the second."""

    def __init__(self, own: Replay, demos: Replay, demos_per_batch: int):
        self.own, self.demos, self.demos_per_batch = own, demos, demos_per_batch

    def add(self, episode: dict[str, np.ndarray]) -> None:
        self.own.add(episode)

    def load(self, stored: int, action_dim: int | None = None) -> int:
        return self.own.load(stored, action_dim)

    def ready(self, length: int) -> bool:
        return self.own.ready(length) and self.demos.ready(length)

    def sample(self, batch_size: int, length: int) -> dict[str, np.ndarray]:
        own = self.own.sample(batch_size - self.demos_per_batch, length)
        demos = self.demos.sample(self.demos_per_batch, length)
        return {key: np.concatenate([own[key], demos[key]]) for key in own}


class RecordedActions:
    """A policy for DualStreamWorldModel.imagine that plays recorded actions [H, N, A], one step per call: it is its own
    action distribution, whose sample is the recorded action and whose entropy is 0."""

    def __init__(self, actions: torch.Tensor):
        self.actions, self.step = actions, 0

    def __call__(self, feat: torch.Tensor) -> RecordedActions:
        return self

    def rsample(self) -> torch.Tensor:
        self.step += 1
        return self.actions[self.step - 1]

    def entropy(self) -> torch.Tensor:
        return self.actions.new_zeros(self.actions.shape[1])


def demos_per_batch(cfg: FinetuneConfig) -> int:
    """Demonstration windows per batch: demo_fraction of batch_size, at least one, leaving one for the agent."""
    if cfg.batch_size < 2:
        raise FinetuneError(f"imitation needs batch_size >= 2 (agent and demonstration windows), got {cfg.batch_size}")
    return min(max(1, round(cfg.demo_fraction * cfg.batch_size)), cfg.batch_size - 1)


def make_replay(cfg: FinetuneConfig, directory: Path, rng: np.random.Generator, action_dim: int) -> MixedReplay:
    demos = dataset_replay(cfg.demos, cfg, action_dim, "--demos", rng)
    return MixedReplay(Replay(directory, cfg.replay_capacity, rng), demos, demos_per_batch(cfg))


class ImitationAgent(Agent):
    """The online agent with a discriminator's reward in imagination and no reward loss."""

    def __init__(self, cfg: FinetuneConfig, action_dim: int, frozen: FrozenWorldModel | None = None,
                 k1_embedding: torch.Tensor | None = None):
        super().__init__(cfg, action_dim, frozen, k1_embedding)
        self.discriminator = Discriminator(self.world_model.feature_dim, action_dim, cfg.units, cfg.layer_norm,
                                           cfg.disc_lr, cfg.disc_gp_scale, cfg.grad_clip)
        self.demos_per_batch = demos_per_batch(cfg)
        self.imagine_expert = cfg.expert_latents == "imagined"
        self.horizon = cfg.horizon  # the depths of the policy's imagined pairs: 0..H−1
        self.demo_pairs: tuple[torch.Tensor, torch.Tensor] | None = None  # this update's expert pairs
        self.imagined_pairs: tuple[torch.Tensor, torch.Tensor] | None = None  # this update's imagined pairs

    def update(self, batch: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        """`batch`: a MixedReplay batch, demonstrations last; its rewards are dropped."""
        return super().update({key: value for key, value in batch.items() if key != "reward"})

    def reward_modules(self) -> list[torch.nn.Module]:
        return [self.discriminator]

    def finish_update(self) -> dict[str, torch.Tensor]:
        """The discriminator's step on this update's expert and imagined pairs."""
        metrics = self.discriminator.update(*self.demo_pairs, *self.imagined_pairs)
        self.demo_pairs = self.imagined_pairs = None
        return metrics

    def imagined_reward(self, batch: dict[str, torch.Tensor], start: Latent) -> RewardFn:
        demos = slice(batch["action"].shape[0] - self.demos_per_batch, None)
        actions = batch["action"][demos, 1:]  # a_t, the action the expert took at step t [B_d, L−1, A]
        self.demo_pairs = self.expert_pairs(start, demos, actions)
        return self.discriminator_reward

    @torch.no_grad()
    def expert_pairs(self, start: Latent, demos: slice, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The expert's pairs (z_t, a_t) from the demonstration windows' posterior states `start` and `actions`.

        imagined: z imagined along the expert's actions from every window position p that has D = min(H, L−1)
        actions after it, over depths 0..D−1 as the policy's pairs (with D = H): z_p, then D − 1 imagined steps
        → feats [D, B_d·P, F] and the actions a_p..a_{p+D−1} [D, B_d·P, A], P = L − D positions.
        posterior (VMAIL's): the posterior states of positions 0..L−2 and their actions, [B_d, L−1, ·].
        """
        if not self.imagine_expert:
            return self.world_model.feature(start)[demos, :-1], actions
        depth = min(self.horizon, actions.shape[1])
        first = start.map(lambda x: x[demos, :actions.shape[1] - depth + 1])  # [B_d, P, ·]
        recorded = actions.unfold(1, depth, 1).permute(3, 0, 1, 2).flatten(1, 2)  # [B_d, P, A, D] → [D, B_d·P, A]
        feats, _, _ = self.world_model.imagine(first, RecordedActions(recorded), depth - 1)
        return feats, recorded

    def discriminator_reward(self, rollout: Rollout) -> torch.Tensor:
        """r_t = ℓ(z_t, a_t) for t = 0..H−1; keeps the (detached) pairs for the discriminator's step."""
        self.imagined_pairs = (rollout.feats[:-1].detach(), rollout.actions.detach())
        return self.discriminator.reward(rollout.feats[:-1], rollout.actions)

    def optimizer_state_dicts(self) -> dict[str, dict]:
        return {**super().optimizer_state_dicts(), "discriminator": self.discriminator.optimizer.state_dict()}

    def load_optimizer_state_dicts(self, states: dict[str, dict]) -> None:
        super().load_optimizer_state_dicts(states)
        self.discriminator.optimizer.load_state_dict(states["discriminator"])


HOOKS = LoopHooks(agent_class=ImitationAgent, make_replay=make_replay, reseed=True)


def train_imitation(cfg: FinetuneConfig, pretrained: str | Path | None = None, progress: bool = True) -> dict[str, float]:
    """Run (or resume) imitation in cfg.logdir until cfg.steps env steps; returns the last evaluation."""
    if cfg.paradigm != "imitation":
        raise FinetuneError(f"train_imitation needs paradigm 'imitation', the config has {cfg.paradigm!r}")
    with exclusive(Path(cfg.logdir)):
        return run(cfg, pretrained, progress, HOOKS)
