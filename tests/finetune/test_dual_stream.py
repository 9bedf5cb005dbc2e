"""The dual-stream world model and agent: frozen parameters never move, new ones all learn, the frozen
stream is conditioned on Δt^e_{k=1} + N(0, σ²) and imagines with its ensemble mean."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from finetune import load_pretrained
from finetune.agent import Agent, DivergedError
from finetune.pretrained import k1_embedding

ACTION_DIM = 3


def random_batch(cfg, rng):
    shape = (cfg.batch_size, cfg.seq_len)
    return {"obs": rng.integers(0, 256, (*shape, 3, 64, 64), dtype=np.uint8),
            "action": rng.uniform(-1, 1, (*shape, ACTION_DIM)).astype(np.float32),
            "reward": rng.normal(size=shape).astype(np.float32)}


def make_agent(cfg, export_dir):
    if cfg.agent == "scratch":
        return Agent(cfg, ACTION_DIM)
    frozen = load_pretrained(export_dir)
    return Agent(cfg, ACTION_DIM, frozen, k1_embedding(frozen))


@pytest.mark.parametrize("agent_kind", ["hauwm", "scratch"])
def test_updates_leave_frozen_parameters_bit_identical_and_change_every_new_one(export_dir, tiny_config, agent_kind):
    torch.manual_seed(0)
    # free_nats 0: with free nats the prior legitimately gets no gradient while the KL is below them
    cfg = tiny_config(agent=agent_kind, free_nats=0.0)
    agent = make_agent(cfg, export_dir)
    frozen_names = {n for n, _ in agent.named_parameters() if n.startswith("world_model.frozen.")}
    assert (len(frozen_names) > 0) == (agent_kind == "hauwm")
    before = {n: p.detach().clone() for n, p in agent.named_parameters()}
    target_before = [p.clone() for p in agent.behavior.target_critic.parameters()]
    rng = np.random.default_rng(0)
    agent.train()
    for _ in range(3):
        agent.update(random_batch(cfg, rng))
    after = dict(agent.named_parameters())
    for name in frozen_names:
        assert torch.equal(after[name], before[name]), name
        assert not after[name].requires_grad and after[name].grad is None, name
    unchanged = [n for n in before if n not in frozen_names and torch.equal(after[n], before[n])]
    assert not unchanged, f"new parameters that did not learn: {unchanged}"
    assert all(not torch.equal(a, b) for a, b in zip(agent.behavior.target_critic.parameters(), target_before))
    if agent_kind == "hauwm":
        assert not agent.world_model.frozen.training


def test_frozen_stream_gets_the_k1_embedding_plus_sigma_noise_and_k0_at_the_first_step(export_dir, tiny_config,
                                                                                        monkeypatch):
    torch.manual_seed(0)
    cfg = tiny_config(batch_size=16, seq_len=32)
    agent = make_agent(cfg, export_dir)
    frozen = agent.world_model.frozen
    seen = []
    original = frozen.rssm.observe
    monkeypatch.setattr(frozen.rssm, "observe", lambda embeds, conds, *a, **k: seen.append(conds) or original(embeds, conds, *a, **k))
    agent.world_model.loss({k: torch.as_tensor(v) for k, v in random_batch(cfg, np.random.default_rng(1)).items()})
    conds = seen[0]  # [B, L, temporal_dim]
    reference = torch.tensor(frozen.temporal.reference_length)
    k1, k0 = frozen.temporal(torch.ones(()), reference), frozen.temporal(torch.zeros(()), reference)
    assert conds.shape == (cfg.batch_size, cfg.seq_len, k1.shape[0])
    # the first step starts from the zero state with the gap-0 embedding, as every pre-training sequence did
    assert (conds[:, 0] - k0).abs().max() < 0.1 and (conds[:, 0] - k1).abs().max() > 0.5
    noise = conds[:, 1:] - k1
    assert noise.abs().max() > 0  # noise is there ...
    assert abs(noise.mean().item()) < 2e-3  # ... centred on the k = 1 embedding ...
    assert noise.std().item() == pytest.approx(0.01, rel=0.1)  # ... with σ = 0.01
    assert not torch.allclose(conds[0, 1], conds[0, 2])  # fresh noise every step


def test_acting_filters_an_episode_as_training_filters_a_window(export_dir, tiny_config, monkeypatch):
    """The frozen and new streams' states while acting (one observe_step at a time from the initial state, with
    restarts) equal those of filtering the same frames in one window: one conditioning rule for both."""
    monkeypatch.setattr(torch, "randn_like", torch.zeros_like)  # posterior samples at their means: no RNG order
    cfg = tiny_config(noise_std=0.0, batch_size=3, seq_len=5)
    agent = make_agent(cfg, export_dir)
    wm = agent.world_model
    batch = {k: torch.as_tensor(v) for k, v in random_batch(cfg, np.random.default_rng(3)).items()}
    batch["action"][:, 0] = 0  # entry 0 has no previous action, as in the replay
    window, _ = wm.observe(batch["obs"], batch["action"])
    latent, _ = agent.initial(cfg.batch_size)
    latent = agent.restart(latent.map(torch.ones_like), torch.zeros(cfg.batch_size, ACTION_DIM),
                           np.ones(cfg.batch_size, bool))[0]  # a restart gives the initial state back
    for t in range(cfg.seq_len):
        latent = wm.observe_step(latent, batch["action"][:, t], batch["obs"][:, t])
        for stream, whole in ((latent.frozen, window.frozen), (latent.new, window.new)):
            assert torch.allclose(stream.deter, whole.deter[:, t], atol=1e-5), t


def test_acting_restarts_the_frozen_stream_of_the_envs_whose_episode_ended_only(export_dir, tiny_config, monkeypatch):
    """With several envs, the zero state (an episode's first step, gap-0 embedding) is told apart per env: env 1
    restarts while env 0 goes on, and each gets what filtering its own frames gives."""
    monkeypatch.setattr(torch, "randn_like", torch.zeros_like)  # posterior samples at their means: no RNG order
    cfg = tiny_config(noise_std=0.0, batch_size=2, seq_len=3)
    agent = make_agent(cfg, export_dir)
    wm = agent.world_model
    batch = {k: torch.as_tensor(v) for k, v in random_batch(cfg, np.random.default_rng(5)).items()}
    batch["action"][:, 0] = 0
    window, _ = wm.observe(batch["obs"], batch["action"])  # env 0's episode: all three frames
    fresh, _ = wm.observe(batch["obs"][1:, 2:], torch.zeros(1, 1, ACTION_DIM))  # env 1's new episode: its last frame
    latent, prev_action = agent.initial(2)
    for t in range(2):
        latent = wm.observe_step(latent, batch["action"][:, t], batch["obs"][:, t])
    latent, prev_action = agent.restart(latent, batch["action"][:, 2], np.array([False, True]))
    latent = wm.observe_step(latent, prev_action, batch["obs"][:, 2])
    for stream, going_on, restarted in ((latent.frozen, window.frozen, fresh.frozen), (latent.new, window.new, fresh.new)):
        assert torch.allclose(stream.deter[0], going_on.deter[0, 2], atol=1e-5)
        assert torch.allclose(stream.deter[1], restarted.deter[0, 0], atol=1e-5)


def test_imagination_advances_the_frozen_stream_with_its_ensemble_mean(export_dir, tiny_config):
    torch.manual_seed(0)
    cfg = tiny_config(noise_std=0.0)
    agent = make_agent(cfg, export_dir)
    wm = agent.world_model
    start, _ = wm.observe(*(torch.as_tensor(v) for v in list(random_batch(cfg, np.random.default_rng(2)).values())[:2]))
    feats, rewards, entropies = wm.imagine(start, agent.behavior.actor, horizon=2)
    n = cfg.batch_size * cfg.seq_len
    assert feats.shape == (3, n, wm.feature_dim) and rewards.shape == (2, n) and entropies.shape == (2, n)
    frozen = wm.frozen.rssm
    state = type(start.frozen)(start.frozen.deter.flatten(0, 1), start.frozen.stoch.flatten(0, 1))
    with torch.no_grad():
        deter, means, _ = frozen.img_step(state, wm.k1_embedding.expand(n, -1))
    expected = torch.cat([deter, means.mean(0)], -1)
    assert torch.allclose(feats[1, :, : frozen.feature_dim], expected, atol=1e-6)


@pytest.mark.parametrize("layer_norm", [True, False])
def test_layer_norm_setting_reaches_actor_and_critic_only(export_dir, tiny_config, layer_norm):
    """`layer_norm` puts a LayerNorm before each hidden ELU of actor, critic and its target; the world
    model's reward head stays a plain MLP either way."""
    agent = make_agent(tiny_config(agent="scratch", layer_norm=layer_norm), export_dir)
    behavior = agent.behavior
    for net in (behavior.actor.net, behavior.critic.net, behavior.target_critic.net):
        assert sum(isinstance(m, torch.nn.LayerNorm) for m in net) == (2 if layer_norm else 0)
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in agent.world_model.reward)


