"""Agent updates per second on this machine (world-model step + imagination + actor and critic steps).

    python bench/bench_agent.py                       # paper sizes and a small CPU setting, 1 thread
    python bench/bench_agent.py --threads 2 --updates 5

Each setting builds the dual-stream agent on a freshly initialised export (timing does not depend on
the weights' values) and the scratch baseline with the same RSSM sizes, then times `--updates` updates
on random 64×64 batches after one warm-up update.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from finetune import load_pretrained  # noqa: E402
from finetune.agent import Agent  # noqa: E402
from finetune.config import FinetuneConfig  # noqa: E402
from finetune.pretrained import k1_embedding  # noqa: E402
from model.config import WorldModelConfig  # noqa: E402
from model.export import export_frozen  # noqa: E402
from model.world_model import WorldModel  # noqa: E402

ACTION_DIM = 6  # cheetah
SETTINGS = {
    # name: (export sizes, agent config)
    "paper (32x50, 400 units, cnn 32)": (dict(), dict(batch_size=32, seq_len=50)),
    "small (16x32, 200 units, cnn 16)": (dict(cnn_width=16, embed_dim=256, deter=100, stoch=20, hidden=100),
                                         dict(batch_size=16, seq_len=32, units=200, hidden=100, encoder_width=16)),
}


def bench(name: str, export_sizes: dict, agent_cfg: dict, updates: int, agent_kind: str) -> float:
    torch.manual_seed(0)
    cfg = FinetuneConfig(agent=agent_kind, **agent_cfg)
    if agent_kind == "scratch":  # same RSSM sizes as the export, its own encoder and decoder
        sizes = {k: export_sizes[k] for k in ("deter", "stoch") if k in export_sizes}
        agent = Agent(dataclasses.replace(cfg, **sizes), ACTION_DIM)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            frozen = load_pretrained(export_frozen(WorldModel(WorldModelConfig(**export_sizes)), tmp))
        agent = Agent(cfg, ACTION_DIM, frozen, k1_embedding(frozen))
    rng = np.random.default_rng(0)
    shape = (cfg.batch_size, cfg.seq_len)
    batch = {"obs": rng.integers(0, 256, (*shape, 3, 64, 64), dtype=np.uint8),
             "action": rng.uniform(-1, 1, (*shape, ACTION_DIM)).astype(np.float32),
             "reward": rng.normal(size=shape).astype(np.float32)}
    agent.update(batch)  # warm-up
    start = time.perf_counter()
    for _ in range(updates):
        agent.update(batch)
    return updates / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs, torch {torch.__version__}, {args.threads} "
          f"thread(s), CPU, {args.updates} timed updates after one warm-up, imagination horizon 15")
    print(f"{'setting':<36} {'agent':<8} {'updates/s':>10}")
    for name, (export_sizes, agent_cfg) in SETTINGS.items():
        for kind in ("hauwm", "scratch"):
            rate = bench(name, export_sizes, agent_cfg, args.updates, kind)
            print(f"{name:<36} {kind:<8} {rate:>10.3f}", flush=True)


if __name__ == "__main__":
    main()
