"""The λ-return (finetune.behavior.lambda_return) on hand-worked examples, and the actor-critic losses built on it."""

from __future__ import annotations

import functools

import torch

from finetune.behavior import ActorCritic, lambda_return

# one trajectory of H = 3 steps: rewards r_1..r_3 and values v(z_0)..v(z_3)
REWARDS = torch.tensor([[1.0], [2.0], [3.0]])
VALUES = torch.tensor([[10.0], [20.0], [30.0], [40.0]])


def reward_first_action(start, policy, horizon, moves=False):
    """A toy model to imagine in: the reward is the action's first component; z stays put, or moves by the sum of
    the action's components (`moves`)."""
    feats, rewards, entropies = [start], [], []
    for _ in range(horizon):
        dist = policy(feats[-1].detach())
        action = dist.rsample()
        entropies.append(dist.entropy())
        rewards.append(action[:, 0])
        feats.append(feats[-1] + action.sum(-1, keepdim=True) if moves else feats[-1])
    return torch.stack(feats), torch.stack(rewards), torch.stack(entropies)


def test_lambda_zero_is_the_one_step_target():
    # V_t = r_{t+1} + γ v(z_{t+1}), γ = 0.5: 1 + 10, 2 + 15, 3 + 20
    returns = lambda_return(REWARDS, VALUES, gamma=0.5, lam=0.0)
    assert returns.squeeze(-1).tolist() == [11.0, 17.0, 23.0]


def test_lambda_one_is_the_discounted_monte_carlo_return():
    # V_2 = 3 + .5·40 = 23;  V_1 = 2 + .5·23 = 13.5;  V_0 = 1 + .5·13.5 = 7.75
    returns = lambda_return(REWARDS, VALUES, gamma=0.5, lam=1.0)
    assert returns.squeeze(-1).tolist() == [7.75, 13.5, 23.0]
    # the same as Σ_i γ^i r + γ^H v(z_H) written out
    assert returns[0, 0] == 1 + 0.5 * 2 + 0.25 * 3 + 0.125 * 40


def test_lambda_half_mixes_the_two():
    # V_2 = 3 + .5·(.5·40 + .5·40) = 23
    # V_1 = 2 + .5·(.5·30 + .5·23) = 2 + .5·26.5 = 15.25
    # V_0 = 1 + .5·(.5·20 + .5·15.25) = 1 + .5·17.625 = 9.8125
    returns = lambda_return(REWARDS, VALUES, gamma=0.5, lam=0.5)
    assert returns.squeeze(-1).tolist() == [9.8125, 15.25, 23.0]


def test_lambda_return_is_per_column_and_keeps_gradients():
    rewards = torch.randn(15, 7, requires_grad=True)
    values = torch.randn(16, 7)
    returns = lambda_return(rewards, values, gamma=0.99, lam=0.95)
    assert returns.shape == (15, 7)
    assert torch.allclose(returns[:, 3], lambda_return(rewards[:, 3:4], values[:, 3:4], 0.99, 0.95)[:, 0])
    returns.sum().backward()
    assert rewards.grad is not None and (rewards.grad > 0).all()


def test_actor_update_moves_actions_towards_imagined_reward():
    """Dynamics backprop: the reward is a differentiable function of the action, and the actor follows it."""
    torch.manual_seed(0)
    learner = ActorCritic(feat_dim=4, action_dim=2, units=32, horizon=3, actor_lr=1e-2, critic_lr=1e-2)
    start = torch.randn(64, 4)

    mean_action = lambda: learner.actor(start).mode[:, 0].mean().item()  # noqa: E731
    before = mean_action()
    for _ in range(30):
        metrics = learner.step(*learner.losses(reward_first_action, start))
    assert mean_action() > before + 0.2
    assert set(metrics) >= {"actor_loss", "critic_loss", "imagined_return"}


