"""Unit checks of the evaluation metrics, the scale fitter and the pack's quantisation (no Blender, no solvers)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from unipixie.core.errors import SimulationDiverged, UserError
from unipixie.training import evaluate as ev
from unipixie.training import ground_truth as G
from unipixie.training import pack


def test_psnr_and_ssim_against_their_definitions():
    rng = np.random.default_rng(0)
    a = rng.uniform(0.2, 0.8, (32, 32, 3))
    assert ev.psnr(a, a) == math.inf
    assert ev.ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    b = a + 0.01  # uniform offset: MSE = 1e-4 -> 40 dB exactly
    assert ev.psnr(a, b) == pytest.approx(40.0, abs=1e-9)
    # SSIM of a constant shift: luminance term (2 m1 m2 + C1) / (m1² + m2² + C1) < 1, structure term 1
    assert 0.99 < ev.ssim(a, b) < 1.0
    assert ev.ssim(a, rng.uniform(0, 1, a.shape)) < 0.2


def test_motion_rmse_and_full_vertex_motion():
    rest = np.random.default_rng(1).normal(size=(50, 3))
    T = 4
    shift = np.array([0.1, -0.2, 0.3])
    pos = np.stack([rest + k * shift for k in range(T)])
    assert G.motion_rmse(pos, pos) == 0.0
    # frame 0 is excluded: RMSE of a constant offset d is |d|
    assert G.motion_rmse(pos, pos + np.array([0.0, 0.0, 0.5])) == pytest.approx(0.5)
    idx = np.arange(0, 50, 3)
    full = ev.full_vertex_motion(rest, idx, rest[idx] + shift)     # rigid translation: exact everywhere
    assert np.allclose(full, rest + shift)


def test_in_range_fractions_and_targets():
    targets = {"E_min": np.array([1e4, 1e6]), "E_max": np.array([1e5, 1e8]), "nu_min": np.array([0.3, 0.2]),
               "nu_max": np.array([0.4, 0.3]), "density_min": np.array([100.0, 1000.0]),
               "density_max": np.array([200.0, 2000.0]), "material": np.array([0, 1])}
    t0 = ev.targets_at(targets, 0.0)
    assert np.allclose(t0["E"], [4.0, 6.0]) and np.allclose(ev.targets_at(targets, 0.5)["E"], [4.5, 7.0])
    pred = {"alphas": np.array([0.0, 1.0]), "log10_E": np.array([[3.95, 6.1], [5.0, 8.3]]),
            "log10_density": np.array([[2.0, 3.0], [np.log10(200), np.log10(2000)]]),
            "nu": np.array([[0.3, 0.2], [0.4, 0.3]])}
    fr = ev.in_range_fractions(pred, targets)
    # voxel 0 at alpha 0: 3.95 is 0.05 below a range 1 decade wide -> inside only with 10 % tolerance
    assert fr["0"]["E"]["0"] == 0.5 and fr["0"]["E"]["0.1"] == 1.0
    # voxel 1 at alpha 1: 8.3 is 0.3 above a 2-decade range -> inside with 25 % (0.5) but not 10 % (0.2)
    assert fr["1"]["E"]["0.1"] == 0.5 and fr["1"]["E"]["0.25"] == 1.0
    assert fr["0"]["all"]["0"] == 0.5


def test_table1_recomputes_from_files(tmp_path):
    root = tmp_path / "predictions"
    K = 10
    rng = np.random.default_rng(2)
    targets = {"E_min": np.full(K, 1e4), "E_max": np.full(K, 1e6), "nu_min": np.full(K, 0.3), "nu_max": np.full(K, 0.4),
               "density_min": np.full(K, 100.0), "density_max": np.full(K, 1000.0), "material": np.zeros(K, np.int16)}
    for oid in ("a", "b"):
        ev._save_npz(root / "targets" / f"{oid}.npz", **targets)
        alphas = np.array([0.0, 0.5, 1.0])
        err = rng.normal(0, 0.1, (3, K))
        ev._save_npz(root / "m" / f"{oid}.npz", alphas=alphas,
                     log10_E=(4 + 2 * alphas[:, None] + err).astype(np.float32),
                     log10_density=(2 + alphas[:, None] + 0 * err).astype(np.float32),
                     nu=(0.3 + 0.1 * alphas[:, None] + 0 * err).astype(np.float32),
                     material=np.zeros((3, K), np.int16), runtime_s=np.float64(0.25))
    m = ev.table1(root)["m"]
    assert m["objects"] == 2 and m["runtime_s"] == 0.25 and m["material_acc"] == 1.0
    assert m["logrho_mse"] < 1e-10 and m["nu_mse"] < 1e-12
    assert 0.003 < m["logE_mse"] < 0.03   # about 0.1²
    assert m["logE_monotone_fraction"] == 1.0   # mean log E rises by 1 per 0.5 of alpha, noise 0.1/sqrt(10)
    with pytest.raises(UserError, match="no targets"):
        ev.table1(tmp_path)


def test_fit_scale_finds_a_parabola_minimum_and_survives_divergence():
    calls = []

    def f(x):
        calls.append(x)
        if x > 1.1:
            raise SimulationDiverged("too stiff")
        return 1.0 + (x - 0.55) ** 2

    fit = G.fit_scale(f, step=0.4, bound=1.6, max_evaluations=6)
    assert fit.log_scale == pytest.approx(0.55, abs=1e-6)   # exact for a parabola
    assert len(calls) <= 6
    walk = G.fit_scale(lambda x: (x + 1.0) ** 2, step=0.4, bound=1.6, max_evaluations=8)  # minimum off the start
    assert walk.log_scale == pytest.approx(-1.0, abs=1e-6)
    with pytest.raises(SimulationDiverged):
        G.fit_scale(lambda x: (_ for _ in ()).throw(SimulationDiverged("x")), 0.4, 1.6, 3)


def test_ordered_scales():
    assert G.ordered_scales(2.0, 3.0, np.array([1.0]), np.array([1.0])) == (2.0, 3.0, False)
    s0, s1, crossed = G.ordered_scales(4.0, 1.0, np.array([1.0, 2.0]), np.array([1.0, 2.0]))
    assert crossed and s0 == s1 == pytest.approx(2.0)
    with pytest.raises(UserError, match="inverted"):
        G.ordered_scales(1.0, 1.0, np.array([2.0]), np.array([1.0]))


def test_wave_speed_cap_factor():
    # fixed-corotated: P-wave modulus M = E (1 - nu) / ((1 + nu)(1 - 2 nu)); nu = 0.25 -> 1.2 E
    assert G.p_wave_factor(0.25, 0) == pytest.approx(1.2)
    # weakly compressible (fluid, id 4): bulk modulus K = E / (3 (1 - 2 nu)); nu = 0.25 -> 2/3 E
    assert G.p_wave_factor(0.25, 4) == pytest.approx(2.0 / 3.0)


def test_feature_quantisation_error_bound():
    rng = np.random.default_rng(3)
    rows = rng.normal(size=(40, 8)).astype(np.float16)
    src = rng.integers(0, 40, 500)
    feats = rows[src]
    q, off, scale, source = pack.quantise_features(feats)
    assert len(q) == len(np.unique(rows, axis=0))
    back = pack.dequantise_features(q, off, scale, source)
    err = np.abs(back.astype(np.float32) - feats.astype(np.float32))
    bound = scale / 510 + np.abs(feats.astype(np.float32)).max(0) * 2 ** -10
    assert np.all(err <= bound + 1e-6)


def test_logE_monotonicity_check():
    up = {"alphas": np.array([1.0, 0.0, 0.5]), "log10_E": np.array([[6.0, 6.0], [4.0, 4.0], [5.0, 5.0]])}
    assert ev.logE_is_monotone(up)                       # unsorted alphas are sorted first
    dip = {"alphas": np.array([0.0, 0.5, 1.0]), "log10_E": np.array([[4.0, 4.0], [5.0, 5.2], [5.0, 5.1]])}
    assert not ev.logE_is_monotone(dip)                  # the mean falls from 5.1 to 5.05 between 0.5 and 1
