"""Actor-critic learned in imagination (paper §4.3 and appendix D; DreamerV2's continuous-action learner).

Every equation of the behaviour learner is in this file. Notation: z_t = [ŝ_t; s̃_t] is the composite
latent state (just s̃_t for the scratch baseline), H = 15 the imagination horizon, r_t the reward the
reward head predicts for the state reached after action a_{t-1}, v the critic, v' its slow target.

    λ-return   V^λ_t = r_{t+1} + γ [ (1 − λ) v'(z_{t+1}) + λ V^λ_{t+1} ],    V^λ_H = v'(z_H)        (γ 0.99, λ 0.95)
    weights    w_t = γ^t                    (no terminal states in these tasks: time limits are not terminals)
    actor      L_π = − Σ_t w_t [ V^λ_t + η · H(π(·|z_t)) ] / (H·N)
               dynamics backprop: a_t = tanh(μ + σ ε) is reparameterised, so ∂V^λ/∂ξ flows through the
               world model's imagined transitions and reward head into the policy parameters ξ
    critic     L_v = Σ_t w_t · ½ (v(z_t) − sg(V^λ_t))² / (H·N)
    target     v' ← (1 − τ) v' + τ v after every update                                   (τ 0.02)

Actor and critic are MLPs with 2 hidden layers of 400 ELU units; both are trained with Adam at 8e-5.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable

import torch
from torch import nn
from torch.distributions import Independent, Normal, TransformedDistribution
from torch.distributions.transforms import TanhTransform


def mlp(in_dim: int, out_dim: int, units: int, layers: int = 2) -> nn.Sequential:
    """`layers` hidden layers of `units` ELU units, then a linear output."""
    modules: list[nn.Module] = []
    for i in range(layers):
        modules += [nn.Linear(in_dim if i == 0 else units, units), nn.ELU()]
    modules.append(nn.Linear(units, out_dim))
    return nn.Sequential(*modules)


def lambda_return(rewards: torch.Tensor, values: torch.Tensor, gamma: float, lam: float) -> torch.Tensor:
    """V^λ_t for t = 0..H−1 from rewards [H, N] (r_{t+1}, the reward of step t → t+1) and values [H+1, N].

    λ = 0 gives the one-step target r_{t+1} + γ v(z_{t+1}); λ = 1 gives the discounted Monte-Carlo
    return Σ_{i≥t} γ^{i−t} r_{i+1} bootstrapped with γ^{H−t} v(z_H).
    """
    horizon = rewards.shape[0]
    returns = [values[horizon]]
    for t in reversed(range(horizon)):
        returns.append(rewards[t] + gamma * ((1 - lam) * values[t + 1] + lam * returns[-1]))
    return torch.stack(returns[:0:-1])  # [H, N], in time order


class Actor(nn.Module):
    """π(a|z): a tanh-squashed diagonal Gaussian (DreamerV1/V2's continuous actor)."""

    def __init__(self, feat_dim: int, action_dim: int, units: int, init_std: float = 5.0, min_std: float = 1e-4):
        super().__init__()
        self.net = mlp(feat_dim, 2 * action_dim, units)
        self.raw_init_std = math.log(math.expm1(init_std))
        self.min_std = min_std

    def forward(self, feat: torch.Tensor) -> TransformedDistribution:
        mean, raw_std = self.net(feat).chunk(2, dim=-1)
        mean = 5.0 * torch.tanh(mean / 5.0)
        std = nn.functional.softplus(raw_std + self.raw_init_std) + self.min_std
        return TransformedDistribution(Independent(Normal(mean, std), 1), [TanhTransform(cache_size=1)])

    @staticmethod
    def mode(dist: TransformedDistribution) -> torch.Tensor:
        """The deterministic action used in evaluation episodes: tanh of the Gaussian mean."""
        return torch.tanh(dist.base_dist.mean)


class Critic(nn.Module):
    """v(z): the expected λ-return from a latent state."""

    def __init__(self, feat_dim: int, units: int):
        super().__init__()
        self.net = mlp(feat_dim, 1, units)

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        return self.net(feat).squeeze(-1)


# imagine(start, policy, horizon) -> (feats [H+1, N, F], rewards [H, N], log_probs [H, N])
Imagine = Callable[[object, Callable[[torch.Tensor], TransformedDistribution], int], tuple[torch.Tensor, ...]]


class ActorCritic(nn.Module):
    def __init__(self, feat_dim: int, action_dim: int, units: int, horizon: int = 15, gamma: float = 0.99,
                 lam: float = 0.95, actor_lr: float = 8e-5, critic_lr: float = 8e-5, entropy_scale: float = 1e-4,
                 target_fraction: float = 0.02, grad_clip: float = 100.0, adam_eps: float = 1e-5):
        super().__init__()
        self.actor = Actor(feat_dim, action_dim, units)
        self.critic = Critic(feat_dim, units)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=actor_lr, eps=adam_eps)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=critic_lr, eps=adam_eps)
        self.horizon, self.gamma, self.lam = horizon, gamma, lam
        self.entropy_scale, self.target_fraction, self.grad_clip = entropy_scale, target_fraction, grad_clip

    def update(self, imagine: Imagine, start: object) -> dict[str, float]:
        """One actor and one critic step on trajectories imagined from the posterior states `start`."""
        feats, rewards, log_probs = imagine(start, self.actor, self.horizon)  # [H+1,N,F], [H,N], [H,N]
        values = self.target_critic(feats)  # [H+1, N]; gradients reach feats (dynamics backprop)
        returns = lambda_return(rewards, values, self.gamma, self.lam)  # [H, N]
        weights = self.gamma ** torch.arange(self.horizon, dtype=returns.dtype, device=returns.device)[:, None]
        entropy = -log_probs  # single-sample estimate of H(π(·|z_t)), [H, N]
        actor_loss = -(weights * (returns + self.entropy_scale * entropy)).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        actor_norm = nn.utils.clip_grad_norm_(self.actor.parameters(), self.grad_clip)
        self.actor_opt.step()

        value = self.critic(feats[:-1].detach())  # [H, N]
        critic_loss = (weights * 0.5 * (value - returns.detach()) ** 2).mean()
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        critic_norm = nn.utils.clip_grad_norm_(self.critic.parameters(), self.grad_clip)
        self.critic_opt.step()

        with torch.no_grad():
            for target, online in zip(self.target_critic.parameters(), self.critic.parameters()):
                target.lerp_(online, self.target_fraction)
        return {
            "actor_loss": actor_loss.item(), "critic_loss": critic_loss.item(),
            "imagined_reward": rewards.mean().item(), "imagined_return": returns.mean().item(),
            "actor_entropy": entropy.mean().item(), "actor_grad_norm": actor_norm.item(),
            "critic_grad_norm": critic_norm.item(),
        }
