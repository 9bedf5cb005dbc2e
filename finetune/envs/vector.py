"""Several training environments stepped as one batch, with gymnasium's vector API.

    envs = make_vector_env("dmc_cheetah_run", seeds=[0, 1, 2, 3], fast_render=True)
    obs, info = envs.reset()                                  # uint8 [4, 3, 64, 64]
    obs, reward, terminated, truncated, info = envs.step(actions)   # actions [4, A]

- One seed: a `SyncVectorEnv`, the env in this process (what a single env gives, step for step).
- More: an `AsyncVectorEnv`, one worker process per env, so that the envs simulate and render on every
  core at once, also while the learner trains (`step_async`, then `step_wait`). Workers are started
  with the "forkserver" context ("spawn" where there is none): MuJoCo's OpenGL contexts, CUDA and
  threads do not survive `fork`; the fork server imports the suite's modules once, so each worker starts
  from a process that has them already — except under `MUJOCO_GL=egl`, where importing dm_control opens
  an EGL display: every worker forked from a server holding one failed to make its context
  (`EGL_BAD_ALLOC`, seen on an H200), so there each worker imports its suite itself. A worker that
  cannot build its env says why in one line and the parent raises `EnvWorkerError` naming the task; one
  that dies later (a crash in the simulator, the out-of-memory killer) is named with its seed and cause.
  Workers (and the fork server) ignore SIGINT: a terminal's Ctrl-C reaches the whole process group, and the
  learner, not each worker, decides what an interrupt does (`closing_envs` ends them, with SIGKILL where SIGTERM
  does not do it: a stopped worker). A worker that has not answered a step or reset for ANSWER_TIMEOUT_S
  (stopped by SIGSTOP, stuck in its renderer), or for STOP_GRACE_S once the run was asked to stop (SIGTERM), is
  named with the state of its process in an EnvWorkerError, instead of the run waiting for it forever. A worker
  whose learner is gone (killed) ends at once and without a word (`quiet_worker`). Frames come back through
  shared memory.
- Workers are pinned to CPUs (`pin=True`, the default; Linux), the way Sample Factory pins its rollout
  workers: with N envs on C usable CPUs (`os.sched_getaffinity`), worker i gets CPU i mod C when C
  divides N, and its own block of C/N CPUs when N divides C; otherwise nothing is pinned. Every CPU gets
  the same share of workers, so several runs on one machine still spread over all of it; the learner's
  process is never pinned. All the worker's threads are pinned, MuJoCo's renderer's included, whose
  wandering between cores cost most: on 2 cores, 2 envs stepped 1.61× one env unpinned and 1.87× pinned
  (medians of 6 runs, bench/README.md). What the envs do is the same either way.

An env whose episode ends is reset inside that same step (gymnasium's SAME_STEP autoreset): the step
returns the new episode's first frame, and the finished episode's last frame is `info["final_obs"][i]`.
(gymnasium's default, NEXT_STEP, would spend the next step on the reset, with a reward of 0 that no
action earned.)
"""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import multiprocessing.connection
import multiprocessing.forkserver
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv, VectorEnv
from gymnasium.vector.async_vector_env import _async_worker

from finetune.envs.opengl import check_rendering
from finetune.envs.registry import make_env, suite_module
from hauwm.messages import killed_by

START_METHOD = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
ANSWER_TIMEOUT_S = 300.0  # a step or reset takes milliseconds to a second: a worker silent this long is stuck
STOP_GRACE_S = 5.0  # how long a run asked to stop (SIGTERM) waits for a silent worker: SLURM's SIGKILL comes in 30 s


class EnvWorkerError(RuntimeError):
    """An env worker process could not build its env, or ended while it ran one; the message says which and why.
    `by_sigterm`: every worker that died was ended by SIGTERM (SLURM's scancel or time limit signal every process
    of a job: the learner's own SIGTERM may come a moment later)."""

    by_sigterm = False


# how an env worker that died can have been killed, and what to do about it
DEATH_CAUSES = {
    signal.SIGKILL: "killed by SIGKILL, most likely by the kernel's out-of-memory killer (`dmesg` says so): lower "
                    "num_envs or give the job more memory",
    signal.SIGSEGV: "crashed in native code (SIGSEGV: the simulator or its OpenGL renderer): num_envs 1 runs the env "
                    "in this process, where the crash shows its place; MUJOCO_GL=egl or osmesa changes the renderer",
}


