"""The online fine-tuning loop (paper Algorithm 1, phase 2): act → replay → update → evaluate → checkpoint.

Counts are environment steps (frames), summed over the `num_envs` training envs. The first `prefill`
steps take uniformly random actions; after that one gradient update (world model, then actor and critic)
runs every `train_every` env steps. With several envs (worker processes, finetune/envs/vector.py) the
envs act as one batch and the updates due run while the workers step; each env fills its own episodes.
Every `eval_every` env steps the policy's mode plays `eval_episodes` episodes on a separately seeded
environment; returns are logged raw and normalised with the paper's Table 4 references where the task
has them. Every `checkpoint_every` env steps the run directory's checkpoint.pt is written, and each
evaluation with the highest mean return so far is kept in best.pt; starting again with the same --logdir
resumes (what a checkpoint holds and the rules of a resume: finetune/run_dir.py).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from finetune.agent import Agent, DivergedError
from finetune.config import FinetuneConfig, FinetuneError, step_unit
from finetune.logger import Logger
from finetune.replay import Replay
from finetune.rollout import AgentPolicy, play_episode
from finetune.run_dir import (CHECKPOINT, Fingerprint, exclusive, keep_best, next_multiple, resume, run_fingerprint,
                              save_checkpoint)
from hauwm.memory import ENV_WORKER_BYTES, PARAMETER_BYTES, beyond_memory, parameter_count, size_text
from hauwm.termination import StopRequest, Terminated, terminable
from model.compiling import compile_mode
from model.config import WorldModelConfig
from model.networks import IMAGE_SHAPE, Decoder, Encoder

ENV_SEED_STRIDE = 1_000_000  # env i of a fresh run starts from seed + i · this (env 0: the seed a single env gets)
EVAL_SEED = 10_000  # a run's evaluation env plays from seed + this (+ the step of a reseeded evaluation)
HELD_OUT_SEED = 1_000_000_000  # `hauwm finetune evaluate` plays from the run's seed + this: an env seed the run's
#                                fresh envs (seed + i · ENV_SEED_STRIDE) and evaluations (seed + EVAL_SEED + step)
#                                never reach (its reseeded episodes, `episode_seed`, only by a 1-in-2^32 chance)


def episode_seed(run_seed: int, env: int, episodes: int) -> int:
    """The env seed of env `env`'s episode after `episodes` episodes of the run (a resumed or reseeded episode): a
    number of its own for each (run seed, env, episodes), so that runs with neighbouring seeds never replay each
    other's episodes (seed + episodes would: run 0's second episode would be run 1's first)."""
    return int(np.random.SeedSequence([run_seed, env, episodes]).generate_state(1)[0])


