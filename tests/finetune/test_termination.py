"""SIGTERM (SLURM's scancel, a job's time limit) ends a fine-tuning run after its current iteration with a
checkpoint of that moment and exit status 143; the same command goes on from there, and an offline run stopped so
ends as an unbroken one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

import finetune.envs.vector
import finetune.train
from finetune.cli import main
from finetune.offline import OfflineAgent, train_offline
from finetune.run_dir import CHECKPOINT
from hauwm.termination import Terminated, interrupted_once, terminable

from test_finetune_runs import tiny_run_settings  # noqa: I001 (tests/finetune/test_finetune_runs.py)
from test_offline import offline_config


def sigterm_once(function, when):
    """`function`, sending this process SIGTERM before the first call (counted from 1) for which `when(call, *args)`."""
    call, sent = 0, False

    def wrapped(*args, **kwargs):
        nonlocal call, sent
        call += 1
        if not sent and when(call, *args):
            sent = True
            os.kill(os.getpid(), signal.SIGTERM)
        return function(*args, **kwargs)
    return wrapped


def test_after_a_first_ctrl_c_the_signals_that_follow_are_ignored_until_the_block_ends():
    """A second Ctrl-C while a run stopped cut the closing of its envs short: freed again by the garbage collector,
    a MetaWorld env's OpenGL context crashed the process (SIGSEGV)."""
    before = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    closed = []
    with pytest.raises(KeyboardInterrupt), interrupted_once():
        try:
            signal.raise_signal(signal.SIGINT)
        finally:  # the clean-up under way when the user presses Ctrl-C again (and a job's SIGTERM comes)
            signal.raise_signal(signal.SIGINT)
            signal.raise_signal(signal.SIGTERM)
            closed.append(True)
    assert closed == [True]
    assert {signum: signal.getsignal(signum) for signum in before} == before
    with pytest.raises(KeyboardInterrupt), interrupted_once():  # a SIGTERM block (a run) left on the way
        try:
            with terminable():
                signal.raise_signal(signal.SIGINT)
        finally:  # the envs' closing comes after it
            sigterm_after_the_run = signal.getsignal(signal.SIGTERM)
    assert sigterm_after_the_run is signal.SIG_IGN
    assert {signum: signal.getsignal(signum) for signum in before} == before


def test_a_process_started_with_ctrl_c_ignored_stays_immune_to_it():
    """`hauwm datasets collect … &` in a script: POSIX starts it with SIGINT ignored, and the commands' own handler
    made a Ctrl-C meant for the script stop it."""
    code = ("import signal\nfrom hauwm.termination import interrupted_once\nwith interrupted_once():\n"
            "    signal.raise_signal(signal.SIGINT)\nprint('immune')")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    assert result.returncode == 0 and result.stdout == "immune\n", result.stderr


def test_the_handler_found_before_is_called_too_and_comes_back():
    """A launcher's or a user's own SIGTERM handler (submitit requeues a job from one) still runs."""
    calls = []

    def own_handler(signum, frame):
        calls.append(signum)

    before = signal.signal(signal.SIGTERM, own_handler)
    try:
        with terminable() as stop:
            os.kill(os.getpid(), signal.SIGTERM)
            assert stop.requested and calls == [signal.SIGTERM]
        assert signal.getsignal(signal.SIGTERM) is own_handler
    finally:
        signal.signal(signal.SIGTERM, before)


@pytest.mark.parametrize("where", ["train_command", "load_config"])
def test_sigterm_while_the_command_starts_is_said_in_one_line(tmp_path, capsys, monkeypatch, where):
    """SIGTERM while `hauwm finetune` imported torch or read its settings, before the run's own handling: it died by
    the signal (status -15) without a line. Nothing was written then, and nothing is now."""
    import finetune.cli
    import finetune.config

    module = finetune.cli if where == "train_command" else finetune.config
    monkeypatch.setattr(module, where, sigterm_once(getattr(module, where), lambda call, *args: True))
    before = signal.getsignal(signal.SIGTERM)
    args = ["--config", "configs/finetune/demo.yaml", "--set", "agent=scratch", "--steps", "10"]
    assert main(args + tiny_run_settings(tmp_path / "run")) == 143
    assert capsys.readouterr().err.strip() == "hauwm finetune: terminated (SIGTERM), before the run started"
    assert not (tmp_path / "run").exists()
    assert signal.getsignal(signal.SIGTERM) is before


def stopped(pid: int) -> bool:
    """Whether process `pid` is stopped by SIGSTOP (the state field of /proc/<pid>/stat)."""
    with open(f"/proc/{pid}/stat") as stat:
        return stat.read().rpartition(")")[2].split()[0] == "T"


def freeze(envs) -> None:
    """Stop `envs`' workers once each has answered its step in flight, before they can read the next one."""
    for pipe, process in zip(envs.parent_pipes, envs.processes):
        assert pipe.poll(60), f"env worker {process.pid} did not answer its step"
        os.kill(process.pid, signal.SIGSTOP)
        deadline = time.monotonic() + 60
        while not stopped(process.pid):
            assert time.monotonic() < deadline, f"env worker {process.pid} did not stop"
            time.sleep(0.01)


@pytest.mark.parametrize(("who", "stopped_at"), [("learner", 64), ("workers", 60), ("everyone", 60),
                                                 ("workers, having answered", 64), ("learner, workers frozen", 60)])
