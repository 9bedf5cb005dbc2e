"""A fine-tuning run directory (--logdir): its checkpoints, the rules for resuming one, its lock.

The run directory holds `checkpoint.pt` (CHECKPOINT), `best.pt` (BEST), `config.yaml`, `.lock` (LOCK), the
replay's episodes in `replay/` (finetune/replay.py) and the CSV logs (finetune/logger.py). A checkpoint
(save_checkpoint) holds the agent's trainable weights and its optimisers, torch's random state (and CUDA's),
the replay sampler's state, the run's counters, its settings and its fingerprint (the sha256 of the frozen export's
weights and, for offline RL and imitation, of the dataset's files); not the frozen export itself, the dataset nor
the replay's episodes; a diverged agent (a weight not finite) is not written (DivergedError), so as not to replace
the last good checkpoint. `best.pt` is the same, written by keep_best at each
evaluation with the highest mean return so far (its counters keep best_return and best_at).

Starting a run in a directory that holds a checkpoint resumes it (`resume`). Reading a checkpoint (read_state)
needs the same export and the settings that shape the agent, and resuming one the same dataset too (playing its
agent, `load_trained`, does not read the dataset); a resume may change only the
RESUMABLE settings (budget, evaluation, logging and checkpoint cadence, how the run computes). A setting a
checkpoint predates counts with the value runs had before it (settings_before_they_existed). A directory with
a config.yaml but no checkpoint (a run stopped before its first) is refused if its settings differ. One
process at a time holds a run directory (`exclusive`). `load_trained` reads a run's agent back from a checkpoint, for
`hauwm finetune evaluate`, the dataset sources and the benches.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import torch
import yaml

from finetune.agent import Agent, DivergedError
from finetune.config import FinetuneConfig, FinetuneError, load_config, others_settings, step_unit
from hauwm.atomic import written_whole
from hauwm.messages import first_line
from hauwm.pid_lock import LockHeld, pid_lock
from model.config import ConfigError
from model.export import WEIGHTS_FILE, damaged_record, non_finite, torch_load_failure

CHECKPOINT = "checkpoint.pt"
BEST = "best.pt"  # the agent at its best evaluation so far (keep_best)
LOCK = ".lock"


@contextlib.contextmanager
def exclusive(logdir: Path) -> Iterator[None]:
    """Hold an exclusive lock on `logdir` (released when the run ends, also if it is killed): two runs
    writing one run directory would interleave their replay files and overwrite each other's checkpoint. A run that
    wrote nothing but its lock (one refused at its start) leaves no trace: the lock and the directories it made go
    (a directory that held files before keeps them)."""
    made = [directory for directory in (logdir, *logdir.parents) if not directory.exists()]  # deepest first
    lock_made = not (logdir / LOCK).exists()
    logdir.mkdir(parents=True, exist_ok=True)
    there = {path.name for path in logdir.iterdir()}
    with contextlib.ExitStack() as held:
        try:
            held.enter_context(pid_lock(logdir / LOCK))
        except LockHeld as other:
            raise FinetuneError(f"{logdir} is in use by another run (pid {other.pid}): wait for it to finish or pass "
                                "another --logdir") from None
        try:
            yield
        finally:
            if lock_made and {path.name for path in logdir.iterdir()} == there | {LOCK}:
                (logdir / LOCK).unlink()
                for directory in made:
                    with contextlib.suppress(OSError):  # another process has written there meanwhile: it stays
                        directory.rmdir()


# what a run trains on, as a checkpoint records it: "export_sha256" ('' for the scratch baseline) and, for offline RL
# and imitation, "dataset_sha256"
Fingerprint = dict[str, str]


def files_sha256(paths: Iterable[Path], root: Path) -> str:
    """sha256 of the files `paths` (under `root`): their paths relative to root and their bytes, in sorted order."""
    digest = hashlib.sha256()
    for path in sorted(paths):
        digest.update(str(path.relative_to(root)).encode() + b"\0")
        with open(path, "rb") as file:
            digest.update(hashlib.file_digest(file, "sha256").digest())
    return digest.hexdigest()


def export_fingerprint(pretrained: str | Path | None) -> str:
    """sha256 of the export's weights ('' for the scratch baseline): a resume must use the same export."""
    if pretrained is None:
        return ""
    with open(Path(pretrained) / WEIGHTS_FILE, "rb") as weights:
        return hashlib.file_digest(weights, "sha256").hexdigest()


