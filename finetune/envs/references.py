"""Random and expert episode returns of the paper's Table 4, for normalised returns.

normalised = (R - random) / (expert - random), so 0 is a random policy and 1 the expert (the design notes,
"Fine-tuning"; paper appendix F.2). The references are the Table 4 means over four seeds; their
returns are per episode of the default length (DMC 1000, Meta-World 500 simulator steps).

RoboDesk's references (push_green 12 / 378, open_slide 7 / 177) are not used: they do not fit the reward
RoboDesk 1.0.0 defines. Its dense reward has a floor well above them (open_slide's "did not move" term is
always 1, since RoboDesk keeps the original position as a live view of the current one; push_green's distance
term is about 0.5 a step): an agent that does nothing returns 211 on open_slide and 258 on push_green over 500
simulator steps, and uniform random actions 199–221 and 153–280 (3 episodes each), so normalised by Table 4
doing nothing would score 1.2 on open_slide, above the "expert". RoboDesk runs report returns and success rates.
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
}
UNFIT_REFERENCES = ("robodesk_push_green", "robodesk_open_slide")  # Table 4's, not this reward's (above)


def normalised_return(task: str, episode_return: float) -> float:
    """Table 4 normalisation of one episode return for one of the paper's DMC and Meta-World tasks."""
    if task in UNFIT_REFERENCES:
        raise KeyError(f"{task}: Table 4's RoboDesk references do not fit RoboDesk 1.0.0's dense reward (doing "
                       "nothing would score above the expert; finetune/envs/references.py): compare returns and "
                       "success rates")
    if task not in REFERENCE_RETURNS:
        raise KeyError(f"no Table 4 reference returns for {task!r}; the tasks with references: "
                       f"{', '.join(REFERENCE_RETURNS)}")
    random_return, expert_return = REFERENCE_RETURNS[task]
    return (episode_return - random_return) / (expert_return - random_return)
