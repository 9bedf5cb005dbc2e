"""`hauwm finetune offline|imitate`: dispatch, the data flags, and clear errors for configs of another paradigm."""

from __future__ import annotations

import pytest

import finetune.imitation
import finetune.offline
import finetune.run_dir
import finetune.train
from finetune.cli import main


@pytest.fixture
def runners(monkeypatch):
    """Record which paradigm's entry point the CLI calls, with which settings, instead of training."""
    calls = []

    def fake(name):
        def run(cfg, pretrained, progress):
            calls.append((name, cfg))
            return {"return": 1.0}
        return run

    monkeypatch.setattr(finetune.offline, "train_offline", fake("offline"))
    monkeypatch.setattr(finetune.imitation, "train_imitation", fake("imitation"))
    monkeypatch.setattr(finetune.train, "train", fake("online"))
    return calls


def test_each_subcommand_runs_its_paradigm_with_its_data_flag(runners, capsys):
    assert main(["offline", "--config", "configs/offline/demo.yaml", "--dataset", "medexp", "--steps", "7"]) == 0
    assert main(["imitate", "--config", "configs/imitation/demo.yaml", "--demos", "expert"]) == 0
    assert main(["--config", "configs/finetune/demo.yaml"]) == 0
    (offline, cfg_offline), (imitation, cfg_imitation), (online, cfg_online) = runners
    assert (offline, cfg_offline.dataset, cfg_offline.steps) == ("offline", "medexp", 7)
    assert (imitation, cfg_imitation.demos) == ("imitation", "expert")
    assert (online, cfg_online.paradigm) == ("online", "online")
    out = capsys.readouterr().out
    assert "(hauwm, offline)" in out and "(hauwm, imitation)" in out and "finished dmc_cartpole_swingup (hauwm)" in out


def test_a_config_of_another_paradigm_is_refused_with_the_right_command(runners, capsys):
    assert main(["--config", "configs/offline/demo.yaml"]) == 2
    assert "run `hauwm finetune offline --config configs/offline/demo.yaml" in capsys.readouterr().err
    assert main(["imitate", "--config", "configs/offline/demo.yaml", "--demos", "x"]) == 2
    assert "a config from configs/imitation/" in capsys.readouterr().err
    assert main(["offline", "--config", "configs/offline/demo.yaml", "--set", "model_heads=1"]) == 2
    assert "hauwm finetune offline: error: penalty 'loglik_std'" in capsys.readouterr().err
    assert main(["--config", "configs/finetune/demo.yaml", "--set", "dataset=hauwm/x-v0"]) == 2  # was ignored
    assert ("setting dataset belongs to `hauwm finetune offline`, not to `hauwm finetune`: drop it" in
            capsys.readouterr().err)
    assert main(["offline", "--config", "configs/offline/demo.yaml", "--dataset", "x", "--set", "demos=y"]) == 2
    assert "setting demos belongs to `hauwm finetune imitate`, not to `hauwm finetune offline`" in capsys.readouterr().err
    # the message said the file was a config for online training: --set had changed what the file says
    assert main(["offline", "--config", "configs/offline/demo.yaml", "--dataset", "x", "--set", "paradigm=online"]) == 2
    assert ("the paradigm is chosen by the command (`hauwm finetune`, `hauwm finetune offline`, `hauwm finetune "
            "imitate`), not by a setting: drop --set paradigm=online") in capsys.readouterr().err
    assert not runners


def test_a_setting_of_another_paradigm_or_given_twice_is_refused_not_ignored(runners, capsys):
    """`offline --set expert_latents=posterior` and `imitate --set penalty_scale=50` ran without them, and
    `--steps 2 --set steps=4` with the flag's value, without a word."""
    assert main(["offline", "--config", "configs/offline/demo.yaml", "--dataset", "x",
                 "--set", "expert_latents=posterior"]) == 2
    assert ("setting expert_latents belongs to `hauwm finetune imitate`, not to `hauwm finetune offline`: drop it"
            in capsys.readouterr().err)
    assert main(["imitate", "--config", "configs/imitation/demo.yaml", "--demos", "x", "--set", "penalty_scale=50"]) == 2
    assert "setting penalty_scale belongs to `hauwm finetune offline`, not to `hauwm finetune imitate`" \
        in capsys.readouterr().err
    assert main(["--config", "configs/finetune/demo.yaml", "--set", "disc_lr=0.001"]) == 2
    assert "setting disc_lr belongs to `hauwm finetune imitate`, not to `hauwm finetune`" in capsys.readouterr().err
    # offline RL steps no env: these ran without a word, then blocked a resume that dropped them (found by a review)
    for setting in ("prefill=5000", "train_every=7", "pin_envs=false"):
        assert main(["offline", "--config", "configs/offline/demo.yaml", "--dataset", "x", "--set", setting]) == 2
        assert (f"setting {setting.split('=')[0]} belongs to `hauwm finetune` and `hauwm finetune imitate`, not to "
                "`hauwm finetune offline`: drop it") in capsys.readouterr().err
    assert main(["--config", "configs/finetune/demo.yaml", "--set", "agent=scratch", "--set", "noise_std=0.5"]) == 2
    assert "noise_std sets the frozen stream's k = 1 embedding: the scratch agent has no frozen" in capsys.readouterr().err
    assert main(["--config", "configs/finetune/demo.yaml", "--steps", "2", "--set", "steps=4"]) == 2
    assert "--steps 2 and --set steps=4 disagree: give one" in capsys.readouterr().err
    assert main(["--config", "configs/finetune/demo.yaml", "--steps", "4", "--set", "steps=4"]) == 0  # agree
    assert main(["--config", "configs/finetune/demo.yaml", "--logdir", "2024", "--set", "logdir=2024"]) == 0
    assert main(["--config", "configs/finetune/demo.yaml", "--logdir", "runs/x", "--set", "logdir=runs/x/"]) == 0
    assert [cfg.steps for _, cfg in runners[:1]] == [4] and [cfg.logdir for _, cfg in runners[1:]] == ["2024", "runs/x"]


