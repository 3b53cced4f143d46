"""Procedural objects and range annotations (core/procedural.py, core/annotation.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from unipixie.core.errors import UserError
from unipixie.core import annotation as A
from unipixie.core import procedural as P

SIZE_RANGE_M = {  # largest extent a real object of the class has (generous bounds), metres
    "potted_plant": (0.2, 1.3), "sport_ball": (0.05, 0.3), "stuffed_toy": (0.08, 0.7), "rubber_duck": (0.05, 0.3),
    "jelly_pudding": (0.05, 0.4), "metal_tool": (0.05, 0.5), "sand_pile": (0.15, 0.9), "snow_pile": (0.2, 1.6),
    "fruit": (0.03, 0.2), "wooden_furniture": (0.3, 1.2),
}


def test_prior_data_is_consistent():
    assert A.check_priors() == []
    assert len(A.SEMANTIC_CLASSES) >= 10
    assert set(P.GEOMETRY) == set(A.SEMANTIC_CLASSES)


@pytest.mark.parametrize("index", range(20))
def test_objects_are_closed_named_parts_at_realistic_sizes(index):
    obj = P.generate(index, seed=3)
    prior = A.class_prior(obj.semantic_class)
    assert obj.part_names == A.parts_of(prior, obj.variant)
    assert obj.part_names == obj.annotation.part_names
    for part in obj.parts:
        assert part.components, part.name
        for comp in part.components:
            assert comp.is_watertight and comp.volume > 0, (obj.object_id, part.name)
    lo, hi = SIZE_RANGE_M[obj.semantic_class]
    size = float(np.max(np.ptp(obj.bounds, axis=0)))
    assert lo <= size <= hi, (obj.object_id, size)
    assert abs(obj.bounds[0][2]) < 1e-9  # stands on z = 0
    assert A.problems(obj.annotation) == []


def test_generation_is_deterministic_and_seeded():
    a, b, c = P.generate(7, seed=1), P.generate(7, seed=1), P.generate(7, seed=2)
    assert np.array_equal(a.vertices(), b.vertices())
    assert a.annotation.to_dict() == b.annotation.to_dict()
    assert a.meta == b.meta
    assert not (a.vertices().shape == c.vertices().shape and np.allclose(a.vertices(), c.vertices()))
    # the class cycles with the index
    assert [P.class_of_index(i) for i in range(10)] == list(A.SEMANTIC_CLASSES)


def test_appearance_carries_the_stiffness():
    """The part's appearance code sets both its colour and where its E range sits in the prior."""
    codes, mids = [], []
    for i in range(0, 400, 10):  # potted plants
        obj = P.generate(i, seed=0)
        part = next(p for p in obj.parts if p.name == "trunk")
        codes.append(part.appearance.code)
        lo, hi = obj.annotation.parts["trunk"].E
        mids.append(0.5 * (np.log10(lo) + np.log10(hi)) - {"shrub": 0, "sapling": 0.2, "succulent": 0}[obj.variant])
    assert np.corrcoef(codes, mids)[0, 1] > 0.7


def test_glb_has_one_textured_node_per_part_and_round_trips(tmp_path):
    import trimesh

    obj = P.generate(0, seed=0)
    path = obj.export_glb(tmp_path / "o.glb")
    scene = trimesh.load(path, force="scene")
    names = sorted(scene.graph.nodes_geometry)
    assert names == sorted(obj.part_names)
    back = np.linalg.inv(P.Z_UP_TO_GLTF)
    for part in obj.parts:
        geom = scene.geometry[scene.graph[part.name][1]]
        assert geom.visual.kind == "texture" and geom.visual.material.baseColorTexture is not None
        v = trimesh.transform_points(np.asarray(geom.vertices), back)
        want = np.concatenate([c.vertices[c.faces].reshape(-1, 3) for c in part.components])
        assert np.allclose(np.sort(v, axis=0), np.sort(want, axis=0), atol=1e-5)  # float32 storage


def test_voxel_labels_union_and_priority():
    from unipixie.core.normalise import Normalisation, unit_cube_grid

    obj = P.generate(1, seed=0)  # a sport ball: the core lies inside the cover and wins
    assert obj.part_names == ["cover", "core"]
    norm = Normalisation.from_points(obj.vertices())
    geo = norm.geometry_to_world(unit_cube_grid(16))
    occ, part = obj.voxel_labels(geo)
    assert part.shape == (int(occ.sum()),)
    centres = geo.centres(np.argwhere(occ))
    r = np.linalg.norm(centres - 0.5 * (obj.bounds[0] + obj.bounds[1]), axis=1)
    R = 0.5 * float(np.ptp(obj.bounds[:, 0]))
    core_r = float(np.max(np.ptp(obj.parts[1].components[0].vertices, axis=0))) / 2
    assert np.all(part[r < core_r - geo.voxel_size] == 1)   # inside the core: core
    assert np.all(part[r > core_r + geo.voxel_size] == 0)   # in the shell: cover
    # a sphere fills pi/6 of its bounding cube (within the voxelisation error of a 16³ grid)
    assert abs(occ.sum() / 16 ** 3 - np.pi / 6 * (2 * R / norm.scale) ** 3) < 0.06


