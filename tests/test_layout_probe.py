"""The layout probe of training/layout_probe.py: shape descriptors, the reader, and scoring as the oracle does.

The decisive check is a synthetic "ball with a core at a fixed depth": the nearest-surface rule can only say
"cover" inside, a reader that sees the depth recovers the core, and the same reader without the depth columns does
not (so dropping depth fails the test); and a reader's predictions do not change when the true interior labels do
(it never reads them).  Bad input is a UserError, and main() turns it into exit status 2."""

from __future__ import annotations

import numpy as np
import pytest

from unipixie.core import procedural as P
from unipixie.core.errors import UserError
from unipixie.training import layout_probe as L
from unipixie.training import oracle as O

R = 20
CORE_DEPTH = 2.5


def _ball(radius: float, centre=(10, 10, 10), squash=(1.0, 1.0, 1.0), oid="ball"):
    """A ball (an ellipsoid with ``squash``) in an R³ grid: part 0 "cover" down to CORE_DEPTH voxels deep, part 1
    "core" below it."""
    g = np.indices((R, R, R)).reshape(3, -1).T
    rel = (g + 0.5 - np.asarray(centre)) / np.asarray(squash)
    idx = g[np.linalg.norm(rel, axis=1) <= radius]
    depth = L.shape_descriptors(idx, R)[:, 0]
    part = (depth > CORE_DEPTH).astype(np.int64)
    return L.object_layout(oid, "sport_ball", ["cover", "core"], part, idx, R), idx


def _interior_accuracy(part, lay):
    inner = ~lay.surface
    return float(np.mean(part[inner] == lay.part_ids[inner]))


def test_shape_descriptors_of_a_box():
    idx = np.argwhere(np.ones((5, 7, 9), bool)) + 2          # a 5 x 7 x 9 box away from the grid's edge
    d = L.shape_descriptors(idx, 16)
    assert d.shape == (len(idx), len(L.CONTINUOUS))
    on_face = np.any((idx == idx.min(0)) | (idx == idx.max(0)), axis=1)
    assert np.all(d[on_face, 0] == 1.0) and np.all(d[~on_face, 0] > 1.0)
    assert d[:, 0].max() == 3.0 and d[:, 1].max() == 1.0      # the centre of the 5-thick axis is 3 voxels deep
    assert d[:, 2:5].min() == 0.0 and d[:, 2:5].max() == 1.0
    assert np.all(d[:, 5:8] == [5, 7, 9])
    edge = np.argwhere(np.ones((3, 3, 3), bool))              # touching the grid's edge: the edge is empty
    assert L.shape_descriptors(edge, 3)[:, 0].max() == 2.0


def test_training_rows_keep_a_rare_part_and_weigh_back_to_the_true_frequencies():
    lay, _ = _ball(8.0)
    inner = ~lay.surface
    counts = np.bincount(lay.part_ids[inner], minlength=2)
    rows, w = L.training_rows(lay, 100, np.random.default_rng(0))
    assert len(rows) <= 100 and not lay.surface[rows].any()
    got = np.bincount(lay.part_ids[rows], minlength=2)
    assert got.min() >= min(50, counts.min())                  # equal shares, whatever the frequencies
    assert np.allclose(np.bincount(lay.part_ids[rows], weights=w, minlength=2), counts)


@pytest.fixture(scope="module")
def fitted():
    import torch

    torch.set_num_threads(1)
    train = [_ball(r, centre=(10 + s, 10 - s, 10), squash=q)[0]
             for r, s, q in [(5, 0, (1, 1, 1)), (6, 1, (1, 1, 1)), (7, 0, (1, 1, 1)), (8, 1, (1, 1, 1)),
                             (6, 0, (1.2, 1, 1)), (7, 1, (1, 1.2, 0.9)), (5.5, 0, (1, 1, 1.3)), (8.5, 0, (1, 1, 1))]]
    return {use_depth: L.LayoutReader(use_depth, per_object=400, seed=0, epochs=300).fit(train)
            for use_depth in (True, False)}