def test_rewards_and_actions_line_up_with_the_states_they_belong_to(export_dir, tiny_config):
    """Replay entry t holds o_t, a_{t−1} and r_t: the reward head learns r_t from s̃_t, the new stream's state at t
    depends on actions up to a_{t−1} only, and imagination's reward is that of the state reached, R(s̃_{t+1})."""
    torch.manual_seed(0)
    cfg = tiny_config(noise_std=0.0)
    wm = make_agent(cfg, export_dir).world_model
    batch = {k: torch.as_tensor(v) for k, v in random_batch(cfg, np.random.default_rng(3)).items()}
    torch.manual_seed(1)
    _, latent, metrics = wm.loss(batch)
    predicted = wm.predicted_reward(wm.rssm.feature(latent.new))  # [B, L]
    torch.testing.assert_close(metrics["reward_nll"], 0.5 * (predicted - batch["reward"]).pow(2).mean())

    changed = {**batch, "action": batch["action"].clone()}
    changed["action"][:, -1] += 0.5  # a_{L−2}, which leads to o_{L−1}
    torch.manual_seed(1)
    latent_changed, _ = wm.observe(changed["obs"], changed["action"])
    assert torch.equal(latent_changed.new.deter[:, :-1], latent.new.deter[:, :-1])  # nothing before it moves
    assert not torch.allclose(latent_changed.new.deter[:, -1], latent.new.deter[:, -1])

    feats, rewards, _ = wm.imagine(latent, make_agent(cfg, export_dir).behavior.actor, horizon=2)
    new_dim = wm.rssm.feature_dim
    for t in range(2):
        torch.testing.assert_close(rewards[t], wm.predicted_reward(feats[t + 1, :, -new_dim:]))