def run_fingerprint(cfg: FinetuneConfig, pretrained: str | Path | None) -> Fingerprint:
    """What the run of `cfg` trains on: the export (hauwm agents) and the dataset of an offline run (--dataset) or
    the demonstrations of an imitation run (--demos): a dataset collected again under the same ID differs."""
    from finetune.datasets.minari_io import dataset_path

    fingerprint = {"export_sha256": export_fingerprint(pretrained if cfg.agent == "hauwm" else None)}
    _, dataset_id = cfg.training_data
    if dataset_id:
        root = dataset_path(dataset_id)
        fingerprint["dataset_sha256"] = files_sha256([path for path in root.rglob("*") if path.is_file()], root)
    return fingerprint


def save_checkpoint(path: Path, agent: Agent, cfg: FinetuneConfig, counters: dict[str, float],
                    fingerprint: Fingerprint, rng: np.random.Generator | None = None) -> None:
    """Write the agent's trainable weights, its optimisers, torch's random state(s), `counters`, cfg and the run's
    fingerprint to `path` (written whole: hauwm.atomic, so an interrupted write keeps the last checkpoint). `rng`: the
    replay's sampler, saved so that a resumed run draws the batches an unbroken run would."""
    weights = agent.trainable_state_dict()
    if diverged := non_finite(weights):
        raise DivergedError(f"the agent's weights are not finite (NaN or inf; e.g. {diverged[0]}): the agent has "
                            f"diverged, and {path.name} was not written over; lower model_lr, actor_lr or critic_lr, "
                            "and start a new run")
    state = {"agent": weights, "optimizers": agent.optimizer_state_dicts(),
             "counters": counters, "config": dataclasses.asdict(cfg), "torch_rng": torch.get_rng_state(),
             **fingerprint}
    if agent.device.type == "cuda":  # the world model's noise and the actor's samples are drawn there
        state["cuda_rng"] = torch.cuda.get_rng_state(agent.device)
    if rng is not None:
        state["replay_rng"] = rng.bit_generator.state
    try:
        with written_whole(path) as partial:
            torch.save(state, partial)
    except (OSError, RuntimeError) as err:  # torch's zip writer reports a full disk as a RuntimeError
        raise FinetuneError(f"{path} could not be written ({first_line(err)}; a full disk or quota?); what "
                            "was written before is kept: free some space and run the same command again (it goes on "
                            "from the last checkpoint)") from None


def keep_best(logdir: Path, agent: Agent, cfg: FinetuneConfig, counters: dict[str, float], fingerprint: Fingerprint,
              result: dict[str, float], step: int) -> None:
    """Save the agent to logdir/BEST when evaluation `result` (at `step`) has the run's highest mean return so
    far (the first of equals); `counters` keep that return and step, so a resumed run goes on comparing."""
    if result["return"] <= counters.get("best_return", -np.inf):
        return
    counters["best_return"], counters["best_at"] = result["return"], step
    save_checkpoint(logdir / BEST, agent, cfg, counters, fingerprint)


def settings_before_they_existed(paradigm: str) -> dict[str, object]:
    """What a run written before these settings existed had: its checkpoint and config.yaml lack them."""
    before: dict[str, object] = {"paradigm": "online", "model_heads": 1, "dataset": None, "demos": None}
    if paradigm == "imitation":
        before["expert_latents"] = "posterior"  # VMAIL's expert pairs, the only kind before the setting
    return before