def test_fill_and_surface_points():
    obj = P.generate(8, seed=0)  # fruit
    pts, part = obj.fill(0.004)
    assert len(pts) > 500 and part.min() >= 0 and part.max() < len(obj.parts)
    sp = obj.surface_points(200, seed=1)
    assert sp.shape == (200, 3)
    assert np.all(sp >= obj.bounds[0] - 1e-9) and np.all(sp <= obj.bounds[1] + 1e-9)


# ------------------------------------------------------------------------------------ annotations
def _plant_dict():
    return {"semantic_class": "potted_plant",
            "parts": {"pot": {"material": "stationary", "E": [1e9, 5e9], "nu": [0.15, 0.2], "density": [1800, 2400]},
                      "trunk": {"material": "jelly", "E": [5e6, 5e7], "nu": [0.3, 0.35], "density": [600, 800]},
                      "leaves": {"material": "jelly", "E": [1e4, 5e4], "nu": [0.4, 0.45], "density": [200, 400]}},
            "constraints": ["assert mat['pot']['E'][0] > mat['trunk']['E'][1]",
                            {"quantity": "E", "greater": "trunk", "lesser": "leaves"}]}


def test_the_papers_example_annotation_is_accepted():
    ann = A.Annotation.from_dict(_plant_dict())
    assert ann.constraints[0] == A.Constraint("E", "pot", "trunk")
    again = A.Annotation.from_dict(json.loads(ann.to_json()))
    assert again.to_dict() == ann.to_dict()


def test_a_violating_annotation_is_refused():
    d = _plant_dict()
    d["parts"]["trunk"]["E"] = [5e3, 5e4]   # the trunk is no longer stiffer than the leaves
    with pytest.raises(UserError, match="constraint violated: trunk stiffer than leaves"):
        A.Annotation.from_dict(d)
    d = _plant_dict()
    d["parts"]["pot"]["E"] = [5e9, 1e9]
    with pytest.raises(UserError, match="empty"):
        A.Annotation.from_dict(d)
    d = _plant_dict()
    d["parts"]["pot"]["material"] = "granite"
    with pytest.raises(UserError, match="unknown material class 'granite'"):
        A.Annotation.from_dict(d)


@pytest.mark.parametrize("text", ["__import__('os').system('echo hi')", "assert mat['a']['E'][0] > 1e5",
                                  "assert mat['a']['E'][0] > mat['b']['nu'][1]", "mat['a']['E'][1] > mat['b']['E'][1]"])
def test_constraints_are_parsed_never_executed(text):
    with pytest.raises(UserError):
        A.parse_constraint(text)


def test_constraint_forms():
    c = A.parse_constraint("mat['leaves']['E'][1] < mat['trunk']['E'][0]")
    assert c == A.Constraint("E", "trunk", "leaves")
    c = A.parse_constraint("assert mat['pot']['density'][0] > 1.5 * mat['soil']['density'][1]")
    assert c.factor == 1.5 and c.quantity == "density"


def test_interpolation_is_log_linear_for_E_and_density():
    assert A.interpolate(1e4, 1e6, 0.5, "E") == pytest.approx(1e5, rel=1e-12)
    assert A.interpolate(100.0, 400.0, 0.5, "density") == pytest.approx(200.0, rel=1e-12)
    assert A.interpolate(0.2, 0.4, 0.25, "nu") == pytest.approx(0.25, rel=1e-12)
    assert A.interpolate(1e4, 1e6, 0.0, "E") == pytest.approx(1e4) and A.interpolate(1e4, 1e6, 1.0, "E") == pytest.approx(1e6)


def test_sampled_annotations_always_satisfy_their_constraints():
    rng = np.random.default_rng(0)
    for name in A.SEMANTIC_CLASSES:
        prior = A.class_prior(name)
        for v in prior.variants:
            parts = A.parts_of(prior, v.name)
            for _ in range(10):
                codes = {p: float(rng.choice([0.0, 1.0])) for p in parts}  # the hardest codes
                ann = A.sample_annotation(name, v.name, codes, rng)
                assert A.problems(ann) == []
