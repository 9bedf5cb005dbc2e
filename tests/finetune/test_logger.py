"""Run logs: CSV rows append across writers (resume), a new column widens the file instead of vanishing, and rows
logged after the step a run starts from are dropped, as are rows a crash damaged."""

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


def damaged(tmp_path, tail: bytes) -> None:
    """eval.csv of two rows, then `tail` appended as a crash leaves it."""
    logger = Logger(tmp_path)
    logger.write("eval", 100, {"return": 1.0})
    logger.write("eval", 200, {"return": 2.0})
    logger.close()
    with (tmp_path / "eval.csv").open("ab") as f:
        f.write(tail)


def test_rows_a_crash_damaged_are_dropped_and_the_next_row_starts_its_own_line(tmp_path, capsys):
    """Bytes that are not UTF-8 raised UnicodeDecodeError in a traceback; the NULs a file system leaves after a power
    loss stayed as a row of step "\\0\\0…", and the next row was glued to them (found by a review)."""
    for tail in (b"300,\xff\xfe", b"\0" * 8, b"150,1."):  # the last: a row cut off, whose step is before 200
        damaged(tmp_path, tail)
        resumed = Logger(tmp_path, start=200)
        resumed.write("eval", 300, {"return": 3.0})
        resumed.close()
        assert read(tmp_path / "eval.csv") == [{"env_step": str(step), "return": f"{step // 100}.0"}
                                               for step in (100, 200, 300)], tail
        assert "eval.csv: 1 damaged rows dropped (cut off or unreadable: a crash?)" in capsys.readouterr().err
        (tmp_path / "eval.csv").unlink()


def test_a_file_whose_header_is_damaged_is_set_aside(tmp_path, capsys):
    (tmp_path / "train.csv").write_bytes(b"\0" * 40)
    logger = Logger(tmp_path, start=0)
    logger.write("train", 10, {"loss": 1.0})
    logger.close()
    assert read(tmp_path / "train.csv") == [{"env_step": "10", "loss": "1.0"}]
    assert (tmp_path / "train.csv.damaged").read_bytes() == b"\0" * 40
    assert "train.csv: its header is damaged (a crash?); set aside as train.csv.damaged" in capsys.readouterr().err
