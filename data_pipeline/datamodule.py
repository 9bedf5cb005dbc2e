"""`ShardDataModule`: the shard loader as a LightningDataModule, and `SetEpoch`, the callback that
reshuffles the shards every epoch (Lightning does not call `set_epoch` on an IterableDataset).

Train: shards shuffled with `seed + epoch`, split by rank and worker, a shuffle buffer, and the same
number of batches on every rank (see `dataset.py`). Validation: a fixed order and a fixed seed, so
every evaluation sees the same `val_batches` batches (rounded down to a multiple of the workers, at least
one per worker) with the same gaps, for the per-k metrics the model computes from `gaps`. Which sequences
those are depends on the number of validation streams (ranks × workers): compare validation figures between
runs with the same `--data.num_workers` and devices. The workers of both loaders start
once and stay for the whole fit (see `dataloader.py` for how they follow the epoch).

    trainer = lightning.Trainer(callbacks=[SetEpoch()])
    trainer.fit(model, datamodule=ShardDataModule("demo-out/shards", batch_size=8))
"""

from __future__ import annotations

import warnings

import lightning
import torch
from lightning.pytorch.utilities import rank_zero_info

from hauwm.arguments import MAX_TIMEOUT

from .dataloader import check_worker_priority, make_dataloader
from .dataset import LoaderError, SequenceDataset, check_shard_url, shard_set
from .sampling import gap_range_note, gaps_beyond_clips
from .shard_format import read_manifest


class SetEpoch(lightning.Callback):
    """Keeps the train dataset's epoch Lightning's: sets it at the start of each epoch, before Lightning creates the
    epoch's iterator (from epoch 1 on; epoch 0's iterator exists already and reads epoch 0, the dataset's initial
    value), and ends, on resume, an epoch that the checkpoint has gone further into than this run's epochs are long."""

    def on_train_epoch_start(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule) -> None:
        dataset = getattr(trainer.train_dataloader, "dataset", None)
        if isinstance(dataset, SequenceDataset):
            dataset.set_epoch(trainer.current_epoch)

    def on_load_checkpoint(self, trainer: lightning.Trainer, pl_module: lightning.LightningModule,
                           checkpoint: dict) -> None:
        """A resume with a larger batch or on more devices has shorter epochs: a checkpoint at batch 9 of a 12-batch
        epoch is past the end of a 6-batch one. Lightning ran that epoch again from its first batch (the loader, past
        it, read the next epoch's data) and then the next epoch's data once more; marked as ended, the fit goes on
        with the next epoch, as the loader does (`ResumableDataLoader.load_state_dict`)."""
        dataset = getattr(trainer.datamodule, "train_set", None)
        progress = checkpoint.get("loops", {}).get("fit_loop", {}).get("epoch_loop.batch_progress")
        if not isinstance(dataset, SequenceDataset) or not progress or progress["is_last_batch"]:
            return
        limit = trainer.limit_train_batches  # the epoch's length as Lightning will count it
        batches = min(len(dataset), limit) if isinstance(limit, int) else int(len(dataset) * limit)
        if progress["current"]["processed"] >= batches:
            progress["is_last_batch"] = True


