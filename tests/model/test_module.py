"""The LightningModule: adaptive λ moves in the documented direction, losses assemble as eq. 4, bad settings
are refused, non-finite steps are skipped and counted."""

from __future__ import annotations

import copy
import dataclasses
import math

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader

from model.module import ConfigError, PretrainModule


def test_lambda_grows_while_the_ensemble_is_too_certain_and_shrinks_once_it_is_not(small_sizes):
    module = PretrainModule(small_sizes, hcu_target=1.0, lambda_init=1.0, lambda_lr=0.05)
    _, dual = module.configure_optimizers()
    values = [module.hcu_weight().item()]
    for _ in range(5):  # k-scaled disagreement 0.1 < target 1.0: λ must grow
        module.dual_step(dual, torch.tensor(0.1))
        values.append(module.hcu_weight().item())
    assert all(b > a for a, b in zip(values, values[1:]))
    for _ in range(40):  # disagreement 5.0 > target: λ must shrink, and stays positive
        module.dual_step(dual, torch.tensor(5.0))
        values.append(module.hcu_weight().item())
    assert values[-1] < values[5] and values[-1] < 1.0 and values[-1] > 0


def test_lambda_starts_at_lambda_init(small_sizes):
    assert math.isclose(PretrainModule(small_sizes, lambda_init=10.0).hcu_weight().item(), 10.0, rel_tol=1e-6)
    assert PretrainModule(small_sizes, lambda_init=0.0).hcu_weight().item() == 0.0


def test_total_loss_is_eq4(small_sizes, fake_batch):
    module = PretrainModule(small_sizes, lambda_init=2.0)
    obs = module.world_model.observe(fake_batch["frames"], fake_batch["gaps"], fake_batch["num_frames"])
    terms = module.compute_losses(fake_batch, obs)
    assert all(torch.isfinite(v) and v.dtype == torch.float32 for v in terms.values())
    assert torch.isclose(terms["loss"], terms["pred"] + 2.0 * terms["hcu"], rtol=1e-5)
    assert torch.isclose(terms["pred"], terms["recon_nll"] + terms["kl_balanced"], rtol=1e-5)
    assert terms["hcu"] < 0 and terms["kl"] > 0


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
    trainer = L.Trainer(max_steps=1, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
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
    def __init__(self):
        self.weights = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.weights.append(copy.deepcopy(pl_module.world_model.state_dict()))


def test_non_finite_steps_are_skipped_and_counted(small_sizes, batch_factory):
    torch.manual_seed(0)
    module = PoisonedStep(small_sizes)
    snapshots = Snapshots()
    trainer = L.Trainer(max_steps=4, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, callbacks=[snapshots])
    batches = [batch_factory(seed=i) for i in range(4)]
    trainer.fit(module, DataLoader(batches, batch_size=None))
    assert trainer.global_step == 4 and module.skipped_steps.item() == 1
    before, after = snapshots.weights[1], snapshots.weights[2]  # the poisoned step is the third
    assert all(torch.equal(before[name], after[name]) for name in before)
    assert all(torch.isfinite(p).all() for p in module.parameters())
    assert not all(torch.equal(snapshots.weights[2][n], snapshots.weights[3][n]) for n in before)  # training went on
