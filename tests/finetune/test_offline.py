"""Offline RL (eq. 6): the uncertainty penalty, and short runs that write eval.csv and resume exactly."""

from __future__ import annotations


import dataclasses
import math
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from model.config import ConfigError
from finetune.config import FinetuneError
from finetune.offline import OfflineAgent, train_offline
from finetune.penalty import PenalisedReward, uncertainty
from model.losses import disagreement
from finetune.datasets.minari_io import dataset_path
from finetune.run_dir import BEST, CHECKPOINT, export_fingerprint, load_trained, run_fingerprint
from test_finetune_runs import rows  # noqa: I001 (tests/finetune/test_finetune_runs.py)

KINDS = ("loglik_std", "max_std", "mean_disagreement")


def heads(spread: float, std_spread: float = 0.0, m: int = 5, n: int = 64, s: int = 6):
    """M prior heads around one prediction: means [M, N, S] spread by `spread`, stds by `std_spread`."""
    generator = torch.Generator().manual_seed(0)
    base, offsets = torch.randn(n, s, generator=generator), torch.randn(m, n, s, generator=generator)
    std = 0.5 + std_spread * torch.rand(m, n, s, generator=generator)
    return base + spread * offsets, std, base + 0.5 * torch.randn(n, s, generator=generator)


@pytest.mark.parametrize("kind", ["loglik_std", "mean_disagreement"])
def test_disagreement_penalties_are_zero_when_heads_agree_and_grow_with_spread(kind):
    values = [uncertainty(kind, *heads(spread)).mean().item() for spread in (0.0, 0.1, 0.5, 2.0)]
    assert values[0] == pytest.approx(0.0, abs=1e-5)
    assert values[1] < values[2] < values[3]


def test_max_std_is_the_common_std_norm_when_heads_agree_and_grows_with_their_std_spread():
    mean, std, sample = heads(0.0)
    assert torch.allclose(uncertainty("max_std", mean, std, sample), std[0].norm(dim=-1))
    values = [uncertainty("max_std", *heads(0.0, std_spread)).mean().item() for std_spread in (0.0, 0.2, 1.0)]
    assert values[0] < values[1] < values[2]


def test_each_penalty_on_a_hand_made_example():
    """u of the three kinds on M = 2 heads, S = 2 latent dims, worked by hand from the formulas of finetune/penalty.py."""
    mean = torch.tensor([[[0.0, 0.0]], [[6.0, 8.0]]])  # [M, N = 1, S]: μ̄ = (3, 4), each head ‖μ_i − μ̄‖ = 5 away
    std = torch.tensor([[[0.6, 0.8]], [[1.5, 2.0]]])  # ‖σ_i‖ = 1 and 2.5
    sample = torch.tensor([[3.0, 4.0]])  # s̃_{t+1}: z = (5, 5) under head 0, (−2, −2) under head 1
    assert uncertainty("mean_disagreement", mean, std, sample).item() == pytest.approx(5.0)  # mean_i ‖μ_i − μ̄‖₂
    assert uncertainty("max_std", mean, std, sample).item() == pytest.approx(2.5)  # max_i ‖σ_i‖₂
    # log N summed over S: head 0 −25 − ln(0.6 · 0.8) − ln 2π, head 1 −4 − ln(1.5 · 2) − ln 2π; the population std
    # of two values is half their distance
    loglik_std = (21 - math.log(3.0 / 0.48)) / 2
    assert uncertainty("loglik_std", mean, std, sample).item() == pytest.approx(loglik_std, rel=1e-5)


def test_every_penalty_has_a_gradient_to_the_heads_means_except_max_std():
    for kind in KINDS:
        mean, std, sample = heads(0.5)
        mean.requires_grad_(True)
        std.requires_grad_(True)
        grad = torch.autograd.grad(uncertainty(kind, mean, std, sample).sum(), mean, allow_unused=True)[0]
        assert (grad is not None and grad.abs().sum() > 0) == (kind != "max_std"), kind


