"""The loader: batch format, gaps U{1..K_max}, frames equal the stored ones, equal batch counts on every
rank and worker over uneven shards, the epoch reshuffle, persistent workers that follow the epoch and the
resume position, and the LightningDataModule around it."""

import json
import logging
import multiprocessing
import os
import re
import shutil
import signal
import tarfile
import time
import warnings
from collections import Counter
from collections.abc import Callable

import lightning
import numpy as np
import pytest
import torch
from scipy.stats import chisquare
from torch.utils.data import DataLoader

from data_pipeline import SetEpoch, ShardDataModule, dataloader
from data_pipeline.dataloader import ResumableDataLoader, make_dataloader
from data_pipeline.dataset import LoaderError, SequenceDataset, ShardSet, shard_set
from data_pipeline.shard_format import ShardDirError, decode_frames, read_samples
from model.checkpointing import LastStepCheckpoint


def stored_clips(directory, split):
    clips = {}
    for shard in json.loads((directory / "manifest.json").read_text())["splits"][split]["shards"]:
        with tarfile.open(directory / shard["name"]) as tar:
            members = {m.name: tar.extractfile(m).read() for m in tar}
        for name in members:
            if name.endswith(".json"):
                key = name[:-5]
                clips[key] = (json.loads(members[name]), decode_frames(members[f"{key}.jpgs"], "jpgs"))
    return clips


def as_stream(monkeypatch, rank, world_size, worker, num_workers):
    """What webdataset's split_by_node/split_by_worker see on that rank, in that DataLoader worker."""
    for name, value in (("RANK", rank), ("WORLD_SIZE", world_size), ("WORKER", worker), ("NUM_WORKERS", num_workers)):
        monkeypatch.setenv(name, str(value))


def test_batches_have_the_contract_format_and_the_stored_frames(built_shards):
    clips = stored_clips(built_shards, "train")
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=3, seq_len=6, k_max=5, num_workers=0)
    batches = list(dataset)
    assert len(batches) == len(dataset) == 18 // 3
    for batch in batches:
        assert batch["frames"].dtype == torch.uint8 and batch["frames"].shape == (3, 6, 3, 64, 64)
        for key in ("gaps", "indices"):
            assert batch[key].dtype == torch.int64 and batch[key].shape == (3, 6)
        assert batch["num_frames"].shape == batch["label"].shape == (3,) and len(batch["id"]) == 3
        assert (batch["gaps"][:, 0] == 0).all()
        assert torch.equal(batch["gaps"][:, 1:], batch["indices"].diff(dim=1))
        for b, clip_id in enumerate(batch["id"]):
            metadata, frames = clips[clip_id]
            indices = batch["indices"][b].numpy()
            assert batch["num_frames"][b] == metadata["num_frames"] == len(frames)
            assert batch["label"][b] == metadata["class_index"]
            assert indices[0] >= 0 and indices[-1] < len(frames)
            np.testing.assert_array_equal(batch["frames"][b].permute(0, 2, 3, 1).numpy(), frames[indices])


def test_a_workers_batch_arrives_as_one_shared_memory_region(built_shards, monkeypatch):
    """Each region costs the training process a round trip to the worker (a file descriptor over a socket): the
    frames and the four integer fields are views of one block. (Pinned, on a GPU machine, each tensor is copied on
    its own: the test looks at the batch as it crosses, before pinning.)"""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=1)
    batch = next(iter(make_dataloader(dataset)))
    regions = {key: value.untyped_storage().data_ptr() for key, value in batch.items() if torch.is_tensor(value)}
    assert len(set(regions.values())) == 1, regions
    assert all(value.is_contiguous() for value in batch.values() if torch.is_tensor(value))
    assert batch["frames"].dtype == torch.uint8 and batch["gaps"].dtype == torch.int64


def test_loader_gaps_follow_the_uniform_distribution(built_shards):
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=5, k_max=5, num_workers=0)
    gaps = []
    for epoch in range(25):  # clips have ≥ 24 frames ≥ 1 + 4·5: every draw fits, so exactly i.i.d.
        dataset.set_epoch(epoch)
        gaps += [batch["gaps"][:, 1:].reshape(-1) for batch in dataset]
    counts = np.bincount(torch.cat(gaps).numpy(), minlength=6)[1:]
    assert counts.sum() == 25 * 9 * 2 * 4
    assert chisquare(counts).pvalue > 1e-3, counts


