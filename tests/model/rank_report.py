"""Test callbacks for the DDP tests: each rank writes how many steps it took, the broadcasts it made while training
and a hash of its final weights; each rank sends itself SIGTERM, at a different point of the same step. And a rank's
body for torch.multiprocessing.spawn (importable by name in the processes it starts, as a test module is not)."""

from __future__ import annotations

import hashlib
import json
import os
import signal
from pathlib import Path

import lightning as L
import torch


class RankReport(L.Callback):
    def __init__(self, out_dir: str):
        self.out_dir = Path(out_dir)
        self.batches = 0
        self.broadcasts = 0  # torch.distributed.broadcast calls while training (each one a wait for a GPU)
        self._broadcast = torch.distributed.broadcast

    def on_train_start(self, trainer, pl_module):
        def counted(*args, **kwargs):
            self.broadcasts += 1
            return self._broadcast(*args, **kwargs)
        torch.distributed.broadcast = counted

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.batches += 1

    def on_train_end(self, trainer, pl_module):
        torch.distributed.broadcast = self._broadcast
        digest = hashlib.sha256()
        for name, tensor in sorted(pl_module.state_dict().items()):
            digest.update(name.encode())
            digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
        self.out_dir.mkdir(parents=True, exist_ok=True)
        report = {"rank": trainer.global_rank, "world_size": trainer.world_size, "global_step": trainer.global_step,
                  "batches": self.batches, "broadcasts": self.broadcasts, "weights_sha256": digest.hexdigest(),
                  "lambda": float(pl_module.hcu_weight()), "skipped": int(pl_module.scaler_skips + pl_module.nonfinite_steps)}
        (self.out_dir / f"rank{trainer.global_rank}.json").write_text(json.dumps(report))


class SigtermEveryRank(L.Callback):
    """SIGTERM to each rank during the third step (global_step 2): rank 0 before the batch, the others inside their
    backward pass, while DDP's gradient all-reduce is under way."""

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == 2 and trainer.global_rank == 0:
            os.kill(os.getpid(), signal.SIGTERM)

    def on_after_backward(self, trainer, pl_module):
        if trainer.global_step == 2 and trainer.global_rank != 0:
            os.kill(os.getpid(), signal.SIGTERM)


class SigtermInSanityCheck(L.Callback):
    """SIGTERM to each rank during the sanity check's first batch, before the fit trains."""

    def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0):
        if trainer.sanity_checking and batch_idx == 0:
            os.kill(os.getpid(), signal.SIGTERM)


class LoaderFailsOnRankOne(L.Callback):
    """Rank 1's loader fails before step 2 (as a corrupt shard only it reads would): rank 0 then waits in a
    collective for a rank that has gone."""

    def on_train_batch_start(self, trainer: L.Trainer, *_) -> None:
        if trainer.global_rank == 1 and trainer.global_step == 2:
            from data_pipeline.dataset import LoaderError

            raise LoaderError("shard train-000001.tar of rank 1 is damaged (a test's)")


def mean_of_two_ranks(rank: int, port: int, out: Path) -> None:
    """Rank `rank` of a 2-process gloo group: write mean_over_ranks of its value, rank + 1."""
    import torch.distributed as dist

    from model.module import mean_over_ranks

    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
    try:
        (out / f"rank{rank}").write_text(str(mean_over_ranks(torch.tensor(rank + 1.0)).item()))
    finally:
        dist.destroy_process_group()
