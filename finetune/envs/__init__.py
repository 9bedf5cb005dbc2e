"""Pixel environments for fine-tuning: DeepMind Control, Meta-World v3 and RoboDesk (paper section 4.3).

    from finetune.envs import make_env
    env = make_env("dmc_cheetah_run", seed=0)          # uint8 [3, 64, 64] frames, actions in [-1, 1]
    obs, info = env.reset()
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

Headless rendering is set up here, before anything imports mujoco: OSMesa by default (Debian package
`libosmesa6`); a user's own `MUJOCO_GL` wins (`egl` renders on the GPU where there is one). The render
thread offloading of dm_control is switched off: each env renders on the thread that uses it, which is
faster and avoids dm_control's failing clean-up at interpreter exit.
"""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
if os.environ["MUJOCO_GL"] in ("osmesa", "egl"):  # PyOpenGL (used by mujoco's Python renderer) must agree
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("DISABLE_RENDER_THREAD_OFFLOADING", "1")

from finetune.envs.references import normalised_return  # noqa: E402
from finetune.envs.registry import PAPER_TASKS, make_env  # noqa: E402

__all__ = ["PAPER_TASKS", "make_env", "normalised_return"]