def test_the_median_clip_length_counts_the_clips_long_enough_to_train_on():
    shards = ShardSet("train", ["a.tar", "b.tar"], [{10: 1, 30: 2}, {20: 1, 40: 1, 5: 3}])
    assert shards.median_frames(8) == 30  # 10, 20, 30, 30, 40 (the 5-frame clips are skipped)
    assert shards.median_frames(15) == 30  # 20, 30, 30, 40
    assert shards.median_frames(30) == 30  # 30, 30, 40: a clip of exactly seq_len frames is trained on
    assert shards.median_frames(31) == 40 and shards.median_frames(41) is None


def test_a_split_whose_clips_all_failed_to_build_is_named_so_not_as_too_short():
    nothing = ShardSet("validation", ["validation-000000.tar"], [{}])  # its 5 clips' videos were missing
    with pytest.raises(LoaderError, match=r"split 'validation' holds no clips \(`hauwm shards inspect` shows why"):
        SequenceDataset(nothing, batch_size=2, seq_len=8)  # "the longest has 0: lower seq_len" before


def test_the_datamodule_records_the_median_length_of_the_clips_it_trains_on(built_shards):
    """train_clip_length (which the export records for fine-tuning's k = 1 embedding) leaves out the train clips
    shorter than seq_len, as training does."""
    train = shard_set(built_shards, "train")
    lengths = sorted(frames for counts in train.frame_counts for frames, n in counts.items() for _ in range(n))
    seq_len = lengths[3] + 1  # the four shortest train clips are too short to train on
    assert train.median_frames(seq_len) != train.median_frames(1)  # the test could tell them in or out
    module = ShardDataModule(str(built_shards), batch_size=2, seq_len=seq_len, num_workers=0)
    module.setup("fit")
    assert module.train_clip_length == train.median_frames(seq_len)


def test_two_ranks_by_two_workers_get_equal_batch_counts_over_uneven_shards(built_shards, monkeypatch):
    shards = shard_set(built_shards, "train")
    assert sorted(shards.eligible(8)) == [2, 4, 4, 4, 4]  # uneven
    counts, seen = {}, {}
    for rank in range(2):
        for worker in range(2):
            as_stream(monkeypatch, rank, 2, worker, 2)
            dataset = SequenceDataset(shards, batch_size=2, seq_len=8, num_workers=2)
            dataset.set_epoch(3)
            batches = list(dataset)
            counts[rank, worker] = len(batches)
            seen[rank, worker] = {clip_id for batch in batches for clip_id in batch["id"]}
            assert len(dataset) == 2 * len(batches)  # batches per rank
    assert set(counts.values()) == {18 // (2 * 2 * 2)}, counts
    streams = list(seen.values())
    assert all(not (a & b) for i, a in enumerate(streams) for b in streams[i + 1:])  # each shard read by one stream


def test_a_worker_reads_for_the_rank_of_the_process_that_made_its_dataset(built_shards, monkeypatch):
    """A DataLoader worker started by forkserver or spawn (Python 3.14's default) has no process group, and
    Lightning sets no RANK: asked there, every rank's workers read as rank 0 of 1, the same shards and draws."""
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=0)
    on_the_rank = [batch["id"] for batch in dataset]
    monkeypatch.delenv("RANK")
    monkeypatch.delenv("WORLD_SIZE")  # as in such a worker
    assert [batch["id"] for batch in dataset] == on_the_rank


def test_each_epoch_deals_the_shards_to_the_streams_anew_and_all_of_them(built_shards):
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=2)
    deals = [(tuple(dataset.stream_urls(0, epoch)), tuple(dataset.stream_urls(1, epoch))) for epoch in range(6)]
    assert all(sorted(first + second) == sorted(dataset.urls) for first, second in deals)  # every shard, once
    assert len(set(deals)) > 1  # the global shuffle with seed + epoch moves shards between streams
    other_seed = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=2, seed=1)
    assert [(tuple(other_seed.stream_urls(0, epoch)), tuple(other_seed.stream_urls(1, epoch)))
            for epoch in range(5)] == deals[1:]  # seed 1's epoch e is seed 0's epoch e + 1 (seed + epoch)


