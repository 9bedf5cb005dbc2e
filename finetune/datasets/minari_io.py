"""Write, read and check Minari datasets of pixel episodes (the offline-RL format of the field).

A dataset ID such as `hauwm/drawer_close-expert-v0` lives in `$MINARI_DATASETS_PATH/<ID>/data`
(Minari's own root variable, default `~/.minari/datasets`). On disk an episode of T agent steps holds,
in Minari's layout, `observations` [T+1] (HWC uint8 frames, raw unless written with `jpeg=True`),
`actions` [T], `rewards` [T], `terminations` / `truncations` [T] and, where the suite has one,
`infos/success` [T+1] (entry 0 is the reset). In memory every episode is a dict in the replay's
Dreamer alignment (finetune/replay.py), so `Replay.add` takes it as it is:

    obs     uint8   [T+1, 3, 64, 64]  o_0 ... o_T
    action  float32 [T+1, A]          0, a_0 ... a_{T-1}   (in [-1, 1])
    reward  float32 [T+1]             0, r_1 ... r_T
    success float32 [T+1]             0, s_1 ... s_T       (all 0 where the suite has no success)
    terminal float32 [T+1]            1 at the last entry if the episode ended in a terminal state

Reading accepts datasets made elsewhere too: Box image observations HWC or CHW, or a Dict observation
with an image entry ("pixels", "image", ...); square-ish images of another size (32x32 at least) are resized
to 64x64 with OpenCV's INTER_AREA. Every other mismatch, of the spaces or of an episode's arrays with them, is
a `DatasetError` naming the dataset (and the episode) and the fix.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import gymnasium
import numpy as np
from tqdm import tqdm

from hauwm.json_kinds import is_count
from hauwm.termination import signals_deferred
from hauwm.pid_lock import lock_holder, locked

IMAGE_SIZE = 64  # the frames the world model is trained on (model.networks.IMAGE_SHAPE, not imported: it imports torch)
IMAGE_KEYS = ("pixels", "image", "rgb", "observation", "obs")  # Dict observation entries tried in this order
MAX_ASPECT = 1.25  # "square-ish": larger/smaller side at most this, else resizing would distort the scene
MIN_SIDE = 32  # smaller images are refused: blown up to 64x64 they would show nothing the world model has seen
METADATA_KEY = "hauwm"  # our settings in the dataset's metadata.json (task, source, env settings)
ID_EXAMPLE = "hauwm/drawer_close-expert-v0"


class DatasetError(ValueError):
    """A dataset that cannot be used (missing, empty, wrong images or actions); printed without a traceback."""


class DeletedOnInterrupt(KeyboardInterrupt):
    """Ctrl-C while write_dataset wrote a dataset it does not keep: the part written, `dataset_id`, was deleted."""

    def __init__(self, dataset_id: str) -> None:
        super().__init__()
        self.dataset_id = dataset_id


class KeptOnInterrupt(KeyboardInterrupt):
    """Ctrl-C between two episodes of write_dataset(keep_finished=True): the episodes written so far were kept
    as a whole dataset, `dataset`."""

    def __init__(self, dataset) -> None:
        super().__init__()
        self.dataset = dataset


def datasets_root() -> Path:
    """$MINARI_DATASETS_PATH, or Minari's default ~/.minari/datasets, as Minari's `get_dataset_path` finds it, without
    making it: reading (`list`, a dataset not found) leaves the disk as it was."""
    root = os.environ.get("MINARI_DATASETS_PATH")
    return Path(root) if root is not None else Path.home() / ".minari" / "datasets"


def dataset_path(dataset_id: str | None = None) -> Path:
    """Where dataset `dataset_id` lives (whether or not it exists): $MINARI_DATASETS_PATH/<ID>; None: the root (made
    where it does not exist, as Minari does: for writing)."""
    from minari.storage.datasets_root_dir import get_dataset_path

    try:
        return get_dataset_path(dataset_id)
    except OSError as error:  # the root cannot be made: a file there, a directory not writable
        root = os.environ.get("MINARI_DATASETS_PATH", "~/.minari/datasets (the default)")
        raise DatasetError(f"MINARI_DATASETS_PATH={root}: the datasets' directory cannot be made there "
                           f"({error.strerror or error}): set MINARI_DATASETS_PATH to a directory") from None


def check_dataset_id(dataset_id: str) -> None:
    """Minari's naming rule: `(namespace/)name-vN`, e.g. hauwm/drawer_close-expert-v0."""
    from minari.dataset.minari_dataset import DATASET_ID_RE

    match = DATASET_ID_RE.fullmatch(dataset_id)
    if match is None or match.group("version") is None:
        raise DatasetError(f"dataset ID {dataset_id!r} is not a Minari ID: write (namespace/)name-vN, "
                           f"e.g. {ID_EXAMPLE} (letters, digits, - and _; a namespace of 2 characters or more; "
                           "the -vN version is required)")


