"""Loss terms: HCU (eq. 3) on a hand-made example, disagreement, KL balancing (eq. 2), reconstruction."""

from __future__ import annotations

import torch

from model.losses import (balanced_kl, disagreement, gaussian_kl, hcu_loss, k_scaled_disagreement, kl_halves,
                          mean_over_jumps, reconstruction_nll)


def test_hcu_equals_eq3_on_a_hand_made_example():
    # M = 3 heads, B = 1, L = 3 (the first step has k = 0), S = 2 latent dims
    means = torch.zeros(3, 1, 3, 2)
    means[:, 0, 1] = torch.tensor([[0.0, 0.0], [1.0, 2.0], [2.0, 4.0]])  # step 1: mean (1, 2)
    means[:, 0, 2] = torch.tensor([[1.0, 1.0], [1.0, 1.0], [4.0, 1.0]])  # step 2: mean (2, 1)
    gaps = torch.tensor([[0, 2, 5]])
    # step 1: per dim Σ_i (μ_i − μ̄)² = (1 + 0 + 1, 4 + 0 + 4) = (2, 8); /(M−1) = (1, 4); mean over dims 2.5
    # step 2: (1 + 1 + 4, 0) = (6, 0); /(M−1) = (3, 0); mean over dims 1.5
    assert torch.allclose(disagreement(means)[0], torch.tensor([0.0, 2.5, 1.5]))
    # HCU = −mean over the steps with k ≥ 1 of k · disagreement = −(2·2.5 + 5·1.5) / 2
    assert torch.isclose(hcu_loss(means, gaps), torch.tensor(-6.25))
    assert torch.isclose(k_scaled_disagreement(means, gaps), torch.tensor(6.25))


def test_disagreement_is_zero_for_agreeing_or_single_heads():
    same = torch.randn(1, 2, 4, 3).expand(5, -1, -1, -1)
    assert torch.allclose(disagreement(same), torch.zeros(2, 4))
    assert torch.equal(disagreement(torch.randn(1, 2, 4, 3)), torch.zeros(2, 4))


def test_hcu_gradient_pushes_heads_apart_more_at_larger_k():
    means = torch.randn(4, 1, 3, 5, requires_grad=True)
    hcu_loss(means, torch.tensor([[0, 1, 4]])).backward()
    spread = means.detach() - means.detach().mean(0)
    step = -means.grad  # a descent step on L_HCU
    assert (step[:, 0, 0] == 0).all()  # k = 0: no push
    # the step points along each head's deviation from μ̄, 4× as strong at k = 4 as at k = 1
    assert torch.allclose(step[:, 0, 2] / spread[:, 0, 2], 4 * step[:, 0, 1] / spread[:, 0, 1], rtol=1e-4)


def test_gaussian_kl_matches_torch_distributions():
    mq, sq, mp, sp = torch.randn(4, 6), torch.rand(4, 6) + 0.1, torch.randn(4, 6), torch.rand(4, 6) + 0.1
    reference = torch.distributions.kl_divergence(torch.distributions.Normal(mq, sq), torch.distributions.Normal(mp, sp))
    assert torch.allclose(gaussian_kl(mq, sq, mp, sp), reference.sum(-1), atol=1e-5)


def test_kl_balancing_splits_the_gradient_0_8_to_the_prior():
    post_mean = torch.randn(2, 3, 4, requires_grad=True)
    prior_mean = torch.randn(3, 2, 3, 4, requires_grad=True)  # M = 3 heads
    std = torch.ones(2, 3, 4)
    balanced, plain = balanced_kl(post_mean, std, prior_mean, std.expand(3, -1, -1, -1), balance=0.8)
    # the value is the plain KL averaged over heads
    manual = torch.stack([gaussian_kl(post_mean, std, prior_mean[i], std) for i in range(3)]).mean(0)
    assert torch.allclose(balanced, manual) and torch.allclose(plain, manual)
    balanced.sum().backward()
    # unit stds: d KL / d prior_i = (prior_i − post) / M, scaled by 0.8; the posterior gets 0.2 of its gradient
    diff = (prior_mean - post_mean).detach()
    assert torch.allclose(prior_mean.grad, 0.8 * diff / 3, atol=1e-6)
    assert torch.allclose(post_mean.grad, 0.2 * (-diff).sum(0) / 3, atol=1e-6)


def test_each_kl_half_trains_its_own_side_only():
    """kl_halves: KL(sg(q) ‖ p_i) sends gradient to the prior heads' means and stds only, KL(q ‖ sg(p_i)) to the
    posterior's only; both have the plain KL's value. (The unit stds of the balancing test above carry no gradient,
    so a std left undetached would pass there.)"""
    post_mean, post_std = torch.randn(2, 3, 4, requires_grad=True), (torch.rand(2, 3, 4) + 0.5).requires_grad_(True)
    prior_mean = torch.randn(3, 2, 3, 4, requires_grad=True)  # M = 3 heads
    prior_std = (torch.rand(3, 2, 3, 4) + 0.5).requires_grad_(True)
    kl_prior, kl_post = kl_halves(post_mean, post_std, prior_mean, prior_std)
    plain = gaussian_kl(post_mean, post_std, prior_mean, prior_std)
    assert torch.allclose(kl_prior, plain) and torch.allclose(kl_post, plain)
    for half, own, other in ((kl_prior, (prior_mean, prior_std), (post_mean, post_std)),
                             (kl_post, (post_mean, post_std), (prior_mean, prior_std))):
        grads = torch.autograd.grad(half.sum(), (*own, *other), retain_graph=True, allow_unused=True)
        assert all(g is not None and g.abs().sum() > 0 for g in grads[:2])
        assert all(g is None for g in grads[2:])


def test_every_head_is_trained_against_the_posterior():
    prior_mean = torch.zeros(4, 1, 1, 2, requires_grad=True)
    post = torch.ones(1, 1, 2)
    balanced, _ = balanced_kl(post, torch.ones(1, 1, 2), prior_mean, torch.ones(4, 1, 1, 2), balance=0.8)
    balanced.sum().backward()
    assert (prior_mean.grad < 0).all()  # every head is pulled toward the posterior mean


def test_reconstruction_nll_sums_over_pixels():
    target = torch.zeros(2, 3, 64, 64)
    assert torch.allclose(reconstruction_nll(torch.full_like(target, 0.5), target), torch.full((2,), 0.5 * 0.25 * 3 * 64 * 64))


def test_the_mean_over_jumps_leaves_out_each_sequences_first_step():
    """The logged disagreement, like the HCU loss, averages the steps with a previous frame: the first step is
    predicted from the zero state and spans no horizon."""
    values = torch.tensor([[100.0, 1.0, 3.0], [100.0, 2.0, 6.0]])
    gaps = torch.tensor([[0, 1, 2], [0, 3, 1]])
    assert mean_over_jumps(values, gaps).item() == 3.0
