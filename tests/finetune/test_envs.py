"""The fine-tuning environments: one gymnasium interface over DMC, Meta-World v3 and RoboDesk.

Real simulators and real (OSMesa/EGL) rendering throughout; `fast_render=True` and short time limits
keep the module to well under a minute of CPU.
"""

from __future__ import annotations

import gc
import os
import subprocess
import sys

import numpy as np
import pytest

from finetune.envs import PAPER_TASKS, make_env, normalised_return
from finetune.envs.base import PixelEnv

# one paper task per suite, with its default action repeat and agent steps per episode
SUITE_TASKS = {
    "dmc_cheetah_run": (2, 500),
    "metaworld_dial_turn": (1, 500),
    "robodesk_push_green": (2, 250),
}


@pytest.fixture
def envs_to_close():
    made: list[PixelEnv] = []
    yield made
    for env in made:
        env.close()


@pytest.mark.parametrize("name", SUITE_TASKS)
def test_spaces_reset_step_and_time_limit(name, envs_to_close):
    env = make_env(name, seed=0, fast_render=True, time_limit=3)
    envs_to_close.append(env)
    assert env.observation_space.shape == (3, 64, 64) and env.observation_space.dtype == np.uint8
    assert env.action_space.dtype == np.float32
    assert np.all(env.action_space.low == -1.0) and np.all(env.action_space.high == 1.0)
    assert env.action_repeat == SUITE_TASKS[name][0]

    obs, info = env.reset()
    assert obs.shape == (3, 64, 64) and obs.dtype == np.uint8
    assert env.observation_space.contains(obs)
    assert obs.std() > 5, "the frame is blank: rendering is broken"

    for step in range(1, 4):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert obs.shape == (3, 64, 64) and obs.dtype == np.uint8
        assert isinstance(reward, float) and np.isfinite(reward)
        assert terminated is False
        assert truncated is (step == 3), "the time limit must truncate exactly at step 3"
        if name.startswith("dmc"):
            assert "success" not in info
        else:
            assert info["success"] in (0.0, 1.0)

    with pytest.raises(RuntimeError, match="call reset"):
        env.step(env.action_space.sample())
    obs, _ = env.reset()  # a new episode after truncation
    assert env.step(env.action_space.sample())[3] is False
    # a diverged policy's NaN is refused (Meta-World's drawer-close would score it as solved)
    with pytest.raises(ValueError, match=f"{name}: non-finite action"):
        env.step(np.full(env.action_space.shape, np.nan, np.float32))
    env.close()
    env.close()  # twice is fine
    for use in (env.reset, lambda: env.step(env.action_space.sample()), env.render):
        with pytest.raises(RuntimeError, match=f"{name}: this env is closed"):
            use()


@pytest.mark.filterwarnings("ignore:.*(render fps|alternative render modes)")
def test_gymnasium_env_checker_passes(envs_to_close):
    from gymnasium.utils.env_checker import check_env

    env = make_env("dmc_cartpole_swingup", seed=0, fast_render=True, time_limit=20)
    envs_to_close.append(env)
    check_env(env)  # spaces, reset(seed=...) determinism, step and render conventions


@pytest.mark.parametrize("name", SUITE_TASKS)
def test_default_episode_length(name, envs_to_close):
    env = make_env(name, seed=0, fast_render=True)
    envs_to_close.append(env)
    assert env.time_limit == SUITE_TASKS[name][1]


@pytest.mark.parametrize("name", SUITE_TASKS)
def test_seeding_gives_the_same_first_frame(name, envs_to_close):
    a, b, c = (make_env(name, seed=s, fast_render=True) for s in (7, 7, 8))
    envs_to_close.extend([a, b, c])
    first = a.reset()[0]
    assert np.array_equal(first, b.reset()[0]), "same seed, different first frame"
    assert not np.array_equal(first, c.reset()[0]), "different seeds gave the same initial state"
    a.reset()  # a later episode starts elsewhere ...
    assert np.array_equal(first, a.reset(seed=7)[0])  # ... and reset(seed=...) re-seeds


def test_full_metaworld_episode_is_truncated_at_500_steps(envs_to_close):
    env = make_env("metaworld_drawer_close", seed=1, fast_render=True)
    envs_to_close.append(env)
    env.reset()
    steps, episode_return = 0, 0.0
    terminated = truncated = False
    while not (terminated or truncated):
        _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        steps, episode_return = steps + 1, episode_return + reward
    assert (steps, terminated, truncated) == (500, False, True)
    assert 0 < episode_return < 5000  # Meta-World rewards are 0-10 per step


