"""The one pixel-control interface every suite wrapper shares (paper section 4.3, appendix D).

`PixelEnv` turns a simulator into a gymnasium environment the agent can use unchanged across
DeepMind Control, Meta-World and RoboDesk:

- observations are RGB frames `uint8 [3, H, W]` (channels first, what `model.networks.preprocess`
  expects);
- actions live in `[-1, 1]^A` and are rescaled to the simulator's own bounds here;
- one agent step repeats the action `action_repeat` times and sums the rewards;
- the time limit counts agent steps (calls to `step`) and ends an episode with `truncated=True`,
  never `terminated=True` (a time limit is not a terminal state: the critic must bootstrap);
- `info["success"]` (1.0 / 0.0) where the suite defines success: whether the task was solved at any
  simulator step inside this agent step;
- random actions (the action space's samples: a prefill, `--policy random`) come from a stream of their own,
  `action_seed(seed)`, not from one seeded like the simulator's.

A suite subclass supplies the hooks `_seed_sim`, `_reset_sim`, `_step_sim`, `_render_frame` and `_close_sim`.
A non-finite action (a diverged policy's NaN) and any use after `close()` are refused by name: a simulator
would otherwise take a NaN (Meta-World's drawer-close even scores it as solved) or fail deep inside.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np


def action_seed(seed: int) -> int:
    """The seed of a policy's own randomness (uniform random actions, an expert's action noise) in an env seeded
    `seed`. Seeded with `seed` itself, its generator was the same PCG64 stream as Meta-World's placements (gymnasium's
    `np_random`): the first random action of an episode held the object's normalised x (found by a review)."""
    return int(np.random.SeedSequence([seed, 1]).generate_state(1)[0])


class EnvSettingError(ValueError):
    """A task or an env setting that cannot be made (an unknown task, a time limit beyond the suite's episodes, a
    MUJOCO_GL that cannot render): bad input, which the commands report in one line naming it."""


class PixelEnv(gymnasium.Env):
    """Base class: spaces, action rescaling, action repeat, time limit, channels-first frames."""

    metadata = {"render_modes": ["rgb_array"]}
    render_mode = "rgb_array"

    def __init__(
        self,
        name: str,
        seed: int,
        action_low: np.ndarray,
        action_high: np.ndarray,
        image_size: int,
        action_repeat: int,
        time_limit: int,
    ) -> None:
        if action_repeat < 1:
            raise EnvSettingError(f"{name}: action_repeat must be >= 1, got {action_repeat}")
        if time_limit < 1:
            raise EnvSettingError(f"{name}: time_limit must be >= 1 agent step, got {time_limit}")
        self.name = name
        self.image_size = image_size
        self.action_repeat = action_repeat  # simulator steps per agent step
        self.time_limit = time_limit  # agent steps per episode
        self._action_low = np.asarray(action_low, dtype=np.float64)  # [A]
        self._action_high = np.asarray(action_high, dtype=np.float64)  # [A]
        self.observation_space = gymnasium.spaces.Box(0, 255, (3, image_size, image_size), np.uint8)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, self._action_low.shape, np.float32,
                                                 seed=action_seed(seed))
        self._agent_steps = 0
        self._episode_over = True  # step() needs a reset() first
        self._closed = False

    # --- the five hooks a suite implements --------------------------------------------------------

    def _seed_sim(self, seed: int) -> None:
        """Re-seed the simulator's own random state (initial states, goals)."""
        raise NotImplementedError

    def _reset_sim(self) -> None:
        """Start a new episode in the simulator."""
        raise NotImplementedError

    def _step_sim(self, action: np.ndarray) -> tuple[float, bool, bool, bool | None]:
        """One simulator step with an action in native bounds -> (reward, terminated, truncated, success).

        `truncated` is the simulator's own episode end (e.g. Meta-World's 500-step path length);
        `success` is None where the suite has no notion of success.
        """
        raise NotImplementedError

    def _render_frame(self) -> np.ndarray:
        """The current frame, uint8 [H, W, 3]."""
        raise NotImplementedError

    def _close_sim(self) -> None:
        """Free the simulator and its renderer (called once, by `close`); nothing to free by default."""

    # --- gymnasium API ---------------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        self._refuse_if_closed()
        super().reset(seed=seed)
        if seed is not None:
            self._seed_sim(seed)
        self._reset_sim()
        self._agent_steps = 0
        self._episode_over = False
        return self._observation(), {}

    def step(self, action: np.ndarray):
        self._refuse_if_closed()
        if self._episode_over:
            raise RuntimeError(
                f"{self.name}: step() called on a finished episode (or before the first reset()); "
                "call reset() after terminated or truncated"
            )
        action = np.asarray(action, dtype=np.float64)  # [A]
        if action.shape != self._action_low.shape:
            raise ValueError(f"{self.name}: action shape {action.shape}, expected {self._action_low.shape}")
        if not np.isfinite(action).all():
            raise ValueError(f"{self.name}: non-finite action {action}: a policy that gives NaN or inf has diverged")
        action = np.clip(action, -1.0, 1.0)
        native = self._action_low + (action + 1.0) * 0.5 * (self._action_high - self._action_low)

        reward, terminated, sim_truncated, success = 0.0, False, False, None
        for _ in range(self.action_repeat):
            step_reward, terminated, sim_truncated, step_success = self._step_sim(native)
            reward += step_reward
            if step_success is not None:
                success = bool(success) or step_success
            if terminated or sim_truncated:
                break
        self._agent_steps += 1
        truncated = not terminated and (sim_truncated or self._agent_steps >= self.time_limit)
        self._episode_over = terminated or truncated
        info = {} if success is None else {"success": float(success)}
        return self._observation(), float(reward), terminated, truncated, info

    def render(self) -> np.ndarray:
        """The current frame, uint8 [H, W, 3] (gymnasium's rgb_array convention)."""
        self._refuse_if_closed()
        return self._render_frame()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._close_sim()

    def _refuse_if_closed(self) -> None:
        if self._closed:
            raise RuntimeError(f"{self.name}: this env is closed; make a new one (finetune.envs.make_env)")

    def _observation(self) -> np.ndarray:
        frame = self._render_frame()  # [H, W, 3]
        return np.ascontiguousarray(frame.transpose(2, 0, 1))  # [3, H, W]
