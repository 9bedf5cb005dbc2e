"""Short fine-tuning runs, one task per suite: they complete, write logs and a checkpoint, and resume."""

from __future__ import annotations

import contextlib
import csv
import os

import numpy as np
import pytest
import torch

from finetune.cli import best_kept, main
from finetune.config import FinetuneError, load_config
from finetune.agent import Agent
from finetune.envs.base import PixelEnv
from finetune.run_dir import (BEST, CHECKPOINT, exclusive, export_fingerprint, load_checkpoint, read_state, resume,
                               run_config, run_fingerprint, save_checkpoint)
import finetune.train
from finetune.train import (EVAL_SEED, build_agent, episode_seed, evaluate, incomparable_returns_note, resolve_device,
                            start_run, task_env, train)
from model.export import export_frozen
from model.world_model import WorldModel

# (task, action repeat, agent steps per episode, env-step budget)
SUITES = [("metaworld_drawer_close", 1, 20, 100), ("robodesk_open_slide", 2, 10, 80)]


def rows(path):
    with path.open() as f:
        return list(csv.DictReader(f))


def tiny_run_settings(logdir, **extra) -> list[str]:
    settings = dict(hidden=24, units=32, batch_size=4, seq_len=8, horizon=5, train_every=10, threads=1,
                    log_every=40, fast_render=True, **extra)
    args = ["--logdir", str(logdir), "--device", "cpu", "--no-progress"]
    for key, value in settings.items():
        args += ["--set", f"{key}={value}"]
    return args


