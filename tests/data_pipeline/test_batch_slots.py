"""Batches handed over in shared-memory slots (data_pipeline/batch_slots.py): the same batches as torch's own
hand-over, a slot freed when its batch is copied out or dropped, a batch that finds no free slot sent the
ordinary way, shared memory too small for the slots refused at the start, workers started by forkserver."""

import itertools
import multiprocessing
import time

import pytest
import torch
from torch.utils.data import DataLoader

from data_pipeline import batch_slots
from data_pipeline.batch_slots import SlotBatch, batch_views, block_bytes
from data_pipeline.dataloader import PREFETCH, ResumableDataLoader, make_dataloader
from data_pipeline.dataset import LoaderError, SequenceDataset, shard_set

from test_loader import summary  # noqa: I001 (tests/data_pipeline/test_loader.py)


def dataset(shards, workers: int) -> SequenceDataset:
    return SequenceDataset(shard_set(shards, "train"), batch_size=2, seq_len=8, num_workers=workers, seed=3,
                           batches_per_worker=8 // workers)


def torch_hand_over(shards, workers: int) -> list[dict]:
    """The batches as torch's DataLoader hands them over itself (a shared-memory region per batch)."""
    return list(DataLoader(dataset(shards, workers), batch_size=None, num_workers=workers))


def test_a_batch_is_views_of_one_aligned_block():
    start, size = block_bytes(2, 3, 4, 5)
    assert start % 8 == 0 and start >= 2 * 3 * 3 * 4 * 5 and size == start + 8 * (2 * 2 * 3 + 2 * 2)
    block = torch.zeros(size, dtype=torch.uint8)
    views = batch_views(block, 2, 3, 4, 5)
    views["label"][:] = torch.tensor([7, 9])
    views["frames"][:] = 1
    assert views["frames"].shape == (2, 3, 3, 4, 5) and views["gaps"].shape == views["indices"].shape == (2, 3)
    assert views["label"].tolist() == [7, 9] and int(block[:start].sum()) == 2 * 3 * 3 * 4 * 5
    assert all(view.untyped_storage().data_ptr() == block.untyped_storage().data_ptr() for view in views.values())


@pytest.mark.parametrize("workers", [1, 2])
def test_workers_hand_over_every_batch_in_a_slot_and_the_batches_are_torchs(built_shards, workers):
    loader = make_dataloader(dataset(built_shards, workers))
    raw = []
    for item in DataLoader.__iter__(loader):  # what crosses from the workers, before the loader copies it out
        raw.append(type(item))
        item.take()
    assert raw == [SlotBatch] * 8  # more batches than slots: each slot freed and used again
    assert summary(loader) == summary(torch_hand_over(built_shards, workers))


def test_a_batch_without_a_free_slot_goes_the_ordinary_way_and_a_dropped_one_frees_its_slot(built_shards,
                                                                                            monkeypatch):
    monkeypatch.setattr(batch_slots, "SLOT_WAIT", 0.05)  # before the worker starts: it inherits it
    loader = make_dataloader(dataset(built_shards, 1))
    items = DataLoader.__iter__(loader)
    held = [next(items) for _ in range(PREFETCH + 1)]  # every slot of the worker, none copied out
    assert all(isinstance(item, SlotBatch) for item in held)
    fourth = next(items)
    assert isinstance(fourth, dict)  # no slot came free: collated in a region of its own
    del held  # dropped unread: their slots are free again
    kinds, rest = [], []
    for item in itertools.islice(items, 4):
        kinds.append(type(item))
        rest.append(item.take() if isinstance(item, SlotBatch) else item)
    # the first two were asked for (PREFETCH in flight) while the slots were held; those asked for since, not
    assert kinds[PREFETCH:] == [SlotBatch, SlotBatch]
    expected = summary(torch_hand_over(built_shards, 1))
    assert summary([fourth]) == expected[3:4] and summary(rest) == expected[4:]


def test_a_new_loader_of_the_same_dataset_hands_over_in_slots_of_its_own(built_shards, monkeypatch):
    """Lightning's `reload_dataloaders_every_n_epochs` makes a new loader of the dataset every epoch. The batches the
    old loader's workers had placed in slots and nobody received kept those slots taken for good, and every batch of
    the next loader waited SLOT_WAIT (1 s) for one before it went the ordinary way: 11 s epochs instead of 0.1 s."""
    monkeypatch.setattr(batch_slots, "SLOT_WAIT", 0.05)  # before the workers start: they inherit it
    source = dataset(built_shards, 2)
    old = make_dataloader(source)
    items = DataLoader.__iter__(old)
    next(items).take()
    time.sleep(1.0)  # the workers place the batches in flight in their slots
    old._iterator._shutdown_workers()  # as at the old loader's end: the batches in flight are never received
    kinds = []
    for item in DataLoader.__iter__(make_dataloader(source)):
        kinds.append(type(item))
        if isinstance(item, SlotBatch):
            item.take()
    assert kinds == [SlotBatch] * 8


def test_shared_memory_too_small_for_the_slots_is_refused_at_the_start(built_shards, monkeypatch):
    monkeypatch.setattr("data_pipeline.dataset.shared_memory_free", lambda: 2**20)
    with pytest.raises(LoaderError, match=r"need \d+ MiB of shared memory .* 1 MiB free: .*--shm-size"):
        make_dataloader(SequenceDataset(shard_set(built_shards, "train"), batch_size=32, seq_len=8, num_workers=2,
                                        batches_per_worker=1))


def test_slots_work_with_workers_started_by_forkserver(built_shards):
    """Python 3.14's default start method on Linux: the workers get the slots (and their semaphores) pickled."""
    source = dataset(built_shards, 2)
    source.share_slots(PREFETCH + 1, multiprocessing.get_context("forkserver"))
    loader = ResumableDataLoader(source, batch_size=None, num_workers=2, multiprocessing_context="forkserver",
                                 prefetch_factor=PREFETCH)
    assert [type(item) for item in DataLoader.__iter__(loader)] == [SlotBatch] * 8
    assert summary(loader) == summary(torch_hand_over(built_shards, 2))
