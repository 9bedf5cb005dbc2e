"""The `hauwm` command: dispatch to a stage, an unknown stage, Ctrl-C while a stage starts up."""

from __future__ import annotations

import importlib

from hauwm.cli import main


def test_an_unknown_stage_lists_the_stages(capsys):
    assert main(["fit"]) == 2
    err = capsys.readouterr().err
    assert "unknown stage 'fit'" in err and "pretrain" in err


def test_ctrl_c_while_a_stage_starts_is_one_line(monkeypatch, capsys):
    def interrupted(name):
        raise KeyboardInterrupt  # as during torch's and Lightning's imports, the first seconds of every stage

    monkeypatch.setattr(importlib, "import_module", interrupted)
    assert main(["pretrain", "fit"]) == 130
    assert capsys.readouterr().err.strip() == "hauwm pretrain: interrupted"
