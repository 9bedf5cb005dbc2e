"""Ensemble RSSM: one GRU deterministic path, one posterior, M Gaussian prior heads (paper eq. 1, appendix D.1).

    deter_t          = GRU(deter_{t-1}, MLP([stoch_{t-1}; Δt_k^e]))      the gap embedding enters where an action would
    prior head i     : N(μ_i(deter_t, Δt_k^e), σ_i(deter_t, Δt_k^e)²)   i = 1..M   (eq. 1; one batched matmul)

Each head also reads Δt_k^e directly, as eq. 1 and section 4.2 say ("this temporal conditioning is input to
each ensemble dynamics head"): how far the heads may spread can then depend on k without first being
routed through the GRU state.
    posterior        : N(μ_q(deter_t, e_t), σ_q(deter_t, e_t)²),  stoch_t ~ posterior   (e_t: image embedding)

Distribution parameters are always float32, also under autocast, because 16-bit RSSMs are known to
overflow in the std/KL path. The std is bounded, min_std + (max_std − min_std) · sigmoid(x + 2) (DreamerV3's
Gaussian latents): with an unbounded std (softplus + floor) a head pays only a logarithmic KL for straying
from the posterior if it widens its std, so the quadratic HCU reward wins and the heads run apart — measured
on tiny.yaml: prior std 0.8 → 6.8 and disagreement 0.01 → 183 within 144 steps. Bounded, the KL cost of
disagreement stays quadratic and the HCU term only weakens the pull between heads, the more so the larger k.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from model.config import WorldModelConfig


class RSSMState(NamedTuple):
    deter: torch.Tensor  # [B, deter]
    stoch: torch.Tensor  # [B, stoch]


class Observation(NamedTuple):
    """A filtered sequence: the posterior states and every head's prior, time along dim 1 (heads first for priors)."""

    deter: torch.Tensor  # [B, L, deter]
    stoch: torch.Tensor  # [B, L, stoch]   posterior sample
    post_mean: torch.Tensor  # [B, L, stoch]
    post_std: torch.Tensor  # [B, L, stoch]
    prior_mean: torch.Tensor  # [M, B, L, stoch]
    prior_std: torch.Tensor  # [M, B, L, stoch]

    def state(self, t: int) -> RSSMState:
        return RSSMState(self.deter[:, t], self.stoch[:, t])


