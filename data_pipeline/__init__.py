"""HAUWM data pipeline: SSv2 → WebDataset shards → batches of variable-gap sequences.

`hauwm shards build|inspect|preview|sample-data` (see `cli.py`); `ShardDataModule` and `SetEpoch` for
Lightning; `SequenceDataset`/`make_dataloader` for plain PyTorch. The guide is docs/data_pipeline.md.
The names below import lazily, so the shard-building CLI does not load torch and Lightning.
"""

from importlib import import_module

_EXPORTS = {"SetEpoch": "datamodule", "ShardDataModule": "datamodule", "LoaderError": "dataset", "ShardDirError": "shard_format",
            "SequenceDataset": "dataset", "collate": "dataset", "make_dataloader": "dataloader", "shard_set": "dataset",
            "sample_indices": "sampling"}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'data_pipeline' has no attribute {name!r}")
    return getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
