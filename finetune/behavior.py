"""Actor-critic learned in imagination (paper §4.3 and appendix D; DreamerV2's continuous-action learner).

Every equation of the behaviour learner is in this file. Notation: z_t = [ŝ_t; s̃_t] is the composite
latent state (just s̃_t for the scratch baseline), H = 15 the imagination horizon, r_t the reward the
reward head predicts for the state reached after action a_{t-1}, v the critic, v' its slow target.

    λ-return   V^λ_t = r_{t+1} + γ [ (1 − λ) v'(z_{t+1}) + λ V^λ_{t+1} ],    V^λ_H = v'(z_H)        (γ 0.99, λ 0.95)
    weights    w_t = γ^t                    (no terminal states in these tasks: time limits are not terminals)
    policy     π(a|z) = N(tanh μ(z), σ(z)²) truncated to [−1, 1],  σ = 2·sigmoid(raw/2) + 0.1   (DreamerV2's
               continuous actor, which APV uses; sampled by inverting the CDF, so samples are reparameterised)
    actor      L_π = − Σ_t w_t [ V^λ_t + η · H(π(·|z_t)) ] / (H·N)                                (η 1e-4)
               dynamics backprop: ∂V^λ/∂ξ flows from the returns through the world model's imagined
               transitions and reward head into the sampled actions and the policy parameters ξ
    critic     L_v = Σ_t w_t · ½ (v(z_t) − sg(V^λ_t))² / (H·N)
    target     v' ← (1 − τ) v' + τ v after every update                                   (τ 0.02)

Actor and critic are MLPs with 2 hidden layers of 400 ELU units; both are trained with Adam at 8e-5.
Each hidden layer has a LayerNorm before its ELU (`layer_norm`, on by default; not in the paper's Table 3).
Without it the HAUWM agent's critic diverged in every CPU learning run: the frozen stream, imagining
open-loop on frames it never saw in pre-training, carries ŝ_t away from its posterior states step by
step, and TD bootstrapping on those ever-more-distant states let the critic's loss grow ~2× every ~400
updates (bench/README.md). LayerNorm in the hidden layers is what makes TD stable in Gallici et al.
(2025), "Simplifying Deep Temporal Difference Learning", and DreamerV3 uses it in every MLP.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from torch import nn
from torch.distributions import Distribution

if TYPE_CHECKING:  # finetune.world_model builds its heads with this module's mlp
    from finetune.world_model import Latent, RewardFn


def mlp(in_dim: int, out_dim: int, units: int, layers: int = 2, layer_norm: bool = False) -> nn.Sequential:
    """`layers` hidden layers of `units` ELU units (each with a LayerNorm before the ELU if `layer_norm`),
    then a linear output."""
    modules: list[nn.Module] = []
    for i in range(layers):
        modules.append(nn.Linear(in_dim if i == 0 else units, units))
        modules += [nn.LayerNorm(units), nn.ELU()] if layer_norm else [nn.ELU()]
    modules.append(nn.Linear(units, out_dim))
    return nn.Sequential(*modules)


def lambda_return(rewards: torch.Tensor, values: torch.Tensor, gamma: float, lam: float) -> torch.Tensor:
    """V^λ_t for t = 0..H−1 from rewards [H, N] (r_{t+1}, the reward of step t → t+1) and values [H+1, N].

    λ = 0 gives the one-step target r_{t+1} + γ v(z_{t+1}); λ = 1 gives the discounted Monte-Carlo
    return Σ_{i≥t} γ^{i−t} r_{i+1} bootstrapped with γ^{H−t} v(z_H).
    """
    rewards, values = rewards.unbind(0), values.unbind(0)  # rows: their gradient is one stack, not H copies summed
    returns = [values[-1]]
    for t in reversed(range(len(rewards))):
        returns.append(rewards[t] + gamma * ((1 - lam) * values[t + 1] + lam * returns[-1]))
    return torch.stack(returns[:0:-1])  # [H, N], in time order


class TruncatedNormal(Distribution):
    """Diagonal N(loc, scale²) truncated to [low, high]; the last dim is the event (one action).

    rsample inverts the CDF, x = loc + scale · Φ⁻¹(Φ(α) + u (Φ(β) − Φ(α))) with u ~ U(0, 1), α = (low − loc)/scale
    and β = (high − loc)/scale, so gradients reach loc and scale. Samples are kept 1e-6 inside the bounds with
    a straight-through clip, as DreamerV2's SafeTruncatedNormal does.
    """

    arg_constraints: dict = {}
    has_rsample = True

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor, low: float = -1.0, high: float = 1.0, clip: float = 1e-6):
        self.loc, self.scale, self.low, self.high, self.clip = loc, scale, low, high, clip
        self.alpha, self.beta = (low - loc) / scale, (high - loc) / scale
        self.cdf_low = torch.special.ndtr(self.alpha)
        self.mass = (torch.special.ndtr(self.beta) - self.cdf_low).clamp(min=1e-8)  # Z = Φ(β) − Φ(α)
        super().__init__(loc.shape[:-1], loc.shape[-1:], validate_args=False)

    @property
    def mode(self) -> torch.Tensor:
        return self.loc.clamp(self.low, self.high)

    def rsample(self, sample_shape: torch.Size = torch.Size()) -> torch.Tensor:
        u = torch.rand(self._extended_shape(sample_shape), dtype=self.loc.dtype, device=self.loc.device)
        p = (self.cdf_low + u * self.mass).clamp(1e-7, 1 - 1e-7)
        x = self.loc + self.scale * torch.special.ndtri(p)
        return x + (x.clamp(self.low + self.clip, self.high - self.clip) - x).detach()

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        z = (value - self.loc) / self.scale
        return (-0.5 * z**2 - 0.5 * math.log(2 * math.pi) - self.scale.log() - self.mass.log()).sum(-1)

    def entropy(self) -> torch.Tensor:
        """log(√(2πe) σ Z) + (α φ(α) − β φ(β)) / (2Z), summed over action dims."""
        def pdf(t: torch.Tensor) -> torch.Tensor:
            return torch.exp(-0.5 * t**2) / math.sqrt(2 * math.pi)

        tails = (self.alpha * pdf(self.alpha) - self.beta * pdf(self.beta)) / (2 * self.mass)
        return (0.5 * math.log(2 * math.pi * math.e) + self.scale.log() + self.mass.log() + tails).sum(-1)


class Actor(nn.Module):
    """π(a|z): DreamerV2's truncated-normal continuous actor, loc tanh(μ) and std in (0.1, 2.1), 1.1 at init."""

    def __init__(self, feat_dim: int, action_dim: int, units: int, layer_norm: bool = True, min_std: float = 0.1):
        super().__init__()
        self.net = mlp(feat_dim, 2 * action_dim, units, layer_norm=layer_norm)
        self.min_std = min_std

    def forward(self, feat: torch.Tensor) -> TruncatedNormal:
        mean, raw_std = self.net(feat).chunk(2, dim=-1)
        return TruncatedNormal(torch.tanh(mean), 2 * torch.sigmoid(raw_std / 2) + self.min_std)