def resolve_device(name: str) -> torch.device:
    """The torch device of a --device flag or `device` setting: auto (CUDA if visible), cpu, cuda or cuda:N."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:  # torch's own message lists every backend it knows
        device = None
    if device is None or device.type not in ("cpu", "cuda") or (device.type == "cpu" and device.index):
        raise FinetuneError(f"device {name!r} is not a device HAUWM runs on: use auto, cpu, cuda or cuda:N")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise FinetuneError(f"device {name!r} asked for but no CUDA device is visible; use --device cpu")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise FinetuneError(f"device {name!r} asked for but this machine has {torch.cuda.device_count()} CUDA "
                            f"device(s), cuda:0 to cuda:{torch.cuda.device_count() - 1}")
    return device


def build_agent(cfg: FinetuneConfig, action_dim: int, pretrained: str | Path | None, device: torch.device,
                agent_class: type[Agent] = Agent) -> Agent:
    """The agent (`agent_class`: Agent for online RL, or offline RL's and imitation's subclasses) on `device`."""
    from finetune.pretrained import k1_embedding, load_pretrained
    from finetune.world_model import ExportSizeError

    if cfg.agent == "scratch":
        agent = agent_class(cfg, action_dim).to(device)
    elif pretrained is None:
        raise FinetuneError("agent 'hauwm' needs --pretrained DIR (an export of `hauwm pretrain export`); "
                            "or run the scratch baseline with --set agent=scratch")
    else:
        frozen = load_pretrained(pretrained)
        try:
            agent = agent_class(cfg, action_dim, frozen, k1_embedding(frozen, cfg.k1_clip_length)).to(device)
        except ExportSizeError as error:
            raise FinetuneError(f"--pretrained {pretrained}: {error}") from None
    agent.set_compile(compile_mode(cfg.compile, device))
    return agent


def load_dataset(dataset_id: str | None, cfg: FinetuneConfig, action_dim: int, flag: str) -> list[dict[str, np.ndarray]]:
    """Episodes of a dataset (finetune.datasets, Minari) in the replay's format, for offline RL (--dataset) and
    imitation (--demos). The dataset must be of cfg.task and, where it records them, have been collected
    with cfg's action_repeat and fast_render (the dynamics and frames the agent is evaluated on); every
    problem is a FinetuneError naming `flag`."""
    if not dataset_id:
        raise FinetuneError(f"{flag} ID is needed: a dataset written by `hauwm datasets collect` (or set "
                            f"{flag.lstrip('-')} in the config)")
    from finetune.datasets import DatasetError, load_episodes
    from finetune.datasets.minari_io import hauwm_metadata, open_dataset
    from finetune.datasets.summary import TERMINALS_IGNORED, ends_terminal

    try:
        dataset = open_dataset(dataset_id)
        collected = hauwm_metadata(dataset)
        if collected.get("task", cfg.task) != cfg.task:  # before its settings, which another task's differ in anyway
            raise FinetuneError(f"{flag} {dataset_id} was collected on {collected['task']}, not on this run's task "
                                f"{cfg.task}: use a dataset of {cfg.task} (`hauwm datasets list` shows their tasks)")
        for key in ("action_repeat", "fast_render"):
            if key in collected and collected[key] != getattr(cfg, key):
                raise FinetuneError(f"{flag} {dataset_id} was collected with {key}={collected[key]!r}, this run has "
                                    f"{key}={getattr(cfg, key)!r}: set {key}: {collected[key]} in the config "
                                    f"(--set {key}={collected[key]})")
        if dataset.total_steps > cfg.replay_capacity:  # the replay would keep only the newest steps, without a word
            raise FinetuneError(f"{flag} {dataset_id} holds {dataset.total_steps} steps, more than replay_capacity "
                                f"{cfg.replay_capacity}: the run would train on its newest {cfg.replay_capacity} only; "
                                f"--set replay_capacity={dataset.total_steps} (memory: about "
                                f"{size_text(replay_bytes(dataset.total_steps, action_dim))} of frames)")
        if problem := beyond_memory({f"its {dataset.total_steps} steps": replay_bytes(dataset.total_steps, action_dim)},
                                    "use a smaller dataset (`hauwm datasets collect` or `merge` of fewer episodes)"):
            raise FinetuneError(f"{flag} {dataset_id}: {problem}")
        episodes = load_episodes(dataset_id, task=cfg.task, action_dim=action_dim, progress=False)
    except DatasetError as error:
        raise FinetuneError(f"{flag} {dataset_id}: {error}") from None
    if terminals := sum(map(ends_terminal, episodes)):
        print(f"note: {terminals} of the {len(episodes)} episodes of {flag} {dataset_id} end in a terminal state: "
              f"{TERMINALS_IGNORED}", file=sys.stderr)
    return episodes


def dataset_replay(dataset_id: str | None, cfg: FinetuneConfig, action_dim: int, flag: str,
                   rng: np.random.Generator) -> Replay:
    """A replay in memory holding a dataset's episodes (load_dataset), sampled with `rng`; a FinetuneError naming
    `flag` if no episode is long enough for a window of seq_len frames."""
    replay = Replay(None, cfg.replay_capacity, rng)
    episodes = load_dataset(dataset_id, cfg, action_dim, flag)
    for episode in episodes:
        replay.add(episode)
    if not replay.ready(cfg.seq_len):
        raise FinetuneError(f"{flag} {dataset_id}: no episode holds seq_len = {cfg.seq_len} frames (one of "
                            f"{cfg.seq_len - 1} steps or more); lower seq_len")
    if short := [len(episode["reward"]) - 1 for episode in episodes if len(episode["reward"]) < cfg.seq_len]:
        steps = sum(len(episode["reward"]) - 1 for episode in episodes)
        print(f"note: {len(short)} of the {len(episodes)} episodes of {flag} {dataset_id} ({sum(short)} of its {steps} "
              f"steps) are shorter than a window of seq_len = {cfg.seq_len} frames and are never sampled; lower "
              "seq_len to train on them", file=sys.stderr)
    return replay


def evaluate(agent: Agent, env, episodes: int, task: str, seed: int | None = None,
             progress: bool = False) -> dict[str, float]:
    """Play `episodes` episodes with the actor's mode; mean return, its std, its normalised value, success rate.
    `seed` reseeds the env first (the same episodes whenever this evaluation is run again, e.g. after resume).
    The world model's posterior samples draw from torch's RNG forked and seeded with `seed` (0 without one): an
    evaluation never moves the training's random stream (how often a run evaluates leaves what it learns as it
    is), and one agent evaluated twice with one env seed gives the same figures."""
    from finetune.envs.references import REFERENCE_RETURNS, normalised_return

    policy = AgentPolicy(agent, explore=False)
    returns, successes = [], []
    with torch.random.fork_rng(devices=[agent.device] if agent.device.type == "cuda" else []):
        torch.manual_seed(0 if seed is None else seed)
        for index in tqdm(range(episodes), unit=" episode", desc=f"evaluate {task}", disable=not progress,
                          dynamic_ncols=True, leave=False):
            episode = play_episode(env, policy, seed=seed if index == 0 else None)
            returns.append(float(episode["reward"].sum(dtype=np.float64)))
            if "success" in episode:  # the suites with a success test (Meta-World, RoboDesk) report one
                successes.append(bool(episode["success"].any()))
    result = {"return": float(np.mean(returns)), "return_std": float(np.std(returns))}
    if task in REFERENCE_RETURNS:  # tasks outside the paper's Table 4 (e.g. the demo's cartpole) have none
        result["normalised_return"] = float(normalised_return(task, result["return"]))
    if successes:
        result["success_rate"] = float(np.mean(successes))
    return result


def scheduled_evaluation(agent: Agent, eval_env, cfg: FinetuneConfig, seed: int | None, counters: dict[str, float],
                         fingerprint: Fingerprint, logger: Logger, window: LogWindow, bar: tqdm,
                         progress: bool) -> dict[str, float]:
    """A run's evaluation once its counters reach next_eval (the online and offline loops'): `evaluate`, its time
    left out of the log window's updates/s and the progress bar's rate; written to eval.csv, kept in best.pt if it is
    the best so far (`keep_best`), and the next one scheduled. Its step is the paradigm's (`step_unit`)."""
    unit, key = step_unit(cfg.paradigm)
    step = counters[key]
    started = time.perf_counter()
    result = evaluate(agent, eval_env, cfg.eval_episodes, cfg.task, seed=seed, progress=progress)
    window.began += time.perf_counter() - started
    bar.unpause()
    logger.write("eval", step, result)
    keep_best(Path(cfg.logdir), agent, cfg, counters, fingerprint, result, step)
    bar.write(f"eval at {step} {unit}s: " + ", ".join(f"{k} {v:.3g}" for k, v in result.items()))
    counters["next_eval"] = next_multiple(step, cfg.eval_every)
    return result


