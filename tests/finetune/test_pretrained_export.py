"""finetune.load_pretrained: checks, freezing, clear errors; and `hauwm finetune` with a bad --pretrained."""

from __future__ import annotations

import json
import pickle
import shutil

import pytest
import torch

from finetune import load_pretrained
from finetune.cli import main
from finetune.pretrained import PretrainedError, k1_embedding


@pytest.fixture
def export_copy(export_dir, tmp_path):
    return shutil.copytree(export_dir, tmp_path / "export")


def test_loads_frozen_with_the_exported_sizes(export_dir, export_sizes):
    model = load_pretrained(export_dir)
    params = list(model.parameters())
    assert params and not any(p.requires_grad for p in params)
    assert not model.training and not any(m.training for m in model.modules())
    model.train()  # an agent switching to train mode must not unfreeze or un-eval the export
    assert not model.training
    assert model.rssm.ensemble == export_sizes.ensemble
    assert model.rssm.feature_dim == export_sizes.deter + export_sizes.stoch


def test_k1_embedding_follows_the_exported_convention(export_dir):
    model = load_pretrained(export_dir)
    reference = model.temporal.reference_length
    # relative mode: k = 1 of a clip of the reference length sits at position 1, i.e. sin(1·f), cos(1·f)
    expected = torch.stack([model.temporal.inv_freq.sin(), model.temporal.inv_freq.cos()], -1).flatten()
    assert torch.allclose(k1_embedding(model), expected)
    # a clip twice the reference length puts k = 1 at position 0.5
    half = torch.stack([(0.5 * model.temporal.inv_freq).sin(), (0.5 * model.temporal.inv_freq).cos()], -1).flatten()
    assert torch.allclose(k1_embedding(model, clip_length=2 * reference), half)


def test_the_gap_embedding_is_made_on_the_device_of_the_model(export_dir):
    """Its inputs were made on the CPU: an export loaded onto a GPU failed in k1_embedding and in the agent's
    constructor (found by a review; the meta device stands in for a GPU)."""
    model = load_pretrained(export_dir).to("meta")
    assert k1_embedding(model).device.type == "meta"


def test_k1_embedding_takes_the_median_length_of_the_exports_pre_training_clips(export_copy):
    """An export that records its clips' median frame count (provenance.train_clip_length) puts k = 1 where a
    typical pre-training clip had it; the setting k1_clip_length still wins."""
    config = json.loads((export_copy / "config.json").read_text())
    _edit_config(export_copy, provenance={**config["provenance"], "train_clip_length": 50})
    model = load_pretrained(export_copy)
    reference = model.temporal.reference_length
    assert torch.allclose(k1_embedding(model), k1_embedding(model, clip_length=50))
    assert not torch.allclose(k1_embedding(model), k1_embedding(model, clip_length=reference))


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda d: shutil.rmtree(d), "no such directory"),
        (lambda d: (d / "config.json").unlink(), "config.json not found"),
        (lambda d: (d / "weights.safetensors").unlink(), "weights.safetensors not found"),
        (lambda d: (d / "config.json").write_text("{not json"), "not valid JSON"),
        (lambda d: _edit_config(d, schema_version=99), "schema_version 99"),
        (lambda d: _edit_sizes(d, deter=25), "does not match"),
        (lambda d: _edit_sizes(d, temporal_mode="log"), "temporal_mode must be one of .* got 'log'"),
        (lambda d: (d / "weights.safetensors").write_bytes(pickle.dumps({"w": torch.zeros(2)})),
         "weights.safetensors is not the file config.json was written with"),
        (lambda d: ((d / "weights.safetensors").write_bytes(pickle.dumps({"w": torch.zeros(2)})),  # an export from
                    _edit_config(d, weights_sha256=None)), "cannot be read as safetensors"),  # before the checksum
        (lambda d: _edit_config(d, normalisation="x / 255"), "image normalisation 'x / 255' differs"),
        (lambda d: _edit_config(d, image_shape=64), "image_shape 64 differs"),
        (lambda d: _edit_config(d, feature_dim="32"), "config.json says feature_dim '32', the world_model settings give"),
        (lambda d: (shutil.rmtree(d), d.write_bytes(b"a checkpoint")), "is a file, not an export directory"),
        (lambda d: _edit_config(d, provenance=[]), "\"provenance\" is \\[\\], not an object"),
        (lambda d: _edit_config(d, provenance={"train_clip_length": -3}), "train_clip_length is -3, not a positive"),
        (lambda d: _edit_config(d, provenance={"train_clip_length": 0}), "train_clip_length is 0, not a positive"),
        (lambda d: _edit_config(d, provenance={"train_clip_length": 10**400}), "train_clip_length is 1000.*, not a positive"),
        (lambda d: _change_a_weight(d), "weights.safetensors is not the file config.json was written with: its sha256 differs"),
        (lambda d: _edit_config(d, weights_sha256="abc"), "weights_sha256 is 'abc', not a sha256 in hex"),
    ],
    ids=["no-dir", "no-config", "no-weights", "bad-json", "wrong-version", "wrong-shapes", "bad-embedding", "a-pickle", "a-pickle-unchecked",
         "normalisation-text", "shape-number", "feature-dim-text", "a-file", "provenance-list", "negative-length", "zero-length",
         "huge-length", "weight-changed", "bad-checksum"],
)
def test_bad_exports_fail_clearly(export_copy, damage, message):
    damage(export_copy)
    with pytest.raises(PretrainedError, match=message) as error:
        load_pretrained(export_copy)
    assert str(export_copy) in str(error.value)


def _edit_config(directory, **changes):
    config = json.loads((directory / "config.json").read_text())
    config.update(changes)
    (directory / "config.json").write_text(json.dumps(config))


def _change_a_weight(directory):
    """Two float32 ones written over the middle of the weights (a disk or copy error: finite, plausible values)."""
    weights = directory / "weights.safetensors"
    data = bytearray(weights.read_bytes())
    data[len(data) // 2:len(data) // 2 + 8] = bytes.fromhex("0000803f0000803f")
    weights.write_bytes(bytes(data))


def _edit_sizes(directory, **changes):
    config = json.loads((directory / "config.json").read_text())
    _edit_config(directory, world_model={**config["world_model"], **changes})


def test_a_version_1_export_still_loads(export_dir, export_sizes, as_v1_export, tmp_path):
    model = load_pretrained(as_v1_export(export_dir, tmp_path / "v1"))
    assert model.export_config["schema_version"] == 1 and model.config == export_sizes
    reference = load_pretrained(export_dir)
    assert all(torch.equal(model.state_dict()[name], t) for name, t in reference.state_dict().items())
    assert torch.equal(k1_embedding(model), k1_embedding(reference))


def test_cli_reports_a_bad_pretrained_without_a_traceback(tmp_path, capsys):
    code = main(["--config", "configs/finetune/demo.yaml", "--pretrained", str(tmp_path / "missing"),
                 "--logdir", str(tmp_path / "run"), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2
    assert "--pretrained" in err and "missing" in err and "hauwm pretrain export" in err
    assert "Traceback" not in err


def test_cli_requires_pretrained_for_the_hauwm_agent(tmp_path, capsys):
    code = main(["--config", "configs/finetune/demo.yaml", "--logdir", str(tmp_path / "run"), "--no-progress"])
    assert code == 2
    assert "needs --pretrained" in capsys.readouterr().err
