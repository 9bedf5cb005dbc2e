"""`hauwm pretrain analyze`: what pre-training learned about uncertainty (the paper's RQ3, section 5.4, fig. 5).

For each exported model, on the same held-out batches:
- disagreement_vs_k.png: ensemble disagreement and open-loop prediction error against the gap k
  (model/evaluation.py), one line per model — e.g. with and without HCU — with the Spearman ρ(k, disagreement);
- rollouts_<model>.png: an imagined rollout of one held-out clip, decoded from several heads side by side
  (each head following its own means) under the ensemble mean and the ground truth, with each step's gap k
  and the ensemble disagreement (the paper's fig. 5);
- figures.json: every number plotted.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure  # no pyplot: no GUI backend, no global figure state
from tqdm import tqdm

from data_pipeline.dataset import SequenceDataset, shard_set
from data_pipeline.sampling import gap_range_note, gaps_beyond_clips
from hauwm.atomic import written_whole
from hauwm.memory import memory_available
from model.config import ConfigError
from model.evaluation import horizon_metrics, horizon_sums
from model.export import FrozenWorldModel, load_frozen
from model.losses import disagreement
from model.networks import IMAGE_SHAPE


def model_label(model: FrozenWorldModel, name: str) -> str:
    provenance = model.export_config.get("provenance", {})
    if not provenance:
        return name
    lambda_init = provenance.get("lambda_init")  # a number or absent (load_frozen checks)
    hcu = ("HCU λ₀=" + ("?" if lambda_init is None else f"{lambda_init:g}")) if provenance.get("hcu") else "no HCU"
    return (f"{name} ({hcu}, M={model.config.ensemble}, K_max={provenance.get('k_max', '?')}, "
            f"step {provenance.get('global_step', '?')})")


def seeded_noise(model: FrozenWorldModel, gaps: torch.Tensor, seed: int) -> torch.Tensor:
    """The posterior noise [B, L, S] for sequences with these gaps [B, L], the same for the same seed."""
    return model.rssm.draw_noise(*gaps.shape, generator=torch.Generator().manual_seed(seed))


@torch.no_grad()
def horizon_figure_data(model: FrozenWorldModel, batches: list[dict], k_max: int, seed: int) -> dict:
    sums = sum(horizon_sums(model, batch, k_max, seeded_noise(model, batch["gaps"], seed + i))[0]
               for i, batch in enumerate(batches))
    return horizon_metrics(sums)


@torch.no_grad()
def rollout(model: FrozenWorldModel, batch: dict, heads: int, context: int, seed: int) -> dict:
    """Observe `context` frames of the first clip, then imagine the rest open-loop with the clip's own gaps."""
    frames, gaps, num_frames = batch["frames"][:1], batch["gaps"][:1], batch["num_frames"][:1]
    obs = model.observe(frames[:, :context], gaps[:, :context], num_frames, seeded_noise(model, gaps[:, :context], seed))
    conds = model.conditions(gaps[:, context:], num_frames)  # [1, H, C]
    start = obs.state(context - 1)
    mean_states, mean_heads = model.rssm.imagine(start, conds)  # heads' means along the ensemble-mean path
    rows = {"ensemble mean": model.decode(mean_states)[0]}
    for head in range(min(heads, model.rssm.ensemble)):
        rows[f"head {head + 1}"] = model.decode(model.rssm.imagine(start, conds, head=head)[0])[0]
    indices, context_indices = batch["indices"][0, context:].tolist(), batch["indices"][0, :context].tolist()
    return {
        "truth": frames[0, context:],
        "rows": rows,
        "gaps": gaps[0, context:].tolist(),
        "indices": indices,
        "context_indices": context_indices,
        "frames_ahead": [index - context_indices[-1] for index in indices],  # since the last observed frame
        "disagreement": disagreement(mean_heads)[0].tolist(),  # [H]
        "id": batch["id"][0],
    }


