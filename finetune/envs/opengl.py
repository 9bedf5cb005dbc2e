"""Which OpenGL platform MuJoCo renders with (`MUJOCO_GL`), decided before anything imports mujoco.

- A `MUJOCO_GL` the user set always wins.
- Where an NVIDIA GPU is visible, `egl` renders on it (tens of times faster than software rendering),
  if an EGL context can actually be made: that is probed once, in a subprocess (about a second), so a
  broken EGL install cannot take the training process down, and the subprocesses this process starts
  (env workers) inherit the answer through the environment. When the probe fails, a warning says why.
- Everywhere else `osmesa` (Mesa's software rasteriser; Debian package `libosmesa6`).
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

EGL_PROBE = "import mujoco; context = mujoco.GLContext(64, 64); context.make_current(); context.free()"


def nvidia_gpu_visible() -> bool:
    """An NVIDIA device node is there and CUDA_VISIBLE_DEVICES does not hide every GPU."""
    if os.environ.get("CUDA_VISIBLE_DEVICES") in ("", "-1"):
        return False
    return any(Path("/dev").glob("nvidia[0-9]*"))


def probe_egl(timeout: float = 60.0) -> str | None:
    """Make a MuJoCo EGL context in a fresh interpreter: None if that works, else the reason it failed."""
    env = {**os.environ, "MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl"}
    try:
        result = subprocess.run([sys.executable, "-c", EGL_PROBE], env=env, capture_output=True, text=True,
                                timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"making an EGL context took over {timeout:.0f} s"
    if result.returncode == 0:
        return None
    lines = result.stderr.strip().splitlines()
    return lines[-1] if lines else f"exit status {result.returncode}"


def choose_mujoco_gl() -> str:
    """`egl` on a machine with an NVIDIA GPU where EGL works, else `osmesa` (see the module docstring)."""
    if not nvidia_gpu_visible():
        return "osmesa"
    failure = probe_egl()
    if failure is None:
        return "egl"
    warnings.warn(
        f"an NVIDIA GPU is visible but MuJoCo could not make an EGL context ({failure}); rendering on the CPU "
        "with OSMesa, which is far slower. Install the NVIDIA EGL library (libnvidia-gl / libegl1) or set "
        "MUJOCO_GL yourself (MUJOCO_GL=osmesa silences this).",
        stacklevel=3,
    )
    return "osmesa"
