"""finetune.datasets: Minari datasets written from real episodes, read back, merged, inspected and refused.

Real Meta-World episodes (fast rendering, 20-90 step time limits) and real Minari/HDF5 storage under a
temporary MINARI_DATASETS_PATH.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import re
import signal
import shutil
import types

import cv2
import gymnasium
import h5py
import minari
import numpy as np
import pytest
import torch
import yaml
from minari.data_collector import EpisodeBuffer

from finetune.datasets import DatasetError, list_datasets, load_episodes, merge_datasets, write_dataset
from finetune.datasets.minari_io import KeptOnInterrupt, hauwm_metadata, open_dataset
from finetune.datasets.cli import main
from finetune.datasets.sources import RandomPolicy, load_agent_policy
from finetune.envs import make_env
from finetune.replay import KEYS, Replay
from finetune.rollout import play_episode
from finetune.run_dir import BEST, CHECKPOINT, save_checkpoint
from hauwm.termination import sigterm_as_interrupt
from finetune.train import build_agent

TASK = "metaworld_drawer_close"


@pytest.fixture(autouse=True)
def datasets_root(tmp_path, monkeypatch):
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


@pytest.fixture(scope="module")
def random_episodes():
    """Three 20-step random episodes of drawer close (replay layout, with success flags)."""
    env = make_env(TASK, seed=0, fast_render=True, time_limit=20)
    policy = RandomPolicy(env.action_space)
    episodes = [play_episode(env, policy) for _ in range(3)]
    env.close()
    return episodes


def write_foreign(dataset_id: str, observation_space, observations, action_space=None, actions=None, rewards=None):
    """A one-episode dataset as another project might write it (Minari's own API, raw frames)."""
    steps = len(observations) - 1 if not isinstance(observations, dict) else len(observations["pixels"]) - 1
    action_space = action_space or gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32)
    actions = np.zeros((steps, *action_space.shape), np.float32) if actions is None else actions
    rewards = np.ones(steps) if rewards is None else rewards
    buffer = EpisodeBuffer(observations=observations, actions=actions, rewards=rewards,
                           terminations=np.zeros(steps, bool), truncations=np.eye(steps, dtype=bool)[-1])
    with pytest.warns(UserWarning):  # Minari asks for an author, a code link...
        minari.create_dataset_from_buffers(dataset_id, [buffer], observation_space=observation_space,
                                           action_space=action_space, jpeg_encoding=False)


@pytest.mark.parametrize("jpeg", [False, True])
def test_round_trip_keeps_actions_rewards_success_and_frames(random_episodes, jpeg):
    write_dataset("test/random-v0", iter(random_episodes), {"task": TASK, "source": "random"}, jpeg=jpeg)
    loaded = load_episodes("test/random-v0", task=TASK, action_dim=4, progress=False)
    assert len(loaded) == 3
    for original, episode in zip(random_episodes, loaded):
        assert episode["obs"].shape == (21, 3, 64, 64) and episode["obs"].dtype == np.uint8
        assert episode["action"].shape == (21, 4) and episode["action"].dtype == np.float32
        for key in ("reward", "success", "terminal"):
            assert episode[key].shape == (21,) and episode[key].dtype == np.float32, key
        np.testing.assert_array_equal(episode["action"], original["action"])
        np.testing.assert_array_equal(episode["reward"], original["reward"])
        np.testing.assert_array_equal(episode["success"], original["success"])
        assert episode["action"][0].sum() == 0 and episode["reward"][0] == 0 and episode["terminal"].sum() == 0
        assert episode["reward"].sum() == pytest.approx(original["reward"].sum())
        error = np.abs(episode["obs"].astype(int) - original["obs"]).mean()
        assert error < 10.0 if jpeg else error == 0  # JPEG is lossy (~6 grey levels), raw is exact
    replay = Replay(None, capacity=1000, rng=np.random.default_rng(0))
    replay.add(loaded[0])  # the loaded layout is the replay's
    assert set(replay.sample(2, 8)) == set(KEYS)


def test_cli_collects_expert_and_random_inspects_merges_and_lists(capsys):
    short = ["--set", "fast_render=true", "--set", "time_limit=90", "--episodes", "2", "--no-progress"]
    assert main(["collect", "--task", TASK, "--policy", "expert", "--dataset-id", "test/expert-v0", *short]) == 0
    assert main(["collect", "--task", TASK, "--policy", "random", "--dataset-id", "test/random-v0", *short]) == 0
    assert "wrote test/random-v0" in capsys.readouterr().out

    rates = {}
    for source in ("expert", "random"):
        assert main(["inspect", f"test/{source}-v0", "--no-progress"]) == 0
        out = capsys.readouterr().out
        assert "episodes        2" in out and "steps           180 (90 per episode)" in out
        assert f"source          {source}" in out and "normalised" in out and "bytes per frame" in out
        assert "episodes of 90 steps, not the suite's 500: not comparable" in out
        rates[source] = float(re.search(r"success rate\s+(\d+)%", out).group(1))
    assert rates["expert"] > rates["random"], rates  # the scripted expert closes the drawer in ~80 steps

    assert main(["merge", "test/random-v0", "test/expert-v0", "--out", "test/medexp-v0", "--no-progress"]) == 0
    merged = load_episodes("test/medexp-v0", task=TASK, action_dim=4, progress=False)
    parts = load_episodes("test/random-v0", progress=False) + load_episodes("test/expert-v0", progress=False)
    assert [e["reward"].sum() for e in merged] == pytest.approx([e["reward"].sum() for e in parts])
    assert minari.load_dataset("test/medexp-v0").combined_datasets == ["test/random-v0", "test/expert-v0"]

    capsys.readouterr()
    (minari.storage.get_dataset_path("test/random-v0") / "data" / "metadata.json").write_text("{half")
    assert main(["list"]) == 0
    listing = capsys.readouterr()
    for dataset_id in ("test/expert-v0", "test/medexp-v0"):
        assert dataset_id in listing.out
    assert "test/random-v0" not in listing.out and "damaged: test/random-v0 (Expecting" in listing.err
    shutil.copytree(minari.storage.get_dataset_path("test/expert-v0"), minari.storage.get_dataset_path("test/copy-v0"))
    assert main(["list"]) == 0  # a copy keeps the ID it was written under, and is read as the one of its directory
    listing = capsys.readouterr()
    assert re.search(r"^test/copy-v0 .* expert .* 2 +180 ", listing.out, re.MULTILINE), listing.out  # "moved" before
    assert "note: test/copy-v0 is a copy of dataset test/expert-v0" in listing.err
    copied = load_episodes("test/copy-v0", task=TASK, action_dim=4, progress=False)
    assert [e["reward"].sum() for e in copied] == [e["reward"].sum() for e in load_episodes("test/expert-v0")]


