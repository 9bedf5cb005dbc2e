"""Sinusoidal temporal embedding Δt_k^e of the gap k between two frames (paper section 4.2, appendix D.2).

relative (default, the paper's "k as a proportion of T"): the Vaswani sinusoid evaluated at position
    k / T · reference_length, where T is the source clip's frame count; a gap spanning the whole clip
    sits at position reference_length whatever the clip's length.
absolute: the plain Vaswani row E[k] (position k), T ignored.

The mode, dim and reference length travel with the checkpoint (config.json of the export), because
fine-tuning must build the k = 1 embedding the same way.
"""

from __future__ import annotations

import math

import torch
from torch import nn

MODES = ("relative", "absolute")


class TemporalEmbedding(nn.Module):
    def __init__(self, dim: int = 32, mode: str = "relative", reference_length: float = 100.0):
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"temporal embedding mode must be one of {MODES}, got {mode!r}")
        if dim < 2 or dim % 2:
            raise ValueError(f"temporal embedding dim must be even and ≥ 2, got {dim}")
        if reference_length <= 0:
            raise ValueError(f"reference_length must be positive, got {reference_length}")
        self.dim, self.mode, self.reference_length = dim, mode, float(reference_length)
        # Vaswani frequencies 1 / 10000^(2i/dim), i = 0 .. dim/2-1
        inv_freq = torch.exp(-math.log(10000.0) * torch.arange(0, dim, 2, dtype=torch.float64) / dim)
        self.register_buffer("inv_freq", inv_freq.float(), persistent=False)

    def positions(self, gaps: torch.Tensor, num_frames: torch.Tensor | None = None) -> torch.Tensor:
        """The (float32) position at which each gap is encoded; num_frames broadcasts against gaps."""
        gaps = gaps.float()
        if self.mode == "absolute":
            return gaps
        if num_frames is None:
            raise ValueError("the relative temporal embedding needs num_frames (the source clip length T)")
        return gaps / num_frames.float().clamp(min=1) * self.reference_length

    def forward(self, gaps: torch.Tensor, num_frames: torch.Tensor | None = None) -> torch.Tensor:
        """gaps [...] int, num_frames [...] int (broadcastable; e.g. [B, 1] against [B, L]) → [..., dim] float32."""
        angles = self.positions(gaps, num_frames).unsqueeze(-1) * self.inv_freq  # [..., dim/2]
        return torch.stack([angles.sin(), angles.cos()], dim=-1).flatten(-2)  # PE[2i] = sin, PE[2i+1] = cos
