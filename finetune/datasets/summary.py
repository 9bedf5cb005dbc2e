"""Episode statistics of a dataset: steps, returns, Table 4 normalised return, success rate.

Fed one episode at a time (replay layout), so summarising a dataset never holds its frames in memory.
The normalised return, (R - random) / (expert - random) with the paper's Table 4 references, is only
comparable for episodes of the suite's default length (Meta-World 500 steps, DMC 1000 env steps).
"""

from __future__ import annotations

import numpy as np

from finetune.envs.references import REFERENCE_RETURNS, normalised_return
from finetune.envs.registry import episode_time_limit


class Summary:
    def __init__(self, task: str | None, action_repeat: int | None = None) -> None:
        """`action_repeat`: the one the episodes were collected with (None: the suite's default)."""
        self.task = task
        self.action_repeat = action_repeat
        self.returns: list[float] = []
        self.lengths: list[int] = []  # agent steps per episode
        self.successes: list[bool] = []  # success at any step of the episode, for episodes with a success flag
        self.terminals = 0  # episodes that end in a terminal state (not a time limit)

    def add(self, episode: dict[str, np.ndarray]) -> None:
        self.returns.append(float(episode["reward"].sum(dtype=np.float64)))
        self.lengths.append(len(episode["reward"]) - 1)
        if "success" in episode:
            self.successes.append(bool(episode["success"].any()))
        self.terminals += ends_terminal(episode)

    def stats(self) -> dict[str, float]:
        returns = np.asarray(self.returns)
        result = {"episodes": len(returns), "steps": int(sum(self.lengths)), "return_mean": float(returns.mean()),
                  "return_min": float(returns.min()), "return_max": float(returns.max())}
        if self.task in REFERENCE_RETURNS:
            result["normalised_return"] = float(normalised_return(self.task, result["return_mean"]))
        if self.successes:
            result["success_rate"] = float(np.mean(self.successes))
        return result

    def lines(self) -> list[str]:
        s = self.stats()
        low, high = min(self.lengths), max(self.lengths)
        per_episode = f"{low}" if low == high else f"{low}-{high}"
        lines = [f"episodes        {s['episodes']}",
                 f"steps           {s['steps']} ({per_episode} per episode)",
                 f"return          mean {s['return_mean']:.1f}, min {s['return_min']:.1f}, max {s['return_max']:.1f}"]
        if "normalised_return" in s:
            random_return, expert_return = REFERENCE_RETURNS[self.task]
            full = episode_time_limit(self.task, self.action_repeat)
            other = sum(length != full for length in self.lengths)  # cut short, or run on past the suite's limit
            caveat = ("" if not other else f"; episodes of {per_episode} steps, not the suite's {full}: not comparable"
                      if other == len(self.lengths) else f"; {other} of {len(self.lengths)} episodes of another length "
                      f"than the suite's {full} steps ({low}-{high}): not comparable")
            lines.append(f"normalised      {s['normalised_return']:.3f} (Table 4: random {random_return:g}, "
                         f"expert {expert_return:g}{caveat})")
        if "success_rate" in s:
            lines.append(f"success rate    {s['success_rate']:.0%} ({sum(self.successes)} of {s['episodes']} episodes)")
        if self.terminals:
            lines.append(f"terminal        {self.terminals} of {s['episodes']} episodes end in a terminal state "
                         f"({TERMINALS_IGNORED})")
        return lines


# what fine-tuning does with a terminal state (docs/finetuning.md, "No continuation head")
TERMINALS_IGNORED = ("HAUWM's learners have no continuation head, as none of the paper's tasks has terminal states: "
                     "they treat the end like a time limit, and imagined returns run on past it")


def ends_terminal(episode: dict[str, np.ndarray]) -> bool:
    """Whether an episode (replay layout) ends in a terminal state; False where it records none (`terminal`)."""
    return "terminal" in episode and bool(episode["terminal"][-1])
