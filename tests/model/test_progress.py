"""The progress bar of `hauwm pretrain fit` counts optimizer steps over the whole fit, across short epochs and
from a resumed checkpoint's step, and shows the last logged loss."""

from __future__ import annotations

import lightning
import torch
from lightning.pytorch.loggers import CSVLogger
from torch.utils.data import DataLoader

from model.progress import StepProgressBar

from conftest import fit  # noqa: I001 (tests/model/conftest.py)


class Regression(lightning.LightningModule):
    """Three optimizer steps per epoch, its loss logged every step."""

    def __init__(self) -> None:
        super().__init__()
        self.layer = torch.nn.Linear(2, 1)

    def training_step(self, batch: torch.Tensor, batch_idx: int) -> torch.Tensor:
        loss = self.layer(batch).pow(2).mean()
        self.log("train/loss", loss)
        return loss

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def train_dataloader(self) -> DataLoader:
        return DataLoader(torch.randn(6, 2, generator=torch.Generator().manual_seed(0)), batch_size=2)


def fit_regression(tmp_path, max_steps: int, ckpt_path=None) -> tuple[lightning.Trainer, StepProgressBar]:
    bar = StepProgressBar()
    trainer = lightning.Trainer(max_steps=max_steps, accelerator="cpu", logger=CSVLogger(tmp_path), callbacks=[bar],
                                log_every_n_steps=1, enable_checkpointing=False, enable_model_summary=False)
    trainer.fit(Regression(), ckpt_path=ckpt_path)
    return trainer, bar


def test_the_bar_runs_once_over_every_step_of_short_epochs(tmp_path):
    _, bar = fit_regression(tmp_path, max_steps=10)
    # 3 + 3 + 3 + 1 steps: Lightning's own bar would end at 1 of 1
    assert bar.train_progress_bar.desc.startswith("Epoch 3:")
    assert (bar.train_progress_bar.n, bar.train_progress_bar.total) == (10, 10)
    assert bar.train_progress_bar.unit == "step"
    assert "loss=" in str(bar.train_progress_bar.postfix)


def test_a_resumed_fit_counts_on_from_the_checkpoints_step(tmp_path, capsys):
    first, _ = fit_regression(tmp_path, max_steps=5)
    checkpoint = tmp_path / "five.ckpt"
    first.save_checkpoint(checkpoint)
    capsys.readouterr()
    _, bar = fit_regression(tmp_path, max_steps=10, ckpt_path=checkpoint)
    progress = bar.train_progress_bar
    assert (progress.initial, progress.n, progress.total) == (5, 10, 10)
    shown = capsys.readouterr().out.replace("\r", "\n").splitlines()
    steps_shown = [line for line in shown if "/10 " in line]
    assert steps_shown and not any(" 0/10 " in line for line in steps_shown), steps_shown  # never back to 0


def test_the_cli_shows_steps_of_the_whole_fit(built_shards, tmp_path, capsys):
    assert fit(built_shards, tmp_path, "--trainer.enable_progress_bar", "true", "--trainer.max_steps", "4",
               "--trainer.val_check_interval", "4", "--trainer.log_every_n_steps", "2") == 0
    shown = capsys.readouterr().out.replace("\r", "\n").splitlines()
    assert any("4/4" in line and "step/s" in line and "loss=" in line for line in shown), shown[-5:]
