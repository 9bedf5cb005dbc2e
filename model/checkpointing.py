"""How a fit writes its last.ckpt: whole, and at the step where it stops.

`AtomicCheckpointIO` writes a checkpoint to a temporary file beside it, flushed to disk, and renames it over the
old one, so a kill at any moment leaves the old checkpoint or the new one, whole. Lightning's own writer stages
a local checkpoint in $TMPDIR; where that is another filesystem than the run's (node-local /tmp, checkpoints on
shared storage: the usual cluster), its rename becomes a copy that truncates the old last.ckpt first, and a kill
during the copy (the OOM killer, SLURM after its grace period) leaves a truncated checkpoint and none before it.

`LastStepCheckpoint` writes last.ckpt at the step a fit stops at, inside its epoch: at `trainer.max_steps`, when
something asked the fit to stop (`trainer.max_time`'s Timer, an early stop), and on SIGTERM (what SLURM and
Kubernetes send at preemption or a time limit; Lightning ends the fit after the current batch and writes nothing),
at the end of the batch the ranks agreed to stop after (model/sigterm.py). Lightning 2.6's ModelCheckpoint, when no
checkpoint was written yet, writes last.ckpt in `on_train_end`, after the fit loop has counted the cut-short epoch
as completed: a resume would then start the next epoch, the rest of the stopped epoch's batches never trained, the
data (SetEpoch) moved on. Written at the end of the last batch instead, the checkpoint holds the position inside
the epoch, as every `every_n_train_steps` checkpoint does, and the resume continues the data stream exactly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO
from lightning.pytorch.utilities.exceptions import SIGTERMException

from hauwm.atomic import written_whole


class AtomicCheckpointIO(TorchCheckpointIO):
    def save_checkpoint(self, checkpoint: dict[str, Any], path: str | Path, storage_options: Any | None = None) -> None:
        if "://" in str(path) or storage_options is not None:  # an object store: Lightning's writer
            return super().save_checkpoint(checkpoint, path, storage_options)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            with written_whole(path) as partial, open(partial, "wb") as file:  # Ctrl-C, a full disk: the old one stays
                torch.save(checkpoint, file)
        except RuntimeError as error:  # torch's zip writer reports a failed write (a full disk) as a RuntimeError
            if not isinstance(error.__context__, OSError):
                raise
            failed = error.__context__
            raise OSError(failed.errno, failed.strerror, str(path)) from None


class LastStepCheckpoint(Callback):
    """Put after `AgreedSigterm` among the callbacks: it reads the stop that callback agrees on at a batch's end."""

    def on_train_batch_end(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        # SIGTERM too: Lightning raises after this batch, but after an epoch's last batch only once it has counted the
        # epoch completed, and a checkpoint written then skips the next epoch when resumed
        if trainer.should_stop or trainer.received_sigterm or 0 <= trainer.max_steps <= trainer.global_step:
            # at a step of its every_n_train_steps ModelCheckpoint writes last.ckpt itself at this batch's end (it runs
            # before this callback: `before_fit` appends ours to the sorted list), so one write either way
            save_last(trainer, unless_due=True)

    def on_exception(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule,
                     exception: BaseException) -> None:
        # a SIGTERM that no batch end saw (AgreedSigterm not among the callbacks): raised after a training batch's
        # callbacks (or at an epoch's end), so the state is a whole step's; during validation the fit is between a
        # step and its checkpoint, which the last periodic one stands for
        if isinstance(exception, SIGTERMException) and not trainer.validating and not trainer.sanity_checking:
            save_last(trainer, unless_due=False)


def save_last(trainer: lightning.Trainer, unless_due: bool) -> None:
    """Write last.ckpt through each save-last ModelCheckpoint that has not written this step's (`unless_due`: and
    does not write at this batch's end), unless it writes nothing now (`--trainer.fast_dev_run`, whose last.ckpt a
    real fit in the same directory then resumed from); its protected methods are the ones it uses itself."""
    for callback in trainer.checkpoint_callbacks:
        if not (isinstance(callback, ModelCheckpoint) and callback.save_last):
            continue
        every = callback._every_n_train_steps
        due = unless_due and every > 0 and trainer.global_step % every == 0
        if not due and not callback._should_skip_saving_checkpoint(trainer):
            callback._save_last_checkpoint(trainer, callback._monitor_candidates(trainer))
