"""The actor's truncated normal (finetune.behavior.TruncatedNormal) against scipy's truncnorm."""

from __future__ import annotations

import pytest
import torch
from scipy import stats

from finetune.behavior import Actor, TruncatedNormal

LOCS = torch.tensor([[0.0, 0.9, -0.95]])
SCALES = torch.tensor([[1.1, 0.1, 2.0]])


def reference(i: int):
    loc, scale = LOCS[0, i].item(), SCALES[0, i].item()
    return stats.truncnorm((-1 - loc) / scale, (1 - loc) / scale, loc=loc, scale=scale)


def test_log_prob_and_entropy_equal_scipys():
    dist = TruncatedNormal(LOCS, SCALES)
    value = torch.tensor([[0.3, 0.95, -0.2]])
    expected_log_prob = sum(reference(i).logpdf(value[0, i].item()) for i in range(3))
    expected_entropy = sum(reference(i).entropy() for i in range(3))
    assert dist.log_prob(value).item() == pytest.approx(expected_log_prob, rel=1e-4)
    assert dist.entropy().item() == pytest.approx(expected_entropy, rel=1e-4)


def test_samples_stay_in_bounds_and_follow_the_distribution():
    torch.manual_seed(0)
    samples = TruncatedNormal(LOCS.expand(20000, -1), SCALES.expand(20000, -1)).rsample()
    assert samples.abs().max() < 1
    for i in range(3):  # Kolmogorov–Smirnov against the exact CDF
        assert stats.kstest(samples[:, i].numpy(), reference(i).cdf).pvalue > 1e-4


def test_samples_are_reparameterised():
    """d E[x] / d loc from the samples equals the derivative of scipy's mean (finite differences)."""
    torch.manual_seed(0)
    loc = torch.full((50000, 1), 0.4, requires_grad=True)
    TruncatedNormal(loc, torch.full((50000, 1), 0.7)).rsample().mean().backward()

    def mean(m: float) -> float:
        return stats.truncnorm((-1 - m) / 0.7, (1 - m) / 0.7, loc=m, scale=0.7).mean()

    expected = (mean(0.4 + 1e-4) - mean(0.4 - 1e-4)) / 2e-4
    assert loc.grad.sum().item() == pytest.approx(expected, rel=0.05)  # Σ_i ∂(mean of samples)/∂loc_i


@pytest.mark.parametrize("layer_norm", [True, False])
def test_actor_starts_wide_and_unsaturated(layer_norm: bool):
    """DreamerV2's init: std 2·sigmoid(raw / 2) + 0.1 ≈ 1.1 before training and the mode inside (−1, 1),
    with or without the LayerNorms (which make the untrained outputs vary more from state to state)."""
    torch.manual_seed(0)
    dist = Actor(feat_dim=120, action_dim=2, units=400, layer_norm=layer_norm)(torch.randn(1000, 120))
    scale = dist.scale.detach().numpy()
    assert abs(scale.mean() - 1.1) < 0.1 and scale.min() > 0.6 and scale.max() < 1.7
    assert dist.mode.abs().mean() < 0.4 and dist.mode.abs().max() < 0.99