def scan_datasets() -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """Under $MINARI_DATASETS_PATH, where Minari's `list_local_datasets` looks (every directory holding `data/`,
    below directories not hidden): (every readable dataset's ID -> its metadata; an ID -> a line about its directory:
    why it cannot be read and what to do, or that it is a copy of another dataset, which reads as itself). Done here:
    Minari 0.5's listing stops with a TypeError at a directory not named `name-vN`."""
    root, datasets, notes = datasets_root(), {}, {}

    def visit(directory: Path, above: frozenset[Path]) -> None:
        """`above`: the directories walked down to this one, resolved (a symlink to one of them would loop)."""
        above = above | {directory.resolve()}
        for child in sorted(directory.iterdir()):
            if not child.is_dir() or child.name.startswith(".") or child.resolve() in above:
                continue
            if not (child / "data").exists():
                visit(child, above)
                continue
            dataset_id = child.relative_to(root).as_posix()
            try:
                check_dataset_id(dataset_id)
                metadata = read_metadata(child / "data")
                if metadata["dataset_id"] != dataset_id:  # a directory copied or moved: its metadata keeps its ID
                    notes[dataset_id] = (f"note: {dataset_id} is a copy of dataset {metadata['dataset_id']} (its "
                                         "data/metadata.json keeps that ID); it is read as the dataset of its directory")
                datasets[dataset_id] = metadata
            except (DatasetError, OSError, ValueError, KeyError) as error:  # JSONDecodeError is a ValueError
                notes[dataset_id] = f"damaged: {dataset_id} ({error}): write it again, or delete {child}"

    if root.exists() and not root.is_dir():
        raise DatasetError(f"MINARI_DATASETS_PATH={root} is a file, not the datasets' directory: set "
                           "MINARI_DATASETS_PATH to a directory")
    if root.is_dir():
        visit(root, frozenset())
    return datasets, notes


# the fields of metadata.json that are read (Minari's, then ours under "hauwm"), each where present: (test, wanted)
METADATA_FIELDS = {"total_episodes": (is_count, "a whole number ≥ 0"),
                   "total_steps": (is_count, "a whole number ≥ 0"),
                   "dataset_size": (lambda v: type(v) in (int, float), "a size in MB")}
HAUWM_FIELDS = {"task": (lambda v: isinstance(v, str), "a task's name"),
                "source": (lambda v: isinstance(v, str), "a word"),
                "action_repeat": (lambda v: is_count(v) and v >= 1, "a whole number ≥ 1"),
                "fast_render": (lambda v: isinstance(v, bool), "true or false"),
                "has_success": (lambda v: isinstance(v, bool), "true or false"),
                "complete": (lambda v: isinstance(v, bool), "true or false"),
                "merged": (lambda v: isinstance(v, list) and all(isinstance(i, str) for i in v), "a list of IDs"),
                "parts": (lambda v: isinstance(v, list) and all(isinstance(i, str) for i in v), "a list of IDs")}


def read_metadata(data: Path) -> dict[str, Any]:
    """A dataset's data/metadata.json, checked to be an object whose "hauwm" entry (where there is one) is one too,
    with fields of the kinds read (METADATA_FIELDS, HAUWM_FIELDS); a DatasetError naming the file and the field
    otherwise (a JSONDecodeError or OSError for a file that cannot be read)."""
    from minari.dataset.minari_storage import MinariStorage

    metadata = MinariStorage.read_raw_metadata(data)
    if not isinstance(metadata, dict) or not isinstance(metadata.get(METADATA_KEY, {}), dict):
        what = (f"its \"{METADATA_KEY}\" entry is {json.dumps(metadata[METADATA_KEY])[:40]}"
                if isinstance(metadata, dict) else f"it is a JSON {type(metadata).__name__}")
        raise DatasetError(f"{data / 'metadata.json'}: {what}, not an object")
    for fields, values, prefix in ((METADATA_FIELDS, metadata, ""),
                                   (HAUWM_FIELDS, metadata.get(METADATA_KEY, {}), f"{METADATA_KEY}.")):
        for name, (test, wanted) in fields.items():
            if name in values and not test(values[name]):
                raise DatasetError(f"{data / 'metadata.json'}: {prefix}{name} is {json.dumps(values[name])[:40]}, not "
                                   f"{wanted}")
    return metadata


def list_datasets() -> dict[str, dict[str, Any]]:
    """Every readable dataset under $MINARI_DATASETS_PATH: ID -> its metadata."""
    return scan_datasets()[0]


