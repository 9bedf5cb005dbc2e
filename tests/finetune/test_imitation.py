"""Imitation (eq. 5): the discriminator, and short runs that learn from no env reward and resume exactly."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from model.config import ConfigError
from finetune.config import FinetuneError
from finetune.discriminator import Discriminator
from finetune.imitation import ImitationAgent, MixedReplay, demos_per_batch, train_imitation
from finetune.envs import make_env
from finetune.replay import Replay
from finetune.run_dir import CHECKPOINT
from finetune.train import ENV_SEED_STRIDE, build_agent, episode_seed
from finetune.world_model import Latent
from test_finetune_runs import rows  # noqa: I001 (tests/finetune/test_finetune_runs.py)


def test_discriminator_separates_expert_latents_from_random_ones_after_a_few_steps():
    torch.manual_seed(0)
    disc = Discriminator(feat_dim=16, action_dim=2, units=32, lr=3e-3)
    expert_feat, expert_action = 1.5 + 0.3 * torch.randn(256, 16), torch.full((256, 2), 0.5)

    def random_pairs():
        return torch.randn(256, 16), torch.rand(256, 2) * 2 - 1

    first = disc.update(expert_feat, expert_action, *random_pairs())
    for _ in range(40):
        last = disc.update(expert_feat, expert_action, *random_pairs())
    assert first["disc_accuracy"] < 0.8 and last["disc_loss"] < 0.5 * first["disc_loss"] and last["disc_accuracy"] > 0.95
    with torch.no_grad():
        assert disc.logit(expert_feat, expert_action).mean() > 0 > disc.logit(*random_pairs()).mean()


def test_the_reward_is_the_logit_with_gradients_to_the_pair_and_none_to_the_discriminator():
    disc = Discriminator(feat_dim=4, action_dim=2, units=8)
    feat, action = torch.randn(5, 4, requires_grad=True), torch.randn(5, 2, requires_grad=True)
    reward = disc.reward(feat, action)
    d = torch.sigmoid(disc.logit(feat, action))
    assert torch.allclose(reward, torch.log(d) - torch.log1p(-d), atol=1e-5)
    reward.sum().backward()
    assert action.grad.abs().sum() > 0 and feat.grad.abs().sum() > 0
    assert all(p.grad is None for p in disc.parameters())


def test_the_gradient_penalty_is_taken_on_the_input():
    """A discriminator whose logit is linear in its input with slope norm g pays (g − 1)² whatever the data."""
    disc = Discriminator(feat_dim=3, action_dim=1, units=4, layer_norm=False)
    with torch.no_grad():
        for module in disc.net:
            if isinstance(module, torch.nn.Linear):
                module.weight.zero_()
                module.bias.zero_()
        disc.net[0].weight[0] = torch.tensor([3.0, 0.0, 4.0, 0.0])  # unit 0 = 3 x_0 + 4 x_2 (|slope| 5)
        disc.net[2].weight[0, 0] = 1.0  # passed on by the second hidden layer and the output
        disc.net[-1].weight[0, 0] = 1.0
    big = 10 + torch.rand(8, 3)  # ELU is the identity for positive inputs: logit = 3 x_0 + 4 x_2, slope norm 5
    metrics = disc.update(big, torch.ones(8, 1), big + 1, torch.ones(8, 1))
    assert metrics["disc_penalty"] == pytest.approx(16.0, rel=1e-4)


def test_the_gradient_penalty_is_taken_at_random_interpolates_of_expert_and_policy_pairs():
    torch.manual_seed(0)
    disc = Discriminator(feat_dim=4, action_dim=2, units=16)
    expert, policy = (torch.randn(32, 4) + 2, torch.rand(32, 2)), (torch.randn(48, 4) - 2, torch.rand(48, 2))
    x_e, x_p = torch.cat(expert, -1), torch.cat(policy, -1)

    def penalty_at(points: torch.Tensor) -> float:
        points = points.clone().requires_grad_(True)
        grad = torch.autograd.grad(disc.net(points).sum(), points)[0]
        return (grad.norm(dim=-1) - 1).pow(2).mean().item()

    torch.manual_seed(1)  # the draws update makes next: one policy pair per expert pair, then α ~ U(0, 1)
    pick, alpha = torch.randint(48, (32,)), torch.rand(32, 1)
    at_interpolates, at_experts = penalty_at(alpha * x_e + (1 - alpha) * x_p[pick]), penalty_at(x_e)
    torch.manual_seed(1)
    assert disc.update(*expert, *policy)["disc_penalty"].item() == pytest.approx(at_interpolates, rel=1e-5)
    assert abs(at_interpolates - at_experts) > 1e-3 * at_interpolates  # the test could tell the two apart


def test_the_gradient_penalty_enters_the_discriminators_gradient_in_proportion_to_its_scale():
    """L_D = bce + c · penalty: D's parameter gradient is linear in c, and the penalty's part is not zero."""
    data = (torch.randn(16, 4) + 1, torch.rand(16, 2), torch.randn(16, 4) - 1, torch.rand(16, 2))
    gradients = {}
    for scale in (0.0, 1.0, 10.0):
        torch.manual_seed(0)
        disc = Discriminator(feat_dim=4, action_dim=2, units=8, gp_scale=scale, grad_clip=1e9)
        disc.update(*data)  # the same initial weights and draws for every scale
        gradients[scale] = torch.cat([p.grad.flatten() for p in disc.net.parameters()])
    penalty_part = gradients[1.0] - gradients[0.0]
    assert penalty_part.abs().max() > 1e-6
    torch.testing.assert_close(gradients[10.0] - gradients[0.0], 10 * penalty_part, rtol=1e-4, atol=1e-6)


def test_a_mixed_batch_holds_the_agents_windows_first_and_the_demonstrations_last(random_episodes):
    """ImitationAgent takes the last demos_per_batch windows of a batch as the expert's: MixedReplay puts them there."""
    own, demos = Replay(None, 1000, np.random.default_rng(0)), Replay(None, 1000, np.random.default_rng(1))
    for replay, reward in ((own, 1.0), (demos, 2.0)):
        for episode in random_episodes(2, 10, 3):
            replay.add({**episode, "reward": np.full_like(episode["reward"], reward)})  # which replay a window is from
    batch = MixedReplay(own, demos, demos_per_batch=2).sample(5, 4)
    assert batch["obs"].shape[:2] == (5, 4)
    np.testing.assert_array_equal(batch["reward"][:, 0], [1.0, 1.0, 1.0, 2.0, 2.0])


