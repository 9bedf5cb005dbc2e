"""Load the frozen pre-trained export for fine-tuning (docs/architecture.md section 4; paper §4.3).

`load_pretrained(DIR)` reads `DIR/config.json` and `DIR/weights.safetensors` through
`model.export.load_frozen` (JSON and safetensors only: nothing is unpickled), which checks what fine-tuning
relies on — kind and schema version (1 or 2), the world_model settings (sizes and the temporal embedding's
convention: mode, dim, reference length), tensor names and shapes, the feature size, the image shape and
normalisation — and freezes every parameter (requires_grad False, eval mode). Every failure is a
`PretrainedError` naming `--pretrained`, the file and what to do.

`k1_embedding(model)` builds the conditioning of the frozen stream, Δt^e_{k=1}, the way pre-training
built embeddings: the relative mode encodes k = 1 at position 1 / T · reference_length. Fine-tuning has
no source clip, so T defaults to the median frame count of the clips the export was pre-trained on
(recorded in its config.json as provenance.train_clip_length: a typical pre-training clip's k = 1), or,
for an export that does not record it, to the reference length (position 1, the same vector as the
absolute mode's E[1]); `k1_clip_length` in the fine-tuning config sets another T. The first step of a sequence
(from the zero state) gets `gap_embedding(model, 0)` instead, as in pre-training.
"""

from __future__ import annotations

from pathlib import Path

import torch

from model.export import ExportError, FrozenWorldModel, load_frozen


class PretrainedError(ValueError):
    """A --pretrained directory that fine-tuning cannot use; the message names the file and the fix."""


def load_pretrained(directory: str | Path, device: torch.device | str = "cpu") -> FrozenWorldModel:
    directory = Path(directory)
    if not directory.is_dir():
        what = ("is a file, not an export directory (a checkpoint? export it first with `hauwm pretrain export "
                f"{directory} --out DIR`)" if directory.exists() else "no such directory")
        raise PretrainedError(f"--pretrained {directory}: {what}; pass the output of `hauwm pretrain export CKPT --out DIR`")
    try:
        return load_frozen(directory, device)  # frozen and in eval mode
    except ExportError as error:
        raise PretrainedError(f"--pretrained {directory}: {error}") from None


def gap_embedding(model: FrozenWorldModel, gap: int, clip_length: float | None = None) -> torch.Tensor:
    """Δt^e_k for the gap k → [temporal_dim]; `clip_length` is T of the relative mode (default: the reference
    length). k = 0 is what every pre-training sequence began with (its first frame has no gap before it)."""
    clip_length = model.temporal.reference_length if clip_length is None else clip_length
    device = model.temporal.inv_freq.device  # a model loaded onto a GPU: its inputs there too
    with torch.no_grad():
        return model.temporal(torch.tensor(float(gap), device=device),
                              torch.tensor(float(clip_length), device=device)).float()


def k1_embedding(model: FrozenWorldModel, clip_length: float | None = None) -> torch.Tensor:
    """Δt^e_{k=1} → [temporal_dim]: the frozen stream's conditioning after the first step; `clip_length` is T
    (default: the median length of the export's pre-training clips, where it records one)."""
    return gap_embedding(model, 1, clip_length or model.export_config.get("provenance", {}).get("train_clip_length"))