def test_real_dataloader_workers_yield_len_batches_without_repeats_within_a_pass(built_shards):
    shards = shard_set(built_shards, "train")
    clips_in = dict(zip(shards.urls, shards.eligible(8)))
    dataset = SequenceDataset(shards, batch_size=2, seq_len=8, num_workers=2)
    dataset.set_epoch(5)
    batches = list(make_dataloader(dataset))
    assert len(batches) == len(dataset) == 2 * (18 // 4)
    for worker in range(2):  # the DataLoader takes batches from its workers in turn
        stream_clips = sum(clips_in[url] for url in dataset.stream_urls(worker))
        ids = [clip_id for batch in batches[worker::2] for clip_id in batch["id"]]
        first_pass = ids[:stream_clips]
        assert len(set(first_pass)) == len(first_pass)


def test_each_epoch_reshuffles_and_an_epoch_replays_exactly(built_shards):
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=0)
    orders = []
    for epoch in (0, 0, 1, 2):
        dataset.set_epoch(epoch)
        orders.append([batch["id"] + batch["indices"].reshape(-1).tolist() for batch in dataset])
    assert orders[0] == orders[1]
    assert orders[0] != orders[2] and orders[2] != orders[3]


def summary(batches) -> list:
    """What identifies a list of batches: the clips, their frame indices and the frames themselves."""
    return [(batch["id"], batch["indices"].tolist(), batch["frames"].sum().item()) for batch in batches]


def worker_pids(before: frozenset = frozenset()) -> list[int]:
    """The child processes alive now (DataLoader workers), less those in `before` (left by earlier tests)."""
    return sorted({process.pid for process in multiprocessing.active_children()} - before)


def test_persistent_workers_give_each_epoch_what_workers_started_for_it_give(built_shards):
    shards = shard_set(built_shards, "train")
    expected = []
    for epoch in range(4):  # workers started for each epoch (the loader before persistent workers)
        fresh = SequenceDataset(shards, batch_size=2, seq_len=8, num_workers=2, seed=7)
        fresh.set_epoch(epoch)
        expected.append(summary(DataLoader(fresh, batch_size=None, num_workers=2)))
    before = frozenset(worker_pids())
    dataset = SequenceDataset(shards, batch_size=2, seq_len=8, num_workers=2, seed=7)
    loader = make_dataloader(dataset)
    pids = []
    for epoch in range(4):
        dataset.set_epoch(epoch)
        batches = iter(loader)
        first = next(batches)
        pids.append(worker_pids(before))
        assert summary([first, *batches]) == expected[epoch]
    assert len(pids[0]) == 2 and all(epoch_pids == pids[0] for epoch_pids in pids)  # started once
    assert len({str(epoch) for epoch in expected}) == 4  # a new order every epoch


@pytest.mark.parametrize("workers", [0, 2])
def test_continuous_workers_run_on_into_the_next_epoch_with_the_same_batches(built_shards, monkeypatch, workers):
    """Training's loader: one stream over the epochs (no pause while the workers start the next epoch), giving
    each epoch what a loader told the epoch gives; a position out of turn (a resume) starts a new stream."""
    shards = shard_set(built_shards, "train")
    reference = SequenceDataset(shards, batch_size=2, seq_len=8, num_workers=workers, seed=7)
    reference_loader = make_dataloader(reference)
    expected = []
    for epoch in range(4):
        reference.set_epoch(epoch)
        expected.append(summary(reference_loader))
    dataset = SequenceDataset(shards, batch_size=2, seq_len=8, num_workers=workers, seed=7, continuous=True)
    loader = make_dataloader(dataset)
    starts, start = [], ResumableDataLoader._started
    monkeypatch.setattr(ResumableDataLoader, "_started", lambda self: starts.append(dataset.epoch) or start(self))
    for epoch in range(4):
        dataset.set_epoch(epoch)  # as SetEpoch does
        assert summary(loader) == expected[epoch]
    assert starts == [0]
    loader.load_state_dict({"epoch": 1, "batches": 3})
    assert summary(loader) == expected[1][3:]
    dataset.set_epoch(2)
    assert summary(loader) == expected[2]
    assert starts == [0, 1]