def read_state(path: Path, cfg: FinetuneConfig, fingerprint: Fingerprint, remedy: str | None = None,
               training: bool = True) -> dict:
    """What save_checkpoint wrote to `path` (checkpoint.pt or best.pt), checked to be of this run: the same export,
    the same dataset (of the keys in `fingerprint`; a checkpoint that predates one is not checked for it) and the
    settings that shape the agent; a FinetuneError naming the file (and `remedy` if it cannot be read). `training`:
    read to train on (a resume), so training in another --logdir is a way out; otherwise read to play the agent
    (evaluate, collect), whose settings are the run's config.yaml.
    Read onto the CPU whatever the agent's device: loading the weights and optimizer states copies them to it,
    and torch.set_rng_state takes a CPU tensor only."""
    anew = ", or train in another --logdir" if training else ""
    remedy = remedy or f"restore it{anew}"
    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)  # best.pt at start: counters only
    except Exception as err:
        raise FinetuneError(f"{path} cannot be read ({torch_load_failure(err)}): {remedy}") from None
    if damaged := damaged_record(path):  # torch.load reads bytes changed in place (a disk, a copy) without a word
        raise FinetuneError(f"{path} is damaged: its record {damaged} fails its checksum (a disk or copy error): "
                            f"{remedy}")
    if not (isinstance(state, dict) and {"agent", "config", "counters", "export_sha256"} <= state.keys()):
        what = f"keys {', '.join(sorted(map(str, state))[:4])}" if isinstance(state, dict) else type(state).__name__
        raise FinetuneError(f"{path} is not a checkpoint of `hauwm finetune` (it holds {what}): {remedy}")
    shaping = ("task", "agent", "action_repeat", "deter", "stoch", "hidden", "units", "layer_norm",
               *settings_before_they_existed(cfg.paradigm))
    if differing := differing_settings(cfg, state["config"], shaping):
        key, written = differing[0]
        asked = (f"this run has {key}={getattr(cfg, key)!r}: use the same settings{anew}" if training else
                 f"{Path(cfg.logdir) / 'config.yaml'} says {key}={getattr(cfg, key)!r}: restore the run's config.yaml")
        raise FinetuneError(f"{path} was written by a run with {key}={written!r}, {asked}")
    if state["export_sha256"] != fingerprint["export_sha256"]:
        anew_elsewhere = " (or, to train anew, another --logdir)" if training else ""
        raise FinetuneError(f"{path} was trained on another --pretrained export (weights sha256 differs): "
                            f"pass the export it was trained on{anew_elsewhere}")
    if (dataset := fingerprint.get("dataset_sha256")) is not None and state.get("dataset_sha256", dataset) != dataset:
        flag, dataset_id = cfg.training_data
        raise FinetuneError(f"{path} was trained on another version of {flag} {dataset_id} (its files' sha256 "
                            "differs: collected again, merged or changed since): restore the dataset it was trained "
                            "on, or train in another --logdir")
    return state


# what a resume may change: the budget, the evaluation, logging and checkpoint cadence, and how the run computes
# (these change what is learned only by rounding, or by drawing other random numbers: num_envs, compile, device); any
# other setting stays as the run began
RESUMABLE = ("steps", "logdir", "eval_every", "eval_episodes", "log_every", "checkpoint_every", "device", "threads",
             "compile", "conv_bf16", "num_envs", "pin_envs")


def differing_settings(cfg: FinetuneConfig, written: dict[str, object],
                       keys: Iterable[str]) -> list[tuple[str, object]]:
    """(key, value written) for each of `keys` whose value in `written` (a checkpoint's settings) is not cfg's; a
    setting the checkpoint predates counts with the value runs had before it (settings_before_they_existed), or
    None."""
    values = {**settings_before_they_existed(cfg.paradigm), **written}
    return [(key, values.get(key)) for key in keys if hasattr(cfg, key) and values.get(key) != getattr(cfg, key)]


def changed_settings(cfg: FinetuneConfig, written: dict[str, object]) -> list[str]:
    """`key=written (asked: cfg's)` for each setting outside RESUMABLE whose value in `written` is not cfg's; the
    settings only another paradigm reads do not count (a run recorded them, and ignored them, before they were
    refused: `hauwm finetune` now refuses them, so the resume must go on without them)."""
    unread = others_settings(cfg.paradigm)
    keys = [key for key in written if key not in RESUMABLE and key not in unread]
    return [f"{key}={value!r} (asked: {getattr(cfg, key)!r})" for key, value in differing_settings(cfg, written, keys)]


def refuse_changed_settings(cfg: FinetuneConfig, written: dict[str, object], path: Path) -> None:
    """A FinetuneError if `cfg` resumes the checkpoint at `path` (trained with the settings `written`) with a setting
    outside RESUMABLE changed: part of the run would have learned with one value and part with another, and
    config.yaml keeps only the last."""
    if changed := changed_settings(cfg, written):
        raise FinetuneError(f"{path} was trained with {', '.join(changed[:3])}: a resume goes on with the settings "
                            f"the run began with (only {', '.join(RESUMABLE)} may change); drop the change, or train "
                            "in another --logdir")


