"""The frozen export handed from pre-training to fine-tuning (docs/architecture.md section 4).

    DIR/weights.safetensors   the WorldModel's state dict (encoder, rssm, decoder; float32)
    DIR/config.json           schema_version 2: the WorldModelConfig under "world_model" (sizes, M, the temporal
                              embedding's mode, dim and reference length), feature_dim, image_shape, the image
                              normalisation, provenance, and weights_sha256 (the weights file's, checked on load;
                              absent from exports written before it)

Schema version 1 (exports before WorldModelConfig) held the world_model keys flat at the top level; it is
still read, and read_config hands both versions back in the version-2 layout.

Loading reads JSON and safetensors only — nothing is unpickled — and checks the kind, the schema version, the
frames the model reads (image_shape, normalisation), the provenance's fields, and every tensor's name and shape
against the architecture the config describes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import pickle
import re
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load, save

from hauwm.atomic import written_whole
from hauwm.json_kinds import is_integer, is_number
from model.config import ConfigError, WorldModelConfig, saved_settings
from model.networks import IMAGE_SHAPE
from model.world_model import WorldModel

SCHEMA_VERSION = 2
READABLE_VERSIONS = (1, 2)
KIND = "hauwm-pretrained-world-model"
WEIGHTS_FILE = "weights.safetensors"
CONFIG_FILE = "config.json"
NORMALISATION = {"formula": "float32 = uint8 / 255 - 0.5", "scale": 1 / 255, "offset": -0.5, "channels": "RGB"}


class ExportError(ValueError):
    """An export directory that cannot be loaded; the message says which file and what to do."""


class FrozenWorldModel(WorldModel):
    """A WorldModel loaded from an export: every parameter frozen, always in eval mode.

    `config` is its WorldModelConfig; `export_config` the whole config.json (in the version-2 layout).
    """

    def __init__(self, export_config: dict[str, Any]):
        super().__init__(WorldModelConfig.from_dict(export_config["world_model"]))
        self.export_config = export_config

    def train(self, mode: bool = True) -> "FrozenWorldModel":
        return super().train(False)


def export_frozen(model: WorldModel, out_dir: str | Path, provenance: dict[str, Any] | None = None) -> Path:
    """Write weights.safetensors and config.json for `model` into out_dir; returns out_dir."""
    out = Path(out_dir)
    if diverged := non_finite(model.state_dict()):
        raise ExportError(f"the model's weights are not finite ({diverged[0]} holds NaN or inf; {len(diverged)} tensors "
                          f"do): it diverged; nothing was written to {out}: export an earlier checkpoint")
    if out.exists() and not out.is_dir():
        raise ExportError(f"--out {out} is a file, not a directory: an export is a directory of two files; choose "
                          "another --out")
    for path in (out / WEIGHTS_FILE, out / CONFIG_FILE):
        if path.exists() and not path.is_file():
            raise ExportError(f"{path} is a {'directory' if path.is_dir() else 'special file'}: an export writes a "
                              "file there; move it away or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    tensors = {name: t.detach().float().contiguous().cpu() for name, t in model.state_dict().items()}
    # one metadata entry: safetensors writes several in a different order each process, and fine-tuning runs
    # recognise their export by the file's sha256 (finetune/run_dir.py), so the same model must give the same bytes
    # safetensors' save_file makes the file readable by its owner only; written as bytes it follows the umask, so an
    # export on shared storage is readable by whoever may read the directory
    weights = save(tensors, metadata={"hauwm": f"{KIND}, schema_version {SCHEMA_VERSION}"})
    config = {
        "schema_version": SCHEMA_VERSION,
        "kind": KIND,
        "world_model": model.config.to_dict(),
        "feature_dim": model.rssm.feature_dim,
        "image_shape": list(IMAGE_SHAPE),
        "normalisation": NORMALISATION,
        "provenance": provenance or {},
        "weights_sha256": hashlib.sha256(weights).hexdigest(),  # bytes changed by a disk or a copy are found on load
    }
    # both written beside their names first, then renamed one after the other: a full disk or a kill while they are
    # written (seconds at paper sizes) leaves an export replaced with --overwrite as it was, whole; only a kill between
    # the two renames could pair the new config.json with the old weights
    with contextlib.ExitStack() as renames:  # on leaving: config.json renamed, then the weights
        for name, data in ((WEIGHTS_FILE, weights), (CONFIG_FILE, (json.dumps(config, indent=2) + "\n").encode())):
            renames.enter_context(written_whole(out / name)).write_bytes(data)
    return out


def read_config(export_dir: str | Path) -> dict[str, Any]:
    """config.json of an export in the version-2 layout (a version-1 file's flat keys moved under
    "world_model"; "schema_version" stays the file's), with its version and world_model checked."""
    path = Path(export_dir) / CONFIG_FILE
    if Path(export_dir).is_file() and Path(export_dir).suffix == ".ckpt":  # the fit's checkpoint, given as the export
        raise ExportError(f"{export_dir} is a checkpoint of `hauwm pretrain fit`, not an export: make one with "
                          f"`hauwm pretrain export {export_dir} --out DIR` and pass DIR")
    if Path(export_dir).is_file():
        raise ExportError(f"{export_dir} is a file: an export is the directory that holds {CONFIG_FILE} and "
                          f"{WEIGHTS_FILE} (e.g. {Path(export_dir).parent})")
    if not path.is_file():
        raise ExportError(
            f"{path} not found: {export_dir} is not a HAUWM export; create one with "
            "`hauwm pretrain export CKPT --out DIR`"
        )
    try:
        config = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ExportError(f"{path} is not valid JSON ({err}); re-export the checkpoint") from None
    version = config.get("schema_version") if isinstance(config, dict) else None
    if type(version) is not int or version not in READABLE_VERSIONS:
        raise ExportError(
            f"{path} has schema_version {version!r}, this code reads versions {READABLE_VERSIONS}; re-export the "
            "checkpoint with this version of hauwm, or load it with the version that wrote it"
        )
    if version == 1:
        flat = saved_settings(config)
        config = {key: value for key, value in config.items() if key not in flat} | {"world_model": flat}
    if config.get("kind", KIND) != KIND:
        raise ExportError(f"{path} is of kind {config['kind']!r}, not a {KIND}: pass the output of `hauwm pretrain "
                          "export CKPT --out DIR`")
    if not isinstance(config.get("world_model"), dict):
        raise ExportError(f"{path} lacks the \"world_model\" settings; re-export the checkpoint")
    _check_frames(config, path)
    if not isinstance(config.get("provenance", {}), dict):
        raise ExportError(f"{path}: \"provenance\" is {config['provenance']!r}, not an object; re-export the checkpoint")
    if (digest := config.get("weights_sha256")) is not None and not re.fullmatch("[0-9a-f]{64}", str(digest)):
        raise ExportError(f"{path}: weights_sha256 is {str(digest)[:70]!r}, not a sha256 in hex; re-export the "
                          "checkpoint")
    for key, (test, wanted) in PROVENANCE_KINDS.items():  # each may be absent or null: not recorded
        if (value := config.get("provenance", {}).get(key)) is not None and not test(value):
            raise ExportError(f"{path}: provenance.{key} is {json.dumps(value)[:40]}, not {wanted}; re-export the "
                              "checkpoint")
    try:
        WorldModelConfig.from_dict(config["world_model"])
    except ConfigError as err:
        raise ExportError(f"{path}: {err}; re-export the checkpoint with this version of hauwm") from None
    return config


def _check_frames(config: dict, path: Path) -> None:
    """The frames every user of an export feeds it (pre-training's shards, the environments of fine-tuning) are
    IMAGE_SHAPE, normalised as NORMALISATION says: an export that records others cannot read them."""
    image_shape = config.get("image_shape", IMAGE_SHAPE)
    if not isinstance(image_shape, (list, tuple)) or list(image_shape) != list(IMAGE_SHAPE):
        raise ExportError(f"{path}: image_shape {image_shape!r} differs from the {list(IMAGE_SHAPE)} frames this "
                          "version of hauwm feeds a world model (the shards', the environments')")
    normalisation = config.get("normalisation", NORMALISATION)
    if not isinstance(normalisation, dict) or \
            (normalisation.get("scale"), normalisation.get("offset")) != (NORMALISATION["scale"], NORMALISATION["offset"]):
        raise ExportError(f"{path}: image normalisation {normalisation!r} differs from this code's "
                          f"{NORMALISATION['formula']}")


def is_positive_length(value: object) -> bool:
    """Whether `value` (from JSON) is a positive, finite number of frames."""
    try:
        return type(value) in (int, float) and 0 < float(value) < math.inf
    except OverflowError:  # an int beyond any float
        return False


# what `world_model_from_checkpoint` records, as the analysis and fine-tuning read it: (test, what it wants)
PROVENANCE_KINDS = {"global_step": (is_integer, "a whole number"),
                    "k_max": (lambda v: is_integer(v) and v >= 1, "a whole number ≥ 1"),
                    "hcu": (lambda v: isinstance(v, bool), "true or false"),
                    "lambda_init": (is_number, "a number"),
                    "lambda_final": (is_number, "a number"),
                    "checkpoint": (lambda v: isinstance(v, str), "a path"),
                    "train_clip_length": (is_positive_length, "a positive number of frames (the median length of the "
                                          "pre-training clips)")}


def non_finite(tensors: Mapping[str, torch.Tensor]) -> list[str]:
    """The names of the floating-point tensors holding NaN or inf (a diverged model's), sorted."""
    return sorted(name for name, tensor in tensors.items() if tensor.is_floating_point() and not tensor.isfinite().all())


def load_frozen(export_dir: str | Path, device: torch.device | str = "cpu") -> FrozenWorldModel:
    """Rebuild the exported world model (frozen, eval mode) from DIR without unpickling anything."""
    config = read_config(export_dir)
    weights_path = Path(export_dir) / WEIGHTS_FILE
    if not weights_path.is_file():
        raise ExportError(f"{weights_path} not found; re-export the checkpoint into {export_dir}")
    source = config.get("provenance", {}).get("checkpoint") or "the checkpoint"
    try:  # read whole (the export's size in memory once more, briefly) to check it against its sha256 first
        data = weights_path.read_bytes()
        recorded = config.get("weights_sha256")  # None in exports written before it
        if recorded is not None and recorded != hashlib.sha256(data).hexdigest():
            raise ExportError(f"{weights_path} is not the file {CONFIG_FILE} was written with: its sha256 differs (bytes "
                              "changed by a disk or a copy, or an export --overwrite killed between writing the two "
                              f"files); re-export {source}")
        tensors = load(data)
    except (SafetensorError, OSError) as err:
        raise ExportError(f"{weights_path} cannot be read as safetensors ({err}); re-export {source}") from None
    model = FrozenWorldModel(config)
    expected = {name: tuple(t.shape) for name, t in model.state_dict().items()}
    found = {name: tuple(t.shape) for name, t in tensors.items()}
    problems = [f"missing {name}" for name in expected.keys() - found.keys()]
    problems += [f"unexpected {name}" for name in found.keys() - expected.keys()]
    problems += [
        f"{name}: file has {found[name]}, config.json implies {expected[name]}"
        for name in expected.keys() & found.keys()
        if found[name] != expected[name]
    ]
    if problems:
        raise ExportError(
            f"{weights_path} does not match {Path(export_dir) / CONFIG_FILE}: " + "; ".join(sorted(problems)[:8])
            + (f" (and {len(problems) - 8} more)" if len(problems) > 8 else "")
        )
    if model.rssm.feature_dim != config.get("feature_dim", model.rssm.feature_dim):
        raise ExportError(f"{Path(export_dir) / CONFIG_FILE} says feature_dim {config['feature_dim']!r}, the world_model "
                          f"settings give {model.rssm.feature_dim}; re-export the checkpoint")
    if diverged := non_finite(tensors):
        raise ExportError(f"{weights_path}: {diverged[0]} holds NaN or inf ({len(diverged)} tensors do): the checkpoint "
                          "it was exported from had diverged; export an earlier checkpoint of that fit")
    model.load_state_dict(tensors)
    return model.to(device).requires_grad_(False).eval()


def torch_load_failure(err: Exception) -> str:
    """Why torch.load(weights_only=True) refused a file, in one clause. torch's own messages run to paragraphs and,
    for a pickle, advise weights_only=False: unsafe, and no fix for a damaged or foreign file."""
    if isinstance(err, pickle.UnpicklingError):
        return "it is not a checkpoint, or one that holds more than tensors and plain data"
    reason = str(err).strip().split(". ")[0] or type(err).__name__
    return f"it is truncated or not a checkpoint: {reason}"


def read_checkpoint(checkpoint: str | Path) -> tuple[dict[str, Any], WorldModelConfig]:
    """A `hauwm pretrain fit` checkpoint (read with weights_only=True) and the world-model sizes it was trained
    with; an ExportError naming the file if it cannot be read or is not one (for export and for resuming a fit)."""
    path = Path(checkpoint)
    if path.is_dir():
        raise ExportError(f"{path} is a directory (an export?), not a checkpoint: pass a .ckpt file, e.g. "
                          "RUN/checkpoints/last.ckpt")
    if not path.is_file():
        raise ExportError(f"checkpoint {path} not found (fit writes RUN/checkpoints/last.ckpt)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise ExportError(f"{path} cannot be read as a Lightning checkpoint of `hauwm pretrain fit` "
                          f"({torch_load_failure(err)}); {another_checkpoint(path)}") from None
    if damaged := damaged_record(path):  # torch.load reads bytes changed in place (a disk, a copy) without a word
        raise ExportError(f"{path} is damaged: its record {damaged} fails its checksum (a disk or copy error); "
                          f"{another_checkpoint(path)}")
    if not (isinstance(state, dict) and {"state_dict", "hyper_parameters", "pytorch-lightning_version"} <= state.keys()):
        raise ExportError(f"{path} is not a Lightning checkpoint (it lacks state_dict, hyper_parameters or "
                          "pytorch-lightning_version); use one that `hauwm pretrain fit` wrote, e.g. RUN/checkpoints/last.ckpt")
    try:  # the settings under "world_model", or flat in checkpoints written before WorldModelConfig
        config = WorldModelConfig.from_dict(saved_settings(state["hyper_parameters"]))
    except ConfigError as err:
        raise ExportError(f"{path} is not a `hauwm pretrain fit` checkpoint (its hyper_parameters: {err})") from None
    return state, config


def damaged_record(path: Path) -> str | None:
    """The first record of a checkpoint (a zip archive, as torch.save writes them) whose data fails its CRC-32, None
    where all pass (or the file is not a zip: torch's legacy format)."""
    try:
        with zipfile.ZipFile(path) as archive:
            return archive.testzip()
    except zipfile.BadZipFile:
        return None


def newest_checkpoint(directory: Path, other_than: Path | None = None) -> Path | None:
    """The checkpoint (*.ckpt) written last in `directory`, `other_than` left out; None where there is none."""
    others = [path for path in directory.glob("*.ckpt") if other_than is None or path.name != other_than.name]
    return max(others, key=lambda path: path.stat().st_mtime, default=None)


def is_intact(path: Path) -> bool:
    """Whether a checkpoint file is a whole zip archive (as torch.save writes them) whose records all pass their
    CRC-32: not truncated, not changed in place."""
    try:
        with zipfile.ZipFile(path) as archive:
            return archive.testzip() is None
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, NotImplementedError, RuntimeError):  # a damaged
        return False  # directory: names that are not UTF-8, a method or an encryption it does not hold