def death_cause(exitcode: int) -> str:
    """What a worker process's exit code says about how it ended."""
    if exitcode >= 0:
        return f"it exited with status {exitcode}"
    return killed_by(-exitcode, DEATH_CAUSES)


# what the state letter of /proc/PID/stat says about a worker that does not answer
PROCESS_STATES = {
    "T": "its process is stopped (SIGSTOP, or a debugger): `kill -CONT {pid}` lets it go on",
    "t": "its process is stopped by a debugger",
    "D": "its process waits on the kernel (disk or GPU driver I/O)",
    "R": "its process is running: stuck in the simulator or renderer?",
    "S": "its process is waiting: stuck in the simulator or renderer?",
}


def process_state(pid: int) -> str:
    """What Linux says about process `pid` (its state in /proc), for a worker that does not answer."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return "its process state is unknown"
    return PROCESS_STATES.get(state, f"its process is in state {state!r}").format(pid=pid)


def naming_dead_workers(method: Callable) -> Callable:
    """A WorkerEnvs method run inside its `_dead_workers_named` (an EnvWorkerError for a worker that died)."""
    @functools.wraps(method)
    def naming(self, *args, **kwargs):
        with self._dead_workers_named():
            return method(self, *args, **kwargs)
    return naming


class WorkerEnvs(AsyncVectorEnv):
    """gymnasium's AsyncVectorEnv whose workers, when one dies mid-run (a segfault in the simulator or renderer,
    the out-of-memory killer), are named in an EnvWorkerError: env index, seed, pid and cause, not the bare
    EOFError or BrokenPipeError its pipe gives."""

    answer_timeout = ANSWER_TIMEOUT_S

    def __init__(self, name: str, seeds: list[int], env_fns: list, stopping: Callable[[], bool], **kwargs):
        self.name, self.seeds, self.stopping = name, seeds, stopping
        super().__init__(env_fns, **kwargs)

    # every call that talks to the workers (step and reset are an _async and a _wait); a _wait without a timeout
    # (the run's) gives up on a silent worker, one with a timeout (gymnasium's close) waits as asked
    step_async = naming_dead_workers(AsyncVectorEnv.step_async)

    @naming_dead_workers
    def reset_async(self, seed: int | list[int | None] | None = None, options: dict | None = None):
        if isinstance(seed, list):  # the seeds the reset envs play from now: those a failure names (a reseeding run)
            mask = (options or {}).get("reset_mask")
            self.seeds = [new if new is not None and (mask is None or mask[index]) else old
                          for index, (old, new) in enumerate(zip(self.seeds, seed))]
        return super().reset_async(seed=seed, options=options)

    @naming_dead_workers
    def reset_wait(self, timeout: float | None = None, **kwargs):
        if timeout is None:
            self._await_answers("reset")
        return super().reset_wait(timeout, **kwargs)

    @naming_dead_workers
    def step_wait(self, timeout: float | None = None):
        if timeout is None:
            self._await_answers("step")
        return super().step_wait(timeout)

    def _await_answers(self, call: str) -> None:
        """Wait until every worker has answered `call` or closed its pipe (one that died: named by
        _dead_workers_named); raise an EnvWorkerError naming the workers silent for answer_timeout seconds, or for
        STOP_GRACE_S after `stopping()` turned true."""
        waiting = {pipe: index for index, pipe in enumerate(self.parent_pipes)}
        start, stop_seen = time.monotonic(), None
        while waiting:
            for pipe in multiprocessing.connection.wait(list(waiting), timeout=1.0):
                del waiting[pipe]
            now = time.monotonic()
            if stop_seen is None and self.stopping():
                stop_seen = now
            if waiting and (now - start >= self.answer_timeout or (stop_seen and now - stop_seen >= STOP_GRACE_S)):
                silent = [f"env worker {index} of {self.name} (seed {self.seeds[index]}, pid {process.pid}) has not "
                          f"answered its {call} in {now - start:.0f} s: {process_state(process.pid)}"
                          for index in sorted(waiting.values()) for process in [self.processes[index]]]
                raise EnvWorkerError("; ".join(silent))

    @contextlib.contextmanager
    def _dead_workers_named(self) -> Iterator[None]:
        try:
            yield
        except (EOFError, ConnectionError) as error:
            dead = []  # a pipe that closed: its process is ending; one wait for all (a second each made 64 envs' news
            #            a minute late)
            multiprocessing.connection.wait([process.sentinel for process in self.processes], timeout=1.0)
            for index, process in enumerate(self.processes):
                if process.exitcode is not None:
                    dead.append(f"env worker {index} of {self.name} (seed {self.seeds[index]}, pid {process.pid}) "
                                f"died: {death_cause(process.exitcode)}")
            failure = EnvWorkerError("; ".join(dead) or f"an env worker of {self.name} stopped answering "
                                     f"({type(error).__name__} from its pipe)")
            failure.by_sigterm = bool(dead) and all(process.exitcode in (None, -signal.SIGTERM)
                                                    for process in self.processes)
            raise failure from None


def make_vector_env(name: str, seeds: list[int], pin: bool = True, stopping: Callable[[], bool] = lambda: False,
                    **kwargs) -> VectorEnv:
    """`len(seeds)` envs of task `name`, env i built by `make_env(name, seed=seeds[i], **kwargs)`; with more than
    one, their worker processes are pinned to CPUs unless `pin` is false, and a wait for a silent worker ends
    STOP_GRACE_S after `stopping()` (the run's SIGTERM) turns true."""
    if len(seeds) == 1:
        return SyncVectorEnv([functools.partial(make_env, name, seed=seeds[0], **kwargs)],
                             autoreset_mode=AutoresetMode.SAME_STEP)
    check_rendering()  # here, once: the fork server and the workers inherit the answer instead of each probing it
    context = multiprocessing.get_context(START_METHOD)
    if START_METHOD == "forkserver":  # takes effect when the fork server starts (the first vector env of a process)
        context.set_forkserver_preload(forkserver_preload(name))
        start_fork_server_ignoring_ctrl_c()
    env_fns = [functools.partial(make_env_in_worker, name, os.getpid(), seed=seed, **kwargs) for seed in seeds]
    try:
        envs = WorkerEnvs(name, seeds, env_fns, stopping, context=START_METHOD, autoreset_mode=AutoresetMode.SAME_STEP,
                          worker=quiet_worker)
    except (EOFError, ConnectionError) as error:  # a worker ended before answering: make_env_in_worker said why
        raise EnvWorkerError(f"an env worker of {name} could not build its env (the worker's reason is on stderr "
                             f"above, unless a signal killed it); {type(error).__name__} from the worker's pipe") from None
    if pin and hasattr(os, "sched_getaffinity"):  # Linux
        cpu_sets = worker_cpus(len(seeds), sorted(os.sched_getaffinity(0)))
        if cpu_sets is not None:
            pin_workers(envs, cpu_sets)
    return envs


def forkserver_preload(name: str) -> list[str]:
    """The modules the fork server imports for every worker: task `name`'s suite too, unless MUJOCO_GL is egl,
    where importing dm_control opens an EGL display that no forked worker can make a context on."""
    modules = ["__main__", "finetune.envs"]
    if os.environ.get("MUJOCO_GL") != "egl":
        modules.append(suite_module(name).__name__)
    return modules


def start_fork_server_ignoring_ctrl_c() -> None:
    """Start the fork server (where it is not running yet) with SIGINT ignored, which it inherits through its exec:
    a terminal's Ctrl-C reaches the whole process group, and one during the server's imports of the suite (seconds)
    printed its KeyboardInterrupt traceback below the learner's line. (The server ignores SIGINT itself, but only
    after those imports.) The learner ignores SIGINT only while it starts the server, a fork and an exec."""
    if threading.current_thread() is not threading.main_thread():  # where no signal handler can be set
        multiprocessing.forkserver.ensure_running()
        return
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        multiprocessing.forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, before)


