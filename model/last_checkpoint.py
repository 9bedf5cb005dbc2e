"""`LastStepCheckpoint`: a fit that stops at `trainer.max_steps` writes its last.ckpt at that step, inside the epoch.

Lightning 2.6's ModelCheckpoint, when no checkpoint was written yet, writes last.ckpt in `on_train_end`, after
the fit loop has counted the cut-short epoch as completed. A resume with a larger max_steps then starts the next
epoch: the rest of the stopped epoch's batches are never trained, the data (SetEpoch) moves on, and the losses
differ from an uninterrupted run's. Written at the end of the last batch instead, the checkpoint holds the
position inside the epoch, as every `every_n_train_steps` checkpoint does, and the resume continues the data
stream exactly; `on_train_end` then finds the last checkpoint written and writes none.
"""

from __future__ import annotations

import lightning
from lightning.pytorch.callbacks import Callback, ModelCheckpoint


class LastStepCheckpoint(Callback):
    def on_train_batch_end(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        if trainer.max_steps < 0 or trainer.global_step < trainer.max_steps:
            return
        for callback in trainer.checkpoint_callbacks:
            if not (isinstance(callback, ModelCheckpoint) and callback.save_last):
                continue
            # ModelCheckpoint runs after this callback (Lightning puts it last) and writes last.ckpt itself at its
            # own every_n_train_steps; its protected methods are the ones it uses there
            every = callback._every_n_train_steps
            if not (every > 0 and trainer.global_step % every == 0):
                callback._save_last_checkpoint(trainer, callback._monitor_candidates(trainer))
