"""Pre-training step time and peak memory on CPU: tiny.yaml and the paper's sizes, and the cost of the ensemble.

One training step = filter the batch through the world model, every loss term of eq. 2–4, backward, Adam step
(PretrainModule.compute_losses, without the Trainer around it), on random uint8 batches of the loader's format.
Each setting runs in a fresh process so its peak resident memory (ru_maxrss) is its own.
The M = 7 / M = 1 ratio is reported for the whole step and for the RSSM alone (the M heads are one batched op).

    python bench/bench_pretrain.py [--steps 3] [--threads 2] [--skip-paper]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import describe_machine  # noqa: E402

SIZES = {  # world-model sizes (configs/pretrain/tiny.yaml and ssv2.yaml) and batch shape
    "tiny": dict(model=dict(cnn_width=8, embed_dim=64, deter=64, stoch=16, hidden=64, temporal_dim=16), batch=8, length=12),
    "paper": dict(model=dict(cnn_width=32, embed_dim=1024, deter=200, stoch=30, hidden=200, temporal_dim=32), batch=32, length=16),
}


def measure(size: str, ensemble: int, steps: int, threads: int, rssm_only: bool, queue) -> None:
    import torch

    from model.config import WorldModelConfig
    from model.module import PretrainModule

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    spec = SIZES[size]
    module = PretrainModule(WorldModelConfig(**spec["model"], ensemble=ensemble), lambda_init=1.0 if ensemble > 1 else 0.0)
    B, L = spec["batch"], spec["length"]
    gaps = torch.randint(1, 6, (B, L))
    gaps[:, 0] = 0
    batch = {"frames": torch.randint(0, 256, (B, L, 3, 64, 64), dtype=torch.uint8), "gaps": gaps,
             "num_frames": torch.full((B,), 48)}
    world_model = module.world_model
    optimizer = torch.optim.Adam(world_model.parameters(), lr=1e-4)
    embeds = world_model.embed(batch["frames"]).detach()
    conds = world_model.conditions(batch["gaps"], batch["num_frames"])

    def step() -> None:
        optimizer.zero_grad()
        if rssm_only:
            obs = world_model.rssm.observe(embeds, conds)
            loss = obs.prior_mean.square().mean() + obs.post_mean.square().mean()
        else:
            obs = world_model.observe(batch["frames"], batch["gaps"], batch["num_frames"])
            loss = module.compute_losses(batch, obs)["loss"]
        loss.backward()
        optimizer.step()

    step()  # warm-up
    durations = []
    for _ in range(steps):
        start = time.perf_counter()
        step()
        durations.append(time.perf_counter() - start)
    # the median: one step slowed by another process on a shared machine does not move it
    queue.put((statistics.median(durations), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))


def run(size: str, ensemble: int, steps: int, threads: int, rssm_only: bool = False) -> tuple[float, float]:
    context = mp.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=measure, args=(size, ensemble, steps, threads, rssm_only, queue))
    process.start()
    result = queue.get()
    process.join()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=3, help="timed steps per setting (after one warm-up)")
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    parser.add_argument("--skip-paper", action="store_true", help="only the tiny sizes (the paper's take minutes)")
    args = parser.parse_args()
    print(f"machine: {describe_machine()}")
    print(f"settings: {args.threads} threads, float32, median of {args.steps} timed steps after 1 warm-up")
    print(f"{'setting':<34} {'batch×len':>9} {'s/step':>8} {'peak RSS MB':>12}")
    ratios = []
    for size in ["tiny"] if args.skip_paper else ["tiny", "paper"]:
        spec = SIZES[size]
        shape = f"{spec['batch']}×{spec['length']}"
        times = {}
        for rssm_only in (False, True):
            for ensemble in (7, 1):
                seconds, peak = run(size, ensemble, args.steps, args.threads, rssm_only)
                times[rssm_only, ensemble] = seconds
                what = "RSSM only" if rssm_only else "full step"
                print(f"{size + ' M=' + str(ensemble) + ' ' + what:<34} {shape:>9} {seconds:8.3f} {peak:12.0f}", flush=True)
        ratios.append((size, times[False, 7] / times[False, 1], times[True, 7] / times[True, 1]))
    for size, full, rssm in ratios:
        print(f"{size}: step time M=7 / M=1 = {full:.2f} (full step), {rssm:.2f} (RSSM only); aim ≤ 1.5")


if __name__ == "__main__":
    main()