def test_dmc_run_through_the_cli_writes_logs_and_a_checkpoint_that_resumes(export_dir, tmp_path, capsys, monkeypatch):
    eval_seeds = []
    monkeypatch.setattr(finetune.train, "task_env", lambda cfg, seed: eval_seeds.append(seed) or task_env(cfg, seed))
    logdir = tmp_path / "run"
    args = ["--config", "configs/finetune/demo.yaml", "--pretrained", str(export_dir)]
    args += tiny_run_settings(logdir, time_limit=20, prefill=80, eval_every=100, checkpoint_every=100, eval_episodes=1)
    assert main(args + ["--steps", "200"]) == 0
    assert "finished dmc_cartpole_swingup" in capsys.readouterr().out
    for name in ("train.csv", "eval.csv", "episodes.csv", "config.yaml", CHECKPOINT):
        assert (logdir / name).exists(), name
    assert list(logdir.glob("events.out.tfevents.*"))
    assert len(list((logdir / "replay").glob("*.npz"))) == 5  # 200 env steps = 5 episodes of 40
    assert [int(r["env_step"]) for r in rows(logdir / "eval.csv")] == [100, 200]
    first = torch.load(logdir / CHECKPOINT, weights_only=True)
    assert first["counters"]["env_step"] == 200 and first["counters"]["updates"] == 12
    assert first["counters"]["next_checkpoint"] == 300  # the next one due: a resume does not write 200's again

    # resume: a fresh agent loads exactly the saved weights; the run continues from 200, not from 0
    cfg = load_config("configs/finetune/demo.yaml", dict(hidden=24, units=32, logdir=str(logdir)))
    agent = build_agent(cfg, 1, export_dir, torch.device("cpu"))
    assert load_checkpoint(logdir / CHECKPOINT, agent, cfg, {"export_sha256": export_fingerprint(export_dir)})["env_step"] == 200
    assert all(torch.equal(agent.trainable_state_dict()[k], v) for k, v in first["agent"].items())

    capsys.readouterr()
    assert main(args + ["--steps", "280"]) == 0
    assert f"resuming {logdir / CHECKPOINT} at env step 200" in capsys.readouterr().err
    second = torch.load(logdir / CHECKPOINT, weights_only=True)
    assert second["counters"]["env_step"] == 280 and second["counters"]["updates"] == 20
    assert [int(r["env_step"]) for r in rows(logdir / "episodes.csv")][-2:] == [240, 280]
    assert [int(r["env_step"]) for r in rows(logdir / "eval.csv")] == [100, 200, 280]
    assert len(list((logdir / "replay").glob("*.npz"))) == 7
    # the resumed run reseeds from its progress: its env does not replay the fresh run's episodes from their start
    # (its first episode, the run's sixth, starts from episode_seed(seed, env 0, 5 episodes)), nor its evaluations
    first_frames = {int(path.name[:6]): np.load(path)["obs"][0] for path in (logdir / "replay").glob("*.npz")}
    probe = task_env(cfg, 0)
    resumed_start = probe.reset(seed=episode_seed(cfg.seed, 0, 5))[0]
    probe.close()
    np.testing.assert_array_equal(first_frames[5], resumed_start)
    assert not np.array_equal(first_frames[5], first_frames[0])
    assert cfg.seed == 0 and [seed for seed in eval_seeds if seed] == [EVAL_SEED, EVAL_SEED + 200]  # 0: a probe

    capsys.readouterr()
    assert main(args + ["--steps", "200"]) == 0  # a budget the run has already spent: it says so, and changes nothing
    assert "nothing to train" in (out := capsys.readouterr().out) and "last evaluation at env_step 280: return" in out
    assert torch.load(logdir / CHECKPOINT, weights_only=True)["counters"]["env_step"] == 280

    # best.pt: the agent of the first evaluation of highest mean return, across the resume; the CLI names it
    evaluations = rows(logdir / "eval.csv")
    best_row = max(evaluations, key=lambda row: float(row["return"]))
    best = torch.load(logdir / BEST, weights_only=True)["counters"]
    assert best["env_step"] == best["best_at"] == int(best_row["env_step"])
    assert best["best_return"] == pytest.approx(float(best_row["return"]))
    assert f"best evaluation: return {best['best_return']:.4g} at env step {best['best_at']}" in out

    # evaluate: the last checkpoint or best.pt on fresh episodes, the same figures each time it is asked
    evaluate = ["evaluate", str(logdir), "--pretrained", str(export_dir), "--episodes", "2", "--no-progress"]
    assert main(evaluate) == 0 and main(evaluate) == 0
    first, again = capsys.readouterr().out.splitlines()
    assert first == again and first.startswith(f"dmc_cartpole_swingup (hauwm, online) {logdir / CHECKPOINT} at env "
                                               "step 280, 2 episodes from env seed 1000000000: return ")
    assert main(evaluate + ["--best", "--seed", "7"]) == 0
    assert f"{logdir / BEST} at env step {best['best_at']}, 2 episodes from env seed 7" in capsys.readouterr().out
    assert main(evaluate[:2] + ["--episodes", "1"]) == 2 and "pass that export with --pretrained DIR" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path)]) == 2 and "not a `hauwm finetune` run directory" in capsys.readouterr().err
    assert main(evaluate + ["--episodes", "0"]) == 2 and "--episodes must be >= 1" in capsys.readouterr().err
    assert main(evaluate + ["--seed", "-1"]) == 2 and "env seed must lie in 0..2^32-1" in capsys.readouterr().err

    # stopped between keeping an evaluation and the next checkpoint: the resumed run does not replace that best.pt
    # with a worse evaluation (here best.pt holds a return none reaches, and the checkpoint knows no best)
    kept = torch.load(logdir / BEST, weights_only=True)
    kept["counters"]["best_return"] = 1e9
    torch.save(kept, logdir / BEST)
    older = torch.load(logdir / CHECKPOINT, weights_only=True)
    del older["counters"]["best_return"], older["counters"]["best_at"]
    torch.save(older, logdir / CHECKPOINT)
    kept_bytes = (logdir / BEST).read_bytes()
    (logdir / "replay").rename(tmp_path / "replay-moved")  # and its replay moved away: the resume says so
    capsys.readouterr()
    assert main(args + ["--steps", "320"]) == 0
    assert f"note: {logdir / 'replay'} holds none of the 7 episodes this run stored" in capsys.readouterr().err
    assert (logdir / BEST).read_bytes() == kept_bytes
    assert torch.load(logdir / CHECKPOINT, weights_only=True)["counters"]["best_return"] == 1e9

    # a resume goes on with what the run learns with; its budget, cadence and speed settings may change
    assert main(args + ["--steps", "320", "--set", "horizon=7", "--set", "eval_episodes=2"]) == 2
    assert "was trained with horizon=5 (asked: 7): a resume goes on with the settings" in capsys.readouterr().err
    assert "horizon: 5" in (logdir / "config.yaml").read_text()
    assert main(args + ["--steps", "320", "--set", "eval_episodes=2", "--set", "checkpoint_every=50"]) == 0

    (logdir / BEST).write_bytes(kept_bytes[:100])  # damaged: named, not a traceback, at resume and after a run
    assert main(args + ["--steps", "360"]) == 2
    assert f"{logdir / BEST} cannot be read (it is truncated" in (err := capsys.readouterr().err) and "move it away" in err
    assert f"{logdir / BEST} cannot be read (it is truncated" in best_kept(logdir, "env step")


