"""The pre-training LightningModule (paper section 4.1, eq. 2–4; appendix D.2): the science, not the engineering.

    L_total = L_pred + λ · L_HCU                                                    (eq. 4)
    L_pred  = −ln p(o_t | s_t) + β · KL-balanced(q ‖ p_i), averaged over the M heads   (eq. 2)
    L_HCU   = −k · (1/(M−1)) Σ_i ‖μ_i − μ̄‖²                                          (eq. 3)

Adaptive λ (eq. 4, "dual optimisation") is dual ascent on the constraint

    E[k · disagreement] ≥ hcu_target         (the k-scaled disagreement, i.e. −L_HCU)

with λ = exp(log λ) (always positive), log λ initialised to log λ₀ and updated by its own Adam (3e-4) on the
dual loss λ · (E[k · disagreement] − hcu_target): λ grows while the ensemble is more certain than the target
and shrinks once it is not, so disagreement cannot grow without bound. λ₀ = 0 turns HCU off (the ablation).

Two optimizers, manual optimisation: the world model's Adam steps through Lightning (16-bit grad scaling,
DDP gradient averaging); λ's gradient is computed in closed form in float32 from the all-reduced constraint,
so every rank holds the same λ, and stepped on the raw Adam (it never touches the grad scaler or the step count).
Steps whose gradients are not finite are skipped and counted (train/skipped_steps).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import lightning as L
import torch
from torch import nn

from model.config import ConfigError, WorldModelConfig, saved_settings
from model.evaluation import horizon_metrics, horizon_sums
from model.losses import balanced_kl, disagreement, k_scaled_disagreement, reconstruction_nll
from model.networks import preprocess
from model.rssm import Observation, RSSMState
from model.world_model import WorldModel


def check_settings(
    world_model: WorldModelConfig, k_max: int, lambda_init: float, kl_balance: float, hcu_target: float
) -> None:
    world_model.validate()
    if lambda_init > 0 and world_model.ensemble < 2:
        raise ConfigError(
            "HCU needs an ensemble of at least 2 heads to measure disagreement, but "
            f"model.world_model.ensemble={world_model.ensemble}; raise --model.world_model.ensemble, or set "
            "--model.lambda_init 0 to train without HCU"
        )
    if lambda_init < 0:
        raise ConfigError(f"model.lambda_init must be ≥ 0 (0 turns HCU off), got {lambda_init}")
    if k_max < 1:
        raise ConfigError(f"k_max (the largest frame gap) must be ≥ 1, got {k_max}; set --data.k_max 1 or more")
    if not 0.0 <= kl_balance <= 1.0:
        raise ConfigError(f"model.kl_balance must lie in [0, 1], got {kl_balance}")
    if hcu_target <= 0:
        raise ConfigError(f"model.hcu_target must be positive, got {hcu_target}")


def refuse_other_size(saved: Mapping[str, Any], asked: WorldModelConfig, source: str) -> None:
    """Raise ConfigError if a checkpoint's world-model settings (its hyper_parameters) differ from this run's."""
    asked_settings = asked.to_dict()
    different = [f"{key}: checkpoint {value!r} vs this run {asked_settings.get(key)!r}"
                 for key, value in saved_settings(saved).items() if value != asked_settings.get(key)]
    if different:
        raise ConfigError(
            f"{source} was trained with a different model size ({', '.join(different)}); resume with the "
            "checkpoint's own settings (its config.yaml sits in the run's lightning_logs/version_N/)"
        )


class PretrainModule(L.LightningModule):
    def __init__(
        self,
        # the world model's sizes (model/config.py; they define the export's architecture)
        world_model: WorldModelConfig = WorldModelConfig(),
        # training (Table 3)
        k_max: int = 5,
        lr: float = 1e-4,
        lambda_init: float = 1.0,
        lambda_lr: float = 3e-4,
        hcu_target: float = 1.0,
        kl_balance: float = 0.8,
        kl_scale: float = 1.0,
        grad_clip: float = 100.0,
        noise_seed: int = 0,
    ):
        super().__init__()
        if isinstance(world_model, Mapping):  # load_from_checkpoint of a module built without the CLI passes the dict
            world_model = WorldModelConfig.from_dict(world_model)
        check_settings(world_model, k_max, lambda_init, kl_balance, hcu_target)
        self.save_hyperparameters()
        self.save_hyperparameters({"world_model": world_model.to_dict()})  # plain data: weights_only=True loads it
        self.automatic_optimization = False
        self.world_model = WorldModel(world_model)
        start = math.log(lambda_init) if lambda_init > 0 else 0.0
        # not trained by backprop: its gradient is set in closed form (dual_step), so DDP leaves it alone
        self.log_lambda = nn.Parameter(torch.tensor(start), requires_grad=False)
        self.register_buffer("skipped_steps", torch.zeros((), dtype=torch.long))
        self._val_sums: torch.Tensor | None = None
        self._step_finite = True  # set each step by on_before_optimizer_step, with the gradient norm
        self._grad_norm = torch.zeros(())

    @property
    def hcu_enabled(self) -> bool:
        return self.hparams.lambda_init > 0

    def hcu_weight(self) -> torch.Tensor:
        """λ (0 when HCU is off), float32 scalar."""
        return self.log_lambda.exp() if self.hcu_enabled else torch.zeros((), device=self.log_lambda.device)

    def configure_optimizers(self):
        world_model = torch.optim.Adam(self.world_model.parameters(), lr=self.hparams.lr)
        dual = torch.optim.Adam([self.log_lambda], lr=self.hparams.lambda_lr)
        return [world_model, dual]

    def noise(self, step: int, stream: int) -> torch.Generator:
        """The posterior-sampling noise of one step, a function of (seed, stream, step, rank): resume is exact."""
        generator = torch.Generator(device=self.device)
        generator.manual_seed(hash((self.hparams.noise_seed, stream, step, self.global_rank)) % 2**63)
        return generator

    def compute_losses(self, batch: dict, obs: Observation) -> dict[str, torch.Tensor]:
        """Every loss term of eq. 2–4 from a filtered batch; distribution terms and λ in float32."""
        images = self.world_model.decode(RSSMState(obs.deter, obs.stoch))  # [B, L, 3, 64, 64]
        with torch.autocast(self.device.type, enabled=False):
            recon_nll = reconstruction_nll(images.float(), preprocess(batch["frames"])).mean()
            kl_balanced, kl = balanced_kl(
                obs.post_mean, obs.post_std, obs.prior_mean, obs.prior_std, self.hparams.kl_balance
            )  # [B, L]
            prediction = recon_nll + self.hparams.kl_scale * kl_balanced.mean()
            k_disagreement = k_scaled_disagreement(obs.prior_mean, batch["gaps"])  # = −L_HCU
            weight = self.hcu_weight().detach()
            return {
                "loss": prediction - weight * k_disagreement,
                "pred": prediction,
                "recon_nll": recon_nll.detach(),
                "kl": kl.mean(),
                "kl_balanced": kl_balanced.detach().mean(),
                "hcu": -k_disagreement.detach(),
                "k_disagreement": k_disagreement.detach(),
                "disagreement": disagreement(obs.prior_mean.detach()).mean(),
                "prior_std": obs.prior_std.detach().mean(),
                "post_std": obs.post_std.detach().mean(),
                "lambda": weight,
            }

    def dual_step(self, optimizer: torch.optim.Optimizer, k_disagreement: torch.Tensor) -> None:
        """One dual-ascent step on log λ: d/dlogλ [λ · (E[k·dis] − target)] = λ · (E[k·dis] − target)."""
        with torch.autocast(self.device.type, enabled=False):
            excess = k_disagreement.float() - self.hparams.hcu_target
            self.log_lambda.grad = (self.log_lambda.exp() * excess).detach().reshape_as(self.log_lambda)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

    def training_step(self, batch: dict, batch_idx: int) -> None:
        world_model_opt, dual_opt = self.optimizers()
        obs = self.world_model.observe(
            batch["frames"], batch["gaps"], batch["num_frames"], self.noise(self.global_step, stream=0)
        )
        terms = self.compute_losses(batch, obs)
        world_model_opt.zero_grad()
        self.manual_backward(terms["loss"])
        world_model_opt.step()  # on_before_optimizer_step clips, or counts and skips a non-finite step
        if self.hcu_enabled and self._step_finite:
            constraint = self.trainer.strategy.reduce(terms["k_disagreement"], reduce_op="mean")
            if torch.isfinite(constraint):
                self.dual_step(dual_opt.optimizer, constraint)
        logged = {f"train/{name}": value.detach() for name, value in terms.items()}
        logged["train/log_lambda"] = self.log_lambda.detach()
        logged["train/skipped_steps"] = self.skipped_steps.float()
        logged["train/grad_norm"] = self._grad_norm
        self.log_dict(logged, on_step=True, on_epoch=False, batch_size=batch["frames"].shape[0])

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """Gradients are unscaled here (also under 16-mixed): clip them, or count and skip a non-finite step."""
        norm = torch.nn.utils.clip_grad_norm_(self.world_model.parameters(), self.hparams.grad_clip)
        self._grad_norm = norm.detach()
        self._step_finite = bool(torch.isfinite(norm))  # identical on every rank: gradients are all-reduced
        if not self._step_finite:
            self.skipped_steps += 1
            if getattr(self.trainer.precision_plugin, "scaler", None) is None:
                optimizer.zero_grad(set_to_none=True)  # Adam leaves weights and moments as they are
            # under 16-mixed the grad scaler skips the step itself and lowers its scale

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        refuse_other_size(checkpoint.get("hyper_parameters", {}), self.world_model.config, "the checkpoint")

    # validation: open-loop one-jump prediction per gap k (model/evaluation.py)

    def on_validation_epoch_start(self) -> None:
        self._val_sums = torch.zeros(3, self.hparams.k_max, dtype=torch.float64, device=self.device)

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        sums, obs = horizon_sums(self.world_model, batch, self.hparams.k_max, self.noise(batch_idx, stream=1))
        self._val_sums += sums
        terms = self.compute_losses(batch, obs)
        keep = ("loss", "recon_nll", "kl", "hcu", "disagreement")
        size = batch["frames"].shape[0]
        self.log_dict({f"val/{name}": terms[name] for name in keep}, on_epoch=True, sync_dist=True, batch_size=size)

    def on_validation_epoch_end(self) -> None:
        metrics = horizon_metrics(self.trainer.strategy.reduce(self._val_sums, reduce_op="sum"))
        logged = {"val/open_loop_mse": metrics["recon_mse_all"]}
        for k, count, mse, spread in zip(metrics["k"], metrics["count"], metrics["recon_mse"], metrics["disagreement"]):
            if count:
                logged[f"val/open_loop_mse_k{k}"] = mse
                logged[f"val/disagreement_k{k}"] = spread
        if not math.isnan(metrics["spearman_k_disagreement"]):
            logged["val/spearman_k_disagreement"] = metrics["spearman_k_disagreement"]
        self.log_dict(logged)
