"""Meta-World v3 manipulation from pixels (dial-turn, lever-pull, door-open, drawer-close, ...).

Built with `gymnasium.make('Meta-World/MT1', env_name='<task>-v3', seed=seed, camera_name='corner2')`.
MT1 would give every reset one of 50 goal/object placements that it fixes from the construction seed; an
evaluation of a few episodes then measures that set, which can be lopsided (drawer close: 74% of the set
of seed 10,000 puts the drawer left of centre, 36% of seed 20,000's; one agent scored 10% on the first and
70% on the second). As APV does (`_freeze_rand_vec = False`), every reset here draws a fresh placement
from the task's whole range instead, with the env's own seeded generator (`reset(seed=s)` reseeds it). The
corner cameras render upside down, so rows are flipped. Episodes are Meta-World's 500-step path length; the
action repeat defaults to 1 as in APV (a Meta-World step is already 5 physics steps, and the rewards,
0-10 per step, sum to Table 4's scale over 500 steps). `info["success"]` is Meta-World's own success
flag; an episode goes on after success (no early termination), as in the paper's setting.
`env.state` is Meta-World's own 39-dim state vector after the last simulator step (what its scripted
policies in `metaworld.policies` act on; the agent never sees it).
"""

from __future__ import annotations

import gymnasium
import metaworld  # noqa: F401  (registers the 'Meta-World/*' gymnasium ids)
import numpy as np

from finetune.envs.base import EnvSettingError, PixelEnv
from finetune.envs.rendering import disable_multisampling, turn_off_scene_flags

EPISODE_SIM_STEPS = 500  # Meta-World's max_path_length; stepping past it is an error in Meta-World
DEFAULT_ACTION_REPEAT = 1
CAMERA = "corner2"


def tasks() -> dict[str, str]:
    """Every Meta-World v3 task as `metaworld_<task>` -> its Meta-World id ('dial-turn-v3')."""
    return {
        f"metaworld_{env_id.removesuffix('-v3').replace('-', '_')}": env_id for env_id in metaworld.ALL_V3_ENVIRONMENTS
    }


class MetaWorldEnv(PixelEnv):
    """One Meta-World v3 task rendered to `uint8 [3, H, W]` frames from the corner2 camera."""

    def __init__(
        self,
        name: str,
        env_id: str,
        seed: int,
        image_size: int,
        action_repeat: int,
        time_limit: int,
        fast_render: bool,
    ) -> None:
        if time_limit * action_repeat > EPISODE_SIM_STEPS:
            raise EnvSettingError(
                f"{name}: time_limit {time_limit} x action_repeat {action_repeat} exceeds Meta-World's "
                f"{EPISODE_SIM_STEPS}-step episodes; " + (
                    f"use time_limit <= {EPISODE_SIM_STEPS // action_repeat}" if action_repeat <= EPISODE_SIM_STEPS
                    else f"lower action_repeat (at most {EPISODE_SIM_STEPS}, with time_limit × action_repeat ≤ "
                         f"{EPISODE_SIM_STEPS})")
            )
        self._env = gymnasium.make(
            "Meta-World/MT1",
            env_name=env_id,
            seed=seed,
            render_mode="rgb_array",
            camera_name=CAMERA,
            width=image_size,
            height=image_size,
            disable_env_checker=True,  # it warns about Meta-World's state observations, which we ignore
        )
        sim = self._env.unwrapped
        low, high = sim.action_space.low, sim.action_space.high
        super().__init__(name, seed, low, high, image_size, action_repeat, time_limit)
        if fast_render:
            disable_multisampling(sim.model)
        self._env.reset()  # MT1's first task: the task's constants (and _set_task_called, which reset needs)
        task_wrapper = self._env
        while not hasattr(task_wrapper, "toggle_sample_tasks_on_reset"):
            task_wrapper = task_wrapper.env
        task_wrapper.toggle_sample_tasks_on_reset(False)  # no more of MT1's 50 fixed placements …
        sim._freeze_rand_vec = False  # … but a fresh one every reset,
        sim.seeded_rand_vec = True  # drawn with the env's generator (numpy's global one otherwise),
        self._seed_sim(seed)  # seeded as reset(seed=seed) seeds it
        sim.mujoco_renderer.render("rgb_array")  # creates the offscreen viewer and its OpenGL context
        self._viewer = sim.mujoco_renderer.viewer
        self.state: np.ndarray | None = None  # float64 [39], set by reset() and step()
        if fast_render:
            turn_off_scene_flags(self._viewer.scn)

    def _seed_sim(self, seed: int) -> None:
        self._env.unwrapped.seed(seed)

    def _reset_sim(self) -> None:
        self.state, _ = self._env.reset()

    def _step_sim(self, action: np.ndarray) -> tuple[float, bool, bool, bool]:
        self.state, reward, terminated, truncated, info = self._env.step(action.astype(np.float32))
        return float(reward), terminated, truncated, bool(info["success"])

    def _render_frame(self) -> np.ndarray:
        # gymnasium's viewer renders into whichever OpenGL context is current; with several envs in
        # one process (train and eval, or another suite) that may be someone else's: make ours current.
        self._viewer.make_context_current()
        return self._env.render()[::-1]  # [H, W, 3]; corner cameras render upside down

    def _close_sim(self) -> None:
        if self._viewer is None:
            return
        # Free our OpenGL objects inside our own context: left to gymnasium and the garbage collector,
        # they are deleted in whichever context is current, which blanks another live env's frames.
        self._viewer.make_context_current()
        self._viewer.con.free()
        self._env.close()
        self._viewer = None

    def __del__(self) -> None:
        if hasattr(self, "_viewer"):
            self.close()


ENV_CLASS = MetaWorldEnv