@dataclasses.dataclass
class LogWindow:
    """The updates since the last `train` log row: the update count and the time the window began at (for updates/s),
    and each update's metrics (tensors on the agent's device, read once when the window closes)."""

    updates: int
    began: float = dataclasses.field(default_factory=time.perf_counter)
    metrics: list[dict[str, torch.Tensor]] = dataclasses.field(default_factory=list)


def mean_metrics(metrics: list[dict[str, torch.Tensor]]) -> dict[str, float]:
    """Each metric's mean over a log window of updates, read from the device in one transfer."""
    rows = torch.stack([torch.stack(list(m.values())) for m in metrics]).tolist()  # [updates, metrics]
    return {name: float(np.mean([row[i] for row in rows])) for i, name in enumerate(metrics[0])}


def close_window(window: LogWindow, updates: int) -> dict[str, float]:
    """A log window's mean metrics and updates/s (`updates`: the update count now); the window begins again. A metric
    that is not finite is a DivergedError: nothing is learned from an infinite loss (its gradients are clipped to
    nothing, or turn the weights into NaN), and the run would go on for its whole budget."""
    now = time.perf_counter()
    metrics = mean_metrics(window.metrics)
    if broken := [f"{name} {value:g}" for name, value in metrics.items() if not math.isfinite(value)]:
        raise DivergedError(f"{', '.join(broken)} in updates {window.updates + 1}..{updates}: the agent's training has "
                            "diverged. Rewards too large for float32's squares (beyond about 1e18: a dataset's?) do "
                            "this; else lower model_lr, actor_lr or critic_lr, and start a new run")
    metrics["updates_per_s"] = (updates - window.updates) / (now - window.began)
    window.updates, window.began, window.metrics = updates, now, []
    return metrics


