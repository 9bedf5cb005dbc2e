"""`StepProgressBar`: the progress of `hauwm pretrain fit` in optimizer steps over the whole fit.

Pre-training is budgeted in steps (600k in the paper's Table 3), while Lightning's default bar counts the batches
of one epoch and starts again every epoch: an epoch of SSv2 is ~5,300 steps at batch 32, and one of a small video
set a handful (240 clips: 7), with the epoch count shown as `Epoch 33/-2` when only `max_steps` is set. This bar
runs once from the run's (or the resumed checkpoint's) step to `trainer.max_steps`, so its rate is steps/s and its
time left is the fit's; the description names the current epoch, the postfix the loss of the last logging step.
Validation keeps Lightning's own bar. `hauwm pretrain fit` puts it in place of Lightning's default bar.
"""

from __future__ import annotations

from typing import Any

import lightning
from lightning.pytorch.callbacks import TQDMProgressBar


class StepProgressBar(TQDMProgressBar):
    def __init__(self, refresh_rate: int = 1) -> None:
        super().__init__(refresh_rate)
        self._loss: tuple[object, float] | None = None  # (the logged tensor, its value): read once per logging

    def on_train_start(self, trainer: lightning.Trainer, *_: Any) -> None:
        super().on_train_start(trainer)
        bar = self.train_progress_bar  # just made: its clock starts now
        bar.total = trainer.max_steps if trainer.max_steps > 0 else None
        bar.initial = bar.n = bar.last_print_n = trainer.global_step  # a resumed fit: its rate counts this run's steps
        bar.unit = "step"
        bar.set_description(f"Epoch {trainer.current_epoch}")  # draws it once, at its step (also mid-epoch)

    def on_train_epoch_start(self, trainer: lightning.Trainer, *_: Any) -> None:
        self.train_progress_bar.set_description(f"Epoch {trainer.current_epoch}", refresh=False)

    def on_train_batch_end(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule, *_: Any) -> None:
        bar = self.train_progress_bar
        step = trainer.global_step
        if self.is_enabled and (step % self.refresh_rate == 0 or step == bar.total):
            bar.set_postfix(self.get_metrics(trainer, pl_module), refresh=False)
            bar.update(step - bar.n)  # redraws at most every `bar.mininterval` (0.1 s): at 100+ steps/s, not each step

    def on_train_epoch_end(self, *_: Any) -> None:
        """Nothing: the bar stays open across epochs, and on_train_batch_end keeps its postfix current."""

    def get_metrics(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> dict:
        """Lightning's items plus the training loss of the last logging step (every `log_every_n_steps`): the
        module logs without `prog_bar`, which would read the loss from the GPU at every step."""
        metrics = super().get_metrics(trainer, pl_module)
        logged = trainer.logged_metrics.get("train/loss")
        if logged is not None and (self._loss is None or self._loss[0] is not logged):
            self._loss = (logged, float(logged))  # a new logging step's tensor: the only read of the GPU
        if self._loss is not None:
            metrics["loss"] = f"{self._loss[1]:.4g}"
        return metrics