@pytest.mark.parametrize("priority, scheduler", [("idle", "SCHED_IDLE"), ("normal", "SCHED_OTHER")])
def test_worker_priority_sets_the_workers_scheduling_class(built_shards, priority, scheduler):
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=2)
    loader = make_dataloader(dataset, worker_priority=priority)
    before = frozenset(worker_pids())
    batches = iter(loader)
    next(batches), next(batches)  # a batch from each worker (round robin): both have run their init
    workers = worker_pids(before)
    assert len(workers) == 2
    assert {os.sched_getscheduler(pid) for pid in workers} == {getattr(os, scheduler)}
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the training process keeps its class
    del batches, loader


def test_ctrl_c_is_left_to_the_training_process(built_shards):
    """A terminal's Ctrl-C reaches every process of the group; the workers leave it to the training process, which
    stops them (a worker interrupted mid-shutdown printed a traceback)."""
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=2)
    before = frozenset(worker_pids())
    batches = iter(make_dataloader(dataset))
    next(batches), next(batches)  # a batch from each worker: both have run their init
    workers = worker_pids(before)
    for pid in workers:
        os.kill(pid, signal.SIGINT)
    next(batches), next(batches)  # both still serve
    assert worker_pids(before) == workers
    del batches


@pytest.mark.parametrize(("settings", "message"), [
    (dict(worker_priority="low"), r"--data.worker_priority must be one of normal, idle, got 'low'"),
    (dict(num_workers=-1), "--data.num_workers must be at least 0, got -1"),
    (dict(val_batches=0), "--data.val_batches must be at least 1, got 0"),
    (dict(timeout=0), "--data.timeout .* must be positive and at most 86400 .*, got 0"),
    (dict(timeout=1e300), "--data.timeout .* at most 86400 .*, got 1e[+]300"),
    (dict(seq_len=1), "--data.seq_len must be at least 2"),
    (dict(batch_size=0), "--data.batch_size must be at least 1, got 0"),
    (dict(shuffle_buffer=-4), "--data.shuffle_buffer must be at least 0, got -4"),
    (dict(seed=-1), "--data.seed must be at least 0, got -1"),
    # a shard_url without {name} made every shard of both splits one tar: validation on training clips, silently
    (dict(shard_url="/data/train-000000.tar"), r"--data.shard_url '/data/train-000000.tar' must name each tar "
                                               r"through \{name\} .*; without it every shard would be the same tar"),
    (dict(shard_url="s3://b/{nam}"), r"must name each tar through \{name\} .*, and no other field \(\{nam\}\)"),
    (dict(shard_url="s3://b/{0}"), r"and no other field \(\{0\}\)"),
    (dict(shard_url="s3://b/{name"), r"--data.shard_url 's3://b/\{name': expected '\}' before end of string"),
    pytest.param(dict(pin_memory=True), "--data.pin_memory true: no CUDA GPU is visible",
                 marks=pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU pins")),
])
def test_bad_loader_settings_are_refused_with_the_flag(built_shards, settings, message):
    with pytest.raises(LoaderError, match=message):
        ShardDataModule(str(built_shards), **settings)


@pytest.mark.parametrize("pin_memory", [None, False])
def test_batches_are_pinned_where_a_gpu_is_there_unless_turned_off(built_shards, pin_memory):
    module = ShardDataModule(str(built_shards), batch_size=2, seq_len=8, num_workers=0, pin_memory=pin_memory)
    module.setup("fit")
    expected = torch.cuda.is_available() if pin_memory is None else False
    assert module.train_dataloader().pin_memory is expected and module.val_dataloader().pin_memory is expected


def test_persistent_workers_follow_a_resume_position_set_between_epochs(built_shards):
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=2, seed=2)
    loader = make_dataloader(dataset)
    dataset.set_epoch(3)
    whole_epoch = summary(loader)
    for done in (3, 4, 0):
        loader.load_state_dict({"epoch": 3, "batches": done})
        assert summary(loader) == whole_epoch[done:]


def starting_late(worker_init: Callable) -> Callable:
    """`worker_init` for `make_dataloader`, with every worker but worker 0 starting 2 s late (a busy machine, the
    spawn start method, idle priority)."""

    def start(priority: str, training_process: int, worker: int) -> None:
        if worker > 0:
            time.sleep(2)
        worker_init(priority, training_process, worker)

    return start