def _missing_message(dataset_id: str) -> str:
    root = datasets_root()
    available = list(list_datasets())
    listing = (f"the datasets there: {', '.join(available)}" if available else
               "there are none; make one with `hauwm datasets collect` or point MINARI_DATASETS_PATH elsewhere")
    return f"dataset {dataset_id!r} not found under MINARI_DATASETS_PATH={root}; {listing}"


def open_dataset(dataset_id: str):
    """The `minari.MinariDataset` of `dataset_id`, or a DatasetError saying what is wrong and what exists."""
    import minari

    check_dataset_id(dataset_id)
    path = datasets_root() / dataset_id
    if not (path / "data").is_dir():
        raise DatasetError(_missing_message(dataset_id))
    try:
        read_metadata(path / "data")
        dataset = minari.load_dataset(dataset_id)
    except ImportError as error:  # a storage format whose extra is not installed, e.g. Arrow
        raise DatasetError(f"dataset {dataset_id!r} at {path} is stored in a format this "
                           f"installation cannot read ({error})") from None
    except DatasetError as error:
        raise DatasetError(f"dataset {dataset_id!r}: {error}; write it again") from None
    except (ValueError, OSError, KeyError, AssertionError, RuntimeError) as error:  # JSONDecodeError: a ValueError
        raise DatasetError(f"dataset {dataset_id!r} at {path} could not be read by Minari "
                           f"{minari.__version__} ({type(error).__name__}: {error}); a dataset of another Minari "
                           "version needs that version, a damaged one must be written again") from None
    if dataset.total_episodes == 0:
        raise DatasetError(f"dataset {dataset_id!r} at {path} holds no episodes: collect into it "
                           "again (delete the directory first)")
    if unfinished(dataset.storage.metadata):
        raise DatasetError(unfinished_message(dataset_id, dataset.total_episodes))
    return dataset


def unfinished(metadata: dict[str, Any]) -> bool:
    """Whether a dataset's metadata says it is not finished: being written, or its writer was killed on the way
    (write_dataset marks a dataset unfinished until its last episode and its metadata are written, so a SIGKILL or
    a crash leaves it marked)."""
    return metadata.get(METADATA_KEY, {}).get("complete") is False


def unfinished_message(dataset_id: str, episodes: int) -> str:
    if (pid := lock_holder(writer_lock(dataset_id))) is not None:
        return (f"dataset {dataset_id!r} at {dataset_path(dataset_id)} is being written (by pid {pid}; {episodes} "
                "episodes so far): wait for its writer to finish")
    return (f"dataset {dataset_id!r} at {dataset_path(dataset_id)} is unfinished: its writer (hauwm datasets collect "
            f"or merge) was killed after {episodes} episodes, before it could close the dataset; delete that "
            "directory and write the dataset again")


def refuse_nested(dataset_id: str) -> None:
    """A DatasetError if `dataset_id` lies inside another dataset's directory, where `list` does not look (a dataset
    holds no datasets) and which deleting that dataset would delete too."""
    root, path = dataset_path(), dataset_path(dataset_id)
    for parent in path.parents:
        if parent == root or root not in parent.parents:
            return
        if (parent / "data").is_dir():
            outer = parent.relative_to(root).as_posix()
            raise DatasetError(f"dataset ID {dataset_id!r} lies inside the directory of dataset {outer} ({parent}): use "
                               f"an ID of its own, e.g. {outer.rsplit('/', 1)[0] + '/' if '/' in outer else ''}"
                               f"{path.name}")


def writer_lock(dataset_id: str) -> Path:
    """The lock file a writer of `dataset_id` holds (`writing`): hidden, beside the dataset's directory."""
    path = dataset_path(dataset_id)
    return path.with_name(f".{path.name}.writing")


@contextlib.contextmanager
def writing(dataset_id: str) -> Iterator[None]:
    """Hold the writer's lock of `dataset_id` (`hauwm.pid_lock` on `writer_lock`) while the block runs: two writers of
    one new ID both crashed, and the one refused by Minari deleted what the other had written. A second writer is
    refused (DatasetError), and `lock_holder` tells a dataset being written from one whose writer was killed."""
    with locked(writer_lock(dataset_id), lambda pid: DatasetError(
            f"dataset {dataset_id!r} is being written by another process (pid {pid}): wait for it to finish, or use "
            "another ID")):
        yield


def hauwm_metadata(dataset) -> dict[str, Any]:
    """Our settings stored with a dataset written here ({} for a dataset made elsewhere)."""
    return dict(dataset.storage.metadata.get(METADATA_KEY, {}))


