"""Training envs as one batch (`num_envs`): one env reproduces what a seed gave before, several envs keep
their episodes apart, and the vector env resets an env inside the step that ends its episode."""

from __future__ import annotations

import contextlib
import gc
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from finetune.config import load_config
from finetune.envs import make_env, opengl
from finetune.envs.vector import EnvWorkerError, closing_envs, forkserver_preload, make_vector_env, worker_cpus
from finetune.run_dir import CHECKPOINT
from finetune.train import ENV_SEED_STRIDE, train
from test_finetune_runs import rows  # noqa: I001 (tests/finetune/test_finetune_runs.py)

# `configs/finetune/demo.yaml` with the tests' export (conftest.py), device cpu, 1 thread: (env_step, return) per
# training episode and per evaluation; (env_step, updates, model_loss, actor_loss, critic_loss, imagined_return)
# per train.csv row. First recorded on main at 073e62e (before num_envs and compile existed; an AMD EPYC with
# AVX2), which the one-env loop reproduced exactly, also on the Intel Xeon development box; recorded again there
# when the frozen stream's first step got the gap-0 embedding (the only change: every figure within 0.2%), and on
# 2026-11-27 when evaluations got a torch RNG of their own (an AMD EPYC with AVX2): the figures up to the first
# evaluation (env step 300) stayed, the evaluations and what follows them moved, as the training's random stream no
# longer passes through an evaluation. Another CPU's kernels round differently: on an AMD EPYC with AVX-512 (torch
# 2.14.1 and 2.11.0 alike) the last evaluation's return moved 5.7e-5 relative, every other figure less than 3e-6.
# So figures must agree to 3e-4 relative: five times that rounding, and below the 0.2% that even the small change
# above moved figures by. Recorded again (an AMD EPYC with AVX-512, 2026-11-27) when the prefill's random actions got
# a stream of their own (finetune/envs/base.py, `action_seed`): every figure moved, as the actions did.
RECORDED = {
    "episodes": [(100, 0.3326647328162145), (200, 0.18120641345950944), (300, 0.29327863815115374),
                 (400, 0.03022751847286804), (500, 0.15324504014739287), (600, 0.018134599268214858)],
    "eval": [(300, 1.532625480419938), (600, 1.922572189859693)],
    "train": [(216, 1, 920.5577392578125, -0.33078140020370483, 0.2242148220539093, 0.3423909544944763),
              (300, 6, 768.266552734375, -0.29955561757087706, 0.18786824643611907, 0.3105583190917969),
              (400, 12, 575.819580078125, -0.23157686491807303, 0.1343910532693068, 0.24053492645422617),
              (500, 18, 435.157709757487, -0.18958216905593872, 0.11524501318732898, 0.19764507561922073),
              (600, 25, 337.73304530552457, -0.17442241949694498, 0.08378960405077253, 0.18200143533093588)],
}
COLUMNS = {"episodes": ("env_step", "return"), "eval": ("env_step", "return"),
           "train": ("env_step", "updates", "model_loss", "actor_loss", "critic_loss", "imagined_return")}


def test_one_env_reproduces_the_figures_recorded_before_num_envs_existed(export_dir, tmp_path):
    torch.set_num_threads(1)
    cfg = load_config("configs/finetune/demo.yaml", dict(logdir=str(tmp_path / "run"), device="cpu", threads=1))
    assert cfg.num_envs == 1 and cfg.compile == "auto"  # the defaults: one env in this process, eager on the CPU
    train(cfg, export_dir, progress=False)
    for kind, recorded in RECORDED.items():
        logged = [tuple(float(row[column]) for column in COLUMNS[kind]) for row in rows(tmp_path / "run" / f"{kind}.csv")]
        assert logged == [pytest.approx(values, rel=3e-4, abs=1e-9) for values in recorded], kind


def replay_episodes(logdir):
    episodes = []
    for path in sorted((logdir / "replay").glob("*.npz")):
        with np.load(path) as data:
            episodes.append({key: data[key] for key in ("obs", "action", "reward")})
    return episodes