def test_metaworld_draws_a_fresh_placement_every_reset_from_its_seed(envs_to_close):
    """Not one of MT1's 50 placements fixed at construction (APV's `_freeze_rand_vec = False`), reproducibly."""
    def drawer_positions(seed: int, resets: int) -> list[float]:
        env = make_env("metaworld_drawer_close", seed=seed, fast_render=True)
        envs_to_close.append(env)
        positions = []
        for index in range(resets):
            env.reset(seed=seed if index == 0 else None)
            positions.append(float(env.state[4]))  # the drawer's x: the placement
        return positions

    first = drawer_positions(3, 60)
    assert len(set(first)) == 60 and min(first) < -0.05 < 0.05 < max(first)  # more than MT1's 50, both sides
    assert drawer_positions(3, 60) == first
    assert drawer_positions(4, 3) != first[:3]


def test_random_actions_are_independent_of_the_placement_the_same_seed_draws(envs_to_close):
    """The action space was seeded with the env's seed, and so drew the same PCG64 stream as Meta-World's placements:
    the first random action of `--policy random` and of a prefill held the drawer's x, exactly (found by a review)."""
    positions, first_actions = [], []
    for seed in range(20):
        env = make_env("metaworld_drawer_close", seed=seed, fast_render=True)
        envs_to_close.append(env)
        env.reset(seed=seed)
        positions.append(float(env.state[4]))  # the drawer's x: the placement
        first_actions.append(env.action_space.sample())
        env.close()
    correlations = [abs(np.corrcoef(positions, np.array(first_actions)[:, dim])[0, 1]) for dim in range(4)]
    assert max(correlations) < 0.9, correlations  # 1.0 before, in dimension 3


def test_metaworld_time_limit_beyond_its_path_length_fails_clearly():
    with pytest.raises(ValueError, match="500-step episodes"):
        make_env("metaworld_dial_turn", seed=0, time_limit=501)


def test_envs_in_one_process_keep_their_own_rendering(envs_to_close):
    """gymnasium's Meta-World viewer renders into whichever OpenGL context is current, and frees its
    objects in it; two live envs (train and eval) must still each render their own scene."""
    default = make_env("metaworld_dial_turn", seed=0)
    fast = make_env("metaworld_dial_turn", seed=0, fast_render=True)
    dmc = make_env("dmc_cheetah_run", seed=0, fast_render=True)
    envs_to_close.extend([default, dmc])
    frame_default, frame_fast = default.reset()[0], fast.reset()[0]
    dmc.reset()
    assert np.array_equal(frame_default, default.render().transpose(2, 0, 1))
    assert frame_fast.std() > 5
    del fast
    gc.collect()
    assert np.array_equal(frame_default, default.render().transpose(2, 0, 1))


def test_torch_compiler_can_load_after_an_env_renders():
    """triton and Mesa's llvmpipe both load LLVM: triton loaded after a context segfaulted (rc -11)."""
    script = (
        "from finetune.envs import make_env\n"
        "env = make_env('dmc_cartpole_swingup', seed=0, fast_render=True)\n"
        "env.reset()\n"
        "import torch._dynamo\n"
        "env.step(env.action_space.sample())\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]


def test_mujoco_imported_first_under_osmesa_warns_instead_of_crashing():
    """`import mujoco` under OSMesa loads its LLVM at once: finetune.envs must then not load triton's."""
    script = ("import mujoco\n"
              "from finetune.envs import make_env\n"
              "env = make_env('dmc_cartpole_swingup', seed=0, fast_render=True)\n"
              "env.reset()\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                            env={**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"})
    assert result.returncode == 0, result.stderr[-2000:]
    assert "mujoco was imported before finetune.envs, so OSMesa is loaded" in result.stderr


def test_fast_render_keeps_dmc_frames_nearly_identical(envs_to_close):
    default, fast = make_env("dmc_cheetah_run", seed=0), make_env("dmc_cheetah_run", seed=0, fast_render=True)
    envs_to_close.extend([default, fast])
    difference = np.abs(default.reset()[0].astype(np.int16) - fast.reset()[0])
    assert 0 < difference.mean() < 4  # the shadows and reflections really are off, and little else moves


def test_robodesk_frames_match_robodesk_own_renderer(monkeypatch, envs_to_close):
    from PIL import Image

    monkeypatch.setattr(Image, "ANTIALIAS", Image.LANCZOS, raising=False)  # Pillow >= 10 removed it
    env = make_env("robodesk_open_slide", seed=0)
    envs_to_close.append(env)
    env.reset()
    env.step(env.action_space.sample())
    assert np.array_equal(env.render(), env._env.render(resize=True))


def test_robodesk_seeding_leaves_numpy_global_state_alone(envs_to_close):
    np.random.seed(123)
    expected = np.random.rand(3)
    np.random.seed(123)
    env = make_env("robodesk_push_green", seed=0, fast_render=True)
    envs_to_close.append(env)
    env.reset()
    assert np.array_equal(np.random.rand(3), expected)


