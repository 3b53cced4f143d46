"""The reference predictors of training/oracle.py: what the best possible model reaches on procedural labels.

Checked against the generator itself: the references' predictions are the conditional means of the
generator's labels (the E centre follows the appearance code; a hidden part's falls back to the prior's
middle), the α-blind reference is the midpoint, the conditional mean beats the midpoint and any shifted
prediction on fresh draws of the labels, and objects the generator did not build are refused."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from unipixie.core.errors import UserError
from unipixie.core import annotation as A
from unipixie.training import oracle as O
from unipixie.core import procedural as P

R = 12


def _layout(parts: int, hidden: tuple = ()):
    """A 12³ grid with a 10³ block: part 0 a shell, then one slab per other part (a slab touches the block's
    faces, so it is visible) or, for a part in ``hidden``, a 2³ cube buried at the block's centre."""
    idx = np.argwhere(np.ones((10, 10, 10), bool)) + 1
    part = np.zeros(len(idx), np.int64)
    inner = np.all((idx >= 3) & (idx <= 8), axis=1)
    visible_rest = [p for p in range(1, parts) if p not in hidden]
    for k, p in enumerate(visible_rest):        # slabs along x through the whole block
        part[(idx[:, 0] == 2 + 2 * k)] = p
    for p in hidden:
        part[np.all((idx >= 5) & (idx <= 6), axis=1)] = p
    assert inner.any()
    return part, idx


def _object(index: int):
    obj = P.generate(index, 0)
    return obj, obj.annotation


def _codes(obj) -> dict:
    return {p.name: p.appearance.code for p in obj.parts}


def test_a_buried_part_is_hidden_and_a_slab_is_visible():
    part, idx = _layout(3, hidden=(2,))
    seen = O.visible_parts(part, idx, R)
    assert seen.tolist() == [True, True, False]


def test_the_generator_codes_come_back_and_foreign_annotations_are_refused():
    obj, ann = _object(1)
    cls, variant, codes = O.generator_codes(ann)
    assert (cls, variant) == (obj.semantic_class, obj.variant) and codes == _codes(obj)
    name = ann.part_names[0]
    lo, hi = ann.parts[name].E
    parts = dict(ann.parts)
    parts[name] = dataclasses.replace(parts[name], E=(lo * 1.5, hi * 1.5))
    tampered = dataclasses.replace(ann, parts=parts)
    with pytest.raises(UserError, match="does not reproduce"):
        O.generator_codes(tampered)
    with pytest.raises(UserError, match="not a procedural object"):
        O.generator_codes(dataclasses.replace(ann, meta={}))


def test_the_predicted_E_centre_follows_the_appearance_code_and_falls_back_to_the_prior_middle_when_hidden():
    obj, ann = _object(1)                          # a sport ball: core and cover
    names = ann.part_names
    prior = A.class_prior(obj.semantic_class)
    vp = A.variant_prior(prior, obj.variant)
    codes = _codes(obj)

    def centre(p, u):
        pp = prior.parts[p]
        return pp.log10_E[0] + float(vp.E_shift.get(p, 0.0)) + u * (pp.log10_E[1] - pp.log10_E[0])

    part, idx = _layout(len(names))
    pred = O.oracle_predictions(ann, part, idx, R, [0.0, 0.5, 1.0], O.OracleSettings(draws=3000))[O.ORACLE]
    for k, p in enumerate(names):
        got = pred["log10_E"][1][part == k].mean()
        u = codes[p]
        if 0.25 <= u <= 0.75:                      # away from the clip of the jittered code at 0 and 1
            assert got == pytest.approx(centre(p, u), abs=0.03), p
        # α = 0 / 1 predict the lower / upper end: below / above the centre by the mean half-width
        hw = np.mean(prior.parts[p].log10_E_halfwidth)
        assert pred["log10_E"][0][part == k].mean() == pytest.approx(got - hw, abs=0.03)
        assert pred["log10_E"][2][part == k].mean() == pytest.approx(got + hw, abs=0.03)
    # the same part hidden: its code is unknown, so the prediction moves to the prior's middle
    hid = len(names) - 1
    part, idx = _layout(len(names), hidden=(hid,))
    pred = O.oracle_predictions(ann, part, idx, R, [0.5], O.OracleSettings(draws=3000))[O.ORACLE]
    assert pred["log10_E"][0][part == hid].mean() == pytest.approx(centre(names[hid], 0.5), abs=0.05)


