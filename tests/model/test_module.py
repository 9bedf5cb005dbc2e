"""The LightningModule: adaptive λ moves in the documented direction, losses assemble as eq. 4, bad settings
are refused, non-finite steps are skipped and counted."""

from __future__ import annotations

import copy
import dataclasses
import math

import lightning as L
import pytest
import torch
from lightning.pytorch.plugins import MixedPrecision
from torch.utils.data import DataLoader

from model.config import WorldModelConfig
from model.evaluation import horizon_metrics, horizon_sums
from model.losses import disagreement, gaussian_kl, k_scaled_disagreement
from model.config import ConfigError
from model.module import PretrainModule


def quiet_trainer(**settings) -> L.Trainer:
    """A CPU Trainer that writes and prints nothing of its own (no logger, checkpoint, bar or summary)."""
    return L.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                     enable_model_summary=False, **settings)


def test_lambda_grows_while_the_ensemble_is_too_certain_and_shrinks_once_it_is_not(small_sizes):
    module = PretrainModule(small_sizes, hcu_target=1.0, lambda_init=1.0, lambda_lr=0.05)
    _, dual = module.configure_optimizers()
    values = [module.hcu_weight().item()]
    for _ in range(5):  # k-scaled disagreement 0.1 < target 1.0: λ must grow
        module.dual_step(dual, torch.tensor(0.1), skip=torch.tensor(False))
        values.append(module.hcu_weight().item())
    assert all(b > a for a, b in zip(values, values[1:]))
    for _ in range(40):  # disagreement 5.0 > target: λ must shrink, and stays positive
        module.dual_step(dual, torch.tensor(5.0), skip=torch.tensor(False))
        values.append(module.hcu_weight().item())
    assert values[-1] < values[5] and values[-1] < 1.0 and values[-1] > 0


def test_a_skipped_or_non_finite_dual_step_changes_neither_lambda_nor_its_adam(small_sizes):
    module = PretrainModule(small_sizes, lambda_lr=0.05)
    _, dual = module.configure_optimizers()
    module.dual_step(dual, torch.tensor(0.1), skip=torch.tensor(False))
    before = (module.log_lambda.clone(), copy.deepcopy(dual.state_dict()["state"]))
    for constraint, skip in [(float("nan"), False), (float("inf"), False), (0.1, True)]:
        module.dual_step(dual, torch.tensor(constraint), skip=torch.tensor(skip))
        assert torch.equal(module.log_lambda, before[0])
        assert all(torch.equal(dual.state_dict()["state"][0][key], value) for key, value in before[1][0].items())
    module.dual_step(dual, torch.tensor(0.1), skip=torch.tensor(False))
    assert module.log_lambda > before[0] and dual.state_dict()["state"][0]["step"] == 2


def test_lambda_starts_at_lambda_init(small_sizes):
    assert math.isclose(PretrainModule(small_sizes, lambda_init=10.0).hcu_weight().item(), 10.0, rel_tol=1e-6)
    assert PretrainModule(small_sizes, lambda_init=0.0).hcu_weight().item() == 0.0


def test_total_loss_is_eq4(small_sizes, fake_batch):
    module = PretrainModule(small_sizes, lambda_init=2.0, kl_scale=0.5)
    obs = module.world_model.observe(fake_batch["frames"], fake_batch["gaps"], fake_batch["num_frames"])
    terms = module.compute_losses(fake_batch, obs)
    assert all(torch.isfinite(v) and v.dtype == torch.float32 for v in terms.values())
    assert torch.isclose(terms["loss"], terms["pred"] + 2.0 * terms["hcu"], rtol=1e-5)
    assert torch.isclose(terms["pred"], terms["recon_nll"] + 0.5 * terms["kl_balanced"], rtol=1e-5)
    assert torch.isclose(terms["hcu"], -k_scaled_disagreement(obs.prior_mean, fake_batch["gaps"]), rtol=1e-5)
    assert terms["hcu"] < 0 and terms["kl"] > 0