@dataclasses.dataclass(frozen=True)
class LoopHooks:
    """What imitation changes in this loop (finetune/imitation.py); the defaults are online RL's."""

    agent_class: type[Agent] = Agent
    # (cfg, replay directory, sampling rng, action dim) -> the replay; None: the online replay of the agent's episodes
    make_replay: Callable[[FinetuneConfig, Path, np.random.Generator, int], Replay] | None = None
    # reseed each training episode and each evaluation from its index, so that a run resumed from a
    # checkpoint taken at an episode's end continues exactly as an unbroken run
    reseed: bool = False


def train(cfg: FinetuneConfig, pretrained: str | Path | None = None, progress: bool = True) -> dict[str, float]:
    """Run (or resume) fine-tuning in cfg.logdir until cfg.steps env steps; returns the last evaluation."""
    with exclusive(Path(cfg.logdir)):
        return run(cfg, pretrained, progress)


def new_episode(obs: np.ndarray, action_shape: tuple[int, ...]) -> dict[str, list]:
    """An episode's first entry: o_0 with a zero action and zero reward (the replay's alignment)."""
    return {"obs": [obs], "action": [np.zeros(action_shape, np.float32)], "reward": [0.0]}


def extend_episodes(episodes: list[dict[str, list]], actions: np.ndarray, rewards: np.ndarray, obs: np.ndarray,
                    done: np.ndarray, info: dict) -> None:
    """Append one step of every env to its episode: a_t [N, A], r_t [N] and o_{t+1} [N, 3, 64, 64]. An env whose
    episode ended (done [N]) was reset inside the step: its `obs` starts its next episode, and this episode's last
    frame is the one the vector env keeps in info["final_obs"]."""
    for i, episode in enumerate(episodes):
        episode["obs"].append(info["final_obs"][i] if done[i] else obs[i])
        episode["action"].append(actions[i])
        episode["reward"].append(float(rewards[i]))


def store_episodes(episodes: list[dict[str, list]], done: np.ndarray, replay: Replay, logger: Logger,
                   counters: dict[str, float]) -> None:
    """Add each episode that ended (done [N]) to the replay and its return and length to episodes.csv."""
    for i in np.flatnonzero(done):
        episode = episodes[i]
        replay.add({"obs": np.stack(episode["obs"]), "action": np.stack(episode["action"]).astype(np.float32),
                    "reward": np.asarray(episode["reward"], np.float32)})
        counters["episodes"] += 1
        logger.write("episodes", counters["env_step"], {"return": float(sum(episode["reward"])),
                                                       "length": len(episode["reward"]) - 1})


def reset_seeded(envs, samplers: list, run_seed: int, episodes: int, starting: np.ndarray) -> np.ndarray:
    """Reset the envs where `starting` [N] is true with their episode seeds (`episode_seed` after `episodes` episodes
    of the run), their prefill samplers reseeded alike; -> every env's frame [N, 3, 64, 64]."""
    from finetune.envs.base import action_seed

    seeds = [episode_seed(run_seed, i, episodes) for i in range(len(starting))]
    for i in np.flatnonzero(starting):
        samplers[i].seed(action_seed(seeds[i]))
    return envs.reset(seed=seeds, options={"reset_mask": starting})[0]


