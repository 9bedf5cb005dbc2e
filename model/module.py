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

The training step has no host synchronisation of its own. A step whose gradient norm is not finite is skipped
on the device — both Adams are fused and take a `found_inf` flag (as GradScaler hands it to them), so neither
the weights, nor log λ, nor any Adam moment or step count moves — and counted in two device counters:
train/scaler_skips (16-mixed: GradScaler's overflow at its current scale with a finite loss, by design while it
calibrates) and train/nonfinite_steps (a non-finite loss, or non-finite gradients without a scaler). The
posterior noise is drawn outside the model from one re-seeded generator; `compile` compiles observe + losses.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import lightning as L
import torch
import torch.distributed as dist
from lightning.pytorch.utilities import rank_zero_info
from torch import nn

from model.compiling import CompileSetting, compile_mode
from model.config import ConfigError, WorldModelConfig, saved_settings
from model.evaluation import horizon_metrics, horizon_sums
from model.losses import balanced_kl, disagreement, hcu_loss, mean_over_jumps, reconstruction_nll
from model.networks import preprocess
from model.rssm import Observation, RSSMState
from model.world_model import WorldModel


def check_settings(world_model: WorldModelConfig, k_max: int, lambda_init: float, kl_balance: float,
                   hcu_target: float, lr: float, lambda_lr: float, grad_clip: float, kl_scale: float,
                   noise_seed: int) -> None:
    """Raise ConfigError naming the first setting out of its range, before anything is built."""
    world_model.validate()
    for name, value in (("lambda_init", lambda_init), ("kl_balance", kl_balance), ("hcu_target", hcu_target),
                        ("lr", lr), ("lambda_lr", lambda_lr), ("grad_clip", grad_clip), ("kl_scale", kl_scale)):
        if not math.isfinite(value):  # 1e999 reads as inf, and .nan passed every range check below
            raise ConfigError(f"model.{name} must be a finite number, got {value}")
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
    for name, value in (("hcu_target", hcu_target), ("lr", lr), ("grad_clip", grad_clip)):
        if not value > 0:
            raise ConfigError(f"model.{name} must be positive, got {value}")
    for name, value in (("lambda_lr", lambda_lr), ("kl_scale", kl_scale), ("noise_seed", noise_seed)):
        if not value >= 0:  # noise_seed: −1 and −2 would draw the same noise (Python's hash(−1) is −2)
            raise ConfigError(f"model.{name} must be ≥ 0, got {value}")


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


def upgrade_checkpoint(checkpoint: dict) -> None:
    """Let a checkpoint written before the fused, synchronisation-free step resume: its one skipped-step counter
    (cause unknown) becomes nonfinite_steps, and its Adam states load into the fused Adams."""
    state = checkpoint.get("state_dict", {})
    if "skipped_steps" in state:
        state["nonfinite_steps"] = state.pop("skipped_steps")
        state["scaler_skips"] = torch.zeros_like(state["nonfinite_steps"])
    for optimizer in checkpoint.get("optimizer_states", []):
        for group in optimizer["param_groups"]:
            group["fused"] = True


def compiled(function: Callable, setting: CompileSetting, device: torch.device) -> Callable:
    """`function` as torch.compile builds it for the `compile` setting on `device` (model/compiling.py; itself
    where that is eager); static shapes (dynamic=False)."""
    mode = compile_mode(setting, device)
    if setting == "reduce-overhead" and mode != setting:
        rank_zero_info(f"model.compile reduce-overhead needs CUDA graphs (a GPU); compiling with mode {mode} on "
                       f"{device}")
    return function if mode is None else torch.compile(function, mode=mode, dynamic=False)


def several_ranks() -> bool:
    """Whether this process is one rank of a DDP job of more than one."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def mean_over_ranks(value: torch.Tensor) -> torch.Tensor:
    """The mean of a tensor over the DDP ranks (itself with one process); an all-reduce without Lightning's barrier."""
    if not several_ranks():
        return value
    total = value.clone()
    dist.all_reduce(total)
    return total / dist.get_world_size()