def make_env_in_worker(name: str, parent_pid: int, seed: int, **kwargs):
    """`make_env` in an env worker process: a failure ends the worker with one line on stderr instead of a
    traceback per worker (the parent then raises EnvWorkerError); `os._exit` skips the half-built renderer's
    finalisers, which would print tracebacks of their own. The worker ignores SIGINT (module docstring). In the
    parent (AsyncVectorEnv builds env 0 there too, for its spaces) a failure is raised as usual."""
    in_worker = os.getpid() != parent_pid
    if in_worker:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        return make_env(name, seed=seed, **kwargs)
    except Exception as error:
        if not in_worker:
            raise
        reason = " ".join(str(error).split())[:400]  # EGLError's text spans many lines
        print(f"env worker of {name} (seed {seed}, pid {os.getpid()}): {type(error).__name__}: {reason}",
              file=sys.stderr, flush=True)
        os._exit(1)


class LearnerPipe:
    """A worker's end of its pipe to the learner, which ends the worker (exit status 0) when the learner is gone."""

    def __init__(self, connection: multiprocessing.connection.Connection):
        self.connection = connection

    def recv(self):
        try:
            return self.connection.recv()
        except (EOFError, ConnectionResetError):
            os._exit(0)

    def send(self, message) -> None:
        try:
            self.connection.send(message)
        except (BrokenPipeError, ConnectionResetError):
            os._exit(0)

    def __getattr__(self, name: str):
        return getattr(self.connection, name)


