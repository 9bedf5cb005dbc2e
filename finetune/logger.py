"""Run logs: one CSV per kind of record (`train.csv`, `episodes.csv`, `eval.csv`) and TensorBoard scalars.

Each CSV row is one record with `env_step` first; a resumed run appends to the same files. TensorBoard
tags are `<kind>/<name>` (e.g. `eval/return`, `train/model_loss`), written to the run directory.
"""

from __future__ import annotations

import csv
from pathlib import Path

from torch.utils.tensorboard import SummaryWriter


class Logger:
    def __init__(self, logdir: Path):
        self.logdir = Path(logdir)
        self.logdir.mkdir(parents=True, exist_ok=True)
        self.writer = SummaryWriter(str(self.logdir))

    def write(self, kind: str, env_step: int, values: dict[str, float]) -> None:
        row = {"env_step": env_step, **values}
        path = self.logdir / f"{kind}.csv"
        new_file = not path.exists()
        if not new_file:
            with path.open() as f:
                header = next(csv.reader(f), [])
            row = {key: row.get(key, "") for key in header} if header else row
        with path.open("a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(row))
            if new_file:
                writer.writeheader()
            writer.writerow(row)
        for name, value in values.items():
            self.writer.add_scalar(f"{kind}/{name}", value, env_step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()