def test_demonstration_windows_per_batch_are_the_nearest_share_leaving_one_of_each_kind():
    for batch_size, fraction, expected in ((16, 0.5, 8), (16, 0.3, 5), (4, 0.05, 1), (4, 0.95, 3)):  # 4.8 → 5
        settings = SimpleNamespace(batch_size=batch_size, demo_fraction=fraction)
        assert demos_per_batch(settings) == expected, (batch_size, fraction)


def imitation_config(tiny_config, logdir, steps, **extra):
    values = dict(paradigm="imitation", task="metaworld_drawer_close", demos="test/two-demos-v0", action_repeat=1,
                  time_limit=8, fast_render=True, steps=steps, prefill=8, train_every=4, eval_every=16,
                  eval_episodes=1, log_every=8, checkpoint_every=16, horizon=3, logdir=str(logdir))
    values.update(extra)
    return tiny_config(**values)


@pytest.fixture
def two_demos(minari_dataset, random_episodes):
    return minari_dataset("test/two-demos-v0", random_episodes(2, 12, 4, seed=1), "metaworld_drawer_close")


def test_imitation_run_learns_from_no_env_reward_and_a_resumed_run_continues_exactly(
        export_dir, tiny_config, tmp_path, two_demos):
    whole = train_imitation(imitation_config(tiny_config, tmp_path / "whole", 32), export_dir, progress=False)
    assert set(whole) >= {"return", "normalised_return", "success_rate"}
    train_imitation(imitation_config(tiny_config, tmp_path / "halves", 16), export_dir, progress=False)
    assert train_imitation(imitation_config(tiny_config, tmp_path / "halves", 32), export_dir, progress=False) == whole

    first = torch.load(tmp_path / "whole" / CHECKPOINT, weights_only=True)
    second = torch.load(tmp_path / "halves" / CHECKPOINT, weights_only=True)
    assert first["counters"] == second["counters"] and first["counters"]["updates"] == 6
    assert any(key.startswith("discriminator.") for key in first["agent"])
    assert "discriminator" in first["optimizers"]
    assert all(torch.equal(value, second["agent"][key]) for key, value in first["agent"].items())
    assert rows(tmp_path / "whole" / "eval.csv") == rows(tmp_path / "halves" / "eval.csv")
    episodes = rows(tmp_path / "whole" / "episodes.csv")
    assert len(episodes) == 4 and all("return" in row for row in episodes)  # the env return is logged
    train = rows(tmp_path / "whole" / "train.csv")
    assert float(train[-1]["reward_nll"]) == 0.0 and 0 <= float(train[-1]["disc_expert_prob"]) <= 1

    # no env reward is learned from: the reward head is as initialised (a fresh agent of the same seed)
    cfg = imitation_config(tiny_config, tmp_path / "fresh", 32)
    torch.manual_seed(cfg.seed)
    fresh = build_agent(cfg, 4, export_dir, torch.device("cpu"), ImitationAgent).trainable_state_dict()
    reward_head = [key for key in fresh if key.startswith("world_model.reward.")]
    assert reward_head and all(torch.equal(fresh[key], first["agent"][key]) for key in reward_head)
    decoder = [key for key in fresh if key.startswith("world_model.decoder.")]
    assert not all(torch.equal(fresh[key], first["agent"][key]) for key in decoder)  # the rest did learn


