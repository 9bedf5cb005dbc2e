"""Fixtures for the fine-tuning tests: a small export written from a freshly initialised world model."""

from __future__ import annotations

import pytest
import torch

from finetune.config import FinetuneConfig
from model.config import WorldModelConfig
from model.export import export_frozen
from model.world_model import WorldModel

# the small pre-trained model of these tests; the new stream must match its deter + stoch for the decoder
EXPORT_SIZES = WorldModelConfig(cnn_width=8, embed_dim=64, deter=24, stoch=8, hidden=24, ensemble=3, temporal_dim=8)


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def export_dir(tmp_path_factory):
    torch.manual_seed(0)
    return export_frozen(WorldModel(EXPORT_SIZES), tmp_path_factory.mktemp("export"), {"source": "tests"})


def _tiny_config(**overrides) -> FinetuneConfig:
    """Network widths and a schedule small enough for CI (the new stream takes the export's deter/stoch)."""
    values = dict(hidden=24, units=32, encoder_width=8, batch_size=4, seq_len=8, horizon=5, device="cpu", threads=1)
    values.update(overrides)
    return FinetuneConfig(**values)


@pytest.fixture
def tiny_config():
    return _tiny_config


@pytest.fixture
def export_sizes() -> WorldModelConfig:
    return EXPORT_SIZES
