"""What `fast_render=True` turns off, shared by every suite.

On a CPU (OSMesa or Mesa's software EGL) rendering costs far more than physics. Three things make
most of that cost: 4x multisample anti-aliasing of the offscreen buffer, the shadow passes and the
planar-reflection pass. Fast rendering turns all three off: 8-20x more frames per second in
`bench/bench_envs.py`, for a mean change of a 64x64 frame of 1-7 grey levels out of 255 in DMC, 11 in
Meta-World (the table's shadow) and 39 in RoboDesk (a darker desk); see docs/environments.md.

Multisampling is a property of the OpenGL context, so `disable_multisampling` must run before the
first render of a model; the scene flags can be switched per render.
"""

from __future__ import annotations

import mujoco

# mujoco.mjtRndFlag names (without the `mjRND_` prefix) that fast rendering switches off; dm_control's
# `render_flag_overrides` takes the same names in lower case.
FAST_RENDER_FLAGS_OFF: dict[str, bool] = {"shadow": False, "reflection": False}


def disable_multisampling(model: mujoco.MjModel) -> None:
    """Render to a single-sample offscreen buffer; call before the model's first render.

    `model` is a `mujoco.MjModel` or dm_control's wrapper of one (same `vis` fields).
    """
    model.vis.quality.offsamples = 0


def turn_off_scene_flags(scene: mujoco.MjvScene) -> None:
    """Switch off the fast-render flags on a raw mujoco scene (used for Meta-World's renderer)."""
    for name, value in FAST_RENDER_FLAGS_OFF.items():
        scene.flags[getattr(mujoco.mjtRndFlag, f"mjRND_{name.upper()}")] = value