def json_safe(value):
    """NaN (a gap never seen) → null, recursively, so figures.json is strict JSON."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, dict):
        return {key: json_safe(v) for key, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def to_image(x: torch.Tensor) -> np.ndarray:
    """uint8 [3, H, W] or float [3, H, W] in preprocess space → float [H, W, 3] in [0, 1]."""
    x = x.float() / 255.0 if x.dtype == torch.uint8 else x.float() + 0.5
    return x.clamp(0, 1).permute(1, 2, 0).cpu().numpy()


def plot_horizon(results: list[dict], path: Path) -> None:
    fig = Figure(figsize=(10, 4))
    left, right = fig.subplots(1, 2)
    for result in results:
        metrics = result["horizon"]
        left.plot(metrics["k"], metrics["disagreement"], marker="o",
                  label=f"{result['label']}  ρ={metrics['spearman_k_disagreement']:.2f} (over the per-k means)")
        right.plot(metrics["k"], metrics["recon_mse"], marker="o", label=result["label"])
    left.set(xlabel="gap k (frames)", ylabel="ensemble disagreement", title="Disagreement against the horizon k")
    right.set(xlabel="gap k (frames)", ylabel="open-loop MSE (per pixel)", title="Prediction error from μ̄")
    for axis in (left, right):
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7)
    fig.tight_layout()
    with written_whole(path) as partial:
        fig.savefig(partial, dpi=120, format="png")


def plot_rollout(data: dict, title: str, path: Path) -> None:
    rows = {"ground truth": data["truth"], **data["rows"]}
    steps = len(data["gaps"])
    fig = Figure(figsize=(1.3 * steps + 1, 1.35 * len(rows) + 0.6))
    axes = fig.subplots(len(rows), steps, squeeze=False)
    for r, (name, images) in enumerate(rows.items()):
        for c in range(steps):
            axis = axes[r, c]
            axis.imshow(to_image(images[c]))
            axis.set_xticks([])
            axis.set_yticks([])
            if c == 0:
                axis.set_ylabel(name, fontsize=7)
            if r == 0:
                axis.set_title(f"t{data['indices'][c]} (k={data['gaps'][c]}, +{data['frames_ahead'][c]})", fontsize=7)
            if r == len(rows) - 1:
                axis.set_xlabel(f"u={data['disagreement'][c]:.3g}", fontsize=7)
    fig.suptitle(f"{title}\nclip {data['id']}, imagined after frames {data['context_indices']}; k = the step's gap, +n = "
                 "frames since the last observed one; u = disagreement", fontsize=8)
    fig.tight_layout()
    with written_whole(path) as partial:
        fig.savefig(partial, dpi=110, format="png")


FIGURES = "figures.json"
HORIZON_PLOT = "disagreement_vs_k.png"
ROLLOUT_PLOTS = "rollouts_*.png"  # one per model


def check_out(out: Path, overwrite: bool) -> None:
    """Refuse an --out that is no directory, or that holds an analysis already, whole or in part (without
    `overwrite`): its figures would be replaced, and its rollouts of models not analysed again deleted (they would
    otherwise stay beside figures that do not list them)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} is a file: analyze writes a directory of plots and {FIGURES}; pass another path")
    if not overwrite and (out / FIGURES).exists():
        raise ConfigError(f"--out {out} holds an analysis already ({FIGURES}): choose another --out, or pass "
                          "--overwrite to replace it")
    plots = sorted(path.name for path in [*out.glob(ROLLOUT_PLOTS), out / HORIZON_PLOT] if path.exists())
    if not overwrite and plots:
        raise ConfigError(f"--out {out} holds plots of an analysis already ({', '.join(plots[:3])}; one stopped before "
                          f"it wrote {FIGURES}?): choose another --out, or pass --overwrite to replace them")


def check_memory(batches: int, batch_size: int, seq_len: int) -> None:
    """Refuse held-out batches (kept in memory, uint8 frames) that would take more than half the memory available."""
    needed = batches * batch_size * seq_len * int(np.prod(IMAGE_SHAPE))
    available = memory_available()
    if available is not None and needed > available / 2:
        raise ConfigError(f"--batches {batches} × --batch-size {batch_size} × --seq-len {seq_len} frames take "
                          f"{needed / 2**30:.1f} GiB, more than half the {available / 2**30:.1f} GiB of memory "
                          "available: lower --batches or --batch-size")


