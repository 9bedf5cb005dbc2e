"""The built-in scenes are stochastic: the further ahead, the less predictable (what HCU needs)."""

import numpy as np

from data_pipeline.sample_data import TEMPLATES, choose_template, fill_template, render_scene


def test_future_positions_get_less_predictable_with_the_gap():
    """Extrapolating each shape at its current velocity: the error grows with the gap k, and is often
    zero at k = 1 (no turn yet), i.e. the scenes are predictable short-term and uncertain long-term."""
    rng = np.random.default_rng(0)
    errors = {k: [] for k in range(1, 6)}
    for _ in range(40):
        _, _, centres = render_scene(rng, 30, 320, height=240)  # centres [T, S, 2]
        for t in range(1, 30 - 5):
            velocity = centres[t] - centres[t - 1]
            for k in errors:
                errors[k].append(np.linalg.norm(centres[t + k] - (centres[t] + k * velocity), axis=-1).mean())
    mean_error = [np.mean(errors[k]) for k in range(1, 6)]
    assert all(a < b for a, b in zip(mean_error, mean_error[1:])), mean_error
    assert mean_error[4] > 3 * mean_error[0]
    assert np.mean(np.array(errors[1]) < 1e-6) > 0.3  # often no surprise one step ahead


def test_captions_fill_the_templates_like_ssv2():
    rng = np.random.default_rng(1)
    _, shapes, centres = render_scene(rng, 12, 352)
    template = choose_template(shapes, centres)
    caption, placeholders = fill_template(template, shapes)
    assert template in TEMPLATES and "[" not in caption and len(placeholders) == template.count("[")