def test_an_online_run_stops_on_sigterm_with_a_checkpoint_and_goes_on_from_it(tmp_path, capsys, monkeypatch, who,
                                                                              stopped_at):
    """SIGTERM while the env workers step (num_envs 2): to the learner, which sees it after this env step; to the
    workers (SLURM signals every process of a job), which die in the step, before or without the learner's own, or
    just after they answered it, when the run stops at their next step. Both ends of that race are made certain: a
    worker is frozen (SIGSTOP) before it can read the step it dies in, or killed once its answer is in the pipe.
    Workers frozen for good (a stuck renderer) hung a learner's SIGTERM: it now waits STOP_GRACE_S for them."""
    logdir = tmp_path / "run"
    args = ["--config", "configs/finetune/demo.yaml", "--set", "agent=scratch", "--steps", "160"]
    args += tiny_run_settings(logdir, time_limit=20, prefill=40, eval_every=200, checkpoint_every=100,
                              eval_episodes=1, num_envs=2)
    made, make_vector_env = [], finetune.envs.vector.make_vector_env
    monkeypatch.setattr(finetune.envs.vector, "make_vector_env",
                        lambda *args, **kwargs: made.append(make_vector_env(*args, **kwargs)) or made[-1])
    train_due, sent = finetune.train.train_due, []  # it runs while the workers step (after step_async)

    def signalled(cfg, agent, replay, counters, window):
        envs = made[0]
        if counters["env_step"] == 56 and who in ("workers", "everyone", "learner, workers frozen"):
            freeze(envs)  # so they die in the next step without having read it
        if counters["env_step"] == 60 and not sent:
            sent.append(who)
            if who == "workers, having answered":
                assert all(pipe.poll(60) for pipe in envs.parent_pipes)
            for process in envs.processes if who.startswith(("workers", "everyone")) else []:
                os.kill(process.pid, signal.SIGTERM)
                os.kill(process.pid, signal.SIGCONT)  # a frozen worker: the pending SIGTERM ends it
                process.join()
            if who.startswith(("learner", "everyone")):
                os.kill(os.getpid(), signal.SIGTERM)
        return train_due(cfg, agent, replay, counters, window)

    monkeypatch.setattr(finetune.train, "train_due", signalled)
    assert main(args) == 143
    err = capsys.readouterr().err
    assert f"terminated (SIGTERM) at env step {stopped_at}; its last checkpoint, {logdir / CHECKPOINT} (written " in err
    frozen = "note: env worker 0 of dmc_cartpole_swingup (seed 0, pid "
    assert (frozen in err and "has not answered its step in" in err) == (who == "learner, workers frozen")
    counters = torch.load(logdir / CHECKPOINT, weights_only=True)["counters"]
    assert counters["env_step"] == stopped_at and counters["next_checkpoint"] == 100  # not a checkpoint_every multiple
    monkeypatch.undo()
    assert main(args) == 0
    assert f"resuming {logdir / CHECKPOINT} at env step {stopped_at}" in capsys.readouterr().err
    assert torch.load(logdir / CHECKPOINT, weights_only=True)["counters"]["env_step"] == 160


def test_an_offline_run_stopped_by_sigterm_and_resumed_ends_as_an_unbroken_one(export_dir, tiny_config, tmp_path,
                                                                                two_episodes, monkeypatch):
    whole = train_offline(offline_config(tiny_config, tmp_path / "whole", 5), export_dir, progress=False)
    update = OfflineAgent.update
    monkeypatch.setattr(OfflineAgent, "update", sigterm_once(update, lambda call, agent, batch: call == 3))
    stopped = offline_config(tiny_config, tmp_path / "stopped", 5)
    try:
        train_offline(stopped, export_dir, progress=False)
    except Terminated as where:
        assert str(where) == "update 3"
    else:
        raise AssertionError("the run did not stop on SIGTERM")
    assert torch.load(tmp_path / "stopped" / CHECKPOINT, weights_only=True)["counters"]["updates"] == 3
    monkeypatch.setattr(OfflineAgent, "update", update)
    assert train_offline(stopped, export_dir, progress=False) == whole
    first = torch.load(tmp_path / "whole" / CHECKPOINT, weights_only=True)["agent"]
    second = torch.load(tmp_path / "stopped" / CHECKPOINT, weights_only=True)["agent"]
    assert all(torch.equal(value, second[key]) for key, value in first.items())


SIGTERM_AS_WORKERS_START = """
import os, signal, sys
from finetune.envs import vector
if __name__ == "__main__":
    make_vector_env = vector.make_vector_env

    def signalled(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return make_vector_env(*args, **kwargs)

    vector.make_vector_env = signalled
    from finetune.cli import main
    sys.exit(main(sys.argv[1:]))
"""


def test_sigterm_while_the_env_workers_start_stops_the_run_with_its_line(tmp_path):
    """SIGTERM came before the run handled it, while its env workers started: the process died with status −15 and
    no word of what it had kept."""
    script = tmp_path / "sigterm_as_workers_start.py"
    script.write_text(SIGTERM_AS_WORKERS_START)
    logdir = tmp_path / "run"
    args = ["--config", "configs/finetune/demo.yaml", "--set", "agent=scratch", "--steps", "160"]
    args += tiny_run_settings(logdir, time_limit=20, prefill=40, eval_every=200, checkpoint_every=100,
                              eval_episodes=1, num_envs=2)
    repo = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([repo, os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, str(script), *args], env=env, capture_output=True, text=True,
                            timeout=300, cwd=repo)
    assert result.returncode == 143, result.stderr[-2000:]
    assert f"terminated (SIGTERM) at env step 4; its last checkpoint, {logdir / CHECKPOINT} (written " in result.stderr
    assert "Traceback" not in result.stderr
