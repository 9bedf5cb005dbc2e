"""The uncertainty-penalised reward of offline RL (paper eq. 6, appendix F.1; LOMPO's pessimism):

    r̃(s̃_t, a_t) = R(s̃_{t+1}) − λ · u(s̃_t, a_t),      λ = penalty_scale

u is read off the M prior heads of the new action-conditioned stream, N(μ_i, σ_i²) for i = 1..M, which all
predict s̃_{t+1} from (s̃_t, a_t), and off s̃_{t+1} itself (the sample imagination drew: from one random head per
step and trajectory, or around the heads' mean with `imagine_heads: mean`; DualStreamWorldModel.next_stoch). Three choices (`penalty`), LOMPO's three, reduced over the latent dims S:

    loglik_std         u = std_i [ log N(s̃_{t+1}; μ_i, σ_i²) ]     (LOMPO's default; population std over heads)
    max_std            u = max_i ‖σ_i‖₂                           (LOMPO's max_var, MOPO's penalty)
    mean_disagreement  u = mean_i ‖μ_i − μ̄‖₂,  μ̄ = mean_i μ_i    (offline DreamerV2 / V-D4RL)

loglik_std and mean_disagreement are 0 when the heads agree and grow with their spread; max_std measures
the heads' predicted noise (aleatoric), so it is ‖σ‖ when they agree and is the only one of the three
that one head can give. The frozen stream's own head disagreement at the imagined step (the HCU signal of
pre-training, model.losses.disagreement) can be added with weight w = penalty_frozen_weight:

    u_total = u + w · (1/(M'−1)) Σ_i ‖μ̂_i − mean_j μ̂_j‖² / S'

The frozen stream imagines open-loop and ignores actions, so this term is the same whatever the policy
does: it lowers the value of start states the export finds uncertain but gives the actor no gradient
(docs/downstream.md). Gradients of the other terms reach the actions (dynamics backprop), so the actor
learns to stay where the heads agree.
"""

from __future__ import annotations

import math

import torch

from finetune.world_model import DualStreamWorldModel, Latent, Rollout
from model.losses import disagreement
from model.rssm import RSSMState


def uncertainty(kind: str, mean: torch.Tensor, std: torch.Tensor, sample: torch.Tensor) -> torch.Tensor:
    """u of `kind` from the heads' mean, std [M, ..., S] and the drawn next latent sample [..., S] → [...]."""
    if kind == "loglik_std":
        z = (sample - mean) / std  # [M, ..., S]
        loglik = (-0.5 * z**2 - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)  # [M, ...]
        return loglik.std(0, unbiased=False)
    if kind == "max_std":
        return std.norm(dim=-1).amax(0)
    if kind == "mean_disagreement":
        return (mean - mean.mean(0, keepdim=True)).norm(dim=-1).mean(0)
    raise ValueError(f"unknown penalty {kind!r}: one of loglik_std, max_std, mean_disagreement")


class PenalisedReward:
    """r̃ for one update's imagination (a finetune.world_model.RewardFn). `metrics` holds the last values of u on
    the dataset's own transitions (`measure_dataset` updates it), `imagined_metrics` those on the imagined steps, a
    new dict each call: compiled code guards on the keys of a dict it finds filled in (a dict that grew after the
    first update would compile the imagination again)."""

    def __init__(self, world_model: DualStreamWorldModel, kind: str, scale: float, frozen_weight: float):
        self.world_model, self.kind, self.scale, self.frozen_weight = world_model, kind, scale, frozen_weight
        self.metrics: dict[str, torch.Tensor] = {}
        self.imagined_metrics: dict[str, torch.Tensor] = {}

    def __call__(self, rollout: Rollout) -> torch.Tensor:
        reward = self.world_model.predicted_reward(rollout.new_feats)  # [H, N]
        u = uncertainty(self.kind, rollout.prior_mean.transpose(0, 1), rollout.prior_std.transpose(0, 1),
                        rollout.new_stoch)  # heads first: [M, H, N, S] → [H, N]
        imagined = {"penalty_u_imagined": u.mean().detach(), "imagined_model_reward": reward.mean().detach()}
        total = u
        if rollout.frozen_means is not None:
            frozen_u = disagreement(rollout.frozen_means.transpose(0, 1))  # [H, N], no gradient (action-free)
            imagined["frozen_disagreement_imagined"] = frozen_u.mean().detach()
            if self.frozen_weight > 0:
                total = u + self.frozen_weight * frozen_u
        self.imagined_metrics = imagined
        return reward - self.scale * total

    @torch.no_grad()
    def measure_dataset(self, start: Latent, actions: torch.Tensor) -> None:
        """u of the dataset's own transitions: from the posterior states s̃_t [B, L, ·] with the recorded a_t
        (entry t + 1 of actions [B, L, A]), one step of every head, as imagination takes it."""
        wm = self.world_model
        new = RSSMState(start.new.deter[:, :-1].flatten(0, 1), start.new.stoch[:, :-1].flatten(0, 1))  # [N, ·]
        _, mean, std = wm.rssm.img_step(new, actions[:, 1:].flatten(0, 1))  # [M, N, S]
        self.metrics["penalty_u_dataset"] = uncertainty(self.kind, mean, std, wm.next_stoch(mean, std)).mean()
        if start.frozen is not None:
            frozen = RSSMState(start.frozen.deter[:, :-1].flatten(0, 1), start.frozen.stoch[:, :-1].flatten(0, 1))
            heads = wm.frozen.rssm.img_step(frozen, wm.frozen_cond(frozen.deter.shape[0]))[1]  # [M', N, S']
            self.metrics["frozen_disagreement_dataset"] = disagreement(heads).mean()
