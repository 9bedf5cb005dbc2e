"""WorldModelConfig: a dict round trip, and every bad size refused with the field's name."""

from __future__ import annotations

import dataclasses

import pytest

from model.config import ConfigError, WorldModelConfig, saved_settings


def test_round_trips_through_a_plain_dict():
    config = WorldModelConfig(deter=64, temporal_mode="absolute")
    assert WorldModelConfig.from_dict(config.to_dict()) == config
    assert all(type(value) in (int, float, str) for value in config.to_dict().values())  # JSON and weights_only safe


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (dict(deter=0), "world_model.deter must be ≥ 1, got 0"),
        (dict(stoch=2.5), "world_model.stoch must be an integer, got 2.5"),
        (dict(ensemble=True), "world_model.ensemble must be an integer, got True"),
        (dict(min_std="0.1"), "world_model.min_std must be a number, got '0.1'"),
        (dict(min_std=1.0), "0 < min_std < max_std, got 1.0 and 1.0"),
        (dict(temporal_mode="log"), "world_model.temporal_mode must be one of ('relative', 'absolute'), got 'log'"),
        (dict(temporal_dim=7), "world_model.temporal_dim must be even"),
        (dict(reference_length=0), "world_model.reference_length must be positive, got 0"),
    ],
)
def test_bad_sizes_are_refused_by_name(change, message):
    with pytest.raises(ConfigError) as error:
        dataclasses.replace(WorldModelConfig(), **change).validate()
    assert message in str(error.value)


def test_from_dict_names_missing_and_unknown_keys():
    values = WorldModelConfig().to_dict()
    del values["deter"]
    with pytest.raises(ConfigError, match=r"lacks \['deter'\]; has unknown keys \['deter_size'\]"):
        WorldModelConfig.from_dict({**values, "deter_size": 200})


def test_saved_settings_read_nested_and_flat_hyper_parameters():
    sizes = WorldModelConfig(deter=64).to_dict()
    assert saved_settings({"world_model": sizes, "lr": 1e-3}) == sizes
    assert saved_settings({**sizes, "lr": 1e-3}) == sizes  # checkpoints written before WorldModelConfig
