"""Random and expert episode returns of the paper's Table 4, for normalised returns.

normalised = (R - random) / (expert - random), so 0 is a random policy and 1 the expert (DESIGN.md,
"Fine-tuning"; paper appendix F.2). The references are the Table 4 means over four seeds; their
returns are per episode of the default length (DMC 1000, Meta-World and RoboDesk 500 simulator steps).
"""

from __future__ import annotations

# task name -> (random return, expert return), Table 4
REFERENCE_RETURNS: dict[str, tuple[float, float]] = {
    "metaworld_dial_turn": (687.0, 4232.0),
    "metaworld_lever_pull": (239.0, 4913.0),
    "metaworld_door_open": (277.0, 4637.0),
    "metaworld_drawer_close": (221.0, 4895.0),
    "dmc_cheetah_run": (71.0, 821.0),
    "dmc_walker_run": (120.0, 932.0),
    "dmc_hopper_hop": (25.0, 478.0),
    "dmc_quadruped_run": (35.0, 795.0),
    "robodesk_push_green": (12.0, 378.0),
    "robodesk_open_slide": (7.0, 177.0),
}


def normalised_return(task: str, episode_return: float) -> float:
    """Table 4 normalisation of one episode return for one of the paper's ten tasks."""
    if task not in REFERENCE_RETURNS:
        raise KeyError(
            f"no Table 4 reference returns for {task!r}; the paper's tasks are: {', '.join(REFERENCE_RETURNS)}"
        )
    random_return, expert_return = REFERENCE_RETURNS[task]
    return (episode_return - random_return) / (expert_return - random_return)