def test_resume_with_another_task_or_export_is_refused(export_dir, export_sizes, tmp_path, capsys):
    logdir = tmp_path / "run"
    settings = tiny_run_settings(logdir, time_limit=10, prefill=20, eval_episodes=1)
    run = ["--config", "configs/finetune/demo.yaml", "--steps", "40"] + settings
    assert main(run + ["--pretrained", str(export_dir)]) == 0
    code = main(run + ["--pretrained", str(export_dir), "--set", "task=dmc_cheetah_run"])
    assert code == 2 and "task='dmc_cartpole_swingup'" in capsys.readouterr().err
    assert main(run + ["--set", "agent=scratch"]) == 2  # named as the agent it is, not as another export
    assert "agent='hauwm', this run has agent='scratch'" in capsys.readouterr().err
    torch.manual_seed(1)
    other = export_frozen(WorldModel(export_sizes), tmp_path / "other-export")
    assert main(run + ["--pretrained", str(other)]) == 2
    assert "another --pretrained export" in capsys.readouterr().err
    evaluate = ["evaluate", str(logdir), "--episodes", "1", "--no-progress"]
    assert main(evaluate + ["--pretrained", str(other)]) == 2  # what to do about it, and no training advice
    err = capsys.readouterr().err
    assert "was trained on another --pretrained export (weights sha256 differs): pass the export it was trained on" \
        in err and "--logdir" not in err
    checkpoint = logdir / CHECKPOINT
    written = (logdir / "config.yaml").read_text()
    checkpoint.rename(tmp_path / "aside.pt")  # a run stopped before its first checkpoint: config.yaml and replay/ only
    assert main(run + ["--pretrained", str(export_dir), "--set", "task=dmc_cheetah_run"]) == 2
    assert (f"{logdir} holds a run with task='dmc_cartpole_swingup' (asked: 'dmc_cheetah_run') that stopped before its "
            "first checkpoint; its replay episodes would train this one") in capsys.readouterr().err
    assert (logdir / "config.yaml").read_text() == written
    (tmp_path / "aside.pt").rename(checkpoint)
    checkpoint.write_bytes(checkpoint.read_bytes()[:3000])  # damaged (the run itself writes it atomically)
    assert main(run + ["--pretrained", str(export_dir)]) == 2
    err = capsys.readouterr().err
    assert f"{checkpoint} cannot be read (it is truncated or not a checkpoint" in err and "Traceback" not in err
    assert main(evaluate + ["--pretrained", str(export_dir)]) == 2
    err = capsys.readouterr().err
    assert f"{checkpoint} cannot be read (it is truncated or not a checkpoint" in err and "--logdir" not in err
    torch.save({"state_dict": {}, "epoch": 3}, checkpoint)  # another program's file, which torch reads
    assert main(run + ["--pretrained", str(export_dir)]) == 2
    err = capsys.readouterr().err  # a KeyError's traceback before
    assert f"{checkpoint} is not a checkpoint of `hauwm finetune` (it holds keys epoch, state_dict)" in err, err
    assert "Traceback" not in err