# --- reading ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImageView:
    """Where the RGB frames are in a dataset's observations and how to turn them into [3, 64, 64]."""

    key: str | None  # entry of a Dict observation, None for a Box observation
    channels_first: bool  # CHW (else HWC)
    height: int
    width: int

    def frames(self, observations, where: str) -> np.ndarray:
        """observations of one episode -> uint8 [T+1, 3, 64, 64]; a DatasetError naming `where` (the dataset and
        the episode) where they are not frames of the observation space (the space is checked once, each episode
        here)."""
        images = np.asarray(observations if self.key is None else observations[self.key])
        frame = (3, self.height, self.width) if self.channels_first else (self.height, self.width, 3)
        if images.dtype != np.uint8 or images.shape[1:] != frame:
            name = "observations" if self.key is None else f"observations/{self.key}"
            raise DatasetError(f"{where}: {name} are {images.dtype} {list(images.shape)}, the dataset's observation "
                               f"space says uint8 [T+1, {', '.join(map(str, frame))}]: the episode was not written as "
                               "its dataset declares; write the dataset again")
        if self.channels_first:
            images = images.transpose(0, 2, 3, 1)  # [T+1, H, W, 3]
        if (self.height, self.width) != (IMAGE_SIZE, IMAGE_SIZE):
            size = (IMAGE_SIZE, IMAGE_SIZE)
            images = np.stack([cv2.resize(image, size, interpolation=cv2.INTER_AREA) for image in images])
        return np.ascontiguousarray(images.transpose(0, 3, 1, 2))


def image_view(dataset_id: str, space: gymnasium.Space) -> ImageView:
    """Find the RGB image in an observation space (Box HWC/CHW, or a Dict with an image entry)."""
    key = None
    if isinstance(space, gymnasium.spaces.Dict):
        images = [name for name, sub in space.spaces.items() if _rgb_layout(sub) is not None]
        named = [name for name in IMAGE_KEYS if name in images]
        if not named and len(images) != 1:
            entries = ", ".join(f"{name} {sub}" for name, sub in space.spaces.items())
            raise DatasetError(f"dataset {dataset_id!r}: its Dict observations ({entries}) hold "
                               f"{'no' if not images else 'several'} uint8 RGB image entries; HAUWM needs one "
                               f"(uint8, (H, W, 3) or (3, H, W)), named one of {', '.join(IMAGE_KEYS)}")
        key = named[0] if named else images[0]
        space = space.spaces[key]
    layout = _rgb_layout(space)
    if layout is None:
        raise DatasetError(f"dataset {dataset_id!r}: observations {space} are not RGB images (HAUWM needs uint8 "
                           f"frames shaped (H, W, 3) or (3, H, W), ideally {IMAGE_SIZE}x{IMAGE_SIZE}); collect pixel "
                           "observations, e.g. with `hauwm datasets collect`")
    channels_first, height, width = layout
    if min(height, width) < MIN_SIDE:
        raise DatasetError(f"dataset {dataset_id!r}: images are {height}x{width}, smaller than {MIN_SIDE}x{MIN_SIDE}: "
                           f"blown up to {IMAGE_SIZE}x{IMAGE_SIZE} they would hold no scene the world model knows; "
                           f"record the episodes at {IMAGE_SIZE}x{IMAGE_SIZE} (e.g. with `hauwm datasets collect`)")
    if max(height, width) > MAX_ASPECT * min(height, width):
        raise DatasetError(f"dataset {dataset_id!r}: images are {height}x{width}, too far from square to resize to "
                           f"{IMAGE_SIZE}x{IMAGE_SIZE} without distorting them (at most {MAX_ASPECT}:1); crop them to a "
                           "square first")
    return ImageView(key, channels_first, height, width)


def _rgb_layout(space: gymnasium.Space) -> tuple[bool, int, int] | None:
    """(channels_first, H, W) of a uint8 Box of RGB images, None for anything else."""
    if not isinstance(space, gymnasium.spaces.Box) or space.dtype != np.uint8 or len(space.shape) != 3:
        return None
    if space.shape[-1] == 3:
        return False, space.shape[0], space.shape[1]
    if space.shape[0] == 3:
        return True, space.shape[1], space.shape[2]
    return None


def check_actions(dataset_id: str, space: gymnasium.Space, task: str | None, action_dim: int | None) -> None:
    """Actions must be a flat Box in [-1, 1] (the agents' range) with the task's dimension."""
    if not isinstance(space, gymnasium.spaces.Box) or len(space.shape) != 1:
        raise DatasetError(f"dataset {dataset_id!r}: actions {space} are not a flat Box; HAUWM's agents act with "
                           "continuous vectors")
    if action_dim is not None and space.shape[0] != action_dim:
        raise DatasetError(f"dataset {dataset_id!r}: actions have {space.shape[0]} dimensions, "
                           f"{task or 'the task'} has {action_dim}; use a dataset collected on that task")
    if not (np.allclose(space.low, -1.0) and np.allclose(space.high, 1.0)):
        bounds = ", ".join(f"[{low:g}, {high:g}]" for low, high in zip(space.low, space.high))
        raise DatasetError(f"dataset {dataset_id!r}: action bounds per dimension are {bounds}; HAUWM's tasks act in "
                           "[-1, 1] in every dimension: rescale the actions into [-1, 1] and write the dataset again")