def test_a_worker_that_starts_late_reads_the_position_its_stream_began_at(built_shards, monkeypatch):
    """A resume in the last round of an epoch: its one batch left comes from worker 0 before worker 1 has started
    (worker 1's stream has none left), and the next epoch's set_epoch then moved the position. Worker 1, starting
    late, read that one and played worker 0's stream in every epoch after, so half the clips came twice and half never
    (found by a review, 2026-11-27; a real fit did the same)."""
    def run(resume_at: int | None = None) -> list[list[str]]:
        dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=2, seed=3,
                                  continuous=True)
        loader = make_dataloader(dataset)
        if resume_at is not None:
            loader.load_state_dict({"epoch": 0, "batches": resume_at})  # as a resumed fit's checkpoint says
        epochs = []
        for epoch in (0, 1, 2):
            if epoch:
                dataset.set_epoch(epoch)  # SetEpoch, at the next epoch's start
            epochs.append([clip for batch in loader for clip in batch["id"]])
        return epochs

    unbroken = run()  # its workers start long before the epoch's end
    monkeypatch.setattr(dataloader, "init_worker", starting_late(dataloader.init_worker))
    last_round = len(unbroken[0]) // 2 - 1  # batches of 2 clips: the epoch's last batch is left
    assert run(resume_at=last_round) == [unbroken[0][-2:], unbroken[1], unbroken[2]]


def test_pipe_urls_read_the_same_data(built_shards):
    local = SequenceDataset(shard_set(built_shards, "validation"), batch_size=3, seq_len=8, shuffle=False)
    piped = SequenceDataset(shard_set(built_shards, "validation", shard_url=f"pipe:cat {built_shards}/{{name}}"),
                            batch_size=3, seq_len=8, shuffle=False)
    for a, b in zip(local, piped, strict=True):
        assert a["id"] == b["id"] and torch.equal(a["frames"], b["frames"])


def test_a_continuous_loader_going_on_into_its_next_epochs_does_not_warn(built_shards):
    """torch warns when an iterator gives more batches than len(loader); the training loader's does, by design."""
    dataset = SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=2, continuous=True)
    loader = make_dataloader(dataset)
    batches = len(loader)  # as Lightning asks before it iterates (torch compares what an iterator gives with it)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for epoch in range(3):
            dataset.set_epoch(epoch)
            assert len(list(loader)) == batches
    assert not [warning for warning in caught if "Length of IterableDataset" in str(warning.message)]


def test_a_pipe_shard_cut_off_at_an_epochs_end_ends_its_command_at_once(built_shards):
    """An epoch that ends inside a shard left its `pipe:` command to the garbage collector, whose close waited for the
    command to end by itself (here, 60 s of a command that stalls; `aws s3 cp` in the middle of a download)."""
    stalling = shard_set(built_shards, "train", shard_url=f"pipe:cat {built_shards}/{{name}}; sleep 60")
    dataset = SequenceDataset(stalling, batch_size=2, seq_len=8, shuffle=False, batches_per_worker=1)
    started = time.monotonic()
    assert len(list(dataset)) == 1  # 2 of the first shard's 4 clips
    assert time.monotonic() - started < 30


def test_too_few_shards_or_clips_give_clear_errors(built_shards, monkeypatch):
    shards = shard_set(built_shards, "train")
    as_stream(monkeypatch, 0, 3, 0, 1)
    with pytest.raises(LoaderError, match="5 shards .* 3 ranks × 2 workers need at least 6 .one each.: rebuild with a "
                                          "smaller --clips-per-shard, or use fewer workers .--data.num_workers., or use "
                                          "fewer devices .--trainer.devices.$"):
        SequenceDataset(shards, batch_size=2, seq_len=8, num_workers=2)
    as_stream(monkeypatch, 0, 6, 0, 1)  # one worker already: only fewer devices can help
    with pytest.raises(LoaderError, match="6 ranks × 1 workers need at least 6 .one each.: rebuild with a smaller "
                                          "--clips-per-shard, or use fewer devices .--trainer.devices.$"):
        SequenceDataset(shards, batch_size=2, seq_len=8, num_workers=1)
    as_stream(monkeypatch, 0, 1, 0, 1)
    with pytest.raises(LoaderError, match="lower --data.batch_size"):
        SequenceDataset(shards, batch_size=64, seq_len=8)
    assert sum(shards.eligible(61)) == 0  # clips have at most 60 frames: too short for L = 61, skipped
    with pytest.raises(LoaderError, match="no clip of at least seq_len=61 frames .the longest has 60.: lower seq_len"):
        SequenceDataset(shards, batch_size=2, seq_len=61)


