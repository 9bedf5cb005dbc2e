"""Offline RL on the frozen export (paper §5.5, appendix F.1; LOMPO-style): `hauwm finetune offline`.

No environment step is taken except to evaluate. The replay is filled once from a dataset
(`finetune.datasets.load_episodes`, e.g. a medexp set: medium-replay plus expert episodes), and every
update is the online agent's: fit the new stream (with `model_heads` prior heads), decoder and reward head
on a batch of dataset windows, then imagine `horizon` (H = 5) steps from every posterior state of that
batch and take one actor and one critic step, with the penalised reward of eq. 6 (finetune/penalty.py)
in place of the reward head's. Counts here are updates: `steps` updates in all, evaluation (the actor's
mode, `eval_episodes` episodes, returns normalised by Table 4), logs and checkpoints every `eval_every`,
`log_every` and `checkpoint_every` updates. `checkpoint.pt` holds the agent, its optimisers, both random
states and the counters, and `best.pt` the agent of the best evaluation so far; each evaluation reseeds
its env, so a resumed run continues exactly as an unbroken one (same batches, same weights, same
evaluation episodes).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from finetune.agent import Agent
from finetune.config import FinetuneConfig, FinetuneError
from finetune.logger import Logger
from finetune.penalty import PenalisedReward
from finetune.run_dir import CHECKPOINT, exclusive, next_multiple, save_checkpoint
from hauwm.termination import Terminated, terminable
from finetune.train import (EVAL_SEED, LogWindow, close_window, dataset_replay, scheduled_evaluation, start_run,
                            task_env)
from finetune.world_model import Latent
from model.export import FrozenWorldModel


class OfflineAgent(Agent):
    """The online agent with eq. 6's penalised reward in imagination; logs u on dataset and imagined steps."""

    def __init__(self, cfg: FinetuneConfig, action_dim: int, frozen: FrozenWorldModel | None = None,
                 k1_embedding: torch.Tensor | None = None):
        super().__init__(cfg, action_dim, frozen, k1_embedding)
        self.penalty = PenalisedReward(self.world_model, cfg.penalty, cfg.penalty_scale, cfg.penalty_frozen_weight)

    def imagined_reward(self, batch: dict[str, torch.Tensor], start: Latent) -> PenalisedReward:
        self.penalty.measure_dataset(start, batch["action"])
        return self.penalty

    def finish_update(self) -> dict[str, torch.Tensor]:
        # the imagined metrics live in the compiled update's CUDA-graph memory: taken here, in the update that made
        # them, and not kept (the next replay overwrites them)
        imagined, self.penalty.imagined_metrics = self.penalty.imagined_metrics, {}
        return {**self.penalty.metrics, **imagined}


def train_offline(cfg: FinetuneConfig, pretrained: str | Path | None = None, progress: bool = True) -> dict[str, float]:
    """Run (or resume) offline RL in cfg.logdir until cfg.steps updates; returns the last evaluation."""
    if cfg.paradigm != "offline":
        raise FinetuneError(f"train_offline needs paradigm 'offline', the config has {cfg.paradigm!r}")
    with exclusive(Path(cfg.logdir)), contextlib.closing(task_env(cfg, cfg.seed + EVAL_SEED)) as eval_env:
        return run_offline(cfg, pretrained, progress, eval_env)


def run_offline(cfg: FinetuneConfig, pretrained: str | Path | None, progress: bool, eval_env) -> dict[str, float]:
    """The loop, in a run directory this process holds the lock of; `eval_env` is the task's env for evaluation."""
    action_dim = eval_env.action_space.shape[0]
    rng = np.random.default_rng(cfg.seed)
    replay = dataset_replay(cfg.dataset, cfg, action_dim, "--dataset", rng)
    counters = {"updates": 0, "next_eval": cfg.eval_every, "next_checkpoint": cfg.checkpoint_every,
                "next_log": cfg.log_every}
    agent, fingerprint, counters = start_run(cfg, pretrained, OfflineAgent, action_dim, counters, rng)
    checkpoint = Path(cfg.logdir) / CHECKPOINT
    last_eval: dict[str, float] = {}
    bar = tqdm(total=cfg.steps, initial=counters["updates"], unit=" update", desc=f"offline {cfg.task}",
               disable=not progress, dynamic_ncols=True)
    window = LogWindow(counters["updates"])
    with terminable() as stop, \
            contextlib.closing(Logger(Path(cfg.logdir), step_name="update", start=int(counters["updates"]))) as logger:
        while counters["updates"] < cfg.steps:
            window.metrics.append(agent.update(replay.sample(cfg.batch_size, cfg.seq_len)))
            counters["updates"] += 1
            bar.update(1)
            updates = counters["updates"]
            if updates >= counters["next_log"] or updates >= cfg.steps:
                metrics = close_window(window, updates)
                logger.write("train", updates, metrics)
                bar.set_postfix(model_loss=f"{metrics['model_loss']:.1f}", u=f"{metrics['penalty_u_imagined']:.3g}")
                counters["next_log"] = next_multiple(updates, cfg.log_every)
            if updates >= counters["next_eval"] or updates >= cfg.steps:
                last_eval = scheduled_evaluation(agent, eval_env, cfg, cfg.seed + EVAL_SEED + updates, counters,
                                                 fingerprint, logger, window, bar, progress)
            if updates >= counters["next_checkpoint"] or updates >= cfg.steps or stop.requested:
                counters["next_checkpoint"] = next_multiple(updates, cfg.checkpoint_every)
                save_checkpoint(checkpoint, agent, cfg, counters, fingerprint, rng)
                if stop.requested:  # SIGTERM: stopped with the checkpoint of this update (hauwm/termination.py)
                    raise Terminated(f"update {updates}")
    bar.close()
    return last_eval
