"""`hauwm datasets`: collect, merge, inspect and list Minari datasets of 64x64 pixel episodes (offline RL).

    hauwm datasets collect --task metaworld_drawer_close --policy expert --episodes 50 --dataset-id hauwm/drawer_close-expert-v0
    hauwm datasets collect --task metaworld_dial_turn --policy expert --action-noise 0.5 --episodes 50 --dataset-id hauwm/dial_turn-noisy-v0
    hauwm datasets collect --task metaworld_drawer_close --policy random --episodes 50 --dataset-id hauwm/drawer_close-random-v0
    hauwm datasets collect --policy agent --checkpoint RUNDIR [--best] [--pretrained DIR] --episodes 50 --dataset-id hauwm/drawer_close-agent-v0
    hauwm datasets collect --from-run RUNDIR --dataset-id hauwm/drawer_close-medium_replay-v0
    hauwm datasets merge hauwm/drawer_close-medium_replay-v0 hauwm/drawer_close-expert-v0 --out hauwm/drawer_close-medexp-v0
    hauwm datasets inspect hauwm/drawer_close-expert-v0
    hauwm datasets list

Datasets live under $MINARI_DATASETS_PATH (Minari's own variable; default ~/.minari/datasets).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hauwm.termination import interrupted_once, sigterm_as_interrupt, stopped_by

# what --set may change: finetune.config.ENV_SETTINGS, repeated here so that `--help` does not import torch (a test
# checks they agree)
ENV_SETTINGS = ("action_repeat", "time_limit", "fast_render")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(allow_abbrev=False, prog="hauwm datasets", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = p.add_subparsers(dest="command", required=True)

    c = commands.add_parser("collect", allow_abbrev=False,
                            help="play episodes (or take a run's replay) and write them as a dataset")
    c.add_argument("--dataset-id", required=True, help="new Minari ID, (namespace/)name-vN, e.g. hauwm/drawer_close-expert-v0")
    c.add_argument("--task", help="e.g. metaworld_drawer_close (with --policy agent or --from-run: the run's task)")
    c.add_argument("--policy", choices=("expert", "random", "agent"),
                   help="expert: Meta-World's scripted policy; random: uniform actions; agent: a run's trained agent")
    c.add_argument("--from-run", metavar="RUNDIR", help="take the replay episodes of a `hauwm finetune` run instead")
    c.add_argument("--episodes", type=int, help="episodes to play (with --from-run: at most this many, oldest first)")
    c.add_argument("--action-noise", type=float, default=0.0, metavar="SIGMA",
                   help="expert: add N(0, SIGMA^2) to every action dimension, clipped to [-1, 1] (barely hurts the "
                        "drawer-close expert: for medium data use --policy agent or --from-run, docs/datasets.md)")
    c.add_argument("--checkpoint", metavar="RUNDIR", help="agent: the `hauwm finetune` run directory to play")
    c.add_argument("--best", action="store_true", help="agent: play the run's best.pt (its best evaluation's agent) "
                                                       "instead of its last checkpoint")
    c.add_argument("--pretrained", help="agent: the export the run was trained on (not needed for agent=scratch runs)")
    c.add_argument("--sample", action="store_true", help="agent: sample actions instead of the actor's mode")
    c.add_argument("--device", default="auto", help="agent: auto, cpu or cuda")
    c.add_argument("--seed", type=int, default=0, help="env seed (initial states, goals) and action-noise seed")
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help=f"env setting, one of {', '.join(ENV_SETTINGS)}; e.g. --set fast_render=true --set time_limit=100")
    c.add_argument("--jpeg", action="store_true", help="store frames as Minari's JPEG (quality 75, 4:2:0): about 7x "
                   "smaller than the default raw frames, but lossy (docs/datasets.md)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar (for logs)")

    m = commands.add_parser("merge", allow_abbrev=False,
                            help="concatenate datasets into a new one (e.g. medium replay + expert)")
    m.add_argument("sources", nargs="+", metavar="ID", help="datasets to merge, in this order")
    m.add_argument("--out", required=True, metavar="ID", help="the new dataset's ID")
    m.add_argument("--no-progress", action="store_true")

    i = commands.add_parser("inspect", allow_abbrev=False,
                            help="episodes, steps, returns, normalised return, success rate of a dataset")
    i.add_argument("dataset_id", metavar="ID")
    i.add_argument("--task", help="for a dataset made elsewhere: its task, one of the paper's ten (its action size is "
                                  "checked; DMC and Meta-World returns are normalised with Table 4's references)")
    i.add_argument("--no-progress", action="store_true")

    commands.add_parser("list", allow_abbrev=False, help="the datasets under $MINARI_DATASETS_PATH")
    return p


def env_settings(pairs: list[str]) -> dict[str, object]:
    """--set KEY=VALUE pairs -> make_env keyword arguments, checked."""
    from finetune.config import parse_override
    from finetune.datasets.minari_io import DatasetError

    settings = dict(parse_override(pair) for pair in pairs)
    unknown = sorted(set(settings) - set(ENV_SETTINGS))
    if unknown:
        raise DatasetError(f"--set {', '.join(unknown)}: not an env setting; the settings are {', '.join(ENV_SETTINGS)}")
    for key, value in settings.items():
        wrong = (not isinstance(value, bool)) if key == "fast_render" else (type(value) is not int or value < 1)
        if wrong:
            raise DatasetError(f"--set {key}={value!r}: {key} must be "
                               + ("true or false" if key == "fast_render" else "a whole number >= 1"))
    return settings


def tracked(episodes: Iterable[dict[str, np.ndarray]], summary, total: int, desc: str, progress: bool) -> Iterator[dict[str, np.ndarray]]:
    """Pass episodes through, adding each to `summary` and showing a progress bar with the last return."""
    with tqdm(total=total, unit=" episode", desc=desc, disable=not progress, dynamic_ncols=True) as bar:
        for episode in episodes:
            summary.add(episode)
            postfix = {"return": f"{summary.returns[-1]:.1f}"}
            if summary.successes:
                postfix["success_rate"] = f"{np.mean(summary.successes):.0%}"
            bar.set_postfix(postfix)
            bar.update()
            yield episode


def collect(args: argparse.Namespace) -> None:
    from finetune.envs import EnvSettingError, make_env

    from finetune.datasets.minari_io import IMAGE_SIZE, DatasetError, dataset_path, write_dataset
    from finetune.datasets.sources import (ExpertPolicy, RandomPolicy, load_agent_policy, policy_episodes,
                                           replay_episodes, run_config)
    from finetune.datasets.summary import Summary

    if args.episodes is not None and args.episodes < 1:
        raise DatasetError(f"--episodes must be >= 1, got {args.episodes}")
    if not 0 <= args.seed < 2**32:
        raise DatasetError(f"--seed must be a whole number in 0..2^32-1, got {args.seed}")
    if not (math.isfinite(args.action_noise) and args.action_noise >= 0):
        raise DatasetError(f"--action-noise is a standard deviation, a number >= 0; got {args.action_noise}")
    if args.action_noise and args.policy != "expert":
        raise DatasetError(f"--action-noise is added to the scripted expert's actions (--policy expert), not to "
                           f"{'the replay of --from-run' if args.from_run else f'--policy {args.policy}'}; drop it")
    if args.best and args.policy != "agent":
        raise DatasetError("--best picks which checkpoint of a run --policy agent plays; drop it, or add --policy agent "
                           "--checkpoint RUNDIR")
    if args.policy != "agent" and (unused := [flag for flag, given in (("--checkpoint", args.checkpoint),
                                                                       ("--pretrained", args.pretrained),
                                                                       ("--sample", args.sample)) if given]):
        raise DatasetError(f"{unused[0]} is for --policy agent (a run's trained agent), not "
                           f"{'--from-run' if args.from_run else f'--policy {args.policy}'}; drop it")
    if args.from_run and args.seed != 0:  # the episodes are the replay's, played already
        raise DatasetError("--from-run takes the run's replay as it is, which no seed changes: drop --seed")
    overrides = env_settings(args.set)
    if args.from_run:
        if args.policy or overrides:
            raise DatasetError("--from-run takes the run's replay as it is: drop --policy and --set")
        metadata, total, episodes = replay_episodes(args.from_run, args.episodes)
        if args.task and args.task != metadata["task"]:
            raise DatasetError(f"--from-run {args.from_run} trained on {metadata['task']}, not --task {args.task}")
        metadata.update(source="replay", image_size=IMAGE_SIZE)
    else:
        if args.policy is None or args.episodes is None:
            raise DatasetError("collect needs --policy and --episodes (or --from-run RUNDIR)")
        settings = {}
        if args.policy == "agent":
            if not args.checkpoint:
                raise DatasetError("--policy agent needs --checkpoint RUNDIR (a `hauwm finetune` run directory)")
            run = run_config(args.checkpoint)
            if args.task and args.task != run.task:
                raise DatasetError(f"--checkpoint {args.checkpoint} trained on {run.task}, not --task {args.task}")
            args.task = run.task
            settings = run.env_settings
            if overrides.get("action_repeat", run.action_repeat) != run.action_repeat:
                raise DatasetError(f"--set action_repeat={overrides['action_repeat']}: the agent of {args.checkpoint} "
                                   f"was trained acting every {run.action_repeat} frames (its action_repeat); played "
                                   f"every {overrides['action_repeat']} its actions mean something else: drop it")
        if not args.task:
            raise DatasetError(f"--policy {args.policy} needs --task, e.g. --task metaworld_drawer_close")
        settings.update(overrides)
        try:
            env = make_env(args.task, seed=args.seed, image_size=IMAGE_SIZE, **settings)
        except EnvSettingError as error:  # unknown task, time limit beyond the suite's episodes
            raise DatasetError(f"--task {args.task}: {error}") from None
        metadata = {"task": args.task, "source": args.policy, "seed": args.seed, "action_repeat": env.action_repeat,
                    "time_limit": env.time_limit, "fast_render": bool(settings.get("fast_render", False)),
                    "image_size": IMAGE_SIZE}
        if args.policy == "expert":
            policy = ExpertPolicy(env, args.action_noise, args.seed)
            metadata["action_noise"] = args.action_noise
        elif args.policy == "random":
            policy = RandomPolicy(env.action_space)
        else:
            from finetune.run_dir import BEST, CHECKPOINT

            checkpoint = BEST if args.best else CHECKPOINT
            policy = load_agent_policy(args.checkpoint, args.pretrained, args.device, args.sample,
                                       env.action_space.shape[0], checkpoint)
            metadata.update(checkpoint=str(Path(args.checkpoint) / checkpoint), actions="sample" if args.sample else "mode")
        total, episodes = args.episodes, policy_episodes(env, policy, args.episodes)

    summary = Summary(metadata["task"], metadata.get("action_repeat"))
    start = time.perf_counter()
    description = f"{metadata['source']} episodes of {metadata['task']} (hauwm datasets collect)"
    dataset = write_dataset(args.dataset_id, tracked(episodes, summary, total, args.dataset_id, not args.no_progress),
                            metadata, jpeg=args.jpeg, description=description, keep_finished=True)
    minutes = (time.perf_counter() - start) / 60
    print(f"wrote {args.dataset_id} to {dataset_path(args.dataset_id)} ({dataset.storage.get_size():.1f} MB, "
          f"{'JPEG' if args.jpeg else 'raw'} frames, {len(summary.returns) / minutes:.1f} episodes/min)")
    print("\n".join(summary.lines()))


def inspect(args: argparse.Namespace) -> None:
    from finetune.datasets.minari_io import (DatasetError, dataset_path, has_success, hauwm_metadata, iterate_episodes,
                                            open_dataset)
    from finetune.datasets.summary import Summary
    from finetune.envs import PAPER_TASKS

    dataset = open_dataset(args.dataset_id)
    settings = hauwm_metadata(dataset)
    if args.task and settings.get("task") not in (None, args.task):
        raise DatasetError(f"{args.dataset_id} records its task, {settings['task']}: --task is for a dataset made "
                           "elsewhere that records none; leave it out")
    if args.task and args.task not in PAPER_TASKS:
        raise DatasetError(f"--task {args.task} is not one of the paper's tasks: {', '.join(PAPER_TASKS)}")
    action_dim = None
    if args.task:  # a dataset made elsewhere: its actions must fit the task it is said to be of
        from finetune.envs import make_env

        with contextlib.closing(make_env(args.task, seed=0)) as env:
            action_dim = env.action_space.shape[0]
    task = args.task or settings.get("task")
    with_success = has_success(dataset)
    summary = Summary(task, settings.get("action_repeat"))
    for episode in iterate_episodes(args.dataset_id, task, action_dim, progress=not args.no_progress):
        if not with_success:
            episode.pop("success")
        summary.add(episode)
    frames = summary.stats()["steps"] + len(summary.returns)
    size_mb = dataset.storage.get_size()
    print(f"dataset         {args.dataset_id} ({dataset_path(args.dataset_id)})")
    print(f"task            {task or 'unknown'}")
    print(f"source          {settings.get('source', 'made elsewhere')}"
          + "".join(f", {k} {v}" for k, v in settings.items() if k not in ("task", "source", "has_success", "complete")))
    print(f"observations    {dataset.observation_space}")
    print(f"actions         {dataset.action_space}")
    print(f"storage         {'JPEG' if dataset.storage.jpeg_encoding else 'raw'} frames, {size_mb:.1f} MB, "
          f"{size_mb * 1e6 / frames:.0f} bytes per frame")
    print("\n".join(summary.lines()))


def list_(args: argparse.Namespace) -> None:
    from finetune.datasets.minari_io import METADATA_KEY, datasets_root, scan_datasets, unfinished, unfinished_message

    datasets, notes = scan_datasets()
    for dataset_id in [dataset_id for dataset_id, metadata in datasets.items() if unfinished(metadata)]:
        print(unfinished_message(dataset_id, datasets.pop(dataset_id).get("total_episodes", 0)), file=sys.stderr)
    for note in notes.values():
        print(note, file=sys.stderr)
    if not datasets:
        print(f"no datasets under {datasets_root()} (MINARI_DATASETS_PATH); make one with `hauwm datasets collect`")
        return
    print(f"{'ID':<44} {'task':<26} {'source':<8} {'episodes':>8} {'steps':>9} {'MB':>8}")
    for dataset_id, metadata in datasets.items():
        settings = metadata.get(METADATA_KEY, {})
        print(f"{dataset_id:<44} {settings.get('task', '?'):<26} {settings.get('source', '?'):<8} "
              f"{metadata.get('total_episodes', 0):>8} {metadata.get('total_steps', 0):>9} "
              f"{metadata.get('dataset_size', 0):>8.1f}")


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(sys.argv[1:] if argv is None else argv)
    with interrupted_once(), sigterm_as_interrupt() as terminated:
        try:
            return run_command(args, terminated)
        except KeyboardInterrupt:  # while run_command imported what it runs (torch: seconds), before anything began
            stopped, status = stopped_by(terminated)
            print(f"hauwm datasets: {stopped}; nothing was written", file=sys.stderr)
            return status


def run_command(args: argparse.Namespace, terminated: list[int]) -> int:
    from finetune.agent import DivergedError
    from finetune.datasets.minari_io import DatasetError, DeletedOnInterrupt, KeptOnInterrupt
    from finetune.pretrained import PretrainedError
    from finetune.replay import ReplayError
    from finetune.config import FinetuneError
    from model.config import ConfigError

    try:
        if args.command == "collect":
            collect(args)
        elif args.command == "merge":
            from finetune.datasets.minari_io import merge_datasets

            dataset = merge_datasets(args.sources, args.out, progress=not args.no_progress)
            print(f"wrote {args.out}: {dataset.total_episodes} episodes, {dataset.total_steps} steps "
                  f"from {', '.join(args.sources)}")
        elif args.command == "inspect":
            inspect(args)
        else:
            list_(args)
    except (DatasetError, ConfigError, DivergedError, FinetuneError, PretrainedError, ReplayError) as error:
        print(f"hauwm datasets: error: {error}", file=sys.stderr)
        return 2
    except KeptOnInterrupt as kept:
        stopped, status = stopped_by(terminated)
        print(f"hauwm datasets: {stopped}; the {kept.dataset.total_episodes} episodes finished are kept as "
              f"{args.dataset_id}: collect more under another ID, with another --seed (the same seed plays the same episodes "
              "again), and `hauwm datasets merge` them", file=sys.stderr)
        return status
    except DeletedOnInterrupt as deleted:
        stopped, status = stopped_by(terminated)
        print(f"hauwm datasets: {stopped}; the part of {deleted.dataset_id} written was deleted", file=sys.stderr)
        return status
    except KeyboardInterrupt:  # before a dataset was begun (a collect's first episode): nothing was written
        stopped, status = stopped_by(terminated)
        print(f"hauwm datasets: {stopped}; nothing was written", file=sys.stderr)
        return status
    return 0


if __name__ == "__main__":
    sys.exit(main())
