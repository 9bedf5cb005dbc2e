"""The world model's sizes in one place: WorldModelConfig (paper Table 3, appendix D.1).

Every setting that defines the architecture (and so the shapes of the exported weights) lives here, once:

- pre-training reads it as PretrainModule's `world_model` argument: `model.world_model.deter` in a config
  YAML, `--model.world_model.deter 200` on the command line (LightningCLI parses the dataclass as a group);
- checkpoints keep it as a plain dict under hyper_parameters["world_model"] (loadable with
  torch.load(weights_only=True)); checkpoints written before it existed hold the same keys flat;
- the export writes it under "world_model" in config.json (schema_version 2; version 1 held the keys flat),
  and fine-tuning rebuilds the frozen model from it.

`ConfigError` is every stage's error for a bad setting; `read_config_file` reads every stage's config files (with
`UniqueKeyLoader`, which refuses a key set twice).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from model.temporal import MODES


class ConfigError(ValueError):
    """A setting or combination of settings that cannot train; the message names the flag and the fix."""


def read_config_file(path: Path, example: str) -> dict:
    """The settings a YAML config file holds, read with UniqueKeyLoader. A file that is not YAML (or not UTF-8 text: a
    checkpoint) is a ConfigError naming the line and column where it went wrong; one with no settings (empty, or
    comments only: more likely a slip than a wish for every default) or not a mapping names what it holds, and
    `example`, the settings such a file holds."""
    try:
        settings = yaml.load(Path(path).read_text(), UniqueKeyLoader)
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"config file {path} is not valid YAML: {getattr(err, 'problem', None) or err}{where}") \
            from None
    if not isinstance(settings, dict):
        raise ConfigError(f"config file {path} holds {'no settings' if settings is None else repr(settings)[:40]}, not "
                          f"a mapping of settings ({example})")
    return settings


class UniqueKeyLoader(yaml.SafeLoader):
    """yaml.safe_load's loader, except that a key written twice in one mapping is an error (YAML itself keeps the
    last: a second `task:` further down a config would silently train another task)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: set[object] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"{key!r} is set twice: keep one",
                                                        key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


# a field's annotation → the Python types it accepts (an int where a float is asked is fine) and its name in errors
KINDS = {"int": (int, "an integer"), "float": ((int, float), "a number"), "str": (str, "a string")}


@dataclasses.dataclass(frozen=True)
class WorldModelConfig:
    """Sizes of the world model; the defaults are the paper's (Table 3).

    Attributes:
        cnn_width: channels of the encoder's first and the decoder's last stage
        embed_dim: size of the image embedding e_t
        deter: size of the deterministic (GRU) state h_t
        stoch: size of the stochastic (Gaussian) state z_t
        hidden: width of the RSSM's MLPs
        ensemble: M, the number of prior heads (Table 3: 7; appendix D.1: 5, configs/pretrain/ssv2-m5.yaml)
        min_std: lower bound of every std: min_std + (max_std − min_std) · sigmoid(x + 2) (model/rssm.py)
        max_std: upper bound of every std
        temporal_mode: Δt_k^e at position k / T · reference_length ("relative") or at k ("absolute")
        temporal_dim: size of Δt_k^e (even: sin and cos pairs)
        reference_length: the relative mode's position of a gap spanning the whole clip
    """

    cnn_width: int = 32
    embed_dim: int = 1024
    deter: int = 200
    stoch: int = 30
    hidden: int = 200
    ensemble: int = 7
    min_std: float = 0.1
    max_std: float = 1.0
    temporal_mode: str = "relative"
    temporal_dim: int = 32
    reference_length: float = 100.0

    def validate(self) -> WorldModelConfig:
        """Return self, or raise ConfigError naming the first bad field."""
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            accepted, what = KINDS[field.type]
            if isinstance(value, bool) or not isinstance(value, accepted):
                raise ConfigError(f"world_model.{field.name} must be {what}, got {value!r}")
            if field.type == "int" and value < 1:
                raise ConfigError(f"world_model.{field.name} must be ≥ 1, got {value}")
            if field.type == "float" and not math.isfinite(value):  # NaN passed every range check below
                raise ConfigError(f"world_model.{field.name} must be a finite number, got {value}")
        if self.temporal_mode not in MODES:
            raise ConfigError(f"world_model.temporal_mode must be one of {MODES}, got {self.temporal_mode!r}")
        if self.temporal_dim % 2:
            raise ConfigError(f"world_model.temporal_dim must be even (sin and cos pairs), got {self.temporal_dim}")
        if not 0 < self.min_std < self.max_std:
            raise ConfigError(f"world_model needs 0 < min_std < max_std, got {self.min_std} and {self.max_std}")
        if self.reference_length <= 0:
            raise ConfigError(f"world_model.reference_length must be positive, got {self.reference_length}")
        return self

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> WorldModelConfig:
        """Exactly the fields of this class, validated; ConfigError names missing and unknown keys."""
        names = [field.name for field in dataclasses.fields(cls)]
        missing = [name for name in names if name not in values]
        unknown = sorted(key for key in values if key not in names)
        if missing or unknown:
            raise ConfigError("world_model " + "; ".join(
                part for part in (missing and f"lacks {missing}", unknown and f"has unknown keys {unknown}") if part))
        return cls(**values).validate()


def saved_settings(hparams: Mapping[str, Any]) -> dict[str, Any]:
    """The world-model settings in a checkpoint's hyper_parameters: the dict under "world_model", or the
    same keys flat at the top level in checkpoints written before WorldModelConfig (possibly incomplete)."""
    if "world_model" in hparams:
        return dict(hparams["world_model"])
    return {field.name: hparams[field.name] for field in dataclasses.fields(WorldModelConfig) if field.name in hparams}
