"""Pixel environments for fine-tuning: DeepMind Control, Meta-World v3 and RoboDesk (paper section 4.3).

    from finetune.envs import make_env
    env = make_env("dmc_cheetah_run", seed=0)          # uint8 [3, 64, 64] frames, actions in [-1, 1]
    obs, info = env.reset()
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

Importing this package sets up headless rendering before anything imports mujoco:

- `MUJOCO_GL`: a user's own setting wins; otherwise `egl` where an NVIDIA GPU is visible and an EGL
  context can be made (probed once in a subprocess, with a warning saying why when it cannot), and
  `osmesa` everywhere else (Debian package `libosmesa6`); either way the first env made checks once that it
  can render a frame, and refuses a setting that cannot in one line; see `opengl.py`;
- dm_control's render-thread offloading is off: each env renders on the thread that uses it, which is
  faster and avoids dm_control's failing clean-up at interpreter exit;
- triton is imported first where it is installed: it and Mesa's software rasteriser (llvmpipe) each
  load LLVM, and loading triton (e.g. through `torch._dynamo`) after an OSMesa or EGL context exists
  crashes the process with a segmentation fault.
"""

import importlib.util
import os
import sys
import warnings

if "MUJOCO_GL" not in os.environ and "mujoco" in sys.modules:
    warnings.warn(
        "mujoco was imported before finetune.envs with MUJOCO_GL unset, so it chose its OpenGL platform "
        "already and headless rendering may fail; set MUJOCO_GL=osmesa (or egl) before starting Python",
        stacklevel=2,
    )
if "MUJOCO_GL" not in os.environ:
    from finetune.envs.opengl import choose_mujoco_gl

    # chosen here: PyOpenGL (mujoco's Python renderer) is told the same platform, over one already set (a GPU image's
    # PYOPENGL_PLATFORM=egl on a CPU box broke every osmesa env)
    os.environ["MUJOCO_GL"] = os.environ["PYOPENGL_PLATFORM"] = choose_mujoco_gl()
elif os.environ["MUJOCO_GL"] in ("osmesa", "egl"):  # the user's own: PyOpenGL must agree, unless they set it too
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
os.environ.setdefault("DISABLE_RENDER_THREAD_OFFLOADING", "1")
if "triton" in sys.modules or importlib.util.find_spec("triton") is None:
    pass
elif "mujoco" in sys.modules and os.environ["MUJOCO_GL"] == "osmesa":  # OSMesa's LLVM is loaded: triton's would crash
    warnings.warn(
        "mujoco was imported before finetune.envs, so OSMesa is loaded and triton (which torch.compile loads) "
        "would crash this process with a segmentation fault if loaded now; it is not loaded: import "
        "finetune.envs before mujoco, dm_control or metaworld to keep torch.compile usable",
        stacklevel=2,
    )
else:
    import triton  # noqa: F401, E402

from finetune.envs.base import EnvSettingError  # noqa: E402
from finetune.envs.references import normalised_return  # noqa: E402
from finetune.envs.registry import PAPER_TASKS, make_env  # noqa: E402

__all__ = ["PAPER_TASKS", "EnvSettingError", "make_env", "normalised_return"]