def test_actor_saturation_is_reported():
    """actor_saturated: the share of imagined states whose loc tanh(μ) is within 1e-3 of a bound."""
    torch.manual_seed(0)
    learner = ActorCritic(feat_dim=4, action_dim=1, units=32, horizon=3)
    start = torch.randn(64, 4)

    def imagine(start, policy, horizon):  # toy model: z stays put, no reward
        feats = [start] * (horizon + 1)
        dists = [policy(f) for f in feats[:-1]]
        return torch.stack(feats), torch.zeros(horizon, len(start)), torch.stack([d.entropy() for d in dists])

    assert learner.step(*learner.losses(reward_first_action, start))["actor_saturated"] == 0.0  # at init tanh μ is near 0
    with torch.no_grad():
        learner.actor.net[-1].bias[0] = 20.0  # μ ≈ 20 on every state: tanh' ≈ 1e-17
    assert learner.step(*learner.losses(reward_first_action, start))["actor_saturated"] == 1.0


def test_the_losses_are_the_documented_formulas_and_the_target_follows_the_critic():
    """Actor: −E[γ^t (V^λ_t + η H_t)] with V^λ bootstrapped from the target critic; critic: E[γ^t ½ (v(z_t) −
    sg V^λ_t)²]; after the step the target moves a fraction τ towards the critic."""
    torch.manual_seed(0)
    learner = ActorCritic(feat_dim=4, action_dim=1, units=8, horizon=3, gamma=0.5, lam=0.7, entropy_scale=0.1,
                          target_fraction=0.02)
    with torch.no_grad():
        learner.critic.net[-1].bias += 5.0  # the critic and its target now differ
    feats, rewards, entropies = torch.randn(4, 6, 4), torch.randn(3, 6), []

    def imagine(start, policy, horizon):  # fixed states and rewards; the actor's own entropy there
        entropies.append(policy(feats[:-1]).entropy())
        return feats, rewards, entropies[-1]

    actor_loss, critic_loss, _, _ = learner.losses(imagine, None)
    entropy = entropies[-1].detach()
    returns = lambda_return(rewards, learner.target_critic(feats), 0.5, 0.7)
    weights = torch.tensor([1.0, 0.5, 0.25])[:, None]
    torch.testing.assert_close(actor_loss, -(weights * (returns + 0.1 * entropy)).mean())
    torch.testing.assert_close(critic_loss, (weights * 0.5 * (learner.critic(feats[:-1]) - returns) ** 2).mean())

    target_before = [p.clone() for p in learner.target_critic.parameters()]
    learner.step(actor_loss, critic_loss, feats, {})
    for target, before, online in zip(learner.target_critic.parameters(), target_before, learner.critic.parameters()):
        torch.testing.assert_close(target, torch.lerp(before, online, 0.02))


def test_each_loss_trains_only_its_own_network():
    """The critic regresses on sg(V^λ): its loss gives the actor no gradient (through the returns, which depend on the
    actions), and the actor's loss gives the critic none (it bootstraps from the target critic). The formula test
    above cannot see a missing stop-gradient: its rewards do not depend on the actor."""
    torch.manual_seed(0)
    learner = ActorCritic(feat_dim=4, action_dim=2, units=8, horizon=3)

    moving = functools.partial(reward_first_action, moves=True)  # z moves with the actions
    actor_loss, critic_loss, _, _ = learner.losses(moving, torch.randn(16, 4))
    actor, critic = list(learner.actor.parameters()), list(learner.critic.parameters())
    assert all(grad is None for grad in torch.autograd.grad(critic_loss, actor, retain_graph=True, allow_unused=True))
    assert all(grad is None for grad in torch.autograd.grad(actor_loss, critic, retain_graph=True, allow_unused=True))
    assert all(grad is not None and grad.any() for grad in torch.autograd.grad(critic_loss, critic, retain_graph=True))
    assert any(grad.any() for grad in torch.autograd.grad(actor_loss, actor))
