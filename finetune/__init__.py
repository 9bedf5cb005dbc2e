"""Fine-tuning the frozen pre-trained world model for control (paper §4.3, appendix D; docs/finetuning.md).

    from finetune import load_pretrained
    frozen = load_pretrained("exports/hauwm")       # checked, frozen FrozenWorldModel

`hauwm finetune --config configs/finetune/<suite>_<task>.yaml --pretrained DIR` runs online RL
(finetune.cli); the environments are in finetune.envs.
"""

from __future__ import annotations

__all__ = ["load_pretrained"]


def __getattr__(name: str):
    # lazy, so that `import finetune.envs` does not import torch and the model package
    if name == "load_pretrained":
        from finetune.pretrained import load_pretrained

        return load_pretrained
    raise AttributeError(f"module 'finetune' has no attribute {name!r}")
