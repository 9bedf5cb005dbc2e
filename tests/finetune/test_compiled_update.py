"""The compiled update and acting step (`compile` setting) agree with the eager ones.

Same seed, same batch: one update and one batched action, eagerly and through torch.compile. The fast
test uses dynamo's `eager` backend (graph capture only): it shows that every region is captured whole —
no graph break, so no host sync such as `.item()` inside — and that the results are bit-identical. The
slow test compiles with inductor (C++ on the CPU, the same code generator as for CUDA), whose fused
kernels round differently: losses and parameter updates agree within a tolerance. A compiled graph may
draw its random numbers in another order than eager code (torch 2.11's inductor does, even with
`fallback_random`; 2.14's does not), which changes which noise lands where but not the arithmetic, so
the slow test replaces the agent's random draws by fixed functions of their shape (`fixed_noise`).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch._dynamo
import torch._inductor.config
from torch._dynamo.utils import counters

from finetune.imitation import ImitationAgent
from finetune.offline import OfflineAgent
from finetune.pretrained import k1_embedding, load_pretrained
from model.compiling import compile_mode
from test_dual_stream import ACTION_DIM, make_agent, random_batch  # noqa: I001 (tests/finetune/test_dual_stream.py)

PARADIGMS = {"offline": (OfflineAgent, {"model_heads": 3}), "imitation": (ImitationAgent, {})}


def run(cfg, export_dir, compile_mode, agent_class=None, updates: int = 1):
    """`updates` updates and one action of a fresh agent (seed 0) → (the last update's metrics, parameters before,
    after, actions)."""
    torch.manual_seed(0)
    if agent_class is None:
        agent = make_agent(cfg, export_dir)
    else:
        frozen = load_pretrained(export_dir)
        agent = agent_class(cfg, ACTION_DIM, frozen, k1_embedding(frozen))
    agent.set_compile(compile_mode)
    before = {name: p.detach().clone() for name, p in agent.named_parameters()}
    batch = random_batch(cfg, np.random.default_rng(0))
    torch.manual_seed(1)
    for _ in range(updates):
        metrics = {name: float(value) for name, value in agent.update(batch).items()}
    latent, prev_action = agent.initial(2)
    actions, _, _ = agent.act(batch["obs"][:2, 0], latent, prev_action, explore=True)
    after = {name: p.detach().clone() for name, p in agent.named_parameters()}
    return metrics, before, after, actions


def small(tiny_config, agent_kind, **extra):
    return tiny_config(agent=agent_kind, seq_len=3, horizon=2, **extra)  # short unrolled loops: quicker to trace


@pytest.mark.parametrize("paradigm", ["online", *PARADIGMS])
def test_every_region_is_captured_whole_and_matches_eager_exactly(export_dir, tiny_config, monkeypatch, paradigm):
    """Offline RL's penalised reward and imitation's discriminator reward are traced inside the imagination region, and
    a second update runs the graphs of the first (nothing it keeps between updates makes them recompile)."""
    compile_ = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, mode: compile_(fn, backend="eager"))
    torch._dynamo.reset()
    counters.clear()
    agent_class, extra = PARADIGMS.get(paradigm, (None, {}))
    cfg = small(tiny_config, "hauwm", paradigm=paradigm, **extra)
    eager_metrics, before, eager_after, eager_actions = run(cfg, export_dir, None, agent_class, updates=2)
    metrics, _, after, actions = run(cfg, export_dir, "default", agent_class, updates=2)
    assert not counters["graph_break"], dict(counters["graph_break"])
    # model loss, imagination with both losses, acting: and the second update compiles nothing again
    assert counters["stats"]["unique_graphs"] == 3
    assert metrics == eager_metrics
    assert all(torch.equal(after[name], eager_after[name]) for name in after)
    assert any(not torch.equal(after[name], before[name]) for name in after)
    np.testing.assert_array_equal(actions, eager_actions)


@pytest.fixture
def fixed_noise(monkeypatch):
    """torch.rand, randn_like and randint (every random draw of an update and of acting) as fixed functions of
    the shape asked for: the same numbers in whatever order a compiled graph draws them."""

    def wave(shape, scale: float, device) -> torch.Tensor:  # deterministic values in [-1, 1]
        shape = tuple(shape[0]) if len(shape) == 1 and not isinstance(shape[0], int) else tuple(shape)
        return torch.sin(torch.arange(math.prod(shape), device=device, dtype=torch.float32) * scale).reshape(shape)

    monkeypatch.setattr(torch, "randn_like", lambda x: wave(x.shape, 0.731, x.device).to(x.dtype))
    monkeypatch.setattr(torch, "rand", lambda *size, dtype=None, device=None:
                        (0.5 + 0.49 * wave(size, 1.37, device)).to(dtype or torch.float32))
    monkeypatch.setattr(torch, "randint", lambda high, size, device=None:
                        ((0.5 + 0.49 * wave(size, 2.1, device)) * high).long())


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("agent_kind", ["hauwm", "scratch"])
def test_inductor_update_agrees_with_eager(export_dir, tiny_config, fixed_noise, agent_kind):
    """About a minute of CPU per agent; in-process compilation (one thread) is quickest on a small loaded machine."""
    torch._dynamo.reset()
    cfg = small(tiny_config, agent_kind)
    eager_metrics, before, eager_after, eager_actions = run(cfg, export_dir, None)
    with torch._inductor.config.patch(compile_threads=1):
        metrics, _, after, actions = run(cfg, export_dir, "default")
    assert metrics.keys() == eager_metrics.keys()
    for name, value in eager_metrics.items():
        assert metrics[name] == pytest.approx(value, rel=1e-4, abs=1e-6), name
    # the metrics include the three gradient norms; the Adam steps of all parameters together agree closely
    # (single elements with a gradient near zero, below Adam's ε, may step differently: rounding noise)
    step = torch.cat([(after[name] - before[name]).flatten() for name in after])
    eager_step = torch.cat([(eager_after[name] - before[name]).flatten() for name in after])
    assert (step - eager_step).norm() <= 0.02 * eager_step.norm()
    np.testing.assert_allclose(actions, eager_actions, atol=1e-5)


def test_compile_setting_resolves_per_device():
    """One reading of the setting for fine-tuning's `compile` and pre-training's `model.compile`."""
    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    assert compile_mode("auto", cuda) == "reduce-overhead" and compile_mode("auto", cpu) is None
    assert compile_mode("off", cuda) is None and compile_mode("off", cpu) is None
    assert compile_mode("default", cpu) == compile_mode("default", cuda) == "default"
    assert compile_mode("reduce-overhead", cuda) == "reduce-overhead"
    assert compile_mode("reduce-overhead", cpu) == "default"  # CUDA graphs need a GPU
    with pytest.raises(ValueError, match="compile must be one of auto, off, default, reduce-overhead, got 'fast'"):
        compile_mode("fast", cpu)
