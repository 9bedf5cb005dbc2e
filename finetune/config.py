"""Fine-tuning settings: one dataclass with the paper's Table 3 defaults, read from a YAML file.

A config file sets any subset of the fields below; `configs/finetune/<suite>_<task>.yaml` set the task,
its budget and its evaluation cadence. The counts `steps`, `prefill` and `*_every` are environment steps (frames:
one agent step is `action_repeat` of them), as in the paper's budgets; offline RL's `steps` and `*_every` count updates.
A setting's own value that is wrong is a ConfigError; `FinetuneError` is every other problem of a
fine-tuning run the user can fix (a flag, a run directory, a dataset), raised throughout finetune/.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import yaml

from model.compiling import COMPILE_SETTINGS
from model.config import ConfigError, read_config_file

PARADIGMS = ("online", "offline", "imitation")
# the settings only some paradigms read (the others' runs would ignore them): the paradigms -> their settings
PARADIGM_SETTINGS = {("offline",): ("dataset", "penalty", "penalty_scale", "penalty_frozen_weight"),
                     ("imitation",): ("demos", "demo_fraction", "disc_lr", "disc_gp_scale", "expert_latents"),
                     ("online", "imitation"): ("prefill", "train_every", "pin_envs")}  # the env-stepping loop's


ENV_SETTINGS = ("action_repeat", "time_limit", "fast_render")  # make_env's keyword arguments, FinetuneConfig's fields


def others_settings(paradigm: str) -> dict[str, tuple[str, ...]]:
    """The settings a `paradigm` run does not read, as other paradigms': setting -> the paradigms that read it."""
    return {key: owners for owners, keys in PARADIGM_SETTINGS.items() if paradigm not in owners for key in keys}

PENALTIES = ("loglik_std", "max_std", "mean_disagreement")
# settings that take one of a few words
CHOICES: dict[str, tuple[str, ...]] = {
    "agent": ("hauwm", "scratch"),
    "paradigm": PARADIGMS,
    "compile": COMPILE_SETTINGS,
    "imagine_heads": ("random", "mean"),
    "penalty": PENALTIES,
    "expert_latents": ("imagined", "posterior"),
}


# allowed ranges of the numeric settings: (names, the rule in words, the test); None ("the export's", "the suite's
# own") is not tested
RANGES: tuple[tuple[tuple[str, ...], str, Callable[[float], bool]], ...] = (
    (("seq_len",), "at least 2 (a window must hold a transition for the world model to learn)", lambda v: v >= 2),
    (("steps", "action_repeat", "time_limit", "replay_capacity", "batch_size", "train_every",
      "eval_every", "eval_episodes", "log_every", "checkpoint_every", "deter", "stoch", "hidden", "model_heads",
      "units", "encoder_width", "horizon", "num_envs"), "at least 1", lambda v: v >= 1),
    (("seed",), "in 0..2^31-1 (the run's env seeds are drawn above it, and an env seed must stay below 2^32)",
     lambda v: 0 <= v < 2**31),
    (("threads", "prefill", "noise_std", "kl_scale", "free_nats", "entropy_scale", "penalty_scale",
      "penalty_frozen_weight", "disc_gp_scale"), ">= 0", lambda v: v >= 0),
    (("model_lr", "actor_lr", "critic_lr", "disc_lr", "grad_clip", "k1_clip_length"), "> 0", lambda v: v > 0),
    (("gamma", "lam", "kl_balance"), "between 0 and 1", lambda v: 0 <= v <= 1),
    (("target_fraction",), "in (0, 1]", lambda v: 0 < v <= 1),
    (("demo_fraction",), "strictly between 0 and 1", lambda v: 0 < v < 1),
)


class FinetuneError(RuntimeError):
    """A problem the user can fix (bad flags, a run directory from another task); printed without a traceback."""