def train_due(cfg: FinetuneConfig, agent: Agent, replay: Replay, counters: dict[str, float], window: LogWindow) -> None:
    """The updates due by counters["env_step"]: one every `train_every` env steps after the prefill, each on a batch
    from the replay (once it holds a window of seq_len); their metrics go to the log window."""
    updates_due = max(0, counters["env_step"] - cfg.prefill) // cfg.train_every
    while counters["updates"] < updates_due and replay.ready(cfg.seq_len):
        window.metrics.append(agent.update(replay.sample(cfg.batch_size, cfg.seq_len)))
        counters["updates"] += 1


def task_env(cfg: FinetuneConfig, seed: int):
    """cfg.task's environment at cfg's settings (finetune.envs.make_env); an unknown task is a FinetuneError."""
    from finetune.envs import EnvSettingError, make_env

    try:
        return make_env(cfg.task, seed=seed, **cfg.env_settings)
    except EnvSettingError as error:  # an unknown task, a time limit beyond the suite's, a MUJOCO_GL that cannot render
        raise FinetuneError(f"task {cfg.task!r}: {error}") from None


def incomparable_returns_note(cfg: FinetuneConfig) -> str | None:
    """A note where the run's normalised returns cannot be compared with the paper's: its episodes are cut shorter
    than the suite's, or run on past it (`time_limit`), and Table 4's references are returns of the suite's episodes."""
    from finetune.envs.references import REFERENCE_RETURNS
    from finetune.envs.registry import episode_time_limit

    full = episode_time_limit(cfg.task, cfg.action_repeat)
    if cfg.task not in REFERENCE_RETURNS or cfg.time_limit is None or cfg.time_limit == full:
        return None
    how = "cuts {}'s episodes short of" if cfg.time_limit < full else "runs {}'s episodes on past"
    return (f"note: time_limit {cfg.time_limit} {how.format(cfg.task)} the suite's {full} agent steps: the normalised "
            "returns in eval.csv are not comparable to the paper's (Table 4's references are returns of the suite's "
            "episodes)")


def replay_bytes(steps: int, action_dim: int) -> int:
    """Bytes of `steps` replay entries: a uint8 frame, a float32 action and a float32 reward each."""
    return steps * (math.prod(IMAGE_SHAPE) + 4 * (action_dim + 1))


def refuse_beyond_memory(cfg: FinetuneConfig, agent_class: type[Agent], action_dim: int, device: torch.device) -> None:
    """Refuse a run that cannot fit in this machine's memory (hauwm/memory.py): the agent's trained parameters (float32
    weights, gradients and Adam state on a CPU; the weights, while they are built, for a GPU) and, where the run collects
    episodes, its replay at its fullest: min(replay_capacity, the run's agent steps) frames with their actions and
    rewards, and its env worker processes. A dataset the run trains on is loaded before: the memory available is what it
    left."""
    # built without the export: the scratch agent's parts, its new stream of the paper's deter and stoch where they follow
    # the export's (a few MB more than a small export's); the hauwm agent's encoder and decoder are the export's (its
    # decoder a copy, of the export's size: left out with the scratch ones, which are sized by encoder_width)
    agent = parameter_count(lambda: agent_class(cfg, action_dim))
    if cfg.agent == "hauwm":
        feature_dim = (cfg.deter or WorldModelConfig.deter) + (cfg.stoch or WorldModelConfig.stoch)
        agent -= parameter_count(lambda: nn.ModuleList([Encoder(cfg.encoder_width, 32 * cfg.encoder_width),
                                                        Decoder(feature_dim, cfg.encoder_width)]))
    defaults = {"units": FinetuneConfig.units, "hidden": FinetuneConfig.hidden, "model_heads": FinetuneConfig.model_heads,
                "deter": WorldModelConfig.deter, "stoch": WorldModelConfig.stoch}
    if cfg.agent == "scratch":
        defaults["encoder_width"] = FinetuneConfig.encoder_width
    larger = [f"{name} {getattr(cfg, name)}" for name, size in defaults.items() if (getattr(cfg, name) or 0) > size]
    sizes = f"the agent's sizes{' (' + ', '.join(larger) + ')' if larger else ''}"
    if device.type == "cpu":  # (what, bytes, its fix)
        parts = [("the agent's weights, gradients and Adam state", 4 * PARAMETER_BYTES * agent, sizes)]
    else:
        parts = [("the agent's weights, built on the host", PARAMETER_BYTES * agent, sizes)]
    if cfg.paradigm != "offline":  # it collects episodes
        steps = min(cfg.replay_capacity, math.ceil(cfg.steps / cfg.action_repeat))
        parts.append((f"the replay of {steps} steps", replay_bytes(steps, action_dim),
                      "replay_capacity (the replay then keeps the newest steps that fit)"))
        if cfg.num_envs > 1:  # each env in a worker process of its own
            parts.append((f"{cfg.num_envs} env processes", cfg.num_envs * ENV_WORKER_BYTES, "num_envs"))
    needs = {what: size for what, size, _ in parts}
    # the fix of each need of a quarter of the total or more, the largest first
    fixes = [fix for _, size, fix in sorted(parts, key=lambda part: -part[1]) if size >= sum(needs.values()) / 4]
    if problem := beyond_memory(needs, f"lower {' or '.join(fixes)}"):
        raise FinetuneError(problem)


