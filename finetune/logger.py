"""Run logs: one CSV per kind of record (`train.csv`, `episodes.csv`, `eval.csv`) and TensorBoard scalars.

Each CSV row is one record with its step first (`env_step`; offline runs count `update`s); a resumed run
appends to the same files, and a record with a column the file lacks widens its header (older rows get
empty cells) rather than losing the column. A run starts from its checkpoint's step (0 without one): the
records a stopped run wrote after that step are dropped, from the CSVs and from TensorBoard's view
(SummaryWriter's `purge_step`), since the run writes them again; so are rows a crash damaged (a cut-off last line,
bytes that are not UTF-8, the NULs a file system leaves after a power loss), and a file whose header is damaged is
set aside as NAME.damaged.
TensorBoard tags are `<kind>/<name>` (e.g. `eval/return`, `train/model_loss`), written to the run directory.
"""

from __future__ import annotations

import csv
import io
import math
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
        """Drop the rows of `path` logged after step `start` (by a run stopped before its next checkpoint), and those a
        crash damaged; a file whose header is damaged goes aside, as NAME.damaged."""
        text = path.read_bytes().decode("utf-8", errors="replace")  # damage becomes U+FFFD, which `intact` refuses
        reader = csv.DictReader(io.StringIO(text, newline=""))
        header = list(reader.fieldnames or [])
        if text and (self.step_name not in header or not all(map(intact, header))):
            aside = path.with_name(f"{path.name}.damaged")
            path.replace(aside)
            print(f"note: {path}: its header is damaged (a crash?); set aside as {aside.name}, and a new file begun",
                  file=sys.stderr)
            return
        rows = list(reader)
        cut_off = bool(text) and not text.endswith("\n")  # its last row was being written: the next would join it
        whole = [row for row in rows[:len(rows) - cut_off] if None not in row and all(map(intact, row.values()))
                 and is_number(row[self.step_name])]
        kept = [row for row in whole if float(row[self.step_name]) <= start]
        if len(whole) < len(rows):
            print(f"note: {path}: {len(rows) - len(whole)} damaged rows dropped (cut off or unreadable: a crash?)",
                  file=sys.stderr)
        if len(kept) < len(whole):
            print(f"note: {path}: {len(whole) - len(kept)} rows after {self.step_name} {start} dropped; they were "
                  "logged after the checkpoint this run starts from, and it logs them again", file=sys.stderr)
        if len(kept) < len(rows) or cut_off:
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


def intact(cell: str | None) -> bool:
    """Whether a CSV cell is as a run writes it: present, without the NULs or undecodable bytes of a crash's damage."""
    return cell is not None and "\x00" not in cell and "\ufffd" not in cell


def is_number(cell: str) -> bool:
    try:
        return math.isfinite(float(cell))
    except ValueError:
        return False


def rewrite(path: Path, header: list[str], rows: list[dict]) -> None:
    """`path` as a CSV of `header` and `rows`, replaced whole (written beside it, then renamed over it)."""
    with written_whole(path) as partial, partial.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=header, restval="")
        writer.writeheader()
        writer.writerows(rows)