def test_datamodule_validates_its_inputs(built_shards, tmp_path):
    with pytest.raises(ShardDirError, match=f"{tmp_path / 'none'} does not exist.*hauwm shards build"):
        ShardDataModule(str(tmp_path / "none")).setup("fit")
    with pytest.raises(ShardDirError, match=f"{tmp_path / 'manifest.json'} not found.*hauwm shards build"):
        ShardDataModule(str(tmp_path)).setup("fit")
    with pytest.raises(LoaderError, match="has no split 'test'.*--split test"):
        ShardDataModule(str(built_shards), val_split="test", batch_size=2, seq_len=8).setup("fit")
    with pytest.raises(LoaderError, match=r"has no split 'bogus' \(it has train, validation\); name one of those$"):
        ShardDataModule(str(built_shards), train_split="bogus", batch_size=2, seq_len=8).setup("fit")
    manifest = json.loads((built_shards / "manifest.json").read_text())
    for change, message in (({"splits": {}}, "lists no split"),
                            ({"splits": manifest["splits"] | {"validation": manifest["splits"]["train"]}},
                             "lists shard train-000000.tar more than once")):
        (tmp_path / "manifest.json").write_text(json.dumps(manifest | change))
        with pytest.raises(ShardDirError, match=message):
            ShardDataModule(str(tmp_path)).setup("fit")


def test_validation_says_when_its_clips_repeat_within_an_evaluation(built_shards, caplog):
    validation_clips = sum(shard_set(built_shards, "validation").eligible(8))
    data = ShardDataModule(str(built_shards), batch_size=2, seq_len=8, num_workers=0, val_batches=validation_clips)
    with caplog.at_level(logging.INFO):
        data.setup("validate")
    assert re.search(rf"validation reads {2 * validation_clips} sequences .* from {validation_clips} clips .* "
                     rf"--data.val_batches {validation_clips // 2} reads no more sequences than there are clips", caplog.text)


def test_a_fit_without_validation_needs_no_usable_validation_split(built_shards, monkeypatch):
    """More ranks than validation shards: refused with the ways out, one of them a fit without validation, which
    then builds no validation set at all."""
    validation_shards = len(shard_set(built_shards, "validation").urls)
    as_stream(monkeypatch, 0, validation_shards + 1, 0, 1)
    data = ShardDataModule(str(built_shards), batch_size=1, seq_len=4, num_workers=0)
    with pytest.raises(LoaderError, match="split 'validation' .* train without validation .--trainer.limit_val_batches 0.$"):
        data.setup("fit")
    data.trainer = lightning.Trainer(limit_val_batches=0, logger=False, enable_checkpointing=False)
    data.setup("fit")
    assert data.val_set is None and data.train_set is not None


class WorkerPids(lightning.Callback):
    """The loader worker processes alive at the end of each training epoch."""

    def __init__(self):
        self.before, self.pids = frozenset(worker_pids()), []

    def on_train_epoch_end(self, trainer, pl_module):
        self.pids.append(worker_pids(self.before))


