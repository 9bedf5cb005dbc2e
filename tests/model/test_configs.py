"""configs/pretrain/: every config parses through the CLI, ssv2.yaml holds Table 3, the ablations change what they say."""

from __future__ import annotations

import contextlib
import dataclasses
import io
from pathlib import Path

import pytest
import torch
import yaml

from model.cli import main
from model.config import WorldModelConfig

from conftest import REPO  # noqa: I001 (tests/model/conftest.py)

CONFIGS = REPO / "configs" / "pretrain"


def resolved(capsys, shards, *configs: str) -> dict:
    args = ["fit"]
    for config in configs:
        args += ["--config", str(CONFIGS / config)]
    assert main([*args, "--data.shards", str(shards), "--print_config"]) == 0
    return yaml.safe_load(capsys.readouterr().out)


def lookup(config: dict, dotted: str):
    for key in dotted.split("."):
        config = config[key]
    return config


@pytest.fixture(scope="module")
def ssv2_config(tmp_path_factory) -> dict:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["fit", "--config", str(CONFIGS / "ssv2.yaml"), "--data.shards", str(tmp_path_factory.mktemp("s")),
                     "--print_config"]) == 0
    return yaml.safe_load(out.getvalue())


def test_ssv2_holds_table_3(ssv2_config):
    model, data, trainer = ssv2_config["model"], ssv2_config["data"], ssv2_config["trainer"]
    assert (data["batch_size"], model["lr"], trainer["max_steps"]) == (32, 1e-4, 600000)
    assert (model["world_model"]["ensemble"], data["k_max"]) == (7, 5)
    assert (model["lambda_init"], model["lambda_lr"], model["kl_balance"]) == (1.0, 3e-4, 0.8)
    assert model["world_model"] == dataclasses.asdict(WorldModelConfig())  # the defaults are Table 3's
    assert (model["world_model"]["deter"], model["world_model"]["stoch"]) == (200, 30)
    assert (trainer["precision"], trainer["strategy"], trainer["devices"]) == ("16-mixed", "ddp", -1)
    assert (model["compile"], trainer["log_every_n_steps"]) == ("reduce-overhead", 50)


@pytest.mark.parametrize(
    ("overlay", "expected"),
    [
        ("ssv2-m5.yaml", {"model.world_model.ensemble": 5}),
        ("ablations/no-hcu.yaml", {"model.lambda_init": 0.0}),
        ("ablations/lambda-10.yaml", {"model.lambda_init": 10.0}),
        ("ablations/lambda-0.1.yaml", {"model.lambda_init": 0.1}),
        ("ablations/lambda-0.01.yaml", {"model.lambda_init": 0.01}),
        ("ablations/kmax-1.yaml", {"data.k_max": 1}),
        ("ablations/kmax-2.yaml", {"data.k_max": 2}),
        ("ablations/kmax-10.yaml", {"data.k_max": 10}),
        ("ablations/apv.yaml", {"model.world_model.ensemble": 1, "model.lambda_init": 0.0, "data.k_max": 1}),
        ("bf16.yaml", {"trainer.precision": "bf16-mixed", "trainer.default_root_dir": "runs/pretrain/ssv2-bf16"}),
    ],
)
def test_overlays_change_only_what_they_name(capsys, tmp_path, ssv2_config, overlay, expected):
    base, config = flat(ssv2_config), flat(resolved(capsys, tmp_path, "ssv2.yaml", overlay))
    assert base.keys() == config.keys()
    changed = {key: value for key, value in config.items() if value != base[key] and key != "data.shards"}
    root = f"runs/pretrain/{Path(overlay).stem}"  # each writes its runs apart from ssv2.yaml's
    assert changed == {"trainer.default_root_dir": root, **expected}