def refuse_other_run(cfg: FinetuneConfig) -> None:
    """A FinetuneError if cfg.logdir (which holds no checkpoint) holds the config.yaml of a run that stopped before its
    first checkpoint with other settings than cfg's (outside RESUMABLE): starting again there would train on that
    run's replay episodes (offline RL keeps none) and overwrite its config.yaml; or files of something else than a
    run (a user's, an export), or another program's config.yaml."""
    logdir = Path(cfg.logdir)
    path = logdir / "config.yaml"
    if not path.is_file():  # this run's own lock aside, files of something else: mixed in, or overwritten
        if others := sorted(entry.name for entry in logdir.iterdir() if entry.name != LOCK):
            raise FinetuneError(f"{logdir} holds files but no `hauwm finetune` run (no config.yaml nor checkpoint; e.g. "
                                f"{others[0]}), which this run would mix with its own or overwrite: train in another "
                                "--logdir, or empty that one first")
        return
    try:
        written = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        written = None  # unreadable: nothing to compare with; it is written again
    if isinstance(written, dict) and not {"task", "agent"} <= written.keys():
        raise FinetuneError(f"{path} is not the config of a `hauwm finetune` run (it has no task or agent), and would "
                            "be overwritten: train in another --logdir")
    if isinstance(written, dict) and (changed := changed_settings(cfg, written)):
        mixed = ("this one would replace its config.yaml and logs" if cfg.paradigm == "offline" else  # no replay
                 "its replay episodes would train this one")
        raise FinetuneError(f"{cfg.logdir} holds a run with {', '.join(changed[:3])} that stopped before its first "
                            f"checkpoint; {mixed}: train in another --logdir, or delete {cfg.logdir} first")


def saved_agents(logdir: Path) -> str:
    """What a run keeps of its agent, for one that diverged: checkpoint.pt and best.pt as last saved, or none."""
    kept = [name for name in (CHECKPOINT, BEST) if (logdir / name).is_file()]
    if not kept:
        return "no checkpoint had been written yet"
    return f"{' and '.join(kept)} in {logdir} hold{'s' if len(kept) == 1 else ''} the agent as last saved"


def load_checkpoint(path: Path, agent: Agent, cfg: FinetuneConfig, fingerprint: Fingerprint,
                    rng: np.random.Generator | None = None, resuming: bool = False) -> dict[str, float]:
    """Restore `agent` (weights, optimizers), torch's and `rng`'s states from `path`; -> its counters. `resuming`:
    `cfg` goes on training it, so only RESUMABLE settings may differ from those it was trained with; otherwise the
    agent is played (evaluate, collect)."""
    state = read_state(path, cfg, fingerprint, training=resuming)
    if resuming:
        refuse_changed_settings(cfg, state["config"], path)
    missing, unexpected = agent.load_state_dict(state["agent"], strict=False)
    missing = [k for k in missing if not k.startswith("world_model.frozen.")]
    if missing or unexpected:
        raise FinetuneError(f"{path} does not fit this agent (missing {missing[:3]}, unexpected {unexpected[:3]})")
    agent.load_optimizer_state_dicts(state["optimizers"])
    torch.set_rng_state(state["torch_rng"])
    if "cuda_rng" in state and agent.device.type == "cuda":
        torch.cuda.set_rng_state(state["cuda_rng"], agent.device)
    if rng is not None and "replay_rng" in state:
        rng.bit_generator.state = state["replay_rng"]
    return dict(state["counters"])


