"""What does an imitation run's discriminator judge: behaviour, or imagined vs posterior latents? (CPU, a minute)

    python bench/bench_imitation_diagnosis.py RUNDIR --pretrained DIR

Reads the run's checkpoint (RUNDIR/checkpoint.pt, config.yaml) and windows of its demonstrations, and
prints the discriminator's mean logit ℓ = log D − log(1 − D) (> 0: "expert") and the share of pairs it
calls expert, on:

- the demonstrations' posterior pairs (z_t from observe, the expert's a_t);
- at each depth of imagination from the windows' first posterior states, the pairs imagined along the
  expert's own actions, and the pairs the run's actor imagines there with its own actions.

A discriminator that judges behaviour calls the first "expert" at every depth and the actor's "policy"
(unless the actor imitates well); one that learned imagined vs posterior latents calls both "policy" from
the first imagined step on. Needs the run's MINARI_DATASETS_PATH (bench_downstream: LOGDIR/minari).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.machine import describe_machine  # noqa: E402
from finetune.imitation import ImitationAgent, RecordedActions  # noqa: E402
from finetune.replay import Replay  # noqa: E402
from finetune.run_dir import load_trained, run_config  # noqa: E402
from finetune.train import load_dataset  # noqa: E402
from finetune.world_model import Latent  # noqa: E402


def judged(logits: torch.Tensor) -> str:
    """'mean logit (share called expert)' of logits [..., N]."""
    return f"{float(logits.mean()):+7.2f} ({float((logits > 0).float().mean()):4.0%})"


def imagined_pairs(agent: ImitationAgent, first: Latent, policy, steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(z_t, a_t) for t < `steps` along `policy` from the states `first`: feats [steps, N, F], actions [steps, N, A]."""
    kept = []

    def keep(rollout):  # a reward function that keeps what imagination visited
        kept.append(rollout)
        return rollout.actions.new_zeros(rollout.actions.shape[:2])

    agent.world_model.imagine(first, policy, steps, reward=keep)
    return kept[0].feats[:-1], kept[0].actions


@torch.no_grad()
def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, help="an imitation run's logdir (checkpoint.pt, config.yaml)")
    p.add_argument("--pretrained", required=True, help="the export the run was trained on")
    p.add_argument("--windows", type=int, default=32, help="demonstration windows of the run's seq_len")
    args = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    cfg = run_config(args.run)
    if cfg.paradigm != "imitation":
        sys.exit(f"{args.run}: an imitation run is needed, this one is {cfg.paradigm!r}")
    demos = load_dataset(cfg.demos, cfg, None, "--demos")
    cfg, agent, counters = load_trained(args.run, args.pretrained, demos[0]["action"].shape[-1])
    replay = Replay(None, cfg.replay_capacity, np.random.default_rng(1))
    for episode in demos:
        replay.add(episode)
    batch = {key: torch.as_tensor(value) for key, value in replay.sample(args.windows, cfg.seq_len).items()}
    _, start, _ = agent.world_model.loss(batch)  # posterior states [B, L, ·]
    recorded = batch["action"][:, 1:]  # a_t, taken at state t [B, L − 1, A]
    logit = agent.discriminator.logit
    first = start.map(lambda x: x[:, :1])
    steps = cfg.seq_len - 1
    expert = imagined_pairs(agent, first, RecordedActions(recorded.transpose(0, 1)), steps)
    actor = imagined_pairs(agent, first, agent.behavior.actor, steps)
    print(f"machine: {describe_machine()}")
    print(f"settings: {args.run} at {counters['env_step']} env steps (expert_latents: {cfg.expert_latents}); "
          f"{args.windows} demonstration windows of {cfg.seq_len} steps")
    print(f"posterior expert pairs: logit (called expert) "
          f"{judged(logit(agent.world_model.feature(start)[:, :-1], recorded))}")
    print(f"{'imagined depth':>14} {'expert actions':>18} {'actor actions':>18}")
    for t in range(steps):
        print(f"{t:>14} {judged(logit(expert[0][t], expert[1][t])):>18} {judged(logit(actor[0][t], actor[1][t])):>18}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