@pytest.mark.parametrize("kind", KINDS)
def test_the_imagined_reward_is_the_model_reward_minus_scale_times_u(kind):
    """Eq. 6: r̃ = R(s̃_{t+1}) − λ · (u + w · frozen disagreement), on one imagination's rollout."""
    mean, std, sample = heads(0.5, 0.3, m=4, n=6)  # [M, N, S]: M heads, N = H · batch imagined steps
    rollout = SimpleNamespace(new_feats=torch.randn(3, 2, 5), prior_mean=mean.view(4, 3, 2, 6).transpose(0, 1),
                              prior_std=std.view(4, 3, 2, 6).transpose(0, 1), new_stoch=sample.view(3, 2, 6),
                              frozen_means=torch.randn(3, 5, 2, 7))  # [H, M', N, S']
    world_model = SimpleNamespace(predicted_reward=lambda feats: feats.sum(-1))  # [H, N]
    u = uncertainty(kind, mean, std, sample).view(3, 2)
    frozen = disagreement(rollout.frozen_means.transpose(0, 1))
    for scale, weight in ((0.0, 0.0), (5.0, 0.0), (5.0, 2.0)):
        reward = PenalisedReward(world_model, kind, scale, weight)(rollout)
        torch.testing.assert_close(reward, rollout.new_feats.sum(-1) - scale * (u + weight * frozen))


def offline_config(tiny_config, logdir, steps, **extra):
    values = dict(paradigm="offline", task="metaworld_drawer_close", dataset="test/two-episodes-v0", action_repeat=1,
                  model_heads=3, horizon=3, time_limit=6, fast_render=True, steps=steps, eval_every=2,
                  eval_episodes=1, log_every=1, checkpoint_every=2, penalty_scale=2.5, logdir=str(logdir))
    values.update(extra)
    return tiny_config(**values)


def test_offline_run_writes_eval_and_a_resumed_run_continues_exactly(export_dir, tiny_config, tmp_path, two_episodes,
                                                                     minari_dataset, random_episodes):
    whole = train_offline(offline_config(tiny_config, tmp_path / "whole", 4), export_dir, progress=False)
    assert set(whole) >= {"return", "normalised_return", "success_rate"}
    train_offline(offline_config(tiny_config, tmp_path / "halves", 2), export_dir, progress=False)
    assert torch.load(tmp_path / "halves" / CHECKPOINT, weights_only=True)["counters"]["updates"] == 2
    for kind in ("train", "eval"):  # as if the run had gone on to update 3 and been killed before its checkpoint
        with (tmp_path / "halves" / f"{kind}.csv").open("a") as f:
            f.write("3" + "," * (len(rows(tmp_path / "halves" / f"{kind}.csv")[0]) - 1) + "\n")
    assert train_offline(offline_config(tiny_config, tmp_path / "halves", 4), export_dir, progress=False) == whole

    first = torch.load(tmp_path / "whole" / CHECKPOINT, weights_only=True)
    second = torch.load(tmp_path / "halves" / CHECKPOINT, weights_only=True)
    assert first["counters"] == second["counters"] and first["counters"]["updates"] == 4
    assert all(torch.equal(value, second["agent"][key]) for key, value in first["agent"].items())
    assert rows(tmp_path / "whole" / "eval.csv") == rows(tmp_path / "halves" / "eval.csv")
    assert [int(r["update"]) for r in rows(tmp_path / "whole" / "eval.csv")] == [2, 4]
    train = rows(tmp_path / "whole" / "train.csv")
    assert len(train) == 4
    assert [row["update"] for row in rows(tmp_path / "halves" / "train.csv")] == ["1", "2", "3", "4"]  # 3 once
    for key in ("penalty_u_dataset", "penalty_u_imagined", "frozen_disagreement_dataset",
                "frozen_disagreement_imagined", "imagined_model_reward"):
        assert np.isfinite(float(train[-1][key])), key

    cfg, agent, counters = load_trained(tmp_path / "whole", export_dir, action_dim=4)  # what benches evaluate
    assert isinstance(agent, OfflineAgent) and not agent.training and counters == first["counters"]
    assert cfg.penalty_scale == 2.5  # the run's own, not the default 5
    assert all(torch.equal(value, agent.trainable_state_dict()[key]) for key, value in first["agent"].items())
    with pytest.raises(FinetuneError, match="holds no config.yaml"):
        load_trained(tmp_path / "nothing", export_dir, action_dim=4)

    # best.pt holds the agent of the evaluation of highest mean return, the same whether the run was resumed
    returns = {int(row["update"]): float(row["return"]) for row in rows(tmp_path / "whole" / "eval.csv")}
    best_at = max(returns, key=returns.get)
    _, best, counters = load_trained(tmp_path / "whole", export_dir, action_dim=4, checkpoint=BEST)
    assert counters["updates"] == counters["best_at"] == best_at and counters["best_return"] == returns[best_at]
    halves = torch.load(tmp_path / "halves" / BEST, weights_only=True)
    assert halves["counters"] == counters and first["counters"]["best_at"] == best_at
    assert all(torch.equal(value, best.trainable_state_dict()[key]) for key, value in halves["agent"].items())

    minari_dataset("test/other-v0", random_episodes(2, 12, 4, seed=5), "metaworld_drawer_close")
    with pytest.raises(FinetuneError, match="dataset='test/two-episodes-v0'"):  # a run directory of another dataset
        train_offline(offline_config(tiny_config, tmp_path / "whole", 6, dataset="test/other-v0"), export_dir,
                      progress=False)
    shutil.rmtree(dataset_path(two_episodes))  # the same ID collected again: other episodes
    minari_dataset(two_episodes, random_episodes(2, 12, 4, seed=7), "metaworld_drawer_close")
    with pytest.raises(FinetuneError, match="another version of --dataset test/two-episodes-v0"):
        train_offline(offline_config(tiny_config, tmp_path / "whole", 6), export_dir, progress=False)
    assert torch.load(tmp_path / "whole" / CHECKPOINT, weights_only=True)["counters"] == first["counters"]


