"""The discriminator of imitation (paper eq. 5, appendix F.1; VMAIL's latent-space adversarial imitation).

D_ψ(z, a) = σ(ℓ_ψ([z; a])) is the probability that a latent pair (feature z_t = [ŝ_t; s̃_t], action a_t)
comes from the expert: expert pairs are the latents of demonstration windows with the actions the expert
took there (imagined along those actions by default, or the posterior ones: `expert_latents`, see
finetune/imitation.py), policy pairs the actor's own (z_t, a_t) in imagination. ℓ_ψ is an MLP with 2
hidden layers of `units` ELU units, as the actor (finetune.behavior.mlp). Its loss is eq. 5's minimax term
with an input-space gradient penalty (Gulrajani et al. 2017, as DAC uses for adversarial imitation):

    L_D = − E_expert[log D] − E_policy[log(1 − D)] + c · E_x̂[(‖∇_x̂ ℓ_ψ(x̂)‖₂ − 1)²],
    x̂ = α x_expert + (1 − α) x_policy,  α ~ U(0, 1)                                    (c = disc_gp_scale, 10)

Eq. 5 as printed puts max_D in front of E_expert[−log D] + E_policy[−log(1 − D)], which has no finite maximum
(D → 0 on the expert's pairs); it is read as the usual GAIL game, D minimising those two terms (L_D above).

VMAIL's code takes its "gradient penalty" with respect to D's parameters; this one is taken with respect to
D's input, which is what bounds how fast D (and so the policy's reward) can change along the latent space.

The policy's reward is the logit, r(z, a) = ℓ_ψ(z, a) = log D − log(1 − D). At the optimal D it is
log ρ_expert(z, a) / ρ_policy(z, a), so the expected return is −KL(ρ_policy ‖ ρ_expert) (AIRL; Ghasemipour et
al. 2019): it is the divergence the policy should shrink. The alternative −log(1 − D) = softplus(ℓ) is
always positive (a bonus for lasting, harmless without terminal states) but its derivative σ(ℓ) vanishes
on the pairs D confidently calls the policy's, which are the ones the policy must leave: the actor learns
by backpropagating the reward into its actions (dynamics backprop), so a reward whose gradient vanishes
where the policy is worst would stall it. The logit's gradient does not vanish, and the penalty keeps
it near 1 in norm.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from finetune.behavior import ADAM_EPS, mlp
from finetune.world_model import no_param_grads


class Discriminator(nn.Module):
    def __init__(self, feat_dim: int, action_dim: int, units: int, layer_norm: bool = True, lr: float = 8e-5,
                 gp_scale: float = 10.0, grad_clip: float = 100.0):
        super().__init__()
        self.net = mlp(feat_dim + action_dim, 1, units, layer_norm=layer_norm)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=lr, eps=ADAM_EPS)
        self.gp_scale, self.grad_clip = gp_scale, grad_clip

    def logit(self, feat: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """ℓ_ψ(z, a) = log D − log(1 − D): feat [..., F], action [..., A] → [...]."""
        return self.net(torch.cat([feat, action], -1)).squeeze(-1)

    def reward(self, feat: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The policy's reward ℓ_ψ(z_t, a_t); gradients reach feat and action, D's parameters record none."""
        with no_param_grads(self):
            return self.logit(feat, action)

    def update(self, expert_feat: torch.Tensor, expert_action: torch.Tensor, policy_feat: torch.Tensor,
               policy_action: torch.Tensor) -> dict[str, torch.Tensor]:
        """One Adam step on L_D from expert pairs [..., F], [..., A] and (detached) policy pairs of any count."""
        expert = torch.cat([expert_feat, expert_action], -1).flatten(0, -2).detach()  # [N_e, F + A]
        policy = torch.cat([policy_feat, policy_action], -1).flatten(0, -2).detach()  # [N_p, F + A]
        expert_logit, policy_logit = self.net(expert).squeeze(-1), self.net(policy).squeeze(-1)
        # −log σ(ℓ) = softplus(−ℓ) and −log(1 − σ(ℓ)) = softplus(ℓ), computed stably
        bce = F.softplus(-expert_logit).mean() + F.softplus(policy_logit).mean()
        pick = torch.randint(policy.shape[0], (expert.shape[0],), device=policy.device)  # one policy pair each
        alpha = torch.rand(expert.shape[0], 1, device=expert.device)
        mixed = (alpha * expert + (1 - alpha) * policy[pick]).requires_grad_(True)
        grad = torch.autograd.grad(self.net(mixed).sum(), mixed, create_graph=True)[0]  # ∇_x̂ ℓ, [N_e, F + A]
        penalty = (grad.norm(dim=-1) - 1).pow(2).mean()
        loss = bce + self.gp_scale * penalty
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        norm = nn.utils.clip_grad_norm_(self.net.parameters(), self.grad_clip)
        self.optimizer.step()
        with torch.no_grad():
            accuracy = 0.5 * ((expert_logit > 0).float().mean() + (policy_logit < 0).float().mean())
            return {"disc_loss": bce.detach(), "disc_penalty": penalty.detach(), "disc_grad_norm": norm,
                    "disc_expert_prob": torch.sigmoid(expert_logit).mean(),
                    "disc_policy_prob": torch.sigmoid(policy_logit).mean(), "disc_accuracy": accuracy}
