"""Environment steps per second for every fine-tuning task, with and without `fast_render`.

    python bench/bench_envs.py                           # the paper's ten tasks, about 3 minutes
    python bench/bench_envs.py --tasks dmc_cheetah_run --seconds 10

For each task and rendering mode: build the env (seed 0), reset, take random actions for about
`--seconds` seconds (at least `--min-steps` agent steps, resetting at episode ends), and report agent
steps/s and simulator steps/s (agent steps x action repeat; one 64x64 frame per agent step). The
`diff` column is the mean absolute difference, in grey levels out of 255, between the first frames of
the two modes (same seed, same state): how much fast rendering changes what the agent sees.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from finetune.envs import PAPER_TASKS, make_env  # noqa: E402  (sets MUJOCO_GL before mujoco loads)

from bench.args import duration, task_name  # noqa: E402
from bench.machine import describe_machine  # noqa: E402
from hauwm.arguments import at_least  # noqa: E402


def measure(task: str, fast_render: bool, seconds: float, min_steps: int) -> tuple[float, int, np.ndarray]:
    """-> (agent steps per second, action repeat, first frame uint8 [3, H, W])."""
    env = make_env(task, seed=0, fast_render=fast_render)
    first, _ = env.reset()
    env.step(env.action_space.sample())  # warm-up: first render allocates buffers
    steps, start = 0, time.perf_counter()
    while steps < min_steps or time.perf_counter() - start < seconds:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        steps += 1
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - start)
    action_repeat = env.action_repeat
    env.close()
    return rate, action_repeat, first


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", type=task_name, default=list(PAPER_TASKS),
                        help="env names (default: the paper's ten)")
    parser.add_argument("--seconds", type=duration, default=5.0, help="time per task and mode")
    parser.add_argument("--min-steps", type=at_least(1), default=5, help="agent steps per task and mode at least")
    args = parser.parse_args()

    print(f"machine: {describe_machine()}")
    print(
        f"settings: MUJOCO_GL={os.environ['MUJOCO_GL']}, 64x64 frames, one process, random actions, seed 0, "
        f"{args.seconds:g} s and at least {args.min_steps} agent steps per task and mode; "
        f"mujoco {version('mujoco')}, dm-control {version('dm-control')}, metaworld {version('metaworld')}, "
        f"robodesk {version('robodesk')}"
    )
    rows = []
    for task in tqdm(args.tasks, desc="tasks", unit="task"):
        default_rate, action_repeat, default_frame = measure(task, False, args.seconds, args.min_steps)
        fast_rate, _, fast_frame = measure(task, True, args.seconds, args.min_steps)
        diff = np.abs(default_frame.astype(np.int16) - fast_frame).mean()
        rows.append((task, action_repeat, default_rate, fast_rate, diff))

    print(
        "\n| task | action repeat | agent steps/s | sim steps/s "
        "| fast: agent steps/s | fast: sim steps/s | speed-up | diff |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for task, repeat, default_rate, fast_rate, diff in rows:
        print(
            f"| {task} | {repeat} | {default_rate:.1f} | {default_rate * repeat:.1f} | {fast_rate:.1f} | "
            f"{fast_rate * repeat:.1f} | {fast_rate / default_rate:.1f}x | {diff:.1f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
