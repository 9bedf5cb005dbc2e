"""`ResumeNotice`: what `hauwm pretrain fit` says when it is stopped with Ctrl-C, by SIGTERM or by an error.

Lightning ends a fit on Ctrl-C with `sys.exit(1)`, without saving a checkpoint of its own, and says only "Detected
KeyboardInterrupt, attempting graceful shutdown"; on SIGTERM it raises a SystemExit after the current batch
(model/checkpointing.py writes last.ckpt there). This callback closes the progress bar (if there is one) and
prints, on rank 0, the step reached and the checkpoint the fit can resume from; `exit_code` tells the CLI to
raise FitInterrupted instead, which exits with 130 on Ctrl-C, as the other stages do, and 143 on SIGTERM (the
shell's 128 + signal). A fit stopped by an error (a dead loader worker, a full disk) gets the same line before
the error's own: which step, which checkpoint.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import lightning
import torch
from lightning.pytorch.callbacks import Callback, TQDMProgressBar
from lightning.pytorch.utilities.exceptions import SIGTERMException


def saved_step(checkpoint: Path) -> str:
    """The optimizer step a Lightning checkpoint was saved at ("?" if it cannot be read), read without loading its
    tensors (mmap): the steps after it are trained again on resume."""
    try:
        return str(torch.load(checkpoint, map_location="cpu", weights_only=True, mmap=True)["global_step"])
    except Exception:  # the notice must not fail while a run stops; the path is what matters
        return "?"


def fit_checkpoint(trainer: lightning.Trainer) -> Path | None:
    """The newest checkpoint file of the fit: any of its ModelCheckpoints has written (a config may have several), or
    the one it resumed from (which those know only where Lightning restored their state: not for a run moved, or
    resumed with other checkpoint settings)."""
    paths = [path for callback in trainer.checkpoint_callbacks for path in (callback.last_model_path,
                                                                             callback.best_model_path)]
    written = [Path(path) for path in (*paths, trainer.ckpt_path) if path and Path(path).is_file()]
    return max(written, key=lambda path: path.stat().st_mtime, default=None)


class FitInterrupted(Exception):
    """A fit stopped with Ctrl-C or SIGTERM, after ResumeNotice said where it can resume from."""

    def __init__(self, exit_code: int) -> None:
        super().__init__(exit_code)
        self.exit_code = exit_code


class ResumeNotice(Callback):
    def __init__(self) -> None:
        self.exit_code: int | None = None  # 130 after Ctrl-C, 143 after SIGTERM

    def on_exception(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule,
                     exception: BaseException) -> None:
        self.exit_code = 130 if isinstance(exception, KeyboardInterrupt) else \
            143 if isinstance(exception, SIGTERMException) else None
        if not trainer.is_global_zero:
            return
        bar = trainer.progress_bar_callback
        if isinstance(bar, TQDMProgressBar) and bar._train_progress_bar is not None:  # None before training began
            bar._train_progress_bar.close()
        where = "no checkpoint was written yet"
        if (last := fit_checkpoint(trainer)) is not None:
            written = time.strftime("%H:%M:%S", time.localtime(last.stat().st_mtime))
            where = f"resume with --ckpt_path {last} (step {saved_step(last)}, written {written})"
        how = {130: "interrupted", 143: "terminated (SIGTERM)"}.get(self.exit_code, "stopped by the error below")
        print(f"hauwm pretrain fit: {how} at step {trainer.global_step}; {where}", file=sys.stderr)