class ShardDataModule(lightning.LightningDataModule):
    def __init__(self, shards: str | None = None, train_split: str = "train", val_split: str = "validation",
                 batch_size: int = 32, seq_len: int = 16, k_max: int = 5, num_workers: int = 2,
                 shuffle_buffer: int = 256, seed: int = 0, val_batches: int = 8, shard_url: str | None = None,
                 timeout: float = 600.0, worker_priority: str = "normal", pin_memory: bool | None = None):
        """Batches of variable-gap sequences from a shard directory, for training and validation.

        Args:
            shards: the shard directory (with manifest.json), built by `hauwm shards build`; required
            train_split: the split trained on
            val_split: the split validated on
            batch_size: sequences per batch (per rank)
            seq_len: frames per sequence L
            k_max: the largest gap K_max; gaps are k ~ U{1..K_max}
            num_workers: loader worker processes per rank (0: in the training process)
            shuffle_buffer: sequences shuffled across shards in each worker's buffer
            seed: seed of the shuffles and gaps (each epoch reshuffles from seed + epoch)
            val_batches: validation batches per rank
            shard_url: URL template for the tars, e.g. `pipe:aws s3 cp s3://bucket/shards/{name} -`, with the
                manifest copied to `shards`
            timeout: seconds a loader worker may take for one batch before the run stops with an error naming
                its shard
            worker_priority: normal, or idle for workers that use only the cores the training step leaves free
                (Linux; for CPU-only runs on few cores, see `dataloader.check_worker_priority`)
            pin_memory: copy each batch into page-locked memory for its copy to the GPU (torch's pinning thread);
                unset: pin where a CUDA GPU is visible. false copies from ordinary memory instead
        """
        if not shards:
            raise LoaderError("no shard directory: pass --data.shards DIR (built by `hauwm shards build`)")
        check_worker_priority(worker_priority)
        check_shard_url(shard_url)
        for name, value, least in (("num_workers", num_workers, 0), ("val_batches", val_batches, 1),
                                   ("batch_size", batch_size, 1), ("shuffle_buffer", shuffle_buffer, 0),
                                   ("seed", seed, 0)):
            if value < least:
                raise LoaderError(f"--data.{name} must be at least {least}, got {value}")
        if seq_len < 2:
            raise LoaderError(f"--data.seq_len must be at least 2 (a sequence must hold a gap k for the model to learn "
                              f"from), got {seq_len}")
        if pin_memory and not torch.cuda.is_available():
            raise LoaderError("--data.pin_memory true: no CUDA GPU is visible to pin batches for; leave it unset "
                              "(batches are pinned where a GPU is there)")
        if not 0 < timeout <= MAX_TIMEOUT:  # the OS cannot wait for 1e300 s: an OverflowError at the first batch
            raise LoaderError(f"--data.timeout (seconds a worker may take for a batch) must be positive and at most "
                              f"{MAX_TIMEOUT:g} (a day), got {timeout}")
        super().__init__()
        self.save_hyperparameters()
        self.train_set: SequenceDataset | None = None
        self.val_set: SequenceDataset | None = None
        self.train_clip_length: float | None = None  # the median frame count of the clips trained on

    def setup(self, stage: str | None = None) -> None:
        hp = self.hparams
        # Lightning warns, for the validation loader first, that a sized IterableDataset may be inaccurate with
        # workers; ours splits the shards per rank and worker and gives each worker its own count.
        warnings.filterwarnings("ignore", message=".*`IterableDataset` has `__len__` defined")
        read_manifest(hp.shards)  # a clear error naming the directory and the build command
        common = dict(batch_size=hp.batch_size, seq_len=hp.seq_len, k_max=hp.k_max, seed=hp.seed)
        if stage in (None, "fit"):
            train_shards = shard_set(hp.shards, hp.train_split, hp.shard_url)
            self.train_clip_length = train_shards.median_frames(hp.seq_len)  # the export records it (PretrainModule)
            lengths = train_shards.clip_lengths()
            if beyond := gaps_beyond_clips(lengths, hp.seq_len, hp.k_max, "--data.k_max"):
                raise LoaderError(f"{beyond} (the {hp.train_split} split's clips)")
            if note := gap_range_note(lengths, hp.seq_len, hp.k_max,
                                      f"--data.k_max {hp.k_max} with --data.seq_len {hp.seq_len}"):
                rank_zero_info(f"note: {note}")
            self.train_set = SequenceDataset(train_shards, num_workers=hp.num_workers, shuffle=True, continuous=True,
                                             shuffle_buffer=hp.shuffle_buffer, **common)
        no_validation = stage == "fit" and self.trainer is not None and self.trainer.limit_val_batches == 0
        if stage in (None, "fit", "validate") and not no_validation:
            val_shards = shard_set(hp.shards, hp.val_split, hp.shard_url)
            world_size = self.trainer.world_size if self.trainer is not None else 1
            usable = sum(n > 0 for n in val_shards.eligible(hp.seq_len))
            workers = max(0, min(hp.num_workers, usable // max(1, world_size)))
            try:
                self.val_set = SequenceDataset(val_shards, num_workers=workers, shuffle=False,
                                               batches_per_worker=max(1, hp.val_batches // max(1, workers)), **common)
            except LoaderError as error:
                raise LoaderError(f"{error}; or train without validation (--trainer.limit_val_batches 0)") from None
            clips = sum(val_shards.eligible(hp.seq_len))
            sequences = self.val_set.streams * self.val_set.batches_per_worker * hp.batch_size  # all ranks' together
            if clips < sequences:  # fine for the per-k metrics (each repeat has other gaps); worth knowing
                per_stream = clips // (self.val_set.streams * hp.batch_size)  # each stream reads whole batches
                remedy = (f"--data.val_batches {per_stream * self.val_set.workers} reads no more sequences than there are "
                          "clips" if per_stream else "fewer workers (--data.num_workers) or a smaller --data.batch_size "
                          "read fewer")
                rank_zero_info(f"validation reads {sequences} sequences ({world_size} rank{'s' * (world_size > 1)} × "
                               f"{len(self.val_set)} batches of {hp.batch_size}) from {clips} clips of at least "
                               f"{hp.seq_len} frames, so clips repeat within an evaluation, with other gaps; {remedy}")

    def train_dataloader(self):
        if self.trainer is not None and not any(isinstance(c, SetEpoch) for c in self.trainer.callbacks):
            warnings.warn("ShardDataModule: add data_pipeline.SetEpoch() to the Trainer's callbacks, or every "
                          "epoch reads the shards in the same order", stacklevel=2)
        loader = make_dataloader(self.train_set, self.hparams.timeout, self.hparams.worker_priority,
                                 self.hparams.pin_memory)
        if self.trainer is not None:  # batches of this epoch trained on, for a checkpoint's data position
            loader.batches_done = lambda: self.trainer.fit_loop.epoch_loop.batch_progress.current.processed
            loader.epoch_ended = lambda: self.trainer.fit_loop.epoch_loop.batch_progress.is_last_batch
        return loader

    def val_dataloader(self):
        hp = self.hparams
        return make_dataloader(self.val_set, hp.timeout, hp.worker_priority, hp.pin_memory)