def test_a_runs_fingerprint_names_its_export_and_the_dataset_it_learns_from(export_dir, tiny_config, tmp_path,
                                                                           two_episodes):
    offline = run_fingerprint(offline_config(tiny_config, tmp_path, 2), export_dir)
    assert offline["export_sha256"] == export_fingerprint(export_dir) and len(offline["dataset_sha256"]) == 64
    imitation = tiny_config(paradigm="imitation", task="metaworld_drawer_close", demos=two_episodes)
    assert run_fingerprint(imitation, None) == offline | {"export_sha256": ""}  # a scratch agent: no export
    assert run_fingerprint(tiny_config(), export_dir) == {"export_sha256": export_fingerprint(export_dir)}


def test_bad_offline_settings_are_refused_with_clear_errors(export_dir, tiny_config, tmp_path, two_episodes,
                                                            minari_dataset, random_episodes, monkeypatch):
    with pytest.raises(ConfigError, match="model_heads >= 2"):
        offline_config(tiny_config, tmp_path, 2, model_heads=1)
    with pytest.raises(ConfigError, match="penalty must be one of"):
        offline_config(tiny_config, tmp_path, 2, penalty="variance")
    with pytest.raises(ConfigError, match="scratch agent has none"):
        offline_config(tiny_config, tmp_path, 2, agent="scratch", penalty_frozen_weight=1.0)
    with pytest.raises(FinetuneError, match="--dataset ID is needed"):
        train_offline(offline_config(tiny_config, tmp_path / "a", 2, dataset=None), export_dir, progress=False)
    with pytest.raises(FinetuneError, match="--dataset test/nope-v0: .*not found under MINARI_DATASETS_PATH"):
        train_offline(offline_config(tiny_config, tmp_path / "b", 2, dataset="test/nope-v0"), export_dir, progress=False)
    minari_dataset("test/repeat2-v0", random_episodes(2, 12, 4), "metaworld_drawer_close", action_repeat=2)
    with pytest.raises(FinetuneError, match="collected with action_repeat=2, this run has action_repeat=1"):
        train_offline(offline_config(tiny_config, tmp_path / "r", 2, dataset="test/repeat2-v0"), export_dir,
                      progress=False)
    # another task's, whose settings differ too: the task is named, not a setting that would lead to the next error
    minari_dataset("test/cheetah-v0", random_episodes(2, 12, 6), "dmc_cheetah_run", action_repeat=2)
    with pytest.raises(FinetuneError, match="--dataset test/cheetah-v0 was collected on dmc_cheetah_run, not on this "
                                            "run's task metaworld_drawer_close"):
        train_offline(offline_config(tiny_config, tmp_path / "t", 2, dataset="test/cheetah-v0"), export_dir,
                      progress=False)
    with pytest.raises(FinetuneError, match=r"no episode holds seq_len = 20 frames \(one of 19 steps or more\)"):
        train_offline(offline_config(tiny_config, tmp_path / "c", 2, seq_len=20), export_dir, progress=False)
    # a dataset larger than the replay: the run trained on its newest episodes only, without a word
    with pytest.raises(FinetuneError, match="--dataset test/two-episodes-v0 holds 24 steps, more than replay_capacity "
                                            "20: the run would train on its newest 20 only; --set replay_capacity=24"):
        train_offline(offline_config(tiny_config, tmp_path / "d", 2, replay_capacity=20), export_dir, progress=False)
    # a dataset larger than the memory: its loading was killed by the kernel (exit 137)
    monkeypatch.setattr("hauwm.memory.memory_available", lambda: 2**17)
    with pytest.raises(FinetuneError, match=r"--dataset test/two-episodes-v0: this run needs at least 0.3 MiB of memory "
                                            r"\(its 24 steps 0.3 MiB\), more than the 0.1 MiB available: use a smaller"):
        train_offline(offline_config(tiny_config, tmp_path / "e", 2), export_dir, progress=False)


