"""What a run will hold in host memory, checked against what the machine has before the run starts.

A size that cannot fit (a world model of `ensemble: 100000`, an actor of `units: 100000`, a replay of 10^7 frames on a
laptop, 100,000 decoder or env worker processes) is refused in one line naming its settings, instead of being ended
by the kernel's OOM killer (exit 137, no message of ours) while it builds, or hours in. Every stage states its needs
as named byte counts:

    problem = beyond_memory({"the world model's weights, gradients and Adam state": 87 * 2**30}, "lower …")
    if problem:
        raise ConfigError(problem)

The counts are estimates from below (parameters, the activations a forward pass keeps for its backward pass, frames,
less than a worker process was measured to hold; not the interpreter, not the libraries), so a run that is refused
could not have finished; one that is not refused may still need more.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where used: `hauwm shards` checks its workers without importing torch (seconds)
    import torch

PARAMETER_BYTES = 4  # float32
UNCOUNTABLE = 2**100  # the need of a tensor whose size overflows torch's 64-bit byte count
DECODER_BYTES = 8 * 2**20  # a shard builder's decoder process (16 MiB of its own measured on the sample clips)
ENV_WORKER_BYTES = 64 * 2**20  # an env worker process (94 MiB of its own measured on DMC cartpole, 64×64 frames)


def memory_available() -> int | None:
    """Bytes of memory available to new allocations: Linux's MemAvailable, or less where this process's memory cgroup
    (a container's, a Slurm job's `--mem`) leaves less; None where neither says."""
    return min((size for size in (meminfo_available(), cgroup_available()) if size is not None), default=None)


def meminfo_available() -> int | None:
    """The machine's MemAvailable (/proc/meminfo), None where there is none."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


# a memory cgroup's files, version 2 and version 1: (limit, usage, the memory.stat key of its inactive page cache)
CGROUP_FILES = {2: ("memory.max", "memory.current", "inactive_file"),
                1: ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")}


def cgroup_available(root: Path = Path("/sys/fs/cgroup"), membership: Path = Path("/proc/self/cgroup")) -> int | None:
    """What this process's memory cgroup and every cgroup above it leave to allocate, the least of them: the limit less
    the usage, plus the inactive page cache the kernel reclaims before its OOM killer acts; None where none has a
    limit. `membership` lists the process's cgroups (version 2's line "0::PATH", version 1's "N:memory:PATH")."""
    try:
        lines = membership.read_text().splitlines()
    except OSError:
        return None
    left = []
    for line in lines:
        if line.count(":") < 2:
            continue
        _, controllers, path = line.split(":", 2)
        version = 2 if controllers == "" else 1 if "memory" in controllers.split(",") else None
        if version is None:
            continue
        base = root if version == 2 else root / "memory"
        directory = base / path.lstrip("/")
        while True:  # a job's limit is often set on a cgroup above the process's own (Slurm: the job's, not the step's)
            if (size := cgroup_left(directory, *CGROUP_FILES[version])) is not None:
                left.append(size)
            if directory == base or base not in directory.parents:
                break
            directory = directory.parent
    return min(left, default=None)


def cgroup_left(directory: Path, limit_file: str, usage_file: str, inactive_key: str) -> int | None:
    """What one cgroup `directory` leaves to allocate, None where it has no limit ("max", or version 1's 2^63 − 4096)
    or cannot be read."""
    try:
        limit = (directory / limit_file).read_text().strip()
        if not limit.isdigit() or int(limit) >= 2**62:
            return None
        usage = int((directory / usage_file).read_text())
    except (OSError, ValueError):
        return None
    try:
        stat = dict(line.split()[:2] for line in (directory / "memory.stat").read_text().splitlines() if line.strip())
        inactive = int(stat.get(inactive_key, 0))
    except (OSError, ValueError):  # the limit still holds
        inactive = 0
    return max(int(limit) - usage + inactive, 0)


def parameter_count(build: Callable[[], torch.nn.Module]) -> int:
    """The parameters of the module `build` returns, built on the meta device: shapes only, no memory, milliseconds
    even for a model that would not fit."""
    import torch

    try:
        with torch.device("meta"):
            return sum(parameter.numel() for parameter in build().parameters())
    except RuntimeError as error:
        if "overflow" in str(error):  # a size past 2^63 bytes: more than any machine has
            return UNCOUNTABLE
        raise


def training_memory(forward: Callable[[], torch.nn.Module]) -> dict[str, int]:
    """The least memory of training the module that `forward` builds and runs forward once (returning the module): its
    float32 weights and Adam's two moments, then, at the end of the forward pass, the activations autograd saved for
    the backward pass, or at the end of the backward pass the gradients, whichever is larger. Run on fake tensors
    (shapes only: no memory, under a second at the paper's sizes)."""
    import torch
    from torch._subclasses.fake_tensor import FakeTensorMode  # what torch.compile traces with: shapes, no memory

    saved: dict[int, int] = {}  # storage → bytes: a tensor saved by several operations is held once

    def keep(tensor: torch.Tensor) -> torch.Tensor:
        storage = tensor.untyped_storage()
        saved[storage._cdata] = storage.nbytes()
        return tensor

    try:
        with FakeTensorMode(), torch.autograd.graph.saved_tensors_hooks(keep, lambda tensor: tensor):
            module = forward()
    except RuntimeError as error:
        if "overflow" in str(error):  # a size past 2^63 bytes: more than any machine has
            return {"weights and Adam state": UNCOUNTABLE}
        raise
    weights = {parameter.untyped_storage()._cdata for parameter in module.parameters()}  # saved, but counted below
    activations = sum(size for storage, size in saved.items() if storage not in weights)
    parameters = sum(parameter.numel() for parameter in module.parameters()) * PARAMETER_BYTES
    return {"weights and Adam state": 3 * parameters, "saved activations or gradients": max(activations, parameters)}


def size_text(size: int) -> str:
    if size >= UNCOUNTABLE:
        return "2^63 bytes"
    for unit, scale in (("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30)):
        if size >= scale:
            return f"{size / scale:.1f} {unit}"
    return f"{size / 2**20:.1f} MiB"


def beyond_memory(needs: dict[str, int], fix: str) -> str | None:
    """A one-line refusal when the bytes of `needs` (what → bytes) add up to more than the memory available: it gives
    the total, the needs of 1% of it or more, what is available, then `fix`; None when they fit (or nothing says what is
    available)."""
    available = memory_available()
    needed = sum(needs.values())
    if available is None or needed <= available:
        return None
    parts = ", ".join(f"{what} {size_text(size)}" for what, size in sorted(needs.items(), key=lambda need: -need[1])
                      if size >= needed / 100)
    return (f"this run needs at least {size_text(needed)} of memory ({parts}), more than the {size_text(available)} "
            f"available: {fix}")
