"""A test callback for the DDP test: each rank writes how many steps it took and a hash of its final weights."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import lightning as L


class RankReport(L.Callback):
    def __init__(self, out_dir: str):
        self.out_dir = Path(out_dir)
        self.batches = 0

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.batches += 1

    def on_train_end(self, trainer, pl_module):
        digest = hashlib.sha256()
        for name, tensor in sorted(pl_module.state_dict().items()):
            digest.update(name.encode())
            digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
        self.out_dir.mkdir(parents=True, exist_ok=True)
        report = {"rank": trainer.global_rank, "world_size": trainer.world_size, "global_step": trainer.global_step,
                  "batches": self.batches, "weights_sha256": digest.hexdigest(),
                  "lambda": float(pl_module.hcu_weight()), "skipped": int(pl_module.scaler_skips + pl_module.nonfinite_steps)}
        (self.out_dir / f"rank{trainer.global_rank}.json").write_text(json.dumps(report))
