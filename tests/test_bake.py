"""Baking, the Blender-free part: frames, sizes, material sources, options, PC2, the armature plan, jobs, shards, manifests."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from unipixie.core import bake
from unipixie.core.errors import UserError
from unipixie.core.normalise import Normalisation, unit_cube_grid
from unipixie.core.types import MaterialField

from motion_helpers import lbs_motion


def _cube(size=1.0, centre=(0.0, 0.0, 0.0), matrix=None, name="Cube"):
    import trimesh

    m = trimesh.creation.box((size, size, size))
    return bake.BakeObject(name, m.vertices + np.asarray(centre), m.faces,
                           matrix_world=np.eye(4) if matrix is None else matrix)


# --------------------------------------------------------------------------- frames
def test_frame_ranges_parse_and_refuse_empty():
    fr = bake.parse_frames("1-120")
    assert (fr.start, fr.end, fr.count) == (1, 120, 120)
    assert np.allclose(fr.times(24.0)[:3], [0.0, 1 / 24, 2 / 24])
    assert bake.parse_frames("-10-5") == bake.FrameRange(-10, 5)
    assert bake.parse_frame_list("1-10,20-30") == [bake.FrameRange(1, 10), bake.FrameRange(20, 30)]
    with pytest.raises(UserError, match="empty"):
        bake.parse_frames("10-5")
    with pytest.raises(UserError, match="single frame"):
        bake.FrameRange(3, 3)
    with pytest.raises(UserError, match="START-END"):
        bake.parse_frames("1 to 9")


# --------------------------------------------------------------------------- the object as arrays
def test_bake_object_world_local_round_trip_with_unit_scale():
    M = np.eye(4)
    M[:3, :3] = Rotation.from_euler("xyz", [0.3, -0.2, 1.1]).as_matrix() @ np.diag([1.0, 2.0, 0.5])
    M[:3, 3] = [1.0, -2.0, 3.0]
    obj = bake.BakeObject("c", np.random.default_rng(0).normal(size=(20, 3)), [[0, 1, 2]], M, unit_scale=0.01)
    world = obj.rest_world
    assert np.allclose(world, (obj.rest_local @ M[:3, :3].T + M[:3, 3]) * 0.01)
    assert np.allclose(obj.to_local(world), obj.rest_local, atol=1e-12)


def test_bake_object_refuses_empty_and_degenerate_input():
    with pytest.raises(UserError, match="no vertices"):
        bake.BakeObject("e", np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(UserError, match="no faces"):
        bake.BakeObject("e", np.zeros((4, 3)), np.zeros((0, 3)))
    with pytest.raises(UserError, match="NaN"):
        bake.BakeObject("e", [[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]], [[0, 1, 2]])
    with pytest.raises(UserError, match="zero scale"):
        bake.BakeObject("e", np.eye(3), [[0, 1, 2]], np.diag([1.0, 0.0, 1.0, 1.0]))


def test_size_checks_refuse_absurd_and_warn_unusual():
    assert bake.check_size(_cube(1.0)) == []
    warn = bake.check_size(_cube(1e-4))
    assert len(warn) == 1 and "real-world size" in warn[0]
    assert bake.check_size(_cube(5e3))
    with pytest.raises(UserError, match="unit scale"):
        bake.check_size(_cube(1e6))
    with pytest.raises(UserError, match="outside the range"):
        bake.check_size(_cube(1e-8))


def test_build_body_repairs_small_holes_refuses_open_sheets_and_drops_zero_area_faces():
    import trimesh

    box = trimesh.creation.box((0.3, 0.3, 0.3))
    holed = bake.BakeObject("holed", box.vertices, box.faces[2:])  # one quad removed
    body, warnings = bake.build_body(holed, "mpm")
    assert body.mesh.is_watertight and len(body.tracked_points) == 8
    sheet = bake.BakeObject("sheet", [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    with pytest.raises(UserError, match="open .* Fill Holes"):
        bake.build_body(sheet, "mpm")
    # a degenerate (zero-area) face on a closed cube: dropped with a warning, the tracked points kept
    verts = np.vstack([box.vertices, [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]]])
    faces = np.vstack([box.faces, [[8, 9, 10]]])
    body, warnings = bake.build_body(bake.BakeObject("degenerate", verts, faces), "spring_mass")
    assert any("zero-area" in w for w in warnings) and len(body.tracked_points) == 11
    flat = bake.BakeObject("flat", [[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]])
    with pytest.raises(UserError, match="zero area"):
        bake.build_body(flat, "mpm")


# --------------------------------------------------------------------------- material sources
def test_homogeneous_source_and_manifest_material_parsing():
    src = bake.HomogeneousSource(E=2e5, nu=0.25, density=900, material="plasticine")
    res = src.resolve(_cube(), alpha=0.3, solver="mpm")
    assert res.spec.E == 2e5 and res.spec.material == 3 and "plasticine" in res.description
    assert isinstance(bake.material_source_from_dict("model"), bake.ModelSource)
    assert isinstance(bake.material_source_from_dict({"file": "f.npz"}), bake.FieldFileSource)
    h = bake.material_source_from_dict({"E": 3e4, "class": "jelly"})
    assert (h.E, h.nu, h.material) == (3e4, bake.DEFAULT_HOMOGENEOUS["nu"], "jelly")
    with pytest.raises(UserError, match="unknown key"):
        bake.material_source_from_dict({"E": 1, "young": 2})
    with pytest.raises(UserError, match="no mass"):
        bake.HomogeneousSource(material="background").resolve(_cube(), None, "mpm")
    with pytest.raises(UserError, match="Poisson"):
        bake.HomogeneousSource(nu=0.5).resolve(_cube(), None, "mpm")


def test_field_file_source_maps_the_normalised_field_onto_the_object(tmp_path):
    obj = _cube(2.0, centre=(10.0, 0.0, 1.0))
    geo = unit_cube_grid(8)
    occ = np.zeros((8, 8, 8), bool)
    occ[1:7, 1:7, 1:7] = True
    K = int(occ.sum())
    E = np.linspace(1e4, 1e6, K)
    f = MaterialField(geo, occ, E, np.full(K, 0.3), np.full(K, 1000.0), np.zeros(K), alpha=0.25)
    path = f.save(tmp_path / "field.npz")
    res = bake.FieldFileSource(str(path)).resolve(obj, alpha=0.25, solver="mpm")
    world = res.spec
    norm = Normalisation.from_points(obj.rest_world)
    assert np.allclose(world.geometry.origin, norm.to_world(geo.origin))
    assert world.geometry.voxel_size == pytest.approx(geo.voxel_size * 2.0)
    assert np.array_equal(world.E, f.E) and res.warnings == []
    res = bake.FieldFileSource(str(path)).resolve(obj, alpha=0.9, solver="mpm")
    assert any("α = 0.25" in w for w in res.warnings)
    with pytest.raises(UserError, match="not found"):
        bake.FieldFileSource(str(tmp_path / "missing.npz")).resolve(obj, 0.5, "mpm")


def test_model_source_needs_a_plan_and_uses_the_one_it_carries(monkeypatch):
    from unipixie.core.bake import sources
    from unipixie.core.model.plan import ModelPlan

    with pytest.raises(UserError, match="needs the UniPixie model"):
        bake.ModelSource().resolve(_cube(), 0.5, "mpm")
    with pytest.raises(UserError, match="needs α"):
        bake.ModelSource().resolve(_cube(), None, "mpm")
    seen = []
    plan = ModelPlan(grid="g.npz", sweep="s.npz", checkpoint="c")

    def model(obj, alpha, solver, given, solver_heads=False):
        seen.append((obj.name, alpha, solver))
        assert given is plan
        from unipixie.solvers.material_sampling import HomogeneousMaterial

        return bake.ResolvedMaterial(HomogeneousMaterial(1e4 * (1 + 99 * alpha), 0.3, 1000), description="test model")

    monkeypatch.setattr(sources, "plan_material", model)      # the model, called with the source's own plan
    res = bake.ModelSource(plan=plan).resolve(_cube(), 1.0, "spring_mass")
    assert res.spec.E == pytest.approx(1e6) and seen == [("Cube", 1.0, "spring_mass")]


# --------------------------------------------------------------------------- options
def test_options_validate_solver_effects_alpha_and_output():
    o = bake.BakeOptions(solver="spring-mass", frames="1-10", effects=["linear_drag:c=0.5"], alpha=0.5)
    assert o.solver == "spring_mass" and o.effects[0].name == "linear_drag" and len(o.times()) == 10
    with pytest.raises(UserError, match="unknown solver"):
        bake.BakeOptions(solver="fem")
    with pytest.raises(UserError, match="unknown effect"):
        bake.BakeOptions(effects=["air_drag:c=1"])
    with pytest.raises(UserError, match=r"\[0, 1\]"):
        bake.BakeOptions(alpha=1.5)
    with pytest.raises(UserError, match="armature bake needs the LBS solver"):
        bake.BakeOptions(solver="mpm", output="armature")
    with pytest.raises(UserError, match="particle object"):
        bake.BakeOptions(solver="lbs", particles=True)
    with pytest.raises(UserError, match="empty"):
        bake.BakeOptions(frames=(10, 1))


def test_choose_output_rules():
    assert bake.choose_output("mpm", "auto", 1000, 100)[0] == "shape_keys"
    mode, notes = bake.choose_output("mpm", "auto", 10_000, 250)
    assert mode == "mesh_cache" and "large" in notes[0]
    assert bake.choose_output("lbs", "auto", 10, 10)[0] == "armature"
    assert bake.choose_output("spring_mass", "auto", 10, 10, has_other_shape_keys=True)[0] == "mesh_cache"
    assert bake.choose_output("mpm", "auto", 10, 10, mesh_shared=True)[0] == "mesh_cache"
    with pytest.raises(UserError, match="shape keys of its own"):
        bake.choose_output("mpm", "shape_keys", 10, 10, has_other_shape_keys=True)


def test_frame_progress_counts_solver_steps_in_either_unit():
    from unipixie.core.progress import Progress

    for unit in (1.0, 0.25):  # MPM steps 1 per frame, spring-mass 1/(T-1)
        parent = Progress(show_bar=False)
        fp = bake.FrameProgress(parent, 4)
        fp.set_status("setting up")
        assert parent.fraction == 0.0
        fp.step(unit, "frame 1")
        fp.step(unit, "frame 2")
        assert parent.fraction == pytest.approx(0.5) and parent.status == "frame 2"
    parent.cancel()
    with pytest.raises(UserError):  # CancelledError is a UserError
        fp.step(unit)


def test_background_run_cancels_and_reraises():
    import threading

    started = threading.Event()

    def work(progress):
        started.set()
        while True:
            progress.step(0.0, "working")

    run = bake.BackgroundRun(work).start()
    started.wait(5)
    assert not run.done
    run.cancel()
    assert run.done
    from unipixie.core.errors import CancelledError

    with pytest.raises(CancelledError):
        run.result()
    ok = bake.BackgroundRun(lambda p: 42).start()
    ok.wait(5)
    assert ok.result() == 42


# --------------------------------------------------------------------------- the armature plan
def test_lbs_blend_form_is_a_convex_blend_equal_to_the_lbs_motion():
    rest = np.random.default_rng(2).normal(size=(30, 3))
    W, HT, pos = lbs_motion(rest)
    maps, bw, labels = bake.lbs_blend_form(W, HT)
    assert np.all(bw >= 0) and np.all(bw <= 1) and np.allclose(bw.sum(1), 1.0)
    assert labels[0] == "constant" and {"00+", "00-"} <= set(labels)
    blended = bake.armature_deform(rest, bw, maps)
    assert np.allclose(blended, pos, atol=1e-10)


def test_blend_form_scales_each_handle_to_keep_bones_proper():
    rng = np.random.default_rng(5)
    rest = rng.normal(size=(40, 3))
    W = np.stack([rng.uniform(0, 5, 40), rng.uniform(-1, 1, 40), np.ones(40)], axis=1)
    HT = np.zeros((3, 3, 3, 4))
    HT[:, 2, :, :3] = np.eye(3)
    HT[:, 0, :, :3] = 0.01 * rng.normal(size=(3, 3, 3))
    HT[:, 1, :, :3] = 0.3 * np.eye(3)  # A − k D₁ collapses at k = 3.3 < max Σ|w| ≈ 6: one common scale fails
    maps, bw, labels = bake.lbs_blend_form(W, HT)
    assert np.all(np.linalg.det(maps[..., :3, :3]) > 0)
    X1 = np.concatenate([rest, np.ones((40, 1))], axis=1)
    pos = np.einsum("tij,nj->tni", HT[:, 2], X1) + np.einsum("nh,thij,nj->tni", W[:, :2], HT[:, :2], X1)
    assert np.allclose(bake.armature_deform(rest, bw, maps), pos, atol=1e-10)
    assert np.allclose(bw.sum(1), 1.0) and bw.min() >= 0


def test_armature_plan_is_exact_for_general_affine_handles_and_refuses_reflections():
    M = np.eye(4)
    M[:3, :3] = Rotation.from_euler("z", 0.7).as_matrix() @ np.diag([1.5, 1.0, 0.8])
    M[:3, 3] = [0.0, 1.0, 2.0]
    obj = _cube(1.0, matrix=M)
    W, HT, pos = lbs_motion(obj.rest_world, shear=0.3)  # shear and stretch along turning axes
    plan, reason = bake.plan_armature(obj, W, HT, pos, tolerance=1e-9)
    assert plan is not None, reason
    assert plan.max_error < 1e-9 and plan.weights.shape == (8, plan.bone_count)
    for q in (plan.parent_rotation, plan.child_rotation):
        assert np.allclose(np.linalg.norm(q, axis=-1), 1.0)
        assert np.all(np.sum(q[1:] * q[:-1], axis=-1) >= 0)  # one hemisphere frame to frame
    # a constant handle that mirrors space cannot be a bone
    HT[:, -1, 0, :3] *= -1
    plan, reason = bake.plan_armature(obj, W, HT, pos)
    assert plan is None and "mirror" in reason
    plan, reason = bake.plan_armature(obj, W[:5], HT, pos)
    assert plan is None and "does not fit" in reason


def test_continuous_svd_keeps_axes_matched_between_frames():
    T = 20
    L = np.stack([Rotation.from_rotvec([0, 0, 0.1 * t]).as_matrix() @ np.diag([1 + 0.05 * np.sin(t), 1.0, 1 - 0.02 * t])
                  for t in range(T)])
    U, s, V = bake.continuous_svd(L)
    assert np.allclose(U * s[:, None, :] @ np.swapaxes(V, 1, 2), L, atol=1e-12)
    assert np.all(np.linalg.det(U) > 0) and np.all(np.linalg.det(V) > 0)
    assert np.all(np.abs(np.einsum("tij,tij->tj", V[1:], V[:-1])) > 0.9)  # no axis swaps or flips


def test_armature_deform_matches_blender_normalisation_rule():
    x = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    w = np.array([[2.0, 2.0], [0.0, 0.0]])  # normalised to 0.5/0.5; zero weight stays at rest
    D = np.tile(np.eye(4), (1, 2, 1, 1))
    D[0, 0, :3, 3] = [1.0, 0, 0]
    D[0, 1, :3, 3] = [0, 1.0, 0]
    out = bake.armature_deform(x, w, D)
    assert np.allclose(out[0, 0], [1.5, 0.5, 0.0]) and np.allclose(out[0, 1], x[1])


# --------------------------------------------------------------------------- PC2
def test_pc2_round_trip_header_and_errors(tmp_path):
    pos = np.random.default_rng(1).normal(size=(7, 11, 3)).astype(np.float32)
    path = bake.write_pc2(tmp_path / "a.pc2", pos, start_frame=5.0, sample_rate=1.0)
    raw = path.read_bytes()
    assert raw[:12] == b"POINTCACHE2\0" and len(raw) == 32 + 7 * 11 * 12
    cache = bake.read_pc2(path)
    assert np.array_equal(cache.positions, pos) and cache.start_frame == 5.0 and cache.sample_rate == 1.0
    assert not list(tmp_path.glob("*.tmp*"))
    (tmp_path / "short.pc2").write_bytes(raw[:-4])
    with pytest.raises(UserError, match="promises"):
        bake.read_pc2(tmp_path / "short.pc2")
    (tmp_path / "bad.pc2").write_bytes(b"NOTACACHE" + raw[9:])
    with pytest.raises(UserError, match="not a PC2"):
        bake.read_pc2(tmp_path / "bad.pc2")
    with pytest.raises(UserError, match="NaN"):
        bake.write_pc2(tmp_path / "nan.pc2", np.full((2, 2, 3), np.nan))
    assert not (tmp_path / "nan.pc2").exists()


# --------------------------------------------------------------------------- jobs, shards, manifests
def test_jobs_expand_batches_and_refuse_conflicting_outputs():
    jobs = bake.expand_jobs("s.blend", ["A", "B"], "out_{object}_{alpha}.blend", alphas=[0.0, 1.0],
                            frame_ranges=[None])
    assert [j.out for j in jobs] == ["out_A_0.blend", "out_A_1.blend", "out_B_0.blend", "out_B_1.blend"]
    jobs = bake.expand_jobs("s.blend", ["A", "B"], "all.blend")
    assert len(bake.group_jobs(jobs)) == 1  # one scene opened, both objects baked, saved once
    with pytest.raises(UserError, match="both write object 'A'"):
        bake.expand_jobs("s.blend", ["A"], "o.blend", alphas=[0.0, 1.0])
    jobs = bake.expand_jobs("s.blend", ["A"], "o_{frames}.blend", frame_ranges=bake.parse_frame_list("1-10,11-20"))
    assert [j.out for j in jobs] == ["o_1-10.blend", "o_11-20.blend"]
    with pytest.raises(UserError, match="unknown placeholder"):
        bake.expand_jobs("s.blend", ["A"], "o_{colour}.blend")
    with pytest.raises(UserError, match="overwrite its input"):
        bake.expand_jobs("s.blend", ["A"], "s.blend")


def test_shards_partition_the_output_groups():
    jobs = bake.expand_jobs("s.blend", [f"O{i}" for i in range(7)], "o_{object}.blend")
    groups = bake.group_jobs(jobs)
    parts = [bake.shard_groups(groups, (i, 3)) for i in range(3)]
    names = [j.object for p in parts for g in p for j in g]
    assert sorted(names) == sorted(j.object for j in jobs) and len(set(names)) == 7
    assert [len(p) for p in parts] == [3, 2, 2]
    assert bake.shard_groups(groups[:1], (2, 3)) == []
    with pytest.raises(UserError):
        bake.shard_groups(groups, (3, 3))


def test_select_objects_with_wildcards():
    avail = ["Rock.001", "Rock.002", "Plant", "Camera"]
    assert bake.select_objects(["Rock*", "Plant"], avail) == ["Rock.001", "Rock.002", "Plant"]
    with pytest.raises(UserError, match="no object named 'Tree'"):
        bake.select_objects(["Tree"], avail)
    with pytest.raises(UserError, match="no object matches"):
        bake.select_objects(["Tree*"], avail)


def test_manifest_schema_paths_and_errors(tmp_path):
    doc = {"format": bake.MANIFEST_FORMAT,
           "defaults": {"solver": "spring_mass", "frames": "1-24", "material": {"E": 2e4, "class": "jelly"}},
           "jobs": [{"scene": "a.blend", "objects": ["Cube", "Ball"], "out": "out/a_baked.blend"},
                    {"scene": "b.blend", "object": "Jelly", "alpha": [0, 1], "out": "out/b_{alpha}.blend",
                     "material": "model", "effects": ["linear_drag:c=0.5"], "scenario": {"ground": None}}]}
    path = tmp_path / "jobs.json"
    path.write_text(json.dumps(doc))
    jobs = bake.load_manifest(path)
    assert len(jobs) == 4
    assert jobs[0].scene == str(tmp_path / "a.blend") and jobs[0].out == str(tmp_path / "out/a_baked.blend")
    assert jobs[0].frames == bake.FrameRange(1, 24) and isinstance(jobs[0].material, bake.HomogeneousSource)
    assert [j.alpha for j in jobs[2:]] == [0.0, 1.0] and isinstance(jobs[3].material, bake.ModelSource)
    assert jobs[3].scenario == {"ground": None} and jobs[3].effects == ["linear_drag:c=0.5"]
    assert len(bake.group_jobs(jobs)) == 3
    for broken, msg in [({"format": "x", "jobs": []}, "format"),
                        ({"format": bake.MANIFEST_FORMAT, "jobs": []}, "non-empty"),
                        ({"format": bake.MANIFEST_FORMAT, "jobs": [{"scene": "a.blend", "out": "o.blend"}]}, "'object'"),
                        ({"format": bake.MANIFEST_FORMAT, "jobs": [{"scene": "a.blend", "object": "A", "out": "o.blend",
                                                                    "colour": 1}]}, "unknown key"),
                        ({"format": bake.MANIFEST_FORMAT, "jobs": [{"scene": "a.blend", "object": "A", "out": "o.blend",
                                                                    "alpha": 2}]}, "alpha"),
                        ({"format": bake.MANIFEST_FORMAT, "jobs": [{"scene": "a.blend", "object": "A", "out": "o.blend",
                                                                    "alpha": 0.5, "material": {"E": 2e5}}]},
                         r"jobs\[0\]: 'alpha' with a homogeneous 'material': .*exactly one source"),
                        ({"format": bake.MANIFEST_FORMAT, "defaults": {"alpha": 0.5},
                          "jobs": [{"scene": "a.blend", "object": "A", "out": "o.blend", "material": {"file": "f.npz"}}]},
                         "'alpha' with a field 'material'")]:
        path.write_text(json.dumps(broken))
        with pytest.raises(UserError, match=msg):
            bake.load_manifest(path)
    path.write_text("{not json")
    with pytest.raises(UserError, match="not valid JSON"):
        bake.load_manifest(path)


def test_bake_record_round_trip():
    text = bake.make_record(mode="shape_keys", frames=[1, 10], files=[], arr=np.arange(3))
    rec = bake.parse_record(text)
    assert rec["mode"] == "shape_keys" and rec["arr"] == [0, 1, 2]
    assert bake.parse_record("") is None and bake.parse_record('{"format": "other"}') is None


# --------------------------------------------------------------------------- the model's material at α
@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    """A randomly initialised tiny UniPixie model saved as a checkpoint, and a feature grid of a cube."""
    torch = pytest.importorskip("torch")
    from unipixie.core.model import UniPixieModel, preset, save_model
    from unipixie.core.types import FeatureGrid

    torch.manual_seed(0)
    cfg = preset("tiny", feature_model="bake-test-features", feature_dim=8, grid_resolution=16, spring_anchors=32)
    d = tmp_path_factory.mktemp("model")
    save_model(UniPixieModel(cfg), d / "ckpt")
    occ = np.zeros((16, 16, 16), bool)
    occ[4:12, 4:12, 4:12] = True
    grid = FeatureGrid(unit_cube_grid(16), occ, np.random.default_rng(0).normal(size=(int(occ.sum()), 8)),
                       feature_model="bake-test-features")
    return d / "ckpt", grid.save(d / "grid.npz")


def test_model_source_predicts_each_solvers_material_from_a_feature_grid(tiny_model):
    ckpt, grid = tiny_model
    obj = _cube(0.4, centre=(1.0, 2.0, 0.5))
    src = bake.ModelSource(features=str(grid), checkpoint=str(ckpt))
    res = src.resolve(obj, 0.5, "mpm")
    field_w = res.spec
    assert isinstance(field_w, MaterialField) and field_w.alpha == 0.5
    norm = Normalisation.from_points(obj.rest_world)
    assert np.allclose(field_w.geometry.origin, norm.to_world(unit_cube_grid(16).origin))
    again = bake.ModelSource(features=str(grid), checkpoint=str(ckpt)).resolve(obj, 0.5, "mpm").spec
    assert np.array_equal(again.E, field_w.E)  # deterministic for a seed
    # by default every solver discretises the MPM head's continuum field (one material, one motion)
    res = src.resolve(obj, 0.5, "lbs")
    assert res.settings["skinning_params"].shape == (650,) and isinstance(res.spec, MaterialField)
    assert np.array_equal(res.spec.E, field_w.E) and np.array_equal(res.spec.nu, field_w.nu)
    res = src.resolve(obj, 0.5, "spring_mass")
    assert np.array_equal(res.spec.E, field_w.E) and "stiffness" not in res.settings
    # the solvers' own heads on request
    heads = bake.ModelSource(features=str(grid), checkpoint=str(ckpt), solver_heads=True)
    res = heads.resolve(obj, 0.5, "lbs")
    assert res.settings["skinning_params"].shape == (650,) and isinstance(res.spec, MaterialField)
    res = heads.resolve(obj, 1.0, "spring_mass")
    assert res.settings["stiffness"].shape == (32,) and res.settings["anchors"] == 32
    assert np.isfinite(res.settings["softness"])
    for s in (src, heads):
        back = bake.material_source_from_dict(s.to_dict())
        assert isinstance(back, bake.ModelSource) and back.solver_heads == s.solver_heads
    with pytest.raises(UserError, match="not a UniPixie checkpoint|not found"):
        bake.ModelSource(features=str(grid), checkpoint=str(ckpt.parent / "nowhere")).resolve(obj, 0.5, "mpm")


def test_model_material_drives_a_real_spring_mass_run(tiny_model):
    from unipixie.solvers.scenario import Scenario

    ckpt, grid = tiny_model
    obj = _cube(0.3, centre=(0.0, 0.0, 0.5))
    opts = bake.BakeOptions(solver="spring_mass", frames=(1, 4), alpha=0.3,
                            material=bake.ModelSource(features=str(grid), checkpoint=str(ckpt), solver_heads=True),
                            solver_settings={"neighbours": 10, "fixed_springs": 5, "fill_per_anchor": 6})
    result = bake.simulate(obj, Scenario(ground_height=0.0), opts)
    assert result.trajectory.positions.shape == (4, 8, 3) and "model at α 0.3" in result.material_description
    assert result.trajectory.meta["anchors"] <= 32


def test_a_grid_too_coarse_for_thin_parts_is_said_in_the_bake():
    """MPM's own notes reach the bake's warnings: a bar 4 cm thick on a grid of 8 cells across its 0.6 m (7.5 cm
    cells: 0.5 cells thick) is under-resolved, which the demo's plant showed damps its swing (docs/fidelity.md)."""
    import trimesh

    from unipixie.solvers.scenario import Scenario

    m = trimesh.creation.box((0.6, 0.04, 0.04))
    bar = bake.BakeObject("Bar", m.vertices + np.array([0.0, 0.0, 0.5]), m.faces, matrix_world=np.eye(4))
    coarse = bake.BakeOptions(solver="mpm", frames=(1, 2), material=bake.HomogeneousSource(E=1e5, nu=0.3, density=500),
                              solver_settings={"cells_across": 8})
    result = bake.simulate(bar, Scenario(ground_height=0.0), coarse)
    (note,) = [w for w in result.warnings if "thinnest parts" in w]
    assert "are only 0.5 cells thick at 8 cells across" in note and "leave cells_across unset" in note
    fine = bake.BakeOptions(solver="mpm", frames=(1, 2), material=bake.HomogeneousSource(E=1e5, nu=0.3, density=500),
                            solver_settings={"cells_across": 32})
    assert not [w for w in bake.simulate(bar, Scenario(ground_height=0.0), fine).warnings if "thinnest parts" in w]
