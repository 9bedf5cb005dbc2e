"""`ResumeNotice`: what `hauwm pretrain fit` says when it is stopped with Ctrl-C or by an error.

Lightning ends a fit on Ctrl-C with `sys.exit(1)`, without saving a checkpoint of its own, and says only "Detected
KeyboardInterrupt, attempting graceful shutdown". This callback closes the progress bar (if there is one) and
prints, on rank 0, the step reached and the checkpoint the fit can resume from; `interrupted` tells the CLI to
raise FitInterrupted instead, which exits with 130, as the other stages do on Ctrl-C. A fit stopped by an error
(a dead loader worker, a full disk) gets the same line before the error's own: which step, which checkpoint.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import lightning
import torch
from lightning.pytorch.callbacks import Callback, TQDMProgressBar


def saved_step(checkpoint: Path) -> str:
    """The optimizer step a Lightning checkpoint was saved at ("?" if it cannot be read), read without loading its
    tensors (mmap): the steps after it are trained again on resume."""
    try:
        return str(torch.load(checkpoint, map_location="cpu", weights_only=True, mmap=True)["global_step"])
    except Exception:  # the notice must not fail while a run stops; the path is what matters
        return "?"


class FitInterrupted(Exception):
    """A fit stopped with Ctrl-C, after ResumeNotice said where it can resume from."""


class ResumeNotice(Callback):
    def __init__(self) -> None:
        self.interrupted = False

    def on_exception(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule,
                     exception: BaseException) -> None:
        self.interrupted = isinstance(exception, KeyboardInterrupt)
        if not trainer.is_global_zero:
            return
        bar = trainer.progress_bar_callback
        if isinstance(bar, TQDMProgressBar) and bar._train_progress_bar is not None:  # None before training began
            bar._train_progress_bar.close()
        checkpoint = trainer.checkpoint_callback
        last = Path(checkpoint.last_model_path or checkpoint.best_model_path) if checkpoint else Path()
        where = "no checkpoint was written yet"  # Path() is ".", never a file
        if last.is_file():
            written = time.strftime("%H:%M:%S", time.localtime(last.stat().st_mtime))
            where = f"resume with --ckpt_path {last} (step {saved_step(last)}, written {written})"
        how = "interrupted" if self.interrupted else "stopped by the error below"
        print(f"hauwm pretrain fit: {how} at step {trainer.global_step}; {where}", file=sys.stderr)