def posterior_starts(agent):
    """The posterior states [2, 4, ·] of two random sequences of 4 frames and 2-dim actions, to imagine from (no
    gradient reaches them, as none reaches an agent's imagination starts)."""
    generator = np.random.default_rng(0)
    with torch.no_grad():
        return agent.world_model.observe(torch.as_tensor(generator.integers(0, 256, (2, 4, 3, 64, 64), dtype=np.uint8)),
                                         torch.as_tensor(generator.uniform(-1, 1, (2, 4, 2)).astype(np.float32)))[0]


def test_the_rollout_given_to_the_penalty_holds_the_sampled_states_and_the_heads_that_drew_them(export_dir,
                                                                                                   tiny_config):
    """u is computed on what `imagine` hands the reward function: each step's sampled s̃_{t+1} (the one the features
    and the next step use) and the M prior heads of the step from s̃_t with a_t. The formula's own test builds that
    rollout itself, so the heads' mean handed on in place of the sample went unnoticed."""
    from finetune.offline import OfflineAgent
    from finetune.train import build_agent
    from model.rssm import RSSMState

    cfg = tiny_config(paradigm="offline", model_heads=3, horizon=3)
    agent = build_agent(cfg, 2, export_dir, torch.device("cpu"), OfflineAgent)
    start = posterior_starts(agent)
    with torch.no_grad():
        handed = []

        def recording(rollout):  # a reward function that keeps what it is given
            handed.append(rollout)
            return rollout.new_feats.new_zeros(rollout.new_feats.shape[:2])

        agent.world_model.imagine(start, agent.behavior.actor, 3, recording)
        rollout, rssm = handed[0], agent.world_model.rssm
        state = RSSMState(start.new.deter.flatten(0, 1), start.new.stoch.flatten(0, 1))  # N = B · L starts
        for t in range(3):
            deter, mean, std = rssm.img_step(state, rollout.actions[t])
            torch.testing.assert_close(rollout.prior_mean[t], mean)
            torch.testing.assert_close(rollout.prior_std[t], std)
            torch.testing.assert_close(rollout.new_feats[t], rssm.feature(RSSMState(deter, rollout.new_stoch[t])))
            torch.testing.assert_close(rollout.feats[t + 1][:, -rssm.feature_dim:], rollout.new_feats[t])
            state = RSSMState(deter, rollout.new_stoch[t])
    assert rollout.prior_mean.shape[1] == 3 and not torch.allclose(rollout.new_stoch, rollout.prior_mean.mean(1))