@dataclass
class FinetuneConfig:
    task: str = "dmc_cheetah_run"
    agent: str = "hauwm"  # "hauwm": dual-stream on the frozen export; "scratch": DreamerV2-like baseline
    paradigm: str = "online"  # "online" RL, "offline" RL or "imitation" (docs/downstream.md); set by the subcommand
    seed: int = 0
    logdir: str = "runs/finetune"
    device: str = "auto"  # "auto" (cuda when available), "cpu", "cuda" or "cuda:N"
    threads: int = 0  # torch CPU threads, 0 = torch's default
    # speed (docs/finetuning.md, "Speed"); a resume may change them: they change what is learned only by rounding, or
    # by drawing other random numbers (num_envs: other env seeds; compile and device: other random streams)
    compile: str = "auto"  # torch.compile of update and acting: auto, off, default, reduce-overhead (compiling.py)
    conv_bf16: bool = False  # bf16 autocast in the convolutional encoder and decoder
    num_envs: int = 1  # training envs; more than 1 steps them in worker processes while the learner trains
    pin_envs: bool = True  # pin those worker processes to CPUs, an equal share of each (finetune/envs/vector.py)
    # environment
    steps: int = 1_000_000  # env steps (frames), Table 3: DMC 1M, Meta-World and RoboDesk 250k
    action_repeat: int = 2
    time_limit: int | None = None  # agent steps per episode, None = the suite's own (DMC 1000 frames / repeat)
    fast_render: bool = False  # no shadows or multisampling (finetune/envs)
    # replay and schedule
    prefill: int = 10_000  # random-policy env steps before learning (Table 3; the text says 5,000)
    replay_capacity: int = 1_000_000
    batch_size: int = 32
    seq_len: int = 50
    train_every: int | None = None  # env steps (frames) per update; None = 5 × action_repeat (DreamerV2, APV)
    eval_every: int = 10_000
    eval_episodes: int = 10
    log_every: int = 1_000
    checkpoint_every: int = 50_000
    # world model (the new action-conditioned stream; the frozen stream's sizes come from the export)
    deter: int | None = None  # None: the export's size (200 for the scratch baseline); the decoder copy needs equal sizes
    stoch: int | None = None  # None: the export's size (30 for the scratch baseline)
    hidden: int = 200
    model_heads: int = 1  # prior heads of the new stream (offline RL's ensemble, LOMPO: 7); 1 = the paper's online agent
    imagine_heads: str = "random"  # with model_heads > 1, imagination draws s̃ from a "random" head per step and
    #                                trajectory (LOMPO: per step for the whole batch) or from the heads' "mean"
    units: int = 400  # reward head, actor and critic: 2 hidden layers × 400 ELU
    noise_std: float = 0.01  # Gaussian noise on the frozen stream's k = 1 temporal embedding
    k1_clip_length: float | None = None  # T of the k = 1 embedding (relative exports only); None: the export's median
    #                                        (of its pre-training clips; the reference length if it has none)
    kl_balance: float = 0.8
    kl_scale: float = 1.0
    free_nats: float = 1.0
    model_lr: float = 3e-4
    # scratch baseline only (the hauwm agent uses the export's encoder)
    encoder_width: int = 32
    # behaviour
    horizon: int = 15
    gamma: float = 0.99
    lam: float = 0.95
    actor_lr: float = 8e-5
    critic_lr: float = 8e-5
    entropy_scale: float = 1e-4
    target_fraction: float = 0.02
    grad_clip: float = 100.0
    layer_norm: bool = True  # LayerNorm before each ELU of actor and critic; not in Table 3 (docs/finetuning.md)
    # offline RL (`hauwm finetune offline`, eq. 6: r̃ = r − penalty_scale · u); steps and *_every count updates there
    dataset: str | None = None  # dataset id for finetune.datasets.load_episodes (--dataset)
    penalty: str = "loglik_std"  # u: "loglik_std" (LOMPO), "max_std" or "mean_disagreement" (offline DreamerV2)
    penalty_scale: float = 5.0  # λ of eq. 6 (LOMPO's default; offline DreamerV2 uses 10 with mean_disagreement)
    penalty_frozen_weight: float = 0.0  # weight of the frozen stream's head disagreement added to u (docs/downstream.md)
    # imitation (`hauwm finetune imitate`, eq. 5): no env reward is used for learning
    demos: str | None = None  # expert demonstrations' dataset id (--demos)
    demo_fraction: float = 0.5  # share of each world-model batch drawn from the demonstrations
    disc_lr: float = 8e-5  # discriminator Adam (VMAIL)
    disc_gp_scale: float = 10.0  # weight of its input-space gradient penalty (WGAN-GP / DAC)
    expert_latents: str = "imagined"  # expert pairs: imagined along the demos' actions, or their posteriors (VMAIL)

    @property
    def env_settings(self) -> dict[str, object]:
        """`make_env`'s keyword arguments for this config: the dynamics and frames its agent acts in."""
        return {name: getattr(self, name) for name in ENV_SETTINGS}

    @property
    def training_data(self) -> tuple[str, str | None]:
        """(the flag, the dataset ID) of the dataset this paradigm learns from: offline RL's --dataset, imitation's
        --demos; ("", None) for online RL."""
        setting = {"offline": "dataset", "imitation": "demos"}.get(self.paradigm)
        return (f"--{setting}", getattr(self, setting)) if setting else ("", None)

    def __post_init__(self) -> None:
        for name, allowed in CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ConfigError(f"setting {name} must be one of {', '.join(allowed)}; got {getattr(self, name)!r}")
        for names, rule, allowed in RANGES:
            for name in names:
                value = getattr(self, name)
                if value is not None and not (math.isfinite(value) and allowed(value)):
                    rule = rule if math.isfinite(value) else "a finite number"
                    raise ConfigError(f"setting {name} must be {rule}, got {value!r}")
        if not str(self.logdir).strip():  # an unset shell variable: the run would fill the current directory
            raise ConfigError("setting logdir is empty (an unset shell variable?): name the run's directory")
        if self.train_every is None:  # DreamerV2 and APV update once every 5 agent steps, each action_repeat frames
            self.train_every = 5 * self.action_repeat
        if self.paradigm == "offline" and self.penalty != "max_std" and self.penalty_scale > 0 and self.model_heads < 2:
            raise ConfigError(f"penalty {self.penalty!r} measures disagreement between the new stream's prior heads: "
                              f"offline RL needs model_heads >= 2 (LOMPO: 7), got {self.model_heads}; or penalty_scale=0")
        if self.agent == "scratch" and self.penalty_frozen_weight > 0:
            raise ConfigError("penalty_frozen_weight needs the frozen stream: the scratch agent has none; set it to 0")
        frozen_only = ("noise_std", "k1_clip_length")  # the frozen stream's k = 1 embedding
        if self.agent == "scratch" and (changed := [key for key in frozen_only
                                                    if getattr(self, key) != getattr(FinetuneConfig, key)]):
            raise ConfigError(f"{changed[0]} sets the frozen stream's k = 1 embedding: the scratch agent has no frozen "
                              "stream; drop it")


