"""Run logs: CSV rows append across writers (resume), a new column widens the file instead of vanishing, and rows
logged after the step a run starts from are dropped."""

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
    resumed = Logger(tmp_path, start=20)
    resumed.write("train", 30, {"extra": 0.25})  # a missing column is left empty
    resumed.close()
    assert read(tmp_path / "train.csv") == [
        {"env_step": "10", "loss": "1.5", "extra": ""},
        {"env_step": "20", "loss": "1.0", "extra": "0.5"},
        {"env_step": "30", "loss": "", "extra": "0.25"},
    ]
    assert not list(tmp_path.glob(".*.partial"))


def test_a_header_only_file_is_widened_too(tmp_path):
    (tmp_path / "eval.csv").write_text("env_step,return\n")
    logger = Logger(tmp_path)
    logger.write("eval", 5, {"return": 2.0, "success_rate": 1.0})
    logger.close()
    assert read(tmp_path / "eval.csv") == [{"env_step": "5", "return": "2.0", "success_rate": "1.0"}]


def test_rows_logged_after_the_step_a_run_starts_from_are_dropped(tmp_path, capsys):
    logger = Logger(tmp_path, step_name="update")
    for step in (1, 2, 3, 4):
        logger.write("train", step, {"loss": float(step)})
    logger.write("eval", 2, {"return": 5.0})
    logger.write("eval", 4, {"return": 6.0})  # a run checkpointed at update 2, then killed after update 4
    logger.close()
    Logger(tmp_path, step_name="update", start=2).close()
    assert [row["update"] for row in read(tmp_path / "train.csv")] == ["1", "2"]
    assert read(tmp_path / "eval.csv") == [{"update": "2", "return": "5.0"}]
    assert "eval.csv: 1 rows after update 2 dropped" in capsys.readouterr().err
    Logger(tmp_path, step_name="update", start=2).close()  # nothing more to drop: the files stay as they are
    assert capsys.readouterr().err == "" and len(read(tmp_path / "train.csv")) == 2