class Critic(nn.Module):
    """v(z): the expected λ-return from a latent state."""

    def __init__(self, feat_dim: int, units: int, layer_norm: bool = True):
        super().__init__()
        self.net = mlp(feat_dim, 1, units, layer_norm=layer_norm)

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        return self.net(feat).squeeze(-1)


ADAM_EPS = 1e-5  # DreamerV2's ε for every Adam of fine-tuning (world model, actor, critic, discriminator)

# |tanh μ| above this means tanh' = 1 − tanh² μ < 2e-3: the dynamics-backprop gradient that reaches μ has all
# but vanished, and an actor whose loc sits there on every state no longer moves (logged as actor_saturated)
SATURATED = 0.999

# imagine(start, policy, horizon[, reward=fn]) -> (feats [H+1, N, F], rewards [H, N], policy entropies [H, N]);
# `reward` (a keyword, passed only when given) is a reward function of the rollout (finetune.world_model.RewardFn)
Imagine = Callable[..., tuple[torch.Tensor, ...]]


class ActorCritic(nn.Module):
    def __init__(self, feat_dim: int, action_dim: int, units: int, horizon: int = 15, gamma: float = 0.99,
                 lam: float = 0.95, actor_lr: float = 8e-5, critic_lr: float = 8e-5, entropy_scale: float = 1e-4,
                 target_fraction: float = 0.02, grad_clip: float = 100.0,
                 layer_norm: bool = True):
        super().__init__()
        self.actor = Actor(feat_dim, action_dim, units, layer_norm)
        self.critic = Critic(feat_dim, units, layer_norm)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=actor_lr, eps=ADAM_EPS)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=critic_lr, eps=ADAM_EPS)
        self.horizon, self.gamma, self.lam = horizon, gamma, lam
        self.entropy_scale, self.target_fraction, self.grad_clip = entropy_scale, target_fraction, grad_clip

    def losses(self, imagine: Imagine, start: Latent, reward: RewardFn | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Imagine from the posterior states `start` → (actor loss, critic loss, the imagined features [H+1, N, F]
        detached, metrics), with the rewards of `reward` (None: the world model's reward head; offline RL and
        imitation pass their own); `step` takes the result.

        The two losses share no parameters (the critic reads detached features and returns), so one
        backward pass through both gives each network its own gradient; the agent may run this compiled.
        """
        given = {} if reward is None else {"reward": reward}
        feats, rewards, entropy = imagine(start, self.actor, self.horizon, **given)  # [H+1,N,F], [H,N], [H,N]
        values = self.target_critic(feats)  # [H+1, N]; gradients reach feats (dynamics backprop)
        returns = lambda_return(rewards, values, self.gamma, self.lam)  # [H, N]
        weights = self.gamma ** torch.arange(self.horizon, dtype=returns.dtype, device=returns.device)[:, None]
        actor_loss = -(weights * (returns + self.entropy_scale * entropy)).mean()
        value = self.critic(feats[:-1].detach())  # [H, N]
        critic_loss = (weights * 0.5 * (value - returns.detach()) ** 2).mean()
        metrics = {"actor_loss": actor_loss, "critic_loss": critic_loss, "imagined_reward": rewards.mean(),
                   "imagined_return": returns.mean(), "actor_entropy": entropy.mean()}
        return actor_loss, critic_loss, feats.detach(), {name: value.detach() for name, value in metrics.items()}

    def step(self, actor_loss: torch.Tensor, critic_loss: torch.Tensor, feats: torch.Tensor,
             metrics: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Backward through both losses, clip, one Adam step each, then the slow target follows the critic."""
        self.actor_opt.zero_grad(set_to_none=True)
        self.critic_opt.zero_grad(set_to_none=True)
        torch.autograd.backward([actor_loss, critic_loss])
        metrics["actor_grad_norm"] = nn.utils.clip_grad_norm_(self.actor.parameters(), self.grad_clip)
        self.actor_opt.step()
        metrics["critic_grad_norm"] = nn.utils.clip_grad_norm_(self.critic.parameters(), self.grad_clip)
        self.critic_opt.step()
        with torch.no_grad():
            for target, online in zip(self.target_critic.parameters(), self.critic.parameters()):
                target.lerp_(online, self.target_fraction)
            metrics["actor_saturated"] = (self.actor(feats[:-1]).loc.abs() > SATURATED).float().mean()
        return metrics