def test_sizes_that_do_not_fit_the_export_are_named_with_it(export_dir, tmp_path, capsys):
    run = ["--config", "configs/finetune/demo.yaml", "--steps", "2", "--pretrained", str(export_dir)]
    assert main(run + ["--logdir", str(tmp_path / "run"), "--set", "deter=8"]) == 2
    assert (f"--pretrained {export_dir}: the new stream's feature size deter+stoch = " in capsys.readouterr().err)


@pytest.mark.parametrize(("settings", "message"), [
    (["--steps", "20000"], "(the replay of 10000 steps 117.3 MiB, the agent's weights, gradients and Adam state"),
    (["--steps", "20000"], "more than the 64.0 MiB available: lower replay_capacity (the replay then keeps the newest"),
    (["--set", "units=2000"], "more than the 64.0 MiB available: lower the agent's sizes (units 2000)"),
    (["--set", "num_envs=8"], "(8 env processes 512.0 MiB)"),
    (["--set", "num_envs=8"], "more than the 64.0 MiB available: lower num_envs"),
])
def test_a_run_too_large_for_the_memory_is_refused_before_it_builds_its_agent(export_dir, tmp_path, capsys, monkeypatch,
                                                                             settings, message):
    monkeypatch.setattr("hauwm.memory.memory_available", lambda: 2**26)  # the replay was killed hours in (exit 137)
    monkeypatch.setattr(finetune.train, "build_agent", lambda *args: pytest.fail("built the agent"))
    run = ["--config", "configs/finetune/demo.yaml", "--pretrained", str(export_dir), "--logdir", str(tmp_path / "run")]
    assert main(run + settings) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "run" / "config.yaml").exists()


def test_a_logdir_of_something_else_is_refused_and_left_as_it_was(export_dir, tmp_path, capsys):
    """Its files were overwritten (config.yaml) or mixed with the run's (eval.csv, a replay/ of another task)."""
    run = ["--config", "configs/finetune/demo.yaml", "--steps", "2", "--pretrained", str(export_dir)]
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "eval.csv").write_text("important\n")
    assert main(run + ["--logdir", str(mine)]) == 2
    assert (f"{mine} holds files but no `hauwm finetune` run (no config.yaml nor checkpoint; e.g. eval.csv), which "
            "this run would mix with its own or overwrite") in capsys.readouterr().err
    (mine / "config.yaml").write_text("trainer:\n  max_steps: 10\n")  # another program's
    assert main(run + ["--logdir", str(mine)]) == 2
    assert f"{mine / 'config.yaml'} is not the config of a `hauwm finetune` run" in capsys.readouterr().err
    assert sorted(path.name for path in mine.iterdir()) == ["config.yaml", "eval.csv"]
    assert (mine / "eval.csv").read_text() == "important\n"
    assert main(run + ["--logdir", ""]) == 2
    assert "setting logdir is empty (an unset shell variable?)" in capsys.readouterr().err