def test_the_conditional_mean_beats_the_midpoint_and_a_shifted_guess_on_fresh_labels():
    obj, ann = _object(4)
    names = ann.part_names
    part, idx = _layout(len(names))
    alphas = [0.0, 0.5, 1.0]
    refs = O.oracle_predictions(ann, part, idx, R, alphas, O.OracleSettings(draws=1000, seed=3))
    mid = refs[O.ORACLE_MIDPOINT]
    assert all(np.array_equal(mid["log10_E"][0], mid["log10_E"][i]) for i in range(3))   # blind to α
    assert np.allclose(mid["log10_E"][0], refs[O.ORACLE]["log10_E"][1], atol=1e-6)       # the midpoint's mean
    rng = np.random.default_rng(11)
    codes = _codes(obj)
    err = {"oracle": 0.0, "midpoint": 0.0, "shifted": 0.0}
    for _ in range(300):                         # fresh labels of the same object, as the generator draws them
        t = A.part_table(A.sample_annotation(obj.semantic_class, obj.variant, codes, rng))
        for i, a in enumerate(alphas):
            y = ((1 - a) * np.log10(t["E_min"]) + a * np.log10(t["E_max"]))[part]
            err["oracle"] += np.mean((refs[O.ORACLE]["log10_E"][i] - y) ** 2)
            err["midpoint"] += np.mean((mid["log10_E"][i] - y) ** 2)
            err["shifted"] += np.mean((refs[O.ORACLE]["log10_E"][i] + 0.1 - y) ** 2)
    assert err["oracle"] < err["midpoint"] and err["oracle"] < err["shifted"]
    assert refs[O.ORACLE]["material"].shape == (3, len(part))
    assert np.array_equal(refs[O.ORACLE]["material"][0], A.part_table(ann)["material"][part])


def test_the_surface_reference_reads_the_outer_surface_parts_straight_inward():
    """``oracle_surface_parts`` agrees with ``oracle_appearance`` on the outer surface; inside, each voxel takes the
    part of its nearest surface voxel (checked by brute force), so a buried part is never predicted."""
    from unipixie.core.lift import surface_mask

    obj, ann = _object(4)
    names = ann.part_names
    hid = len(names) - 1
    part, idx = _layout(len(names), hidden=(hid,))
    refs = O.oracle_predictions(ann, part, idx, R, [0.0, 1.0], O.OracleSettings(draws=200, seed=1))
    surf, full = refs[O.ORACLE_SURFACE], refs[O.ORACLE]
    occ = np.zeros((R,) * 3, bool)
    occ[tuple(idx.T)] = True
    on_surface = surface_mask(occ)[tuple(idx.T)]
    d2 = ((idx[:, None, :] - idx[None, on_surface, :]) ** 2).sum(-1)
    expected = O.nearest_surface_parts(part, idx, R)
    nearest = d2 == d2.min(axis=1, keepdims=True)   # each voxel's nearest surface voxels (ties included)
    assert np.all([np.any(part[on_surface][nearest[k]] == expected[k]) for k in range(len(idx))])
    np.testing.assert_array_equal(expected[on_surface], part[on_surface])
    assert not np.any(expected == hid) and np.any(part == hid)
    for key in ("log10_E", "log10_density", "nu", "material"):
        np.testing.assert_array_equal(surf[key][:, on_surface], full[key][:, on_surface])
    # inside, the values are those the full reference gives the nearest surface voxel's part
    first_voxel_of = {p: int(np.argmax(part == p)) for p in np.unique(expected)}
    cols = [first_voxel_of[p] for p in expected]
    np.testing.assert_array_equal(surf["log10_E"], full["log10_E"][:, cols])
    assert not np.array_equal(surf["log10_E"][:, part == hid], full["log10_E"][:, part == hid])


def test_bad_inputs_are_refused():
    obj, ann = _object(1)
    part, idx = _layout(len(ann.part_names))
    with pytest.raises(UserError, match="part labels outside"):
        O.oracle_predictions(ann, part + 5, idx, R, [0.5])
    with pytest.raises(UserError, match="part labels for"):
        O.oracle_predictions(ann, part[:-1], idx, R, [0.5])
    with pytest.raises(UserError, match="at least 10"):
        O.OracleSettings(draws=3)