def test_free_nats_floor_each_kl_part(export_dir, tiny_config):
    """DreamerV2's free nats: a KL part below `free_nats` counts as free_nats and sends no gradient."""
    torch.manual_seed(0)
    cfg = tiny_config(free_nats=100.0, kl_scale=0.5)  # far above this model's KL; small enough that float32 tells
    wm = make_agent(cfg, export_dir).world_model      # the reward's NLL (~0.5) in the sum
    batch = {k: torch.as_tensor(v) for k, v in random_batch(cfg, np.random.default_rng(4)).items()}
    loss, _, metrics = wm.loss(batch)
    assert metrics["kl"] < 100.0
    torch.testing.assert_close(loss, metrics["recon_nll"] + metrics["reward_nll"] + 0.5 * 100.0)
    loss.backward()
    assert wm.rssm.prior_out.weight.grad is None or not wm.rssm.prior_out.weight.grad.any()  # the heads learn nothing


def test_an_actor_that_gives_nan_is_refused_by_name(export_dir, tiny_config):
    agent = make_agent(tiny_config(), export_dir)
    latent, prev_action = agent.initial(2)
    obs = np.zeros((2, 3, 64, 64), np.uint8)
    agent.act(obs, latent, prev_action, explore=False)  # finite weights: fine
    with torch.no_grad():
        for parameter in agent.behavior.actor.parameters():
            parameter.fill_(float("nan"))
    with pytest.raises(DivergedError, match="non-finite action .* the agent has diverged"):
        agent.act(obs, latent, prev_action, explore=False)