def test_parallel_envs_keep_their_episodes_apart_and_resume(export_dir, tiny_config, tmp_path):
    """Random-action episodes of 2 envs in worker processes equal, entry for entry, those of single envs with
    each env's seed; then the run goes on with updates and resumes."""
    settings = dict(task="dmc_cartpole_swingup", action_repeat=2, time_limit=10, fast_render=True, prefill=80,
                    train_every=10, eval_every=1000, eval_episodes=1, log_every=40, checkpoint_every=1000)
    single = [tiny_config(**settings, seed=seed, steps=40, logdir=str(tmp_path / f"single{seed}"))
              for seed in (0, ENV_SEED_STRIDE)]
    for cfg in single:
        train(cfg, export_dir, progress=False)
    parallel = tiny_config(**settings, seed=0, steps=80, num_envs=2, logdir=str(tmp_path / "parallel"))
    train(parallel, export_dir, progress=False)

    episodes = replay_episodes(tmp_path / "parallel")  # envs 0 and 1 end their episodes in the same steps
    expected = [replay_episodes(tmp_path / "single0"), replay_episodes(tmp_path / f"single{ENV_SEED_STRIDE}")]
    assert len(episodes) == 4 and all(len(e) == 2 for e in expected)
    for index, episode in enumerate(episodes):  # order: env 0, env 1, env 0, env 1
        for key, value in episode.items():
            np.testing.assert_array_equal(value, expected[index % 2][index // 2][key], err_msg=f"{index} {key}")

    logdir = tmp_path / "parallel"
    train(load_config(logdir / "config.yaml", dict(steps=160)), export_dir, progress=False)  # resumes at 80
    counters = torch.load(logdir / CHECKPOINT, weights_only=True)["counters"]
    assert counters["env_step"] == 160 and counters["episodes"] == 8
    assert counters["updates"] == (160 - 80) // 10  # every update due, also those due at the last step
    assert len(replay_episodes(logdir)) == 8
    assert [int(row["env_step"]) for row in rows(logdir / "episodes.csv")] == [40, 40, 80, 80, 120, 120, 160, 160]


def test_vector_env_resets_an_env_in_the_step_that_ends_its_episode():
    """SAME_STEP autoreset: the last frame of the episode in info["final_obs"], the next episode's first in obs;
    every env steps exactly as a single env with its seed."""
    seeds, actions = [3, 4], np.random.default_rng(0).uniform(-1, 1, (3, 2, 1)).astype(np.float32)
    envs = make_vector_env("dmc_cartpole_swingup", seeds, fast_render=True, time_limit=3)
    singles = [make_env("dmc_cartpole_swingup", seed=seed, fast_render=True, time_limit=3) for seed in seeds]
    try:
        obs, _ = envs.reset()
        for i, env in enumerate(singles):
            np.testing.assert_array_equal(obs[i], env.reset()[0])
        for t in range(3):
            obs, rewards, terminated, truncated, info = envs.step(actions[t])
            assert not terminated.any() and list(truncated) == [t == 2] * 2
            for i, env in enumerate(singles):
                frame, reward, _, _, _ = env.step(actions[t, i])
                assert rewards[i] == reward
                np.testing.assert_array_equal(info["final_obs"][i] if t == 2 else obs[i], frame)
        for i, env in enumerate(singles):  # the next episode has begun
            np.testing.assert_array_equal(obs[i], env.reset()[0])
        assert not np.array_equal(obs[0], obs[1])  # two seeds, two start states
    finally:
        envs.close()
        for env in singles:
            env.close()


def test_worker_cpus_give_every_cpu_an_equal_share_or_pin_nothing():
    assert worker_cpus(2, [0, 1]) == [{0}, {1}]
    assert worker_cpus(4, [0, 1]) == [{0}, {1}, {0}, {1}]
    assert worker_cpus(2, [2, 5, 7, 9]) == [{2, 5}, {7, 9}]  # the usable CPUs, as taskset or SLURM leave them
    assert worker_cpus(1, [3, 4]) == [{3, 4}]
    assert worker_cpus(3, [0, 1]) is None and worker_cpus(3, [0, 1, 2, 3]) is None


def thread_cpus(pid: int) -> set[frozenset[int]]:
    """The CPU sets of every thread of process `pid`."""
    return {frozenset(os.sched_getaffinity(int(t))) for t in os.listdir(f"/proc/{pid}/task")}


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="CPU affinity is Linux-only")
def test_env_workers_are_pinned_with_all_their_threads_and_the_learner_is_not():
    usable = os.sched_getaffinity(0)
    for pin in (True, False):
        envs = make_vector_env("dmc_cartpole_swingup", [0, 1], pin=pin, fast_render=True, time_limit=3)
        try:
            envs.reset()
            envs.step(np.zeros((2, 1), np.float32))  # the renderer has made its threads
            expected = (pin and worker_cpus(2, sorted(usable))) or [usable, usable]  # None: an odd number of CPUs
            for process, cpus in zip(envs.processes, expected):
                assert thread_cpus(process.pid) == {frozenset(cpus)}, (pin, process.pid)
            assert os.sched_getaffinity(0) == usable
        finally:
            envs.close()


def test_mujoco_gl_is_egl_only_with_a_gpu_where_egl_works(monkeypatch):
    monkeypatch.setattr(opengl, "nvidia_gpu_visible", lambda: False)
    assert opengl.choose_mujoco_gl() == "osmesa"
    monkeypatch.setattr(opengl, "nvidia_gpu_visible", lambda: True)
    monkeypatch.setattr(opengl, "probe", lambda platform: None)
    assert opengl.choose_mujoco_gl() == "egl"
    monkeypatch.setattr(opengl, "probe", lambda platform: "eglInitialize failed")
    with pytest.warns(UserWarning, match="eglInitialize failed.*OSMesa"):
        assert opengl.choose_mujoco_gl() == "osmesa"


def test_the_rendering_probe_reports_why_it_failed(monkeypatch):
    monkeypatch.setattr(opengl, "RENDER_PROBE", "raise SystemExit('no EGL device')")
    assert opengl.probe("egl") == "no EGL device"


def test_the_rendering_probe_keeps_the_users_pyopengl_platform(monkeypatch):
    """The probe renders as this process will: MUJOCO_GL=egl with PYOPENGL_PLATFORM=osmesa cannot."""
    monkeypatch.setenv("PYOPENGL_PLATFORM", "osmesa")
    assert "PYOPENGL_PLATFORM" in (opengl.probe("egl") or "")


@pytest.mark.parametrize(("setting", "reason"), [("glfw", "The DISPLAY environment variable is missing"),
                                                 ("bogus", "invalid value for environment variable MUJOCO_GL")])
def test_a_users_mujoco_gl_that_cannot_render_is_refused_in_one_line(export_dir, tmp_path, setting, reason):
    env = {key: value for key, value in os.environ.items()
           if key not in ("DISPLAY", "WAYLAND_DISPLAY", "PYOPENGL_PLATFORM", opengl.CHECKED)}
    env["MUJOCO_GL"] = setting
    result = subprocess.run([sys.executable, "-m", "hauwm.cli", "finetune", "--config", "configs/finetune/demo.yaml",
                             "--pretrained", str(export_dir), "--logdir", str(tmp_path / "run"), "--no-progress"],
                            env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert f"MuJoCo cannot render with MUJOCO_GL={setting!r}" in result.stderr and reason in result.stderr
    assert "unset MUJOCO_GL" in result.stderr


@pytest.mark.parametrize("user_setting", ["osmesa", "egl"])
def test_a_users_mujoco_gl_wins(user_setting):
    env = {key: value for key, value in os.environ.items() if key != "PYOPENGL_PLATFORM"}
    env["MUJOCO_GL"] = user_setting
    code = "import os, finetune.envs; print(os.environ['MUJOCO_GL'], os.environ['PYOPENGL_PLATFORM'])"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == [user_setting, user_setting]


def test_a_pyopengl_platform_of_the_image_follows_the_mujoco_gl_chosen():
    """PYOPENGL_PLATFORM=egl (GPU images set it) on a machine where osmesa was chosen broke every env with a message to
    unset MUJOCO_GL, which was not set (found by a review): HAUWM's choice of MUJOCO_GL now sets both."""
    env = {key: value for key, value in os.environ.items() if key not in ("MUJOCO_GL", opengl.CHECKED)}
    env["PYOPENGL_PLATFORM"] = "egl" if not opengl.nvidia_gpu_visible() else "osmesa"  # the other one
    code = "import os, finetune.envs; print(os.environ['MUJOCO_GL'], os.environ['PYOPENGL_PLATFORM'])"
    chosen, pyopengl = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                      check=True).stdout.split()
    assert chosen == pyopengl


def test_a_rendering_check_holds_only_for_the_platforms_it_checked(monkeypatch):
    """The mark of a check was "1", inherited by every child: one started with another MUJOCO_GL skipped the check and
    failed deep inside MuJoCo (found by a review)."""
    monkeypatch.setenv(opengl.CHECKED, "1")  # as a parent checked under osmesa wrote it
    monkeypatch.setenv("MUJOCO_GL", "bogus")
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    with pytest.raises(opengl.RenderingError, match="MuJoCo cannot render with MUJOCO_GL='bogus'"):
        opengl.check_rendering()


# Every env worker fails to build its env, as each did with EGL_BAD_ALLOC on an H200 before forkserver_preload: the
# script's top level runs again in the fork server (a process other than the parent), where it breaks make_env.
WORKERS_FAIL = """
import os
from finetune.envs import vector
PARENT = os.environ.setdefault("PARENT_PID", str(os.getpid()))
if str(os.getpid()) != PARENT:
    def broken(name, seed, **kwargs):
        raise RuntimeError("EGLError(\\n\\terr = EGL_BAD_ALLOC,\\n\\tbaseOperation = eglCreateContext)")
    vector.make_env = broken
if __name__ == "__main__":
    try:
        vector.make_vector_env("dmc_cartpole_swingup", [0, 1], fast_render=True, time_limit=3)
    except vector.EnvWorkerError as error:
        print(f"refused: {error}")
"""


def test_an_env_worker_that_cannot_build_its_env_ends_with_one_line_and_the_parent_names_the_task(tmp_path):
    script = tmp_path / "workers_fail.py"
    script.write_text(WORKERS_FAIL)
    repo = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([repo, os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("refused: an env worker of dmc_cartpole_swingup could not build its env")
    assert "Traceback" not in result.stderr
    reasons = [line for line in result.stderr.splitlines() if line.startswith("env worker of dmc_cartpole_swingup")]
    assert reasons and all(line.endswith("RuntimeError: EGLError( err = EGL_BAD_ALLOC, baseOperation = eglCreateContext)")
                           for line in reasons), result.stderr


def test_the_fork_server_imports_the_suite_only_where_no_egl_display_comes_with_it(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    assert forkserver_preload("dmc_cartpole_swingup") == ["__main__", "finetune.envs", "finetune.envs.dmc_env"]
    monkeypatch.setenv("MUJOCO_GL", "egl")  # importing dm_control would open an EGL display in the fork server
    assert forkserver_preload("dmc_cartpole_swingup") == ["__main__", "finetune.envs"]


def test_env_workers_ignore_ctrl_c_so_the_learner_decides_what_an_interrupt_does():
    envs = make_vector_env("dmc_cartpole_swingup", [0, 1], pin=False, fast_render=True, time_limit=3)
    with closing_envs(envs):
        envs.reset()
        for process in envs.processes:  # what a terminal's Ctrl-C sends the whole process group
            os.kill(process.pid, signal.SIGINT)
        envs.step(np.zeros((2, 1), np.float32))  # the workers are still there and answer
        assert all(process.is_alive() for process in envs.processes)
    assert not any(process.is_alive() for process in envs.processes)


@pytest.mark.parametrize("worker_killed", [False, True])
def test_an_interrupt_while_the_workers_step_ends_them_and_stays_an_interrupt(worker_killed):
    """Ctrl-C between step_async and step_wait: no warning about the pending step, and a worker killed meanwhile
    must not turn the KeyboardInterrupt into a BrokenPipeError (which `hauwm` reported as a closed stdout)."""
    envs = make_vector_env("dmc_cartpole_swingup", [0, 1], pin=False, fast_render=True, time_limit=3)
    envs.reset()
    processes = envs.processes
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(KeyboardInterrupt), closing_envs(envs):
            envs.step_async(np.zeros((2, 1), np.float32))
            if worker_killed:
                os.kill(processes[0].pid, signal.SIGKILL)
                processes[0].join()
            raise KeyboardInterrupt
        assert envs.closed  # so its __del__ does not try again, with the warning and a traceback of its own
        del envs
        gc.collect()
    assert not [w for w in caught if "pending call" in str(w.message)]
    for process in processes:
        process.join(timeout=10)
        assert not process.is_alive()


def test_an_env_worker_that_dies_mid_run_is_named_with_its_seed_and_cause():
    """The out-of-memory killer (SIGKILL) ends env worker 1 between steps: the next step names the worker, its
    seed and the likely cause instead of a bare EOFError from its pipe."""
    envs = make_vector_env("dmc_cartpole_swingup", [0, 7], pin=False, fast_render=True, time_limit=3)
    with pytest.raises(EnvWorkerError, match=r"env worker 1 of dmc_cartpole_swingup \(seed 7, pid \d+\) died: "
                                             r"killed by SIGKILL, most likely by the kernel's out-of-memory killer"), \
            closing_envs(envs):
        envs.reset()
        os.kill(envs.processes[1].pid, signal.SIGKILL)
        envs.processes[1].join()
        envs.step(np.zeros((2, 1), np.float32))
    assert not any(process.is_alive() for process in envs.processes)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("stopping", [False, True])
def test_an_env_worker_that_stops_answering_is_named_with_its_state_and_ended(stopping):
    """A worker stopped by SIGSTOP (or stuck in its renderer) hung the run for ever: step_wait waited on its pipe, and
    Ctrl-C or SIGTERM then hung in closing_envs, whose SIGTERM a stopped process does not act on. The wait now gives
    up after answer_timeout seconds, or STOP_GRACE_S once the run is asked to stop, and closing_envs kills it."""
    stop_requested = [False]
    envs = make_vector_env("dmc_cartpole_swingup", [0, 7], pin=False, stopping=lambda: stop_requested[0],
                           fast_render=True, time_limit=3)
    envs.answer_timeout = 1e9 if stopping else 2.0
    processes = envs.processes
    try:
        with pytest.raises(EnvWorkerError, match=r"env worker 1 of dmc_cartpole_swingup \(seed 7, pid \d+\) has not "
                                                 r"answered its step in \d+ s: its process is stopped \(SIGSTOP, or a "
                                                 r"debugger\): `kill -CONT \d+` lets it go on"), closing_envs(envs):
            envs.reset()
            os.kill(processes[1].pid, signal.SIGSTOP)
            stop_requested[0] = stopping
            started = time.monotonic()
            envs.step(np.zeros((2, 1), np.float32))
        assert time.monotonic() - started < 30
        for process in processes:
            assert not process.is_alive()
    finally:
        for process in processes:
            with contextlib.suppress(ProcessLookupError):
                os.kill(process.pid, signal.SIGKILL)


LEARNER_KILLED = """
import os, signal
import numpy as np
from finetune.envs.vector import make_vector_env
if __name__ == "__main__":
    envs = make_vector_env("dmc_cartpole_swingup", [0, 1, 2, 3], pin=False, fast_render=True, time_limit=3)
    envs.reset()
    print(*[process.pid for process in envs.processes], flush=True)
    envs.step_async(np.zeros((4, 1), np.float32))
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_dead_env_worker_is_named_with_the_seed_of_its_episode_after_a_reseeding_reset():
    """A reseeding run (imitation) resets its envs with each episode's seed: a worker that died was named with the seed
    it was built with, which does not reproduce its episode (found by a review)."""
    envs = make_vector_env("dmc_cartpole_swingup", [0, 7], pin=False, fast_render=True, time_limit=3)
    with pytest.raises(EnvWorkerError, match=r"env worker 1 of dmc_cartpole_swingup \(seed 123, pid \d+\) died"), \
            closing_envs(envs):
        envs.reset(seed=[5, 123])
        envs.reset(seed=[9, 456], options={"reset_mask": np.array([True, False])})  # env 1 plays on from 123
        os.kill(envs.processes[1].pid, signal.SIGKILL)
        envs.processes[1].join()
        envs.step(np.zeros((2, 1), np.float32))


def test_env_workers_whose_learner_is_killed_end_at_once_and_without_a_word(tmp_path):
    """A learner killed (kill -9, the out-of-memory killer) left each worker printing ~20 lines of BrokenPipeError
    traceback; with ~100 workers some never ended (their error queue full, with no learner to read it)."""
    script = tmp_path / "learner_killed.py"
    script.write_text(LEARNER_KILLED)
    repo = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([repo, os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == -signal.SIGKILL
    workers = [int(pid) for pid in result.stdout.split()]
    deadline = time.monotonic() + 30
    while any(Path(f"/proc/{pid}").exists() for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [pid for pid in workers if Path(f"/proc/{pid}").exists()]
    assert "Traceback" not in result.stderr, result.stderr[-2000:]


# The fork server imports the preloaded modules first (the suite's: seconds); this one records how SIGINT is handled
# while it does.
SIGINT_AT_PRELOAD = """
import os, sys
from finetune.envs import vector
if __name__ == "__main__":
    vector.forkserver_preload = lambda name: ["__main__", "sigint_probe"]
    envs = vector.make_vector_env("dmc_cartpole_swingup", [0, 1], pin=False, fast_render=True, time_limit=3)
    envs.close()
"""


def test_the_fork_server_ignores_ctrl_c_from_its_first_import(tmp_path):
    """A Ctrl-C while the fork server imported the suite printed its KeyboardInterrupt traceback."""
    (tmp_path / "fork_server_ignores.py").write_text(SIGINT_AT_PRELOAD)
    (tmp_path / "sigint_probe.py").write_text("import os, signal\n"
                                              "with open(os.environ['PROBE_OUT'], 'w') as out:\n"
                                              "    out.write(str(signal.getsignal(signal.SIGINT)))\n")  # '1': SIG_IGN
    repo = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([repo, str(tmp_path), os.environ.get("PYTHONPATH", "")]),
           "PROBE_OUT": str(tmp_path / "sigint.txt")}  # the fork server finds sigint_probe on PYTHONPATH
    subprocess.run([sys.executable, str(tmp_path / "fork_server_ignores.py")], env=env, check=True, timeout=300)
    assert (tmp_path / "sigint.txt").read_text() == str(signal.SIG_IGN)
