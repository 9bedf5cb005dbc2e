"""How many kernels a training step launches: pre-training's step, eager and compiled, and fine-tuning's update.

On a GPU the paper-size step is launch-bound (issue 12; fine-tuning's eager update too, issue 14): every operator
of an eager step is one kernel launch or more, and a compiled step's CUDA graph replays one node per kernel — the
H100's bare compiled step spent 3 ms of its 10 ms of host time in its two cudaGraphLaunch calls, which grow with the
nodes. The counts are the same on any device, so they are measured here on the CPU:

  eager: the operators one training step dispatches (forward, every loss term, backward; no optimizer), counted
         below autograd with a TorchDispatchMode, views and allocations left out (they launch nothing);
  compiled: the kernels inductor generates for the step's observe + losses, forward and backward (its C++
         kernels on a CPU; Triton's on a GPU fuse a little differently, so compare counts on one device only);
  agent: the operators of one eager fine-tuning update (`Agent.update` of the HAUWM agent: both streams' filtering,
         the model loss, imagination, the actor-critic losses, backward and the Adam steps) at Table 3's sequence
         length 50 and horizon 15, small widths (the counts depend on lengths, not widths). On a CPU torch's Adam
         runs per parameter; on a GPU it runs multi-tensor, with fewer operators.

    python bench/bench_step_ops.py [--sizes paper tiny] [--length 16] [--no-compile] [--no-agent]
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_pretrain import SIZES  # noqa: E402
from bench.machine import describe_machine  # noqa: E402
from model.config import WorldModelConfig  # noqa: E402
from model.module import PretrainModule  # noqa: E402

LAUNCH_NOTHING = {"detach", "empty", "empty_strided", "new_empty", "new_empty_strided", "lift_fresh", "set_"}


class KernelCounter(TorchDispatchMode):
    """Counts the operators that reach the kernels: no view (it only re-describes memory), no bare allocation."""

    def __init__(self):
        super().__init__()
        self.counts: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if not func.is_view and name not in LAUNCH_NOTHING:
            self.counts[name] += 1
        return func(*args, **(kwargs or {}))


def module_and_batch(size: str, length: int) -> tuple[PretrainModule, dict, torch.Tensor]:
    """A PretrainModule of `size`'s widths (M 7), a batch of 2 sequences of `length` frames and its noise: the
    counts do not depend on the batch size."""
    torch.manual_seed(0)
    module = PretrainModule(WorldModelConfig(**SIZES[size]["model"], ensemble=7))
    gaps = torch.randint(1, 6, (2, length))
    gaps[:, 0] = 0
    batch = {"frames": torch.randint(0, 256, (2, length, 3, 64, 64), dtype=torch.uint8), "gaps": gaps,
             "num_frames": torch.full((2,), 48)}
    return module, batch, module.noise(gaps, 0, stream=0)


def eager_kernels(size: str, length: int) -> Counter[str]:
    module, batch, noise = module_and_batch(size, length)
    with KernelCounter() as counter:
        module.training_losses(batch["frames"], batch["gaps"], batch["num_frames"], noise)["loss"].backward()
    return counter.counts


def compiled_kernels(size: str, length: int) -> tuple[int, float]:
    """Inductor's generated kernels for the step's forward and backward → (kernels, compile seconds)."""
    from torch._inductor import metrics

    module, batch, noise = module_and_batch(size, length)
    torch._dynamo.reset()
    metrics.reset()
    started = time.perf_counter()
    step = torch.compile(module.training_losses, dynamic=False)
    step(batch["frames"], batch["gaps"], batch["num_frames"], noise)["loss"].backward()
    return metrics.generated_kernel_count, time.perf_counter() - started


def agent_update_kernels(length: int = 50) -> Counter[str]:
    """The operators of one eager update of the HAUWM agent on a batch of 2 sequences of `length` (after one warm-up
    update: the optimizers' states exist)."""
    import numpy as np

    from bench.bench_agent import ACTION_DIM, SETTINGS, build

    export_sizes, _ = SETTINGS["small (16x32, 200 units, cnn 16)"]
    agent, _ = build(export_sizes, dict(batch_size=2, seq_len=length, units=200, hidden=100, encoder_width=16),
                     "hauwm", torch.device("cpu"), None)
    rng = np.random.default_rng(0)
    batch = {"obs": rng.integers(0, 256, (2, length, 3, 64, 64), dtype=np.uint8),
             "action": rng.uniform(-1, 1, (2, length, ACTION_DIM)).astype(np.float32),
             "reward": rng.normal(size=(2, length)).astype(np.float32)}
    agent.update(batch)
    with KernelCounter() as counter:
        agent.update(batch)
    return counter.counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", choices=sorted(SIZES), default=["paper"])
    parser.add_argument("--length", type=int, default=16, help="frames per sequence L (ssv2.yaml: 16)")
    parser.add_argument("--no-compile", action="store_true", help="count the eager operators only")
    parser.add_argument("--no-agent", action="store_true", help="leave out the fine-tuning update")
    args = parser.parse_args()
    print(f"machine: {describe_machine()}")
    print(f"settings: L {args.length}, M 7, batch 2 (the counts do not depend on it), float32")
    for size in args.sizes:
        counts = eager_kernels(size, args.length)
        top = ", ".join(f"{name} {count}" for name, count in counts.most_common(6))
        print(f"{size}: eager step (forward + backward) {sum(counts.values())} kernel-launching operators ({top})")
        if not args.no_compile:
            kernels, seconds = compiled_kernels(size, args.length)
            print(f"{size}: compiled step (forward + backward) {kernels} inductor kernels "
                  f"(compiled in {seconds:.0f} s)")
    if not args.no_agent:
        counts = agent_update_kernels()
        top = ", ".join(f"{name} {count}" for name, count in counts.most_common(6))
        print(f"agent: eager update (L 50, H 15) {sum(counts.values())} kernel-launching operators ({top})")


if __name__ == "__main__":
    main()