def test_a_diverged_agent_never_replaces_the_last_good_checkpoint(export_dir, tiny_config, tmp_path):
    """Offline RL acts only at evaluations: a run that diverged between two went on writing NaN weights over its
    last good checkpoint.pt, every checkpoint_every updates."""
    from finetune.run_dir import run_fingerprint, save_checkpoint

    cfg = tiny_config()
    agent = make_agent(cfg, export_dir)
    checkpoint = tmp_path / "checkpoint.pt"
    fingerprint = run_fingerprint(cfg, export_dir)
    save_checkpoint(checkpoint, agent, cfg, {"env_steps": 1}, fingerprint)
    good = checkpoint.read_bytes()
    with torch.no_grad():
        next(agent.behavior.critic.parameters()).view(-1)[0] = float("nan")
    with pytest.raises(DivergedError, match=r"the agent's weights are not finite \(NaN or inf; e.g. behavior.critic.* "
                                            r"checkpoint.pt was not written over"):
        save_checkpoint(checkpoint, agent, cfg, {"env_steps": 2}, fingerprint)
    assert checkpoint.read_bytes() == good and not list(tmp_path.glob(".*.partial"))


def test_one_envs_non_finite_action_is_refused_too(export_dir, tiny_config):
    """A NaN in one env's row (its state diverged; the others' actions are finite) is refused as well."""
    agent = make_agent(tiny_config(), export_dir)
    latent, prev_action = agent.initial(2)
    prev_action[1] = float("nan")  # env 1's previous action: its new-stream state and action turn NaN
    obs = np.zeros((2, 3, 64, 64), np.uint8)
    action = agent._policy_step(torch.as_tensor(obs), latent, prev_action, False)[1]
    assert torch.isfinite(action[0]).all() and not torch.isfinite(action[1]).any()  # one row only
    with pytest.raises(DivergedError, match="non-finite action"):
        agent.act(obs, latent, prev_action, explore=False)


def test_the_kl_term_balances_its_two_halves_each_above_the_free_nats(export_dir, tiny_config, monkeypatch):
    """L_KL = α · max(KL(sg(q) ‖ p), free) + (1 − α) · max(KL(q ‖ sg(p)), free), with each half averaged first."""
    import finetune.world_model

    agent = make_agent(tiny_config(free_nats=1.0, kl_balance=0.8, kl_scale=1.0), export_dir)
    # trains the prior (mean 4.0, half its values below the free nats); regularises the posterior (0.5 everywhere)
    halves = (torch.tensor([0.5, 7.5]).repeat(16).reshape(1, 4, 8), torch.full((1, 4, 8), 0.5))
    monkeypatch.setattr(finetune.world_model, "kl_halves", lambda *distributions: halves)
    batch = {key: torch.as_tensor(value) for key, value in random_batch(tiny_config(), np.random.default_rng(4)).items()}
    _, _, metrics = agent.world_model.loss(batch)
    kl_term = metrics["model_loss"] - metrics["recon_nll"] - metrics["reward_nll"]
    # (float32 sums) the posterior's half sits below the free nats; the prior's is averaged before the floor (a floor
    # on each value first would give 0.8 · 4.25)
    assert kl_term.item() == pytest.approx(0.8 * 4.0 + 0.2 * 1.0, abs=1e-3)
    assert metrics["kl"].item() == pytest.approx(0.5)