def analyze(
    models: list[Path], shards: Path, out: Path, split: str = "validation", batches: int = 8, batch_size: int = 8,
    seq_len: int = 12, k_max: int | None = None, heads: int = 4, seed: int = 0, overwrite: bool = False,
) -> list[Path]:
    """Evaluate each export in `models` on the same `batches` held-out batches of `shards`' `split` (sequences of
    `seq_len` frames at gaps 1..`k_max`: the export's K_max unless given), decode `heads` heads' rollouts, and
    write the plots and figures.json into `out` (each file whole or not at all; with `overwrite`, the rollouts of
    an earlier analysis there that this one does not write again are deleted); -> the files written."""
    check_out(out, overwrite)
    check_memory(batches, batch_size, seq_len)
    loaded = [load_frozen(path) for path in models]
    trained = {model.export_config.get("provenance", {}).get("k_max") for model in loaded}
    k_max = k_max or loaded[0].export_config.get("provenance", {}).get("k_max") or 5
    if len(trained) > 1:  # a K_max ablation beside the main model: gaps beyond its K_max are outside its training
        print(f"note: the models were trained with K_max {', '.join(map(str, sorted(trained, key=str)))}; all are "
              f"evaluated at gaps 1..{k_max} (--k-max), beyond some models' training range", file=sys.stderr)
    held_out_shards = shard_set(shards, split)
    lengths = held_out_shards.clip_lengths()
    if beyond := gaps_beyond_clips(lengths, seq_len, k_max, "--k-max"):
        raise ConfigError(f"{beyond} (the {split} split's clips)")
    if note := gap_range_note(lengths, seq_len, k_max, f"--k-max {k_max} with --seq-len {seq_len}"):
        print(f"note: {note}; the per-k figures of the long gaps rest on fewer frames", file=sys.stderr)
    dataset = SequenceDataset(held_out_shards, batch_size=batch_size, seq_len=seq_len, k_max=k_max,
                              num_workers=0, shuffle=False, seed=seed, batches_per_worker=batches)
    if (clips := sum(held_out_shards.eligible(seq_len))) < batches * batch_size:
        print(f"note: {batches} batches of {batch_size} from {clips} {split} clips of at least {seq_len} frames: clips "
              "repeat, with other gaps", file=sys.stderr)
    held_out = list(tqdm(dataset, total=batches, desc=f"reading {split} batches", unit="batch"))
    out.mkdir(parents=True, exist_ok=True)
    results, written = [], []
    for index, (path, model) in enumerate(tqdm(list(zip(models, loaded)), desc="analysing models", unit="model")):
        name = path.name if [p.name for p in models].count(path.name) == 1 else f"{index}-{path.name}"
        label = model_label(model, name)
        data = rollout(model, held_out[0], heads, context=max(1, seq_len // 2), seed=seed)
        rollout_path = out / ROLLOUT_PLOTS.replace("*", name)
        plot_rollout(data, label, rollout_path)
        written.append(rollout_path)
        results.append({
            "model": str(path), "label": label, "config": model.export_config,
            "horizon": horizon_figure_data(model, held_out, k_max, seed),
            "rollout": {key: data[key] for key in ("id", "gaps", "indices", "context_indices", "frames_ahead",
                                                   "disagreement")},
        })
    horizon_path = out / HORIZON_PLOT
    plot_horizon(results, horizon_path)
    json_path = out / FIGURES
    settings = dict(shards=str(shards), split=split, batches=batches, batch_size=batch_size, seq_len=seq_len,
                    k_max=k_max, seed=seed)
    with written_whole(json_path) as partial:
        partial.write_text(json.dumps(json_safe({"settings": settings, "models": results}), indent=2) + "\n")
    for stale in set(out.glob(ROLLOUT_PLOTS)) - set(written):  # an earlier analysis's (--overwrite)
        stale.unlink()
    return [horizon_path, *written, json_path]
