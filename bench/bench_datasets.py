"""Offline datasets: collection speed, bytes per frame raw vs JPEG, and the returns of each source.

    python bench/bench_datasets.py                                   # drawer close, 5 full episodes per source
    python bench/bench_datasets.py --task metaworld_dial_turn --episodes 3 --noise 0.5

Plays `--episodes` full-length episodes (fast rendering, seed 0) with Meta-World's scripted expert,
the expert with N(0, noise^2) action noise and uniform random actions, timing the episodes
(episodes/min, what `hauwm datasets collect` spends besides writing); writes the expert's episodes as
a raw and as a JPEG Minari dataset in a temporary MINARI_DATASETS_PATH (bytes per frame on disk,
write and read times), and measures what JPEG changes: the mean absolute error and PSNR of the decoded
frames, once and after a second encode (a merge of JPEG datasets).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from finetune.envs import make_env  # noqa: E402  (sets MUJOCO_GL before mujoco loads)

from bench.machine import describe_machine  # noqa: E402
from finetune.datasets import load_episodes, write_dataset  # noqa: E402
from finetune.datasets.sources import ExpertPolicy, RandomPolicy  # noqa: E402
from finetune.datasets.summary import Summary  # noqa: E402
from finetune.rollout import play_episode  # noqa: E402


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b) ** 2)
    return float(10 * np.log10(255.0**2 / mse)) if mse > 0 else float("inf")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="metaworld_drawer_close")
    parser.add_argument("--episodes", type=int, default=5, help="full-length episodes per source")
    parser.add_argument("--noise", type=float, default=0.5, help="action noise of the medium source")
    args = parser.parse_args()
    print(f"machine: {describe_machine()}")
    print(f"settings: {args.task}, {args.episodes} episodes per source, fast_render, seed 0, MUJOCO_GL="
          f"{os.environ['MUJOCO_GL']}; minari {version('minari')}, h5py {version('h5py')}, Pillow {version('pillow')}")

    env = make_env(args.task, seed=0, fast_render=True)
    sources = {"expert": ExpertPolicy(env, 0.0, 0), f"expert+noise {args.noise}": ExpertPolicy(env, args.noise, 0),
               "random": RandomPolicy(env.action_space)}
    expert_episodes = []
    print(f"\n{'source':<18} {'episodes/min':>12} {'return mean':>11} {'min':>8} {'max':>8} {'normalised':>10} {'success':>8}")
    for name, policy in sources.items():
        summary = Summary(args.task)
        start = time.perf_counter()
        for _ in range(args.episodes):
            episode = play_episode(env, policy)
            summary.add(episode)
            if name == "expert":
                expert_episodes.append(episode)
        per_minute = args.episodes / (time.perf_counter() - start) * 60
        s = summary.stats()
        print(f"{name:<18} {per_minute:>12.1f} {s['return_mean']:>11.1f} {s['return_min']:>8.1f} {s['return_max']:>8.1f} "
              f"{s.get('normalised_return', float('nan')):>10.3f} {s.get('success_rate', float('nan')):>8.0%}")
    env.close()

    frames = np.concatenate([episode["obs"] for episode in expert_episodes])  # [N, 3, 64, 64]
    with tempfile.TemporaryDirectory() as root:
        os.environ["MINARI_DATASETS_PATH"] = root
        print(f"\n{'storage':<8} {'bytes/frame':>11} {'write s':>8} {'read s':>7} {'mean |error|':>12} {'PSNR dB':>8}")
        decoded = {}
        for jpeg in (False, True):
            dataset_id = f"bench/{'jpeg' if jpeg else 'raw'}-v0"
            start = time.perf_counter()
            dataset = write_dataset(dataset_id, iter(expert_episodes), {"task": args.task, "source": "expert"}, jpeg=jpeg)
            written = time.perf_counter() - start
            start = time.perf_counter()
            decoded[jpeg] = load_episodes(dataset_id, progress=False)
            read = time.perf_counter() - start
            size = sum(f.stat().st_size for f in dataset.storage.data_path.glob("*"))
            loaded = np.concatenate([e["obs"] for e in decoded[jpeg]])
            print(f"{'JPEG' if jpeg else 'raw':<8} {size / len(frames):>11.0f} {written:>8.1f} {read:>7.1f} "
                  f"{np.abs(loaded.astype(int) - frames).mean():>12.2f} {psnr(loaded, frames):>8.1f}")
        write_dataset("bench/jpeg2-v0", iter(decoded[True]), {"task": args.task}, jpeg=True)
        again = np.concatenate([e["obs"] for e in load_episodes("bench/jpeg2-v0", progress=False)])
        print(f"{'JPEG x2':<8} {'':>11} {'':>8} {'':>7} {np.abs(again.astype(int) - frames).mean():>12.2f} "
              f"{psnr(again, frames):>8.1f}   (decoded and encoded again, as a merge of JPEG datasets does)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