@pytest.mark.parametrize("name", [name for name in PAPER_TASKS if name.startswith("dmc")])
def test_every_paper_dmc_task_builds_and_steps(name, envs_to_close):
    env = make_env(name, seed=0, fast_render=True, time_limit=2)
    envs_to_close.append(env)
    obs, _ = env.reset()
    assert obs.std() > 5
    env.step(env.action_space.sample())
    assert env.step(env.action_space.sample())[3] is True


def test_any_dmc_task_and_action_repeat_override(envs_to_close):
    env = make_env("dmc_ball_in_cup_catch", seed=0, image_size=32, action_repeat=4, fast_render=True)
    envs_to_close.append(env)
    assert env.reset()[0].shape == (3, 32, 32)
    assert (env.action_repeat, env.time_limit) == (4, 250)


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("dmc_cheetah_fly", "dmc_cheetah_run"),  # lists the valid DMC names
        ("metaworld_dial_spin", "metaworld_dial_turn"),
        ("robodesk_stack", "robodesk_push_green"),
        ("atari_pong", "dmc_, metaworld_, robodesk_"),
    ],
)
def test_unknown_name_fails_with_the_valid_ones(name, message):
    with pytest.raises(ValueError, match=message):
        make_env(name, seed=0)


def test_normalised_return_uses_table_4():
    assert normalised_return("dmc_cheetah_run", 71.0) == 0.0
    assert normalised_return("dmc_cheetah_run", 821.0) == 1.0
    assert normalised_return("metaworld_dial_turn", (687.0 + 4232.0) / 2) == pytest.approx(0.5)
    with_references = [name for name in PAPER_TASKS if not name.startswith("robodesk")]
    assert len(with_references) == 8 and all(normalised_return(name, 0.0) < 0 for name in with_references)
    with pytest.raises(KeyError, match="dmc_cheetah_run"):
        normalised_return("dmc_cartpole_swingup", 100.0)


def test_robodesk_is_not_normalised_by_references_its_reward_does_not_fit():
    """Table 4's RoboDesk references (open_slide: random 7, expert 177) lie below what doing nothing returns."""
    env = make_env("robodesk_open_slide", seed=0, fast_render=True)
    env.reset()
    idle = sum(env.step(np.zeros(env.action_space.shape, np.float32))[1] for _ in range(env.time_limit))
    env.close()
    assert idle > 177.0  # above Table 4's expert: these references cannot normalise this reward
    with pytest.raises(KeyError, match="do not fit RoboDesk 1.0.0's dense reward"):
        normalised_return("robodesk_open_slide", idle)


class _Counter(PixelEnv):
    """A stand-in simulator that records the native actions it receives (tests `PixelEnv` alone)."""

    def __init__(self, action_repeat: int, terminate_at: int | None = None) -> None:
        super().__init__("counter", 0, np.array([0.0, -2.0]), np.array([10.0, 2.0]), 8, action_repeat, 100)
        self.native_actions: list[np.ndarray] = []
        self.terminate_at = terminate_at

    def _seed_sim(self, seed):
        pass

    def _reset_sim(self):
        self.native_actions.clear()

    def _step_sim(self, action):
        self.native_actions.append(action)
        terminated = len(self.native_actions) == self.terminate_at
        return 1.0, terminated, False, len(self.native_actions) == 2

    def _render_frame(self):
        return np.zeros((8, 8, 3), np.uint8)


def test_pixel_env_rescales_repeats_and_sums():
    env = _Counter(action_repeat=3)
    env.reset()
    _, reward, terminated, truncated, info = env.step(np.array([-1.0, 5.0]))  # 5 is clipped to 1
    assert reward == 3.0 and not terminated and not truncated
    assert info["success"] == 1.0  # success at the second of the three simulator steps counts
    np.testing.assert_allclose(env.native_actions, [[0.0, 2.0]] * 3)


def test_pixel_env_stops_repeating_at_a_terminal():
    env = _Counter(action_repeat=3, terminate_at=2)
    env.reset()
    _, reward, terminated, truncated, _ = env.step(np.zeros(2))
    assert (reward, terminated, truncated) == (2.0, True, False)
    np.testing.assert_allclose(env.native_actions, [[5.0, 0.0]] * 2)


def test_pixel_env_refuses_an_action_with_any_non_finite_entry():
    """One NaN or inf among finite entries is refused as well, before the simulator sees anything."""
    env = _Counter(action_repeat=2)
    env.reset()
    for bad in ([np.nan, 0.0], [0.0, np.inf], [-np.inf, 0.5]):
        with pytest.raises(ValueError, match="counter: non-finite action"):
            env.step(np.array(bad))
    assert env.native_actions == []