def agent_on_a_batch(cfg, export_dir, random_episodes) -> tuple[ImitationAgent, torch.Tensor, Latent, slice]:
    """An imitation agent, the actions [B, L, A] of a batch of random windows, their posterior states, and the
    slice of the batch's demonstration windows."""
    agent = build_agent(cfg, 4, export_dir, torch.device("cpu"), ImitationAgent)
    episodes = random_episodes(cfg.batch_size, cfg.seq_len - 1, 4, seed=3)
    batch = {key: torch.as_tensor(np.stack([episode[key] for episode in episodes])) for key in ("obs", "action")}
    with torch.no_grad():
        _, start, _ = agent.world_model.loss({**batch, "reward": torch.zeros(batch["action"].shape[:2])})
    return agent, batch["action"], start, slice(cfg.batch_size - agent.demos_per_batch, None)


@pytest.mark.parametrize("kind", ["imagined", "posterior"])
def test_expert_pairs_are_imagined_along_the_demonstrations_actions_or_are_their_posteriors(
        export_dir, tiny_config, tmp_path, random_episodes, kind):
    cfg = imitation_config(tiny_config, tmp_path, 16, expert_latents=kind)  # L = 8, H = 3
    torch.manual_seed(0)
    agent, all_actions, start, demos = agent_on_a_batch(cfg, export_dir, random_episodes)
    actions = all_actions[demos, 1:]  # [B_d, L − 1, A]
    posterior = agent.world_model.feature(start)[demos]  # [B_d, L, F]

    def expert(actions):
        torch.manual_seed(1)  # the same draws in imagination
        return agent.expert_pairs(start, demos, actions)

    feats, paired = expert(actions)
    if kind == "posterior":
        assert torch.equal(feats, posterior[:, :-1]) and torch.equal(paired, actions)
        return
    depth, positions = cfg.horizon, cfg.seq_len - cfg.horizon  # depths 0..H−1 from positions 0..L−1−H
    demo_count = actions.shape[0]
    assert feats.shape == (depth, demo_count * positions, posterior.shape[-1])
    assert paired.shape == (depth, demo_count * positions, actions.shape[-1])
    for demo, position in [(0, 0), (demo_count - 1, positions - 1), (demo_count - 1, 1)]:
        column = demo * positions + position
        assert torch.equal(feats[0, column], posterior[demo, position])  # imagination starts at a posterior state
        assert torch.equal(paired[:, column], actions[demo, position:position + depth])  # a_p..a_{p+H−1}
    along = posterior.unfold(1, depth, 1)[:, :positions].permute(3, 0, 1, 2).flatten(1, 2)  # z_{p+t}, [H, B_d·P, F]
    assert torch.equal(along[0], feats[0]) and not torch.allclose(feats[1:], along[1:])  # imagined, not observed
    assert torch.equal(expert(actions)[0], feats)
    torch.manual_seed(1)
    agent.imagined_reward({"action": all_actions}, start)  # what an update pairs: entry t + 1 holds a_t
    assert torch.equal(agent.demo_pairs[0], feats) and torch.equal(agent.demo_pairs[1], paired)
    new = slice(-agent.world_model.rssm.feature_dim, None)  # the new stream: the one that reads the actions
    other, _ = expert(-actions)
    assert torch.equal(other[0], feats[0]) and not torch.allclose(other[1:, :, new], feats[1:, :, new])


def test_expert_pairs_of_windows_shorter_than_the_horizon_cover_what_the_window_holds(
        export_dir, tiny_config, tmp_path, random_episodes):
    cfg = imitation_config(tiny_config, tmp_path, 16, seq_len=3, horizon=5)
    agent, actions, start, demos = agent_on_a_batch(cfg, export_dir, random_episodes)
    for length in (2, 1):  # L − 1 = 2 actions: one start, depths 0 and 1; one action: the posterior state alone
        feats, paired = agent.expert_pairs(start, demos, actions[demos, 1:1 + length])
        assert feats.shape[:2] == paired.shape[:2] == (length, agent.demos_per_batch)
    assert torch.equal(feats[0], agent.world_model.feature(start)[demos, 0])