def start_run(cfg: FinetuneConfig, pretrained: str | Path | None, agent_class: type[Agent], action_dim: int,
              counters: dict[str, float], rng: np.random.Generator) -> tuple[Agent, Fingerprint, dict[str, float]]:
    """The start every paradigm shares: torch's threads and seed, the agent, and the run directory's checkpoint
    if there is one (`resume`: it restores the agent, `rng` and the counters; a fresh run keeps `counters`), the best
    return best.pt holds if it is higher than the counters', and config.yaml written. -> (agent, what the run
    trains on (run_fingerprint), counters)."""
    device = resolve_device(cfg.device)
    if cfg.threads:
        cpus = os.cpu_count() or cfg.threads
        if cfg.threads > cpus:  # thousands of threads fail to allocate their stacks deep inside a library
            print(f"note: threads {cfg.threads} is more than this machine's {cpus} CPUs; using {cpus}", file=sys.stderr)
        torch.set_num_threads(min(cfg.threads, cpus))
    if cfg.num_envs > (cpus := os.cpu_count() or 1):  # 100,000 were accepted, and ran the machine out of memory
        print(f"note: num_envs {cfg.num_envs} is more than this machine's {cpus} CPUs: each env is a process of its own "
              "(its simulator and renderer, about 100 MB), and envs beyond the CPUs step no faster", file=sys.stderr)
    if note := incomparable_returns_note(cfg):
        print(note, file=sys.stderr)
    refuse_beyond_memory(cfg, agent_class, action_dim, device)
    torch.manual_seed(cfg.seed)
    agent = build_agent(cfg, action_dim, pretrained, device, agent_class)
    fingerprint = run_fingerprint(cfg, pretrained)
    counters = resume(cfg, agent, fingerprint, counters, rng)
    return agent, fingerprint, counters


