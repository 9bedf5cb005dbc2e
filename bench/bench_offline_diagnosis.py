"""Why an offline run fails: does eq. 6's penalty see where its actor leaves the data? (CPU, a minute)

    python bench/bench_offline_diagnosis.py RUNDIR --pretrained DIR [--heldout ID]

Reads the run's checkpoint (RUNDIR/checkpoint.pt, config.yaml) and, on windows of its training dataset and
of a held-out dataset of the same task (default: bench_downstream's 10 expert demonstrations, episodes the
run never saw), prints:

1. the world model's losses on both (is the model overfitting the fixed dataset?);
2. on the held-out windows, the actor's actions (its mode at each posterior state) against the actions
   recorded there: mean |a_π − a_data| and how often |a_π| ≥ 0.99;
3. the penalty u (the run's `penalty`, finetune/penalty.py) of one imagined step from the same posterior
   states with the recorded actions and with the actor's: if u does not grow where the actor deviates,
   eq. 6 cannot hold it near the data, whatever λ;
4. from each window's first posterior state, L − 1 steps imagined along the recorded actions and along the
   actor's mode: the reward head's mean reward per step on each, beside the recorded one. A world model
   that rates an actor that fails in the environment above the recorded (expert) actions is being
   exploited: its reward head overestimates off the data.

`--checkpoint best.pt` diagnoses the run's best evaluation's agent instead of its last.

Reads datasets from MINARI_DATASETS_PATH, by default RUNDIR/../minari where that exists (bench_downstream's
LOGDIR/minari).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import describe_machine  # noqa: E402
from finetune.offline import OfflineAgent  # noqa: E402
from finetune.pretrained import PretrainedError  # noqa: E402
from finetune.config import FinetuneError  # noqa: E402
from finetune.run_dir import BEST, CHECKPOINT, load_trained, run_config  # noqa: E402
from finetune.train import dataset_replay, task_env  # noqa: E402
from finetune.world_model import Latent  # noqa: E402

MODEL_METRICS = ("model_loss", "recon_nll", "reward_nll", "kl")


class Fixed:
    """What DualStreamWorldModel.imagine asks of a policy (a distribution with rsample and entropy), for given actions."""

    def __init__(self, action: torch.Tensor):
        self.action = action  # [N, A]

    def rsample(self) -> torch.Tensor:
        return self.action

    def entropy(self) -> torch.Tensor:
        return torch.zeros(self.action.shape[0])


def imagined_reward_per_step(agent: OfflineAgent, first: Latent, horizon: int,
                             recorded: torch.Tensor | None = None) -> float:
    """The reward head's mean over `horizon` steps imagined from `first` [B, 1, ·]: along the `recorded` actions
    [B, horizon, A], or (None) along the actor's mode."""
    steps = iter(recorded.unbind(1)) if recorded is not None else None

    def policy(feat: torch.Tensor) -> Fixed:
        return Fixed(next(steps) if steps is not None else agent.behavior.actor(feat).mode)

    return float(agent.world_model.imagine(first, policy, horizon)[1].mean())


def windows(dataset_id: str, cfg, action_dim: int, count: int, seed: int, flag: str) -> list[dict[str, torch.Tensor]]:
    """`count` replay batches (cfg.batch_size windows of cfg.seq_len steps) of a dataset, as tensors; `flag` names
    the dataset in errors."""
    replay = dataset_replay(dataset_id, cfg, action_dim, flag, np.random.default_rng(seed))
    return [{key: torch.as_tensor(value) for key, value in replay.sample(cfg.batch_size, cfg.seq_len).items()}
            for _ in range(count)]


@torch.no_grad()
def diagnose(agent: OfflineAgent, batches: list[dict[str, torch.Tensor]]) -> dict[str, float]:
    """Means over `batches` of the model's losses, the actor's deviation from the recorded actions, and u of
    one imagined step with either."""
    sums: dict[str, float] = {}
    for batch in batches:
        _, start, metrics = agent.world_model.loss(batch)  # start: posterior states [B, L, ·]
        recorded = batch["action"]  # [B, L, A]; entry t + 1 is the action taken at state t
        mode = agent.behavior.actor(agent.world_model.feature(start)).mode  # the actor at each state [B, L, A]
        actor = torch.cat([recorded[:, :1], mode[:, :-1]], 1)  # the same layout: entry t + 1 acts at state t
        values = {name: float(metrics[name]) for name in MODEL_METRICS}
        values["action_gap"] = float((mode[:, :-1] - recorded[:, 1:]).abs().mean())
        values["actor_at_bound"] = float((mode.abs() >= 0.99).float().mean())
        for name, actions in (("u_recorded_actions", recorded), ("u_actor_actions", actor)):
            agent.penalty.measure_dataset(start, actions)
            values[name] = float(agent.penalty.metrics["penalty_u_dataset"])
        first, horizon = start.map(lambda x: x[:, :1]), recorded.shape[1] - 1
        values["reward_recorded"] = float(batch["reward"][:, 1:].mean())
        values["reward_imagined_recorded_actions"] = imagined_reward_per_step(agent, first, horizon, recorded[:, 1:])
        values["reward_imagined_actor"] = imagined_reward_per_step(agent, first, horizon)
        for name, value in values.items():
            sums[name] = sums.get(name, 0.0) + value / len(batches)
    return sums


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="an offline run's logdir (checkpoint.pt, config.yaml)")
    p.add_argument("--pretrained", required=True, help="the export the run was trained on")
    p.add_argument("--heldout", default="bench/drawer_close-demos-v0", help="a dataset of the same task")
    p.add_argument("--batches", type=int, default=8)
    p.add_argument("--checkpoint", default=CHECKPOINT, choices=[CHECKPOINT, BEST], help="the last checkpoint or best.pt")
    args = p.parse_args()
    if (args.run.parent / "minari").is_dir():  # bench_downstream's layout: LOGDIR/RUN beside LOGDIR/minari
        os.environ.setdefault("MINARI_DATASETS_PATH", str(args.run.parent / "minari"))
    torch.set_num_threads(1)
    try:
        cfg = run_config(args.run, {"device": "cpu"})
        if cfg.paradigm != "offline":
            raise FinetuneError(f"{args.run}: an offline run is needed, this one is {cfg.paradigm!r}")
        with contextlib.closing(task_env(cfg, cfg.seed)) as env:
            action_dim = env.action_space.shape[0]
        cfg, agent, counters = load_trained(args.run, args.pretrained, action_dim, checkpoint=args.checkpoint)
        print(f"machine: {describe_machine()}")
        print(f"settings: {args.run / args.checkpoint} at {counters['updates']} updates: penalty {cfg.penalty}, "
              f"λ {cfg.penalty_scale:g}; {args.batches} batches of {cfg.batch_size} × {cfg.seq_len} per dataset")
        results = {"training dataset": diagnose(agent, windows(cfg.dataset, cfg, action_dim, args.batches, 1,
                                                               "the run's dataset (RUNDIR/config.yaml)")),
                   "held-out": diagnose(agent, windows(args.heldout, cfg, action_dim, args.batches, 2, "--heldout"))}
    except (FinetuneError, PretrainedError) as error:
        p.exit(2, f"{p.prog}: error: {error}\n")
    names = list(next(iter(results.values())))
    print(f"{'':<34}" + "".join(f"{name:>20}" for name in results))
    for name in names:
        print(f"{name:<34}" + "".join(f"{values[name]:>20.3f}" for values in results.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
