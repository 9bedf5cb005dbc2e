"""Loss terms of pre-training: the ELBO of eq. 2 with KL balancing, the HCU loss of eq. 3, ensemble disagreement.

Shapes: posterior [B, L, S]; the M prior heads [M, B, L, S]; gaps k [B, L] with k = 0 before the first frame.
Everything here runs in float32 (callers pass float32 distribution parameters; images are upcast).
"""

from __future__ import annotations

import torch


def gaussian_kl(mean_q: torch.Tensor, std_q: torch.Tensor, mean_p: torch.Tensor, std_p: torch.Tensor) -> torch.Tensor:
    """KL(N(mean_q, std_q²) ‖ N(mean_p, std_p²)) of diagonal Gaussians, summed over the last dim."""
    var_ratio = (std_q / std_p) ** 2
    mahalanobis = ((mean_q - mean_p) / std_p) ** 2
    return 0.5 * (var_ratio + mahalanobis - 1.0 - var_ratio.log()).sum(-1)


def kl_halves(
    post_mean: torch.Tensor, post_std: torch.Tensor, prior_mean: torch.Tensor, prior_std: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The two halves of KL balancing (DreamerV2), each [M, B, L] for M prior heads against the posterior q.

    KL(sg(q) ‖ p_i) trains the prior heads; KL(q ‖ sg(p_i)) regularises the posterior. Both have the plain KL's value.
    """
    kl_prior = gaussian_kl(post_mean.detach(), post_std.detach(), prior_mean, prior_std)
    kl_post = gaussian_kl(post_mean, post_std, prior_mean.detach(), prior_std.detach())
    return kl_prior, kl_post


def balanced_kl(
    post_mean: torch.Tensor, post_std: torch.Tensor, prior_mean: torch.Tensor, prior_std: torch.Tensor, balance: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """KL balancing of every head against the posterior, averaged over heads → (balanced [B, L], KL [B, L]).

    balanced = balance · KL(sg(q) ‖ p_i) + (1 − balance) · KL(q ‖ sg(p_i)): the prior heads move toward the
    posterior faster than the posterior toward them.
    """
    kl_prior, kl_post = kl_halves(post_mean, post_std, prior_mean, prior_std)  # [M, B, L] each
    return (balance * kl_prior + (1.0 - balance) * kl_post).mean(0), kl_prior.detach().mean(0)


def reconstruction_nll(mean_image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """−ln N(target; mean_image, I) up to a constant, summed over pixels: [..., 3, H, W] → [...]."""
    return 0.5 * ((mean_image.float() - target) ** 2).sum((-3, -2, -1))


def disagreement(prior_mean: torch.Tensor) -> torch.Tensor:
    """Ensemble disagreement (1/(M−1)) Σ_i ‖μ_i − μ̄‖², averaged over latent dims: [M, ..., S] → [...].

    Zero for a single head (M = 1), where there is no spread to measure.
    """
    heads = prior_mean.shape[0]
    if heads < 2:
        return prior_mean.new_zeros(prior_mean.shape[1:-1])
    spread = (prior_mean - prior_mean.mean(0, keepdim=True)) ** 2
    return spread.sum(0).mean(-1) / (heads - 1)


def mean_over_jumps(values: torch.Tensor, gaps: torch.Tensor) -> torch.Tensor:
    """The mean of values [B, L] over the steps that have a previous frame (k ≥ 1); a sequence's first step, predicted
    from the zero state, spans no horizon."""
    valid = (gaps > 0).float()  # [B, L]
    return (values * valid).sum() / valid.sum().clamp(min=1.0)


def k_scaled_disagreement(prior_mean: torch.Tensor, gaps: torch.Tensor) -> torch.Tensor:
    """k · disagreement averaged over the steps that have a previous frame (k ≥ 1): the scalar −L_HCU."""
    return mean_over_jumps(gaps.float() * disagreement(prior_mean), gaps)


def hcu_loss(prior_mean: torch.Tensor, gaps: torch.Tensor) -> torch.Tensor:
    """Eq. 3: L_HCU = −k · (1/(M−1)) Σ_i (μ_i − μ̄)², averaged over batch, time (steps with k ≥ 1) and latent dims."""
    return -k_scaled_disagreement(prior_mean, gaps)
