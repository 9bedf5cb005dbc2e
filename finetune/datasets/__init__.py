"""Offline datasets of 64x64 pixel episodes in Minari's format (collect, merge, inspect, load).

    from finetune.datasets import load_episodes, DatasetError
    episodes = load_episodes("hauwm/drawer_close-expert-v0", task="metaworld_drawer_close", action_dim=4)
    # [{"obs": uint8 [T+1, 3, 64, 64], "action": float32 [T+1, 4], "reward": float32 [T+1],
    #   "success": float32 [T+1], "terminal": float32 [T+1]}, ...]   (finetune/replay.py's alignment)

`hauwm datasets collect|merge|inspect|list` (finetune.datasets.cli) writes and describes them;
docs/datasets.md has the formats and the figures.
"""

from finetune.datasets.minari_io import (
    DatasetError,
    iterate_episodes,
    list_datasets,
    load_episodes,
    merge_datasets,
    write_dataset,
)

__all__ = ["DatasetError", "iterate_episodes", "list_datasets", "load_episodes", "merge_datasets", "write_dataset"]
