"""The DataLoader that runs a `SequenceDataset` (dataset.py) in worker processes: workers that start once, a
resume inside an epoch, and worker failures named.

Workers start once and live for the whole fit (`persistent_workers`). The DataLoader calls the dataset's
`__iter__` in each worker when the worker starts and again at each `iter(loader)` (torch sends the workers
`_ResumeIteration` after the main process wrote the data position), so each epoch's iterator sees what a worker
started for that epoch would. For the continuous training set, `ResumableDataLoader` keeps torch's iterator over
the epochs and re-creates it only where the position is not the one its stream has reached (the first epoch, a
resume), so there is no pause at an epoch's start (docs/data_pipeline.md). Lightning stores the position in every
checkpoint through `state_dict()` and gives it back through `load_state_dict()`.

A failing worker becomes a `LoaderError` naming the worker, the shard it was reading and the likely cause. An
exception inside a worker is handed over as the worker's last item and raised here; a worker that dies (SIGKILL:
the out-of-memory killer; SIGBUS: /dev/shm full; a native crash) or stalls past `timeout` is reported where torch
notices it, while the main process waits for a batch. Batches cross from the workers in shared-memory slots
(batch_slots.py).
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import re
import signal
import threading
import warnings
from collections.abc import Callable, Iterator
from functools import partial

import torch
from torch.utils.data import DataLoader

from hauwm.messages import killed_by

from .batch_slots import BatchSlots, SlotBatch
from .dataset import VERIFY_HINT, LoaderError, SequenceDataset, WorkerItem

RESUME_HINT = "the checkpoints written so far are intact: resume with `--ckpt_path RUN/checkpoints/last.ckpt`"
# how torch's DataLoader iterator reports a worker that died or a batch that did not come in time
TORCH_WORKER_FAILURES = ("DataLoader worker", "DataLoader timed out")
DEATH_CAUSES = {
    signal.SIGKILL: "killed by SIGKILL, most likely by the kernel's out-of-memory killer (`dmesg` says so): "
                    "lower --data.num_workers, --data.shuffle_buffer or --data.batch_size, or give it more memory",
    signal.SIGBUS: "killed by SIGBUS: the shared memory that carries batches from the workers (/dev/shm) is full: "
                   "in Docker run with --shm-size 8g (or --ipc=host), or lower --data.num_workers or --data.batch_size",
    signal.SIGSEGV: "crashed in native code (SIGSEGV; a frame decoder or another library): re-run with "
                    f"--data.num_workers 0 to see where, and {VERIFY_HINT}",
}


WORKER_PRIORITIES = ("normal", "idle")


def check_worker_priority(priority: str) -> None:
    """`normal`: workers compete for cores with the training step. `idle`: workers run under Linux's `SCHED_IDLE`,
    only on cores the training process leaves free — on a CPU-only run with few cores the step keeps its threads
    (bench/README.md, "Pre-training speed on a GPU"); on a node fully loaded by other jobs such workers may starve."""
    if priority not in WORKER_PRIORITIES:
        raise LoaderError(f"--data.worker_priority must be one of {', '.join(WORKER_PRIORITIES)}, got {priority!r}")
    if priority == "idle" and not hasattr(os, "SCHED_IDLE"):
        raise LoaderError("--data.worker_priority idle needs Linux's SCHED_IDLE, which this system lacks: "
                          "use --data.worker_priority normal")


def init_worker(priority: str, training_process: int, _: int) -> None:
    import cv2

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the training process's to handle; it stops the workers
    _end_only_with(training_process)
    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    if priority == "idle":
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def _end_only_with(training_process: int) -> None:
    """Let a worker end on SIGTERM only from the training process (pid `training_process`; torch's shutdown of its
    workers, multiprocessing's at exit), and ignore one from anyone else.

    SLURM (`scancel`, a time limit) and `kill -TERM -PGID` signal every process of a job, the workers too; one that
    died of it before the training process stopped (after its step: model/sigterm.py) broke the validation under
    way, and the fit ended with exit status 2 and no checkpoint of that step. torch's own handler ends a worker on any
    SIGTERM, by exiting at once for its parent's. Here SIGTERM is blocked in the worker and a thread waits for it
    (`sigwaitinfo`, which names the sender); for the training process's (or the parent's, where that is a fork
    server) the worker exits as torch's handler would, with status 0, which torch does not report as a death. A worker
    still ends with the training process: by its SIGTERM, its end of the epoch, or torch's watchdog once it is gone.
    Processes that a worker starts (a `pipe:` shard URL's command) inherit the blocked signal and end on the broken
    pipe when the worker does."""
    senders = {training_process, os.getppid()}
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})

    def wait() -> None:
        while signal.sigwaitinfo({signal.SIGTERM}).si_pid not in senders:
            pass
        os._exit(0)

    threading.Thread(target=wait, name="sigterm", daemon=True).start()


_FETCHING = threading.Event()  # set while the main thread waits for a batch of a ResumableDataLoader


def _defer_worker_deaths() -> None:
    """torch's SIGCHLD handler raises "DataLoader worker (pid N) is killed by signal" wherever the main thread
    is when a worker dies: inside the training step, a checkpoint save, compiled code. Wrap it (once) so that it
    raises only while the main thread waits for a batch, where `ResumableDataLoader` turns it into a
    `LoaderError`; a death at any other moment is found by the loader's check of its workers before each batch."""
    handler = signal.getsignal(signal.SIGCHLD)
    if not callable(handler) or getattr(handler, "defers_worker_deaths", False) \
            or threading.current_thread() is not threading.main_thread():
        return

    def deferring(signum, frame) -> None:
        try:
            handler(signum, frame)
        except RuntimeError as error:
            if _FETCHING.is_set() or not str(error).startswith(TORCH_WORKER_FAILURES):
                raise

    deferring.defers_worker_deaths = True
    signal.signal(signal.SIGCHLD, deferring)


class ResumableDataLoader(DataLoader):
    """A DataLoader that Lightning resumes inside an epoch and whose worker failures name the worker, the shard
    and the likely cause. Lightning stores `state_dict()` in every checkpoint and, on resume, calls
    `load_state_dict()` right before it creates the resumed epoch's iterator (before any epoch hook could set
    the epoch). `batches_done` reports how many batches of the current epoch the training loop has consumed
    (the data module points it at the Trainer's progress)."""

    batches_done: Callable[[], int] = staticmethod(lambda: 0)
    epoch_ended: Callable[[], bool] = staticmethod(lambda: False)  # the epoch's last batch is done (a limit too)
    worker_priority: str = "normal"  # set by `make_dataloader`, for the stalled-worker message
    slots: BatchSlots | None = None  # where this loader's workers place their batches (`make_dataloader`)
    _stream: Iterator[WorkerItem] | None = None  # torch's iterator of a continuous dataset, over the epochs
    _stream_at: tuple[int, int] = (-1, 0)  # the (epoch, batches of it) `_stream` gives next

    def state_dict(self) -> dict:
        return {"epoch": self.dataset.epoch, "batches": int(self.batches_done()), "epoch_ended": bool(self.epoch_ended()),
                "streams": self.dataset.streams, "content_id": self.dataset.content_id}

    def load_state_dict(self, state: dict) -> None:
        epoch, batches = state["epoch"], state["batches"]
        if state.get("streams", self.dataset.streams) != self.dataset.streams:
            warnings.warn(f"the checkpoint's {self.dataset.split} loader ran {state['streams']} streams (ranks × "
                          f"DataLoader workers), this run {self.dataset.streams}: the rest of epoch {epoch} is not "
                          "what an unbroken run would have read (clips may repeat or be left out in it), later epochs "
                          "are; resume with the same --data.num_workers and devices for an exact resume", stacklevel=2)
        if state.get("content_id", self.dataset.content_id) != self.dataset.content_id:
            warnings.warn(f"the checkpoint's {self.dataset.split} loader read other shards than this run's --data.shards "
                          f"(their sha256s differ): the rest of epoch {epoch} skips the {batches} batches a rank had "
                          "read of those in this run's order of these, so it is what neither run alone would read; "
                          "later epochs read these as a new run would. A resume from the same shards (moved or "
                          "copied elsewhere) is exact", stacklevel=2)
        # saved after an epoch's last batch (all of them, or the last that limit_train_batches lets through), or
        # past the end of this run's shorter epochs (SetEpoch.on_load_checkpoint marks Lightning's epoch ended then):
        # Lightning goes on with the next epoch, from this iterator and without the epoch-start hooks (so without
        # SetEpoch)
        if state.get("epoch_ended", False) or self.epoch_ended() or batches >= len(self):
            epoch, batches = epoch + 1, 0
        self.dataset.resume_at(epoch, batches)

    def __iter__(self) -> Iterator[dict]:
        """One epoch of batches. For a continuous dataset, from the stream the workers keep going into the next
        epoch (no pause at an epoch's start); a new stream only where the dataset's position is not the one the
        stream has reached: the first epoch, a resume, a `set_epoch` out of turn. (Only torch's iterator is kept
        here: a generator of this loader's methods, kept by the loader, would be a reference cycle that a later
        fork could collect in a worker.)"""
        if not self.dataset.continuous:
            return self._raising_worker_errors(self._started())
        at = (self.dataset.epoch, self.dataset.skip_batches)
        if self._stream is None or at != self._stream_at:
            # torch counts an iterator's batches against len(loader) and warns past it: this one gives len batches
            # per epoch, epoch after epoch, by design
            warnings.filterwarnings("ignore", message="Length of IterableDataset <" + re.escape(
                f"{SequenceDataset.__module__}.{SequenceDataset.__name__}"))
            self._stream, self._stream_at = self._started(), at
        return self._rest_of_epoch()

    def _started(self) -> Iterator[WorkerItem]:
        """torch's iterator, from workers told the dataset's position (started the first time, resumed after)."""
        self.dataset.begin_stream()
        batches = self._fetch(super().__iter__)
        if self.num_workers > 0:
            _defer_worker_deaths()
        return batches

    def _next_batch(self, batches: Iterator[WorkerItem]) -> dict | None:
        """The next batch, None at the end (a worker's slot copied out and freed, where pinning did not already);
        an error inside a worker, handed over as its last item, raised."""
        batch = self._fetch(lambda: next(batches, None))
        if isinstance(batch, LoaderError):
            raise batch
        return batch.take() if isinstance(batch, SlotBatch) else batch

    def _raising_worker_errors(self, batches: Iterator[WorkerItem]) -> Iterator[dict]:
        while (batch := self._next_batch(batches)) is not None:
            yield batch

    def _rest_of_epoch(self) -> Iterator[dict]:
        """The stream's batches up to the end of the epoch it is in; a failure ends the stream."""
        epoch, done = self._stream_at
        while done < len(self):
            try:
                batch = self._next_batch(self._stream)
                if batch is None:
                    raise LoaderError(f"the loader's stream ended in epoch {epoch} after {done} of {len(self)} batches")
            except BaseException:
                self._stream = None
                raise
            done += 1
            self._stream_at = (epoch, done) if done < len(self) else (epoch + 1, 0)
            yield batch

    def _fetch(self, wait: Callable):
        """`wait()`, with a worker that died before or during it, or a batch that did not come in time, raised as
        a `LoaderError` naming each dead worker, the shard it was reading and the likely cause."""
        _FETCHING.set()  # first: a death from here on interrupts, one before is seen by the check
        try:
            if report := self._dead_workers_report():
                raise LoaderError(report)
            return wait()
        except (RuntimeError, OSError, EOFError) as error:
            failure = error
        finally:
            _FETCHING.clear()
        report = self._failure_report(failure)
        if report is None:
            raise failure
        raise LoaderError(report) from failure

    def _worker_processes(self) -> list:
        """The worker processes of the iterator torch keeps for persistent workers (none before the first
        `iter()` and after a shutdown), in worker order."""
        iterator = self._iterator
        return [] if iterator is None or iterator._shutdown else iterator._workers

    def _dead_workers_report(self) -> str | None:
        dead = [(worker, process) for worker, process in enumerate(self._worker_processes())
                if not process.is_alive()]
        if not dead:
            return None
        return "; ".join(f"DataLoader worker {worker} ({self.dataset.split} split, pid {process.pid}) died while reading shard "
                         f"{self.dataset.reading(worker)}: {_death_cause(process.exitcode)}"
                         for worker, process in dead) + f"; {RESUME_HINT}"

    def _failure_report(self, error: Exception) -> str | None:
        """What to tell about `error`; None when no worker failure explains it. Besides torch's RuntimeErrors, a
        worker killed while a batch of it waited in the queue makes receiving that batch fail with a broken
        connection (the batch's shared memory goes with it), possibly before its death is visible: wait for it."""
        torch_reports = isinstance(error, RuntimeError) and str(error).startswith(TORCH_WORKER_FAILURES)
        if isinstance(error, RuntimeError) and not torch_reports:
            return None
        timed_out = str(error).startswith("DataLoader timed out")
        if (processes := self._worker_processes()) and not timed_out:
            ended = multiprocessing.connection.wait([process.sentinel for process in processes], timeout=5.0)
            for process in processes:  # a dying process closes its files (the sentinel) before it becomes a
                if process.sentinel in ended:  # zombie that is_alive() sees: wait for that (a blocking waitpid)
                    process.join()
        if (report := self._dead_workers_report()) or not torch_reports:
            return report
        reading = ", ".join(f"worker {worker} reading shard {self.dataset.reading(worker)}"
                            for worker in range(self.num_workers))
        if timed_out:
            starved = (" or, with --data.worker_priority idle, other processes that keep every core busy"
                       if self.worker_priority == "idle" else "")
            return (f"no batch came from the DataLoader workers for {self.timeout:.0f} s ({reading}): a `pipe:` "
                    f"command or a file system that stalls{starved}; raise --data.timeout if fetching a shard takes "
                    f"longer; {RESUME_HINT}")
        return f"{error} ({reading}); {RESUME_HINT}"


def _death_cause(exitcode: int | None) -> str:
    if exitcode is None or exitcode >= 0:
        return f"it exited (status {exitcode}) with batches still to give: re-run with --data.num_workers 0 to see why"
    return killed_by(-exitcode, DEATH_CAUSES)


PREFETCH = 2  # batches each worker has in flight (torch's default prefetch_factor)


def make_dataloader(dataset: SequenceDataset, timeout: float = 600.0, worker_priority: str = "normal",
                    pin_memory: bool | None = None) -> ResumableDataLoader:
    """Batches come collated from the dataset, so `batch_size=None`. With workers, they start once and stay for
    the whole run (`persistent_workers`; each epoch's iterator reads the position from shared memory), a
    worker that gives no batch for `timeout` seconds is reported as stalled, `worker_priority` is their
    scheduling class (`check_worker_priority`), and each places its batches in PREFETCH + 1 shared-memory slots
    (batch_slots.py: one more than it has in flight, so the next is free by the time it is asked for). Batches
    are pinned for the copy to a GPU where `pin_memory` says so (None: where CUDA is available), by torch's pinning
    thread (on the training thread they were far slower: bench/README.md, the 7th GPU session)."""
    check_worker_priority(worker_priority)
    workers = dataset.num_workers > 0
    loader = ResumableDataLoader(dataset, batch_size=None, num_workers=dataset.num_workers,
                                 worker_init_fn=partial(init_worker, worker_priority, os.getpid()),
                                 persistent_workers=workers, timeout=timeout if workers else 0,
                                 pin_memory=torch.cuda.is_available() if pin_memory is None else pin_memory,
                                 prefetch_factor=PREFETCH if workers else None)
    loader.worker_priority = worker_priority
    if workers:  # the context torch starts the workers with (its default: the platform's)
        loader.slots = dataset.share_slots(PREFETCH + 1, loader.multiprocessing_context or multiprocessing.get_context())
    return loader