def test_the_logged_disagreement_leaves_out_each_sequences_first_step(small_sizes, fake_batch):
    """train/ and val/disagreement average the frames that have a previous frame, as the HCU loss does: with one gap
    k after every first frame, the logged disagreement is E[k · disagreement] / k."""
    module = PretrainModule(small_sizes)
    batch = {**fake_batch, "gaps": torch.where(fake_batch["gaps"] > 0, 3, 0)}
    assert (batch["gaps"][:, 0] == 0).all() and (batch["gaps"][:, 1:] == 3).all()
    obs = module.world_model.observe(batch["frames"], batch["gaps"], batch["num_frames"])
    terms = module.compute_losses(batch, obs)
    torch.testing.assert_close(terms["disagreement"], terms["k_disagreement"] / 3)
    every_step = disagreement(obs.prior_mean.detach()).mean()
    assert not torch.isclose(every_step, terms["disagreement"])  # the test could tell the first step in or out


def test_the_kl_averages_every_head_against_the_posterior(small_sizes, fake_batch):
    module = PretrainModule(small_sizes, lambda_init=0.0)
    obs = module.world_model.observe(fake_batch["frames"], fake_batch["gaps"], fake_batch["num_frames"])
    terms = module.compute_losses(fake_batch, obs)
    per_head = gaussian_kl(obs.post_mean, obs.post_std, obs.prior_mean, obs.prior_std).mean((1, 2))  # [M]
    torch.testing.assert_close(terms["kl"], per_head.mean())
    assert per_head.std() > 0  # the heads differ, so a KL of one head alone would not pass
    grad = torch.autograd.grad(terms["pred"], module.world_model.rssm.prior_out.weight)[0]  # [M, H, 2S]
    assert all(grad[i].abs().sum() > 0 for i in range(small_sizes.ensemble))  # every head learns from it


def test_the_kl_trains_the_prior_heads_with_kl_balance_and_the_posterior_with_the_rest(small_sizes, fake_batch):
    """eq. 2's KL balancing as the loss wires it: the balanced KL has the plain KL's value whatever the split, so
    only the gradients tell kl_balance from 1 − kl_balance (prior heads 0.8 of the plain KL's, posterior 0.2)."""
    module = PretrainModule(small_sizes, lambda_init=0.0, kl_balance=0.8, kl_scale=0.5)
    obs = module.world_model.observe(fake_batch["frames"], fake_batch["gaps"], fake_batch["num_frames"])
    post_mean, prior_mean = (obs.post_mean.detach().requires_grad_(), obs.prior_mean.detach().requires_grad_())
    loss = module.compute_losses(fake_batch, obs._replace(post_mean=post_mean, prior_mean=prior_mean))["loss"]
    to_posterior, to_priors = torch.autograd.grad(loss, [post_mean, prior_mean])  # only the KL reads these two
    plain = gaussian_kl(post_mean, obs.post_std.detach(), prior_mean, obs.prior_std.detach()).mean()
    plain_to_posterior, plain_to_priors = torch.autograd.grad(plain, [post_mean, prior_mean])
    torch.testing.assert_close(to_priors, 0.5 * 0.8 * plain_to_priors)
    torch.testing.assert_close(to_posterior, 0.5 * 0.2 * plain_to_posterior)


def test_the_posterior_noise_differs_by_step_stream_and_rank_and_repeats_for_each(small_sizes, fake_batch,
                                                                                    monkeypatch):
    """One draw per (seed, stream, step, rank), so that a resume draws what the run would have: noise that did not
    depend on the step (the same draw every step) resumed just as exactly."""
    module = PretrainModule(small_sizes, noise_seed=7)
    gaps = fake_batch["gaps"]
    first = module.noise(gaps, 0, stream=0)
    assert first.shape == (*gaps.shape, small_sizes.stoch)
    torch.testing.assert_close(module.noise(gaps, 0, stream=0), first, rtol=0, atol=0)
    others = [module.noise(gaps, 1, stream=0), module.noise(gaps, 0, stream=1),
              PretrainModule(small_sizes, noise_seed=8).noise(gaps, 0, stream=0)]
    monkeypatch.setattr(PretrainModule, "global_rank", property(lambda self: 1))
    others.append(module.noise(gaps, 0, stream=0))
    assert all(not torch.allclose(other, first) for other in others)


