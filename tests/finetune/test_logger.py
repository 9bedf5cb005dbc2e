"""Run logs: CSV rows append across writers (resume), and a new column widens the file instead of vanishing."""

import csv

from finetune.logger import Logger


def read(path):
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_rows_append_and_a_new_column_widens_the_header(tmp_path):
    logger = Logger(tmp_path)
    logger.write("train", 10, {"loss": 1.5})
    logger.write("train", 20, {"loss": 1.0, "extra": 0.5})  # e.g. a metric added by a newer version
    logger.close()
    resumed = Logger(tmp_path)
    resumed.write("train", 30, {"extra": 0.25})  # a missing column is left empty
    resumed.close()
    assert read(tmp_path / "train.csv") == [
        {"env_step": "10", "loss": "1.5", "extra": ""},
        {"env_step": "20", "loss": "1.0", "extra": "0.5"},
        {"env_step": "30", "loss": "", "extra": "0.25"},
    ]
    assert not list(tmp_path.glob("*.tmp"))


def test_a_header_only_file_is_widened_too(tmp_path):
    (tmp_path / "eval.csv").write_text("env_step,return\n")
    logger = Logger(tmp_path)
    logger.write("eval", 5, {"return": 2.0, "success_rate": 1.0})
    logger.close()
    assert read(tmp_path / "eval.csv") == [{"env_step": "5", "return": "2.0", "success_rate": "1.0"}]