class RecordingModel(lightning.LightningModule):
    """Records every training sequence as (clip id, frame indices), and the validation batches; learns nothing."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(1))
        self.train_ids, self.val_batches = {}, []

    def training_step(self, batch, batch_index):
        self.train_ids.setdefault(self.current_epoch, []).extend(zip(batch["id"], map(tuple, batch["indices"].tolist())))
        return (self.weight * batch["frames"].float().mean()).sum()

    def validation_step(self, batch, batch_index):
        self.val_batches.append((batch["id"], batch["gaps"].clone()))

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.0)


def test_lightning_fit_with_set_epoch_reshuffles_and_validates_deterministically(built_shards):
    data = ShardDataModule(str(built_shards), batch_size=2, seq_len=8, num_workers=2, val_batches=2, seed=1)
    model, pids = RecordingModel(), WorkerPids()
    trainer = lightning.Trainer(max_epochs=3, accelerator="cpu", devices=1, callbacks=[SetEpoch(), pids],
                                logger=False, enable_checkpointing=False, enable_progress_bar=False,
                                num_sanity_val_steps=0, enable_model_summary=False)
    trainer.fit(model, datamodule=data)
    # 2 train workers and 1 validation worker (the split has one shard), the same processes every epoch
    assert len(pids.pids) == 3 and len(pids.pids[0]) == 3 and all(p == pids.pids[0] for p in pids.pids)
    assert worker_pids(pids.before) == []  # shut down when the fit ends
    assert [len(ids) for ids in model.train_ids.values()] == [2 * 2 * (18 // 4)] * 3
    assert len({tuple(ids) for ids in model.train_ids.values()}) == 3  # a new order every epoch
    assert len(model.val_batches) == 3 * 2
    first, *rest = [model.val_batches[i:i + 2] for i in range(0, 6, 2)]
    for later in rest:  # every evaluation sees the same clips with the same gaps
        assert [ids for ids, _ in later] == [ids for ids, _ in first]
        assert all(torch.equal(a, b) for (_, a), (_, b) in zip(later, first))
    assert Counter(len(ids) for ids, _ in first) == Counter({2: 2})


def test_a_truncated_shard_is_refused_with_its_name(built_shards, tmp_path):
    shard = built_shards / "train-000000.tar"
    broken = tmp_path / shard.name
    broken.write_bytes(shard.read_bytes()[: shard.stat().st_size // 3])  # cut inside a member
    with pytest.raises(ValueError, match=rf"{broken.name} is not a readable shard.*--verify"):
        with open(broken, "rb") as stream:
            list(read_samples(stream, str(broken)))


def test_a_shard_repacked_by_gnu_tar_reads_the_same(built_shards, tmp_path):
    import subprocess

    if shutil.which("tar") is None:
        pytest.skip("no tar command")
    shard = built_shards / "train-000000.tar"
    unpacked, repacked = tmp_path / "unpacked", tmp_path / "repacked.tar"
    unpacked.mkdir()
    with tarfile.open(shard) as tar:
        names = tar.getnames()
        tar.extractall(unpacked, filter="data")
    subprocess.run(["tar", "--format=pax", "-cf", str(repacked), *names], cwd=unpacked, check=True)
    with open(shard, "rb") as original, open(repacked, "rb") as copy:
        assert list(read_samples(copy, "repacked")) == list(read_samples(original, "original"))


def test_a_resume_with_another_number_of_loader_streams_is_warned_about(built_shards):
    """The position a checkpoint holds (batches of the epoch read per rank) means other clips with another number
    of ranks × workers: such a resume warns; the same number, or a checkpoint from before the field, does not."""
    loader = make_dataloader(SequenceDataset(shard_set(built_shards, "train"), batch_size=2, seq_len=8, num_workers=2))
    state = loader.state_dict()
    assert state["streams"] == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loader.load_state_dict({**state, "batches": 1})
        loader.load_state_dict({key: value for key, value in state.items() if key != "streams"})
    with pytest.warns(UserWarning, match=r"ran 1 streams \(ranks × DataLoader workers\), this run 2: the rest of "
                                         r"epoch 0 .*--data.num_workers"):
        loader.load_state_dict({**state, "streams": 1})


def test_a_resume_onto_other_shards_is_warned_about_and_one_onto_moved_shards_is_not(built_shards, tmp_path):
    """The position a checkpoint holds means other clips in other shards: such a resume warns (it went on without a
    word); the same shards in another directory, or a checkpoint from before the field, do not."""
    def loader(shards):
        return make_dataloader(SequenceDataset(shard_set(shards, "train"), batch_size=2, seq_len=8, num_workers=2))

    state = loader(built_shards).state_dict()
    moved = shutil.copytree(built_shards, tmp_path / "moved")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loader(moved).load_state_dict({**state, "batches": 1})
        loader(moved).load_state_dict({key: value for key, value in state.items() if key != "content_id"})
    other = tmp_path / "other"
    shutil.copytree(built_shards, other)
    manifest = json.loads((other / "manifest.json").read_text())
    manifest["splits"]["train"]["shards"].pop()  # one shard fewer: a dataset grown or cut since
    (other / "manifest.json").write_text(json.dumps(manifest))
    with pytest.warns(UserWarning, match=r"the checkpoint's train loader read other shards than this run's "
                                         r"--data.shards \(their sha256s differ\): the rest of epoch 0 skips the 1 "):
        loader(other).load_state_dict({**state, "batches": 1})


@pytest.mark.parametrize("stop_at", [5, 6, 9])  # mid-epoch (an epoch here is 6 batches), at its end, inside the second
def test_resuming_mid_epoch_continues_the_data_stream_exactly(built_shards, tmp_path, stop_at):
    """A run stopped at step `stop_at` and resumed from its checkpoint sees the same batches, in the same
    order, as an uninterrupted run: the epoch's shard order and the position inside the epoch come back."""

    def run(max_steps: int, root, ckpt_path=None) -> list[str]:
        data = ShardDataModule(str(built_shards), batch_size=3, seq_len=8, num_workers=2, val_batches=2, seed=3)
        model = RecordingModel()
        checkpoint = lightning.pytorch.callbacks.ModelCheckpoint(dirpath=root, every_n_train_steps=stop_at)
        trainer = lightning.Trainer(max_steps=max_steps, accelerator="cpu", devices=1, logger=False,
                                    callbacks=[SetEpoch(), checkpoint], enable_progress_bar=False,
                                    limit_val_batches=0, num_sanity_val_steps=0, enable_model_summary=False)
        trainer.fit(model, datamodule=data, ckpt_path=ckpt_path)
        return [clip for epoch in sorted(model.train_ids) for clip in model.train_ids[epoch]]

    total = 14
    uninterrupted = run(total, tmp_path / "full")
    first = run(stop_at, tmp_path / "first")
    resumed = run(total, tmp_path / "resumed", ckpt_path=next((tmp_path / "first").glob("*.ckpt")))
    assert first == uninterrupted[: 3 * stop_at]
    assert resumed == uninterrupted[3 * stop_at:]