def step_unless(optimizer: torch.optim.Optimizer, skip: torch.Tensor) -> None:
    """Step a fused Adam unless the device flag `skip` is set: the kernel then leaves weights, moments and the
    step count as they were, with no host synchronisation (the `found_inf` contract GradScaler uses)."""
    optimizer.found_inf = skip.float()
    optimizer.step()
    del optimizer.found_inf


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
        # engineering: how the step runs, not what it computes
        compile: CompileSetting = "off",
    ):
        """The world model trained on eq. 2's ELBO + λ · eq. 3's HCU loss, λ following eq. 4.

        Args:
            world_model: the world model's sizes (model/config.py); they define the export's architecture
            k_max: the largest gap K_max (linked to --data.k_max, which sets it)
            lr: Adam learning rate of the world model (Table 3: 1e-4)
            lambda_init: λ's initial value; 0 turns HCU off (the no-HCU ablation)
            lambda_lr: Adam learning rate of log λ's dual ascent (eq. 4)
            hcu_target: the level of E[k · disagreement] that λ's dual ascent holds the model to
            kl_balance: KL balancing: the share of the KL's gradient that trains the prior heads
            kl_scale: the weight β of the KL term of eq. 2
            grad_clip: the world model's global gradient-norm clip
            noise_seed: seed of the posterior samples' noise (one draw per step and rank: exact resume)
            compile: torch.compile of the step: off, default (inductor), reduce-overhead (inductor + CUDA graphs),
                auto (reduce-overhead on a GPU, off elsewhere)
        """
        super().__init__()
        if isinstance(world_model, Mapping):  # load_from_checkpoint of a module built without the CLI passes the dict
            world_model = WorldModelConfig.from_dict(world_model)
        check_settings(world_model, k_max, lambda_init, kl_balance, hcu_target, lr, lambda_lr, grad_clip, kl_scale,
                       noise_seed)
        self.save_hyperparameters()
        self.save_hyperparameters({"world_model": world_model.to_dict()})  # plain data: weights_only=True loads it
        self.automatic_optimization = False
        self.world_model = WorldModel(world_model)
        self._world_model_params = list(self.world_model.parameters())  # walked once: the module tree is fixed, moves keep them
        start = math.log(lambda_init) if lambda_init > 0 else 0.0
        # not trained by backprop: its gradient is set in closed form (dual_step), so DDP leaves it alone
        self.log_lambda = nn.Parameter(torch.tensor(start), requires_grad=False)
        self.register_buffer("scaler_skips", torch.zeros((), dtype=torch.long))
        self.register_buffer("nonfinite_steps", torch.zeros((), dtype=torch.long))
        self.step_losses: Callable[..., dict[str, torch.Tensor]] = self.training_losses  # compiled in on_fit_start
        self._cuda_graphs = False  # step_losses replays CUDA graphs (set in on_fit_start)
        self._noise_generator: torch.Generator | None = None
        self._val_sums: torch.Tensor | None = None
        self._skip = torch.zeros((), dtype=torch.bool)  # set each step by on_before_optimizer_step
        self._grad_norm = torch.zeros(())

    @property
    def hcu_enabled(self) -> bool:
        return self.hparams.lambda_init > 0

    def hcu_weight(self) -> torch.Tensor:
        """λ (0 when HCU is off), float32 scalar."""
        return self.log_lambda.exp() if self.hcu_enabled else torch.zeros((), device=self.log_lambda.device)

    def configure_optimizers(self):
        # fused: each takes a device-side found_inf flag and skips its update on the device (step_unless)
        world_model = torch.optim.Adam(self.world_model.parameters(), lr=self.hparams.lr, fused=True)
        dual = torch.optim.Adam([self.log_lambda], lr=self.hparams.lambda_lr, fused=True)
        return [world_model, dual]

    def noise(self, gaps: torch.Tensor, step: int, stream: int) -> torch.Tensor:
        """The posterior-sampling noise [B, L, S] of one step (gaps [B, L]), a function of (seed, stream, step,
        rank): resume is exact. One generator, re-seeded each step (host-side: no synchronisation)."""
        if self._noise_generator is None or self._noise_generator.device != self.device:
            self._noise_generator = torch.Generator(device=self.device)
        self._noise_generator.manual_seed(hash((self.hparams.noise_seed, stream, step, self.global_rank)) % 2**63)
        return self.world_model.rssm.draw_noise(*gaps.shape, generator=self._noise_generator, device=self.device)

    def training_losses(
        self, frames: torch.Tensor, gaps: torch.Tensor, num_frames: torch.Tensor, noise: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """Filtering and every loss term of one training batch: the part of the step that `compile` compiles."""
        obs = self.world_model.observe(frames, gaps, num_frames, noise)
        return self.compute_losses({"frames": frames, "gaps": gaps}, obs)

    def compute_losses(self, batch: dict, obs: Observation) -> dict[str, torch.Tensor]:
        """Every loss term of eq. 2–4 from a filtered batch; distribution terms and λ in float32."""
        images = self.world_model.decode(RSSMState(obs.deter, obs.stoch))  # [B, L, 3, 64, 64]
        with torch.autocast(obs.deter.device.type, enabled=False):
            recon_nll = reconstruction_nll(images.float(), preprocess(batch["frames"])).mean()
            kl_balanced, kl = balanced_kl(
                obs.post_mean, obs.post_std, obs.prior_mean, obs.prior_std, self.hparams.kl_balance
            )  # [B, L]
            prediction = recon_nll + self.hparams.kl_scale * kl_balanced.mean()
            hcu = hcu_loss(obs.prior_mean, batch["gaps"])  # eq. 3: −E[k · disagreement]
            weight = self.hcu_weight().detach()
            return {
                "loss": prediction + weight * hcu,  # eq. 4 with λ held fixed (λ takes its own dual step)
                "pred": prediction,
                "recon_nll": recon_nll.detach(),
                "kl": kl.mean(),
                "kl_balanced": kl_balanced.detach().mean(),
                "hcu": hcu.detach(),
                "k_disagreement": -hcu.detach(),  # the constraint of λ's dual step
                "disagreement": mean_over_jumps(disagreement(obs.prior_mean.detach()), batch["gaps"]),
                "prior_std": obs.prior_std.detach().mean(),
                "post_std": obs.post_std.detach().mean(),
                "lambda": weight,
            }

    def dual_step(self, optimizer: torch.optim.Optimizer, k_disagreement: torch.Tensor, skip: torch.Tensor) -> None:
        """One dual-ascent step on log λ: d/dlogλ [λ · (E[k·dis] − target)] = λ · (E[k·dis] − target).

        Skipped on the device when `skip` (the world model's step was skipped) or the constraint is not finite.
        """
        with torch.autocast(self.log_lambda.device.type, enabled=False):
            excess = k_disagreement.float() - self.hparams.hcu_target
            self.log_lambda.grad = (self.log_lambda.exp() * excess).detach().reshape_as(self.log_lambda)
        step_unless(optimizer, skip | ~torch.isfinite(excess))
        optimizer.zero_grad(set_to_none=True)

    def on_fit_start(self) -> None:
        self.step_losses = compiled(self.training_losses, self.hparams.compile, self.device)
        self._cuda_graphs = compile_mode(self.hparams.compile, self.device) == "reduce-overhead"

    def training_step(self, batch: dict, batch_idx: int) -> None:
        world_model_opt, dual_opt = self.optimizers()
        log_now = self.trainer.log_every_n_steps > 0 and (self.global_step + 1) % self.trainer.log_every_n_steps == 0
        noise = self.noise(batch["gaps"], self.global_step, stream=0)
        if self._cuda_graphs:
            torch.compiler.cudagraph_mark_step_begin()  # the last step's graph outputs are no longer read
        terms = self.step_losses(batch["frames"], batch["gaps"], batch["num_frames"], noise)
        world_model_opt.zero_grad()
        self.manual_backward(terms["loss"])
        world_model_opt.step()  # on_before_optimizer_step unscales, clips, and flags a non-finite step (self._skip)
        loss_finite, k_disagreement = torch.isfinite(terms["loss"]), terms["k_disagreement"]
        if several_ranks():  # both over the ranks, in one all-reduce: a NaN loss on one rank makes every rank's step
            #                 a skip, which every rank must count as non-finite, not as the scaler's
            nonfinite, k_disagreement = mean_over_ranks(torch.stack([(~loss_finite).float(), k_disagreement.float()]))
            loss_finite = nonfinite == 0
        self.count_skip(self._skip, loss_finite, scaled=self._grad_scaler() is not None)
        if self.hcu_enabled:
            self.dual_step(dual_opt.optimizer, k_disagreement, self._skip)
        if log_now:  # every trainer.log_every_n_steps: reading the values waits for the GPU
            logged = {f"train/{name}": value.detach().clone() for name, value in terms.items()}
            logged["train/log_lambda"] = self.log_lambda.detach().clone()
            logged["train/grad_norm"] = self._grad_norm
            logged["train/scaler_skips"] = self.scaler_skips.float()
            logged["train/nonfinite_steps"] = self.nonfinite_steps.float()
            self.log_dict(logged, on_step=True, on_epoch=False, batch_size=batch["frames"].shape[0])

    def count_skip(self, skip: torch.Tensor, loss_finite: torch.Tensor, scaled: bool) -> None:
        """Advance the skip counters on the device for a step flagged `skip`: a scaler skip where the loss was finite
        under GradScaler (`scaled`: its float16 overflow at its current scale), a non-finite step otherwise."""
        by_scaler = skip & loss_finite & scaled
        self.scaler_skips += by_scaler
        self.nonfinite_steps += skip & ~by_scaler

    def _grad_scaler(self) -> torch.amp.GradScaler | None:
        """The 16-mixed grad scaler of the Trainer, None under other precisions."""
        return getattr(self.trainer.precision_plugin, "scaler", None)

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """Unscale (16-mixed), clip, and flag on the device a step whose gradient norm is not finite (self._skip)."""
        scaler = self._grad_scaler()
        if scaler is not None:  # fused Adam would unscale inside its step, after the clipping: unscale here instead
            scaler.unscale_(optimizer)
        norm = self.clip_world_model_gradients()
        self._grad_norm = norm.detach()
        self._skip = ~torch.isfinite(norm)  # identical on every rank: gradients are all-reduced
        if scaler is None:  # read by the fused step right after this hook (a scaler hands it its own, equal flag)
            optimizer.found_inf = self._skip.float()

    def clip_world_model_gradients(self) -> torch.Tensor:
        """Clip the world model's gradients to norm grad_clip → their norm before clipping (a device scalar)."""
        return torch.nn.utils.clip_grad_norm_(self._world_model_params, self.hparams.grad_clip, foreach=True)

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """The median frame count of the clips trained on, where a ShardDataModule gives it: the export records it
        for fine-tuning's k = 1 embedding (finetune/pretrained.py)."""
        length = getattr(self.trainer.datamodule, "train_clip_length", None)
        if length is not None:
            checkpoint["train_clip_length"] = length

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        refuse_other_size(checkpoint.get("hyper_parameters", {}), self.world_model.config, "the checkpoint")
        upgrade_checkpoint(checkpoint)

    # validation: open-loop one-jump prediction per gap k (model/evaluation.py)

    def on_validation_epoch_start(self) -> None:
        self._val_sums = torch.zeros(3, self.hparams.k_max, dtype=torch.float64, device=self.device)

    def validation_step(self, batch: dict, batch_idx: int) -> None:  # eager: validation shapes may differ
        sums, obs = horizon_sums(self.world_model, batch, self.hparams.k_max, self.noise(batch["gaps"], batch_idx, stream=1))
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
        self.log_dict(logged, sync_dist=True)  # equal on every rank (summed above); sync_dist keeps Lightning from warning
