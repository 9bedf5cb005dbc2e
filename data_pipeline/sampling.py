"""Variable-gap frame sampling (paper section 4.2, appendix D.2): L frame indices of one clip with gaps
k_j = t_{j+1} − t_j drawn i.i.d. from U{1..K_max}.

The too-short policy. A clip of T frames holds a sequence when its span fits: 1 + Σ k_j ≤ T.
- T ≥ 1 + (L − 1)·K_max: every draw fits; the gaps are exactly i.i.d. U{1..K_max}.
- L ≤ T < 1 + (L − 1)·K_max: the gaps are drawn i.i.d. U{1..K_max} *conditioned on fitting*, exactly
  (sequentially, from the counts of gap vectors that fit; no rejection loop), so the long gaps are
  somewhat rarer on short clips. Every gap vector that fits is equally likely.
- T < L: the clip cannot hold L distinct frames and is skipped (`sample_indices` returns None).
The first index is uniform over the starts that leave room for the span.
"""

from __future__ import annotations

from bisect import bisect_right
from functools import lru_cache

import numpy as np


def _fit_probabilities(gaps: int, k_max: int, budget: int) -> np.ndarray:
    """P[j, s] = probability that j i.i.d. U{1..K_max} gaps sum to at most s, for j ≤ gaps, s ≤ budget."""
    table = np.zeros((gaps + 1, budget + 1))
    table[0, :] = 1.0
    for j in range(1, gaps + 1):
        for k in range(1, min(k_max, budget) + 1):
            table[j, k:] += table[j - 1, : budget + 1 - k] / k_max
    return table


@lru_cache(maxsize=1024)
def _step_cdfs(num_gaps: int, k_max: int, budget: int) -> list[list[list[float]]]:
    """cdfs[r][b][k − 1] = P(next gap ≤ k | r gaps still to follow, b frames of budget left, the rest fit)."""
    table = _fit_probabilities(num_gaps, k_max, budget)
    cdfs = []
    for remaining in range(num_gaps):
        rows = []
        for left in range(budget + 1):
            weights = [table[remaining, left - k] for k in range(1, min(k_max, left - remaining) + 1)]
            total = sum(weights)
            rows.append((np.cumsum(weights) / total).tolist() if total > 0 else [])
        cdfs.append(rows)
    return cdfs


def sample_gaps(num_gaps: int, k_max: int, budget: int, rng: np.random.Generator) -> np.ndarray | None:
    """`int64 [num_gaps]` gaps i.i.d. U{1..k_max} conditioned on summing to at most `budget`; None if none fit."""
    if num_gaps * k_max <= budget:
        return rng.integers(1, k_max + 1, num_gaps)
    if num_gaps > budget:
        return None
    cdfs = _step_cdfs(num_gaps, k_max, budget)
    gaps = []
    for j, uniform in enumerate(rng.random(num_gaps).tolist()):
        cdf = cdfs[num_gaps - j - 1][budget]
        gap = min(bisect_right(cdf, uniform), len(cdf) - 1) + 1
        gaps.append(gap)
        budget -= gap
    return np.array(gaps, np.int64)


def sample_indices(num_frames: int, length: int, k_max: int, rng: np.random.Generator) -> np.ndarray | None:
    """`int64 [length]` strictly increasing frame indices inside `[0, num_frames)`; None if the clip is too short."""
    gaps = sample_gaps(length - 1, k_max, num_frames - 1, rng)
    if gaps is None:
        return None
    span = int(gaps.sum())
    start = int(rng.integers(0, num_frames - span))
    return start + np.concatenate([[0], np.cumsum(gaps)]).astype(np.int64)


def gap_shares(frame_counts: dict[int, int], length: int, k_max: int) -> np.ndarray:
    """float64 [k_max]: the share of each gap 1..k_max among those `sample_indices` draws, one sequence per clip, from
    clips of these frame counts ({T: clips}; clips shorter than `length` draw none): U{1..K_max}'s 1/K_max each where
    every clip holds a full span, less for the long gaps where clips are short. The marginal of one gap of a short
    clip: P(k) = P(the other gaps fit in T − 1 − k) / (K_max · P(all gaps fit in T − 1))."""
    num_gaps, total = length - 1, np.zeros(k_max)
    for frames, clips in frame_counts.items():
        budget = frames - 1
        if frames < length or clips == 0:
            continue
        if num_gaps == 0 or num_gaps * k_max <= budget:
            total += clips / k_max
            continue
        table = _fit_probabilities(num_gaps, k_max, budget)
        rest_fits = np.array([table[num_gaps - 1, budget - k] if k <= budget else 0.0 for k in range(1, k_max + 1)])
        total += clips * rest_fits / (k_max * table[num_gaps, budget])
    return total / max(total.sum(), 1e-300)


def gaps_beyond_clips(frame_counts: dict[int, int], length: int, k_max: int, where: str) -> str | None:
    """A line saying that no sequence of `length` frames of these clips can hold a gap as large as k_max (the
    longest clip of F frames allows gaps up to F − length + 1), None where one can, or where no clip holds `length`
    frames (the caller refuses that). Gaps above it are never drawn: k_max is a mistake there (and a huge one
    made the gap tables and the per-k evaluation run for hours). `where` names the setting, e.g. "--data.k_max"."""
    longest = max((frames for frames, n in frame_counts.items() if n and frames >= length), default=None)
    if longest is None or k_max <= longest - length + 1:
        return None
    return (f"{where} {k_max} with sequences of {length} frames: the longest clip has {longest} frames, so no gap above "
            f"{longest - length + 1} can be drawn; lower it to at most {longest - length + 1}")


def gap_range_note(frame_counts: dict[int, int], length: int, k_max: int, where: str) -> str | None:
    """A line saying how far the gaps drawn from these clips fall short of U{1..K_max} (None when the longest gap
    keeps at least half its share, or where no clip holds `length` frames: the caller refuses that): `where` names
    the settings, e.g. "--data.k_max 5 with --data.seq_len 16"."""
    clips = sum(n for frames, n in frame_counts.items() if frames >= length)
    shares = gap_shares(frame_counts, length, k_max)
    if k_max == 1 or clips == 0 or shares[-1] >= 0.5 / k_max:
        return None
    span = 1 + (length - 1) * k_max
    shorter = sum(n for frames, n in frame_counts.items() if length <= frames < span)
    mean = float(np.arange(1, k_max + 1) @ shares)
    return (f"{where}: a sequence spans up to {span} frames, but {shorter} of the {clips} clips are shorter, and on "
            f"those the gaps are drawn conditioned on fitting: k = {k_max} is {shares[-1]:.1%} of the gaps drawn "
            f"({1 / k_max:.1%} under U{{1..{k_max}}}), the mean gap {mean:.2f} ({(k_max + 1) / 2:.2f}); a smaller k_max "
            "or seq_len draws closer to U{1..K_max} (docs/data_pipeline.md, the too-short policy)")


def gaps_of(indices: np.ndarray) -> np.ndarray:
    """`[..., L]` indices → `[..., L]` gaps with 0 before the first frame."""
    gaps = np.diff(indices, axis=-1, prepend=indices[..., :1])
    return gaps.astype(np.int64)