def has_success(dataset) -> bool:
    """Whether the dataset's episodes carry a per-step success flag (infos/success)."""
    written = hauwm_metadata(dataset).get("has_success")
    if written is not None:
        return bool(written)
    index = int(dataset.episode_indices[0])
    first = next_episode(dataset.storage.get_episodes([index]), dataset.id, index)
    return "success" in (first.get("infos") or {})


def next_episode(episodes: Iterator[dict], dataset_id: str, index: int) -> dict:
    """The next episode (`index`) Minari reads from a dataset's storage; a DatasetError where h5py cannot read it."""
    try:
        return next(episodes)
    except (KeyError, OSError, ValueError, RuntimeError) as error:  # a missing array or a damaged file
        raise DatasetError(f"dataset {dataset_id!r}: episode {index} could not be read ({type(error).__name__}: "
                           f"{error}); the dataset is damaged, write it again") from None


def iterate_episodes(dataset_id: str, task: str | None = None, action_dim: int | None = None,
                     progress: bool = True) -> Iterator[dict[str, np.ndarray]]:
    """The episodes of `dataset_id` one at a time, in the replay's layout (see the module docstring).

    Spaces are checked before the first episode is read: RGB images (resized to 64x64 when square-ish),
    actions in [-1, 1] with `action_dim` dimensions, and the task the dataset was collected on (when it
    says and `task` is given). Each episode's arrays are checked as it is read.
    """
    dataset = open_dataset(dataset_id)
    collected_on = hauwm_metadata(dataset).get("task")
    if task is not None and collected_on is not None and collected_on != task:  # before the spaces another task's fail
        raise DatasetError(f"dataset {dataset_id!r} was collected on {collected_on}, not {task}; "
                           "use a dataset of that task")
    view = image_view(dataset_id, dataset.observation_space)
    check_actions(dataset_id, dataset.action_space, task, action_dim)
    episodes = dataset.storage.get_episodes(dataset.episode_indices)
    bar = tqdm(total=dataset.total_episodes, unit=" episode", desc=f"reading {dataset_id}", disable=not progress,
               leave=False, dynamic_ncols=True)
    for index in dataset.episode_indices:
        raw = next_episode(episodes, dataset_id, index)
        yield _to_replay_layout(f"dataset {dataset_id!r}, episode {index}", raw, view, dataset.action_space.shape[0])
        bar.update()
    bar.close()


def load_episodes(dataset_id: str, task: str | None = None, action_dim: int | None = None,
                  progress: bool = True) -> list[dict[str, np.ndarray]]:
    """All episodes of `dataset_id` in memory (see `iterate_episodes`); raises DatasetError on a bad dataset."""
    return list(iterate_episodes(dataset_id, task, action_dim, progress))


