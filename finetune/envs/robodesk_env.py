"""RoboDesk 1.0.0 from pixels (push_green, open_slide, ...).

`robodesk.RoboDesk(task, reward='dense')` is an old-`gym` env with three quirks handled here:

- it renders a frame inside every `step` (and renders with Pillow's removed `Image.ANTIALIAS`): we
  replace its `_get_obs` so the simulator steps without rendering, and render once per agent step
  ourselves with the same camera, crop and resize (LANCZOS, which `ANTIALIAS` was an alias of),
  through one reusable camera that fast rendering can strip down;
- it draws initial states from numpy's global generator: we give each env its own generator and
  swap it in around `reset`, so seeding is per env and touches nobody else's random state;
- its episode end is a `done` flag; we turn its limit off and let `PixelEnv` truncate.

Defaults: 500 simulator steps per episode (Table 4's returns are over 500 steps of a 0-1 dense
reward) with action repeat 2: RoboDesk's end-effector moves 1 cm per step, so two repeats lose little
control, and they halve the rendering, which dominates RoboDesk's cost. `info["success"]` is
RoboDesk's own success test for the task.
"""

from __future__ import annotations

import contextlib
import io

import numpy as np
from dm_control.mujoco import engine
from PIL import Image

from finetune.envs.base import PixelEnv
from finetune.envs.rendering import FAST_RENDER_FLAGS_OFF, disable_multisampling

with contextlib.redirect_stderr(io.StringIO()):  # old gym prints a deprecation notice on import
    import robodesk

EPISODE_SIM_STEPS = 500
DEFAULT_ACTION_REPEAT = 2
# RoboDesk.render's camera: a free camera looking down at the desk, 120 px, then cropped and resized.
CAMERA = {"distance": 1.8, "azimuth": 90.0, "elevation": -60.0, "lookat": (0.0, 0.535, 1.1)}
RENDER_SIZE = 120
CROP_BOX = (16.75, 25.0, 105.0, 88.75)
TASKS = ("push_green", "open_slide")  # the paper's two; RoboDesk defines more


def tasks() -> dict[str, str]:
    """The paper's RoboDesk tasks as `robodesk_<task>` -> RoboDesk task name."""
    return {f"robodesk_{task}": task for task in TASKS}


class RoboDeskEnv(PixelEnv):
    """One RoboDesk task rendered to `uint8 [3, H, W]` frames."""

    def __init__(
        self,
        name: str,
        task: str,
        seed: int,
        image_size: int,
        action_repeat: int,
        time_limit: int,
        fast_render: bool,
    ) -> None:
        self._env = robodesk.RoboDesk(task=task, reward="dense", action_repeat=1, episode_length=None)
        self._env._get_obs = lambda: None  # no rendering inside RoboDesk's step (see module docstring)
        self._task = task
        self._rng = np.random.RandomState(seed)
        bound = np.ones(self._env.action_dim)  # RoboDesk's actions are already in [-1, 1]
        super().__init__(name, seed, -bound, bound, image_size, action_repeat, time_limit)
        physics = self._env.physics
        if fast_render:
            disable_multisampling(physics.model)
        self._camera = engine.MovableCamera(physics, RENDER_SIZE, RENDER_SIZE)
        self._camera.set_pose(CAMERA["lookat"], CAMERA["distance"], CAMERA["azimuth"], CAMERA["elevation"])
        self._render_flags = FAST_RENDER_FLAGS_OFF if fast_render else {}

    def _seed_sim(self, seed: int) -> None:
        self._rng.seed(seed)

    def _reset_sim(self) -> None:
        global_state = np.random.get_state()
        np.random.set_state(self._rng.get_state())
        try:
            self._env.reset()
        finally:
            self._rng.set_state(np.random.get_state())
            np.random.set_state(global_state)

    def _step_sim(self, action: np.ndarray) -> tuple[float, bool, bool, bool]:
        _, reward, _, _ = self._env.step(action)
        success = bool(self._env.reward_functions[self._task]("success"))
        return float(reward), False, False, success

    def _render_frame(self) -> np.ndarray:
        frame = self._camera.render(render_flag_overrides=self._render_flags)  # [120, 120, 3]
        image = Image.fromarray(frame).crop(CROP_BOX).resize((self.image_size,) * 2, Image.LANCZOS)
        return np.asarray(image)  # [H, W, 3]

    def _close_sim(self) -> None:
        self._env.physics.free()  # frees the OpenGL context now, not in a noisy atexit hook


ENV_CLASS = RoboDeskEnv
