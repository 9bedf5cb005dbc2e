"""Fixtures of the pre-training tests: a random batch in the loader's format, tiny model sizes, and one short
`hauwm pretrain fit` run of configs/pretrain/tiny.yaml on the shared `built_shards` (session-scoped)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from model.cli import main
from model.config import WorldModelConfig

REPO = Path(__file__).resolve().parents[2]
TINY_CONFIG = REPO / "configs" / "pretrain" / "tiny.yaml"
# model sizes small enough for unit tests (the tiny.yaml sizes are used by the CLI runs)
SMALL = WorldModelConfig(cnn_width=8, embed_dim=32, deter=24, stoch=6, hidden=24, ensemble=3, temporal_dim=8)
# a short run over built_shards: validation has 3 clips, train 18 (5 shards), all with ≥ 24 frames
# (logged every step, which the tests read; tiny.yaml itself logs every 10)
RUN_ARGS = ["--data.batch_size", "3", "--data.seq_len", "8", "--data.num_workers", "0", "--data.val_batches", "1",
            "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
            "--trainer.log_every_n_steps", "1"]
RUN_STEPS = 40
# the world_model section of tiny.yaml (min_std and max_std left at their defaults)
TINY_SIZES = WorldModelConfig(cnn_width=8, embed_dim=64, deter=64, stoch=16, hidden=64, ensemble=7, temporal_dim=16)


def make_batch(batch_size: int = 2, length: int = 6, k_max: int = 5, seed: int = 0) -> dict:
    """A batch as docs/architecture.md section 2 specifies, with random frames and gaps."""
    generator = torch.Generator().manual_seed(seed)
    gaps = torch.randint(1, k_max + 1, (batch_size, length), generator=generator)
    gaps[:, 0] = 0
    indices = gaps.cumsum(1)
    return {
        "frames": torch.randint(0, 256, (batch_size, length, 3, 64, 64), dtype=torch.uint8, generator=generator),
        "gaps": gaps,
        "indices": indices,
        "num_frames": indices[:, -1] + 1 + torch.randint(0, 20, (batch_size,), generator=generator),
        "label": torch.zeros(batch_size, dtype=torch.int64),
        "id": [f"clip{i}" for i in range(batch_size)],
    }


@pytest.fixture
def fake_batch() -> dict:
    return make_batch()


@pytest.fixture
def batch_factory():
    return make_batch


@pytest.fixture
def small_sizes() -> WorldModelConfig:
    return SMALL


def fit(shards: Path, root: Path, *extra: str) -> int:
    return main(["fit", "--config", str(TINY_CONFIG), "--data.shards", str(shards),
                 "--trainer.default_root_dir", str(root), *RUN_ARGS, *extra])


@pytest.fixture(scope="session")
def tiny_run(built_shards, tmp_path_factory) -> Path:
    """The run directory of RUN_STEPS steps of tiny.yaml (checkpoints/last.ckpt, lightning_logs/version_0)."""
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("tiny-run")
    assert fit(built_shards, root, "--trainer.max_steps", str(RUN_STEPS), "--trainer.val_check_interval", "20") == 0
    return root


@pytest.fixture(scope="session")
def tiny_export(tiny_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tiny-export")
    assert main(["export", str(tiny_run / "checkpoints" / "last.ckpt"), "--out", str(out)]) == 0
    return out