def test_the_hcu_term_trains_the_world_model_with_weight_lambda(small_sizes, fake_batch):
    """The gradient of the loss's HCU part, loss − pred = −λ · E[k · disagreement], reaches the world model's
    weights (eq. 4 minimises it with respect to them; λ alone is held fixed), as −λ times the disagreement's own."""
    module = PretrainModule(small_sizes, lambda_init=2.0)
    obs = module.world_model.observe(fake_batch["frames"], fake_batch["gaps"], fake_batch["num_frames"])
    terms = module.compute_losses(fake_batch, obs)
    weights = [w for w in module.world_model.parameters()]
    hcu_part = torch.autograd.grad(terms["loss"] - terms["pred"], weights, retain_graph=True, allow_unused=True)
    own = torch.autograd.grad(k_scaled_disagreement(obs.prior_mean, fake_batch["gaps"]), weights, allow_unused=True)
    reached = [(g, o) for g, o in zip(hcu_part, own) if o is not None and o.abs().sum() > 0]
    assert reached and all(g is not None and torch.allclose(g, -2.0 * o, rtol=1e-4, atol=1e-8) for g, o in reached)
    assert module.log_lambda.grad is None  # λ moves by its own dual step (eq. 4), not by this loss


def test_the_dual_step_follows_the_k_scaled_disagreement_of_the_batch(small_sizes, batch_factory, monkeypatch):
    """Training feeds λ's step E[k · disagreement] of the step's own batch (eq. 4's constraint), with the closed-form
    gradient λ · (E[k·dis] − target) on log λ."""
    module = PretrainModule(small_sizes, lambda_init=1.5, hcu_target=0.3)
    fed, gradients = [], []
    step = module.dual_step

    def spy(optimizer, k_disagreement, skip):
        fed.append(k_disagreement.item())
        step(optimizer, k_disagreement, skip)

    monkeypatch.setattr(module, "dual_step", spy)
    monkeypatch.setattr(torch.optim.Adam, "step", lambda self, *a, **k: gradients.append(
        [p.grad.clone() for group in self.param_groups for p in group["params"] if p.grad is not None]))
    batch = batch_factory(seed=3)
    trainer = quiet_trainer(max_steps=1)
    trainer.fit(module, DataLoader([batch], batch_size=None))
    noise = module.noise(batch["gaps"], 0, stream=0)
    obs = module.world_model.observe(batch["frames"], batch["gaps"], batch["num_frames"], noise)  # the same step
    expected = k_scaled_disagreement(obs.prior_mean, batch["gaps"]).item()
    assert fed == [pytest.approx(expected, rel=1e-5)]
    assert gradients[-1][0].item() == pytest.approx(1.5 * (expected - 0.3), rel=1e-5)


def test_without_hcu_the_loss_is_the_elbo(small_sizes, fake_batch):
    module = PretrainModule(small_sizes, lambda_init=0.0)
    obs = module.world_model.observe(fake_batch["frames"], fake_batch["gaps"], fake_batch["num_frames"])
    terms = module.compute_losses(fake_batch, obs)
    assert torch.equal(terms["loss"], terms["pred"])


@pytest.mark.parametrize(
    ("sizes", "settings", "message"),
    [
        (dict(ensemble=1), dict(lambda_init=1.0), "HCU needs an ensemble of at least 2 heads"),
        (dict(deter=0), {}, r"world_model.deter must be ≥ 1, got 0"),
        (dict(temporal_dim=7), {}, "world_model.temporal_dim must be even"),
        ({}, dict(k_max=0), "k_max"),
        ({}, dict(lambda_init=-1.0), "lambda_init"),
        ({}, dict(kl_balance=1.5), "kl_balance"),
        ({}, dict(lr=-1.0), "model.lr must be positive, got -1.0"),
        ({}, dict(lambda_lr=-1e-3), "model.lambda_lr must be ≥ 0"),
        ({}, dict(noise_seed=-1), "model.noise_seed must be ≥ 0, got -1"),  # drew seed −2's noise
    ],
)
def test_bad_settings_are_refused(small_sizes, sizes, settings, message):
    with pytest.raises(ConfigError, match=message):
        PretrainModule(dataclasses.replace(small_sizes, **sizes), **settings)


def test_single_head_without_hcu_is_allowed(small_sizes):
    PretrainModule(dataclasses.replace(small_sizes, ensemble=1), lambda_init=0.0)  # the APV-style baseline


