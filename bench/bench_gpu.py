"""Pre-training speed on one GPU (issue 12): the bare training step eager vs compiled, and the real fit.

    python bench/bench_gpu.py                     # a GPU: ssv2.yaml settings, L = 16 and 50; under 8 minutes
    python bench/bench_gpu.py --device cpu        # tiny.yaml settings, few steps: the same code on a CPU
        [--shards DIR] [--lengths 16 50] [--steps 40] [--workers 4] [--worker-priority idle] [--precision bf16-mixed]

Bare step: PretrainModule's noise, observe + losses (`training_losses`, eager or through `model.compile`),
backward (GradScaler under 16-mixed), unscale, clip, the fused Adam's step, the skip counters and λ's dual step —
what `training_step` does, without Lightning and its logging every N steps — on batches read from the shards beforehand, in the config's
precision. Per length: ms per step and steps/s (the mean of --steps steps after 3 warm-up steps), the wall
time of the 3 warm-up steps (compiling, CUDA-graph recording), peak memory, and the process's CPU time per
step, all threads ("host ms": near the wall time per step on a GPU, the step is bound by the host); on a GPU
also the device's busy time per step over 10 profiled steps ("GPU busy ms": near ms/step, the GPU is the limit).

Real fit: `hauwm pretrain fit` through model.cli's LightningCLI with configs/pretrain/ssv2.yaml (GPU) or
tiny.yaml (CPU) on one device: its precision, model.compile and log_every_n_steps, --workers DataLoader
workers at the config's data.worker_priority (or --worker-priority); progress bar off (its output would
interleave) and no validation. Steps/s over the steps after the warm-up (whole epochs for short epochs), on
  (a) long epochs: the sample train shards linked 63 times (over 500 steps an epoch at batch 32, 4 workers);
  (b) short epochs: the sample data's 258 train clips (8 steps an epoch at batch 32, 4 workers: a new
      epoch every 8 steps, served by the same persistent workers; before them, the workers started again);
with the skipped steps by cause (GradScaler's overflows, non-finite steps); on a GPU (a) again with the config's
own workers (ssv2.yaml: 8), and with batches copied from ordinary memory (--data.pin_memory false, "unpinned"; at
most 1,000 steps). Before the fits, the fit's train loader alone (no model) on the same shards and
workers: the batches/s it gives is the most steps/s the fit could reach with them. Then the bare step fed by
that loader (long epochs; on a GPU with pinned memory and without): near the bare step, Lightning's machinery is
what the fit adds; near the fit, the loader's hand-over in the training process is. On the CPU also the issue's CPU
target: the fit with 2 workers against the bare step loop on the same batches (aim ≥ 0.9×), and with 0 workers.
A shared CPU host drifts by more than that margin within minutes, so on the CPU every fit is bracketed: the
bare eager loop is timed again right after it, each fit is compared with the mean of the bare runs just before
and just after, and the whole sequence runs --rounds times (default 3) with the median ratio printed last.
Then each fit by the host's clock: the mean and median time inside its steps and between them, inside's median over
its first 200 timed steps and the rest (do steps slow down as the fit goes on?), its slow steps (an interval over
twice the median: a logging step, a late batch, an epoch's end) with what they add to the mean, and on a GPU how many
steps the GPU had queued at a step's end (about 0: it has finished the step and waits for the host; 1 or more: it
is behind the host, which blocks in a launch once CUDA's queue is full).
Last, where a fit step's time goes (StepDiagnosis, one more short fit on long epochs): the operations that make
the host wait for the GPU, by call site; the host's time inside and between steps; a profiled window.
At the end, the graphs compiled over the whole bench and the CUDA-graph skips (a compiled graph run without its
CUDA graph: none expected).
Shards: built from `hauwm shards sample-data --clips 344` in a temporary directory, or --shards DIR.
"""

from __future__ import annotations

import argparse
import atexit
import gc
import itertools
import json
import logging
import math
import os
import resource
import shutil
import statistics
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter, deque
from collections.abc import Iterator
from pathlib import Path

import lightning as L
import torch
import yaml
from torch._dynamo.utils import counters
from torch.utils.data import DataLoader

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.machine import describe_machine  # noqa: E402
from data_pipeline.datamodule import ShardDataModule  # noqa: E402
from data_pipeline.dataloader import WORKER_PRIORITIES  # noqa: E402
from data_pipeline.dataset import SequenceDataset, shard_set  # noqa: E402
from data_pipeline.shard_format import MANIFEST_FILE, ShardDirError, read_manifest  # noqa: E402
from model.lightning_cli import lightning_cli  # noqa: E402
from model.config import WorldModelConfig  # noqa: E402
from model.module import PretrainModule, compiled, step_unless  # noqa: E402

