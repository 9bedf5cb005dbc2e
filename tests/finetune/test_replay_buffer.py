"""finetune.replay.Replay: aligned windows inside episodes, the capacity, and reloading from disk."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chisquare

from finetune.replay import Replay, ReplayError


def episode(index: int, length: int) -> dict[str, np.ndarray]:
    """Entries carry their episode index and step, so windows can be checked for alignment."""
    steps = np.arange(length + 1)
    obs = np.zeros((length + 1, 3, 64, 64), np.uint8)
    obs[:, 0, 0, 0], obs[:, 0, 0, 1] = index, steps
    action = np.stack([np.full(length + 1, index), steps], -1).astype(np.float32)
    action[0] = 0
    reward = (index * 1000 + steps).astype(np.float32)
    reward[0] = 0
    return {"obs": obs, "action": action, "reward": reward}


def test_windows_stay_inside_one_episode_and_keep_alignment(tmp_path):
    replay = Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0))
    for i, length in enumerate([5, 30, 12]):
        replay.add(episode(i + 1, length))
    assert replay.num_steps == 47 and replay.ready(10) and not replay.ready(40)
    batch = replay.sample(batch_size=64, length=10)
    assert batch["obs"].shape == (64, 10, 3, 64, 64) and batch["obs"].dtype == np.uint8
    assert batch["action"].shape == (64, 10, 2) and batch["reward"].shape == (64, 10)
    ep, step = batch["obs"][:, :, 0, 0, 0].astype(int), batch["obs"][:, :, 0, 0, 1].astype(int)
    assert (ep == ep[:, :1]).all()  # one episode per window
    assert (np.diff(step, axis=1) == 1).all()  # consecutive entries
    assert set(np.unique(ep)) == {2, 3}  # the 5-step episode cannot hold a window of 10
    later = step > 0
    assert (batch["reward"][later] == (ep * 1000 + step)[later]).all()
    assert (batch["action"][..., 1][later] == step[later]).all()


def test_every_window_start_is_drawn_uniformly_up_to_the_last_that_fits():
    replay = Replay(None, capacity=10_000, rng=np.random.default_rng(0))
    replay.add(episode(1, 9))  # 10 entries: a window of 10 has one start, 0
    assert replay.ready(10) and (replay.sample(4, 10)["obs"][:, 0, 0, 0, 1] == 0).all()
    replay.add(episode(2, 14))  # 15 entries: starts 0..5
    batch = replay.sample(batch_size=7_000, length=10)
    ep, start = batch["obs"][:, 0, 0, 0, 0].astype(int), batch["obs"][:, 0, 0, 0, 1].astype(int)
    counts = {(e, s): n for (e, s), n in zip(*np.unique(np.stack([ep, start], 1), axis=0, return_counts=True))}
    assert set(counts) == {(1, 0)} | {(2, s) for s in range(6)}  # the last start of each episode too
    assert chisquare(list(counts.values())).pvalue > 1e-3  # 7 starts, each as likely


def test_capacity_drops_the_oldest_episodes_and_disk_reload_keeps_the_newest(tmp_path):
    replay = Replay(tmp_path, capacity=50, rng=np.random.default_rng(0))
    for i in range(5):
        replay.add(episode(i + 1, 20))
    assert replay.num_steps == 40 and len(replay.episodes) == 2
    assert len(list(tmp_path.glob("*.npz"))) == 5  # files stay on disk

    reloaded = Replay(tmp_path, capacity=50, rng=np.random.default_rng(0))
    assert reloaded.load(stored=5) == 2
    assert [int(ep["obs"][0, 0, 0, 0]) for ep in reloaded.episodes] == [4, 5]
    reloaded.add(episode(6, 20))
    assert (tmp_path / "000005-20.npz").exists()  # numbering continues after the reload


def test_a_reload_past_the_millionth_episode_keeps_the_newest(tmp_path):
    """Episode files sorted by name put 1000000 before 100001: a reload past the millionth episode took old ones
    (found by a review)."""
    replay = Replay(tmp_path, capacity=50, rng=np.random.default_rng(0))
    replay.num_saved = 999_998  # as a long run's replay stands
    for i in range(4):
        replay.add(episode(i + 1, 20))
    assert sorted(path.name for path in tmp_path.glob("*.npz"))[:2] == ["1000000-20.npz", "1000001-20.npz"]
    reloaded = Replay(tmp_path, capacity=50, rng=np.random.default_rng(0))
    assert reloaded.load(stored=1_000_002) == 2
    assert [int(ep["obs"][0, 0, 0, 0]) for ep in reloaded.episodes] == [3, 4]


def test_episodes_that_fill_the_capacity_exactly_are_all_kept_and_reloaded(tmp_path):
    """The capacity is the most steps held: episodes that sum to it exactly all stay, in memory and on reload."""
    replay = Replay(tmp_path, capacity=40, rng=np.random.default_rng(0))
    for i in range(2):
        replay.add(episode(i + 1, 20))
    assert replay.num_steps == 40 and len(replay.episodes) == 2
    assert Replay(tmp_path, capacity=40, rng=np.random.default_rng(0)).load(stored=2) == 2
    replay.add(episode(3, 1))  # one step over: the oldest episode goes
    assert replay.num_steps == 21 and [int(ep["obs"][0, 0, 0, 0]) for ep in replay.episodes] == [2, 3]


def test_an_episode_longer_than_the_capacity_is_kept_alone_and_reloaded_alike(tmp_path):
    """The newest episode always stays, even when it alone exceeds the capacity; a resumed run reloads it too (it
    reloaded nothing, so the resumed run made no update until its next episode ended)."""
    replay = Replay(tmp_path, capacity=10, rng=np.random.default_rng(0))
    replay.add(episode(1, 5))
    replay.add(episode(2, 20))
    assert [int(ep["obs"][0, 0, 0, 0]) for ep in replay.episodes] == [2] and replay.ready(8)
    reloaded = Replay(tmp_path, capacity=10, rng=np.random.default_rng(0))
    assert reloaded.load(stored=2) == 1 and reloaded.num_steps == replay.num_steps == 20
    assert [int(ep["obs"][0, 0, 0, 0]) for ep in reloaded.episodes] == [2] and reloaded.ready(8)


def test_sampling_without_a_long_enough_episode_says_what_to_change(tmp_path):
    replay = Replay(None, capacity=100, rng=np.random.default_rng(0))
    replay.add(episode(1, 5))
    with pytest.raises(ValueError, match="seq_len"):
        replay.sample(4, 10)


def test_a_damaged_episode_file_is_named_and_a_deleted_one_overwrites_nothing(tmp_path):
    replay = Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0))
    for i in range(3):
        replay.add(episode(i + 1, 5))
    first, second, third = sorted(tmp_path.glob("*.npz"))
    second.write_bytes(second.read_bytes()[:100])  # truncated, as by a full disk or a broken copy
    with pytest.raises(ReplayError, match=f"{second}: this replay episode cannot be read .* delete it"):
        Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0)).load(stored=3)
    second.unlink()  # what the message offers: the run goes on without that episode
    resumed = Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0))
    assert resumed.load(stored=3) == 2
    resumed.add(episode(4, 5))
    assert [path.name for path in sorted(tmp_path.glob("*.npz"))] == [first.name, third.name, "000003-5.npz"]


def test_an_episode_of_another_task_in_the_replay_is_named_not_a_numpy_error(tmp_path):
    replay = Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0))
    for i in range(2):
        replay.add(episode(i + 1, 5))
    foreign = episode(3, 5)
    foreign["action"] = np.zeros((6, 4), np.float32)  # a 4-dimensional task's episode, copied in from another run
    np.savez_compressed(tmp_path / "000002-5.npz", **foreign)
    with pytest.raises(ReplayError, match=f"000002-5.npz: its actions have 4 dimensions, the run's 2: an episode of "
                                          f"another run or task\\? move it out of {tmp_path}"):
        Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0)).load(stored=3, action_dim=2)
    larger = episode(0, 5) | {"obs": np.zeros((6, 3, 84, 84), np.uint8)}  # the oldest file is the foreign one
    np.savez_compressed(tmp_path / "000000-5.npz", **larger)
    with pytest.raises(ReplayError, match=r"000000-5.npz: its frames are \[3, 84, 84\], the world model's \[3, 64, 64\]"):
        Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0)).load(stored=3)
    (tmp_path / "000000-5.npz").unlink()
    np.savez_compressed(tmp_path / "000002-5.npz", **(foreign | {"obs": foreign["obs"][:, 0]}))  # frames lose a dim
    with pytest.raises(ReplayError, match=r"000002-5.npz: it holds obs uint8 \[6, 64, 64\], action \[6, 4\]"):
        Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0)).load(stored=3, action_dim=2)


def test_episodes_stored_after_the_checkpoint_are_deleted_and_their_numbers_reused(tmp_path, capsys):
    """A run resumes from its checkpoint, which counted `stored` episodes: the ones written after it are collected
    again by the resumed run, so the reload leaves them out and deletes them (their files would hold the same
    numbers as the new ones: `000003-5.npz` and `000003-7.npz` side by side)."""
    replay = Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0))
    for i in range(5):
        replay.add(episode(i + 1, 5))
    resumed = Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0))
    assert resumed.load(stored=3) == 3
    assert f"note: {tmp_path}: 2 episodes stored after the checkpoint" in capsys.readouterr().err
    assert [int(ep["obs"][0, 0, 0, 0]) for ep in resumed.episodes] == [1, 2, 3]
    resumed.add(episode(4, 7))
    assert [path.name for path in sorted(tmp_path.glob("*.npz"))] == ["000000-5.npz", "000001-5.npz", "000002-5.npz",
                                                                     "000003-7.npz"]
    assert Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0)).load(stored=4) == 4
    assert "note" not in capsys.readouterr().err


def test_a_file_not_named_as_a_replay_episode_is_named_not_a_value_error(tmp_path):
    replay = Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0))
    replay.add(episode(1, 5))
    np.savez_compressed(tmp_path / "expert-demo.npz", **episode(2, 5))  # copied in by hand
    with pytest.raises(ReplayError, match=f"{tmp_path / 'expert-demo.npz'}: not the name of a replay episode "
                                          f"\\(NNNNNN-STEPS.npz, as a run writes them\\): move it out of {tmp_path}"):
        Replay(tmp_path, capacity=10_000, rng=np.random.default_rng(0)).load(stored=1)
