"""Episode replay: every finished episode is kept in memory and written to disk as one `.npz`.

An episode of T agent steps holds T + 1 entries, aligned as in Dreamer: entry t is the observation o_t,
the action a_{t−1} that led to it and the reward r_t received with it (entry 0 has a zero action and
zero reward). Training batches are random windows of `length` consecutive entries from one episode
(32 × 50 in the paper's Table 3), so a window never crosses an episode boundary. The capacity
(10^6 steps) is enforced by dropping the oldest episodes from memory; files stay on disk, and a resumed
run reloads the newest episodes that fit. The files are numbered in the order the run stored them; a run resumes
from its checkpoint, so the files numbered past the checkpoint's count (written by a run stopped before its next
checkpoint) are deleted at the reload: the resumed run collects those episodes again.
"""

from __future__ import annotations

import sys
import zipfile
from collections import deque
from pathlib import Path

import numpy as np

from hauwm.atomic import written_whole
from model.networks import IMAGE_SHAPE

KEYS = ("obs", "action", "reward")


def episode_files(directory: Path) -> list[Path]:
    """The episode files a replay directory holds, oldest first, by their number (from the millionth on it has 7
    digits: sorted by name, it came before the 100,001st); half-written ones, `.NAME.partial`, left out, and
    `NAME.tmp.npz`, as runs before 2026-11-27 named them. A file not named as a run names them is a ReplayError."""
    return sorted((p for p in Path(directory).glob("*.npz") if not p.name.endswith(".tmp.npz")), key=episode_name)


class ReplayError(RuntimeError):
    pass


def episode_name(path: Path) -> tuple[int, int]:
    """(number, steps) of an episode file `NNNNNN-STEPS.npz`: its place in the order the run stored its episodes,
    and its agent steps."""
    number, _, steps = path.stem.partition("-")
    if not (number.isdigit() and steps.isdigit()):
        raise ReplayError(f"{path}: not the name of a replay episode (NNNNNN-STEPS.npz, as a run writes them): move "
                          f"it out of {path.parent}")
    return int(number), int(steps)


def read_episode(path: Path, action_dim: int | None = None) -> dict[str, np.ndarray]:
    """One episode file: obs uint8 [T+1, 3, 64, 64], action float32 [T+1, A], reward float32 [T+1], A = `action_dim`
    where given (a file of another task or run would stop the first batch that draws it in a numpy error)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            episode = {key: data[key] for key in KEYS}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as err:
        raise ReplayError(f"{path}: this replay episode cannot be read ({err}); it is damaged: restore it, or delete "
                          "it and the run goes on without that episode") from None
    if problem := layout_problem(episode, action_dim):
        raise ReplayError(f"{path}: {problem}: an episode of another run or task? move it out of {path.parent}")
    return episode


def layout_problem(episode: dict[str, np.ndarray], action_dim: int | None = None) -> str | None:
    """Why `episode` cannot join a replay of the world model's frames (IMAGE_SHAPE) and actions of `action_dim`
    dimensions, or None when it can."""
    obs, action, reward = (episode[key] for key in KEYS)
    if not (obs.dtype == np.uint8 and obs.ndim == 4 and action.ndim == 2 and reward.ndim == 1
            and len(obs) == len(action) == len(reward)):
        return (f"it holds obs {obs.dtype} {list(obs.shape)}, action {list(action.shape)} and reward {list(reward.shape)}, "
                "not a replay episode's obs uint8 [T+1, 3, H, W], action [T+1, A] and reward [T+1]")
    if obs.shape[1:] != IMAGE_SHAPE:
        return f"its frames are {list(obs.shape[1:])}, the world model's {list(IMAGE_SHAPE)}"
    if action_dim is not None and action.shape[1] != action_dim:
        return f"its actions have {action.shape[1]} dimensions, the run's {action_dim}"
    return None


class Replay:
    def __init__(self, directory: Path | None, capacity: int, rng: np.random.Generator):
        self.directory = Path(directory) if directory is not None else None
        self.capacity = capacity
        self.rng = rng
        self.episodes: deque[dict[str, np.ndarray]] = deque()
        self.num_steps = 0  # agent steps held in memory
        self.num_saved = 0  # episodes ever written (numbers the files)

    def add(self, episode: dict[str, np.ndarray]) -> None:
        """Store one finished episode: obs uint8 [T+1, 3, H, W], action float32 [T+1, A], reward float32 [T+1]."""
        episode = {key: np.asarray(episode[key]) for key in KEYS}
        length = len(episode["reward"]) - 1
        if self.directory is not None:
            self.directory.mkdir(parents=True, exist_ok=True)
            with written_whole(self.directory / f"{self.num_saved:06d}-{length}.npz") as partial, \
                    open(partial, "wb") as file:
                np.savez_compressed(file, **episode)
        self.num_saved += 1
        self._keep(episode)

    def load(self, stored: int, action_dim: int | None = None) -> int:
        """Reload the newest of the first `stored` episodes on disk (those the run's checkpoint counts) that fit the
        capacity, and at least the newest one, as `_keep` holds them (for resume), all of the run's frame size and
        `action_dim`; returns how many. Episodes numbered `stored` or later are deleted, with a note."""
        self.num_saved = stored  # a deleted file leaves a gap in the numbers; the next file is numbered by the count
        if self.directory is None or not self.directory.is_dir():
            return 0
        files = [(path, *episode_name(path)) for path in episode_files(self.directory)]
        if after := [path for path, number, _ in files if number >= stored]:
            print(f"note: {self.directory}: {len(after)} episodes stored after the checkpoint this run starts from "
                  "deleted; the run collects them again", file=sys.stderr)
            for path in after:
                path.unlink()
        chosen, steps = [], 0
        for path, number, length in reversed(files):
            if number >= stored:
                continue
            if chosen and steps + length > self.capacity:  # the newest stays, as in _keep
                break
            chosen.append(path)
            steps += length
        for path in reversed(chosen):
            self._keep(read_episode(path, action_dim))
        return len(chosen)

    def _keep(self, episode: dict[str, np.ndarray]) -> None:
        self.episodes.append(episode)
        self.num_steps += len(episode["reward"]) - 1
        while self.num_steps > self.capacity and len(self.episodes) > 1:
            self.num_steps -= len(self.episodes.popleft()["reward"]) - 1

    def ready(self, length: int) -> bool:
        return any(len(ep["reward"]) >= length for ep in self.episodes)

    def sample(self, batch_size: int, length: int) -> dict[str, np.ndarray]:
        """`batch_size` windows of `length` entries, each window start uniform over all valid starts."""
        starts_per_episode = np.array([max(len(ep["reward"]) - length + 1, 0) for ep in self.episodes])
        if starts_per_episode.sum() == 0:
            raise ValueError(f"no episode in the replay holds {length} frames ({length - 1} steps): lower seq_len or "
                             "raise time_limit")
        picks = self.rng.choice(starts_per_episode.sum(), size=batch_size)
        offsets = np.cumsum(starts_per_episode) - starts_per_episode
        batch = {key: [] for key in KEYS}
        for pick in picks:
            index = int(np.searchsorted(offsets, pick, side="right") - 1)
            start = pick - offsets[index]
            for key in KEYS:
                batch[key].append(self.episodes[index][key][start:start + length])
        return {key: np.stack(values) for key, values in batch.items()}  # obs [B, L, 3, H, W], ...
