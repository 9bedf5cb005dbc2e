"""DeepMind Control Suite from pixels (cheetah_run, walker_run, hopper_hop, quadruped_run, ...).

Settings follow the Dreamer/APV convention the paper builds on: `suite.load(domain, task,
task_kwargs={'random': seed})`, 64x64 frames from camera 0 (camera 2 for quadruped), action repeat 2,
1000 simulator steps per episode (500 agent steps). DMC's own time limit is switched off
(`time_limit=inf`) and `PixelEnv` applies ours, so an episode end is `truncated`, never a terminal;
a real terminal (a DMC step with discount 0) is `terminated`.
"""

from __future__ import annotations

import numpy as np
from dm_control import suite
from dm_control.mujoco import engine

from finetune.envs.base import PixelEnv
from finetune.envs.rendering import FAST_RENDER_FLAGS_OFF, disable_multisampling

# dm-control 1.0.28's quadruped calls np.in1d, which numpy 2.4 removed; np.isin is its documented
# replacement with the same result for these 1-D arrays.
if not hasattr(np, "in1d"):
    np.in1d = np.isin

EPISODE_SIM_STEPS = 1000
DEFAULT_ACTION_REPEAT = 2
CAMERA_IDS = {"quadruped": 2}  # every other domain uses camera 0


def tasks() -> dict[str, tuple[str, str]]:
    """Every DMC task as `dmc_<domain>_<task>` -> (domain, task)."""
    return {f"dmc_{domain}_{task}": (domain, task) for domain, task in suite.ALL_TASKS}


class DMCEnv(PixelEnv):
    """One DMC task rendered to `uint8 [3, H, W]` frames."""

    def __init__(
        self,
        name: str,
        domain_task: tuple[str, str],
        seed: int,
        image_size: int,
        action_repeat: int,
        time_limit: int,
        fast_render: bool,
    ) -> None:
        domain, task = domain_task
        self._env = suite.load(domain, task, task_kwargs={"random": seed, "time_limit": float("inf")})
        spec = self._env.action_spec()
        super().__init__(name, seed, spec.minimum, spec.maximum, image_size, action_repeat, time_limit)
        physics = self._env.physics
        if fast_render:
            disable_multisampling(physics.model)
        self._camera = engine.Camera(physics, image_size, image_size, CAMERA_IDS.get(domain, 0))
        self._render_flags = FAST_RENDER_FLAGS_OFF if fast_render else {}

    def _seed_sim(self, seed: int) -> None:
        self._env.task.random.seed(seed)

    def _reset_sim(self) -> None:
        self._env.reset()

    def _step_sim(self, action: np.ndarray) -> tuple[float, bool, bool, None]:
        time_step = self._env.step(action)
        terminated = time_step.last() and time_step.discount == 0.0
        return float(time_step.reward or 0.0), terminated, time_step.last() and not terminated, None

    def _render_frame(self) -> np.ndarray:
        return self._camera.render(render_flag_overrides=self._render_flags)  # [H, W, 3]

    def _close_sim(self) -> None:
        self._env.physics.free()  # frees the OpenGL context now, not in a noisy atexit hook


ENV_CLASS = DMCEnv
