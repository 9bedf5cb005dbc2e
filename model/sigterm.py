"""`AgreedSigterm`: on SIGTERM, the fit stops after the current step (under DDP the next) with last.ckpt of that
step, on every DDP rank after the same one, whichever ranks got the signal.

SLURM (`scancel`, a job's time limit, preemption) and Kubernetes send SIGTERM to every process of a job at once.
Lightning 2.6's handler then calls `torch.distributed.broadcast` inside the signal handler, on every rank, at
whatever point each rank is (inside DDP's gradient all-reduce, inside the step's own broadcast of the flag): the
collectives no longer pair up, and the fit hangs without writing a checkpoint (5 of 6 tries with 2 gloo ranks,
docs/pretraining.md). And at a step that validates, in one process as under DDP, Lightning raises inside the
validation, where no checkpoint can be written. From the sanity check on (or the start of training, without one),
this callback stands in for Lightning's handler: the signal only sets a flag (and is passed on to the ranks that
Lightning's launcher started from this process, and to a handler the process had before the fit, as Lightning
does); after every step the ranks take the maximum of their flags in one all-reduce of one number (a single process
reads its own). When one was signalled, all of them set Lightning's own `received_sigterm` after that step, where
`LastStepCheckpoint` (the next callback) writes last.ckpt, so that Lightning raises its SIGTERMException on every
rank at the end of it; a step that validates runs its validation to its end first. Lightning restores the handlers
it found when the fit ends.

Under DDP the agreement costs the step no wait for the GPU: the all-reduced flag of step s is read at the end of
step s + 1 (so the ranks stop one step after the signal), by which time its copy to the host is done, where reading
it at once would make the host wait for all of step s's GPU work before it could queue the next step. And since
Lightning's `received_sigterm` is now only set here, after the ranks agreed, Lightning's own check of it, a
broadcast read on the host before every step under DDP (`_broadcast_sigterm_tensor`, 2.6), is turned off: it
would find nothing and cost a synchronisation each step.
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
        self.handler_before = None  # the process's own SIGTERM handler before the fit (submitit's, a user's)
        self.stopping = False  # the ranks agreed to stop after this step
        # DDP, from a fit's first step: this rank's flag on the device, the last step's agreed flag on the host, and
        # the CUDA event of its copy there (None on a CPU)
        self._agreement: tuple[torch.Tensor, torch.Tensor, torch.cuda.Event | None] | None = None

    def setup(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule, stage: str) -> None:
        self.handler_before = signal.getsignal(signal.SIGTERM)  # before Lightning installs its own, after this hook

    def on_sanity_check_start(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> None:
        self.take_over(trainer)  # a signal in the sanity check reached Lightning's handler, which hung the ranks

    def on_train_start(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> None:
        self.take_over(trainer)
        self._agreement = None  # nothing agreed yet in this fit
        if trainer.received_sigterm:  # Lightning's handler got one first, on this rank: the ranks agree on it after
            #                           the first step (not raised on this rank alone)
            self.signalled, trainer._signal_connector.received_sigterm = True, False

    def take_over(self, trainer: lightning.Trainer) -> None:
        if threading.current_thread() is threading.main_thread():
            self.launcher = trainer.strategy.launcher
            signal.signal(signal.SIGTERM, self.note)
            # Lightning's per-step broadcast of its flag, which only this callback sets now (module docstring)
            trainer.fit_loop.epoch_loop._broadcast_sigterm_tensor = lambda: None

    def note(self, signum: int, frame: FrameType | None) -> None:
        if not self.signalled and self.launcher is not None:
            self.launcher.kill(signum)  # the ranks Lightning started from this one, where it did (none on a cluster)
        self.signalled = True
        if callable(self.handler_before) and self.handler_before != self.note:  # it runs too, as under Lightning's
            self.handler_before(signum, frame)

    def on_train_batch_end(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        agreed = self.signalled if trainer.world_size == 1 else self.agree_one_step_late(pl_module.device)
        if agreed:
            # Lightning's own flag (it has no setter): the training loop raises SIGTERMException after this batch
            self.stopping = trainer._signal_connector.received_sigterm = True

    def agree_one_step_late(self, device: torch.device) -> bool:
        """Start the all-reduce (max) of this step's flag and its copy to the host, and return the ranks' agreed
        flag of the step before (False at the first step): that copy was queued a whole step ago, so reading it
        does not wait for this step's GPU work. The flag lives on the device and is set there by a kernel, as
        making a tensor from a Python number on a GPU would wait for the GPU."""
        if self._agreement is None:  # the first step: nothing agreed yet
            cuda = device.type == "cuda"
            self._agreement = (torch.zeros((), device=device), torch.zeros((), pin_memory=cuda),
                               torch.cuda.Event() if cuda else None)
        flag, host_flag, copied = self._agreement
        if copied is not None:
            copied.synchronize()  # returns at once before its first record
        agreed = bool(host_flag)  # 0 before the first copy
        flag.fill_(float(self.signalled))
        torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
        host_flag.copy_(flag, non_blocking=True)
        if copied is not None:
            copied.record()
        return agreed

    def on_validation_start(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> None:
        if self.stopping:  # the step validates: its evaluation loop would raise after its first batch
            trainer._signal_connector.received_sigterm = False

    def on_validation_end(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> None:
        if self.stopping:  # raised after the validation, with the fit's state a whole step's
            trainer._signal_connector.received_sigterm = True
