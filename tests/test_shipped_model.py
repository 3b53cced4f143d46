"""The model shipped in ``models/default/``: it loads with this code, predicts, and its card's report has
the contract's keys, with the numbers its own table holds."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from unipixie.core.model.checkpoint import is_checkpoint, read_config
from unipixie.core.model.inference import DEFAULT_CHECKPOINT, Predictor
from unipixie.core.types import FeatureGrid, GridGeometry

METRICS = ("logE_mse", "logrho_mse", "nu_mse", "material_acc", "runtime_s")

pytestmark = pytest.mark.skipif(not is_checkpoint(DEFAULT_CHECKPOINT), reason="no shipped model in this checkout")


def test_shipped_weights_are_small_enough_and_load():
    weights = DEFAULT_CHECKPOINT / "model.safetensors"
    assert weights.stat().st_size <= 50 * 1024 * 1024
    cfg = read_config(DEFAULT_CHECKPOINT)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        p = Predictor.load(DEFAULT_CHECKPOINT, device="cpu")
        R = cfg.grid_resolution
        occ = np.zeros((R, R, R), bool)
        occ[R // 2 - 4: R // 2 + 4, R // 2 - 4: R // 2 + 4, R // 2 - 4: R // 2 + 4] = True
        feats = np.random.default_rng(0).normal(size=(int(occ.sum()), cfg.feature_dim)).astype(np.float16)
        grid = FeatureGrid(GridGeometry(R, [-0.5] * 3, 1.0 / R), occ, feats, feature_model=cfg.feature_model)
        pred = p.predict(grid, alphas=[0.0, 1.0], heads=("mpm",), steps=1)
    finally:
        torch.set_num_threads(threads)
    E0, E1 = pred.mpm[0].E, pred.mpm[1].E
    assert E0.shape == (int(occ.sum()),) and np.all(np.isfinite(E0)) and np.all(E0 > 0)
    assert float(np.mean(np.log10(E1))) > float(np.mean(np.log10(E0)))  # α = 1 is stiffer on average


def test_shipped_evaluation_report_has_the_contract_keys():
    doc = json.loads((DEFAULT_CHECKPOINT / "evaluation.json").read_text())
    methods = doc["methods"]
    for name in ("unipixie", "unet_deterministic"):
        for key in METRICS:
            v = methods[name][key]
            assert isinstance(v, float) and math.isfinite(v) and v >= 0.0, (name, key, v)
        # `methods` is the summary of the full table, not a second set of numbers
        for key in ("logE_mse", "logrho_mse", "nu_mse", "material_acc"):
            assert methods[name][key] == doc["table1"][name][key]
    cfg = read_config(DEFAULT_CHECKPOINT)
    assert doc["objects"] >= 1 and cfg.feature_model in (DEFAULT_CHECKPOINT / "README.md").read_text()
