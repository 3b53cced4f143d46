"""training/feature_probe.py's measures on synthetic data (no Blender): the boundary width and the ridge probe."""

from __future__ import annotations

import numpy as np

from unipixie.training.feature_probe import probe, ridge_fit, transition_width


def _bar(profile):
    """A 64 × 16 × 16 bar along x whose voxels' single feature follows ``profile(x)``."""
    occ = np.zeros((64, 64, 64), bool)
    occ[:, 24:40, 24:40] = True
    idx = np.argwhere(occ)
    return idx, np.asarray([profile(i) for i in idx[:, 0]], np.float64)[:, None], occ


def test_transition_width_of_a_step_and_of_ramps():
    idx, f, occ = _bar(lambda x: 0.0 if x < 32 else 1.0)
    assert abs(transition_width(idx, f, occ) - 0.8) < 1e-9           # a step between two slices
    idx, f, occ = _bar(lambda x: float(np.clip((x - 27.5) / 9.0, 0, 1)))
    assert abs(transition_width(idx, f, occ) - 0.8 * 9.0) < 1e-6      # a linear ramp over 9 slices
    idx, f, occ = _bar(lambda x: 3.0 - 2.0 * (x >= 32))               # direction and scale do not matter
    assert abs(transition_width(idx, f, occ) - 0.8) < 1e-9


def test_ridge_probe_recovers_a_linear_code_and_scores_held_out_objects():
    rng = np.random.default_rng(0)
    objects = []
    for _ in range(6):
        code = rng.random(200)
        X = np.stack([code * 2.0 + 0.01 * rng.normal(size=200), rng.normal(size=200)], axis=1)
        objects.append({"features": {"good": X, "noise": rng.normal(size=(200, 2))}, "code": code,
                        "boundary": rng.random(200) < 0.1})
    w, b = ridge_fit(objects[0]["features"]["good"], objects[0]["code"], 1e-6)
    assert abs(w[0] - 0.5) < 0.01 and abs(b) < 0.01
    res = probe(objects, train=[0, 1, 2, 3], test=[4, 5])
    assert res["good"]["test_rms"] < 0.02
    assert res["noise"]["test_rms"] > 0.25 and abs(res["noise"]["test_rms"] - res["train_mean_predictor_test_rms"]) < 0.03
