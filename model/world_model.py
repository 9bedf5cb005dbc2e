"""The pre-trained world model as one nn.Module: encoder → temporal embedding → EnsembleRSSM → decoder.

The LightningModule trains it, the export saves it, and fine-tuning loads it back (model.export.load_frozen);
its sizes are one WorldModelConfig (model/config.py), so the same config rebuilds the same architecture.
"""

from __future__ import annotations

import torch
from torch import nn

from model.config import WorldModelConfig
from model.networks import Decoder, Encoder, preprocess
from model.rssm import EnsembleRSSM, Observation, RSSMState
from model.temporal import TemporalEmbedding


class WorldModel(nn.Module):
    def __init__(self, config: WorldModelConfig):
        super().__init__()
        self.config = config.validate()
        self.encoder = Encoder(config.cnn_width, config.embed_dim)
        self.temporal = TemporalEmbedding(config.temporal_dim, config.temporal_mode, config.reference_length)
        self.rssm = EnsembleRSSM(config.embed_dim, config.temporal_dim, config.deter, config.stoch, config.hidden,
                                 config.ensemble, config.min_std, config.max_std)
        self.decoder = Decoder(self.rssm.feature_dim, config.cnn_width)

    def embed(self, frames: torch.Tensor) -> torch.Tensor:
        """uint8 frames [B, L, 3, 64, 64] → image embeddings [B, L, embed_dim]."""
        return self.encoder(preprocess(frames))

    def conditions(self, gaps: torch.Tensor, num_frames: torch.Tensor) -> torch.Tensor:
        """gaps [B, L], clip lengths T [B] → Δt embeddings [B, L, temporal_dim]."""
        return self.temporal(gaps, num_frames.unsqueeze(-1))

    def observe(
        self, frames: torch.Tensor, gaps: torch.Tensor, num_frames: torch.Tensor, noise: torch.Tensor | None = None
    ) -> Observation:
        """Filter a batch of variable-gap sequences (docs/architecture.md section 2) into posterior states;
        noise [B, L, S] from `rssm.draw_noise` (fresh draws when None)."""
        return self.rssm.observe(self.embed(frames), self.conditions(gaps, num_frames), noise=noise)

    def decode(self, state: RSSMState) -> torch.Tensor:
        """States with any leading dims → mean images [..., 3, 64, 64] in preprocess space ([-0.5, 0.5])."""
        return self.decoder(self.rssm.feature(state))

