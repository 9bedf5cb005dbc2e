"""configs/finetune: one config per paper task with Table 3's budgets; config loading errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from finetune.config import load_config, parse_override
from finetune.envs import PAPER_TASKS
from model.config import ConfigError

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "finetune"


@pytest.mark.parametrize("task", PAPER_TASKS)
def test_every_paper_task_has_a_config_with_the_table3_budget(task):
    cfg = load_config(CONFIGS / f"{task}.yaml")
    assert cfg.task == task and cfg.agent == "hauwm"
    assert cfg.steps == (1_000_000 if task.startswith("dmc") else 250_000)
    assert (cfg.batch_size, cfg.seq_len, cfg.replay_capacity, cfg.horizon) == (32, 50, 1_000_000, 15)
    assert (cfg.gamma, cfg.lam, cfg.model_lr, cfg.actor_lr, cfg.critic_lr) == (0.99, 0.95, 3e-4, 8e-5, 8e-5)
    assert (cfg.units, cfg.noise_std) == (400, 0.01)
    if task.startswith("dmc"):
        assert cfg.action_repeat == 2
    assert cfg.train_every == 5 * cfg.action_repeat  # DreamerV2's and APV's update every 5 agent steps


def test_train_every_defaults_to_five_agent_steps_and_keeps_a_value_given():
    assert [load_config(None, {"action_repeat": repeat}).train_every for repeat in (1, 2, 4)] == [5, 10, 20]
    assert load_config(None, {"action_repeat": 2, "train_every": 5}).train_every == 5


def test_demo_config_is_small():
    cfg = load_config(CONFIGS / "demo.yaml")
    assert cfg.steps <= 1000 and cfg.task.startswith("dmc_")


def test_overrides_are_typed_and_unknown_keys_rejected(tmp_path):
    cfg = load_config(CONFIGS / "demo.yaml", dict([parse_override("steps=1e3"), parse_override("agent=scratch")]))
    assert cfg.steps == 1000 and isinstance(cfg.steps, int) and cfg.agent == "scratch"
    with pytest.raises(ConfigError, match=r"unknown setting\(s\) in the overrides \(--set\): stepz \(did you mean steps\?\)"):
        load_config(CONFIGS / "demo.yaml", {"stepz": 3})
    (tmp_path / "typo.yaml").write_text("bath_size: 4\nzzz: 1\n")
    with pytest.raises(ConfigError, match=r"in config file .*typo.yaml: bath_size \(did you mean batch_size\?\), zzz;"):
        load_config(tmp_path / "typo.yaml")
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="agent must be"):
        load_config(None, {"agent": "apv"})


TABLE2_TASKS = ("dmc_cheetah_run", "dmc_hopper_hop", "metaworld_dial_turn", "metaworld_drawer_close", "robodesk_push_green")
ROOT = CONFIGS.parent


@pytest.mark.parametrize("task", TABLE2_TASKS)
def test_every_table2_task_has_an_offline_and_an_imitation_config(task):
    offline = load_config(ROOT / "offline" / f"{task}.yaml")
    assert (offline.task, offline.paradigm, offline.horizon, offline.model_heads) == (task, "offline", 5, 7)
    assert offline.eval_episodes >= 10 and offline.penalty == "loglik_std"
    imitation = load_config(ROOT / "imitation" / f"{task}.yaml")
    assert (imitation.task, imitation.paradigm, imitation.eval_episodes) == (task, "imitation", 10)
    assert imitation.model_heads == 1 and imitation.steps == (1_000_000 if task.startswith("dmc") else 250_000)


@pytest.mark.parametrize("paradigm", ["offline", "imitation"])
def test_downstream_demo_configs_are_small_drawer_close_runs(paradigm):
    cfg = load_config(ROOT / paradigm / "demo.yaml")
    assert (cfg.paradigm, cfg.task, cfg.fast_render) == (paradigm, "metaworld_drawer_close", True)
    assert cfg.units <= 64 and cfg.steps <= 1000


def test_bad_downstream_settings_are_refused():
    for settings, message in [({"paradigm": "batch"}, "paradigm must be one of"),
                              ({"imagine_heads": "all"}, "imagine_heads must be one of"),
                              ({"model_heads": 0}, "model_heads must be at least 1"),
                              ({"penalty_scale": -1}, "must be >= 0")]:
        with pytest.raises(ConfigError, match=message):
            load_config(None, settings)


def test_speed_settings_are_checked():
    assert load_config(None, dict([parse_override("compile=off")])).compile == "off"  # YAML reads off as false
    assert load_config(None, {"compile": "reduce-overhead", "num_envs": 4}).num_envs == 4
    with pytest.raises(ConfigError, match="compile must be one of auto, off, default, reduce-overhead"):
        load_config(None, {"compile": "max-autotune"})
    with pytest.raises(ConfigError, match="num_envs must be at least 1"):
        load_config(None, {"num_envs": 0})
    with pytest.raises(ConfigError, match="conv_bf16 must be true or false"):
        load_config(None, {"conv_bf16": "yes"})


def test_numeric_settings_are_range_checked():
    """A negative budget or a fractional batch is refused by name, not run (nor rounded) silently."""
    for settings, message in [({"steps": -5}, "steps must be at least 1, got -5"),
                              ({"batch_size": 1.5}, "batch_size must be a whole number, got 1.5"),
                              ({"seq_len": 1}, "seq_len must be at least 2"),
                              ({"deter": 2.5}, "deter must be a whole number"),
                              ({"steps": None}, "steps must be a number, got None"),
                              ({"steps": True}, "steps must be a number, got True"),
                              ({"gamma": 1.5}, "gamma must be between 0 and 1"),
                              ({"actor_lr": 0}, "actor_lr must be > 0"),
                              ({"prefill": -1}, "prefill must be >= 0"),
                              ({"seed": -1}, r"seed must be in 0..2\^31-1"),
                              # a seed near 2^32 failed inside the env library (its message named the task, not seed),
                              # at the start or, with an evaluation's seed + 10,000 + env steps, at a resume
                              ({"seed": 4_294_960_000}, r"seed must be in 0..2\^31-1 \(the run's env seeds"),
                              ({"model_lr": float("inf")}, "model_lr must be a finite number, got inf"),
                              ({"penalty_scale": "inf"}, "penalty_scale must be a finite number, got inf")]:
        with pytest.raises(ConfigError, match=message):
            load_config(None, settings)
    cfg = load_config(None, {"time_limit": None, "deter": None, "prefill": 0, "steps": "1e6"})  # None: the suite's/export's
    assert (cfg.time_limit, cfg.deter, cfg.prefill, cfg.steps) == (None, None, 0, 1_000_000)


def test_a_config_that_is_not_yaml_or_a_value_of_another_kind_is_refused_by_name(tmp_path):
    broken = tmp_path / "broken.yaml"
    broken.write_text("steps: [1, 2\nagent: x\n")
    with pytest.raises(ConfigError, match=f"config file {broken} is not valid YAML: .* at line 2, column 6"):
        load_config(broken)
    broken.write_text("task: dmc_cheetah_run\nsteps: 10\ntask: dmc_walker_run\n")  # YAML alone keeps the last
    with pytest.raises(ConfigError, match=f"config file {broken} is not valid YAML: 'task' is set twice: keep one at "
                                          "line 3, column 1"):
        load_config(broken)
    broken.write_text("# settings to come\n")
    with pytest.raises(ConfigError, match=f"config file {broken} holds no settings, not a mapping of settings \\(a "
                                          "config names at least its task"):
        load_config(broken)
    broken.write_text("- task: dmc_cheetah_run\n")
    with pytest.raises(ConfigError, match=f"config file {broken} holds \\[{{'task': 'dmc_cheetah_run'}}\\], not a "
                                          "mapping"):
        load_config(broken)
    with pytest.raises(ConfigError, match="setting steps must be a number, got '\\[1'"):
        load_config(None, dict([parse_override("steps=[1")]))  # not YAML: the text, judged by the setting
    with pytest.raises(ConfigError, match="setting task must be text, got 5"):
        load_config(None, dict([parse_override("task=5")]))
    with pytest.raises(ConfigError, match="setting compile must be one of .*reduce-overhead.*, got True"):
        load_config(None, dict([parse_override("compile=yes")]))  # YAML's yes: true
    assert load_config(None, dict([parse_override("dataset=null")])).dataset is None


def test_a_config_file_that_is_not_text_is_refused_by_name(tmp_path):
    """A binary file given as --config (a checkpoint, an export's weights) is a ConfigError naming it, not a
    UnicodeDecodeError traceback."""
    binary = tmp_path / "weights.yaml"
    binary.write_bytes(b"\xdd\x00\xff binary")
    with pytest.raises(ConfigError, match=f"config file {binary} is not valid YAML: 'utf-8' codec can't decode"):
        load_config(binary)
