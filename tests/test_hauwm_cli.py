"""The `hauwm` command: dispatch to a stage, an unknown stage, Ctrl-C while a stage starts up, a closed stdout, a path
that cannot be written."""

from __future__ import annotations

import errno
import importlib
import os
import subprocess
import sys
import types

import pytest

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


@pytest.mark.parametrize("args", [["datasets", "list"], ["--help"]])
def test_output_piped_into_a_reader_that_has_gone_ends_quietly(tmp_path, args):
    """`hauwm … | head`: once head has exited, the next write finds the pipe closed; like any Unix tool the
    command ends (rc 141, as if killed by SIGPIPE) without a traceback. (`python -m hauwm` is the command.)"""
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before the command writes anything
    result = subprocess.run([sys.executable, "-m", "hauwm", *args], stdout=write_end, stderr=subprocess.PIPE,
                            text=True, timeout=120,
                            env={**os.environ, "MINARI_DATASETS_PATH": str(tmp_path)})  # list prints one line: none there
    os.close(write_end)
    assert result.returncode == 141 and result.stderr == ""


def test_output_to_a_socket_whose_peer_has_gone_ends_quietly():
    """stdout a socket (a service's log collector) whose peer closed: as for a pipe, rc 141 and no traceback."""
    import socket

    ours, theirs = socket.socketpair()
    theirs.close()
    result = subprocess.run([sys.executable, "-m", "hauwm", "--help"], stdout=ours.fileno(), stderr=subprocess.PIPE,
                            text=True, timeout=120)
    ours.close()
    assert result.returncode == 141 and result.stderr == ""


def test_a_broken_pipe_that_is_not_stdout_is_not_taken_for_a_reader_that_has_gone(monkeypatch):
    """A pipe to a worker process that died (the shard build's decoders had one) ended the command with exit status
    141 and no word, as `| head` does; it is an error of its own, with its traceback."""
    def stage(name):
        def main(argv):
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")
        return types.SimpleNamespace(main=main)

    monkeypatch.setattr(importlib, "import_module", stage)
    with pytest.raises(BrokenPipeError):
        main(["shards", "build"])


def test_an_output_path_where_a_file_is_is_named_in_one_line(tmp_path, capsys):
    (tmp_path / "taken").write_text("")
    assert main(["shards", "sample-data", "--out", str(tmp_path / "taken" / "ssv2"), "--clips", "3"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hauwm shards: error: ") and f"{tmp_path / 'taken'}" in err and "is a file" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_a_full_disk_is_named_and_other_os_errors_keep_their_traceback(monkeypatch, capsys):
    def stage(error):
        def main(argv):
            raise error
        return types.SimpleNamespace(main=main)

    monkeypatch.setattr(importlib, "import_module", lambda name: stage(OSError(errno.ENOSPC, "No space left", "/d/x.tar")))
    assert main(["shards", "build"]) == 2
    assert "no space left on the device while writing /d/x.tar: free some space, then run the same command again (a " \
           "build keeps the shards it finished)" in capsys.readouterr().err  # "a run goes on from its last checkpoint"
    monkeypatch.setattr(importlib, "import_module", lambda name: stage(OSError(errno.EDQUOT, "Disk quota exceeded")))
    assert main(["finetune"]) == 2  # a write to a file already open: no path to name, the cause still said
    assert "hauwm finetune: error: the disk quota is reached: free some space" in capsys.readouterr().err
    monkeypatch.setattr(importlib, "import_module", lambda name: stage(ConnectionResetError("peer")))
    with pytest.raises(ConnectionResetError):  # not about a path: a bug or a network failure, shown in full
        main(["shards", "build"])


@pytest.mark.parametrize("error", [RuntimeError("[enforce fail at alloc_cpu.cpp:121] data. DefaultCPUAllocator: can't "
                                                "allocate memory: you tried to allocate 58982400000 bytes."),
                                   MemoryError("Unable to allocate 55.0 GiB for an array"),
                                   OSError(errno.ENOMEM, "Cannot allocate memory")],
                         ids=["torch", "numpy", "mmap"])
def test_memory_that_ran_out_is_one_line_naming_what_to_lower(monkeypatch, capsys, error):
    stage = types.ModuleType("model.cli")

    def out_of_memory(argv):
        raise error

    stage.main = out_of_memory
    monkeypatch.setitem(sys.modules, "model.cli", stage)
    assert main(["pretrain", "analyze", "--batch-size", "100000"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"hauwm pretrain: error: out of memory ({str(error).splitlines()[0]}): lower --data.batch_size")
    assert "--batch-size (analyze)" in err and "Traceback" not in err

    def another_runtime_error(argv):
        raise RuntimeError("shape mismatch")

    stage.main = another_runtime_error  # keeps its traceback: not about memory
    with pytest.raises(RuntimeError, match="shape mismatch"):
        main(["pretrain", "fit"])


@pytest.mark.parametrize(("args", "refused"), [
    (["shards", "sample-data", "--out", "{tmp}/ssv2", "--clip", "3"], "unrecognized arguments: --clip 3"),
    (["datasets", "merge", "a-v0", "--ou", "b-v0"], "the following arguments are required: --out"),
    (["finetune", "--config", "{tmp}/none.yaml", "--step", "3"], "unrecognized arguments: --step 3"),
    (["pretrain", "export", "{tmp}/last.ckpt", "--ou", "{tmp}/export"], "the following arguments are required: --out"),
    (["pretrain", "fit", "--trainer.max_step", "3"], "unrecognized arguments: --trainer.max_step 3"),
])
def test_no_stage_takes_the_beginning_of_a_flag_for_the_flag(tmp_path, capsys, args, refused):
    """argparse's default: `--clip 3` set --clips; a misspelling would set whichever flag it begins."""
    try:
        status = main([arg.replace("{tmp}", str(tmp_path)) for arg in args])
    except SystemExit as exit:  # argparse's way out, where a stage does not catch it
        status = exit.code
    assert status == 2
    assert refused in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written
