"""The `machine:` line that every bench script prints before its figures.

A figure in bench/README.md is only comparable with one from the same machine, so each script names it the same
way: the CPU model, the CPUs this process may use (taskset and SLURM cpusets shrink them) of those the machine has,
with its physical cores where the kernel tells them apart from hyper-threads (two busy threads on one core slow each
other), the GPU, the versions of Python and torch, and the load average when the bench started (a busy shared machine
slows every figure). Settings that belong to one bench (threads, MUJOCO_GL, sizes) go on its own `settings:` line.
"""

from __future__ import annotations

import os
import platform
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


def cpu_model() -> str:
    """The CPU's marketing name from /proc/cpuinfo (Linux), else what `platform` knows."""
    cpuinfo = Path("/proc/cpuinfo")
    for line in cpuinfo.read_text().splitlines() if cpuinfo.exists() else []:
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "unknown CPU"


def physical_cores() -> int | None:
    """The machine's physical cores, as the kernel sees them: distinct (physical id, core id) pairs in /proc/cpuinfo;
    None where it does not say (another OS, some virtual machines)."""
    cpuinfo = Path("/proc/cpuinfo")
    cores, package = set(), None
    for line in cpuinfo.read_text().splitlines() if cpuinfo.exists() else []:
        key, _, value = line.partition(":")
        if key.strip() == "physical id":
            package = value.strip()
        elif key.strip() == "core id":
            cores.add((package, value.strip()))
    return len(cores) or None


def gpu_name(device: str = "cpu") -> str:
    """The GPU behind `device` and its CUDA version, or "no GPU" for a CPU device."""
    if not str(device).startswith("cuda"):
        return "no GPU"
    import torch  # only a CUDA bench asks, and it has torch loaded already

    if not torch.cuda.is_available():  # the bench's own first CUDA call will say why
        return f"no GPU, although {device} was asked for"
    return f"{torch.cuda.get_device_name(device)}, CUDA {torch.version.cuda}"


def describe_machine(device: str = "cpu") -> str:
    """One line: CPU, usable/all CPUs (and physical cores), GPU, Python and torch versions, load average now."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    cores = physical_cores()
    cores_text = f" ({cores} physical cores)" if cores and cores != os.cpu_count() else ""
    try:
        torch_version = f"torch {version('torch')}"
    except PackageNotFoundError:
        torch_version = "no torch"
    return (f"{cpu_model()}, {usable} of {os.cpu_count()} CPUs usable{cores_text}; {gpu_name(device)}; "
            f"Python {platform.python_version()}, {torch_version}; load average {os.getloadavg()[0]:.1f}")