WHERE_CONFIGS_ARE = "the configs are in configs/finetune/, configs/offline/ and configs/imitation/"


def step_unit(paradigm: str) -> tuple[str, str]:
    """What a paradigm's `steps` and cadences count, as (its words, its counters' key): offline RL never acts, so it
    counts gradient updates; online RL and imitation count env steps."""
    return ("update", "updates") if paradigm == "offline" else ("env step", "env_step")


def load_config(path: str | Path | None, overrides: dict[str, object] | None = None) -> FinetuneConfig:
    """Read a YAML config (None: the defaults) and apply `overrides`; unknown keys are an error."""
    values: dict[str, object] = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            what = "is a directory, not a YAML file" if path.is_dir() else "not found"
            raise ConfigError(f"config file {path} {what} ({WHERE_CONFIGS_ARE})")
        values = read_config_file(path, f"a config names at least its task: {WHERE_CONFIGS_ARE}")
    fields = {f.name: f for f in dataclasses.fields(FinetuneConfig)}
    for source, settings in ((f"config file {path}", values), ("the overrides (--set)", overrides or {})):
        if unknown := sorted(set(settings) - set(fields)):
            named = [f"{name} (did you mean {close[0]}?)" if (close := difflib.get_close_matches(name, fields, 1))
                     else name for name in unknown]
            raise ConfigError(f"unknown setting(s) in {source}: {', '.join(named)}; the settings: {', '.join(sorted(fields))}")
    values.update(overrides or {})
    if values.get("compile") is False:  # YAML reads a bare `off` as false
        values["compile"] = "off"
    types = typing.get_type_hints(FinetuneConfig)
    for name, value in values.items():
        if value is None and type(None) in typing.get_args(types[name]):
            continue  # None: "the export's", "the suite's own" or "not given"
        if types[name] is bool and not isinstance(value, bool):
            raise ConfigError(f"setting {name} must be true or false, got {value!r}")
        if types[name] in (str, str | None) and not isinstance(value, str):  # YAML reads yes, on, true as true
            wanted = f"one of {', '.join(CHOICES[name])}" if name in CHOICES else "text"
            raise ConfigError(f"setting {name} must be {wanted}, got {value!r}")
        if types[name] in (int, float, int | None, float | None):
            try:
                if isinstance(value, bool) or not isinstance(value, (int, float, str)):
                    raise ValueError
                number = float(value)  # YAML reads 1e6 as a string
            except ValueError:
                raise ConfigError(f"setting {name} must be a number, got {value!r}") from None
            whole = types[name] in (int, int | None)
            if whole and not number.is_integer():
                raise ConfigError(f"setting {name} must be a whole number, got {value!r}")
            values[name] = int(number) if whole else number
    return FinetuneConfig(**values)


def parse_override(text: str) -> tuple[str, object]:
    """`key=value` with the value read as YAML (so numbers, booleans and null get their types)."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise ConfigError(f"--set expects key=value, got {text!r}")
    try:
        return key.strip(), yaml.safe_load(value)
    except yaml.YAMLError:  # not YAML (e.g. "[1"): the text itself, which the setting's own check then judges
        return key.strip(), value