def test_collect_from_a_runs_replay_and_with_its_agent(tmp_path, tiny_config, capsys):
    rundir = tmp_path / "run"
    cfg = tiny_config(task=TASK, agent="scratch", deter=16, stoch=4, action_repeat=1, time_limit=10, fast_render=True)
    (rundir / "replay").mkdir(parents=True)
    (rundir / "config.yaml").write_text(yaml.safe_dump(dataclasses.asdict(cfg)))
    env = make_env(TASK, seed=0, fast_render=True, time_limit=10)
    replay = Replay(rundir / "replay", capacity=1000, rng=np.random.default_rng(0))
    for _ in range(2):
        replay.add(play_episode(env, RandomPolicy(env.action_space)))
    env.close()
    save_checkpoint(rundir / CHECKPOINT, build_agent(cfg, 4, None, torch.device("cpu")), cfg, {}, {"export_sha256": ""})

    assert main(["collect", "--from-run", str(rundir), "--dataset-id", "test/replay-v0", "--no-progress"]) == 0
    episodes = load_episodes("test/replay-v0", task=TASK, action_dim=4, progress=False)
    assert [e["reward"].sum() for e in episodes] == pytest.approx([e["reward"].sum() for e in replay.episodes])

    args = ["collect", "--policy", "agent", "--checkpoint", str(rundir), "--device", "cpu", "--episodes", "1",
            "--dataset-id", "test/agent-v0", "--no-progress"]
    assert main(args) == 0
    (episode,) = load_episodes("test/agent-v0", task=TASK, action_dim=4, progress=False)
    assert episode["obs"].shape == (11, 3, 64, 64)  # the run's time limit
    assert main(args[:-2] + ["test/repeat-v0", "--set", "action_repeat=4"]) == 2  # was played so, without a word
    assert (f"--set action_repeat=4: the agent of {rundir} was trained acting every 1 frames (its action_repeat); "
            "played every 4 its actions mean something else: drop it") in capsys.readouterr().err
    assert main(["collect", "--from-run", str(rundir), "--task", "dmc_cheetah_run", "--dataset-id", "test/x-v0"]) == 2
    assert "trained on metaworld_drawer_close" in capsys.readouterr().err

    best = args[:-2] + ["test/best-v0", "--best", "--no-progress"]  # best.pt: the run's best evaluation's agent
    assert main(best) == 2 and f"{rundir} holds no best.pt: no evaluation has been kept" in capsys.readouterr().err
    (rundir / CHECKPOINT).rename(rundir / BEST)
    assert main(best) == 0 and "test/best-v0" in list_datasets()
    assert hauwm_metadata(open_dataset("test/best-v0"))["checkpoint"] == str(rundir / BEST)
    assert main(["collect", "--policy", "random", "--best", "--task", TASK, "--episodes", "1", "--dataset-id",
                 "test/y-v0"]) == 2
    assert "--best picks which checkpoint of a run --policy agent plays" in capsys.readouterr().err


def test_sigterm_while_collecting_keeps_the_finished_episodes_like_ctrl_c(datasets_root, monkeypatch, capsys):
    """SLURM's scancel or time limit: the episodes collected so far stay a whole dataset (with its task), exit 143."""
    import finetune.datasets.sources

    policy_episodes = finetune.datasets.sources.policy_episodes

    def terminated_after_one(env, policy, episodes):
        for index, episode in enumerate(policy_episodes(env, policy, episodes)):
            if index == 1:
                os.kill(os.getpid(), signal.SIGTERM)
            yield episode

    monkeypatch.setattr(finetune.datasets.sources, "policy_episodes", terminated_after_one)
    before = signal.getsignal(signal.SIGTERM)
    args = ["collect", "--policy", "random", "--task", TASK, "--episodes", "3", "--dataset-id", "test/cut-v0",
            "--set", "time_limit=5", "--no-progress"]
    assert main(args) == 143
    assert "hauwm datasets: terminated (SIGTERM); the 1 episodes finished are kept as test/cut-v0" in \
        capsys.readouterr().err
    assert open_dataset("test/cut-v0").total_episodes == 1
    assert hauwm_metadata(open_dataset("test/cut-v0"))["task"] == TASK
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_while_an_episode_is_written_waits_for_its_end(random_episodes, monkeypatch, datasets_root, signum):
    """Ctrl-C or SIGTERM in the middle of an episode's write (the HDF5 part of a collection) deleted the whole
    dataset: only a signal between episodes kept the episodes finished."""
    write = minari.MinariDataset.update_dataset_from_buffer
    writes, handlers = [], []  # the handler the signal met, for a failure's message

    def signalled_during_the_second(dataset, buffers) -> None:
        writes.append(len(writes))
        if len(writes) == 2:
            handlers.append(signal.getsignal(signum))
            signal.raise_signal(signum)  # to this thread, whose handler Python runs at once, mid-write
        write(dataset, buffers)

    monkeypatch.setattr(minari.MinariDataset, "update_dataset_from_buffer", signalled_during_the_second)
    kept = None
    try:
        with sigterm_as_interrupt():
            write_dataset("test/kept-v0", iter(random_episodes[:3]), {"task": TASK}, keep_finished=True)
    except KeptOnInterrupt as stopped:
        kept = stopped.dataset
    assert kept is not None, f"the write was not stopped: writes {writes}, the signal met {handlers}, " \
                             f"{signal.Signals(signum).name} is handled by {signal.getsignal(signum)}"
    assert kept.total_episodes == 2 and writes == [0, 1]
    assert hauwm_metadata(open_dataset("test/kept-v0"))["task"] == TASK


def test_a_second_ctrl_c_while_a_merge_deletes_its_part_is_ignored(random_episodes, monkeypatch, datasets_root, capsys):
    """Ctrl-C pressed twice: the second cut the deletion of the merge's part short, which left a dataset directory
    that blocked its ID, and the command said "nothing was written" (collect's env, freed half-way, crashed)."""
    from finetune.datasets import minari_io

    for dataset_id in ("test/a-v0", "test/b-v0"):
        write_dataset(dataset_id, iter(random_episodes[:2]), {"task": TASK})
    write, rmtree = minari.MinariDataset.update_dataset_from_buffer, shutil.rmtree

    def interrupted_during_the_second(dataset, buffers) -> None:
        if dataset.total_episodes == 1:
            signal.raise_signal(signal.SIGINT)  # delivered once the episode is written
        write(dataset, buffers)

    def rmtree_interrupted(path, **kwargs) -> None:
        signal.raise_signal(signal.SIGINT)  # a second Ctrl-C while the part is deleted
        rmtree(path, **kwargs)

    monkeypatch.setattr(minari.MinariDataset, "update_dataset_from_buffer", interrupted_during_the_second)
    monkeypatch.setattr(minari_io.shutil, "rmtree", rmtree_interrupted)
    handler = signal.getsignal(signal.SIGINT)
    assert main(["merge", "test/a-v0", "test/b-v0", "--out", "test/ab-v0", "--no-progress"]) == 130
    assert "hauwm datasets: interrupted; the part of test/ab-v0 written was deleted" in capsys.readouterr().err
    assert not (datasets_root / "test" / "ab-v0").exists()
    assert signal.getsignal(signal.SIGINT) is handler  # as it was, for whatever runs next in this process