CONFIGS = ROOT / "configs" / "pretrain"
SAMPLE_CLIPS = 344  # 258 train clips (the sample data keeps 1/8 each for validation and test)
LONG_EPOCH_COPIES = 63  # 63 × 258 train clips: 126 batches of 32 per worker, 504 steps an epoch with 4 workers
WARM_UP = 3  # bare steps before the timing: compiling and CUDA-graph recording happen here
FIT_WARM_UP = 20  # fit steps before the timing (rounded up to whole epochs for short epochs)
FED_STEPS = 500  # at most, timed steps of the bare step fed by the loader (each run compiles the step anew)
VARIANT_STEPS = 1000  # at most, steps of the unpinned fit
QUEUE_PROBE = 64  # at most, the steps the GPU is seen to have queued (a fit step launches ~80 kernels and 2 graphs)
EARLY_STEPS = 200  # the timed steps a fit's host times are first shown for, then the rest (do steps slow down?)
PROFILED_STEPS = 10  # bare steps profiled after the timed ones (a GPU): the device's busy time a step


class StepTimer(L.Callback):
    """The wall-clock time at the start of training and at the start and end of every training batch, and the CPU
    time of the training process (all its threads) at each batch end; the device is synchronised at the last step's
    end, so the last time covers all queued work, and not the last.ckpt the fit writes after it (the
    checkpoint callbacks run after this one). On a GPU also, at each batch end, how many steps the GPU has queued:
    those whose work it has not finished, this one included (CUDA events, which complete in order). About 0 when
    the GPU waits for the host (it has finished the step by the time the host ends it); 1 or more when the host runs
    ahead, until CUDA's launch queue is full and a launch blocks the host: then the host's time inside a step is the
    GPU's, whatever the GPU's busy time."""

    def __init__(self):
        self.start, self.starts, self.times, self.cpu_times = 0.0, [], [], []
        self.queued: list[int] = []
        self._events: deque[torch.cuda.Event] = deque(maxlen=QUEUE_PROBE)

    def on_train_start(self, trainer, pl_module):
        self.start = time.perf_counter()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.starts.append(time.perf_counter())

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step >= trainer.max_steps:
            synchronize(pl_module.device)
        self.times.append(time.perf_counter())
        self.cpu_times.append(time.process_time())
        if pl_module.device.type == "cuda":
            self._events.append(torch.cuda.Event())
            self._events[-1].record()
            self.queued.append(next((index for index, event in enumerate(reversed(self._events)) if event.query()),
                                    len(self._events)))


class StepDiagnosis(L.Callback):
    """Where a fit's step time goes, in two windows after FIT_WARM_UP steps (short: each slows the fit).

    SYNC_STEPS steps under CUDA's sync debug mode (a GPU only): every operation that makes the host wait for the
    GPU, counted by where it was called (the innermost frame of this repository, and of torch or Lightning) —
    with none, the host queues steps ahead of the GPU; with one a step, host and GPU take turns. In the same window,
    the host's wall time inside the step (on_train_batch_start to _end: training_step and its hooks) and between
    steps (Lightning's loop, the next batch from the loader, its copy to the device). Then PROFILE_STEPS steps under
    torch.profiler: the device's busy time per step (the union of its kernels' intervals), the time spent in CUDA
    calls that wait (synchronize, blocking copies), and the host operators that take the most time. A window the
    fit leaves early (it ended, or raised) is closed at teardown, so nothing of it outlives the fit."""

    SYNC_STEPS, PROFILE_STEPS = 30, 10

    def __init__(self):
        self.sync_sites: Counter[str] = Counter()
        self.inside: list[float] = []  # host seconds inside each step of the sync window
        self.between: list[float] = []  # host seconds from the end of a step to the start of the next, same window
        self.profile: dict | None = None
        self._started = self._ended = 0.0
        self._catcher: warnings.catch_warnings | None = None
        self._profiler: torch.profiler.profile | None = None
        self._show_warning = warnings.showwarning

    def window(self, step: int) -> str | None:
        """"sync", "profile" or None: the window the 0-based step `step` falls in."""
        sync_from = FIT_WARM_UP
        profile_from = sync_from + self.SYNC_STEPS
        if sync_from <= step < profile_from:
            return "sync"
        return "profile" if profile_from <= step < profile_from + self.PROFILE_STEPS else None

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        step, device = trainer.global_step, pl_module.device
        self._started = time.perf_counter()
        if self.window(step) == "sync":
            if step > 0:
                self.between.append(self._started - self._ended)
            if self._catcher is None and device.type == "cuda":
                self.open_sync_window()
        if self.window(step) == "profile" and self._profiler is None:
            activities = [torch.profiler.ProfilerActivity.CPU]
            if device.type == "cuda":
                activities.append(torch.profiler.ProfilerActivity.CUDA)
            self._profiler = torch.profiler.profile(activities=activities, acc_events=True)
            self._profiler.__enter__()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step - 1  # the step just done (global_step counts it already)
        self._ended = time.perf_counter()
        if self.window(step) == "sync":
            self.inside.append(self._ended - self._started)
            if self.window(step + 1) != "sync":
                self.close_sync_window()
        if self.window(step) == "profile" and self.window(step + 1) != "profile":
            synchronize(pl_module.device)
            self.close_profile(self.PROFILE_STEPS)

    def teardown(self, trainer, pl_module, stage) -> None:
        self.close_sync_window()
        if self._profiler is not None:  # the fit ended inside the window: its figures would be of fewer steps
            self.close_profile(steps=0)

    def open_sync_window(self) -> None:
        self._catcher = warnings.catch_warnings()
        self._catcher.__enter__()
        warnings.filterwarnings("always", message=".*synchroniz")
        self._show_warning, warnings.showwarning = warnings.showwarning, self.record_sync
        torch.cuda.set_sync_debug_mode("warn")

    def close_sync_window(self) -> None:
        if self._catcher is not None:
            torch.cuda.set_sync_debug_mode("default")  # reports itself as synchronising: record_sync skips it
            self._catcher.__exit__(None, None, None)  # the warning filters and showwarning as they were
            self._catcher = None

    def close_profile(self, steps: int) -> None:
        """Stop the profiler; with `steps` > 0 keep its summary per step."""
        self._profiler.__exit__(None, None, None)
        if steps:
            self.profile = summarise_profile(self._profiler, steps)
        self._profiler = None

    def record_sync(self, message, category, filename, lineno, file=None, line=None) -> None:
        """warnings.showwarning in the sync window: a synchronising call is counted by where it was made (the
        innermost frame of this repository, then of torch or Lightning); any other warning is shown as usual."""
        if "synchroniz" not in str(message):
            return self._show_warning(message, category, filename, lineno, file, line)
        frames = traceback.extract_stack()[:-1]
        ours = [f for f in frames if f.filename.startswith(str(ROOT)) and "/bench/" not in f.filename
                and "site-packages" not in f.filename]
        library = [f for f in frames if "/torch/" in f.filename or "/lightning/" in f.filename]
        if library and library[-1].name == "set_sync_debug_mode":  # the window's own closing
            return None
        site = " via ".join(f"{Path(f.filename).name}:{f.lineno} ({f.name})" for f in ours[-1:] + library[-1:])
        self.sync_sites[site or f"{filename}:{lineno}"] += 1


