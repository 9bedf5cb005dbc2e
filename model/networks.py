"""Image encoder and decoder of the world model (paper appendix D.1): ResNet-style CNNs, 64×64×3.

The encoder maps a frame o_t to the embedding that the posterior q(s_t | s_{t-1}, Δt, o_t) reads; the
decoder is the emission p(o_t | s_t) of eq. 2, returning the mean image (unit-variance Gaussian NLL).
Each has three residual blocks, one per resolution stage. Both accept any leading dims.
"""

from __future__ import annotations

import torch
from torch import nn

IMAGE_SHAPE = (3, 64, 64)


def preprocess(frames: torch.Tensor) -> torch.Tensor:
    """uint8 RGB frames [..., 3, H, W] → float32 in [-0.5, 0.5] (the normalisation recorded in exports)."""
    if frames.dtype != torch.uint8:
        raise TypeError(f"preprocess expects uint8 frames, got {frames.dtype}")
    return frames.float() / 255.0 - 0.5


def _norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(min(8, channels), channels)


class ResidualBlock(nn.Module):
    """x + conv(act(norm(conv(act(norm(x)))))) at constant resolution and width."""

    def __init__(self, channels: int):
        super().__init__()
        self.block = nn.Sequential(
            _norm(channels), nn.SiLU(), nn.Conv2d(channels, channels, 3, padding=1),
            _norm(channels), nn.SiLU(), nn.Conv2d(channels, channels, 3, padding=1),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.block(x)


class Encoder(nn.Module):
    """[..., 3, 64, 64] float → [..., embed_dim]: stem 64→32, then 3 × (residual block, stride-2 conv) → 4×4."""

    def __init__(self, width: int = 32, embed_dim: int = 1024):
        super().__init__()
        self.embed_dim = embed_dim
        layers: list[nn.Module] = [nn.Conv2d(3, width, 4, stride=2, padding=1)]  # 32×32
        channels = width
        for _ in range(3):  # 16×16, 8×8, 4×4
            layers += [ResidualBlock(channels), nn.Conv2d(channels, 2 * channels, 4, stride=2, padding=1)]
            channels *= 2
        layers += [_norm(channels), nn.SiLU(), nn.Flatten(), nn.Linear(channels * 4 * 4, embed_dim)]
        self.net = nn.Sequential(*layers)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        lead = images.shape[:-3]
        out = self.net(images.reshape(-1, *IMAGE_SHAPE))  # [N, embed_dim]
        return out.reshape(*lead, self.embed_dim)


class Decoder(nn.Module):
    """[..., feat_dim] → [..., 3, 64, 64] mean image: 4×4, then 3 × (residual block, stride-2 deconv), then 64×64."""

    def __init__(self, feat_dim: int, width: int = 32):
        super().__init__()
        channels = 8 * width
        layers: list[nn.Module] = [nn.Linear(feat_dim, channels * 4 * 4), nn.Unflatten(1, (channels, 4, 4))]
        for _ in range(3):  # 8×8, 16×16, 32×32
            layers += [ResidualBlock(channels), nn.ConvTranspose2d(channels, channels // 2, 4, stride=2, padding=1)]
            channels //= 2
        layers += [_norm(channels), nn.SiLU(), nn.ConvTranspose2d(channels, 3, 4, stride=2, padding=1)]  # 64×64
        self.net = nn.Sequential(*layers)
        self.feat_dim = feat_dim

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        lead = features.shape[:-1]
        out = self.net(features.reshape(-1, self.feat_dim))  # [N, 3, 64, 64]
        return out.reshape(*lead, *IMAGE_SHAPE)