def _to_replay_layout(where: str, raw: dict[str, Any], view: ImageView, action_dim: int) -> dict[str, np.ndarray]:
    """One episode as Minari stores it -> the replay's layout, each array checked; `where` names the episode."""
    rewards, actions = raw.get("rewards"), raw.get("actions")
    if actions is not None and len(actions) == 0:  # rewards and observations cut with them, as a rule
        raise DatasetError(f"{where} holds no steps (no actions): an episode cut short or never written; write the "
                           "dataset again without it")
    if rewards is None or len(rewards) == 0:
        raise DatasetError(f"{where} has no rewards; HAUWM's offline learners need the reward of every step")
    rewards = np.asarray(rewards, np.float32)
    if rewards.ndim == 2 and rewards.shape[1] == 1:  # [T, 1], as some writers store a scalar per step
        rewards = rewards[:, 0]
    if rewards.ndim != 1:
        raise DatasetError(f"{where}: rewards are shaped {list(rewards.shape)}; HAUWM needs one reward a step, [T]")
    if not np.all(np.isfinite(rewards)):
        raise DatasetError(f"{where}: rewards are missing (NaN or infinite); write the dataset with real rewards")
    actions = np.asarray(actions, np.float32)
    if actions.ndim != 2 or actions.shape[1] != action_dim:
        raise DatasetError(f"{where}: actions are {list(actions.shape)}, the dataset's action space says "
                           f"[T, {action_dim}]: the episode was not written as its dataset declares; write the dataset "
                           "again")
    if not np.all(np.isfinite(actions)):  # NaN would pass the bounds check below and train every weight into NaN
        raise DatasetError(f"{where}: actions hold NaN or infinite values; write the dataset with the actions taken")
    obs = view.frames(raw["observations"], where)
    steps = len(rewards)
    if len(actions) != steps or len(obs) != steps + 1:
        raise DatasetError(f"{where}: {len(obs)} observations, {len(actions)} actions and {steps} rewards; Minari "
                           "episodes hold T + 1 observations for T actions and rewards")
    if np.abs(actions).max(initial=0.0) > 1.0 + 1e-5:
        raise DatasetError(f"{where}: actions reach {np.abs(actions).max():.3g}, outside the declared [-1, 1]")
    zero = np.zeros(1, np.float32)
    success = (raw.get("infos") or {}).get("success")
    success = np.zeros(steps + 1) if success is None else np.asarray(success)
    if not (np.issubdtype(success.dtype, np.number) or success.dtype == bool):
        raise DatasetError(f"{where}: infos/success holds {success.dtype} values, not numbers (1 where the task was "
                           "solved, else 0); write the dataset again")
    success = success.astype(np.float32).reshape(-1)
    if len(success) == steps:  # a per-step flag without the reset entry
        success = np.concatenate([zero, success])
    if len(success) != steps + 1:
        raise DatasetError(f"{where}: infos/success holds {len(success)} entries for {steps} steps")
    terminations, truncations = (np.asarray(raw.get(key, ()), bool).reshape(-1)
                                 for key in ("terminations", "truncations"))
    if len(terminations) != steps or len(truncations) != steps:
        raise DatasetError(f"{where}: terminations hold {len(terminations)} entries, truncations {len(truncations)}, "
                           f"for {steps} steps; Minari episodes hold one of each a step: write the dataset again")
    ends = terminations | truncations
    if ends[:-1].any():
        raise DatasetError(f"{where}: it ends at step {np.argmax(ends) + 1} of {steps} (terminations or truncations "
                           "before its last step); a Minari episode ends at its first: split it there and write the "
                           "dataset again")
    terminal = np.zeros(steps + 1, np.float32)
    terminal[-1] = float(terminations[-1])
    return {"obs": obs, "action": np.concatenate([np.zeros((1, actions.shape[1]), np.float32), actions]),
            "reward": np.concatenate([zero, rewards]), "success": success, "terminal": terminal}


# --- writing ---------------------------------------------------------------------------------------


def _episode_buffer(episode: dict[str, np.ndarray]):
    """One episode in the replay's layout -> a minari.data_collector.EpisodeBuffer."""
    from minari.data_collector import EpisodeBuffer

    steps = len(episode["reward"]) - 1
    terminated = bool(episode.get("terminal", np.zeros(1))[-1])
    terminations = np.zeros(steps, bool)
    truncations = np.zeros(steps, bool)
    (terminations if terminated else truncations)[-1] = True
    infos = {"success": np.asarray(episode["success"], np.float32)} if "success" in episode else None
    return EpisodeBuffer(observations=np.ascontiguousarray(episode["obs"].transpose(0, 2, 3, 1)),  # [T+1, H, W, 3]
                         actions=np.asarray(episode["action"][1:], np.float32),
                         rewards=np.asarray(episode["reward"][1:], np.float64),
                         terminations=terminations, truncations=truncations, infos=infos)


class NoRoom(DatasetError):
    """The disk has no room for the next episode (`check_room`)."""


def check_room(path: Path, episode: dict[str, np.ndarray]) -> None:
    """Refuse (NoRoom) to write `episode` where the disk has less room than twice its raw bytes: HDF5 does not
    fail cleanly on a full disk (it crashed the process, leaving a damaged dataset behind), so it must never get there."""
    existing = next(parent for parent in (path, *path.parents) if parent.exists())
    needed, free = 2 * sum(value.nbytes for value in episode.values()), shutil.disk_usage(existing).free
    if free < needed:
        raise NoRoom(f"no room for the next episode under {existing} ({free / 1e6:.1f} MB free, {needed / 1e6:.1f} "
                     "MB needed): free some space or point MINARI_DATASETS_PATH elsewhere")


