"""`AgreedSigterm`: on SIGTERM, the fit stops after the current step with last.ckpt of that step, on every DDP rank
after the same one, whichever ranks got the signal.

SLURM (`scancel`, a job's time limit, preemption) and Kubernetes send SIGTERM to every process of a job at once.
Lightning 2.6's handler then calls `torch.distributed.broadcast` inside the signal handler, on every rank, at
whatever point each rank is (inside DDP's gradient all-reduce, inside the step's own broadcast of the flag): the
collectives no longer pair up, and the fit hangs without writing a checkpoint (5 of 6 tries with 2 gloo ranks,
docs/pretraining.md). And at a step that validates, in one process as under DDP, Lightning raises inside the
validation, where no checkpoint can be written. From the sanity check on (or the start of training, without one),
this callback stands in for Lightning's handler: the signal only sets a flag (and is passed on to the ranks that
Lightning's launcher started from this process, as Lightning does); after every step the ranks take the maximum
of their flags in one all-reduce of one number (a single process reads its own). When one was signalled, all of
them set Lightning's own `received_sigterm` after that same step, so that Lightning raises its SIGTERMException on
every rank at the end of it, where `LastStepCheckpoint` writes last.ckpt; a step that validates runs its
validation to its end first. Lightning restores the handlers it found when the fit ends.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType

import lightning
import torch
from lightning.pytorch.callbacks import Callback


class AgreedSigterm(Callback):
    def __init__(self) -> None:
        self.signalled = False  # this rank got SIGTERM (from the cluster or from the rank that started it)
        self.launcher = None
        self.stopping = False  # the ranks agreed to stop after this step

    def on_sanity_check_start(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> None:
        self.take_over(trainer)  # a signal in the sanity check reached Lightning's handler, which hung the ranks

    def on_train_start(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> None:
        self.take_over(trainer)
        if trainer.received_sigterm:  # Lightning's handler got one first, on this rank: the ranks agree on it after
            #                           the first step (not raised on this rank alone)
            self.signalled, trainer._signal_connector.received_sigterm = True, False

    def take_over(self, trainer: lightning.Trainer) -> None:
        if threading.current_thread() is threading.main_thread():
            self.launcher = trainer.strategy.launcher
            signal.signal(signal.SIGTERM, self.note)

    def note(self, signum: int, frame: FrameType | None) -> None:
        if not self.signalled and self.launcher is not None:
            self.launcher.kill(signum)  # the ranks Lightning started from this one, where it did (none on a cluster)
        self.signalled = True

    def on_train_batch_end(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        signalled = self.signalled
        if trainer.world_size > 1:
            flags = torch.tensor(float(signalled), device=pl_module.device)
            torch.distributed.all_reduce(flags, op=torch.distributed.ReduceOp.MAX)
            signalled = bool(flags.item())
        if signalled:
            # Lightning's own flag (it has no setter): the training loop raises SIGTERMException after this batch
            self.stopping = trainer._signal_connector.received_sigterm = True

    def on_validation_start(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> None:
        if self.stopping:  # the step validates: its evaluation loop would raise after its first batch
            trainer._signal_connector.received_sigterm = False

    def on_validation_end(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> None:
        if self.stopping:  # raised after the validation, with the fit's state a whole step's
            trainer._signal_connector.received_sigterm = True
