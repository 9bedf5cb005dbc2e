"""`make_env(name, seed, ...)`: one constructor for every fine-tuning task (paper section 4.3).

Names are `<suite>_<task>`: `dmc_<domain>_<task>` (any DeepMind Control task, e.g. `dmc_cheetah_run`,
`dmc_cartpole_swingup`), `metaworld_<task>` (any Meta-World v3 task, dashes written as underscores,
e.g. `metaworld_dial_turn`), `robodesk_<task>` (e.g. `robodesk_push_green`). Each suite module is
imported only when one of its tasks is made, so DMC users never import Meta-World or RoboDesk.

Defaults per suite (docs/environments.md says why):

| suite      | action repeat | simulator steps per episode | agent steps (time_limit) |
|------------|---------------|-----------------------------|--------------------------|
| DMC        | 2             | 1000                        | 500                      |
| Meta-World | 1             | 500                         | 500                      |
| RoboDesk   | 2             | 500                         | 250                      |
"""

from __future__ import annotations

import importlib
from types import ModuleType

from finetune.envs.base import EnvSettingError, PixelEnv
from finetune.envs.opengl import check_rendering

# The ten tasks of the paper's Table 4, in its order of suites.
PAPER_TASKS: tuple[str, ...] = (
    "dmc_cheetah_run",
    "dmc_walker_run",
    "dmc_hopper_hop",
    "dmc_quadruped_run",
    "metaworld_dial_turn",
    "metaworld_lever_pull",
    "metaworld_door_open",
    "metaworld_drawer_close",
    "robodesk_push_green",
    "robodesk_open_slide",
)

# name prefix -> module with `tasks()`, `ENV_CLASS`, `DEFAULT_ACTION_REPEAT`, `EPISODE_SIM_STEPS`
_SUITE_MODULES = {
    "dmc": "finetune.envs.dmc_env",
    "metaworld": "finetune.envs.metaworld_env",
    "robodesk": "finetune.envs.robodesk_env",
}


def suite_module(name: str) -> ModuleType:
    prefix = name.split("_", 1)[0]
    if prefix not in _SUITE_MODULES:
        raise EnvSettingError(
            f"unknown environment {name!r}: names start with one of "
            f"{', '.join(p + '_' for p in _SUITE_MODULES)}. The paper's tasks: {', '.join(PAPER_TASKS)}"
        )
    return importlib.import_module(_SUITE_MODULES[prefix])


def check_task(name: str) -> tuple[ModuleType, dict]:
    """(its suite's module, the suite's tasks) for a task `name`; an EnvSettingError listing the valid names otherwise."""
    suite = suite_module(name)
    tasks = suite.tasks()
    if name not in tasks:
        raise EnvSettingError(
            f"unknown environment {name!r}. Valid {name.split('_', 1)[0]} names: {', '.join(sorted(tasks))}"
        )
    return suite, tasks


def episode_time_limit(name: str, action_repeat: int | None = None, time_limit: int | None = None) -> int:
    """The agent steps of an episode of task `name`: `time_limit`, or the suite's episode length divided by
    `action_repeat` (the suite's default repeat where None)."""
    if time_limit is not None:
        return time_limit
    suite = suite_module(name)
    return max(1, suite.EPISODE_SIM_STEPS // max(1, action_repeat or suite.DEFAULT_ACTION_REPEAT))


def make_env(
    name: str,
    seed: int,
    image_size: int = 64,
    action_repeat: int | None = None,
    fast_render: bool = False,
    time_limit: int | None = None,
) -> PixelEnv:
    """Build task `name` as a gymnasium env with `uint8 [3, image_size, image_size]` observations.

    `action_repeat` defaults to the suite's (DMC 2, Meta-World 1, RoboDesk 2); `time_limit` counts
    agent steps and defaults to the suite's episode length divided by the action repeat;
    `fast_render` turns off shadows, reflections and multisampling (see `rendering.py`).
    """
    check_rendering()  # a MUJOCO_GL the user set must be able to draw a frame: once per process tree
    suite, tasks = check_task(name)
    if action_repeat is None:
        action_repeat = suite.DEFAULT_ACTION_REPEAT
    time_limit = episode_time_limit(name, action_repeat, time_limit)
    return suite.ENV_CLASS(name, tasks[name], seed, image_size, action_repeat, time_limit, fast_render)