def summarise_profile(profiler: torch.profiler.profile, steps: int) -> dict:
    """Per step: the device's busy ms (union of kernel intervals), ms in waiting CUDA calls, the top host ops."""
    events = profiler.events()
    kernels = sorted((e.time_range.start, e.time_range.end) for e in events
                     if e.device_type == torch.autograd.DeviceType.CUDA)
    busy, covered_to = 0.0, -math.inf
    for start, end in kernels:
        busy += max(0.0, end - max(start, covered_to))
        covered_to = max(covered_to, end)
    waits = Counter()
    for event in events:
        if event.name in ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpy"):
            waits[event.name] += event.time_range.elapsed_us()
    host = sorted(profiler.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)[:6]
    return {"device_busy_ms": busy / 1000 / steps,
            "waits": {name: us / 1000 / steps for name, us in waits.items()},
            "host_top": [(e.key, e.self_cpu_time_total / 1000 / steps, e.count / steps) for e in host]}


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def peak_memory_gib(device: torch.device) -> float:
    """Peak GPU memory allocated since the last reset; on a CPU the process's peak resident set so far."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def reset(device: torch.device) -> None:
    """Forget compiled graphs and cached memory between settings, so each is measured on its own."""
    torch._dynamo.reset()
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def sample_shards(work: Path) -> Path:
    """The built-in sample data and its shards (8 clips a shard, so 4 workers each get several)."""
    from data_pipeline.cli import main as shards_main

    shards = work / "shards"
    workers = str(max(1, min(8, len(os.sched_getaffinity(0)) // 2)))
    assert shards_main(["sample-data", "--out", str(work / "ssv2"), "--clips", str(SAMPLE_CLIPS),
                        "--workers", workers]) == 0
    assert shards_main(["build", "--annotations", str(work / "ssv2" / "annotations"), "--videos",
                        str(work / "ssv2" / "videos"), "--out", str(shards), "--clips-per-shard", "8",
                        "--workers", workers]) == 0
    return shards


def linked_copies(shards: Path, out: Path, copies: int) -> Path:
    """A shard directory whose train split lists every train shard `copies` times (symbolic links, one
    manifest): the same clips, an epoch `copies` times as long. The validation split is linked once."""
    manifest = read_manifest(shards)
    out.mkdir(parents=True, exist_ok=True)
    for split, entry in manifest["splits"].items():
        times = copies if split == "train" else 1
        listed = []
        for copy in range(times):
            for shard in entry["shards"]:
                name = f"copy{copy:03d}-{shard['name']}"
                link = out / name
                if not link.exists():
                    link.symlink_to((shards / shard["name"]).resolve())
                listed.append({**shard, "name": name})
        entry["shards"] = listed
        entry["clips"] = entry["clips"] * times
    (out / MANIFEST_FILE).write_text(json.dumps(manifest))
    return out


def load_batches(shards: Path, batch_size: int, length: int, k_max: int, count: int, device: torch.device) -> list[dict]:
    """`count` train batches read in the main process (cycled if the split holds fewer), on `device`."""
    dataset = SequenceDataset(shard_set(shards, "train"), batch_size=batch_size, seq_len=length, k_max=k_max)
    batches = []
    while len(batches) < count:
        for batch in dataset:
            batches.append({key: value.to(device) for key, value in batch.items() if torch.is_tensor(value)})
            if len(batches) == count:
                break
    return batches


def bare_steps(settings: dict, batches: Iterator[dict], compile_setting: str, steps: int, device: torch.device,
               warm_up: int = WARM_UP) -> dict:
    """Time the bare training step (module docstring) on `batches` (on `device`) → ms, steps/s, warm-up seconds,
    peak memory, the process's CPU ms a step (cpu_ms) and, on a GPU, the device's busy ms a step over
    PROFILED_STEPS more steps (busy_ms)."""
    reset(device)
    torch.manual_seed(0)
    module = PretrainModule(**{**settings["model"], "compile": compile_setting}).to(device)
    module.step_losses = compiled(module.training_losses, compile_setting, device)
    world_model_opt, dual_opt = module.configure_optimizers()
    precision = settings["precision"]
    scaler = torch.amp.GradScaler(device.type, enabled=precision == "16-mixed")
    dtype = {"16-mixed": torch.float16, "bf16-mixed": torch.bfloat16}.get(precision)

    def step(index: int) -> None:
        batch = next(batches)
        noise = module.noise(batch["gaps"], index, stream=0)
        if compile_setting != "off":
            torch.compiler.cudagraph_mark_step_begin()
        with torch.autocast(device.type, dtype=dtype, enabled=dtype is not None, cache_enabled=False):
            terms = module.step_losses(batch["frames"], batch["gaps"], batch["num_frames"], noise)
        world_model_opt.zero_grad(set_to_none=True)
        scaler.scale(terms["loss"]).backward()
        scaler.unscale_(world_model_opt)
        skip = ~torch.isfinite(module.clip_world_model_gradients())
        if scaler.is_enabled():
            scaler.step(world_model_opt)
            scaler.update()
        else:
            step_unless(world_model_opt, skip)
        module.count_skip(skip, torch.isfinite(terms["loss"]), scaled=scaler.is_enabled())
        if module.hcu_enabled:
            module.dual_step(dual_opt, terms["k_disagreement"], skip)

    started = time.perf_counter()
    for index in range(warm_up):
        step(index)
    synchronize(device)
    warm_up_s = time.perf_counter() - started
    started, cpu_started = time.perf_counter(), time.process_time()
    for index in range(warm_up, warm_up + steps):
        step(index)
    synchronize(device)
    seconds = (time.perf_counter() - started) / steps
    cpu_ms = 1000 * (time.process_time() - cpu_started) / steps
    busy_ms = math.nan
    if device.type == "cuda":  # the device's own time a step: near ms/step, the GPU is what limits
        try:
            cuda = [torch.profiler.ProfilerActivity.CUDA]
            with torch.profiler.profile(activities=cuda, acc_events=True) as profiler:
                for index in range(warm_up + steps, warm_up + steps + PROFILED_STEPS):
                    step(index)
                synchronize(device)
            busy_ms = summarise_profile(profiler, PROFILED_STEPS)["device_busy_ms"]
        except Exception as error:  # noqa: BLE001 — a diagnostic: the timing above stands without it
            print(f"(profiling the bare step failed: {type(error).__name__}: {error})")
    return {"ms": 1000 * seconds, "steps_per_s": 1 / seconds, "warm_up_s": warm_up_s,
            "peak_gib": peak_memory_gib(device), "cpu_ms": cpu_ms, "busy_ms": busy_ms}


def fit_loader(shards: Path, data: dict, workers: int, worker_priority: str,
               pinned: bool = True) -> tuple[ShardDataModule, DataLoader]:
    """The fit's own train loader (ShardDataModule's: persistent workers, pinned memory on a GPU unless not
    `pinned`) with its DataModule."""
    datamodule = ShardDataModule(**{**data, "shards": str(shards), "num_workers": workers,
                                    "worker_priority": worker_priority, "pin_memory": None if pinned else False})
    datamodule.setup("fit")
    return datamodule, datamodule.train_dataloader()


def device_batches(datamodule: ShardDataModule, loader: DataLoader, device: torch.device) -> Iterator[dict]:
    """`loader`'s batches epoch after epoch (advanced as SetEpoch does), each tensor copied to `device` as
    Lightning copies it (non-blocking)."""
    for epoch in itertools.count():
        datamodule.train_set.set_epoch(epoch)
        for batch in loader:
            yield {key: value.to(device, non_blocking=True) for key, value in batch.items() if torch.is_tensor(value)}


def loader_alone(shards: Path, data: dict, workers: int, worker_priority: str, total: int,
                 device: torch.device) -> dict:
    """The fit's train loader with no model, each batch copied to `device`, over the `total` batches a fit of
    `total` steps reads → batches/s after the same warm-up as the fit's: the most steps/s the fit could reach with
    these workers."""
    datamodule, loader = fit_loader(shards, data, workers, worker_priority)
    times = [time.perf_counter() for _, _ in zip(range(total), device_batches(datamodule, loader, device))]
    synchronize(device)
    warm = fit_warm_up(len(loader), total)
    return {"batches_per_s": (total - warm) / (time.perf_counter() - times[warm - 1]), "per_epoch": len(loader)}


def step_anatomy(starts: list[float], ends: list[float], queued: list[int], warm: int) -> dict:
    """The timed steps (from `warm` on) by the host's clock, in ms: inside a step (batch start to end: training_step
    and its hooks) and between steps (the loop, the next batch, its copy), mean and median, and inside's median over
    the first EARLY_STEPS timed steps and the rest; the slow steps, whose interval from the last step's end is over
    twice the median, with what they add to the mean interval; on a GPU the mean number of steps it had queued at
    a step's end (StepTimer), first EARLY_STEPS and the rest. Means above medians say that a few steps (logging, a
    late batch, a pause) take the time, not every step; a later median above the early one, that steps slow down."""
    inside = [1000 * (end - start) for start, end in zip(starts[warm:], ends[warm:])]
    between = [1000 * (start - end) for start, end in zip(starts[warm:], ends[warm - 1:])]
    intervals = [1000 * (end - before) for end, before in zip(ends[warm:], ends[warm - 1:])]
    typical = statistics.median(intervals)
    slow = [interval for interval in intervals if interval > 2 * typical]

    def early_late(values: list, summary) -> tuple[float, float]:
        return tuple(summary(part) if part else math.nan for part in (values[:EARLY_STEPS], values[EARLY_STEPS:]))

    return {"inside": (statistics.fmean(inside), statistics.median(inside)),
            "inside_early_late": early_late(inside, statistics.median),
            "between": (statistics.fmean(between), statistics.median(between)),
            "slow_steps": len(slow), "slow_ms": sum(interval - typical for interval in slow) / len(intervals),
            "queued": early_late(queued[warm:], statistics.fmean)}


def whole_epochs(steps: int, per_epoch: int) -> int:
    """At least `steps` steps, rounded up to whole epochs."""
    return math.ceil(steps / per_epoch) * per_epoch


def fit_warm_up(per_epoch: int, total: int) -> int:
    """The steps of a `total`-step fit (or loader run) left out of its timing: FIT_WARM_UP (at most half of them)
    within one long epoch, whole epochs for short epochs."""
    return min(FIT_WARM_UP, total // 2) if per_epoch >= total else whole_epochs(FIT_WARM_UP, per_epoch)


def real_fit(config: Path, shards: Path, workers: int, worker_priority: str, max_steps: int, precision: str,
             log_every: int, root: Path, device: torch.device, diagnose: bool = False, pinned: bool = True) -> dict:
    """`hauwm pretrain fit` (model.cli's LightningCLI) on one device → steps/s after the warm-up and more; with
    `diagnose`, StepDiagnosis's findings too (its windows slow the fit: its steps/s is not a figure); `pinned`
    False: --data.pin_memory false."""
    reset(device)
    args = ["fit", "--config", str(config), "--data.shards", str(shards), "--data.num_workers", str(workers),
            "--data.worker_priority", worker_priority,
            "--trainer.precision", precision, "--trainer.max_steps", str(max_steps), "--trainer.devices", "1",
            "--trainer.log_every_n_steps", str(log_every),
            "--trainer.strategy", "auto", "--trainer.limit_val_batches", "0", "--trainer.enable_progress_bar",
            "false", "--trainer.enable_model_summary", "false", "--trainer.default_root_dir", str(root),
            "--trainer.callbacks+=bench_gpu.StepTimer"] + ([] if pinned else ["--data.pin_memory", "false"])
    if diagnose:
        args.append("--trainer.callbacks+=bench_gpu.StepDiagnosis")
    cli = lightning_cli(args)
    # the callbacks are instances of the module `bench_gpu` that LightningCLI imported, not of this `__main__`
    by_name = {type(callback).__name__: callback for callback in cli.trainer.callbacks}
    timer = by_name["StepTimer"]
    per_epoch = cli.trainer.num_training_batches
    warm = fit_warm_up(per_epoch, max_steps)
    times, cpu_times = timer.times, timer.cpu_times
    return {"steps_per_s": (len(times) - warm) / (times[-1] - times[warm - 1]), "steps_per_epoch": per_epoch,
            "cpu_ms": 1000 * (cpu_times[-1] - cpu_times[warm - 1]) / (len(times) - warm),
            "timed_steps": len(times) - warm, "first_step_s": times[0] - timer.start,
            "anatomy": step_anatomy(timer.starts, times, timer.queued, warm),
            "scaler_skips": int(cli.model.scaler_skips), "nonfinite_steps": int(cli.model.nonfinite_steps),
            "peak_gib": peak_memory_gib(device), "diagnosis": by_name.get("StepDiagnosis")}


def print_diagnosis(diagnosis: StepDiagnosis, reference: dict | None, device: torch.device) -> None:
    """StepDiagnosis's findings, with the bare step's ms for scale (the compiled step on a GPU, eager on a CPU)."""
    print(f"\nwhere a fit step's time goes (long epochs; steps {FIT_WARM_UP}–{FIT_WARM_UP + diagnosis.SYNC_STEPS - 1}"
          f" timed by the host, then {diagnosis.PROFILE_STEPS} profiled; bare step "
          + (f"{reference['ms']:.1f} ms)" if reference else "not timed)"))
    if not (diagnosis.inside and diagnosis.between):
        print(f"  not measured: the fit ended before step {FIT_WARM_UP + 2}")
        return
    print(f"  host, inside the step (training_step + hooks): median {1000 * statistics.median(diagnosis.inside):.2f} ms;"
          f" between steps (loop, next batch, copy): median {1000 * statistics.median(diagnosis.between):.2f} ms")
    if device.type == "cuda":
        total = sum(diagnosis.sync_sites.values())
        print(f"  host waits for the GPU (sync debug mode): {total} in {diagnosis.SYNC_STEPS} steps"
              + ("" if total else " — none: the host can queue steps ahead"))
        for site, count in diagnosis.sync_sites.most_common(8):
            print(f"    {count:>4}  {site}")
    profile = diagnosis.profile
    if profile is None:
        print("  profile: not taken (the fit ended before its window was over)")
        return
    if device.type == "cuda":
        waits = ", ".join(f"{name} {ms:.2f}" for name, ms in profile["waits"].items()) or "none"
        print(f"  profiled, per step: device busy {profile['device_busy_ms']:.2f} ms; waiting CUDA calls (ms): {waits}")
    print("  host operators by own time, per step: " + "; ".join(
        f"{name} {ms:.2f} ms ×{count:.0f}" for name, ms, count in profile["host_top"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", choices=["cuda", "cpu"], default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--shards", type=Path, default=None, help=f"default: build {SAMPLE_CLIPS} sample clips")
    parser.add_argument("--lengths", type=int, nargs="+", default=None, help="bare-step L (GPU: 16 50; CPU: 12)")
    parser.add_argument("--steps", type=int, default=None, help="timed bare steps (GPU: 40; CPU: 16)")
    parser.add_argument("--fit-steps", type=int, default=None, help="fit steps, long epochs (GPU: 500; CPU: 80)")
    parser.add_argument("--workers", type=int, default=None, help="fit DataLoader workers (GPU: 4; CPU: 2)")
    parser.add_argument("--worker-priority", choices=WORKER_PRIORITIES, default=None,
                        help="fit workers' scheduling (default: the config's, normal in every shipped config)")
    parser.add_argument("--precision", default=None, help="default: the config's (16-mixed on GPU, 32-true on CPU)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--log-every", type=int, default=None, help="fit's log_every_n_steps (default: the config's)")
    parser.add_argument("--rounds", type=int, default=None, help="times the fits run (GPU: 1; CPU: 3, each bracketed)")
    args = parser.parse_args()
    if args.shards:  # a wrong --shards fails now, not minutes later
        try:
            read_manifest(args.shards)
        except ShardDirError as err:
            parser.error(f"--shards: {err}")
    for name in ("lightning.pytorch", "lightning.fabric"):  # not each fit's banner ("GPU available", tips, seed)
        logging.getLogger(name).setLevel(logging.WARNING)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    gpu = device.type == "cuda"
    config = CONFIGS / ("ssv2.yaml" if gpu else "tiny.yaml")
    loaded = yaml.safe_load(config.read_text())
    model = {**loaded["model"], "k_max": loaded["data"]["k_max"]}
    model["world_model"] = WorldModelConfig(**model["world_model"])  # the sizes the config leaves out: defaults
    settings = {"model": model,
                "precision": args.precision or loaded["trainer"]["precision"]}
    batch_size, k_max = loaded["data"]["batch_size"], loaded["data"]["k_max"]
    lengths = args.lengths or ([16, 50] if gpu else [12])
    steps = args.steps or (40 if gpu else 16)
    fit_steps = args.fit_steps or (500 if gpu else 80)
    workers = args.workers if args.workers is not None else (4 if gpu else 2)
    compile_setting = "reduce-overhead" if gpu else "default"
    rounds = args.rounds or (1 if gpu else 3)
    log_every = args.log_every or loaded["trainer"]["log_every_n_steps"]
    worker_priority = args.worker_priority or loaded["data"].get("worker_priority", "normal")
    fit_length = loaded["data"]["seq_len"]

    print(f"machine: {describe_machine(str(device))}")
    sizes = model["world_model"]
    print(f"settings: {config.relative_to(ROOT)} (M {sizes.ensemble}, deter {sizes.deter}, stoch {sizes.stoch}, "
          f"batch {batch_size}, K_max {k_max}), "
          f"{settings['precision']}, compiled = model.compile {compile_setting}; bare: L {lengths}, "
          f"{WARM_UP} warm-up + {steps} timed steps; fit: L {fit_length}, model.compile "
          f"{loaded['model'].get('compile', 'off')}, {workers} workers ({worker_priority} priority), "
          f"log every {log_every} steps; "
          f"{torch.get_num_threads()} torch threads; lightning {L.__version__}", flush=True)
    work = Path(tempfile.mkdtemp(prefix="bench-gpu-"))  # sample shards and the fits' checkpoints
    atexit.register(shutil.rmtree, work, ignore_errors=True)
    started = time.perf_counter()
    shards = args.shards or sample_shards(work)
    print(f"shards: {shards} ({time.perf_counter() - started:.0f} s)", flush=True)

    print(f"\n{'bare step':<24} {'L':>3} {'ms/step':>8} {'steps/s':>8} {'warm-up s':>10} {'peak GiB':>9} "
          f"{'host ms':>8} {'GPU busy ms':>11}  (host ms: the process's CPU time a step, all threads; GPU busy: "
          "its kernels' time a step, profiled)")
    bare = {}
    for length in lengths:
        batches = load_batches(shards, batch_size, length, k_max, 4, device)
        for mode in ("off", compile_setting):
            result = bare[length, mode] = bare_steps(settings, itertools.cycle(batches), mode, steps, device)
            label = "eager" if mode == "off" else f"compiled ({mode})"
            print(f"{label:<24} {length:>3} {result['ms']:8.1f} {result['steps_per_s']:8.1f} "
                  f"{result['warm_up_s']:10.1f} {result['peak_gib']:9.2f} {result['cpu_ms']:8.1f} "
                  f"{result['busy_ms']:11.2f}", flush=True)

    long_epochs = linked_copies(shards, work / "long-epochs", LONG_EPOCH_COPIES)
    per_epoch = len(SequenceDataset(shard_set(shards, "train"), batch_size=batch_size, seq_len=fit_length,
                                    k_max=k_max, num_workers=workers))  # short epochs: warm-up + about half as many
    short_steps = whole_epochs(FIT_WARM_UP, per_epoch) + whole_epochs(fit_steps // 2, per_epoch)  # timed steps
    runs = [("(a) long epochs", long_epochs, workers, fit_steps, True)]  # (label, shards, workers, steps, pinned)
    if not gpu:
        runs.append(("(a) long epochs", long_epochs, 0, fit_steps, True))
    runs.append(("(b) short epochs", shards, workers, short_steps, True))
    config_workers = loaded["data"]["num_workers"]
    if gpu and config_workers != workers:  # what a user's fit gets (ssv2.yaml: 8)
        runs.append(("(a) long epochs", long_epochs, config_workers, fit_steps, True))
    if gpu:  # batches copied from ordinary memory (--data.pin_memory false): one bench showed the fed step faster
        runs.append(("(a) long, unpinned", long_epochs, workers, min(fit_steps, VARIANT_STEPS), False))

    reference_mode = compile_setting if gpu else "off"
    reference = bare.get((fit_length, reference_mode))
    print(f"\n{'loader alone':<18} {'workers':>7} {'batches/epoch':>13} {'batches/s':>10} {'× bare':>9}"
          "  (the fit's train loader, no model, batches copied to the device)")
    for label, directory, fit_workers, max_steps, pinned in runs:
        if fit_workers == 0 or not pinned:  # the loader alone copies as the pinned fit does
            continue
        result = loader_alone(directory, loaded["data"], fit_workers, worker_priority, max_steps, device)
        ratio = f" {result['batches_per_s'] / reference['steps_per_s']:8.2f}×" if reference is not None else ""
        print(f"{label:<18} {fit_workers:>7} {result['per_epoch']:>13} {result['batches_per_s']:10.1f}{ratio}",
              flush=True)
    if reference is not None:
        print(f"\n{'bare step fed by the loader':<28} {'workers':>7} {'pinned':>6} {'steps/s':>8} {'host ms':>8} "
              f"{'× bare':>8}  (the bare {'compiled' if gpu else 'eager'} step, its batches from the fit's train "
              "loader on long epochs: what the loader costs the step without Lightning)")
        for pinned in (True, False) if gpu else (False,):  # pinning needs a GPU
            feed = device_batches(*fit_loader(long_epochs, loaded["data"], workers, worker_priority, pinned), device)
            result = bare_steps(settings, feed, reference_mode, min(fit_steps, FED_STEPS), device, warm_up=FIT_WARM_UP)
            print(f"{'(a) long epochs':<28} {workers:>7} {'yes' if pinned else 'no':>6} {result['steps_per_s']:8.1f} "
                  f"{result['cpu_ms']:8.1f} {result['steps_per_s'] / reference['steps_per_s']:7.2f}×", flush=True)
            feed.close()  # its workers end here, not at some later collection
    print(f"\n{'real fit':<18} {'workers':>7} {'steps/epoch':>11} {'timed steps':>11} {'steps/s':>8} "
          f"{'1st step s':>10} {'scaler skips':>12} {'non-finite':>10} {'peak GiB':>9} {'host ms':>8}"
          f" {'× bare':>9}" + ("" if gpu else f" {'bare ms':>8}  (the bare loop re-timed after each fit)"))
    if reference is not None and not gpu:  # timed again just before the first fit, as after every fit
        fit_batches = load_batches(shards, batch_size, fit_length, k_max, 4, device)
        reference = bare_steps(settings, itertools.cycle(fit_batches), "off", steps, device)
    ratios: dict[tuple[str, int], list[float]] = {}  # (run, workers) → each round's fit / bare steps/s
    anatomies = []  # (run, workers, step_anatomy) of every fit
    for round_index in range(rounds):
        for index, (label, directory, fit_workers, max_steps, pinned) in enumerate(runs):
            result = real_fit(config, directory, fit_workers, worker_priority, max_steps, settings["precision"],
                              log_every, work / f"fit-{round_index}-{index}", device, pinned=pinned)
            ratio_text = ""
            if reference is not None:
                after = reference if gpu else bare_steps(settings, itertools.cycle(fit_batches), "off", steps,
                                                         device)  # bracket on a CPU
                ratio = result["steps_per_s"] / ((reference["steps_per_s"] + after["steps_per_s"]) / 2)
                ratios.setdefault((label, fit_workers), []).append(ratio)
                ratio_text = f" {ratio:8.2f}×" + ("" if gpu else f" {after['ms']:8.1f}")
                reference = after
            print(f"{label:<18} {fit_workers:>7} {result['steps_per_epoch']:>11} {result['timed_steps']:>11} "
                  f"{result['steps_per_s']:8.2f} {result['first_step_s']:10.1f} {result['scaler_skips']:>12} "
                  f"{result['nonfinite_steps']:>10} {result['peak_gib']:9.2f} {result['cpu_ms']:8.1f}{ratio_text}",
                  flush=True)
            anatomies.append((label, fit_workers, result["anatomy"]))

    kind = "bare compiled step (aim ≥ 0.8×)" if gpu else "bare eager step loop on the same batches (aim ≥ 0.9×)"
    for (label, fit_workers), values in ratios.items():
        shown = ", ".join(f"{ratio:.2f}" for ratio in values)
        print(f"{label}, {fit_workers} workers: {statistics.median(values):.2f}× the {kind}"
              + (f" (median of {shown})" if len(values) > 1 else ""))
    print(f"\n{'the fits by the host':<18} {'workers':>7} {'inside ms':>13} {'early / late':>13} {'between ms':>13} "
          f"{'slow steps':>10} {'+ms a step':>10} {'GPU queue':>11}  (every timed step: inside and between steps, mean "
          f"/ median; inside's median over the first {EARLY_STEPS} timed steps / the rest; slow: over twice the median "
          f"interval, and what they add to the mean; GPU queue: mean steps queued at a step's end, first {EARLY_STEPS} "
          "timed steps / the rest)")
    for label, fit_workers, anatomy in anatomies:
        inside, early_late, between, queued = (" / ".join("—" if math.isnan(value) else f"{value:.2f}" for value in pair)
                                               for pair in (anatomy["inside"], anatomy["inside_early_late"],
                                                            anatomy["between"], anatomy["queued"]))
        print(f"{label:<18} {fit_workers:>7} {inside:>13} {early_late:>13} {between:>13} {anatomy['slow_steps']:>10} "
              f"{anatomy['slow_ms']:10.2f} {queued if gpu else '—':>11}")
    try:  # last: a profiler failure must not cost the figures above
        diagnosis = real_fit(config, long_epochs, config_workers if gpu else workers, worker_priority,
                             FIT_WARM_UP + StepDiagnosis.SYNC_STEPS + StepDiagnosis.PROFILE_STEPS + 2,
                             settings["precision"], log_every, work / "fit-diagnosis", device, diagnose=True)
        print_diagnosis(diagnosis["diagnosis"], reference, device)
    except Exception as error:  # noqa: BLE001 — a diagnostic, reported, never fatal
        print(f"\nwhere a fit step's time goes: failed ({type(error).__name__}: {error})")

    print(f"\ncompiling, the whole bench: {counters['stats']['unique_graphs']} graphs compiled (each compiled step "
          f"compiles its own), {counters['inductor']['cudagraph_skips']} CUDA-graph skips (a compiled graph run "
          "without its CUDA graph under reduce-overhead: more than 0 is a finding)")
    print(f"wall time {time.perf_counter() - started:.0f} s; load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
