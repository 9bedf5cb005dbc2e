"""Several training environments stepped as one batch, with gymnasium's vector API.

    envs = make_vector_env("dmc_cheetah_run", seeds=[0, 1, 2, 3], fast_render=True)
    obs, info = envs.reset()                                  # uint8 [4, 3, 64, 64]
    obs, reward, terminated, truncated, info = envs.step(actions)   # actions [4, A]

- One seed: a `SyncVectorEnv`, the env in this process (what a single env gives, step for step).
- More: an `AsyncVectorEnv`, one worker process per env, so that the envs simulate and render on every
  core at once, also while the learner trains (`step_async`, then `step_wait`). Workers are started
  with the "forkserver" context ("spawn" where there is none): MuJoCo's OpenGL contexts, CUDA and
  threads do not survive `fork`; the fork server imports the suite's modules once, so each worker starts
  from a process that has them already. Frames come back through shared memory.

An env whose episode ends is reset inside that same step (gymnasium's SAME_STEP autoreset): the step
returns the new episode's first frame, and the finished episode's last frame is `info["final_obs"][i]`.
(gymnasium's default, NEXT_STEP, would spend the next step on the reset, with a reward of 0 that no
action earned.)
"""

from __future__ import annotations

import functools
import multiprocessing

from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv, VectorEnv

from finetune.envs.registry import _suite, make_env

START_METHOD = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"


def make_vector_env(name: str, seeds: list[int], **kwargs) -> VectorEnv:
    """`len(seeds)` envs of task `name`, env i built by `make_env(name, seed=seeds[i], **kwargs)`."""
    env_fns = [functools.partial(make_env, name, seed=seed, **kwargs) for seed in seeds]
    if len(env_fns) == 1:
        return SyncVectorEnv(env_fns, autoreset_mode=AutoresetMode.SAME_STEP)
    context = multiprocessing.get_context(START_METHOD)
    if START_METHOD == "forkserver":  # takes effect when the fork server starts (the first vector env of a process)
        context.set_forkserver_preload(["__main__", "finetune.envs", _suite(name).__name__])
    return AsyncVectorEnv(env_fns, context=START_METHOD, autoreset_mode=AutoresetMode.SAME_STEP)