def test_a_checkpoint_that_cannot_be_written_keeps_the_one_before(tiny_config, tmp_path, monkeypatch):
    cfg = tiny_config(agent="scratch", logdir=str(tmp_path))
    agent = build_agent(cfg, 1, None, torch.device("cpu"))
    save_checkpoint(tmp_path / CHECKPOINT, agent, cfg, {"env_step": 100}, {"export_sha256": ""})
    before = (tmp_path / CHECKPOINT).read_bytes()

    def full_disk(state, path):  # what torch's zip writer says when the disk fills halfway through
        path.write_bytes(before[:100])
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 64 vs 0")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(FinetuneError, match=r"checkpoint.pt could not be written \(\[enforce fail .*; a full disk or "
                                            r"quota\?\); what was written before is kept"):
        save_checkpoint(tmp_path / CHECKPOINT, agent, cfg, {"env_step": 200}, {"export_sha256": ""})
    assert (tmp_path / CHECKPOINT).read_bytes() == before and not list(tmp_path.glob(".*.partial"))


@pytest.mark.parametrize("device", ["gpu", "GPU", "cuda:x", "mps", "meta", "xpu", "cpu:3"])
def test_a_device_hauwm_does_not_run_on_is_refused_by_name(device):
    """Devices torch knows but HAUWM does not run on (mps, meta) ended in a traceback from inside torch."""
    with pytest.raises(FinetuneError, match=f"device '{device}' is not a device HAUWM runs on: use auto, cpu, cuda or "
                                            "cuda:N"):
        resolve_device(device)


def test_a_cuda_index_beyond_the_machines_devices_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert resolve_device("cuda:0") == torch.device("cuda:0") and resolve_device("cuda") == torch.device("cuda")
    with pytest.raises(FinetuneError, match=r"device 'cuda:1' asked for but this machine has 1 CUDA device\(s\), "
                                            "cuda:0 to cuda:0"):
        resolve_device("cuda:1")


def test_a_run_directory_in_use_is_refused(export_dir, tmp_path, capsys):
    logdir = tmp_path / "run"
    run = ["--config", "configs/finetune/demo.yaml", "--steps", "40", "--pretrained", str(export_dir)]
    run += tiny_run_settings(logdir, time_limit=10, prefill=20, eval_episodes=1)
    with exclusive(logdir):  # another run holds the directory
        assert main(run) == 2
        assert "is in use by another run" in capsys.readouterr().err
        assert not (logdir / CHECKPOINT).exists()
    assert not logdir.exists()  # made for the lock alone, so removed again, as after any run refused at its start
    assert main(run + ["--set", "seq_len=64"]) == 2 and not logdir.exists()
    deeper = tmp_path / "new" / "deeper"
    assert main(run + ["--set", "seq_len=64", "--logdir", str(deeper)]) == 2 and not (tmp_path / "new").exists()
    logdir.mkdir()
    assert main(run + ["--set", "seq_len=64"]) == 2 and not any(logdir.iterdir())  # an empty one stays as it was
    assert main(run) == 0  # free again once that run ends


@pytest.mark.parametrize("task, repeat, episode, steps", SUITES, ids=[s[0].split("_")[0] for s in SUITES])
def test_each_suite_completes_a_short_run(export_dir, tiny_config, tmp_path, task, repeat, episode, steps):
    cfg = tiny_config(task=task, action_repeat=repeat, time_limit=episode, steps=steps, prefill=steps // 2,
                      train_every=10, eval_every=steps, eval_episodes=1, log_every=steps // 4,
                      checkpoint_every=steps, fast_render=True, logdir=str(tmp_path / task))
    result = train(cfg, export_dir, progress=False)
    # Table 4 normalises Meta-World's returns; RoboDesk's references do not fit its reward (finetune/envs/references.py)
    assert ("normalised_return" in result) == task.startswith("metaworld") and 0.0 <= result["success_rate"] <= 1.0
    assert (tmp_path / task / CHECKPOINT).exists()
    assert rows(tmp_path / task / "train.csv")
    assert torch.load(tmp_path / task / CHECKPOINT, weights_only=True)["counters"]["env_step"] == steps


def test_a_budget_within_the_prefill_says_it_makes_no_update(export_dir, tmp_path, capsys):
    settings = tiny_run_settings(tmp_path / "run", time_limit=10, prefill=20, eval_episodes=1)
    assert main(["--config", "configs/finetune/demo.yaml", "--steps", "20", "--pretrained", str(export_dir)] + settings) == 0
    assert "note: steps 20 end within the prefill of 20 env steps of random actions" in capsys.readouterr().err
    assert rows(tmp_path / "run" / "eval.csv") and not (tmp_path / "run" / "train.csv").exists()


def test_a_budget_that_ends_before_the_first_episodes_do_says_it_makes_no_update(export_dir, tmp_path, capsys):
    """num_envs 2 × time_limit 10 × action_repeat 2: no episode ends before env step 40, and without one the replay
    has nothing to train on; the run evaluated its untrained agent without a word."""
    args = ["--config", "configs/finetune/demo.yaml", "--pretrained", str(export_dir)]
    for steps, updates in ((36, False), (40, True)):
        logdir = tmp_path / f"run{steps}"
        settings = tiny_run_settings(logdir, time_limit=10, prefill=20, eval_episodes=1, num_envs=2)
        assert main(args + ["--steps", str(steps)] + settings) == 0
        note = (f"note: steps {steps} end before the envs finish their first episodes (at env step 40: 2 envs × "
                "time_limit 10 × action_repeat 2): the replay gets no episode to train on")
        assert (note in capsys.readouterr().err) != updates
        assert (torch.load(logdir / CHECKPOINT, weights_only=True)["counters"]["updates"] > 0) == updates


@pytest.mark.parametrize("num_envs", [1, 2])
def test_the_prefill_acts_at_random_and_the_agent_acts_after_it(export_dir, tiny_config, tmp_path, monkeypatch, num_envs):
    """The first `prefill` env steps (over all envs) take uniform random actions; every later one is the agent's."""
    from finetune.agent import Agent
    from finetune.replay import episode_files

    act = Agent.act

    def marked(self, obs, latent, prev_action, explore):  # the agent's actions, marked 0.123
        actions, latent, prev_action = act(self, obs, latent, prev_action, explore)
        return np.full_like(actions, 0.123), latent, torch.full_like(prev_action, 0.123)

    monkeypatch.setattr(Agent, "act", marked)
    cfg = tiny_config(task="dmc_cartpole_swingup", action_repeat=2, time_limit=10, steps=80, prefill=40, train_every=20,
                      eval_every=80, eval_episodes=1, checkpoint_every=80, num_envs=num_envs, fast_render=True,
                      logdir=str(tmp_path / "run"))
    train(cfg, export_dir, progress=False)
    episodes = [np.load(path)["action"][1:, 0] for path in episode_files(tmp_path / "run" / "replay")]  # a_0..a_{T−1}
    by_env = [np.concatenate(episodes[i::num_envs]) for i in range(num_envs)]  # the envs finish episodes in turn
    random_steps = cfg.prefill // (num_envs * cfg.action_repeat)  # agent steps of each env within the prefill
    for actions in by_env:
        assert len(actions) == cfg.steps // (num_envs * cfg.action_repeat)
        assert not np.isclose(actions[:random_steps], 0.123).any() and np.isclose(actions[random_steps:], 0.123).all()


class _SolvedMidway(PixelEnv):
    """A stand-in simulator: reward 1 per simulator step, success at the second agent step only."""

    def __init__(self) -> None:
        super().__init__("solved_midway", 0, np.array([-1.0, -1.0]), np.array([1.0, 1.0]), 64, action_repeat=2,
                         time_limit=4)
        self.sim_steps = 0

    def _seed_sim(self, seed):
        pass

    def _reset_sim(self):
        self.sim_steps = 0

    def _step_sim(self, action):
        self.sim_steps += 1
        return 1.0, False, False, self.sim_steps in (3, 4)  # the two simulator steps of agent step 2

    def _render_frame(self):
        return np.zeros((64, 64, 3), np.uint8)


def test_evaluation_counts_an_episode_solved_at_any_step_and_normalises_its_return_by_table_4(tiny_config):
    """An episode is a success if the task was solved at any step (not only at its last); the return sums every
    simulator step's reward, and dmc_cheetah_run's Table 4 references (random 71, expert 821) normalise it."""
    agent = Agent(tiny_config(agent="scratch"), action_dim=2)
    result = evaluate(agent, _SolvedMidway(), episodes=2, task="dmc_cheetah_run", seed=0)
    assert result["success_rate"] == 1.0
    assert result["return"] == 8.0 and result["return_std"] == 0.0  # 4 agent steps × 2 simulator steps × 1
    assert result["normalised_return"] == pytest.approx((8.0 - 71.0) / (821.0 - 71.0))


def test_normalised_returns_of_episodes_cut_short_or_run_on_are_said_to_be_incomparable(tiny_config):
    note = incomparable_returns_note(tiny_config(task="metaworld_drawer_close", action_repeat=1, time_limit=100))
    assert note.startswith("note: time_limit 100 cuts metaworld_drawer_close's episodes short of the suite's 500 agent "
                           "steps: the normalised returns in eval.csv are not comparable to the paper's")
    # 2,000 simulator steps against the 1,000 of Table 4's references: no note before (found by a review)
    note = incomparable_returns_note(tiny_config(task="dmc_cheetah_run", action_repeat=2, time_limit=1000))
    assert note.startswith("note: time_limit 1000 runs dmc_cheetah_run's episodes on past the suite's 500 agent steps")
    assert incomparable_returns_note(tiny_config(task="dmc_cheetah_run", action_repeat=2, time_limit=500)) is None
    assert incomparable_returns_note(tiny_config(task="dmc_cheetah_run", action_repeat=4, time_limit=None)) is None
    assert incomparable_returns_note(tiny_config(task="dmc_cartpole_swingup", time_limit=10)) is None  # no references


def test_more_threads_or_envs_than_cpus_get_a_note(tmp_path, capsys):
    """threads=100000 failed to allocate the threads' stacks deep inside a library; the run uses the machine's CPUs.
    num_envs=100000 was taken without a word, and ran the machine out of memory starting its env processes."""
    cfg = load_config("configs/finetune/demo.yaml", dict(agent="scratch", hidden=24, units=32, threads=100_000,
                                                         num_envs=os.cpu_count() + 1, device="cpu",
                                                         logdir=str(tmp_path)))
    threads = torch.get_num_threads()
    try:
        start_run(cfg, None, Agent, 1, {"env_step": 0}, np.random.default_rng(0))
        assert torch.get_num_threads() == os.cpu_count()
    finally:
        torch.set_num_threads(threads)
    err = capsys.readouterr().err
    assert f"threads 100000 is more than this machine's {os.cpu_count()} CPUs; using {os.cpu_count()}" in err
    assert f"num_envs {os.cpu_count() + 1} is more than this machine's {os.cpu_count()} CPUs: each env is a" in err


def test_a_run_directory_whose_config_yaml_is_not_text_is_named(tmp_path):
    (tmp_path / "config.yaml").write_bytes(bytes(range(256)))  # a checkpoint copied over it, say
    with pytest.raises(FinetuneError, match=f"{tmp_path / 'config.yaml'}: config file .* is not valid YAML"):
        run_config(tmp_path)


def test_what_a_run_learns_does_not_depend_on_how_it_is_evaluated(export_dir, tmp_path):
    """Evaluations drew the world model's posterior samples from the training's torch RNG, so a seed's run learned
    other weights with eval_episodes 2 than with 1; and one agent evaluated twice gave two different results."""
    weights = []
    for eval_episodes in (1, 2):
        logdir = tmp_path / f"eval{eval_episodes}"
        args = ["--config", "configs/finetune/demo.yaml", "--pretrained", str(export_dir), "--steps", "160"]
        args += tiny_run_settings(logdir, time_limit=20, prefill=40, eval_every=80, checkpoint_every=160,
                                  eval_episodes=eval_episodes)
        assert main(args) == 0
        assert len(rows(logdir / "eval.csv")) == 2
        weights.append(torch.load(logdir / CHECKPOINT, weights_only=True)["agent"])
    assert all(torch.equal(weights[0][key], weights[1][key]) for key in weights[0])

    cfg = load_config("configs/finetune/demo.yaml", dict(hidden=24, units=32, time_limit=20, fast_render=True,
                                                         device="cpu"))
    agent = build_agent(cfg, 1, export_dir, torch.device("cpu"))
    agent.load_state_dict(weights[0], strict=False)
    with contextlib.closing(task_env(cfg, 7)) as env:
        first, second = (evaluate(agent, env, episodes=1, task=cfg.task, seed=7) for _ in range(2))
    assert first == second


def test_a_cadence_lowered_on_resume_applies_from_the_resumed_step(export_dir, tmp_path):
    """next_eval and next_checkpoint came back from the checkpoint: a run resumed with eval_every and
    checkpoint_every lowered from 10,000 to 80 evaluated and saved nothing until env step 10,000 (a kill on the way
    lost everything since the resume)."""
    logdir = tmp_path / "run"
    args = ["--config", "configs/finetune/demo.yaml", "--pretrained", str(export_dir)]
    settings = dict(time_limit=20, prefill=40, eval_episodes=1)
    assert main(args + tiny_run_settings(logdir, eval_every=10_000, checkpoint_every=10_000, **settings)
                + ["--steps", "120"]) == 0
    assert main(args + tiny_run_settings(logdir, eval_every=80, checkpoint_every=80, **settings)
                + ["--steps", "280"]) == 0
    assert [int(row["env_step"]) for row in rows(logdir / "eval.csv")] == [120, 160, 240, 280]
    assert torch.load(logdir / CHECKPOINT, weights_only=True)["counters"]["next_checkpoint"] == 320


def test_a_run_resumed_after_a_crash_learns_what_the_same_resume_without_the_crash_learns(export_dir, tmp_path, capsys):
    """A run killed between two checkpoints had written the episodes it finished since the first to its replay; the
    resume from that checkpoint reloaded them and collected them again, so it trained on each twice."""
    logdir = tmp_path / "run"
    args = ["--config", "configs/finetune/demo.yaml", "--pretrained", str(export_dir)]
    args += tiny_run_settings(logdir, time_limit=20, prefill=40, eval_every=1000, checkpoint_every=80, eval_episodes=1)
    assert main(args + ["--steps", "80"]) == 0
    at_80 = (logdir / CHECKPOINT).read_bytes()
    assert main(args + ["--steps", "160"]) == 0
    unbroken = torch.load(logdir / CHECKPOINT, weights_only=True)["agent"]
    assert len(list((logdir / "replay").glob("*.npz"))) == 4

    (logdir / CHECKPOINT).write_bytes(at_80)  # as if the run had been killed after episode 3, before its checkpoint
    capsys.readouterr()
    assert main(args + ["--steps", "160"]) == 0
    resumed = torch.load(logdir / CHECKPOINT, weights_only=True)
    assert all(torch.equal(resumed["agent"][key], unbroken[key]) for key in unbroken)
    assert resumed["counters"]["episodes"] == 4 and len(list((logdir / "replay").glob("*.npz"))) == 4
    assert (f"note: {logdir / 'replay'}: 2 episodes stored after the checkpoint this run starts from deleted"
            in capsys.readouterr().err)


def test_config_yaml_cut_short_by_a_full_disk_keeps_the_one_before(tiny_config, tmp_path, monkeypatch):
    """config.yaml was written in place: a full disk (or a kill) halfway left half a YAML, which `evaluate` then read
    with defaults for the missing settings."""
    cfg = tiny_config(agent="scratch", logdir=str(tmp_path))
    agent, fingerprint = build_agent(cfg, 1, None, torch.device("cpu")), run_fingerprint(cfg, None)
    resume(cfg, agent, fingerprint, {"env_step": 0}, np.random.default_rng(0))
    before = (tmp_path / "config.yaml").read_text()
    write_text = type(tmp_path).write_text

    def disk_fills(path, text, *args, **kwargs):
        write_text(path, text[:len(text) // 2])
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(type(tmp_path), "write_text", disk_fills)
    with pytest.raises(OSError, match="No space left"):
        resume(cfg, agent, fingerprint, {"env_step": 0}, np.random.default_rng(0))
    assert (tmp_path / "config.yaml").read_text() == before and not list(tmp_path.glob(".*.partial"))


def test_a_checkpoint_damaged_in_place_is_refused(tiny_config, tmp_path, damaged_in_place):
    """torch.load reads a checkpoint whose bytes changed in place (a disk or copy error) without a word."""
    cfg = tiny_config(agent="scratch", logdir=str(tmp_path))
    agent, fingerprint = build_agent(cfg, 1, None, torch.device("cpu")), run_fingerprint(cfg, None)
    save_checkpoint(tmp_path / "whole.pt", agent, cfg, {"env_step": 100}, fingerprint)
    record = damaged_in_place(tmp_path / "whole.pt", tmp_path / CHECKPOINT)
    assert read_state(tmp_path / "whole.pt", cfg, fingerprint)["counters"] == {"env_step": 100}
    with pytest.raises(FinetuneError, match=f"{CHECKPOINT} is damaged: its record {record} fails its checksum "
                                            r"\(a disk or copy error\): restore it, or train in another --logdir"):
        read_state(tmp_path / CHECKPOINT, cfg, fingerprint)
