"""`unipixie bench objects`: Table 2's protocol on test objects and the ground truth's convergence."""

import argparse
import math

import numpy as np
import pytest

from unipixie.core.errors import UserError
from unipixie.training.benchmarks import objects as B

TINY = {"frames": 3, "spring_anchors": 32, "lbs_cubature_points": 32, "lbs_mass_samples": 300, "fit_evaluations": 1,
        "min_particles": 100, "tracked_points": 32}


def test_the_objects_are_the_test_split_of_the_shipped_build():
    # the shipped dataset's (seed 0) first test objects are 000006_sand_pile and 000019_wooden_furniture
    assert B.test_indices(2) == [6, 19]
    from unipixie.training.dataset import split_of

    assert all(split_of(i) == "test" for i in B.test_indices(12))


def test_one_object_gives_every_comparison_and_their_medians():
    row = B.measure_object(19, 0, (4, 6), 0.5, dict(TINY, device="cpu"), bake_default=False)
    assert row["object"] == "000019_wooden_furniture" and not row["errors"]
    expected = {"mpm4 vs mpm6", "spring_mass fit vs mpm4", "lbs fit vs mpm4", "spring_mass fit vs mpm6",
                "lbs fit vs mpm6"}
    assert set(row["pairs"]) == expected
    assert all(math.isfinite(v) and v >= 0 for v in row["pairs"].values())
    assert row["pairs"]["mpm4 vs mpm6"] > 0  # two resolutions are two different motions
    out = B.entries([row, row], "test CPU", (4, 6))
    medians = [e for e in out if e["case"].startswith("median over 2 objects")]
    assert len(medians) == len(expected)
    for e in medians:
        pair = e["case"].split(": ", 1)[1]
        assert e["value"] == pytest.approx(row["pairs"][pair]) and e["objects"] == 2


@pytest.mark.parametrize("cells", ["1,12", "12,x", ""])
def test_bad_levels_are_refused_with_the_rule(cells):
    args = argparse.Namespace(cells=cells, objects=1, workers=1, alpha=0.5, device="cpu", overrides=[], seed=0,
                              no_bake_default=True)
    with pytest.raises(UserError, match="--cells"):
        B.run(args)


def test_a_misspelt_setting_is_refused():
    with pytest.raises(UserError, match="ground-truth setting"):
        B._parse_overrides(["frame=3"])
    assert B._parse_overrides(["frames=3"]) == {"frames": 3}