def test_the_frozen_disagreement_term_gives_the_actor_no_gradient(export_dir, tiny_config):
    """The frozen stream imagines without the actions: adding its disagreement to u changes the rewards but
    not their gradient with respect to the actor (dynamics backprop)."""
    from finetune.offline import OfflineAgent
    from finetune.train import build_agent

    cfg = tiny_config(paradigm="offline", model_heads=3, horizon=3, penalty_frozen_weight=10.0)
    agent = build_agent(cfg, 2, export_dir, torch.device("cpu"), OfflineAgent)
    start = posterior_starts(agent)
    results = []
    for weight in (0.0, 10.0):
        agent.penalty.frozen_weight = weight
        torch.manual_seed(1)
        rewards = agent.world_model.imagine(start, agent.behavior.actor, 3, agent.penalty)[1]
        grads = torch.autograd.grad(rewards.sum(), list(agent.behavior.actor.parameters()))
        results.append((rewards.detach(), grads))
    (rewards_without, grads_without), (rewards_with, grads_with) = results
    assert (rewards_with < rewards_without - 1e-6).all()  # the term is there
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(grads_without, grads_with))


def test_the_penalty_measured_on_the_dataset_steps_each_posterior_state_with_its_own_recorded_action(tiny_config):
    """penalty_u_dataset: u of one step of every head from s̃_t with a_t, which the replay holds at entry t + 1."""
    cfg = tiny_config(paradigm="offline", agent="scratch", model_heads=3, penalty="mean_disagreement")
    agent = OfflineAgent(cfg, 2)
    generator = np.random.default_rng(0)
    obs = torch.as_tensor(generator.integers(0, 256, (2, 4, 3, 64, 64), dtype=np.uint8))
    actions = torch.as_tensor(generator.uniform(-1, 1, (2, 4, 2)).astype(np.float32))
    with torch.no_grad():
        start, _ = agent.world_model.observe(obs, actions)
        agent.penalty.measure_dataset(start, actions)
        states = type(start.new)(start.new.deter[:, :-1].flatten(0, 1), start.new.stoch[:, :-1].flatten(0, 1))

        def u_with(step_actions):
            _, mean, std = agent.world_model.rssm.img_step(states, step_actions.flatten(0, 1))
            return uncertainty("mean_disagreement", mean, std, mean[0]).mean()

        expected, misaligned = u_with(actions[:, 1:]), u_with(actions[:, :-1])
    torch.testing.assert_close(agent.penalty.metrics["penalty_u_dataset"], expected)
    assert not torch.isclose(expected, misaligned)  # the test could tell the two alignments apart


def test_the_mean_rule_draws_around_the_mean_of_the_heads_means_with_the_mean_of_their_stds(tiny_config, monkeypatch):
    from finetune.world_model import DualStreamWorldModel

    world_model = DualStreamWorldModel(tiny_config(agent="scratch", model_heads=2, imagine_heads="mean", deter=8, stoch=3),
                                       2, None, None)
    monkeypatch.setattr(torch, "randn_like", torch.ones_like)  # a draw one std above the mean
    mean = torch.tensor([0.0, 2.0])[:, None, None].expand(2, 5, 3)
    std = torch.tensor([1.0, 3.0])[:, None, None].expand(2, 5, 3)
    assert torch.allclose(world_model.next_stoch(mean, std), torch.full((5, 3), 1.0 + 2.0))  # μ̄ = 1, σ̄ = 2


