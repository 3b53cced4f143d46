"""``unipixie bench model``: inference time of a trained checkpoint at its own sizes (``--checkpoint``)."""

from __future__ import annotations

import argparse

import pytest

from unipixie.core.errors import UserError
from unipixie.training.benchmarks import model as bench_model


def _args(**kw):
    p = argparse.ArgumentParser()
    bench_model.add_arguments(p)
    return p.parse_args([f"--{k.replace('_', '-')}={v}" for k, v in kw.items()])


def test_a_checkpoint_is_timed_at_its_own_sizes_and_spring_anchors(tiny_checkpoint):
    rows = bench_model.run(_args(checkpoint=tiny_checkpoint, device="cpu", voxels=3000, cases="mpm1,all1"))
    assert [r["metric"] for r in rows] == ["inference_s_mpm_1alpha", "inference_s_all_heads_1alpha"]
    for r in rows:
        # the case names the model that was timed: its own N_a (64 here, not the preset's 2048) and feature width
        assert "checkpoint tiny" in r["case"] and "64 spring anchors" in r["case"], r["case"]
        assert "D=32" in r["case"] and "offline-random-vit-w32" in r["case"], r["case"]
        assert r["value"] > 0 and r["unit"] == "s" and r["device"]


def test_a_checkpoint_with_the_training_case_is_refused(tiny_checkpoint):
    with pytest.raises(UserError, match="leave 'train' out"):
        bench_model.run(_args(checkpoint=tiny_checkpoint, device="cpu", cases="mpm1,train"))