def run(cfg: FinetuneConfig, pretrained: str | Path | None, progress: bool, hooks: LoopHooks = LoopHooks()) -> dict[str, float]:
    """The loop itself, in a run directory this process holds the lock of."""
    from finetune.envs.vector import EnvWorkerError, closing_envs, make_vector_env

    logdir = Path(cfg.logdir)
    probe = task_env(cfg, cfg.seed)
    action_dim, episode_entries = probe.action_space.shape[0], probe.time_limit + 1  # o_0 and one per agent step
    probe.close()
    if cfg.seq_len > episode_entries:
        raise FinetuneError(f"seq_len = {cfg.seq_len} is longer than an episode of {cfg.task} ({episode_entries} "
                            f"frames at time_limit {probe.time_limit}): no update could ever train; lower seq_len "
                            "or raise time_limit")
    rng = np.random.default_rng([cfg.seed, 0])  # the replay's sampler; a checkpoint restores its state
    if hooks.make_replay is None:
        replay = Replay(logdir / "replay", cfg.replay_capacity, rng)
    else:  # before start_run: a dataset refused must leave the run directory's config.yaml as it was
        replay = hooks.make_replay(cfg, logdir / "replay", rng, action_dim)
    # the run's progress, saved in every checkpoint: what it has done, and when the next evaluation, checkpoint and
    # train log row are due (keep_best adds best_return and best_at)
    counters = {"env_step": 0, "updates": 0, "episodes": 0, "next_eval": cfg.eval_every,
                "next_checkpoint": cfg.checkpoint_every, "next_log": cfg.log_every}
    agent, fingerprint, counters = start_run(cfg, pretrained, hooks.agent_class, action_dim, counters, rng)
    first_episodes_end = counters["env_step"] + cfg.num_envs * probe.time_limit * cfg.action_repeat  # envs in lockstep
    if cfg.steps <= cfg.prefill:
        print(f"note: steps {cfg.steps} end within the prefill of {cfg.prefill} env steps of random actions: this run "
              "collects episodes and evaluates the untrained agent, but makes no update", file=sys.stderr)
    elif not counters["episodes"] and cfg.steps < first_episodes_end:
        print(f"note: steps {cfg.steps} end before the envs finish their first episodes (at env step "
              f"{first_episodes_end:.0f}: {cfg.num_envs} envs × time_limit {probe.time_limit} × action_repeat "
              f"{cfg.action_repeat}): the replay gets no episode to train on, so this run makes no update and "
              "evaluates the untrained agent; raise steps or lower num_envs", file=sys.stderr)

    # a resumed run reseeds from its progress, so it does not replay the same random streams; with hooks.reseed
    # each episode is seeded from its index instead, in the envs of a fresh run. Env i of num_envs gets its own
    # seeds (env 0 a single env's).
    if hooks.reseed or not counters["episodes"]:
        seeds = [cfg.seed + ENV_SEED_STRIDE * i for i in range(cfg.num_envs)]
    else:
        seeds = [episode_seed(cfg.seed, i, counters["episodes"]) for i in range(cfg.num_envs)]
    if not replay.load(int(counters["episodes"]), action_dim) and counters["episodes"]:
        print(f"note: {logdir / 'replay'} holds none of the {int(counters['episodes'])} episodes this run stored (moved "
              "or deleted?): it trains on the episodes it collects from here", file=sys.stderr)
    eval_seed = cfg.seed + EVAL_SEED + (0 if hooks.reseed else counters["env_step"])
    with terminable() as stop, contextlib.closing(task_env(cfg, eval_seed)) as eval_env, \
            contextlib.closing(Logger(logdir, start=int(counters["env_step"]))) as logger:
        try:
            envs = make_vector_env(cfg.task, seeds, cfg.pin_envs, lambda: stop.requested, **cfg.env_settings)
        except EnvWorkerError as error:
            if stop.requested:  # the job's SIGTERM, which ended the workers as they started
                raise Terminated(f"env step {int(counters['env_step'])}, as its env workers started") from None
            raise FinetuneError(f"task {cfg.task!r}: {error}") from None
        try:
            with closing_envs(envs):
                return loop(cfg, agent, envs, seeds, eval_env, replay, rng, logger, counters, logdir / CHECKPOINT,
                            fingerprint, progress, hooks.reseed, stop)
        except EnvWorkerError as error:  # a worker died or stopped answering mid-run
            if stop.requested or error.by_sigterm:  # the job's SIGTERM, which ended the workers first: as in loop()
                if not error.by_sigterm:  # a worker that died or stopped answering for another reason: said too
                    print(f"note: {error}", file=sys.stderr)
                save_checkpoint(logdir / CHECKPOINT, agent, cfg, counters, fingerprint, rng)
                raise Terminated(f"env step {int(counters['env_step'])}") from None
            raise FinetuneError(f"task {cfg.task!r}: {error}; the same command goes on from the run's last "
                                "checkpoint.pt, if one was written") from None


