"""Run logs: one CSV per kind of record (`train.csv`, `episodes.csv`, `eval.csv`) and TensorBoard scalars.

Each CSV row is one record with its step first (`env_step`; offline runs count `update`s); a resumed run
appends to the same files, and a record with a column the file lacks widens its header (older rows get
empty cells) rather than losing the column.
TensorBoard tags are `<kind>/<name>` (e.g. `eval/return`, `train/model_loss`), written to the run directory.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

from torch.utils.tensorboard import SummaryWriter


class Logger:
    def __init__(self, logdir: Path, step_name: str = "env_step"):
        self.logdir = Path(logdir)
        self.step_name = step_name
        self.logdir.mkdir(parents=True, exist_ok=True)
        self.writer = SummaryWriter(str(self.logdir))

    def write(self, kind: str, step: int, values: dict[str, float]) -> None:
        row = {self.step_name: step, **values}
        path = self.logdir / f"{kind}.csv"
        header = []
        if path.exists():
            with path.open(newline="") as f:
                header = next(csv.reader(f), [])
        if header and all(key in header for key in row):
            with path.open("a", newline="") as f:
                csv.DictWriter(f, fieldnames=header, restval="").writerow(row)
        else:  # a new file, or a column this file has not seen (a run resumed by a newer version)
            rows = []
            if header:
                with path.open(newline="") as f:
                    rows = list(csv.DictReader(f))
            tmp = path.with_suffix(".csv.tmp")
            with tmp.open("w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=header + [key for key in row if key not in header], restval="")
                writer.writeheader()
                writer.writerows([*rows, row])
            os.replace(tmp, path)
        for name, value in values.items():
            self.writer.add_scalar(f"{kind}/{name}", value, step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()