def test_a_run_that_recorded_another_paradigms_setting_still_resumes_without_it():
    """Runs made before such settings were refused kept them in config.yaml and their checkpoint; dropping the setting,
    as the refusal says, then met the resume's "trained with penalty_scale=10.0 (asked: 5.0)": the run was stuck."""
    import dataclasses

    from finetune.config import FinetuneConfig
    from finetune.run_dir import changed_settings

    cfg = FinetuneConfig(task="dmc_cartpole_swingup")
    written = {**dataclasses.asdict(cfg), "penalty_scale": 10.0, "disc_lr": 1e-3}
    assert changed_settings(cfg, written) == []
    offline = FinetuneConfig(task="dmc_cartpole_swingup", paradigm="offline", dataset="x", model_heads=2)
    assert changed_settings(offline, {**dataclasses.asdict(offline), "prefill": 5000, "train_every": 7}) == []
    assert changed_settings(cfg, {**written, "horizon": 7}) == ["horizon=7 (asked: 15)"]


def test_a_missing_dataset_is_a_clear_error(export_dir, tmp_path, capsys):
    args = ["offline", "--config", "configs/offline/demo.yaml", "--pretrained", str(export_dir), "--logdir",
            str(tmp_path / "run"), "--device", "cpu", "--no-progress", "--set", "units=32", "--set", "hidden=24"]
    assert main(args) == 2
    assert "--dataset ID is needed" in capsys.readouterr().err


def test_an_interrupted_run_says_which_checkpoint_is_kept(monkeypatch, tmp_path, capsys):
    def interrupted(cfg, pretrained, progress):
        raise KeyboardInterrupt

    monkeypatch.setattr(finetune.train, "train", interrupted)
    args = ["--config", "configs/finetune/demo.yaml", "--logdir", str(tmp_path)]
    assert main(args) == 130
    assert "interrupted; no checkpoint was written yet: the same command starts it again" in capsys.readouterr().err
    (tmp_path / finetune.run_dir.CHECKPOINT).write_bytes(b"")
    assert main(args) == 130
    assert f"its last checkpoint, {tmp_path / 'checkpoint.pt'} (written " in capsys.readouterr().err


def test_offline_rl_says_it_does_not_use_num_envs(monkeypatch, capsys):
    monkeypatch.setattr("finetune.offline.train_offline", lambda cfg, pretrained, progress: {"r": 1.0})
    assert main(["offline", "--config", "configs/offline/demo.yaml", "--dataset", "d-v0", "--set", "num_envs=4"]) == 0
    assert "offline RL steps no training env (evaluation plays one), so num_envs 4 is not used" in capsys.readouterr().err


def test_the_scratch_agent_says_it_does_not_use_the_export(monkeypatch, capsys):
    given = []
    monkeypatch.setattr(finetune.train, "train", lambda cfg, pretrained, progress: given.append(pretrained) or {"r": 1.0})
    assert main(["--config", "configs/finetune/demo.yaml", "--set", "agent=scratch", "--pretrained", "exports/x"]) == 0
    assert given == [None]  # the run is handed no export it would ignore
    assert "the scratch agent does not use --pretrained exports/x" in capsys.readouterr().err


@pytest.mark.parametrize("subcommand, unit", [("offline", "updates"), ("imitate", "env steps")])
def test_a_subcommands_help_says_what_it_does_and_what_steps_count(subcommand, unit, capsys):
    with pytest.raises(SystemExit) as done:
        main([subcommand, "--help"])
    assert done.value.code == 0
    shown = capsys.readouterr().out
    assert f"hauwm finetune {subcommand} --config configs/" in shown and f"--steps counts {unit};" in shown
    assert "hauwm finetune evaluate" not in shown  # the other commands' examples stay in `hauwm finetune --help`


def test_ctrl_c_while_the_settings_are_read_is_one_line(monkeypatch, capsys):
    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr("finetune.config.load_config", interrupted)
    assert main(["--config", "configs/finetune/demo.yaml"]) == 130  # an UnboundLocalError (no cfg yet) before
    assert capsys.readouterr().err.strip() == "hauwm finetune: interrupted, before the run started"


def test_a_diverged_run_says_which_checkpoints_hold_its_agent(monkeypatch, tmp_path, capsys):
    """A run that diverged before its first checkpoint said that checkpoint.pt and best.pt held its agent."""
    from finetune.agent import DivergedError

    def diverges(cfg, pretrained, progress):
        raise DivergedError("model_loss inf in updates 1..1: the agent's training has diverged")

    monkeypatch.setattr(finetune.offline, "train_offline", diverges)
    command = ["offline", "--config", "configs/offline/demo.yaml", "--dataset", "x", "--logdir", str(tmp_path)]
    assert main(command) == 2
    assert capsys.readouterr().err.endswith("has diverged (no checkpoint had been written yet)\n")
    (tmp_path / "checkpoint.pt").touch()
    assert main(command) == 2
    assert f"has diverged (checkpoint.pt in {tmp_path} holds the agent as last saved)\n" in capsys.readouterr().err
    (tmp_path / "best.pt").touch()
    assert main(command) == 2
    assert f"(checkpoint.pt and best.pt in {tmp_path} hold the agent as last saved)" in capsys.readouterr().err
