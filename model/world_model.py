"""The pre-trained world model as one nn.Module: encoder → temporal embedding → EnsembleRSSM → decoder.

The LightningModule trains it, the export saves it, and fine-tuning loads it back (model.export.load_frozen);
`config` holds exactly the constructor arguments, so the same dict rebuilds the same architecture.
"""

from __future__ import annotations

import inspect

import torch
from torch import nn

from model.networks import Decoder, Encoder, preprocess
from model.rssm import EnsembleRSSM, Observation, RSSMState
from model.temporal import TemporalEmbedding


class WorldModel(nn.Module):
    def __init__(
        self,
        cnn_width: int = 32,
        embed_dim: int = 1024,
        deter: int = 200,
        stoch: int = 30,
        hidden: int = 200,
        ensemble: int = 7,
        min_std: float = 0.1,
        max_std: float = 1.0,
        temporal_mode: str = "relative",
        temporal_dim: int = 32,
        reference_length: float = 100.0,
    ):
        super().__init__()
        self.config = dict(
            cnn_width=cnn_width, embed_dim=embed_dim, deter=deter, stoch=stoch, hidden=hidden, ensemble=ensemble,
            min_std=min_std, max_std=max_std,
            temporal_mode=temporal_mode, temporal_dim=temporal_dim, reference_length=reference_length,
        )
        self.encoder = Encoder(cnn_width, embed_dim)
        self.temporal = TemporalEmbedding(temporal_dim, temporal_mode, reference_length)
        self.rssm = EnsembleRSSM(embed_dim, temporal_dim, deter, stoch, hidden, ensemble, min_std, max_std)
        self.decoder = Decoder(self.rssm.feature_dim, cnn_width)

    def embed(self, frames: torch.Tensor) -> torch.Tensor:
        """uint8 frames [B, L, 3, 64, 64] → image embeddings [B, L, embed_dim]."""
        return self.encoder(preprocess(frames))

    def conditions(self, gaps: torch.Tensor, num_frames: torch.Tensor) -> torch.Tensor:
        """gaps [B, L], clip lengths T [B] → Δt embeddings [B, L, temporal_dim]."""
        return self.temporal(gaps, num_frames.unsqueeze(-1))

    def observe(
        self, frames: torch.Tensor, gaps: torch.Tensor, num_frames: torch.Tensor, generator: torch.Generator | None = None
    ) -> Observation:
        """Filter a batch of variable-gap sequences (docs/architecture.md section 2) into posterior states."""
        return self.rssm.observe(self.embed(frames), self.conditions(gaps, num_frames), generator=generator)

    def decode(self, state: RSSMState) -> torch.Tensor:
        """States with any leading dims → mean images [..., 3, 64, 64] in preprocess space ([-0.5, 0.5])."""
        return self.decoder(self.rssm.feature(state))


MODEL_KEYS = tuple(inspect.signature(WorldModel.__init__).parameters)[1:]  # the architecture-defining settings