def test_a_checkpoint_of_another_size_is_refused(small_sizes):
    module = PretrainModule(small_sizes)
    other = PretrainModule(dataclasses.replace(small_sizes, deter=32))
    with pytest.raises(ConfigError, match=r"different model size \(deter: checkpoint 32 vs this run 24\)"):
        module.on_load_checkpoint({"hyper_parameters": dict(other.hparams)})
    flat = {**other.hparams["world_model"], "lr": other.hparams["lr"]}  # checkpoints before WorldModelConfig
    with pytest.raises(ConfigError, match=r"different model size \(deter: checkpoint 32 vs this run 24\)"):
        module.on_load_checkpoint({"hyper_parameters": flat})


def test_a_checkpoint_keeps_the_sizes_as_plain_data_and_loads_back(small_sizes, batch_factory, tmp_path):
    module = PretrainModule(small_sizes, lr=1e-3)
    trainer = quiet_trainer(max_steps=1)
    trainer.fit(module, DataLoader([batch_factory()], batch_size=None))
    trainer.save_checkpoint(tmp_path / "step1.ckpt")
    saved = torch.load(tmp_path / "step1.ckpt", weights_only=True)["hyper_parameters"]
    assert saved["world_model"] == small_sizes.to_dict() and saved["lr"] == 1e-3
    loaded = PretrainModule.load_from_checkpoint(tmp_path / "step1.ckpt")
    assert loaded.world_model.config == small_sizes and loaded.hparams.lr == 1e-3
    assert all(torch.equal(t, module.state_dict()[name]) for name, t in loaded.state_dict().items())


class PoisonedStep(PretrainModule):
    """Makes the loss of one training step non-finite."""

    poisoned_step = 2

    def compute_losses(self, batch, obs):
        terms = super().compute_losses(batch, obs)
        if self.training and self.global_step == self.poisoned_step:
            terms["loss"] = terms["loss"] * float("nan")
        return terms


class Snapshots(L.Callback):
    """The module's state dict (weights, log λ) and both Adams' states (moments, step counts) at the start and
    after every batch."""

    def __init__(self):
        self.states = []

    def snapshot(self, trainer, pl_module) -> None:
        self.states.append(copy.deepcopy({"weights": pl_module.state_dict(),
                                          "optimizers": [o.state_dict()["state"] for o in trainer.optimizers]}))

    def on_train_start(self, trainer, pl_module):
        self.snapshot(trainer, pl_module)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.snapshot(trainer, pl_module)


def unchanged(before: dict, after: dict) -> bool:
    """Weights, log λ and Adam states equal between two snapshots (the skip counters aside)."""
    weights = all(torch.equal(before["weights"][n], after["weights"][n]) for n in before["weights"]
                  if n not in ("scaler_skips", "nonfinite_steps"))
    moments = all(torch.equal(a[key], b[key]) for old, new in zip(before["optimizers"], after["optimizers"])
                  for a, b in zip(old.values(), new.values()) for key in a)
    return weights and moments


def fit_poisoned(sizes: WorldModelConfig, batches: list[dict], precision: MixedPrecision | None) -> tuple[PoisonedStep, list[int]]:
    """Train on `batches` with step PoisonedStep.poisoned_step poisoned → the module and the steps that changed nothing."""
    torch.manual_seed(0)
    module = PoisonedStep(sizes)
    snapshots = Snapshots()
    trainer = quiet_trainer(max_steps=len(batches), plugins=precision and [precision], callbacks=[snapshots])
    trainer.fit(module, DataLoader(batches, batch_size=None))
    assert trainer.global_step == len(batches)
    states = snapshots.states
    return module, [step for step in range(len(batches)) if unchanged(states[step], states[step + 1])]


def test_gradient_clipping_reaches_every_world_model_weight_after_the_module_moves(small_sizes):
    """The clipped parameters are listed once, when the module is built: a move or cast (Lightning's .to(device))
    must leave that list the world model's own tensors."""
    module = PretrainModule(small_sizes, grad_clip=0.5).double()
    weights = list(module.world_model.parameters())
    for weight in weights:
        weight.grad = torch.ones_like(weight)
    norm = module.clip_world_model_gradients()
    assert norm.item() == pytest.approx(math.sqrt(sum(weight.numel() for weight in weights)))
    clipped = torch.linalg.vector_norm(torch.cat([weight.grad.flatten() for weight in weights]))
    assert clipped.item() == pytest.approx(0.5, rel=1e-4)


