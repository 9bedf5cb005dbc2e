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


def _random_episode(rng, length: int, action_dim: int) -> dict:
    action = rng.uniform(-1, 1, (length + 1, action_dim)).astype("float32")
    action[0] = 0.0
    reward = rng.uniform(0, 1, length + 1).astype("float32")
    reward[0] = 0.0
    return {"obs": rng.integers(0, 256, (length + 1, 3, 64, 64), dtype="uint8"), "action": action, "reward": reward,
            "success": (reward > 0.9).astype("float32")}


@pytest.fixture
def random_episodes():
    """`random_episodes(count, length, action_dim, seed)`: episodes in finetune.replay's format (entry 0 has a
    zero action and reward; `success` as load_episodes gives it), random frames, actions and rewards."""
    import numpy as np

    def make(count: int, length: int, action_dim: int, seed: int = 0) -> list[dict]:
        rng = np.random.default_rng(seed)
        return [_random_episode(rng, length, action_dim) for _ in range(count)]

    return make


@pytest.fixture
def minari_dataset(tmp_path, monkeypatch):
    """`minari_dataset(dataset_id, episodes, task, **settings)`: write a real Minari dataset
    (finetune.datasets.write_dataset, `settings` as its collection settings) under a temporary
    MINARI_DATASETS_PATH; returns the id."""
    from finetune.datasets import write_dataset

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))

    def write(dataset_id: str, episodes: list[dict], task: str, **settings) -> str:
        write_dataset(dataset_id, episodes, {"task": task, "source": "tests", **settings})
        return dataset_id

    return write


@pytest.fixture
def two_episodes(minari_dataset, random_episodes):
    """A Minari dataset of 2 random drawer-close episodes (test/two-episodes-v0), for offline runs."""
    return minari_dataset("test/two-episodes-v0", random_episodes(2, 12, 4), "metaworld_drawer_close")