def test_sigterm_while_the_command_starts_is_said_as_sigterm(monkeypatch, capsys):
    """SIGTERM while the command imported its modules (torch: seconds) was reported as Ctrl-C, with status 130."""
    from finetune.datasets import cli

    real = cli.run_command

    def terminated_while_importing(args, terminated):
        os.kill(os.getpid(), signal.SIGTERM)
        return real(args, terminated)

    monkeypatch.setattr(cli, "run_command", terminated_while_importing)
    assert main(["list"]) == 143
    assert capsys.readouterr().err.strip() == "hauwm datasets: terminated (SIGTERM); nothing was written"


def test_a_write_that_fails_leaves_no_partial_dataset(random_episodes, monkeypatch, datasets_root):
    def cut_short():
        yield random_episodes[0]
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_dataset("test/cut-v0", cut_short(), {"task": TASK})
    assert not list_datasets()
    with pytest.raises(KeptOnInterrupt) as stopped:  # what `collect` asks for: the finished episodes are kept
        write_dataset("test/kept-v0", cut_short(), {"task": TASK}, keep_finished=True)
    assert stopped.value.dataset.total_episodes == 1 and list(list_datasets()) == ["test/kept-v0"]
    assert hauwm_metadata(open_dataset("test/kept-v0"))["task"] == TASK
    shutil.rmtree(datasets_root / "test" / "kept-v0")
    update_metadata = minari.dataset.minari_storage.MinariStorage.update_metadata

    def full_at_the_end(storage, metadata: dict) -> None:  # the disk fills as our metadata goes in, after every episode
        if "hauwm" in metadata:
            raise OSError(errno.ENOSPC, "No space left on device")
        update_metadata(storage, metadata)

    monkeypatch.setattr(minari.dataset.minari_storage.MinariStorage, "update_metadata", full_at_the_end)
    with pytest.raises(OSError, match="No space left"):
        write_dataset("test/full-v0", iter(random_episodes[:1]), {"task": TASK})
    assert not list_datasets() and not any(datasets_root.rglob("*.hdf5"))

    # HDF5 crashes the process on a full disk: the room for each episode is checked before it is written
    monkeypatch.undo()
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(datasets_root))
    episode_bytes = sum(value.nbytes for value in random_episodes[0].values())
    free = iter([10 * episode_bytes, episode_bytes])  # room for the first episode, not for the second
    monkeypatch.setattr(shutil, "disk_usage", lambda path: types.SimpleNamespace(free=next(free)))
    with pytest.raises(DatasetError, match=r"no room for the next episode under .* MB free, .* MB needed\): free some"
                                           r".*; the part written is deleted"):
        write_dataset("test/room-v0", iter(random_episodes[:2]), {"task": TASK})
    assert not list_datasets()
    free = iter([10 * episode_bytes, episode_bytes])  # what `collect` asks for: the finished episodes are kept, as on
    with pytest.raises(DatasetError, match=r"no room for the next episode .*; the 1 episodes finished are kept as "
                                           r"test/room-v0, a whole dataset"):  # Ctrl-C (they were deleted)
        write_dataset("test/room-v0", iter(random_episodes[:2]), {"task": TASK}, keep_finished=True)
    assert open_dataset("test/room-v0").total_episodes == 1


def test_missing_malformed_and_existing_ids_are_refused_with_what_exists(random_episodes, capsys):
    with pytest.raises(DatasetError, match="there are none"):
        load_episodes("test/nothing-v0")
    write_dataset("test/random-v0", iter(random_episodes[:1]), {"task": TASK, "source": "random"})
    with pytest.raises(DatasetError, match=r"not found under MINARI_DATASETS_PATH=.*the datasets there: test/random-v0"):
        load_episodes("test/nothing-v0")
    with pytest.raises(DatasetError, match="not a Minari ID"):
        load_episodes("test/no-version")
    with pytest.raises(DatasetError, match="already exists"):
        write_dataset("test/random-v0", iter(random_episodes[:1]), {"task": TASK})
    with pytest.raises(DatasetError, match="collected on metaworld_drawer_close, not metaworld_dial_turn"):
        load_episodes("test/random-v0", task="metaworld_dial_turn", action_dim=4)
    with pytest.raises(DatasetError, match="actions have 4 dimensions, the task has 6"):
        load_episodes("test/random-v0", task=None, action_dim=6)
    assert main(["inspect", "test/nothing-v0"]) == 2
    assert "hauwm datasets: error: dataset 'test/nothing-v0' not found" in capsys.readouterr().err
    write_dataset("test/dial-v0", iter(random_episodes[:1]), {"task": "metaworld_dial_turn"})
    with pytest.raises(DatasetError, match="cannot merge datasets with different task"):
        merge_datasets(["test/random-v0", "test/dial-v0"], "test/both-v0")
    write_dataset("test/slow-v0", iter(random_episodes[:1]), {"task": TASK, "fast_render": False})
    write_dataset("test/fast-v0", iter(random_episodes[:1]), {"task": TASK, "fast_render": True})
    with pytest.raises(DatasetError, match="cannot merge datasets with different fast_render"):
        merge_datasets(["test/slow-v0", "test/fast-v0"], "test/both-v0")
    assert main(["inspect", "test/random-v0", "--task", "dmc_cheetah_run"]) == 2  # a task of its own: not replaced
    assert f"test/random-v0 records its task, {TASK}: --task is for a dataset made elsewhere" in capsys.readouterr().err