def next_multiple(step: int, every: int) -> int:
    """The first multiple of `every` after `step` (the next log, evaluation or checkpoint)."""
    return (step // every + 1) * every


def resume(cfg: FinetuneConfig, agent: Agent, fingerprint: Fingerprint, counters: dict[str, float],
           rng: np.random.Generator) -> dict[str, float]:
    """A run's start in cfg.logdir: its checkpoint if there is one (it restores the agent and `rng` and gives the
    counters; a fresh run keeps `counters`, once refuse_other_run lets it start), the best return best.pt holds if it
    is higher than the counters', and config.yaml written. -> the counters."""
    checkpoint = Path(cfg.logdir) / CHECKPOINT
    if checkpoint.exists():
        counters = load_checkpoint(checkpoint, agent, cfg, fingerprint, rng, resuming=True)
        unit, key = step_unit(cfg.paradigm)
        for name, every in (("next_eval", cfg.eval_every), ("next_checkpoint", cfg.checkpoint_every),
                            ("next_log", cfg.log_every)):  # a cadence lowered on resume applies from here on
            counters[name] = min(counters[name], next_multiple(int(counters[key]), every))
        print(f"resuming {checkpoint} at {unit} {int(counters[key])}", file=sys.stderr)
    else:
        refuse_other_run(cfg)
    best = Path(cfg.logdir) / BEST
    if best.exists():  # a run stopped between keeping an evaluation and its next checkpoint: its best.pt is better
        #                than the checkpoint's counters know, and a worse evaluation must not replace it on resume
        kept = read_state(best, cfg, fingerprint, remedy="restore it, or move it away to go on "
                          "without it (the run then keeps its next best evaluation)")["counters"]
        if kept.get("best_return", -np.inf) > counters.get("best_return", -np.inf):
            counters.update(best_return=kept["best_return"], best_at=kept["best_at"])
    with written_whole(Path(cfg.logdir) / "config.yaml") as partial:  # `evaluate` reads it, and may read it now
        partial.write_text(yaml.safe_dump(dataclasses.asdict(cfg), sort_keys=False))
    return counters


def run_config(logdir: str | Path, overrides: dict[str, object] | None = None) -> FinetuneConfig:
    """The FinetuneConfig a `hauwm finetune` run wrote to LOGDIR/config.yaml, with `overrides` and, for the settings
    the run predates, the values it ran with (settings_before_they_existed); a FinetuneError if there is none or
    it cannot be read."""
    path = Path(logdir) / "config.yaml"
    if not path.is_file():
        raise FinetuneError(f"{logdir} is not a `hauwm finetune` run directory (no config.yaml)")
    try:
        written = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError):
        written = None  # load_config below says what is wrong with the file
    written = written if isinstance(written, dict) else {}
    before = settings_before_they_existed(str(written.get("paradigm", "online")))
    older = {key: value for key, value in before.items() if key not in written}  # an older run's values
    try:
        return load_config(path, {**older, **(overrides or {})})
    except ConfigError as error:
        raise FinetuneError(f"{path}: {error}") from None


def load_trained(logdir: Path, pretrained: str | Path | None, action_dim: int,
                 device: torch.device = torch.device("cpu"), checkpoint: str = CHECKPOINT
                 ) -> tuple[FinetuneConfig, Agent, dict[str, float]]:
    """A run's agent (online, offline or imitation, as its config says) as its `checkpoint` (the last one, or
    BEST) left it, in eval mode: (the run's config, the agent, its counters then); to play it (datasets) and
    for benches and diagnoses."""
    from finetune.imitation import ImitationAgent
    from finetune.offline import OfflineAgent
    from finetune.train import build_agent  # here, not above: finetune.train imports this module

    logdir = Path(logdir)
    for name in ("config.yaml", checkpoint):
        if not (logdir / name).is_file():
            why = ("no evaluation has been kept (a run writes best.pt at its evaluations; older versions did not)"
                   if name == BEST else "not a run directory, or a run that has not checkpointed yet")
            raise FinetuneError(f"{logdir} holds no {name}: {why}")
    cfg = run_config(logdir, {"device": str(device)})
    if cfg.agent == "hauwm" and pretrained is None:
        raise FinetuneError(f"{logdir} trained agent 'hauwm' on a frozen export: pass that export with --pretrained "
                            "DIR (its sha256 is checked)")
    agent_class = {"online": Agent, "offline": OfflineAgent, "imitation": ImitationAgent}[cfg.paradigm]
    hauwm = pretrained if cfg.agent == "hauwm" else None
    agent = build_agent(cfg, action_dim, hauwm, device, agent_class)
    counters = load_checkpoint(logdir / checkpoint, agent, cfg, {"export_sha256": export_fingerprint(hauwm)})
    agent.eval()
    return cfg, agent, counters