@pytest.mark.parametrize("rule", ["random", "mean"])
def test_imagination_draws_the_next_latent_from_one_head_per_trajectory_or_from_their_mean(tiny_config, rule):
    from finetune.world_model import DualStreamWorldModel

    world_model = DualStreamWorldModel(tiny_config(agent="scratch", model_heads=4, imagine_heads=rule, deter=8, stoch=3), 2,
                             None, None)
    mean = torch.arange(4.0)[:, None, None].expand(4, 50, 3).clone()  # head i predicts i everywhere
    sample = world_model.next_stoch(mean, torch.full_like(mean, 1e-6))  # [50, 3]
    if rule == "mean":
        assert torch.allclose(sample, torch.full_like(sample, 1.5), atol=1e-4)
    else:
        heads = sample[:, 0].round()
        assert torch.allclose(sample, heads[:, None].expand_as(sample), atol=1e-4)  # one head per trajectory
        assert len(heads.unique()) > 1  # and not the same head for all


def test_a_loss_that_is_not_finite_stops_the_run_and_names_it(export_dir, tiny_config, tmp_path, minari_dataset,
                                                               random_episodes):
    """Rewards of 1e38 are finite, so the dataset was read; their squared error is not, every update's loss was inf
    and clipped to nothing, and the run ended with status 0 having learned nothing."""
    from finetune.agent import DivergedError

    episodes = random_episodes(2, 12, 4)
    for episode in episodes:
        episode["reward"][1:] = 1e38
    minari_dataset("test/huge-rewards-v0", episodes, "metaworld_drawer_close")
    cfg = offline_config(tiny_config, tmp_path / "huge", 4, dataset="test/huge-rewards-v0")
    with pytest.raises(DivergedError, match=r"model_loss inf, reward_nll inf.* in updates 1\.\.1: the agent's training "
                                            r"has diverged.* Rewards too large"):
        train_offline(cfg, export_dir, progress=False)


def test_an_offline_run_stopped_before_its_first_checkpoint_is_refused_without_a_replay_it_lacks(
        export_dir, tiny_config, tmp_path, two_episodes):
    """The refusal of other settings in its --logdir said that its replay episodes would train the new run: an
    offline run keeps no replay."""
    cfg = offline_config(tiny_config, tmp_path / "run", 2)
    train_offline(cfg, export_dir, progress=False)
    for name in (CHECKPOINT, BEST):  # as a run stopped before its first checkpoint leaves its directory
        (tmp_path / "run" / name).unlink(missing_ok=True)
    with pytest.raises(FinetuneError, match=r"holds a run with penalty_scale=2\.5 \(asked: 1\.0\) that stopped before "
                                            r"its first checkpoint; this one would replace its config.yaml and logs: "
                                            r"train in another --logdir"):
        train_offline(offline_config(tiny_config, tmp_path / "run", 2, penalty_scale=1.0), export_dir, progress=False)


def test_episodes_shorter_than_a_window_are_named_as_never_sampled(tiny_config, minari_dataset, random_episodes,
                                                                    capsys):
    """A medexp merged from 12-step and 5-step episodes trained on the long ones only, without a word (seq_len 8)."""
    from finetune.train import dataset_replay

    episodes = random_episodes(2, 12, 4) + random_episodes(3, 5, 4, seed=1)
    minari_dataset("test/mixed-lengths-v0", episodes, "metaworld_drawer_close")
    cfg = offline_config(tiny_config, "unused", 2, dataset="test/mixed-lengths-v0")
    replay = dataset_replay(cfg.dataset, cfg, 4, "--dataset", np.random.default_rng(0))
    assert ("note: 3 of the 5 episodes of --dataset test/mixed-lengths-v0 (15 of its 39 steps) are shorter than a "
            "window of seq_len = 8 frames and are never sampled; lower seq_len") in capsys.readouterr().err
    assert {len(window) for window in replay.sample(16, 8)["reward"]} == {8}
    dataset_replay(cfg.dataset, dataclasses.replace(cfg, seq_len=6), 4, "--dataset", np.random.default_rng(0))
    assert "never sampled" not in capsys.readouterr().err  # 6 frames: every episode holds a window