def write_dataset(dataset_id: str, episodes: Iterable[dict[str, np.ndarray]], metadata: dict[str, Any],
                  jpeg: bool = False, description: str | None = None, keep_finished: bool = False):
    """Write episodes (replay layout, obs [T+1, 3, 64, 64]) as a new Minari dataset; returns the MinariDataset.

    Episodes are appended one at a time as `episodes` yields them (a generator never holds the dataset in
    memory); if anything fails on the way, the partial dataset is deleted. With `keep_finished`, Ctrl-C while
    `episodes` makes the next episode keeps those written as the dataset and raises KeptOnInterrupt, and a disk with
    no room for the next episode keeps them too (a DatasetError that says so): collecting them may have taken hours;
    a merge, whose part would be a misleading dataset, does not keep them. Frames are
    stored raw (lossless) unless `jpeg`: Minari's JPEG (Pillow, quality 75, 4:2:0 chroma) is about 7x smaller but
    changes a 64x64 Meta-World frame by ~6 grey levels on average (docs/datasets.md). `metadata` (our settings: task,
    source, env settings) is stored under the "hauwm" key of the dataset's metadata.json; Table 4's random
    and expert returns become Minari's ref_min_score / ref_max_score where the task has them.
    """
    check_dataset_id(dataset_id)
    refuse_nested(dataset_id)
    with writing(dataset_id):
        return _write_dataset(dataset_id, episodes, metadata, jpeg, description, keep_finished)


def _write_dataset(dataset_id: str, episodes: Iterable[dict[str, np.ndarray]], metadata: dict[str, Any], jpeg: bool,
                   description: str | None, keep_finished: bool):
    """write_dataset, by the holder of the dataset's writer lock."""
    import minari

    from finetune.envs.references import REFERENCE_RETURNS

    path = dataset_path(dataset_id)

    def refuse_existing() -> None:
        if path.exists():
            raise DatasetError(f"dataset {dataset_id!r} already exists at {path}: use another ID (e.g. the next version "
                               "-vN) or delete that directory")

    refuse_existing()
    settings = {**metadata, "complete": False}  # until the end: a writer killed on the way leaves it marked unfinished
    dataset, with_success, stopped, made, no_room = None, None, False, False, None
    iterator = iter(episodes)
    try:
        while not stopped:
            try:
                if (episode := next(iterator, None)) is None:
                    break
                with signals_deferred():  # a signal in the middle of writing an episode waits for its end
                    check_room(path, episode)
                    if dataset is None:
                        refuse_existing()  # made meanwhile by a writer that takes no lock (not hauwm)
                        made = True
                        with_success = "success" in episode
                        observation_space = gymnasium.spaces.Box(0, 255, episode["obs"].shape[2:] + (3,), np.uint8)
                        action_space = gymnasium.spaces.Box(-1.0, 1.0, episode["action"].shape[1:], np.float32)
                        with warnings.catch_warnings():  # Minari's reminders to name an author, a code link, an env
                            warnings.simplefilter("ignore", UserWarning)
                            dataset = minari.create_dataset_from_buffers(
                                dataset_id, [], observation_space=observation_space, action_space=action_space,
                                algorithm_name=str(metadata.get("source", "unknown")), description=description,
                                jpeg_encoding=jpeg)
                        settings["has_success"] = with_success
                        dataset.storage.update_metadata({METADATA_KEY: settings})
                    if ("success" in episode) != with_success:
                        raise ValueError("episodes of one dataset must all have, or all lack, a success flag")
                    dataset.update_dataset_from_buffer([_episode_buffer(episode)])
            except (KeyboardInterrupt, NoRoom) as stop:
                if not (keep_finished and dataset is not None):
                    raise
                stopped = True  # between two episodes: those written make a whole dataset
                no_room = stop if isinstance(stop, NoRoom) else None
        if dataset is None:
            raise DatasetError(f"dataset {dataset_id!r}: no episodes to write")
        extra: dict[str, Any] = {METADATA_KEY: {**settings, "complete": True}}
        if metadata.get("task") in REFERENCE_RETURNS:
            extra["ref_min_score"], extra["ref_max_score"] = map(float, REFERENCE_RETURNS[metadata["task"]])
        try:
            with signals_deferred():
                dataset.storage.update_metadata(extra)  # a dataset without it would pass for one of unknown task
        except KeyboardInterrupt:  # after it: the dataset is whole
            if not keep_finished:
                raise
            stopped = True
    except BaseException as error:
        if made:
            shutil.rmtree(path, ignore_errors=True)
            if isinstance(error, KeyboardInterrupt):
                raise DeletedOnInterrupt(dataset_id) from None
            if isinstance(error, NoRoom):
                raise NoRoom(f"{error}; the part written is deleted") from None
        raise
    if no_room is not None:
        raise NoRoom(f"{no_room}; the {dataset.total_episodes} episodes finished are kept as {dataset_id}, a whole "
                     "dataset") from None
    if stopped:
        raise KeptOnInterrupt(dataset)
    return dataset