def quiet_worker(index: int, env_fn: Callable, pipe: multiprocessing.connection.Connection, *args) -> None:
    """gymnasium's worker loop, ended by a learner gone (kill -9) at once and without a word. gymnasium's own put
    the error on its error queue, which nobody reads any more: once that queue's pipe was full its feeder thread
    held the worker's exit for ever (38 of 100 workers, and the fork server, stayed), and each worker printed the
    traceback of the BrokenPipeError its report met (2,111 lines of stderr from 100 workers)."""
    _async_worker(index, env_fn, LearnerPipe(pipe), *args)


@contextlib.contextmanager
def closing_envs(envs: VectorEnv) -> Iterator[VectorEnv]:
    """Close `envs` when the block ends. When it ends by an exception (Ctrl-C while the workers step, a worker that
    died or stopped answering), the workers are ended without waiting for the step in flight (SIGTERM, then SIGKILL
    for one that outlives it by a few seconds: a stopped process), gymnasium's warning about that call is silenced,
    and a worker that is gone already (killed) cannot turn the exception into a BrokenPipeError."""
    try:
        yield envs
    except BaseException:
        if isinstance(envs, WorkerEnvs):  # ended here first: gymnasium's close would wait on each for ever
            end_workers(envs.processes)
        with warnings.catch_warnings(), contextlib.suppress(OSError, EOFError, EnvWorkerError):
            warnings.simplefilter("ignore")
            envs.close(terminate=True)
        envs.closed = True  # also where close stopped at a dead worker's pipe: no __del__ tries again
        raise
    envs.close()


def end_workers(processes: list[multiprocessing.Process], grace: float = 5.0) -> None:
    """SIGTERM each worker process, and SIGKILL those still there after `grace` seconds; wait for all of them."""
    for process in processes:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + grace
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join()


def worker_cpus(num_envs: int, cpus: list[int]) -> list[set[int]] | None:
    """The CPUs of each of `num_envs` workers on the usable `cpus`: an equal share of every CPU, or None."""
    if num_envs % len(cpus) == 0:  # N = k·C: k workers on each CPU
        return [{cpus[i % len(cpus)]} for i in range(num_envs)]
    if len(cpus) % num_envs == 0:  # C = k·N: k CPUs for each worker
        block = len(cpus) // num_envs
        return [set(cpus[i * block:(i + 1) * block]) for i in range(num_envs)]
    return None  # uneven: a lock-step batch would wait for the workers that share a CPU


def pin_workers(envs: AsyncVectorEnv, cpu_sets: list[set[int]]) -> None:
    """Pin every thread of worker i (started, so its renderer's threads exist) to `cpu_sets[i]`."""
    for index, (process, cpus) in enumerate(zip(envs.processes, cpu_sets)):
        try:
            for thread in os.listdir(f"/proc/{process.pid}/task"):
                with contextlib.suppress(ProcessLookupError):  # a thread that ended since the listing
                    os.sched_setaffinity(int(thread), cpus)
        except OSError as error:  # no /proc, or a sandbox that forbids it: the envs still work, unpinned
            warnings.warn(f"could not pin env worker {index} (pid {process.pid}) to CPUs {sorted(cpus)}: {error}; "
                          "it and the workers after it run unpinned (setting pin_envs: false skips pinning)", stacklevel=2)
            return
