"""What a `compile` setting means on a device: one reading for pre-training's `model.compile` and fine-tuning's
`compile` (docs/pretraining.md, docs/finetuning.md).

    auto             CUDA graphs on a GPU ("reduce-overhead"), eager elsewhere
    off              eager
    default          inductor
    reduce-overhead  inductor + CUDA graphs; CUDA graphs need a GPU, so elsewhere it is inductor's default mode
"""

from __future__ import annotations

from typing import Literal

import torch

CompileSetting = Literal["auto", "off", "default", "reduce-overhead"]
COMPILE_SETTINGS: tuple[str, ...] = CompileSetting.__args__


def compile_mode(setting: str, device: torch.device) -> str | None:
    """The torch.compile mode that `setting` asks for on `device`, or None for eager."""
    if setting not in COMPILE_SETTINGS:
        raise ValueError(f"compile must be one of {', '.join(COMPILE_SETTINGS)}, got {setting!r}")
    if setting == "auto":
        return "reduce-overhead" if device.type == "cuda" else None
    if setting == "off":
        return None
    return "default" if setting == "reduce-overhead" and device.type != "cuda" else setting