def refuse_replayed(source_ids: list[str], settings: list[dict[str, Any]]) -> None:
    """A DatasetError if two datasets were collected alike (the scripted expert or the random policy, the same seed and
    settings): the seeded envs and policies play the same episodes again, which a merge would hold twice."""
    recipes: dict[str, str] = {}
    for dataset_id, written in zip(source_ids, settings):
        if written.get("source") not in ("expert", "random") or "seed" not in written:
            continue  # an agent (its run's checkpoint.pt may have been trained on since), a replay, a merge, elsewhere
        recipe = json.dumps({key: value for key, value in written.items() if key not in ("complete", "has_success")},
                            sort_keys=True)
        if (first := recipes.setdefault(recipe, dataset_id)) != dataset_id:
            raise DatasetError(f"{first} and {dataset_id} were collected alike ({written['source']}, seed "
                               f"{written['seed']}, the same settings): their first episodes are the same ones; "
                               f"collect {dataset_id} again with another --seed")


def merged_parts(dataset_id: str, settings: dict[str, Any]) -> list[str]:
    """The datasets whose episodes `dataset_id` holds: itself, or for a merge the parts it records (every dataset it
    was merged from, through merges of merges; a merge written before "parts" records its direct sources)."""
    if settings.get("source") != "merge":
        return [dataset_id]
    return list(settings.get("parts", settings.get("merged", [dataset_id])))


def refuse_overlapping(source_ids: list[str], settings: list[dict[str, Any]]) -> list[str]:
    """The parts of a merge of `source_ids` (`merged_parts`), or a DatasetError if two sources hold the same part's
    episodes (a merge and one of its parts, two merges sharing one)."""
    holder: dict[str, str] = {}  # part -> the source holding it
    for dataset_id, written in zip(source_ids, settings):
        for part in merged_parts(dataset_id, written):
            if (first := holder.setdefault(part, dataset_id)) != dataset_id:
                raise DatasetError(f"the episodes of {part} are in {first} and in {dataset_id}: the merge would hold "
                                   "them twice, over-weighting them in every batch; leave one of the two out, or merge "
                                   f"the parts of {first if first != part else dataset_id} that are not in the other")
    return list(holder)


def merge_datasets(source_ids: list[str], out_id: str, progress: bool = True):
    """Concatenate the episodes of `source_ids` into a new dataset `out_id` (e.g. medium replay + expert).

    The sources must agree on the task and the env settings they were collected with (where they say; the
    new dataset records what those that say agree on, also when a source made elsewhere says nothing); the
    new dataset is JPEG-encoded only if every source is (JPEG frames are decoded and encoded again), and keeps
    success flags only if every source has them.
    """
    if len(source_ids) < 2:
        raise DatasetError("merge needs at least two datasets")
    if repeated := [dataset_id for dataset_id in dict.fromkeys(source_ids) if source_ids.count(dataset_id) > 1]:
        raise DatasetError(f"{repeated[0]} is named {source_ids.count(repeated[0])} times: the merge would hold each of its "
                           "episodes that often, over-weighting them in every batch; name each dataset once")
    datasets = [open_dataset(dataset_id) for dataset_id in source_ids]
    settings = [hauwm_metadata(dataset) for dataset in datasets]
    parts = refuse_overlapping(source_ids, settings)
    refuse_replayed(source_ids, settings)
    agreed = {}  # what the sources that record it agree on, kept even where a source made elsewhere records nothing
    for key in ("task", "action_repeat", "fast_render", "image_size"):  # what offline RL and imitation check
        values = {s[key] for s in settings if key in s}
        if len(values) == 1:
            agreed[key] = values.pop()
        if len(values) > 1:
            described = ", ".join(f"{i} has {s.get(key)!r}" for i, s in zip(source_ids, settings))
            raise DatasetError(f"cannot merge datasets with different {key}: {described}; merge datasets collected "
                               f"with the same {key}")
    action_dims = {dataset.action_space.shape for dataset in datasets}
    if len(action_dims) > 1:
        raise DatasetError(f"cannot merge datasets with different action shapes {sorted(action_dims)}: "
                           f"{', '.join(source_ids)}")
    keep_success = all(has_success(dataset) for dataset in datasets)
    jpeg = all(dataset.storage.jpeg_encoding for dataset in datasets)

    def episodes() -> Iterator[dict[str, np.ndarray]]:
        for dataset_id in source_ids:
            for episode in iterate_episodes(dataset_id, progress=progress):
                if not keep_success:
                    episode.pop("success")
                yield episode

    shared = {key: value for key, value in settings[0].items() if all(s.get(key) == value for s in settings[1:])}
    merged = {**shared, **agreed, "source": "merge", "merged": list(source_ids), "parts": parts}
    dataset = write_dataset(out_id, episodes(), merged, jpeg=jpeg, description=f"merge of {', '.join(source_ids)}")
    dataset.storage.update_metadata({"combined_datasets": list(source_ids)})
    return dataset
