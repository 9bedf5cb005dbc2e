"""How a batch crosses from a DataLoader worker to the training process: one block of bytes, in a shared slot.

A batch (docs/architecture.md §2) is one uint8 block: the frames, then the four int64 fields, 8-byte aligned;
`batch_views` gives its tensors as views of the block. Handed over the way torch does it, each block is a new
shared-memory region whose file descriptor the receiving thread fetches from the worker over a socket, with a
handshake in Python, while the training step waits for the GIL (bench/README.md: about 1.4 ms a batch).

`BatchSlots` skips that: the training process allocates, before the workers start, a few slots of shared
memory per worker (one more than the batches torch lets a worker have in flight), and a worker writes its batch
into its next slot and sends a `SlotBatch` — where the batch lies and its shape, a few bytes. The training
process copies the block out (into pinned memory when batches go to a GPU: the copy torch's pinning makes
anyway) and frees the slot. Each slot has a semaphore: a worker waits for its slot to be freed, and if it is not
within `SLOT_WAIT` seconds (a batch the training process dropped unread, which frees its slot when collected)
the batch goes the ordinary way. No process outside the training job is involved (unlike torch's
`file_system` sharing strategy and its `torch_shm_manager`), and the slots vanish with the processes.
"""

from __future__ import annotations

import contextlib
import os
import uuid
import weakref
from multiprocessing.context import BaseContext

import torch

SLOT_WAIT = 1.0  # seconds a worker waits for its slot before sending the batch the ordinary way
SHARED_MEMORY = "/dev/shm"
_ALL_SLOTS: weakref.WeakValueDictionary[str, BatchSlots] = weakref.WeakValueDictionary()  # in the training process


def block_bytes(batch: int, length: int, height: int, width: int) -> tuple[int, int]:
    """(where the int64 fields start, the block's size in bytes) of a batch of this shape."""
    start = -(-batch * length * 3 * height * width // 8) * 8  # 8-byte aligned after the frames
    return start, start + 8 * (2 * batch * length + 2 * batch)


def batch_views(block: torch.Tensor, batch: int, length: int, height: int, width: int) -> dict[str, torch.Tensor]:
    """The tensors of a batch of this shape as views of `block` (uint8, at least block_bytes long)."""
    start, end = block_bytes(batch, length, height, width)
    fields = block[start:end].view(torch.int64).split([batch * length, batch * length, batch, batch])
    return {
        "frames": block[:batch * length * 3 * height * width].view(batch, length, 3, height, width),  # uint8
        "gaps": fields[0].view(batch, length),  # gaps[:, 0] == 0
        "indices": fields[1].view(batch, length),
        "num_frames": fields[2],
        "label": fields[3],
    }


class BatchSlots:
    """`per_worker` shared-memory slots of `slot_bytes` for each of `workers` DataLoader workers, and a semaphore
    for each (1: free), of the multiprocessing `context` that starts the workers (fork, forkserver, spawn). Made
    in the training process before its workers start; they inherit it."""

    def __init__(self, workers: int, per_worker: int, slot_bytes: int, context: BaseContext):
        self.buffer = torch.empty(workers, per_worker, slot_bytes, dtype=torch.uint8).share_memory_()
        self.semaphores = [[context.Semaphore(1) for _ in range(per_worker)] for _ in range(workers)]
        self.key = uuid.uuid4().hex
        self._placed = 0  # batches this process (a worker) has placed in its slots
        _ALL_SLOTS[self.key] = self

    def place(self, worker: int) -> tuple[int, torch.Tensor] | None:
        """A worker's next slot, (its index, its bytes) once free; None if it stays taken for SLOT_WAIT seconds (the
        next batch tries the slot after it)."""
        slot = self._placed % len(self.semaphores[worker])
        self._placed += 1
        if not self.semaphores[worker][slot].acquire(timeout=SLOT_WAIT):
            return None
        return slot, self.buffer[worker, slot]

    def vacate(self, worker: int, slot: int) -> None:
        self.semaphores[worker][slot].release()


def shared_memory_free() -> int | None:
    """Bytes free in the shared memory that slots (and torch's own hand-over) take, None where there is none."""
    if not os.path.isdir(SHARED_MEMORY):
        return None
    stats = os.statvfs(SHARED_MEMORY)
    return stats.f_bavail * stats.f_frsize


class SlotBatch:
    """A batch that a worker wrote into slot `slot` of its `BatchSlots`, as it travels to the training process.
    There, `take()` (or `pin_memory()`, which torch's pinning thread calls) copies it out and frees the slot; one
    dropped unread frees its slot when it is collected."""

    def __init__(self, key: str, worker: int, slot: int, shape: tuple[int, int, int, int], ids: list[str]):
        self.key, self.worker, self.slot, self.shape, self.ids = key, worker, slot, shape, ids
        self._holds_slot = False  # the worker's object does not: the received one does (__setstate__)

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._holds_slot = True

    def take(self, pin: bool = False) -> dict:
        """The batch (its tensors views of one copy of the block, pinned if `pin`); the slot is freed."""
        slots = _ALL_SLOTS[self.key]
        _, size = block_bytes(*self.shape)
        block = slots.buffer[self.worker, self.slot, :size]
        # unpinned: one memcpy on this thread, not torch's clone, which at this size runs on every intra-op thread and
        # leaves them spinning (6× the copy's CPU time at 2 threads; 174.7 ms of CPU a step at 16 on a GPU host)
        copy = block.pin_memory() if pin else torch.from_numpy(block.numpy().copy())
        self.release()
        return {**batch_views(copy, *self.shape), "id": self.ids}

    def pin_memory(self) -> dict:
        return self.take(pin=True)

    def release(self) -> None:
        if self._holds_slot:
            self._holds_slot = False
            if (slots := _ALL_SLOTS.get(self.key)) is not None:
                slots.vacate(self.worker, self.slot)

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # at interpreter exit the semaphores may be gone already
            self.release()