def test_a_training_step_clips_the_gradient_adam_steps_with(small_sizes, batch_factory, monkeypatch):
    """grad_clip acts in the fit's own step (on_before_optimizer_step), not only when clip_world_model_gradients is
    called: the world model's Adam steps with gradients of norm grad_clip."""
    norms = []

    def record(self, closure=None):
        if closure is not None:  # Lightning's: it runs on_before_optimizer_step, which clips
            closure()
        if len(self.param_groups[0]["params"]) > 1:  # the world model's Adam, not λ's
            norms.append(torch.linalg.vector_norm(torch.cat([p.grad.flatten() for p in self.param_groups[0]["params"]
                                                             if p.grad is not None])).item())

    monkeypatch.setattr(torch.optim.Adam, "step", record)
    module = PretrainModule(small_sizes, grad_clip=1e-3)
    trainer = quiet_trainer(max_steps=2)
    trainer.fit(module, DataLoader([batch_factory(seed=0), batch_factory(seed=1)], batch_size=None))
    assert norms == [pytest.approx(1e-3, rel=1e-3)] * 2  # the unclipped norm is orders of magnitude larger


def test_validation_logs_each_gaps_error_and_disagreement_summed_over_its_batches(small_sizes, batch_factory):
    """val/open_loop_mse_k{k} and val/disagreement_k{k}: model/evaluation.py's statistics over every validation batch
    (each with its own noise), each under its own name."""
    module = PretrainModule(small_sizes, k_max=5)
    batches = [batch_factory(seed=i) for i in range(2)]
    trainer = quiet_trainer()
    logged = trainer.validate(module, DataLoader(batches, batch_size=None), verbose=False)[0]
    with torch.no_grad():
        sums = sum(horizon_sums(module.world_model, batch, 5, module.noise(batch["gaps"], i, stream=1))[0]
                   for i, batch in enumerate(batches))
    metrics = horizon_metrics(sums)
    assert logged["val/open_loop_mse"] == pytest.approx(metrics["recon_mse_all"], rel=1e-5)
    seen = [(k, mse, spread) for k, count, mse, spread in
            zip(metrics["k"], metrics["count"], metrics["recon_mse"], metrics["disagreement"]) if count]
    assert len(seen) >= 3
    for k, mse, spread in seen:
        assert logged[f"val/open_loop_mse_k{k}"] == pytest.approx(mse, rel=1e-5)
        assert logged[f"val/disagreement_k{k}"] == pytest.approx(spread, rel=1e-5)


def test_non_finite_steps_are_skipped_and_counted(small_sizes, batch_factory):
    module, skipped = fit_poisoned(small_sizes, [batch_factory(seed=i) for i in range(4)], None)
    assert skipped == [PoisonedStep.poisoned_step]  # weights, log λ, Adam moments and step counts stay; training goes on
    assert (module.nonfinite_steps.item(), module.scaler_skips.item()) == (1, 0)
    assert all(torch.isfinite(p).all() for p in module.parameters())


def test_grad_scaler_skips_are_told_from_non_finite_steps(small_sizes, batch_factory):
    """16-mixed (float16 autocast with GradScaler; the plugin is given explicitly, since the Trainer would turn
    16-mixed into bf16-mixed on a CPU): the scaler's first step overflows by design and counts as a scaler skip,
    the poisoned step as non-finite. Both change nothing and halve the scale. (init_scale 256 instead of 65536:
    float16 is slow on a CPU, and from 65536 this model takes 8 halvings to stop overflowing.)"""
    scaler = torch.amp.GradScaler("cpu", init_scale=256.0)
    batches = [batch_factory(batch_size=2, length=3, seed=i) for i in range(4)]
    module, skipped = fit_poisoned(small_sizes, batches, MixedPrecision("16-mixed", "cpu", scaler))
    assert skipped == [0, PoisonedStep.poisoned_step]
    assert (module.scaler_skips.item(), module.nonfinite_steps.item()) == (1, 1)
    assert scaler.get_scale() == 64.0
