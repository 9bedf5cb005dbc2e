"""Fine-tuning throughput: agent updates/s (eager and compiled), acting steps/s, env steps/s with parallel envs.

    python bench/bench_agent.py                          # CPU: small sizes, eager and compiled, 1 and 2 envs
    python bench/bench_agent.py --device cuda            # GPU: Table 3 sizes, CUDA graphs, 1, 4 and 8 envs (~8 min)
    python bench/bench_agent.py --paper --compile off    # CPU: Table 3 sizes, eager only (tens of s per update)

Updates: the dual-stream agent on a freshly initialised export (timing does not depend on the weights'
values) and the scratch baseline with the same RSSM sizes, on a random 64×64 batch; one warm-up update
(for a compiled agent: the compilation, timed separately), then `--updates` timed ones. Acting: one
batched `Agent.act` on `--act-batches` frames at a time (one per env), in steps (frames) per second.
Envs: `--task` stepped with random actions as the training loop steps them (`finetune.envs.vector`: in
this process for one env, one worker process each for more), in agent steps per second summed over
the envs, after the workers have started (start-up timed separately), pinned to CPUs unless --no-pin-envs.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch._inductor.config

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.args import duration, task_name  # noqa: E402
from bench.machine import describe_machine  # noqa: E402
from hauwm.arguments import at_least  # noqa: E402
from finetune import load_pretrained  # noqa: E402
from finetune.agent import Agent  # noqa: E402
from finetune.config import FinetuneConfig  # noqa: E402
from finetune.envs.vector import EnvWorkerError, make_vector_env  # noqa: E402  (sets MUJOCO_GL: the settings line shows the choice)
from finetune.pretrained import k1_embedding  # noqa: E402
from model.config import WorldModelConfig  # noqa: E402
from model.export import export_frozen  # noqa: E402
from model.world_model import WorldModel  # noqa: E402

ACTION_DIM = 6  # cheetah
SETTINGS = {
    # name: (export sizes, agent config)
    "paper (32x50, 400 units, cnn 32)": (dict(), dict(batch_size=32, seq_len=50)),
    "small (16x32, 200 units, cnn 16)": (dict(cnn_width=16, embed_dim=256, deter=100, stoch=20, hidden=100),
                                         dict(batch_size=16, seq_len=32, units=200, hidden=100, encoder_width=16)),
}


def build(export_sizes: dict, agent_cfg: dict, agent_kind: str, device: torch.device, compile_mode: str | None,
          conv_bf16: bool = False) -> tuple[Agent, FinetuneConfig]:
    torch.manual_seed(0)
    cfg = FinetuneConfig(agent=agent_kind, conv_bf16=conv_bf16, **agent_cfg)
    if agent_kind == "scratch":  # same RSSM sizes as the export, its own encoder and decoder
        sizes = {k: export_sizes[k] for k in ("deter", "stoch") if k in export_sizes}
        agent = Agent(dataclasses.replace(cfg, **sizes), ACTION_DIM)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            frozen = load_pretrained(export_frozen(WorldModel(WorldModelConfig(**export_sizes)), tmp))
        agent = Agent(cfg, ACTION_DIM, frozen, k1_embedding(frozen))
    agent = agent.to(device)
    agent.set_compile(compile_mode)
    return agent, cfg


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def bench_updates(agent: Agent, cfg: FinetuneConfig, updates: int) -> tuple[float, float]:
    """-> (seconds of the first update, which compiles a compiled agent; updates per second after it)."""
    rng = np.random.default_rng(0)
    shape = (cfg.batch_size, cfg.seq_len)
    batch = {"obs": rng.integers(0, 256, (*shape, 3, 64, 64), dtype=np.uint8),
             "action": rng.uniform(-1, 1, (*shape, ACTION_DIM)).astype(np.float32),
             "reward": rng.normal(size=shape).astype(np.float32)}
    start = time.perf_counter()
    agent.update(batch)
    sync(agent.device)
    first = time.perf_counter() - start
    agent.update(batch)  # CUDA graphs are recorded on the second call
    sync(agent.device)
    start = time.perf_counter()
    for _ in range(updates):
        metrics = agent.update(batch)
    float(metrics["model_loss"])  # waits for the device, as the training loop's log does
    return first, updates / (time.perf_counter() - start)


def bench_acting(agent: Agent, envs: int, seconds: float) -> tuple[float, float]:
    """-> (seconds of the first action, actions (frames) per second for `envs` frames at a time)."""
    obs = np.random.default_rng(0).integers(0, 256, (envs, 3, 64, 64), dtype=np.uint8)
    latent, prev_action = agent.initial(envs)
    start = time.perf_counter()
    _, latent, prev_action = agent.act(obs, latent, prev_action, explore=True)
    first = time.perf_counter() - start
    _, latent, prev_action = agent.act(obs, latent, prev_action, explore=True)  # CUDA graphs: recorded on the second
    calls, start = 0, time.perf_counter()
    while calls < 3 or time.perf_counter() - start < seconds:
        _, latent, prev_action = agent.act(obs, latent, prev_action, explore=True)  # includes the copy to the host
        calls += 1
    return first, envs * calls / (time.perf_counter() - start)


def bench_envs(task: str, num_envs: int, seconds: float, fast_render: bool, pin: bool) -> tuple[float, float]:
    """-> (seconds to start the envs, agent steps per second summed over them)."""
    start = time.perf_counter()
    envs = make_vector_env(task, list(range(num_envs)), pin, fast_render=fast_render)
    envs.reset()
    envs.action_space.seed(0)
    started = time.perf_counter() - start
    envs.step(envs.action_space.sample())  # warm-up: the first render allocates buffers
    steps, start = 0, time.perf_counter()
    while steps < 3 or time.perf_counter() - start < seconds:
        envs.step(envs.action_space.sample())
        steps += 1
    rate = num_envs * steps / (time.perf_counter() - start)
    envs.close()
    return started, rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--paper", action="store_true", help="Table 3 sizes (the default on cuda; small on cpu)")
    parser.add_argument("--agents", nargs="+", default=["hauwm", "scratch"], choices=["hauwm", "scratch"])
    parser.add_argument("--compile", default=None, choices=["off", "default", "reduce-overhead"],
                        help="compiled mode to compare with eager (default: reduce-overhead on cuda, default on cpu)")
    parser.add_argument("--conv-bf16", action="store_true", help="also time eager updates with conv_bf16")
    parser.add_argument("--updates", type=at_least(1), default=None, help="timed updates (default: 20 on cuda, 2 on cpu)")
    parser.add_argument("--threads", type=at_least(1), default=1, help="torch CPU threads")
    parser.add_argument("--act-batches", nargs="*", type=at_least(1), default=None, help="frames per act call (default 1 4 8)")
    parser.add_argument("--task", type=task_name, default=None, help="env for the env section (default: dmc_cheetah_run on cuda, "
                                                     "metaworld_drawer_close with fast rendering on cpu)")
    parser.add_argument("--envs", nargs="*", type=at_least(1), default=None, help="env counts (default: 1 4 8 on cuda, 1 2 on cpu)")
    parser.add_argument("--fast-render", action=argparse.BooleanOptionalAction, default=None,
                        help="fast rendering in the env section (default: off on cuda, on on cpu)")
    parser.add_argument("--pin-envs", action=argparse.BooleanOptionalAction, default=True,
                        help="pin the env workers to CPUs, as training does by default (setting pin_envs)")
    parser.add_argument("--seconds", type=duration, default=10.0, help="time per acting and env measurement")
    args = parser.parse_args()
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    if cuda and not torch.cuda.is_available():
        parser.error("--device cuda: no CUDA device is visible")
    torch.set_num_threads(args.threads)
    if not cuda:  # inductor's pool of compile workers is slower than compiling in-process on a few shared cores
        torch._inductor.config.compile_threads = 1
    setting = list(SETTINGS)[0 if cuda or args.paper else 1]
    export_sizes, agent_cfg = SETTINGS[setting]
    compiled = args.compile or ("reduce-overhead" if cuda else "default")
    modes = [None] + ([] if compiled == "off" else [compiled])
    updates = args.updates or (20 if cuda else 2)
    act_batches = [1, 4, 8] if args.act_batches is None else args.act_batches
    task = args.task or ("dmc_cheetah_run" if cuda else "metaworld_drawer_close")
    env_counts = args.envs if args.envs is not None else ([1, 4, 8] if cuda else [1, 2])
    fast_render = (not cuda) if args.fast_render is None else args.fast_render

    print(f"machine: {describe_machine(str(device))}")
    print(f"settings: {setting}, imagination horizon 15, {updates} timed updates after warm-up; {args.threads} torch "
          f"thread(s), MUJOCO_GL={os.environ.get('MUJOCO_GL', 'unset')}")
    print(f"\n{'agent':<8} {'mode':<16} {'first update s':>15} {'updates/s':>10}")
    for kind in args.agents:
        for mode in modes:
            agent, cfg = build(export_sizes, agent_cfg, kind, device, mode)
            first, rate = bench_updates(agent, cfg, updates)
            print(f"{kind:<8} {mode or 'eager':<16} {first:>15.1f} {rate:>10.3f}", flush=True)
        if args.conv_bf16:
            agent, cfg = build(export_sizes, agent_cfg, kind, device, None, conv_bf16=True)
            first, rate = bench_updates(agent, cfg, updates)
            print(f"{kind:<8} {'eager, conv_bf16':<16} {first:>15.1f} {rate:>10.3f}", flush=True)
    if cuda:
        print(f"peak GPU memory {torch.cuda.max_memory_allocated(device) / 2**30:.1f} GiB")

    if act_batches:
        print(f"\n{'acting (hauwm)':<16} {'frames per call':>15} {'first call s':>13} {'steps/s':>9}")
        for mode in modes:
            agent, _ = build(export_sizes, agent_cfg, "hauwm", device, mode)
            for envs in act_batches:
                first, rate = bench_acting(agent, envs, args.seconds)
                print(f"{mode or 'eager':<16} {envs:>15} {first:>13.1f} {rate:>9.1f}", flush=True)

    if env_counts:
        render = "fast rendering" if fast_render else "default rendering"
        pinning = "workers pinned to CPUs" if args.pin_envs else "workers not pinned"
        print(f"\nenvs: {task}, {render}, {pinning}, random actions; agent steps/s summed over the envs")
        print(f"{'envs':>5} {'start s':>8} {'steps/s':>9} {'vs first':>9}")
        single = None
        for count in env_counts:
            try:
                started, rate = bench_envs(task, count, args.seconds, fast_render, args.pin_envs)
            except EnvWorkerError as error:  # the workers' own lines are above; the other counts may still run
                print(f"{count:>5} failed: {error}", flush=True)
                continue
            single = single or rate
            print(f"{count:>5} {started:>8.1f} {rate:>9.1f} {rate / single:>8.2f}x", flush=True)


if __name__ == "__main__":
    main()
