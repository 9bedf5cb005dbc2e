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
                  "lambda": float(pl_module.hcu_weight()), "scaler_skips": int(pl_module.scaler_skips),
                  "nonfinite_steps": int(pl_module.nonfinite_steps)}
        (self.out_dir / f"rank{trainer.global_rank}.json").write_text(json.dumps(report))


class NanOnRankOne(L.Callback):
    """Rank 1's third step (global_step 2) runs with a NaN in one weight, so its loss alone is not finite; the weight
    is put back after the step (which every rank skips: the all-reduced gradients are not finite)."""

    def __init__(self) -> None:
        self.saved: torch.Tensor | None = None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == 2 and trainer.global_rank == 1:
            weight = next(pl_module.world_model.parameters())
            self.saved = weight.detach().clone()
            with torch.no_grad():
                weight.view(-1)[0] = float("nan")

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if self.saved is not None:
            with torch.no_grad():
                next(pl_module.world_model.parameters()).copy_(self.saved)
            self.saved = None


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


def fp16_fit_with_a_nan_on_rank_one(rank: int, port: int, out: Path) -> None:
    """Rank `rank` of a 2-process DDP fit over gloo (started as a launcher starts ranks) under 16-mixed, its
    GradScaler from 256 (float16 is slow on a CPU; the plugin is given explicitly, since the Trainer would turn 16-mixed
    into bf16-mixed on a CPU), rank 1's third step with a NaN loss (NanOnRankOne); RankReport writes its counters."""
    from lightning.pytorch.plugins.precision import MixedPrecision

    from model.config import WorldModelConfig
    from model.module import PretrainModule

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), WORLD_SIZE="2", NODE_RANK="0",
                      LOCAL_RANK=str(rank), RANK=str(rank))
    generator = torch.Generator().manual_seed(rank)
    batches = [{"frames": torch.randint(0, 256, (2, 3, 3, 64, 64), dtype=torch.uint8, generator=generator),
                "gaps": torch.tensor([[0, 1, 2]] * 2), "num_frames": torch.tensor([20, 20])} for _ in range(4)]
    torch.manual_seed(0)
    module = PretrainModule(WorldModelConfig(cnn_width=8, embed_dim=32, deter=24, stoch=6, hidden=24, ensemble=3,
                                             temporal_dim=8))
    precision = MixedPrecision("16-mixed", "cpu", torch.amp.GradScaler("cpu", init_scale=256.0))
    trainer = L.Trainer(accelerator="cpu", devices=2, strategy="ddp", plugins=[precision], max_steps=len(batches),
                        logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                        callbacks=[RankReport(str(out)), NanOnRankOne()])
    trainer.fit(module, torch.utils.data.DataLoader(batches, batch_size=None))