def test_images_are_found_and_resized_or_refused(capsys):
    steps = 3
    chw = gymnasium.spaces.Box(0, 255, (3, 84, 84), np.uint8)
    t, c, y, x = np.ogrid[:steps + 1, :3, :84, :84]  # frames unlike under a swap of H and W, a crop or a shift
    frames = ((40 * t + 60 * c + 3 * y + x // 2) % 256).astype(np.uint8)  # [T+1, 3, 84, 84]
    write_foreign("other/chw84-v0", chw, frames)
    (episode,) = load_episodes("other/chw84-v0", action_dim=4, progress=False)
    resized = [cv2.resize(frame.transpose(1, 2, 0), (64, 64), interpolation=cv2.INTER_AREA) for frame in frames]
    np.testing.assert_array_equal(episode["obs"], np.stack(resized).transpose(0, 3, 1, 2))  # [T+1, 3, 64, 64]
    assert episode["success"].shape == (steps + 1,) and not episode["success"].any()  # no success in this suite
    assert main(["inspect", "other/chw84-v0", "--task", TASK, "--no-progress"]) == 0  # made elsewhere: 4-dim actions
    assert f"task            {TASK}" in capsys.readouterr().out
    assert main(["inspect", "other/chw84-v0", "--task", "dmc_cheetah_run", "--no-progress"]) == 2  # not its task
    assert "actions have 4 dimensions, dmc_cheetah_run has 6" in capsys.readouterr().err
    assert main(["inspect", "other/chw84-v0", "--task", "cheetah"]) == 2
    assert "--task cheetah is not one of the paper's tasks" in capsys.readouterr().err
    robodesk = gymnasium.spaces.Box(-1.0, 1.0, (5,), np.float32)
    write_foreign("other/desk-v0", chw, np.full((steps + 1, 3, 84, 84), 200, np.uint8), robodesk,
                  np.zeros((steps, 5), np.float32))
    assert main(["inspect", "other/desk-v0", "--task", "robodesk_push_green", "--no-progress"]) == 0
    shown = capsys.readouterr().out  # a paper task, though Table 4's references do not normalise RoboDesk's reward
    assert "task            robodesk_push_green" in shown and "normalised" not in shown

    pixels = gymnasium.spaces.Dict({"pixels": gymnasium.spaces.Box(0, 255, (64, 64, 3), np.uint8),
                                    "state": gymnasium.spaces.Box(-1, 1, (5,), np.float64)})
    write_foreign("other/dict-v0", pixels, {"pixels": np.zeros((steps + 1, 64, 64, 3), np.uint8),
                                            "state": np.zeros((steps + 1, 5))})
    assert load_episodes("other/dict-v0", progress=False)[0]["obs"].shape == (steps + 1, 3, 64, 64)

    tiny = gymnasium.spaces.Box(0, 255, (3, 3, 3), np.uint8)  # was blown up to 64x64 without a word
    write_foreign("other/tiny-v0", tiny, np.zeros((steps + 1, 3, 3, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"images are 3x3, smaller than 32x32: blown up to 64x64 they would hold no "
                                           r"scene the world model knows"):
        load_episodes("other/tiny-v0")
    wide = gymnasium.spaces.Box(0, 255, (32, 96, 3), np.uint8)
    write_foreign("other/wide-v0", wide, np.zeros((steps + 1, 32, 96, 3), np.uint8))
    with pytest.raises(DatasetError, match="images are 32x96, too far from square"):
        load_episodes("other/wide-v0")
    state = gymnasium.spaces.Box(-1, 1, (39,), np.float64)
    write_foreign("other/state-v0", state, np.zeros((steps + 1, 39)))
    with pytest.raises(DatasetError, match="are not RGB images"):
        load_episodes("other/state-v0")


def test_bad_actions_missing_rewards_and_empty_datasets_are_refused(random_episodes):
    frames = gymnasium.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    obs = np.zeros((4, 64, 64, 3), np.uint8)
    write_foreign("other/bounds-v0", frames, obs, gymnasium.spaces.Box(-2.0, 2.0, (4,), np.float32))
    with pytest.raises(DatasetError, match=r"action bounds per dimension are \[-2, 2\], \[-2, 2\], \[-2, 2\], \[-2, 2\]"):
        load_episodes("other/bounds-v0", task=TASK, action_dim=4)
    write_foreign("other/nan-v0", frames, obs, rewards=np.full(3, np.nan))
    with pytest.raises(DatasetError, match="rewards are missing"):
        load_episodes("other/nan-v0")
    write_foreign("other/nanactions-v0", frames, obs, actions=np.full((3, 4), np.nan, np.float32))
    with pytest.raises(DatasetError, match="episode 0: actions hold NaN or infinite values"):
        load_episodes("other/nanactions-v0")
    write_foreign("other/columnrewards-v0", frames, obs, rewards=np.arange(3.0)[:, None])  # [T, 1]: read as [T]
    assert load_episodes("other/columnrewards-v0", progress=False)[0]["reward"].tolist() == [0, 0, 1, 2]
    write_foreign("other/pairrewards-v0", frames, obs, rewards=np.ones((3, 2)))
    with pytest.raises(DatasetError, match=r"episode 0: rewards are shaped \[3, 2\]; HAUWM needs one reward a step"):
        load_episodes("other/pairrewards-v0")

    dataset = write_dataset("test/norewards-v0", iter(random_episodes[:1]), {"task": TASK})
    with h5py.File(dataset.storage.data_path / "main_data.hdf5", "a") as f:
        del f["episode_0/rewards"]
    with pytest.raises(DatasetError, match="episode 0 could not be read.*rewards"):
        load_episodes("test/norewards-v0")

    dataset = write_dataset("test/cut-v0", iter(random_episodes[:1]), {"task": TASK})
    with h5py.File(dataset.storage.data_path / "main_data.hdf5", "a") as f:  # cut to its first observation
        for name in ("observations", "actions", "rewards", "terminations", "truncations"):
            kept = f[f"episode_0/{name}"][:1 if name == "observations" else 0]
            del f[f"episode_0/{name}"]
            f[f"episode_0/{name}"] = kept
    with pytest.raises(DatasetError, match=r"episode 0 holds no steps \(no actions\)"):  # "no rewards"
        load_episodes("test/cut-v0")

    with pytest.warns(UserWarning):
        minari.create_dataset_from_buffers("other/empty-v0", [], observation_space=frames,
                                           action_space=gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32))
    with pytest.raises(DatasetError, match="holds no episodes"):
        load_episodes("other/empty-v0")


def _replace_array(dataset, name: str, change) -> None:
    """Replace episode 0's array `name` (e.g. "observations", "infos/success") by `change(array)`."""
    with h5py.File(dataset.storage.data_path / "main_data.hdf5", "a") as f:
        array = f[f"episode_0/{name}"][()]
        del f[f"episode_0/{name}"]
        f[f"episode_0/{name}"] = change(array)


@pytest.mark.parametrize("name, change, message", [
    ("observations", lambda a: a[:, :, :32], r"observations are uint8 \[21, 64, 32, 3\], the dataset's observation space "
                                            r"says uint8 \[T\+1, 64, 64, 3\]"),
    ("observations", lambda a: np.concatenate([a, a[..., :1]], -1), r"observations are uint8 \[21, 64, 64, 4\]"),
    ("observations", lambda a: a.astype(np.float32), r"observations are float32 \[21, 64, 64, 3\]"),
    ("actions", lambda a: np.concatenate([a, a[:, :1]], 1), r"actions are \[20, 5\], the dataset's action space says "
                                                           r"\[T, 4\]"),
    ("infos/success", lambda a: np.where(a > 0, b"yes", b"no"), r"infos/success holds \|S3 values, not numbers"),
    ("terminations", lambda a: a[:-3], r"terminations hold 17 entries, truncations 20, for 20 steps"),
], ids=["narrower", "rgba", "float", "action-width", "success-strings", "terminations-short"])
def test_an_episode_whose_arrays_differ_from_the_datasets_spaces_is_refused_naming_them(random_episodes, name, change,
                                                                                       message):
    """Such episodes were read as they were: training failed deep in the replay (`all input arrays must have the same
    shape`) or the model (`preprocess expects uint8 frames`), and inspect raised numpy's errors or said nothing."""
    dataset = write_dataset("test/altered-v0", iter(random_episodes[:1]), {"task": TASK})
    _replace_array(dataset, name, change)
    with pytest.raises(DatasetError, match=rf"dataset 'test/altered-v0', episode 0: {message}"):
        load_episodes("test/altered-v0", task=TASK, action_dim=4, progress=False)


def test_a_dataset_of_another_task_is_named_so_before_its_spaces_are_checked(random_episodes):
    write_dataset("test/dial-v0", iter(random_episodes[:1]), {"task": "metaworld_dial_turn"})
    with pytest.raises(DatasetError, match="was collected on metaworld_dial_turn, not dmc_cheetah_run"):
        load_episodes("test/dial-v0", task="dmc_cheetah_run", action_dim=6)  # "actions have 4 dimensions" before


def test_a_device_torch_does_not_know_is_named_as_the_device_not_the_run(tmp_path):
    with pytest.raises(DatasetError, match=r"^device 'gpu' is not a device"):  # "--checkpoint RUNDIR: device …" before
        load_agent_policy(tmp_path, None, "gpu", False, 4)


def test_tasks_without_a_scripted_expert_say_what_to_use(capsys):
    args = ["collect", "--task", "dmc_cartpole_swingup", "--policy", "expert", "--episodes", "1",
            "--dataset-id", "test/x-v0", "--set", "time_limit=5", "--no-progress"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "dmc_cartpole_swingup has no scripted expert" in err and "--policy agent --checkpoint RUNDIR" in err


def test_bad_env_settings_are_refused(capsys):
    base = ["collect", "--task", TASK, "--policy", "random", "--episodes", "1", "--dataset-id", "test/x-v0"]
    for setting, message in (("time_limit=abc", "time_limit must be a whole number"), ("fast_render=2", "true or false"),
                             ("image_size=32", "not an env setting"), ("time_limit=600", "exceeds Meta-World's 500-step episodes; use time_limit <= 500"),
                             ("action_repeat=1000", "exceeds Meta-World's 500-step episodes; lower action_repeat (at most 500")):
        assert main([*base, "--set", setting]) == 2, setting
        assert message in capsys.readouterr().err, setting


def test_bad_collect_flags_are_refused_before_an_env_is_made(capsys):
    base = ["collect", "--task", TASK, "--episodes", "1", "--dataset-id", "test/x-v0"]
    for flags, message in ((["--policy", "expert", "--action-noise", "nan"], "--action-noise is a standard deviation"),
                           (["--policy", "expert", "--action-noise", "-0.5"], "a number >= 0; got -0.5"),
                           (["--policy", "random", "--action-noise", "0.5"], "not to --policy random; drop it"),
                           (["--policy", "random", "--seed", "-5"], "--seed must be a whole number in 0..2^32-1"),
                           # these were dropped without a word
                           (["--policy", "expert", "--sample"], "--sample is for --policy agent (a run's trained agent), "
                                                                "not --policy expert; drop it"),
                           (["--policy", "expert", "--checkpoint", "RUN"], "--checkpoint is for --policy agent"),
                           (["--policy", "random", "--pretrained", "EXPORT"], "--pretrained is for --policy agent"),
                           (["--from-run", "RUN", "--seed", "5"], "--from-run takes the run's replay as it is, which "
                                                                  "no seed changes: drop --seed")):
        assert main([*base, *flags]) == 2, flags
        assert message in capsys.readouterr().err, flags


def test_a_runs_replay_records_the_suites_time_limit_where_the_run_left_it_to_the_suite(tmp_path, tiny_config):
    rundir = tmp_path / "run"
    cfg = tiny_config(task=TASK, agent="scratch", action_repeat=1, fast_render=True)  # time_limit: the suite's
    (rundir / "replay").mkdir(parents=True)
    (rundir / "config.yaml").write_text(yaml.safe_dump(dataclasses.asdict(cfg)))
    env = make_env(TASK, seed=0, fast_render=True, time_limit=4)
    Replay(rundir / "replay", capacity=100, rng=np.random.default_rng(0)).add(
        play_episode(env, RandomPolicy(env.action_space)))
    env.close()
    assert main(["collect", "--from-run", str(rundir), "--dataset-id", "test/suite-limit-v0", "--no-progress"]) == 0
    assert hauwm_metadata(open_dataset("test/suite-limit-v0"))["time_limit"] == 500  # Meta-World's 500 steps


def test_a_run_without_replay_episodes_says_how_to_record_its_agent(tmp_path, capsys):
    (tmp_path / "config.yaml").write_text("task: metaworld_drawer_close\nparadigm: offline\nmodel_heads: 7\n")
    assert main(["collect", "--from-run", str(tmp_path), "--dataset-id", "test/replay-v0"]) == 2
    err = capsys.readouterr().err
    assert "an offline run never acts" in err and f"--policy agent --checkpoint {tmp_path}" in err


def test_a_merge_with_a_dataset_made_elsewhere_keeps_the_task_the_others_record(random_episodes):
    settings = {"task": TASK, "source": "random", "action_repeat": 1, "fast_render": True, "image_size": 64}
    write_dataset("test/random-v0", iter(random_episodes[:1]), settings)
    write_foreign("other/plain-v0", gymnasium.spaces.Box(0, 255, (64, 64, 3), np.uint8), np.zeros((4, 64, 64, 3), np.uint8))
    merged = merge_datasets(["test/random-v0", "other/plain-v0"], "test/mixed-v0", progress=False)
    assert {key: hauwm_metadata(merged)[key] for key in settings if key != "source"} == \
        {key: value for key, value in settings.items() if key != "source"}
    with pytest.raises(DatasetError, match=f"collected on {TASK}, not metaworld_dial_turn"):
        load_episodes("test/mixed-v0", task="metaworld_dial_turn")


def test_a_merge_that_names_a_dataset_twice_is_refused_not_doubled(random_episodes, capsys):
    write_dataset("test/random-v0", iter(random_episodes[:1]), {"task": TASK, "source": "random"})
    write_dataset("test/other-v0", iter(random_episodes[1:2]), {"task": TASK, "source": "random"})
    assert main(["merge", "test/random-v0", "test/other-v0", "test/random-v0", "--out", "test/merged-v0",
                 "--no-progress"]) == 2
    assert "test/random-v0 is named 2 times: the merge would hold each of its episodes that often" in capsys.readouterr().err
    assert "test/merged-v0" not in list_datasets()


def test_a_merge_with_a_dataset_already_in_one_of_its_sources_is_refused_not_doubled(random_episodes, capsys):
    """`merge medexp expert`, medexp being medium + expert: the expert episodes went in twice (found by a review)."""
    write_dataset("test/medium-v0", iter(random_episodes[:1]), {"task": TASK, "source": "random", "seed": 0})
    write_dataset("test/expert-v0", iter(random_episodes[1:2]), {"task": TASK, "source": "random", "seed": 1})
    write_dataset("test/other-v0", iter(random_episodes[2:3]), {"task": TASK, "source": "random", "seed": 2})
    assert main(["merge", "test/medium-v0", "test/expert-v0", "--out", "test/medexp-v0", "--no-progress"]) == 0
    assert main(["merge", "test/medexp-v0", "test/expert-v0", "--out", "test/twice-v0", "--no-progress"]) == 2
    assert ("the episodes of test/expert-v0 are in test/medexp-v0 and in test/expert-v0: the merge would hold them "
            "twice") in capsys.readouterr().err
    assert main(["merge", "test/other-v0", "test/medexp-v0", "--out", "test/all-v0", "--no-progress"]) == 0
    assert main(["merge", "test/all-v0", "test/medium-v0", "--out", "test/twice-v0", "--no-progress"]) == 2  # nested
    assert "the episodes of test/medium-v0 are in test/all-v0 and in test/medium-v0" in capsys.readouterr().err
    assert "test/twice-v0" not in list_datasets()
    assert len(load_episodes("test/all-v0")) == 3


def test_a_merge_of_two_datasets_collected_alike_is_refused_not_doubled(random_episodes, capsys):
    """Following the advice after a Ctrl-C (collect more under another ID, merge them) with the same command played
    the same episodes again: the merge held each twice, byte for byte, without a word."""
    recipe = {"task": TASK, "source": "expert", "seed": 0, "action_noise": 0.0, "time_limit": 20}
    write_dataset("test/first-v0", iter(random_episodes[:1]), recipe)
    write_dataset("test/more-v0", iter(random_episodes[:2]), recipe)
    write_dataset("test/seed1-v0", iter(random_episodes[1:2]), {**recipe, "seed": 1})
    assert main(["merge", "test/first-v0", "test/more-v0", "--out", "test/merged-v0", "--no-progress"]) == 2
    assert ("test/first-v0 and test/more-v0 were collected alike (expert, seed 0, the same settings): their first "
            "episodes are the same ones; collect test/more-v0 again with another --seed") in capsys.readouterr().err
    assert main(["merge", "test/first-v0", "test/seed1-v0", "--out", "test/merged-v0", "--no-progress"]) == 0
    agent = {**recipe, "source": "agent", "checkpoint": "runs/x/checkpoint.pt", "actions": "mode"}  # trained on since?
    write_dataset("test/agent-v0", iter(random_episodes[:1]), agent)
    write_dataset("test/agent-later-v0", iter(random_episodes[1:2]), agent)
    assert main(["merge", "test/agent-v0", "test/agent-later-v0", "--out", "test/agents-v0", "--no-progress"]) == 0


def test_a_dataset_inside_another_datasets_directory_is_refused(random_episodes, datasets_root):
    """`collect --dataset-id test/outer-v0/inner-v0` wrote a dataset that `list` did not show, and that deleting
    test/outer-v0, as its messages advise, would delete too."""
    write_dataset("test/outer-v0", iter(random_episodes[:1]), {"task": TASK})
    with pytest.raises(DatasetError, match=r"dataset ID 'test/outer-v0/inner-v0' lies inside the directory of dataset "
                                           r"test/outer-v0 \(.*\): use an ID of its own, e.g. test/inner-v0"):
        write_dataset("test/outer-v0/inner-v0", iter(random_episodes[:1]), {"task": TASK})
    assert not (datasets_root / "test" / "outer-v0" / "inner-v0").exists()


def test_list_reads_each_directory_once_and_makes_none(random_episodes, datasets_root, tmp_path, monkeypatch, capsys):
    """A symlink to a directory above it made `list` walk the loop until the paths grew too long (1,313 lines about
    datasets that are one); and `list` made the datasets' directory where there was none."""
    write_dataset("test/kept-v0", iter(random_episodes[:1]), {"task": TASK})
    (datasets_root / "test" / "loop").symlink_to(datasets_root)
    (datasets_root / "a-link").symlink_to(datasets_root / "test")  # listed first, a dataset of its own: as before
    assert main(["list"]) == 0
    listed = capsys.readouterr()
    assert re.findall(r"^\S+kept-v0", listed.out, re.MULTILINE) == ["a-link/kept-v0", "test/kept-v0"]
    assert listed.err.strip() == "note: a-link/kept-v0 is a copy of dataset test/kept-v0 (its data/metadata.json keeps " \
                                 "that ID); it is read as the dataset of its directory"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "none-yet"))
    assert main(["list"]) == 0
    assert f"no datasets under {tmp_path / 'none-yet'}" in capsys.readouterr().out
    assert not (tmp_path / "none-yet").exists()


def test_a_dict_observation_without_a_uint8_image_names_its_entries():
    floats = gymnasium.spaces.Dict({"pixels": gymnasium.spaces.Box(0.0, 1.0, (64, 64, 3), np.float32)})
    write_foreign("other/floatpixels-v0", floats, {"pixels": np.zeros((4, 64, 64, 3), np.float32)})
    with pytest.raises(DatasetError, match=r"Dict observations \(pixels Box\(0.0, 1.0, \(64, 64, 3\), float32\)\) hold no "
                                           r"uint8 RGB image entries"):
        load_episodes("other/floatpixels-v0")


def test_a_dataset_in_a_storage_format_not_installed_is_refused_with_its_message(random_episodes, monkeypatch):
    write_dataset("test/random-v0", iter(random_episodes[:1]), {"task": TASK})

    def arrow(dataset_id):  # what minari raises for an Arrow dataset without pyarrow
        raise ImportError('pyarrow is not installed. Please install it using `pip install "minari[arrow]"`')

    monkeypatch.setattr(minari, "load_dataset", arrow)
    with pytest.raises(DatasetError, match=r"'test/random-v0' at \S+ is stored in a format this installation cannot "
                                           r"read \(pyarrow is not installed. .*minari\[arrow\]"):
        open_dataset("test/random-v0")


def test_collect_from_a_run_whose_replay_holds_another_tasks_episode_writes_nothing(tmp_path, tiny_config, capsys):
    rundir = tmp_path / "run"
    cfg = tiny_config(task=TASK, agent="scratch", action_repeat=1, time_limit=5, fast_render=True)
    (rundir / "replay").mkdir(parents=True)
    (rundir / "config.yaml").write_text(yaml.safe_dump(dataclasses.asdict(cfg)))
    replay = Replay(rundir / "replay", capacity=1000, rng=np.random.default_rng(0))
    for width in (4, 1):  # the run's own episode, then one of a 1-dimensional task copied in
        replay.add({"obs": np.zeros((6, 3, 64, 64), np.uint8), "action": np.zeros((6, width), np.float32),
                    "reward": np.zeros(6, np.float32)})
    assert main(["collect", "--from-run", str(rundir), "--dataset-id", "test/mixed-v0", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"{rundir / 'replay' / '000001-5.npz'}: its actions have 1 dimensions, the run's 4" in err
    assert "Traceback" not in err and "test/mixed-v0" not in list_datasets()  # the partial dataset is deleted


def test_a_relative_datasets_path_is_read_from_the_directory_the_command_ran_in(tmp_path, monkeypatch, capsys):
    """Minari joined a relative root to itself: `minari/hauwm/x/data/minari/hauwm/x/data/main_data.hdf5`."""
    from hauwm.cli import main as hauwm

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MINARI_DATASETS_PATH", "relative-root")
    assert hauwm(["datasets", "collect", "--policy", "random", "--task", TASK, "--episodes", "1", "--dataset-id",
                  "test/relative-v0", "--set", "time_limit=3", "--no-progress"]) == 0
    assert hauwm(["datasets", "inspect", "test/relative-v0"]) == 0
    assert "test/relative-v0" in capsys.readouterr().out
    assert (tmp_path / "relative-root" / "test" / "relative-v0" / "data" / "main_data.hdf5").is_file()


# A script that writes dataset sys.argv[1] from the episodes its `episodes()` yields (each the same 4 steps).
WRITER = """
import os, signal, sys, time
from pathlib import Path
import numpy as np
from finetune.datasets import write_dataset

STEPS = 4
EPISODE = {"obs": np.zeros((STEPS + 1, 3, 64, 64), np.uint8), "action": np.zeros((STEPS + 1, 4), np.float32),
           "reward": np.ones(STEPS + 1, np.float32), "success": np.zeros(STEPS + 1, np.float32),
           "terminal": np.zeros(STEPS + 1, np.float32)}
{episodes}
write_dataset(sys.argv[1], episodes(), {"task": "metaworld_drawer_close", "source": "random"})
"""
KILLED_WRITER = WRITER.replace("{episodes}", """
def episodes():
    yield EPISODE
    yield EPISODE
    os.kill(os.getpid(), signal.SIGKILL)  # the writer dies between two episodes, with no chance to clean up
""")


def test_a_dataset_whose_writer_was_killed_is_refused_as_unfinished(datasets_root, capsys):
    """SIGKILL (the OOM killer, a node lost) in the middle of a collection left a dataset that read as a whole one
    made elsewhere: its episodes so far, with no task recorded, so offline RL trained on it without a word."""
    import subprocess
    import sys

    killed = subprocess.run([sys.executable, "-c", KILLED_WRITER, "test/killed-v0"], capture_output=True, text=True,
                            env={**os.environ, "MINARI_DATASETS_PATH": str(datasets_root)})
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert (datasets_root / "test" / "killed-v0" / "data").is_dir()  # its episodes are on disk
    unfinished = r"'test/killed-v0' at .* is unfinished: its writer .* was killed after 2 episodes.* delete that directory"
    with pytest.raises(DatasetError, match=unfinished):
        load_episodes("test/killed-v0")
    assert main(["inspect", "test/killed-v0"]) == 2
    assert re.search(unfinished, capsys.readouterr().err)
    assert main(["list"]) == 0
    listed = capsys.readouterr()
    assert re.search(unfinished, listed.err) and "test/killed-v0" not in listed.out


# A writer that waits for a file to appear before each of its two episodes: the test looks at the dataset there.
PAUSED_WRITER = WRITER.replace("{episodes}", """
def episodes():
    for go in ("go1", "go2"):
        print("waiting", go, flush=True)
        while not (Path(sys.argv[2]) / go).exists():
            time.sleep(0.05)
        yield EPISODE
""")


def test_a_dataset_being_written_refuses_a_second_writer_and_says_it_is_being_written(random_episodes, datasets_root,
                                                                                        tmp_path, capsys):
    """Two collects into one new ID both crashed, and the one Minari refused deleted what the other had written;
    a reader of the dataset being written was told that its writer had been killed, and to delete it."""
    import subprocess
    import sys

    writer = subprocess.Popen([sys.executable, "-c", PAUSED_WRITER, "test/busy-v0", str(tmp_path)], text=True,
                              stdout=subprocess.PIPE, env={**os.environ, "MINARI_DATASETS_PATH": str(datasets_root)})
    try:
        busy = f"dataset 'test/busy-v0' is being written by another process \\(pid {writer.pid}\\): wait for it"
        assert writer.stdout.readline() == "waiting go1\n"  # before its first episode: no directory yet
        with pytest.raises(DatasetError, match=busy):
            write_dataset("test/busy-v0", iter(random_episodes[:1]), {"task": TASK})
        (tmp_path / "go1").touch()
        assert writer.stdout.readline() == "waiting go2\n"  # its first episode is written
        with pytest.raises(DatasetError, match=busy):
            write_dataset("test/busy-v0", iter(random_episodes[:1]), {"task": TASK})
        being_written = f"'test/busy-v0' at .* is being written \\(by pid {writer.pid}; 1 episodes so far\\): wait"
        with pytest.raises(DatasetError, match=being_written):
            load_episodes("test/busy-v0")
        assert main(["list"]) == 0 and re.search(being_written, capsys.readouterr().err)
        (tmp_path / "go2").touch()
        assert writer.wait(timeout=120) == 0
    finally:
        writer.kill()
    assert len(load_episodes("test/busy-v0")) == 2  # whole: the refused writers deleted nothing
    assert not list(datasets_root.rglob(".*.writing"))


def test_a_directory_not_named_as_a_dataset_is_listed_apart_not_a_traceback(random_episodes, datasets_root, capsys):
    """Minari's own listing stopped with a TypeError at a directory without the -vN version (a backup copy), and so
    did every message that lists the datasets there are."""
    write_dataset("test/kept-v0", iter(random_episodes[:1]), {"task": TASK})
    shutil.copytree(datasets_root / "test" / "kept-v0", datasets_root / "test" / "kept-backup")
    assert main(["list"]) == 0
    listed = capsys.readouterr()
    assert "test/kept-v0" in listed.out and "kept-backup" not in listed.out
    assert "damaged: test/kept-backup (dataset ID 'test/kept-backup' is not a Minari ID" in listed.err
    with pytest.raises(DatasetError, match="'test/typo-v0' not found .* the datasets there: test/kept-v0$"):
        load_episodes("test/typo-v0")


def test_the_normalised_return_of_episodes_of_another_length_than_the_suites_says_it_is_not_comparable():
    """Episodes of 30, 30 and 500 steps: only the longest was looked at, and the caveat was left out; episodes longer
    than the suite's (a larger time limit) had none either."""
    from finetune.datasets.summary import Summary

    summary = Summary(TASK)
    for steps in (30, 30, 500):
        summary.add({"reward": np.ones(steps + 1, np.float32)})
    assert "2 of 3 episodes of another length than the suite's 500 steps (30-500): not comparable" in \
        "\n".join(summary.lines())
    summary = Summary(TASK)
    for steps in (500, 1000):
        summary.add({"reward": np.ones(steps + 1, np.float32)})
    assert "1 of 2 episodes of another length than the suite's 500 steps (500-1000): not comparable" in \
        "\n".join(summary.lines())
    summary = Summary(TASK)
    for steps in (10, 30):  # all shorter, of two lengths: it said "episodes of 30 steps"
        summary.add({"reward": np.ones(steps + 1, np.float32)})
    assert "; episodes of 10-30 steps, not the suite's 500: not comparable" in "\n".join(summary.lines())


@pytest.mark.parametrize("damage", [lambda m: {**m, "hauwm": None}, lambda m: {**m, "hauwm": "drawer"}, lambda m: [],
                                    # fields of the wrong kind: a TypeError in `list` (hiding every dataset), in
                                    # Minari's loading or in the summary; a task of null read as "collected on None"
                                    lambda m: {**m, "dataset_size": None}, lambda m: {**m, "total_episodes": "two"},
                                    lambda m: {**m, "hauwm": {**m["hauwm"], "task": None}},
                                    lambda m: {**m, "hauwm": {**m["hauwm"], "action_repeat": "1"}}],
                         ids=["our-settings-null", "our-settings-text", "a-list", "size-null", "episodes-text",
                              "task-null", "action-repeat-text"])
def test_a_metadata_file_of_another_shape_is_named_damaged_and_the_others_listed(random_episodes, datasets_root,
                                                                                 capsys, damage):
    """One such file made `hauwm datasets list` fail with an AttributeError or TypeError, for every dataset there."""
    write_dataset("test/kept-v0", iter(random_episodes[:1]), {"task": TASK})
    write_dataset("test/odd-v0", iter(random_episodes[:1]), {"task": TASK})
    path = datasets_root / "test" / "odd-v0" / "data" / "metadata.json"
    path.write_text(json.dumps(damage(json.loads(path.read_text()))))
    assert main(["list"]) == 0
    listed = capsys.readouterr()
    assert "test/kept-v0" in listed.out and "test/odd-v0" not in listed.out
    assert re.search(r"damaged: test/odd-v0 \(.*metadata.json.*\): write it again, or delete", listed.err), listed.err
    assert main(["inspect", "test/odd-v0", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "test/odd-v0" in err and "metadata.json" in err and "Traceback" not in err


def test_an_episode_that_ends_before_its_last_step_is_refused():
    """A termination at step 3 of 8 was read as no terminal at all, and the steps after it trained on."""
    space = gymnasium.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    observations = np.zeros((9, 64, 64, 3), np.uint8)
    buffer = EpisodeBuffer(observations=observations, actions=np.zeros((8, 4), np.float32), rewards=np.ones(8),
                           terminations=np.eye(8, dtype=bool)[2], truncations=np.eye(8, dtype=bool)[-1])
    with pytest.warns(UserWarning):
        minari.create_dataset_from_buffers("test/ends-early-v0", [buffer], observation_space=space,
                                           action_space=gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32))
    with pytest.raises(DatasetError, match="episode 0: it ends at step 3 of 8 .* split it there"):
        load_episodes("test/ends-early-v0")


def test_ctrl_c_says_whether_a_dataset_was_begun_and_deleted(random_episodes, monkeypatch, capsys):
    """Ctrl-C in a collect's first episode said "a dataset being written was deleted"; nothing had been written."""
    from finetune.datasets import cli, minari_io

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "collect", interrupted)
    assert main(["collect", "--task", TASK, "--policy", "random", "--episodes", "1", "--dataset-id", "test/x-v0"]) == 130
    assert "hauwm datasets: interrupted; nothing was written" in capsys.readouterr().err
    write_dataset("test/a-v0", iter(random_episodes[:1]), {"task": TASK})
    write_dataset("test/b-v0", iter(random_episodes[1:2]), {"task": TASK})
    iterate_episodes = minari_io.iterate_episodes

    def cut_at_the_second_source(dataset_id, **kwargs):  # Ctrl-C as the merge reads its second source
        if dataset_id == "test/b-v0":
            raise KeyboardInterrupt
        return iterate_episodes(dataset_id, **kwargs)

    monkeypatch.setattr(minari_io, "iterate_episodes", cut_at_the_second_source)
    assert main(["merge", "test/a-v0", "test/b-v0", "--out", "test/ab-v0"]) == 130
    assert "hauwm datasets: interrupted; the part of test/ab-v0 written was deleted" in capsys.readouterr().err
    assert "test/ab-v0" not in list_datasets()


def test_a_datasets_path_that_is_a_file_is_named_as_the_variable(tmp_path, monkeypatch, capsys):
    (tmp_path / "afile").touch()
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "afile"))
    assert main(["list"]) == 2
    assert (f"hauwm datasets: error: MINARI_DATASETS_PATH={tmp_path / 'afile'} is a file, not the datasets' directory: "
            "set MINARI_DATASETS_PATH to a directory") in capsys.readouterr().err
    args = ["collect", "--task", TASK, "--policy", "random", "--episodes", "1", "--dataset-id", "test/x-v0", "--set",
            "time_limit=3", "--no-progress"]
    assert main(args) == 2
    assert (f"hauwm datasets: error: MINARI_DATASETS_PATH={tmp_path / 'afile'}: the datasets' directory cannot be made "
            "there (File exists): set MINARI_DATASETS_PATH to a directory") in capsys.readouterr().err


def test_episodes_that_end_in_a_terminal_state_are_counted_and_a_run_says_it_treats_them_as_time_limits(
        random_episodes, tiny_config, capsys):
    """HAUWM's learners have no continuation head: a dataset with terminal states (someone else's) was trained on as
    if its episodes had run into a time limit, and neither `inspect` nor the run said so."""
    from finetune.train import load_dataset

    ended = [dict(episode, terminal=np.eye(len(episode["reward"]), dtype=np.float32)[-1]) if i == 1 else episode
             for i, episode in enumerate(random_episodes)]
    write_dataset("test/terminal-v0", iter(ended), {"task": TASK})
    assert main(["inspect", "test/terminal-v0", "--no-progress"]) == 0
    assert "terminal        1 of 3 episodes end in a terminal state (HAUWM's learners have no continuation head" \
        in capsys.readouterr().out
    episodes = load_dataset("test/terminal-v0", tiny_config(task=TASK), 4, "--dataset")
    assert [episode["terminal"][-1] for episode in episodes] == [0, 1, 0]
    assert "note: 1 of the 3 episodes of --dataset test/terminal-v0 end in a terminal state: HAUWM's learners have " \
           "no continuation head" in capsys.readouterr().err
    write_dataset("test/time-limits-v0", iter(random_episodes), {"task": TASK})  # the paper's tasks: no word
    assert main(["inspect", "test/time-limits-v0", "--no-progress"]) == 0
    load_dataset("test/time-limits-v0", tiny_config(task=TASK), 4, "--dataset")
    assert "terminal" not in "".join(capsys.readouterr())


@pytest.mark.parametrize("made_here", [True, False], ids=["collected", "made-elsewhere"])
@pytest.mark.parametrize("damage", ["zeroed", "truncated"])
def test_a_damaged_hdf5_file_is_named_not_a_traceback(random_episodes, datasets_root, capsys, made_here, damage):
    """Bytes zeroed inside the HDF5 file raised h5py's RuntimeError through inspect, merge and the runs; a truncated
    file of a dataset made elsewhere raised its OSError where inspect looked for success flags."""
    if made_here:
        write_dataset("test/damaged-v0", iter(random_episodes), {"task": TASK})
    else:
        write_foreign("test/damaged-v0", gymnasium.spaces.Box(0, 255, (64, 64, 3), np.uint8),
                      np.zeros((9, 64, 64, 3), np.uint8))
    path = datasets_root / "test" / "damaged-v0" / "data" / "main_data.hdf5"
    with open(path, "r+b") as file:
        if damage == "zeroed":  # the layout's own records, past the superblock
            file.seek(2000)
            file.write(bytes(4000))
        else:
            file.truncate(5000)
    assert main(["inspect", "test/damaged-v0", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "test/damaged-v0" in err and "write it again" in err and "Traceback" not in err, err
    with pytest.raises(DatasetError, match="test/damaged-v0.* write it again"):
        load_episodes("test/damaged-v0")
    write_dataset("test/kept-v0", iter(random_episodes[:1]), {"task": TASK})
    assert main(["merge", "test/kept-v0", "test/damaged-v0", "--out", "test/merged-v0", "--no-progress"]) == 2
    assert "Traceback" not in capsys.readouterr().err
    assert not (datasets_root / "test" / "merged-v0").exists()


def test_the_env_settings_collect_takes_are_the_configs():
    from finetune.config import ENV_SETTINGS
    from finetune.datasets import cli

    assert cli.ENV_SETTINGS == ENV_SETTINGS  # repeated there so that `--help` does not import torch
