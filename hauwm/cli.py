"""The `hauwm` command: dispatches to each stage's own CLI, importing only the stage asked for.

    hauwm shards   ...   data_pipeline.cli   (SSv2 -> WebDataset shards, inspect, preview, sample data)
    hauwm pretrain ...   model.cli           (LightningCLI fit and validate, export, analyze)
    hauwm finetune ...   finetune.cli        (online RL, `offline` RL and `imitate`, from the frozen export)
    hauwm datasets ...   finetune.datasets.cli (Minari datasets for offline RL: collect, merge, inspect, list)

A stage's own errors are its to report; what reaches this dispatcher is reported here in one line: Ctrl-C while
a stage starts up, a reader of stdout that has gone (`| head`), a path that cannot be made, read or written, a
full disk or quota, and memory that ran out (on the GPU or in the host).
"""

from __future__ import annotations

import errno
import importlib
import os
import select
import signal
import sys

from hauwm.messages import first_line

STAGES = {
    "shards": ("data_pipeline.cli", "shard SSv2 into WebDataset tars, inspect and preview them"),
    "pretrain": ("model.cli", "pre-train the ensemble RSSM (fit, validate), export it, analyze it"),
    "finetune": ("finetune.cli", "train an agent on a control task from the frozen export (online RL; `offline`, "
                                 "`imitate`, `evaluate`)"),
    "datasets": ("finetune.datasets.cli", "collect, merge, inspect and list Minari datasets for offline RL"),
}


def usage() -> str:
    lines = [f"usage: hauwm {{{','.join(STAGES)}}} ...", "", "stages:"]
    lines += [f"  {name:<9} {help_}" for name, (_, help_) in STAGES.items()]
    lines += ["", "Run `hauwm STAGE --help` for the stage's own flags."]
    return "\n".join(lines)


# what lowers a stage's memory, for an allocation that failed (a batch that does not fit on the GPU, most often)
SMALLER = {
    "pretrain": "lower --data.batch_size or --data.seq_len (fit, validate; a fit goes on from its last checkpoint with "
                "--ckpt_path last) or --batch-size (analyze)",
    "finetune": "lower batch_size or seq_len (--set batch_size=16), or num_envs; a run goes on from its last checkpoint",
}
FULL = (errno.ENOSPC, errno.EDQUOT)  # a full disk, or the user's disk quota reached (common on clusters)


# what running a stage's command again does, after a full disk stopped it
AGAIN = {
    "pretrain": " (a fit goes on from its last checkpoint with --ckpt_path last; an export or analysis starts anew)",
    "finetune": " (a run goes on from its last checkpoint)",
    "shards": " (a build keeps the shards it finished)",
}


def path_problem(err: OSError, stage: str) -> str:
    """What went wrong with err.filename (None for a write to a file already open), and what to do, in one clause."""
    path = err.filename
    if err.errno in FULL:
        where = f" while writing {path}" if path else ""
        full = "no space left on the device" if err.errno == errno.ENOSPC else "the disk quota is reached"
        return f"{full}{where}: free some space, then run the same command again{AGAIN.get(stage, '')}"
    if err.errno in (errno.EEXIST, errno.ENOTDIR):  # mkdir of an output directory where a file is
        return f"{path} is a file, or lies under one, where a directory is needed: pass another path"
    return f"{path}: {err.strerror}: check the path and its permissions"


def stdout_gone() -> bool:
    """Whether stdout's reader has gone: poll(2) reports an error on the write end of a pipe or FIFO whose reader
    closed it, and a hang-up on a socket whose peer did."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # no file descriptor (a test's captured output), or one closed
        return False


def out_of_memory(err: BaseException) -> bool:
    """torch's OutOfMemoryError (CUDA), a host allocation torch or numpy could not make (without importing either)."""
    return isinstance(err, MemoryError) or type(err).__name__ == "OutOfMemoryError" or (
        isinstance(err, RuntimeError) and "can't allocate memory" in str(err))


def memory_ran_out(stage: str, err: BaseException) -> int:
    """Say in one line that `stage` ran out of memory, and what lowers its memory; the exit status."""
    what = first_line(err)
    print(f"hauwm {stage}: error: out of memory ({what}): {SMALLER.get(stage, 'lower the sizes this command was given')}",
          file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    stage = argv[0] if argv else "--help"
    if stage not in STAGES and stage not in ("-h", "--help"):
        print(f"hauwm: unknown stage {stage!r}\n\n{usage()}", file=sys.stderr)
        return 2
    if os.environ.get("MINARI_DATASETS_PATH"):  # Minari joins a relative root to itself: made absolute here, once
        os.environ["MINARI_DATASETS_PATH"] = os.path.abspath(os.environ["MINARI_DATASETS_PATH"])
    try:
        try:
            if stage not in STAGES:
                print(usage())
                return 0
            return importlib.import_module(STAGES[stage][0]).main(argv[1:]) or 0
        finally:
            sys.stdout.flush()  # a reader that went away (`hauwm datasets inspect ID | head`) shows here, not at exit
    except KeyboardInterrupt:  # each stage reports an interrupted run itself; this is Ctrl-C while starting up
        print(f"\nhauwm {stage}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # as a command killed by SIGPIPE ends, without a traceback
        if not stdout_gone():  # a pipe of the stage's own (to a process that died): an error, not `| head`
            raise
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the interpreter's last flush goes nowhere
        return 128 + signal.SIGPIPE
    except OSError as err:  # a path a stage could not make, read or write: one line naming it, not a traceback
        if err.errno == errno.ENOMEM:  # a fork or mmap the host had no memory for
            return memory_ran_out(stage, err)
        if err.filename is None and err.errno not in FULL:  # not about a path (a socket, a library's own failure)
            raise
        print(f"hauwm {stage}: error: {path_problem(err, stage)}", file=sys.stderr)
        return 2
    except (MemoryError, RuntimeError) as err:
        if not out_of_memory(err):
            raise
        return memory_ran_out(stage, err)


if __name__ == "__main__":
    sys.exit(main())