def flat(config: dict, prefix: str = "") -> dict:
    """A nested config as {"a.b.c": value}."""
    items = {}
    for key, value in config.items():
        if isinstance(value, dict) and value:
            items |= flat(value, f"{prefix}{key}.")
        else:
            items[f"{prefix}{key}"] = value
    return items


def test_tiny_runs_on_cpu(capsys, tmp_path):
    config = resolved(capsys, tmp_path, "tiny.yaml")
    assert config["trainer"]["accelerator"] == "cpu" and config["model"]["world_model"]["ensemble"] == 7
    assert config["model"]["compile"] == "off" and config["trainer"]["log_every_n_steps"] == 10


def test_every_setting_is_overridable(capsys, tmp_path):
    args = ["fit", "--config", str(CONFIGS / "ssv2.yaml"), "--data.shards", str(tmp_path), "--trainer.max_steps", "50",
            "--model.hcu_target", "0.3", "--model.world_model.temporal_mode", "absolute", "--data.seq_len", "24", "--print_config"]
    assert main(args) == 0
    config = yaml.safe_load(capsys.readouterr().out)
    assert config["trainer"]["max_steps"] == 50 and config["model"]["hcu_target"] == 0.3
    assert config["model"]["world_model"]["temporal_mode"] == "absolute" and config["data"]["seq_len"] == 24


def test_help_lists_the_sizes_under_model_world_model(capsys, tmp_path):
    assert main(["fit", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--model.world_model.deter DETER" in out and "size of the deterministic (GRU) state" in out
    assert "--model.deter" not in out


def test_sizes_in_the_old_flat_place_are_refused_with_their_new_place(capsys, tmp_path):
    assert main(["fit", "--config", str(CONFIGS / "tiny.yaml"), "--data.shards", str(tmp_path),
                 "--model.deter", "48", "--print_config"]) == 2
    assert "--model.deter is now --model.world_model.deter" in capsys.readouterr().err
    old = tmp_path / "old.yaml"
    old.write_text("model:\n  deter: 48\n  lr: 1.0e-3\n")
    assert main(["fit", "--config", str(CONFIGS / "tiny.yaml"), f"--config={old}", "--data.shards", str(tmp_path),
                 "--print_config"]) == 2
    err = capsys.readouterr().err
    assert f"{old}: model.deter (like every size) now belongs under model.world_model" in err and "Traceback" not in err


def test_a_config_file_that_is_not_yaml_is_named_among_several(capsys, tmp_path):
    broken = tmp_path / "extra.yaml"
    broken.write_text("trainer:\n  max_steps: [1\n")
    assert main(["fit", "--config", str(CONFIGS / "tiny.yaml"), "--config", str(broken), "--data.shards",
                 str(tmp_path)]) == 2
    assert f"error: config file {broken} is not valid YAML: expected ',' or ']'" in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="the refusals of a machine without a GPU")
def test_the_gpu_config_on_a_cpu_machine_says_which_flags_make_it_run(built_shards, capsys):
    gpu = ["fit", "--config", str(CONFIGS / "ssv2.yaml"), "--data.shards", str(built_shards)]
    assert main(gpu) == 2
    assert "trainer.accelerator is gpu and no CUDA GPU is visible: for a (slow) CPU run add --trainer.accelerator " \
           "cpu --trainer.devices 1 --trainer.strategy auto" in capsys.readouterr().err
    assert main(gpu + ["--trainer.accelerator", "cpu"]) == 2
    assert "trainer.devices -1 means every GPU, and this run is on the CPU" in capsys.readouterr().err


def test_a_config_file_that_is_not_text_is_named(capsys, tmp_path):
    binary = tmp_path / "last.ckpt"
    binary.write_bytes(b"\xdd\x00\xff binary")
    assert main(["fit", "--config", str(CONFIGS / "tiny.yaml"), "--config", str(binary), "--data.shards",
                 str(tmp_path)]) == 2
    assert f"error: config file {binary} is not valid YAML: 'utf-8' codec can't decode" in capsys.readouterr().err
