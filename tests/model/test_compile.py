"""model.compile: the compiled training losses (inductor on the CPU here, with gcc) equal the eager ones, and
"reduce-overhead" (CUDA graphs) falls back to inductor's default mode off the GPU with a one-line note."""

from __future__ import annotations

import logging

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader

from model.config import WorldModelConfig
from model.module import PretrainModule, compiled


def losses_and_gradients(module: PretrainModule, function, batch: dict, noise: torch.Tensor):
    module.zero_grad(set_to_none=True)
    terms = function(batch["frames"], batch["gaps"], batch["num_frames"], noise)
    terms["loss"].backward()
    return terms, {name: p.grad.clone() for name, p in module.world_model.named_parameters()}


@pytest.mark.slow
def test_compiled_losses_and_gradients_equal_eager(small_sizes, batch_factory):
    torch.manual_seed(0)
    module = PretrainModule(small_sizes)
    batch = batch_factory(batch_size=2, length=3)
    noise = module.world_model.rssm.draw_noise(2, 3, torch.Generator().manual_seed(0))
    eager_terms, eager_grads = losses_and_gradients(module, module.training_losses, batch, noise)
    torch._dynamo.reset()
    step = compiled(module.training_losses, "default", torch.device("cpu"))
    for _ in range(2):  # the second call runs the cached graphs
        terms, grads = losses_and_gradients(module, step, batch, noise)
        for name, value in eager_terms.items():
            torch.testing.assert_close(terms[name], value, rtol=1e-4, atol=1e-4, msg=name)
        # float32 sums in another order; a bias right before a one-channel-per-group GroupNorm has the
        # gradient 0 in exact arithmetic, so each gradient is also allowed a millionth of the whole norm
        total = torch.cat([grad.flatten() for grad in eager_grads.values()]).norm()
        for name, grad in eager_grads.items():
            assert (grads[name] - grad).norm() <= 1e-3 * grad.norm() + 1e-6 * total, name
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] >= 1  # compiled, not eager twice


def test_reduce_overhead_falls_back_to_default_off_the_gpu(monkeypatch, caplog):
    modes = []
    monkeypatch.setattr(torch, "compile", lambda function, mode, dynamic: modes.append((mode, dynamic)) or function)
    with caplog.at_level(logging.INFO):
        compiled(len, "reduce-overhead", torch.device("cpu"))
    assert modes == [("default", False)]
    assert "needs CUDA graphs (a GPU); compiling with mode default on cpu" in caplog.text
    compiled(len, "default", torch.device("cpu"))
    assert modes[1:] == [("default", False)]  # default: inductor on any device
    assert compiled(len, "off", torch.device("cpu")) is len and len(modes) == 2
    assert compiled(len, "auto", torch.device("cpu")) is len and len(modes) == 2  # auto: CUDA graphs on a GPU only


class Losses(L.Callback):
    def __init__(self):
        self.values = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.values.append(float(trainer.callback_metrics["train/loss"]))


def fit_losses(sizes: WorldModelConfig, batches: list[dict], val_batches: list[dict], compile_mode: str) -> list[float]:
    torch.manual_seed(0)
    module = PretrainModule(sizes, compile=compile_mode)
    losses = Losses()
    trainer = L.Trainer(max_steps=len(batches), accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, callbacks=[losses],
                        val_check_interval=1, num_sanity_val_steps=0, log_every_n_steps=1)
    trainer.fit(module, DataLoader(batches, batch_size=None), DataLoader(val_batches, batch_size=None))
    return losses.values


@pytest.mark.slow
def test_a_compiled_fit_follows_the_eager_one_and_validates_without_recompiling(small_sizes, batch_factory):
    batches = [batch_factory(batch_size=2, length=3, seed=i) for i in range(3)]
    val_batches = [batch_factory(batch_size=3, length=5, seed=9)]  # other shapes: validation runs eager
    eager = fit_losses(small_sizes, batches, val_batches, "off")
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()  # graphs of tests run before this one in the same process
    compiled_losses = fit_losses(small_sizes, batches, val_batches, "reduce-overhead")  # default mode on the CPU
    assert compiled_losses == pytest.approx(eager, rel=1e-4)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 1  # one graph for 3 steps and 3 validations
