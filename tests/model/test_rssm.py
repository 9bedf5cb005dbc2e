"""EnsembleRSSM: shapes and dtypes through the model, the batched heads against a per-head reference."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from model.rssm import EnsembleRSSM, Observation, RSSMState, _mean_std
from model.world_model import WorldModel

from conftest import SMALL  # noqa: I001 (tests/model/conftest.py)


def small_rssm(ensemble: int = 5) -> EnsembleRSSM:
    torch.manual_seed(0)
    return EnsembleRSSM(embed_dim=12, cond_dim=8, deter=20, stoch=6, hidden=16, ensemble=ensemble)


def test_steps_return_documented_shapes_and_float32():
    rssm = small_rssm()
    prev = rssm.initial(4, "cpu")
    assert prev.deter.shape == (4, 20) and prev.stoch.shape == (4, 6)
    deter, mean, std = rssm.img_step(prev, torch.randn(4, 8))
    assert deter.shape == (4, 20) and mean.shape == std.shape == (5, 4, 6)
    cond = torch.randn(4, 8)
    post, post_mean, post_std = rssm.obs_step(prev, cond, torch.randn(4, 12))
    assert isinstance(post, RSSMState) and post.stoch.shape == post_mean.shape == post_std.shape == (4, 6)
    prior_mean, prior_std = rssm.heads(post.deter, cond)
    assert prior_mean.shape == (5, 4, 6)
    assert rssm.feature(post).shape == (4, 26)
    assert all(t.dtype == torch.float32 for t in (post_mean, post_std, prior_mean, prior_std))
    assert (std >= 0.1).all() and (post_std >= 0.1).all() and (std <= 1.0).all() and (post_std <= 1.0).all()


def test_observe_and_imagine_shapes():
    rssm = small_rssm()
    obs = rssm.observe(torch.randn(3, 7, 12), torch.randn(3, 7, 8))
    assert obs.deter.shape == (3, 7, 20) and obs.stoch.shape == (3, 7, 6)
    assert obs.post_mean.shape == (3, 7, 6) and obs.prior_mean.shape == obs.prior_std.shape == (5, 3, 7, 6)
    conds = torch.randn(3, 4, 8)
    states, means = rssm.imagine(obs.state(6), conds)
    assert states.deter.shape == (3, 4, 20) and states.stoch.shape == (3, 4, 6) and means.shape == (5, 3, 4, 6)
    # along the ensemble-mean path, each next stoch is the mean over heads
    assert torch.allclose(states.stoch, means.mean(0))
    head_states, head_means = rssm.imagine(obs.state(6), conds, head=2)
    assert head_states.stoch.shape == (3, 4, 6)
    assert torch.equal(head_states.stoch, head_means[2])  # along head 2's own path, its mean is the next stoch
    assert not torch.allclose(head_states.stoch, states.stoch)  # not the ensemble-mean path


def test_the_transition_is_a_gru_of_the_previous_state_and_the_condition():
    """deter_t = GRU(deter_{t−1}, ELU(W [stoch_{t−1}; c_t] + b)), written out by hand (torch's GRUCell equations):
    the filter's test steps img_step itself, so a transition that dropped its previous stoch, its condition (the
    gap) or its recurrence passed it too."""
    rssm = small_rssm()
    prev, cond = RSSMState(torch.randn(4, 20), torch.randn(4, 6)), torch.randn(4, 8)
    x = F.elu(torch.cat([prev.stoch, cond], -1) @ rssm.img_in[0].weight.T + rssm.img_in[0].bias)
    cell = rssm.cell
    x_r, x_z, x_n = (x @ cell.weight_ih.T + cell.bias_ih).chunk(3, -1)
    h_r, h_z, h_n = (prev.deter @ cell.weight_hh.T + cell.bias_hh).chunk(3, -1)
    reset, update = torch.sigmoid(x_r + h_r), torch.sigmoid(x_z + h_z)
    candidate = torch.tanh(x_n + reset * h_n)
    deter = rssm.transition(prev, cond)
    torch.testing.assert_close(deter, (1 - update) * candidate + update * prev.deter)
    for changed in (RSSMState(prev.deter, prev.stoch + 1), RSSMState(prev.deter + 1, prev.stoch)):
        assert not torch.allclose(rssm.transition(changed, cond), deter)
    assert not torch.allclose(rssm.transition(prev, cond + 1), deter)


@pytest.mark.parametrize("head", [None, 2])
def test_imagine_feeds_back_the_ensemble_mean_or_its_heads_own_mean_from_the_start_state(head):
    rssm = small_rssm()
    obs = rssm.observe(torch.randn(3, 7, 12), torch.randn(3, 7, 8))
    conds = torch.randn(3, 4, 8)
    states, means = rssm.imagine(obs.state(6), conds, head=head)
    state = obs.state(6)
    for t in range(4):  # by hand, from the start state
        deter, mean, _ = rssm.img_step(state, conds[:, t])
        state = RSSMState(deter, mean.mean(0) if head is None else mean[head])
        torch.testing.assert_close(states.deter[:, t], state.deter)
        torch.testing.assert_close(states.stoch[:, t], state.stoch)
        torch.testing.assert_close(means[:, :, t], mean)


def test_batched_heads_equal_a_per_head_reference():
    rssm = small_rssm(ensemble=7)
    deter, cond = torch.randn(9, 20), torch.randn(9, 8)
    mean, std = rssm.heads(deter, cond)
    for i in range(7):
        hidden = F.elu(torch.cat([deter, cond], -1) @ rssm.prior_hidden.weight[i] + rssm.prior_hidden.bias[i])
        raw = hidden @ rssm.prior_out.weight[i] + rssm.prior_out.bias[i]
        ref_mean, ref_std = raw.chunk(2, -1)
        assert torch.allclose(mean[i], ref_mean, atol=1e-6)
        assert torch.allclose(std[i], 0.1 + 0.9 * torch.sigmoid(ref_std + 2.0), atol=1e-6)
    # and the heads really differ (independent initialisation)
    assert not torch.allclose(mean[0], mean[1])


def test_heads_refuse_a_time_axis_that_would_pass_for_the_heads_axis():
    """deter [B, L, D] with B = M went through head i for batch row i only, and came out [M, L, S] without a word."""
    rssm = small_rssm(ensemble=3)
    with pytest.raises(ValueError, match=r"heads takes deter \[B, D\], not \[3, 7, 20\]: flatten the leading axes"):
        rssm.heads(torch.randn(3, 7, 20), torch.randn(3, 7, 8))


def test_observe_equals_a_step_by_step_filter_in_values_and_gradients():
    """observe computes the prior heads of all steps after the loop and unbinds its inputs along time: the same
    numbers, forward and backward, as the transition, heads and posterior taken one step at a time."""
    rssm = small_rssm()
    embeds, conds = torch.randn(3, 5, 12, requires_grad=True), torch.randn(3, 5, 8, requires_grad=True)
    noise = rssm.draw_noise(3, 5, torch.Generator().manual_seed(0))

    def step_by_step() -> list[torch.Tensor]:
        state, steps = rssm.initial(3), []
        for t in range(5):
            deter, prior_mean, prior_std = rssm.img_step(state, conds[:, t])
            post_mean, post_std = _mean_std(rssm.posterior(torch.cat([deter, embeds[:, t]], -1)), 0.1, 1.0)
            state = RSSMState(deter, post_mean + post_std * noise[:, t])
            steps.append((deter, state.stoch, post_mean, post_std, prior_mean, prior_std))
        return [torch.stack(values, 2 if name.startswith("prior") else 1)
                for name, values in zip(Observation._fields, zip(*steps))]

    def values_and_gradients(filtered: list[torch.Tensor]) -> list[torch.Tensor]:
        loss = sum((value * torch.linspace(-1, 1, value.numel()).view_as(value)).sum() for value in filtered)
        inputs = [embeds, conds, *rssm.parameters()]
        return filtered + list(torch.autograd.grad(loss, inputs))

    for ours, reference in zip(values_and_gradients(list(rssm.observe(embeds, conds, noise=noise))),
                               values_and_gradients(step_by_step())):
        torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-6)


def test_distribution_parameters_stay_float32_under_autocast():
    rssm = small_rssm()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        obs = rssm.observe(torch.randn(2, 3, 12), torch.randn(2, 3, 8))
    assert obs.prior_mean.dtype == obs.prior_std.dtype == obs.post_std.dtype == torch.float32


def test_world_model_observes_a_loader_batch(fake_batch, small_sizes):
    model = WorldModel(small_sizes)
    obs = model.observe(fake_batch["frames"], fake_batch["gaps"], fake_batch["num_frames"])
    B, L = fake_batch["gaps"].shape
    assert obs.deter.shape == (B, L, small_sizes.deter) and obs.prior_mean.shape == (small_sizes.ensemble, B, L, small_sizes.stoch)
    images = model.decode(RSSMState(obs.deter, obs.stoch))
    assert images.shape == (B, L, 3, 64, 64) and images.dtype == torch.float32


def test_posterior_samples_follow_the_noise():
    rssm = small_rssm()
    embeds, conds = torch.randn(2, 4, 12), torch.randn(2, 4, 8)
    a, b, c = (rssm.observe(embeds, conds, noise=rssm.draw_noise(2, 4, torch.Generator().manual_seed(seed)))
               for seed in (1, 1, 2))
    assert torch.equal(a.stoch, b.stoch) and not torch.equal(a.stoch, c.stoch)
    zero = rssm.observe(embeds, conds, noise=torch.zeros(2, 4, rssm.stoch_dim))
    assert torch.equal(zero.stoch, zero.post_mean)  # stoch = mean + std · noise


def test_the_heads_read_the_gap_and_the_posterior_reads_the_new_state():
    """p_i(s_t | h_t, Δt_k) and q(s_t | h_t, e_t): the heads see the step's gap embedding, the posterior the
    deterministic state of this step (not the previous one)."""
    rssm = small_rssm()
    prev = rssm.obs_step(rssm.initial(4, "cpu"), torch.randn(4, 8), torch.randn(4, 12))[0]  # h ≠ 0
    cond, embed = torch.randn(4, 8), torch.randn(4, 12)
    deter, mean, std = rssm.img_step(prev, cond)
    heads_mean, heads_std = rssm.heads(deter, cond)
    assert torch.equal(mean, heads_mean) and torch.equal(std, heads_std)
    assert not torch.allclose(rssm.heads(deter, torch.zeros_like(cond))[0], mean)  # the gap changes the heads
    state, post_mean, post_std = rssm.obs_step(prev, cond, embed, noise=torch.zeros(4, 6))
    expected_mean, expected_std = _mean_std(rssm.posterior(torch.cat([deter, embed], -1)), rssm.min_std, rssm.max_std)
    assert torch.equal(state.deter, deter)
    assert torch.equal(post_mean, expected_mean) and torch.equal(post_std, expected_std)
    assert torch.equal(state.stoch, post_mean)  # zero noise: the sample is the mean


def test_each_frame_is_conditioned_on_the_gap_before_it_and_its_clips_length(monkeypatch):
    torch.manual_seed(0)
    model = WorldModel(SMALL)
    gaps, num_frames = torch.tensor([[0, 1, 3, 2], [0, 5, 1, 1]]), torch.tensor([40, 90])
    seen = []
    observe = model.rssm.observe
    monkeypatch.setattr(model.rssm, "observe", lambda embeds, conds, **kw: seen.append(conds) or observe(embeds, conds, **kw))
    model.observe(torch.zeros(2, 4, 3, 64, 64, dtype=torch.uint8), gaps, num_frames)
    for b in range(2):
        for t in range(4):
            torch.testing.assert_close(seen[0][b, t], model.temporal(gaps[b, t], num_frames[b]))
    assert not torch.allclose(model.conditions(gaps, torch.tensor([40, 40]))[1], seen[0][1])  # T matters (relative)