class StopAt(lightning.Callback):
    """Asks the fit to stop after optimizer step `step`, as `trainer.max_time`'s Timer does when time is up."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_end(self, trainer: lightning.Trainer, *_) -> None:
        if trainer.global_step >= self.step:
            trainer.should_stop = True


@pytest.mark.parametrize("stop_at, limit, how", [(5, None, "max_steps"), (6, None, "max_steps"), (8, 4, "max_steps"),
                                                 (9, 4, "max_steps"), (5, None, "should_stop")])
def test_the_last_checkpoint_of_a_stopped_fit_resumes_exactly(built_shards, tmp_path, stop_at, limit, how):
    """`--trainer.max_steps N` (or a fit told to stop at step N, as by `--trainer.max_time`), then the same with a
    larger N and `--ckpt_path last`: the last.ckpt written when the first fit stopped (LastStepCheckpoint: at its
    last step, not at Lightning's train end, which counts the cut-short epoch as done) continues the data stream
    exactly; also where limit_train_batches ends every epoch early (the loader's state says the epoch ended,
    though fewer than len(loader) batches were read)."""

    def run(max_steps: int, root, ckpt_path=None, stop: int | None = None) -> list[str]:
        data = ShardDataModule(str(built_shards), batch_size=3, seq_len=8, num_workers=2, val_batches=2, seed=3)
        model = RecordingModel()
        checkpoint = lightning.pytorch.callbacks.ModelCheckpoint(dirpath=root, save_last=True, every_n_train_steps=100)
        trainer = lightning.Trainer(max_steps=max_steps, accelerator="cpu", devices=1, logger=False,
                                    callbacks=[SetEpoch(), *([StopAt(stop)] if stop else []), checkpoint,
                                               LastStepCheckpoint()], enable_progress_bar=False,
                                    limit_val_batches=0, num_sanity_val_steps=0, enable_model_summary=False,
                                    limit_train_batches=limit)
        trainer.fit(model, datamodule=data, ckpt_path=ckpt_path)
        return [clip for epoch in sorted(model.train_ids) for clip in model.train_ids[epoch]]

    uninterrupted = run(14, tmp_path / "full")
    first = run(stop_at, tmp_path / "first") if how == "max_steps" else run(14, tmp_path / "first", stop=stop_at)
    assert first == uninterrupted[: 3 * stop_at]
    assert run(14, tmp_path / "resumed", ckpt_path=tmp_path / "first" / "last.ckpt") == uninterrupted[3 * stop_at:]
