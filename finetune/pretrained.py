"""Load the frozen pre-trained export for fine-tuning (docs/architecture.md section 4; paper §4.3).

`load_pretrained(DIR)` reads `DIR/config.json` and `DIR/weights.safetensors` through
`model.export.load_frozen` (JSON and safetensors only: nothing is unpickled), then checks what
fine-tuning relies on — schema version (1 or 2), the world_model settings (sizes and the temporal
embedding's convention: mode, dim, reference length), tensor names and shapes, the feature size and the
image normalisation — and freezes every parameter (requires_grad False, eval mode). Every failure is a `PretrainedError` naming the file and
what to do.

`k1_embedding(model)` builds the conditioning of the frozen stream, Δt^e_{k=1}, the way pre-training
built embeddings: the relative mode encodes k = 1 at position 1 / T · reference_length. Fine-tuning has
no source clip, so T defaults to the median frame count of the clips the export was pre-trained on
(recorded in its config.json as provenance.train_clip_length: a typical pre-training clip's k = 1), or,
for an export that does not record it, to the reference length (position 1, the same vector as the
absolute mode's E[1]); `k1_clip_length` in the fine-tuning config sets another T. The first step of a sequence
(from the zero state) gets `gap_embedding(model, 0)` instead, as in pre-training.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from model.export import NORMALISATION, ExportError, FrozenWorldModel, load_frozen, read_config
from model.networks import IMAGE_SHAPE


class PretrainedError(ValueError):
    """A --pretrained directory that fine-tuning cannot use; the message names the file and the fix."""


def load_pretrained(directory: str | Path, device: torch.device | str = "cpu") -> FrozenWorldModel:
    directory = Path(directory)
    if not directory.is_dir():
        what = ("is a file, not an export directory (a checkpoint? export it first with `hauwm pretrain export "
                f"{directory} --out DIR`)" if directory.exists() else "no such directory")
        raise PretrainedError(f"--pretrained {directory}: {what}; pass the output of `hauwm pretrain export CKPT --out DIR`")
    try:
        config = read_config(directory)
        _check_convention(config, directory / "config.json")
        model = load_frozen(directory, device)
    except ExportError as error:
        raise PretrainedError(f"--pretrained {directory}: {error}") from None
    if model.rssm.feature_dim != config.get("feature_dim", model.rssm.feature_dim):
        raise PretrainedError(f"--pretrained {directory}: config.json says feature_dim {config['feature_dim']!r}, "
                              f"the weights give {model.rssm.feature_dim}; re-export the checkpoint")
    return model  # load_frozen returns it frozen and in eval mode


def _check_convention(config: dict, path: Path) -> None:
    """What the world_model settings (checked by read_config) do not cover: the frames fine-tuning feeds in."""
    image_shape = config.get("image_shape", IMAGE_SHAPE)
    if not isinstance(image_shape, (list, tuple)) or list(image_shape) != list(IMAGE_SHAPE):
        raise PretrainedError(f"{path}: image_shape {image_shape!r} differs from the {list(IMAGE_SHAPE)} "
                              "frames the environments give")
    length = config.get("provenance", {}).get("train_clip_length")
    if length is not None and not _a_length(length):
        raise PretrainedError(f"{path}: provenance.train_clip_length {length!r} is not a positive number of frames "
                              "(the median length of the pre-training clips); remove it, or re-export the checkpoint")
    normalisation = config.get("normalisation", NORMALISATION)
    if not isinstance(normalisation, dict) or \
            (normalisation.get("scale"), normalisation.get("offset")) != (NORMALISATION["scale"], NORMALISATION["offset"]):
        raise PretrainedError(f"{path}: image normalisation {normalisation!r} differs from this code's "
                              f"{NORMALISATION['formula']}")


def gap_embedding(model: FrozenWorldModel, gap: int, clip_length: float | None = None) -> torch.Tensor:
    """Δt^e_k for the gap k → [temporal_dim]; `clip_length` is T of the relative mode (default: the reference
    length). k = 0 is what every pre-training sequence began with (its first frame has no gap before it)."""
    clip_length = model.temporal.reference_length if clip_length is None else clip_length
    with torch.no_grad():
        return model.temporal(torch.tensor(float(gap)), torch.tensor(float(clip_length))).float()


def _a_length(value: object) -> bool:
    """Whether `value` (from JSON) is a positive, finite number of frames."""
    try:
        return type(value) in (int, float) and 0 < float(value) < math.inf
    except OverflowError:  # an int beyond any float
        return False


def k1_embedding(model: FrozenWorldModel, clip_length: float | None = None) -> torch.Tensor:
    """Δt^e_{k=1} → [temporal_dim]: the frozen stream's conditioning after the first step; `clip_length` is T
    (default: the median length of the export's pre-training clips, where it records one)."""
    return gap_embedding(model, 1, clip_length or model.export_config.get("provenance", {}).get("train_clip_length"))
