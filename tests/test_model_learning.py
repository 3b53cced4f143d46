"""Learning works: the tiny model overfits a handful of synthetic objects on the CPU.

One training run (train() — the same code as ``unipixie train``) of the ``tiny`` preset on 4 synthetic
8³ objects, then three checks on it:

* the training objective on fixed random draws falls by at least 100× (all heads together);
* Heun sampling at α = 0 / α = 1 reproduces y_min / y_max: mean |log10 E error| ≤ 0.2 decades per
  object (the synthetic ranges span 1-2 decades), log10 ρ ≤ 0.05, ν ≤ 0.02, material class ≥ 95 %
  of voxels, LBS log10 E ≤ 0.2, spring log10 k ≤ 0.3 and η ≤ 0.06 (its range spans 0.05-0.45),
  HyperNetwork parameters ≤ 0.05;
* mean log10 E over each object does not decrease with α (11 values, shared noise).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from unipixie.core.model.inference import Predictor
from unipixie.core.model.objective import SamplingSettings, TrainingObjective, make_draws, sample_seed
from unipixie.training.sample_format import TrainingSample, list_samples
from unipixie.training.synthetic import make_dataset
from unipixie.training.train import Collate, TrainSettings, train

STEPS = 600


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: one thread is fastest and leaves the other core free
    try:
        root = tmp_path_factory.mktemp("learn")
        make_dataset(root / "data", 4, resolution=8, feature_dim=16, anchors=12, seed=0)
        files = list_samples(root / "data")
        samples = [TrainingSample.load(f) for f in files]
        settings = TrainSettings(data=str(root / "data"), out=str(root / "ck"), steps=STEPS, batch=4, lr=3e-3,
                                 warmup=20, preset="tiny", device="cpu", precision="fp32", save_every=10 ** 9,
                                 log_every=50)
        from unipixie.training.train import build_config
        from unipixie.core.model.network import UniPixieModel

        torch.manual_seed(settings.seed)  # the same initial weights train() starts from
        initial = UniPixieModel(build_config(settings, samples[0], files))
        before = _fixed_draw_loss(initial, samples)
        stats = train(settings)
        predictor = Predictor.load(root / "ck", device="cpu")
        after = _fixed_draw_loss(predictor.model, samples)
        yield {"samples": samples, "predictor": predictor, "before": before, "after": after, "stats": stats}
    finally:
        torch.set_num_threads(threads)


def _fixed_draw_loss(model, samples, draws_per_object=16):
    """The training objective averaged over fixed random draws (same draws before and after training)."""
    objective = TrainingObjective(model).eval()
    collate = Collate(model.cfg)
    total = 0.0
    with torch.no_grad():
        for r in range(draws_per_object):
            batch = collate([(s, sample_seed(1234, r, i), s.object_id) for i, s in enumerate(samples)])
            draws = make_draws(batch, model.cfg.spring_dim, True, SamplingSettings(), "cpu")
            total += float(objective(batch, draws)["total"])
    return total / draws_per_object


def test_training_loss_falls_100x(trained):
    print(f"fixed-draw loss {trained['before']:.4g} -> {trained['after']:.4g} "
          f"({trained['before'] / trained['after']:.0f}x) in {STEPS} steps")
    assert trained["after"] * 100.0 <= trained["before"], (trained["before"], trained["after"])
    assert trained["stats"]["final_step"] == STEPS


def test_alpha_endpoints_reproduce_the_ranges(trained):
    p = trained["predictor"]
    for s in trained["samples"]:
        pred = p.predict(s.grid, [0.0, 1.0], seed=0)
        for i, (E, rho, nu, lE, k, eta) in enumerate([
                (s.mpm.E_min, s.mpm.density_min, s.mpm.nu_min, s.lbs.E_min, s.spring.stiffness_min, s.spring.softness_min),
                (s.mpm.E_max, s.mpm.density_max, s.mpm.nu_max, s.lbs.E_max, s.spring.stiffness_max, s.spring.softness_max)]):
            m, b, sp = pred.mpm[i], pred.lbs[i], pred.spring_mass[i]
            where = f"{s.object_id} alpha={i}"
            assert np.abs(np.log10(m.E) - np.log10(E)).mean() <= 0.2, where
            assert np.abs(np.log10(m.density) - np.log10(rho)).mean() <= 0.05, where
            assert np.abs(m.nu - nu).mean() <= 0.02, where
            assert (m.material == s.mpm.material).mean() >= 0.95, where
            assert np.abs(np.log10(b.E) - np.log10(lE)).mean() <= 0.2, where
            assert np.abs(b.params - s.lbs.params).mean() <= 0.05, where
            assert np.abs(np.log10(sp.stiffness) - np.log10(k)).mean() <= 0.3, where
            assert abs(sp.softness - eta) <= 0.06, where


def test_mean_log_E_is_monotone_in_alpha(trained):
    p = trained["predictor"]
    alphas = np.linspace(0.0, 1.0, 11)
    for s in trained["samples"]:
        pred = p.predict(s.grid, alphas, heads=("mpm",), seed=0)
        means = np.array([np.log10(m.E).mean() for m in pred.mpm])
        assert np.all(np.diff(means) >= -1e-3), (s.object_id, means)
        assert means[-1] - means[0] >= 0.5 * (np.log10(s.mpm.E_max) - np.log10(s.mpm.E_min)).mean()
