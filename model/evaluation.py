"""Horizon statistics (the paper's RQ3): open-loop prediction error and ensemble disagreement for each gap k.

For every frame j ≥ 1 of a variable-gap sequence, the prior at j is the model's one-jump prediction of o_j
from the posterior at j − 1 over the gap k = gaps[j]; it is decoded from the ensemble mean μ̄ (section 4.1).
Grouping the frames by k gives, for each k in 1..K_max, the prediction error and the disagreement, and the
Spearman rank correlation between k and disagreement says whether uncertainty grows with the horizon.
Validation (model/module.py) and `hauwm pretrain analyze` (model/analyze.py) both use these functions.
"""

from __future__ import annotations

import math

import torch
from scipy.stats import spearmanr

from model.losses import disagreement
from model.networks import preprocess
from model.rssm import Observation, RSSMState
from model.world_model import WorldModel

COUNT, SQUARED_ERROR, DISAGREEMENT = range(3)


def horizon_sums(
    model: WorldModel, batch: dict, k_max: int, noise: torch.Tensor | None = None
) -> tuple[torch.Tensor, Observation]:
    """Sums over one batch, float64 [3, k_max]: frame counts, open-loop per-pixel MSE, disagreement; and the filtering
    (posterior noise [B, L, S] from `model.rssm.draw_noise`, fresh draws when None)."""
    obs = model.observe(batch["frames"], batch["gaps"], batch["num_frames"], noise)
    ensemble_mean = obs.prior_mean[:, :, 1:].mean(0)  # [B, L-1, S]
    predicted = model.decode(RSSMState(obs.deter[:, 1:], ensemble_mean))  # [B, L-1, 3, 64, 64]
    mse = ((predicted.float() - preprocess(batch["frames"][:, 1:])) ** 2).mean((-3, -2, -1))  # [B, L-1]
    spread = disagreement(obs.prior_mean[:, :, 1:])  # [B, L-1]
    k = batch["gaps"][:, 1:]
    valid = (k >= 1) & (k <= k_max)
    index = k[valid] - 1
    sums = torch.zeros(3, k_max, dtype=torch.float64, device=mse.device)
    sums[COUNT].index_add_(0, index, torch.ones_like(mse[valid], dtype=torch.float64))
    sums[SQUARED_ERROR].index_add_(0, index, mse[valid].double())
    sums[DISAGREEMENT].index_add_(0, index, spread[valid].double())
    return sums, obs


def horizon_metrics(sums: torch.Tensor) -> dict[str, object]:
    """Per-k means from accumulated sums [3, k_max] and the Spearman rank correlation of k with disagreement, taken
    over the per-k means (K_max points: with K_max = 5 it moves in steps of 0.1, and says nothing of the spread
    within each k; `count` says how many frames each mean has)."""
    sums = sums.cpu()
    counts = sums[COUNT]
    means = (sums / counts.clamp(min=1)).tolist()
    # NaN where a gap never occurred
    recon, spread = ([m if n > 0 else math.nan for m, n in zip(means[row], counts)] for row in (SQUARED_ERROR, DISAGREEMENT))
    ks = [k + 1 for k, n in enumerate(counts) if n > 0]
    observed = [spread[k - 1] for k in ks]
    rho = float(spearmanr(ks, observed).statistic) if len(ks) > 1 and len(set(observed)) > 1 else math.nan
    return {
        "k": list(range(1, len(counts) + 1)),
        "count": [int(n) for n in counts],
        "recon_mse": recon,
        "disagreement": spread,
        "spearman_k_disagreement": rho,
        "recon_mse_all": float(sums[SQUARED_ERROR].sum() / counts.sum()) if counts.sum() > 0 else math.nan,
    }
