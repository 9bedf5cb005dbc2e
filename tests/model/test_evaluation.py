"""The RQ3 statistics of model/evaluation.py against hand computations: each frame's one-jump prediction over its
own gap k, grouped by k, and the rank correlation over the per-k means."""

from __future__ import annotations

import json
import math

import torch
from scipy.stats import spearmanr

from model.config import WorldModelConfig
from model.evaluation import COUNT, DISAGREEMENT, SQUARED_ERROR, horizon_metrics, horizon_sums
from model.networks import preprocess
from model.rssm import RSSMState
from model.world_model import WorldModel

from conftest import make_batch  # noqa: I001 (tests/model/conftest.py)


@torch.no_grad()
def test_horizon_sums_are_one_jump_predictions_over_each_frames_own_gap():
    torch.manual_seed(0)
    model = WorldModel(WorldModelConfig(cnn_width=8, embed_dim=32, deter=32, stoch=8, hidden=32, ensemble=5,
                                        temporal_dim=16)).eval()
    k_max = 4
    gaps = torch.tensor([[0, 1, 2, 3, 4, 1], [0, 4, 4, 1, 1, 2], [0, 3, 7, 2, 1, 1]])  # 7 > K_max: left out
    frames = torch.randint(0, 256, (3, 6, 3, 64, 64), dtype=torch.uint8)
    num_frames = torch.tensor([30, 40, 50])
    noise = model.rssm.draw_noise(3, 6, generator=torch.Generator().manual_seed(1))
    sums, obs = horizon_sums(model, {"frames": frames, "gaps": gaps, "num_frames": num_frames}, k_max, noise)
    expected = torch.zeros(3, k_max, dtype=torch.float64)
    for b in range(3):
        for j in range(1, 6):  # frame 0 has no previous frame
            k = int(gaps[b, j])
            if k > k_max:
                continue
            previous = RSSMState(obs.deter[b:b + 1, j - 1], obs.stoch[b:b + 1, j - 1])  # the posterior at j − 1
            embedding = model.temporal(torch.tensor([[k]]), num_frames[b:b + 1, None])[:, 0]
            deter, heads, _ = model.rssm.img_step(previous, embedding)  # heads [M, 1, S]
            image = model.decode(RSSMState(deter, heads.mean(0)))  # decoded from the ensemble mean
            expected[COUNT, k - 1] += 1
            expected[SQUARED_ERROR, k - 1] += ((image - preprocess(frames[b:b + 1, j])) ** 2).mean().double()
            spread = ((heads - heads.mean(0)) ** 2).sum(0).mean() / (heads.shape[0] - 1)  # eq. 3's disagreement
            expected[DISAGREEMENT, k - 1] += spread.double()
    assert torch.allclose(sums, expected, rtol=1e-5, atol=1e-7)


def test_horizon_metrics_average_per_k_skip_unseen_gaps_and_rank_the_per_k_means():
    sums = torch.zeros(3, 6, dtype=torch.float64)
    sums[COUNT] = torch.tensor([4, 2, 0, 1, 3, 5.0])  # k = 3 never sampled
    sums[DISAGREEMENT] = torch.tensor([4, 4, 0, 3, 9, 10.0])  # per-k means 1, 2, –, 3, 3, 2
    sums[SQUARED_ERROR] = torch.tensor([2, 1, 0, 1, 3, 5.0])
    metrics = horizon_metrics(sums)
    assert metrics["count"] == [4, 2, 0, 1, 3, 5]
    assert metrics["disagreement"][:2] == [1.0, 2.0] and math.isnan(metrics["disagreement"][2])
    assert metrics["disagreement"][3:] == [3.0, 3.0, 2.0]
    assert metrics["spearman_k_disagreement"] == spearmanr([1, 2, 4, 5, 6], [1, 2, 3, 3, 2]).statistic
    assert metrics["recon_mse_all"] == 12 / 15  # pooled over frames, not a mean of the per-k means
    nothing = horizon_metrics(torch.zeros(3, 5, dtype=torch.float64))
    assert math.isnan(nothing["recon_mse_all"]) and math.isnan(nothing["spearman_k_disagreement"])


@torch.no_grad()
def test_analyze_rolls_each_head_out_from_the_last_observed_state_with_the_clips_own_gaps(small_sizes, tmp_path):
    """`analyze`'s rollout rows: the ensemble-mean path and each head's own path, imagined from the state after the
    `context` observed frames, conditioned on the clip's own later gaps (its test checked only their number)."""
    from model.analyze import rollout, seeded_noise
    from model.export import export_frozen, load_frozen

    torch.manual_seed(0)
    model = load_frozen(export_frozen(WorldModel(small_sizes), tmp_path, {"source": "tests"}))
    batch = make_batch(batch_size=2, length=8, seed=3)
    batch["gaps"][0] = torch.tensor([0, 2, 1, 3, 1, 4, 2, 5])  # later gaps that differ: ignoring them would show
    batch["indices"] = batch["gaps"].cumsum(1)
    batch["num_frames"] = batch["indices"][:, -1] + 1
    data = rollout(model, batch, heads=3, context=4, seed=7)
    obs = model.observe(batch["frames"][:1, :4], batch["gaps"][:1, :4], batch["num_frames"][:1],
                        seeded_noise(model, batch["gaps"][:1, :4], 7))
    conds = model.conditions(batch["gaps"][:1, 4:], batch["num_frames"][:1])  # [1, 4, C]
    expected = {"ensemble mean": model.decode(model.rssm.imagine(obs.state(3), conds)[0])[0]}
    expected |= {f"head {i + 1}": model.decode(model.rssm.imagine(obs.state(3), conds, head=i)[0])[0] for i in range(3)}
    assert data["rows"].keys() == expected.keys()
    for name, images in expected.items():
        torch.testing.assert_close(data["rows"][name], images)
    assert not torch.allclose(data["rows"]["head 1"], data["rows"]["head 2"])
    assert data["gaps"] == batch["gaps"][0, 4:].tolist()


@torch.no_grad()
def test_analyzes_horizon_figures_sum_every_batch_with_its_own_seeded_noise(small_sizes):
    """The same seed gives the same figures (noise drawn from the global RNG would not), and batch i's noise comes
    from seed + i."""
    from model.analyze import horizon_figure_data, seeded_noise

    torch.manual_seed(0)
    model = WorldModel(small_sizes).eval()
    batches = [make_batch(batch_size=2, length=6, seed=i) for i in range(2)]
    figures = json.dumps(horizon_figure_data(model, batches, 5, seed=11))  # NaN (a gap never drawn) as NaN
    assert json.dumps(horizon_figure_data(model, batches, 5, seed=11)) == figures
    sums = sum(horizon_sums(model, batch, 5, seeded_noise(model, batch["gaps"], 11 + i))[0]
               for i, batch in enumerate(batches))
    assert figures == json.dumps(horizon_metrics(sums))