def test_a_run_resumes_only_with_the_expert_latents_it_was_trained_with(export_dir, tiny_config, tmp_path, two_demos):
    run = tmp_path / "run"
    train_imitation(imitation_config(tiny_config, run, 16, expert_latents="posterior"), export_dir, progress=False)
    with pytest.raises(FinetuneError, match="expert_latents='posterior', this run has expert_latents='imagined'"):
        train_imitation(imitation_config(tiny_config, run, 32), export_dir, progress=False)
    state = torch.load(run / CHECKPOINT, weights_only=True)
    del state["config"]["expert_latents"]  # as written before the setting existed: posterior expert pairs
    torch.save(state, run / CHECKPOINT)
    with pytest.raises(FinetuneError, match="expert_latents='posterior', this run has expert_latents='imagined'"):
        train_imitation(imitation_config(tiny_config, run, 32), export_dir, progress=False)
    train_imitation(imitation_config(tiny_config, run, 32, expert_latents="posterior"), export_dir, progress=False)


def test_bad_imitation_settings_are_refused_with_clear_errors(export_dir, tiny_config, tmp_path, two_demos):
    with pytest.raises(ConfigError, match="demo_fraction must be strictly between 0 and 1"):
        imitation_config(tiny_config, tmp_path, 16, demo_fraction=1.0)
    with pytest.raises(FinetuneError, match="--demos ID is needed"):
        train_imitation(imitation_config(tiny_config, tmp_path / "a", 16, demos=None), export_dir, progress=False)
    with pytest.raises(FinetuneError, match="--demos test/two-demos-v0: no episode holds seq_len = 20 frames"):
        train_imitation(imitation_config(tiny_config, tmp_path / "b", 16, seq_len=20, time_limit=30), export_dir,
                        progress=False)
    with pytest.raises(FinetuneError, match=r"seq_len = 12 is longer than an episode of metaworld_drawer_close \(9 "
                                            r"frames at time_limit 8\): no update could ever train"):
        train_imitation(imitation_config(tiny_config, tmp_path / "d", 16, seq_len=12), export_dir, progress=False)
    with pytest.raises(FinetuneError, match="paradigm 'imitation'"):
        train_imitation(tiny_config(logdir=str(tmp_path / "c")), export_dir, progress=False)


def test_a_refused_dataset_leaves_the_run_directory_as_it_was(export_dir, tiny_config, tmp_path, two_demos):
    train_imitation(imitation_config(tiny_config, tmp_path / "run", 16), export_dir, progress=False)
    written = (tmp_path / "run" / "config.yaml").read_text()
    with pytest.raises(FinetuneError, match="--demos test/missing-v0"):
        train_imitation(imitation_config(tiny_config, tmp_path / "run", 32, demos="test/missing-v0"), export_dir,
                        progress=False)
    assert (tmp_path / "run" / "config.yaml").read_text() == written


def test_with_parallel_envs_every_episode_starts_from_its_own_seed(export_dir, tiny_config, tmp_path, two_demos):
    """num_envs 2: env i's episodes are reset with episode_seed(seed, i, episodes so far), in the env made with
    the seed of a fresh run, and end up apart in the replay."""
    cfg = imitation_config(tiny_config, tmp_path / "run", 32, num_envs=2, eval_every=32, checkpoint_every=32)
    train_imitation(cfg, export_dir, progress=False)
    episodes = sorted((tmp_path / "run" / "replay").glob("*.npz"))
    assert len(episodes) == 4  # both envs end an 8-step episode at env steps 16 and 32
    env_kwargs = dict(action_repeat=1, time_limit=8, fast_render=True)
    for index, path in enumerate(episodes):  # order: env 0, env 1, env 0, env 1
        env_index, episodes_before = index % 2, 2 * (index // 2)
        env = make_env(cfg.task, seed=cfg.seed + ENV_SEED_STRIDE * env_index, **env_kwargs)
        first = env.reset(seed=episode_seed(cfg.seed, env_index, episodes_before))[0]
        env.close()
        with np.load(path) as episode:
            assert len(episode["obs"]) == 9
            np.testing.assert_array_equal(episode["obs"][0], first, err_msg=f"episode {index}")


def test_runs_with_neighbouring_seeds_play_different_episodes():
    """seed + episodes would make run 0's second episode run 1's first; episode_seed gives each its own."""
    seeds = {episode_seed(run, env, episodes) for run in range(4) for env in range(2) for episodes in range(50)}
    assert len(seeds) == 4 * 2 * 50 and all(0 <= seed < 2**32 for seed in seeds)