def test_a_reader_with_depth_recovers_a_core_that_the_nearest_surface_rule_cannot(fitted):
    for radius, squash in ((6.5, (1, 1, 1)), (7.5, (1.1, 1, 1))):
        lay, _ = _ball(radius, centre=(9.5, 10, 10.5), squash=squash)
        assert (lay.part_ids[~lay.surface] == 1).mean() > 0.2   # a real core
        nearest = _interior_accuracy(lay.nearest, lay)
        probe = _interior_accuracy(fitted[True].predict_proba(lay).argmax(axis=1), lay)
        no_depth = _interior_accuracy(fitted[False].predict_proba(lay).argmax(axis=1), lay)
        assert nearest < 0.8 and probe > 0.97, (radius, nearest, probe)
        assert no_depth < 0.95, (radius, no_depth)                # the depth columns are what finds the core


def test_the_reader_never_reads_the_true_interior_parts(fitted):
    lay, _ = _ball(7.0)
    prob = fitted[True].predict_proba(lay)
    assert np.allclose(prob.sum(axis=1), 1.0)
    assert np.array_equal(prob[lay.surface].argmax(axis=1), lay.part_ids[lay.surface])   # the visible parts
    scrambled = L.ObjectLayout(**{**lay.__dict__, "part_ids": np.where(lay.surface, lay.part_ids,
                                                                        1 - lay.part_ids)})
    assert np.array_equal(fitted[True].predict_proba(scrambled), prob)
    unseen = L.ObjectLayout(**{**lay.__dict__, "semantic_class": "fruit"})     # no training objects: nearest rule
    assert np.array_equal(fitted[True].predict_proba(unseen).argmax(axis=1), lay.nearest)


def test_part_moments_reproduce_the_oracle_predictions():
    obj = P.generate(1, 0)                                     # a sport ball: cover and core
    ann = obj.annotation
    idx = np.argwhere(np.ones((10, 10, 10), bool)) + 1
    names = ann.part_names
    part = np.zeros(len(idx), np.int64)
    part[np.all((idx >= 4) & (idx <= 7), axis=1)] = len(names) - 1     # a buried (hidden) part
    settings = O.OracleSettings(draws=20, seed=2)
    alphas = [0.0, 0.5, 1.0]
    refs = O.oracle_predictions(ann, part, idx, 12, alphas, settings)
    moments = L.part_moments(ann, part, idx, 12, settings)
    nearest = O.nearest_surface_parts(part, idx, 12)
    for ref, voxel_part in ((O.ORACLE, part), (O.ORACLE_SURFACE, nearest)):
        got = L.predictions_from_parts(moments, alphas, part=voxel_part)
        for key in ("log10_E", "log10_density", "nu", "material"):
            assert np.array_equal(got[key], refs[ref][key]), (ref, key)
    onehot = np.eye(len(names))[part]
    soft = L.predictions_from_parts(moments, alphas, prob=onehot)
    assert np.allclose(soft["log10_E"], refs[O.ORACLE]["log10_E"], atol=1e-5)
    half = L.predictions_from_parts(moments, alphas, prob=np.full((len(idx), len(names)), 1.0 / len(names)))
    lo, hi = moments["E"]
    assert np.allclose(half["log10_E"][1], np.mean(0.5 * (lo + hi)), atol=1e-5)


def test_bad_input_is_a_user_error(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "split.json").write_text('{"train": ["a"], "val": [], "test": []}')
    with pytest.raises(UserError, match="test split holds no objects"):
        L.run_probe(tmp_path / "data", tmp_path / "out", log=None)
    with pytest.raises(UserError, match="draws must be at least 10"):
        L.run_probe(tmp_path / "data", tmp_path / "out", draws=5, log=None)
    assert not (tmp_path / "out").exists()                     # refused before anything is written


def test_main_on_a_missing_dataset_returns_2_with_the_message(tmp_path, capsys):
    assert L.main(["--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("layout_probe: error: ") and "not found" in err and "Traceback" not in err