class EnsembleLinear(nn.Module):
    """M independent linear layers applied as one batched matmul: [M, B, in] (or shared [B, in]) → [M, B, out]."""

    def __init__(self, ensemble: int, in_features: int, out_features: int):
        super().__init__()
        bound = 1.0 / math.sqrt(in_features)  # nn.Linear's default init, per head
        self.weight = nn.Parameter(torch.empty(ensemble, in_features, out_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(ensemble, 1, out_features).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() == 2:  # the same input for every head
            x = x.unsqueeze(0).expand(self.weight.shape[0], -1, -1)
        return torch.baddbmm(self.bias, x, self.weight)


def _mean_std(raw: torch.Tensor, min_std: float, max_std: float) -> tuple[torch.Tensor, torch.Tensor]:
    mean, std = raw.float().chunk(2, dim=-1)  # float32 even under autocast
    return mean, min_std + (max_std - min_std) * torch.sigmoid(std + 2.0)


class EnsembleRSSM(nn.Module):
    """A building block: the pre-trained WorldModel builds it from its WorldModelConfig (cond_dim = the temporal
    embedding's size), fine-tuning's action-conditioned stream with cond_dim = the action size and M = 1."""

    def __init__(
        self,
        embed_dim: int,
        cond_dim: int,
        deter: int,
        stoch: int,
        hidden: int,
        ensemble: int,
        min_std: float = WorldModelConfig.min_std,
        max_std: float = WorldModelConfig.max_std,
    ):
        super().__init__()
        if ensemble < 1:
            raise ValueError(f"ensemble (M) must be ≥ 1, got {ensemble}")
        if not 0 < min_std < max_std:
            raise ValueError(f"need 0 < min_std < max_std, got {min_std}, {max_std}")
        self.deter_dim, self.stoch_dim, self.ensemble = deter, stoch, ensemble
        self.min_std, self.max_std = min_std, max_std
        self.img_in = nn.Sequential(nn.Linear(stoch + cond_dim, hidden), nn.ELU())
        self.cell = nn.GRUCell(hidden, deter)
        self.prior_hidden = EnsembleLinear(ensemble, deter + cond_dim, hidden)
        self.prior_out = EnsembleLinear(ensemble, hidden, 2 * stoch)
        self.posterior = nn.Sequential(nn.Linear(deter + embed_dim, hidden), nn.ELU(), nn.Linear(hidden, 2 * stoch))

    @property
    def feature_dim(self) -> int:
        return self.deter_dim + self.stoch_dim

    def initial(self, batch_size: int, device: torch.device | str | None = None) -> RSSMState:
        return RSSMState(
            torch.zeros(batch_size, self.deter_dim, device=device),
            torch.zeros(batch_size, self.stoch_dim, device=device),
        )

    def draw_noise(
        self, batch_size: int, length: int, generator: torch.Generator | None = None, device: torch.device | str | None = None
    ) -> torch.Tensor:
        """Standard-normal draws for the posterior samples of `observe`: [B, L, S] float32."""
        return torch.randn(batch_size, length, self.stoch_dim, generator=generator, device=device)

    def feature(self, state: RSSMState) -> torch.Tensor:
        return torch.cat([state.deter, state.stoch.to(state.deter.dtype)], dim=-1)  # [..., deter + stoch]

    def heads(self, deter: torch.Tensor, cond: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """All M prior heads at once: deter [B, D], cond [B, C] → mean, std [M, B, S] float32."""
        if deter.dim() != 2:  # a [B, L, D] input would pass for one input per head where B = M: wrong, silently
            raise ValueError(f"heads takes deter [B, D], not {list(deter.shape)}: flatten the leading axes first")
        hidden = F.elu(self.prior_hidden(torch.cat([deter, cond.to(deter.dtype)], dim=-1)))  # [M, B, H]
        return _mean_std(self.prior_out(hidden), self.min_std, self.max_std)

    def transition(self, prev: RSSMState, cond: torch.Tensor) -> torch.Tensor:
        """The deterministic path: deter_t [B, D] from the previous state and this step's condition [B, C]."""
        x = self.img_in(torch.cat([prev.stoch, cond.to(prev.stoch.dtype)], dim=-1))
        return self.cell(x, prev.deter.to(x.dtype))

    def img_step(self, prev: RSSMState, cond: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One transition without an observation: → deter [B, D], prior mean and std [M, B, S]."""
        deter = self.transition(prev, cond)
        return (deter, *self.heads(deter, cond))

    def obs_step(
        self,
        prev: RSSMState,
        cond: torch.Tensor,
        embed: torch.Tensor,
        noise: torch.Tensor | None = None,
    ) -> tuple[RSSMState, torch.Tensor, torch.Tensor]:
        """Transition plus posterior: → (post state, post mean, post std [B, S]). The prior heads of this step are
        `heads(state.deter, cond)`: the recurrence does not need them.

        noise [B, S]: the standard-normal draw of the posterior sample (fresh from the global RNG when None).
        """
        deter = self.transition(prev, cond)
        raw = self.posterior(torch.cat([deter, embed.to(deter.dtype)], dim=-1))
        post_mean, post_std = _mean_std(raw, self.min_std, self.max_std)
        stoch = post_mean + post_std * (torch.randn_like(post_mean) if noise is None else noise)
        return RSSMState(deter, stoch), post_mean, post_std

    def observe(
        self,
        embeds: torch.Tensor,
        conds: torch.Tensor,
        noise: torch.Tensor | None = None,
    ) -> Observation:
        """Filter a sequence from the initial state: embeds [B, L, E], conds [B, L, C] (cond of the gap before each
        frame) → Observation.

        noise [B, L, S]: the standard-normal draws of the posterior samples (`draw_noise`; when None, each step
        draws its own from the global RNG). Passing it in keeps the random draw out of a compiled region and
        makes it reproducible (pre-training); fine-tuning draws step by step.

        Only the GRU and the posterior are recurrent: the M prior heads of all L steps are one batched call after
        the loop, and the inputs are unbound along time (the gradient of L slices is then one stack, not L
        zero-filled copies summed) — fewer, larger kernels on a launch-bound GPU (bench/bench_step_ops.py).
        """
        batch, length = embeds.shape[:2]
        state = self.initial(batch, embeds.device)
        noises = [None] * length if noise is None else noise.unbind(1)
        steps = []
        for cond, embed, step_noise in zip(conds.unbind(1), embeds.unbind(1), noises):
            state, post_mean, post_std = self.obs_step(state, cond, embed, step_noise)
            steps.append((state.deter, state.stoch, post_mean, post_std))
        deter, stoch, post_mean, post_std = (torch.stack(values, 1) for values in zip(*steps))
        prior_mean, prior_std = self.heads(deter.flatten(0, 1), conds.flatten(0, 1))  # [M, B·L, S]
        return Observation(deter, stoch, post_mean, post_std,
                           prior_mean.unflatten(1, (batch, length)), prior_std.unflatten(1, (batch, length)))

    def imagine(self, state: RSSMState, conds: torch.Tensor, head: int | None = None) -> tuple[RSSMState, torch.Tensor]:
        """Open-loop rollout over conds [B, H, C]: each next stoch is the ensemble mean μ̄ (head=None) or head i's mean.

        Returns the visited states (deter [B, H, D], stoch [B, H, S]) and every head's mean [M, B, H, S].
        """
        deters, stochs, means = [], [], []
        for t in range(conds.shape[1]):
            deter, mean, _ = self.img_step(state, conds[:, t])
            state = RSSMState(deter, mean.mean(0) if head is None else mean[head])
            deters.append(state.deter)
            stochs.append(state.stoch)
            means.append(mean)
        return RSSMState(torch.stack(deters, 1), torch.stack(stochs, 1)), torch.stack(means, 2)
