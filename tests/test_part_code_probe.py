"""training/part_code_probe.py: the per-(class, part) code reader and the references it feeds (no Blender)."""

import numpy as np
import pytest

from unipixie.training import oracle as oracle_mod
from unipixie.training.part_code_probe import PartRow, fit_code_maps, read_codes, surface_mask


def test_surface_mask_marks_voxels_with_an_empty_neighbour():
    occ = np.zeros((6, 6, 6), bool)
    occ[1:5, 1:5, 1:5] = True                       # a 4-voxel cube: its 2³ core is interior
    surf = surface_mask(occ)
    assert surf.shape == (64,) and int((~surf).sum()) == 8
    full = np.ones((3, 3, 3), bool)                 # the grid's border counts as empty
    assert int((~surface_mask(full)).sum()) == 1


def _rows(rng, n_per_group, informative=True):
    """Two classes, two parts each; each group's colour moves along its own direction with the code."""
    rows = []
    directions = {("a", "p"): [1, 0, 0], ("a", "q"): [0, 1, 0], ("b", "p"): [0, 0, 1], ("b", "q"): [-1, 1, 0]}
    bases = np.random.default_rng(42).uniform(0, 1, (len(directions), 3))    # the palette: the same every call
    for ((cls, part), d), base in zip(directions.items(), bases):
        for i in range(n_per_group):
            u = rng.uniform()
            f = base + 0.4 * u * np.asarray(d, float) + rng.normal(0, 0.01, 3) if informative else rng.uniform(0, 1, 3)
            rows.append(PartRow(f"{cls}{i}", cls, part, float(u), f, 10))
    return rows


def test_reader_recovers_codes_per_group_and_not_from_noise():
    rng = np.random.default_rng(0)
    train, test = _rows(rng, 40), _rows(rng, 20)
    truth = np.array([r.code for r in test])
    rms = np.sqrt(np.mean((read_codes(fit_code_maps(train), test) - truth) ** 2))
    assert rms < 0.06                               # 0.01 colour noise over a 0.4 colour span: ~0.03
    # one map for all groups cannot: the directions differ between groups
    pooled = [PartRow(r.object_id, "all", "all", r.code, r.mean_features, r.surface_voxels) for r in train]
    pooled_test = [PartRow(r.object_id, "all", "all", r.code, r.mean_features, r.surface_voxels) for r in test]
    assert np.sqrt(np.mean((read_codes(fit_code_maps(pooled), pooled_test) - truth) ** 2)) > 2 * rms
    noise = np.sqrt(np.mean((read_codes(fit_code_maps(_rows(rng, 40, False)), _rows(rng, 20, False)) - truth) ** 2))
    assert noise > 0.2


def test_small_groups_read_their_mean_and_unknown_groups_the_middle():
    rng = np.random.default_rng(1)
    train = _rows(rng, 3)                           # below MIN_TRAINING_PARTS: no map, the group's mean code
    maps = fit_code_maps(train)
    assert all(isinstance(m, float) for m in maps.values())
    g = [r for r in train if (r.semantic_class, r.part) == ("a", "p")]
    assert read_codes(maps, g[:1])[0] == pytest.approx(np.mean([r.code for r in g]))
    stranger = PartRow("x", "c", "z", 0.9, np.zeros(3), 1)
    assert read_codes(maps, [stranger])[0] == 0.5


def test_oracle_with_read_codes_moves_only_the_parts_read():
    from unipixie.core import procedural

    obj = procedural.generate(0, 0, "potted_plant")
    ann = obj.annotation
    names = ann.part_names
    part_ids = np.repeat(np.arange(len(names)), 4)  # four isolated voxels per part, all on the surface
    indices = np.stack([np.arange(len(part_ids)) * 2, np.zeros(len(part_ids), int), np.zeros(len(part_ids), int)], 1)
    settings = oracle_mod.OracleSettings(draws=40, seed=0)
    base = oracle_mod.oracle_predictions(ann, part_ids, indices, 64, [0.5], settings)[oracle_mod.ORACLE]["log10_E"]
    _, _, codes = oracle_mod.generator_codes(ann)
    same = oracle_mod.oracle_predictions(ann, part_ids, indices, 64, [0.5], settings, codes=dict(codes))
    np.testing.assert_array_equal(same[oracle_mod.ORACLE]["log10_E"], base)
    part = names[0]
    higher = oracle_mod.oracle_predictions(ann, part_ids, indices, 64, [0.5], settings,
                                           codes={part: min(1.0, codes[part] + 0.5)})[oracle_mod.ORACLE]["log10_E"]
    assert np.all(higher[0, part_ids == 0] > base[0, part_ids == 0] + 0.1)   # a stiffer-looking part reads stiffer