def another_checkpoint(path: Path) -> str:
    """Advice for a checkpoint that cannot be used: the newest whole checkpoint beside it (is_intact: a disk or a copy
    that damaged one may have damaged the others), or what to do where there is none."""
    others = sorted((other for other in path.parent.glob("*.ckpt") if other.name != path.name),
                    key=lambda other: other.stat().st_mtime, reverse=True)
    if whole := next(filter(is_intact, others), None):
        return f"use another one, e.g. {whole} (the newest whole one beside it)"
    if others:
        return (f"the {len(others)} other checkpoint(s) beside it are damaged too: restore one from a copy, or start "
                "the fit afresh")
    return "use another one, e.g. RUN/checkpoints/last.ckpt"


def checkpoint_world_model(state: dict[str, Any], config: WorldModelConfig, path: Path) -> WorldModel:
    """The WorldModel of a checkpoint read by read_checkpoint; an ExportError naming the file if its weights are not
    those of its own world_model settings (another version's layout)."""
    model = WorldModel(config)
    prefix = "world_model."
    try:
        model.load_state_dict({name[len(prefix):]: t for name, t in state["state_dict"].items()
                               if name.startswith(prefix)})
    except RuntimeError as err:  # names or shapes that are not those of its own world_model settings
        detail = " ".join(str(err).split())[:300]
        raise ExportError(f"{path}: its weights do not fit its own world_model settings ({detail}); use a checkpoint "
                          "written by `hauwm pretrain fit` of this version") from None
    return model


def world_model_from_checkpoint(checkpoint: str | Path) -> tuple[WorldModel, dict[str, Any]]:
    """The WorldModel inside a `hauwm pretrain fit` checkpoint and its provenance."""
    path = Path(checkpoint)
    state, config = read_checkpoint(path)
    hparams = state["hyper_parameters"]
    model = checkpoint_world_model(state, config, path)
    log_lambda = state["state_dict"].get("log_lambda")
    provenance = {
        "checkpoint": str(path.resolve()),
        "global_step": int(state.get("global_step", 0)),
        "k_max": hparams.get("k_max"),
        "hcu": hparams.get("lambda_init", 0) > 0,
        "lambda_init": hparams.get("lambda_init"),
        "lambda_final": float(log_lambda.exp()) if log_lambda is not None and hparams.get("lambda_init", 0) > 0 else 0.0,
        "train_clip_length": state.get("train_clip_length"),  # median T of the clips trained on (None: not recorded)
    }
    return model, provenance
