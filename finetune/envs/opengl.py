"""Which OpenGL platform MuJoCo renders with (`MUJOCO_GL`), decided before anything imports mujoco.

- A `MUJOCO_GL` the user set always wins.
- Where an NVIDIA GPU is visible, `egl` renders on it (tens of times faster than software rendering),
  if an EGL context can actually be made: that is probed once, in a subprocess (about a second), so a
  broken EGL install cannot take the training process down, and the subprocesses this process starts
  (env workers) inherit the answer through the environment. When the probe fails, a warning says why.
- Everywhere else `osmesa` (Mesa's software rasteriser; Debian package `libosmesa6`).

Whatever is in force, the first env made checks once that it can render (a frame drawn in a subprocess, a
few tenths of a second), so a setting that cannot (`glfw` without a display, a typo, a missing library) is
refused in one line instead of failing deep inside MuJoCo.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

from finetune.envs.base import EnvSettingError

# draws one frame: a GL context alone "works" under glfw without a display, and rendering then fails
RENDER_PROBE = ("import mujoco; model = mujoco.MjModel.from_xml_string('<mujoco/>'); renderer = mujoco.Renderer(model, 8, 8); "
                "renderer.update_scene(mujoco.MjData(model)); renderer.render(); renderer.close()")
CHECKED = "HAUWM_MUJOCO_GL_CHECKED"  # the platforms known to render (`platforms`); env worker processes inherit it


class RenderingError(EnvSettingError):
    """MuJoCo cannot render with the MUJOCO_GL set; the message says what to set instead."""


def nvidia_gpu_visible() -> bool:
    """An NVIDIA device node is there and CUDA_VISIBLE_DEVICES does not hide every GPU."""
    if os.environ.get("CUDA_VISIBLE_DEVICES") in ("", "-1"):
        return False
    return any(Path("/dev").glob("nvidia[0-9]*"))


def probe(platform: str, timeout: float = 60.0) -> str | None:
    """Render a frame with MuJoCo under MUJOCO_GL=`platform` in a fresh interpreter: None if that works, else why
    not (GLFW's own complaint where it has one: its later errors only say that no context exists)."""
    env = {**os.environ, "MUJOCO_GL": platform}
    if platform in ("egl", "osmesa"):  # as finetune.envs sets it: a user's own setting is kept, and probed with
        env.setdefault("PYOPENGL_PLATFORM", platform)
    try:
        result = subprocess.run([sys.executable, "-c", RENDER_PROBE], env=env, capture_output=True, text=True,
                                timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"rendering a frame took over {timeout:.0f} s"
    if result.returncode == 0:
        return None
    lines = result.stderr.strip().splitlines()
    glfw = [match[1] for line in lines if (match := re.search(r"GLFWError: \(\d+\) b'(.*)'", line))]
    if glfw:
        return glfw[0]
    return lines[-1] if lines else f"exit status {result.returncode}"


def platforms() -> str:
    """MUJOCO_GL and PYOPENGL_PLATFORM as they are now: what a check of rendering holds for (a child process started
    with others must check again)."""
    return f"{os.environ.get('MUJOCO_GL', '')}/{os.environ.get('PYOPENGL_PLATFORM', '')}"


def check_rendering() -> None:
    """Once per process tree and platform: raise RenderingError if the MUJOCO_GL in force cannot render a frame."""
    if os.environ.get(CHECKED) == platforms():
        return
    platform = os.environ.get("MUJOCO_GL", "")
    failure = probe(platform)
    if failure is not None:
        raise RenderingError(f"MuJoCo cannot render with MUJOCO_GL={platform!r} ({failure}): unset MUJOCO_GL and HAUWM "
                             "picks egl on an NVIDIA GPU where it works, osmesa elsewhere (Debian package libosmesa6)")
    os.environ[CHECKED] = platforms()


def choose_mujoco_gl() -> str:
    """`egl` on a machine with an NVIDIA GPU where EGL works, else `osmesa` (see the module docstring)."""
    if not nvidia_gpu_visible():
        return "osmesa"
    failure = probe("egl")
    if failure is None:
        return "egl"
    warnings.warn(
        f"an NVIDIA GPU is visible but MuJoCo could not make an EGL context ({failure}); rendering on the CPU "
        "with OSMesa, which is far slower. Install the NVIDIA EGL library (libnvidia-gl / libegl1) or set "
        "MUJOCO_GL yourself (MUJOCO_GL=osmesa silences this).",
        stacklevel=3,
    )
    return "osmesa"
