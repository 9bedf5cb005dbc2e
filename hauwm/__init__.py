"""HAUWM: pre-training world models with horizon-calibrated uncertainty (the `hauwm` command)."""

__version__ = "0.1.0"
