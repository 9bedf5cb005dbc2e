"""Run logs: one CSV per kind of record (`train.csv`, `episodes.csv`, `eval.csv`) and TensorBoard scalars.

Each CSV row is one record with its step first (`env_step`; offline runs count `update`s); a resumed run
appends to the same files, and a record with a column the file lacks widens its header (older rows get
empty cells) rather than losing the column. A run starts from its checkpoint's step (0 without one): the
records a stopped run wrote after that step are dropped, from the CSVs and from TensorBoard's view
(SummaryWriter's `purge_step`), since the run writes them again.
TensorBoard tags are `<kind>/<name>` (e.g. `eval/return`, `train/model_loss`), written to the run directory.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

from torch.utils.tensorboard import SummaryWriter

from hauwm.atomic import written_whole


class Logger:
    def __init__(self, logdir: Path, step_name: str = "env_step", start: int = 0):
        self.logdir = Path(logdir)
        self.step_name = step_name
        self.logdir.mkdir(parents=True, exist_ok=True)
        for path in sorted(self.logdir.glob("*.csv")):
            self.drop_rows_after(path, start)
        self.writer = SummaryWriter(str(self.logdir), purge_step=start + 1)

    def drop_rows_after(self, path: Path, start: int) -> None:
        """Drop the rows of `path` logged after step `start` (by a run stopped before its next checkpoint)."""
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            rows, header = list(reader), list(reader.fieldnames or [])
        kept = [row for row in rows if not logged_after(row.get(self.step_name), start)]
        if len(kept) < len(rows):
            print(f"note: {path}: {len(rows) - len(kept)} rows after {self.step_name} {start} dropped; they were "
                  "logged after the checkpoint this run starts from, and it logs them again", file=sys.stderr)
            rewrite(path, header, kept)

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
            rewrite(path, header + [key for key in row if key not in header], [*rows, row])
        for name, value in values.items():
            self.writer.add_scalar(f"{kind}/{name}", value, step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def logged_after(step: str | None, start: int) -> bool:
    """Whether a row's step cell names a step after `start` (a cell that is no number is kept)."""
    try:
        return float(step) > start
    except (TypeError, ValueError):
        return False


def rewrite(path: Path, header: list[str], rows: list[dict]) -> None:
    """`path` as a CSV of `header` and `rows`, replaced whole (written beside it, then renamed over it)."""
    with written_whole(path) as partial, partial.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=header, restval="")
        writer.writeheader()
        writer.writerows(rows)
