"""Variable-gap sampling: gaps i.i.d. U{1..K_max}, the too-short policy, indices inside the clip."""

import itertools
from collections import Counter

import numpy as np
from scipy.stats import chisquare

from data_pipeline.sampling import gap_range_note, gap_shares, gaps_of, sample_gaps, sample_indices


def test_gaps_are_iid_uniform_on_clips_long_enough():
    rng = np.random.default_rng(0)
    length, k_max, num_frames = 8, 5, 1 + 7 * 5  # every draw fits
    gaps = np.stack([gaps_of(sample_indices(num_frames, length, k_max, rng)) for _ in range(4000)])
    assert (gaps[:, 0] == 0).all()
    counts = np.bincount(gaps[:, 1:].ravel(), minlength=k_max + 1)[1:]
    assert chisquare(counts).pvalue > 1e-3, counts
    pairs = Counter(zip(gaps[:, 1].tolist(), gaps[:, 2].tolist()))  # independence of neighbouring gaps
    assert chisquare([pairs[p] for p in itertools.product(range(1, 6), repeat=2)]).pvalue > 1e-3


def test_short_clips_draw_every_fitting_gap_vector_equally_often():
    rng = np.random.default_rng(1)
    num_gaps, k_max, budget = 3, 4, 6  # 3 gaps from U{1..4} summing to at most 6
    fitting = [v for v in itertools.product(range(1, 5), repeat=3) if sum(v) <= budget]
    counts = Counter(tuple(sample_gaps(num_gaps, k_max, budget, rng).tolist()) for _ in range(20 * len(fitting) * 20))
    assert set(counts) == set(fitting)
    assert chisquare([counts[v] for v in fitting]).pvalue > 1e-3


def test_too_short_policy():
    rng = np.random.default_rng(2)
    assert sample_indices(15, 16, 5, rng) is None  # fewer frames than L: skipped
    assert sample_indices(16, 16, 5, rng).tolist() == list(range(16))  # exactly L frames: all gaps 1
    assert sample_indices(0, 1, 5, rng) is None  # an empty clip holds nothing
    assert sample_indices(1, 1, 5, rng).tolist() == [0]  # L = 1: one frame, no gap


def test_indices_lie_inside_the_clip_and_increase():
    rng = np.random.default_rng(3)
    for _ in range(500):
        num_frames, length, k_max = int(rng.integers(1, 130)), int(rng.integers(1, 20)), int(rng.integers(1, 11))
        indices = sample_indices(num_frames, length, k_max, rng)
        if num_frames < length:
            assert indices is None
            continue
        gaps = np.diff(indices)
        assert len(indices) == length and indices[0] >= 0 and indices[-1] < num_frames
        assert ((gaps >= 1) & (gaps <= k_max)).all()


def test_starts_cover_the_whole_clip():
    rng = np.random.default_rng(4)
    starts = {int(sample_indices(40, 4, 2, rng)[0]) for _ in range(3000)}
    ends = {int(sample_indices(40, 4, 2, rng)[-1]) for _ in range(3000)}
    assert 0 in starts and 39 in ends


def test_the_start_is_uniform_over_the_starts_that_leave_room_for_the_span():
    """Reaching frame 0 and the last frame at all (above) would pass a sampler that began most sequences at 0."""
    rng = np.random.default_rng(5)
    fixed_span = np.bincount([sample_indices(40, 4, 1, rng)[0] for _ in range(3700)], minlength=37)  # span 3: 37 starts
    assert len(fixed_span) == 37 and fixed_span.min() > 60 and fixed_span.max() < 145  # 100 each, sd 10
    drawn = [sample_indices(40, 4, 3, rng) for _ in range(4000)]
    room = np.array([(indices[0] + 0.5) / (40 - (indices[-1] - indices[0])) for indices in drawn])  # U(0, 1)
    assert abs(room.mean() - 0.5) < 0.02 and abs((room < 0.25).mean() - 0.25) < 0.025


def test_gap_shares_are_those_the_sampler_draws_and_the_note_comes_when_long_gaps_fall_short():
    """The fit and `analyze` say when the clips are too short for K_max: the gaps then drawn are far from U{1..K_max}
    (before, a K_max of 20 on 45-frame clips trained on gaps of mostly 1-3 without a word)."""
    rng = np.random.default_rng(3)
    clips = {20: 2, 45: 3, 120: 1}  # frame count -> clips; 120 frames hold every span of 12 gaps up to 5
    drawn = np.concatenate([np.diff(sample_indices(frames, 13, 5, rng)) for frames, n in clips.items()
                            for _ in range(n * 3000)])
    frequencies = np.bincount(drawn, minlength=6)[1:] / len(drawn)
    np.testing.assert_allclose(gap_shares(clips, 13, 5), frequencies, atol=0.005)
    np.testing.assert_allclose(gap_shares({120: 4, 10: 9}, 13, 5), 0.2)  # long clips: U{1..5}; clips < L draw none
    assert gap_range_note(clips, 13, 5, "k_max 5") is None  # k = 5 keeps more than half its 20%
    note = gap_range_note(clips, 13, 20, "--data.k_max 20 with --data.seq_len 13")
    assert note.startswith("--data.k_max 20 with --data.seq_len 13: a sequence spans up to 241 frames, but 6 of the 6 "
                           "clips are shorter") and "(5.0% under U{1..20}), the mean gap" in note
    assert gap_range_note(clips, 500, 5, "--data.seq_len 500") is None  # no clip holds 500: "0 of the 0 clips" said