def loop(cfg: FinetuneConfig, agent: Agent, envs, seeds: list[int], eval_env, replay: Replay, rng: np.random.Generator,
         logger: Logger, counters: dict[str, float], checkpoint: Path, fingerprint: Fingerprint, progress: bool,
         reseed: bool, stop: StopRequest) -> dict[str, float]:
    """Act in `envs` (a gymnasium vector env), store finished episodes, update, log, evaluate, checkpoint; after
    SIGTERM (`stop`), checkpoint and raise Terminated (hauwm/termination.py).

    With several envs in worker processes, the updates due run while the workers step and render; with
    one env in this process, the loop runs one env step at a time, as a single env always did. With
    `reseed`, every episode env i starts is reset with episode_seed(seed, i, episodes so far) (and its
    prefill sampler reseeded alike), and every evaluation with seed + 10,000 + env steps: with one env,
    a run resumed from a checkpoint taken at an episode's end continues exactly as an unbroken one.
    """
    from finetune.envs.base import action_seed

    parallel = cfg.num_envs > 1
    samplers = [copy.deepcopy(envs.single_action_space) for _ in seeds]  # prefill's uniform actions, per env
    for sampler, seed in zip(samplers, seeds):
        sampler.seed(action_seed(seed))
    action_shape = envs.single_action_space.shape
    if reseed:
        obs = reset_seeded(envs, samplers, cfg.seed, counters["episodes"], np.ones(cfg.num_envs, bool))
    else:
        obs = envs.reset()[0]  # [N, 3, 64, 64]
    latent, prev_action = agent.initial(cfg.num_envs)
    episodes = [new_episode(frame, action_shape) for frame in obs]
    last_eval: dict[str, float] = {}
    bar = tqdm(total=cfg.steps, initial=counters["env_step"], unit=" env step", desc=cfg.task, disable=not progress,
               dynamic_ncols=True)
    window = LogWindow(counters["updates"])

    while counters["env_step"] < cfg.steps:
        # act: the exploring policy, or uniform random actions within the prefill
        actions, latent, prev_action = agent.act(obs, latent, prev_action, explore=True)  # [N, A]
        if counters["env_step"] < cfg.prefill:
            actions = np.stack([sampler.sample() for sampler in samplers]).astype(np.float32)
            prev_action = torch.as_tensor(actions, device=agent.device)
        if parallel:
            envs.step_async(actions)
            train_due(cfg, agent, replay, counters, window)  # the learner trains while the workers step and render
            obs, rewards, terminated, truncated, info = envs.step_wait()
        else:
            obs, rewards, terminated, truncated, info = envs.step(actions)
        done = terminated | truncated  # those envs were reset in this step: obs[i] starts their next episode
        extend_episodes(episodes, actions, rewards, obs, done, info)
        counters["env_step"] += cfg.num_envs * cfg.action_repeat
        bar.update(cfg.num_envs * cfg.action_repeat)
        if done.any():
            store_episodes(episodes, done, replay, logger, counters)
            if reseed:  # the autoreset's first frames are replaced by those of the seeded resets
                obs = reset_seeded(envs, samplers, cfg.seed, counters["episodes"], done)
            for i in np.flatnonzero(done):
                episodes[i] = new_episode(obs[i], action_shape)
            latent, prev_action = agent.restart(latent, prev_action, done)
        if not parallel:
            train_due(cfg, agent, replay, counters, window)

        # log, evaluate and checkpoint when due
        step = counters["env_step"]
        if step >= counters["next_log"] and window.metrics:
            metrics = close_window(window, counters["updates"])
            metrics["updates"] = counters["updates"]
            logger.write("train", step, metrics)
            bar.set_postfix(updates_per_s=f"{metrics['updates_per_s']:.2f}", model_loss=f"{metrics['model_loss']:.1f}")
            counters["next_log"] = next_multiple(step, cfg.log_every)
        eval_due = step >= counters["next_eval"] or step >= cfg.steps
        checkpoint_due = step >= counters["next_checkpoint"] or step >= cfg.steps or stop.requested
        if eval_due or checkpoint_due:
            train_due(cfg, agent, replay, counters, window)  # they see every update due so far, also with parallel envs
        if eval_due:
            eval_seed = cfg.seed + EVAL_SEED + step if reseed else None
            last_eval = scheduled_evaluation(agent, eval_env, cfg, eval_seed, counters, fingerprint, logger, window, bar,
                                             progress)
        if checkpoint_due:
            counters["next_checkpoint"] = next_multiple(step, cfg.checkpoint_every)
            save_checkpoint(checkpoint, agent, cfg, counters, fingerprint, rng)
            if stop.requested:
                raise Terminated(f"env step {step}")
    bar.close()
    return last_eval
