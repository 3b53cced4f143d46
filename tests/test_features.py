"""Dense features (offline random ViT, local CLIP weights), the whole features pipeline through bpy with its
cache, the ``unipixie features`` command, the panel operators and bad input."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("open_clip")

from unipixie.core import clip_features as cf  # noqa: E402
from unipixie.core.errors import UserError  # noqa: E402


@pytest.fixture
def no_clip_env(monkeypatch):
    monkeypatch.delenv(cf.CLIP_WEIGHTS_ENV, raising=False)


# --------------------------------------------------------------------------- extractors (no Blender)
def test_offline_extractor_is_deterministic_named_and_not_clip():
    state = torch.random.get_rng_state()
    a = cf.offline_extractor()
    b = cf.offline_extractor()
    assert torch.equal(torch.random.get_rng_state(), state)          # the caller's RNG is untouched
    import open_clip

    assert isinstance(a.visual, open_clip.transformer.VisionTransformer)   # the open_clip code path
    assert a.name == cf.OFFLINE_FEATURE_MODEL == "offline-random-vit-w32" and not a.is_clip
    assert a.dim == 32 and a.patch_size == 16 and a.image_size == 224 and a.token_grid == 14
    images = np.random.default_rng(1).random((3, 96, 96, 3), dtype=np.float32)   # resized to 224 inside
    fa, fb = a(images), b(images)
    assert fa.shape == (3, 14, 14, 32) and torch.equal(fa, fb)
    assert not torch.equal(fa, cf.offline_extractor(seed=1)(images))
    assert cf.offline_extractor(seed=1).name == "offline-random-vit-w32-seed1"
    assert a.identity == cf.offline_identity()
    # features depend on the image
    assert (fa[0] - fa[1]).abs().mean() > 1e-3
    # only models with loaded CLIP weights count as CLIP (not the timing-only random ViT-B-16)
    timing = cf.FeatureExtractor("ViT-B-16-random-weights", None, 224, 16, 768, (0,) * 3, (1,) * 3,
                                 identity={"model": "ViT-B-16", "random_seed": 0})
    assert not timing.is_clip


def test_missing_clip_weights_say_where_to_put_them(no_clip_env, tmp_path, monkeypatch):
    with pytest.raises(UserError) as err:
        cf.make_extractor()
    msg = str(err.value)
    assert str(cf.default_weights_dir()) in msg and cf.CLIP_WEIGHTS_ENV in msg and "--clip-weights" in msg
    assert "--offline-features" in msg and "not CLIP" in msg
    monkeypatch.setenv(cf.CLIP_WEIGHTS_ENV, str(tmp_path / "nowhere.bin"))
    with pytest.raises(UserError, match="nowhere.bin.*UNIPIXIE_CLIP_WEIGHTS"):
        cf.load_clip()
    with pytest.raises(UserError, match="given as the CLIP weights path"):
        cf.load_clip(tmp_path / "missing")
    (tmp_path / "empty_dir").mkdir()
    (tmp_path / "empty_dir" / "readme.txt").write_text("x")
    with pytest.raises(UserError, match="holds no checkpoint"):
        cf.load_clip(tmp_path / "empty_dir")


def _tiny_open_clip_dir(path):
    """An open_clip 'local-dir' model folder (config + weights) of a tiny ViT, as a user would download one."""
    import open_clip

    cfg = {"embed_dim": 16,
           "vision_cfg": {"image_size": 64, "patch_size": 16, "width": 24, "layers": 1, "head_width": 8},
           "text_cfg": {"context_length": 8, "vocab_size": 64, "width": 8, "heads": 1, "layers": 1}}
    torch.manual_seed(3)
    model = open_clip.create_model("ViT-B-16", pretrained=None, **cfg)
    path.mkdir()
    (path / "open_clip_config.json").write_text(json.dumps({"model_cfg": cfg, "preprocess_cfg": {}}))
    torch.save(model.state_dict(), path / "open_clip_pytorch_model.bin")
    return model


def test_clip_weights_load_from_a_local_folder_and_bad_files_fail(tmp_path, no_clip_env):
    model = _tiny_open_clip_dir(tmp_path / "tiny")
    ext = cf.load_clip(tmp_path / "tiny")
    assert ext.is_clip and ext.name == cf.CLIP_MODEL and ext.dim == 24 and ext.token_grid == 4
    for name, p in model.visual.state_dict().items():            # the weights were loaded, not re-initialised
        assert torch.equal(ext.visual.state_dict()[name], p), name
    feats = ext(np.random.default_rng(0).random((2, 64, 64, 3), dtype=np.float32))
    assert feats.shape == (2, 4, 4, 24)
    assert ext.identity["weights"]["files"][0][0] in ("open_clip_config.json", "open_clip_pytorch_model.bin")
    # a checkpoint of another architecture given as a file for ViT-B-16: clear error, no traceback
    with pytest.raises(UserError, match="could not load CLIP weights"):
        cf.load_clip(tmp_path / "tiny" / "open_clip_pytorch_model.bin")
    (tmp_path / "notes.txt").write_text("not weights")
    with pytest.raises(UserError, match="not a checkpoint file"):
        cf.load_clip(tmp_path / "notes.txt")


def test_pictures_are_written(tmp_path):
    from unipixie.core.features import pca_colours, save_feature_slices, save_view_sheet
    from unipixie.core.normalise import unit_cube_grid
    from unipixie.core.types import FeatureGrid, Views

    rng = np.random.default_rng(0)
    views = Views(rng.random((5, 32, 32, 3)), np.ones((5, 32, 32)), np.tile(np.eye(3), (5, 1, 1)), np.tile(np.eye(4), (5, 1, 1)))
    occ = np.zeros((64, 64, 64), bool)
    occ[20:40, 10:50, 30:34] = True
    idx = np.argwhere(occ)
    grid = FeatureGrid(unit_cube_grid(), occ, np.c_[idx, rng.random((len(idx), 5))].astype(np.float16), "test")
    colours = pca_colours(grid.features)
    assert colours.shape == (len(idx), 3) and colours.min() >= 0 and colours.max() <= 1
    # the first principal component follows the direction of largest spread (here y, 40 voxels)
    assert abs(np.corrcoef(colours[:, 0], idx[:, 1])[0, 1]) > 0.9
    from PIL import Image

    for path in (save_view_sheet(views, tmp_path / "sheet.png"), save_feature_slices(grid, tmp_path / "slices.png")):
        with Image.open(path) as im:
            assert im.size[0] > 300 and im.size[1] > 200


# --------------------------------------------------------------------------- through Blender
FAST = dict(view_count=6, resolution=64, samples=2, offline=True, render_device="cpu")


def _x_material(bpy):
    mat = bpy.data.materials.new("blue")
    mat.diffuse_color = (0.1, 0.2, 0.9, 1.0)
    bsdf = next((n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED"), None)
    if bsdf is not None:
        bsdf.inputs["Base Color"].default_value = (0.1, 0.2, 0.9, 1.0)
    return mat


@pytest.mark.blender
def test_pipeline_on_a_blender_object_is_cached_and_maps_back_to_world(blender):
    bpy = blender
    from unipixie.core.features import FeatureOptions, compute_features
    from unipixie.core.normalise import Normalisation
    from unipixie.core.types import FeatureGrid, Views

    bpy.ops.mesh.primitive_cylinder_add(radius=0.3, depth=1.2, location=(2.0, -1.0, 0.5))
    obj = bpy.context.active_object
    obj.data.materials.append(_x_material(bpy))
    options = FeatureOptions(**FAST)
    result = compute_features(obj, options)
    grid = result.grid
    assert not result.cache_hit and grid.feature_model == "offline-random-vit-w32" and grid.dim == 32
    assert grid.meta["is_clip"] is False and grid.meta["view_count"] == 6
    assert grid.features.dtype == np.float16 and grid.features.shape[0] == grid.occupancy.sum()
    # a cylinder of radius 0.25 and height 1 (normalised) fills pi r^2 h of the cube: 2 % tolerance
    expected = np.pi * 16 ** 2 * 64
    assert abs(int(grid.occupancy.sum()) - expected) < 0.02 * expected
    assert grid.meta["painted_fraction_of_surface"] > 0.95
    for stage in ("geometry", "render", "occupancy", "features", "lift"):
        assert stage in result.timings
    # occupied voxels map back onto the object in world metres
    norm = Normalisation.of(grid)
    world = norm.geometry_to_world(grid.geometry).centres(grid.indices)
    assert np.allclose(world.mean(axis=0), (2.0, -1.0, 0.5), atol=0.02)
    assert np.allclose(world.max(axis=0) - world.min(axis=0), (0.6, 0.6, 1.2), atol=2 * norm.scale / 64)
    assert Views.load(result.views_path).count == 6 and FeatureGrid.load(result.grid_path).dim == 32

    t = time.perf_counter()
    again = compute_features(obj, options)
    assert again.cache_hit and time.perf_counter() - t < 0.5       # "instant": no render, no model
    assert np.array_equal(again.grid.features, grid.features) and again.grid_path == result.grid_path
    # a change of material or view count is a new entry
    obj.data.materials[0].diffuse_color = (0.9, 0.2, 0.1, 1.0)
    assert compute_features(obj, options).grid_path != result.grid_path


@pytest.mark.blender
def test_files_are_imported_into_a_temporary_scene_and_removed(blender, tmp_path):
    bpy = blender
    import trimesh

    from unipixie.core.blender_io.scene_import import loaded_objects, snapshot_ids
    from unipixie.core.features import FeatureOptions, features_for_file

    box = trimesh.creation.box((2.0, 1.0, 0.5))
    box.export(tmp_path / "box.obj")
    box.export(tmp_path / "box.glb")
    bpy.ops.mesh.primitive_cube_add()
    before = snapshot_ids()
    result = features_for_file(tmp_path / "box.glb", options=FeatureOptions(**FAST))
    assert abs(int(result.grid.occupancy.sum()) - 64 * 32 * 16) <= 0.02 * 64 * 32 * 16
    assert result.grid.meta["source"].endswith("box.glb")
    with loaded_objects(tmp_path / "box.obj") as objects:
        assert len(objects) == 1 and objects[0].type == "MESH" and len(objects[0].data.polygons) in (6, 12)
        assert bpy.context.scene.objects.get(objects[0].name) is None      # not in the user's scene
    assert snapshot_ids() == before
    (tmp_path / "box.xyz").write_text("0 0 0\n")
    with pytest.raises(UserError, match="unsupported file type '.xyz'"):
        features_for_file(tmp_path / "box.xyz")


@pytest.mark.blender
def test_blend_files_need_an_object_name_when_they_hold_several(blender, tmp_path):
    bpy = blender
    from unipixie.core.features import FeatureOptions, features_for_file

    bpy.ops.mesh.primitive_cube_add(location=(0, 0, 0))
    crate = bpy.context.active_object
    crate.name = "Crate"
    crate.modifiers.new("round", "SUBSURF").render_levels = 2        # modifiers are applied
    bpy.ops.mesh.primitive_ico_sphere_add(location=(4, 0, 0))
    bpy.context.active_object.name = "Ball"
    bpy.ops.object.empty_add(location=(0, 7, 0))
    crate.parent = bpy.context.active_object                          # and parents' transforms
    path = tmp_path / "two.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    with pytest.raises(UserError, match=r"several objects with geometry \(Ball, Crate\).*--object"):
        features_for_file(path, options=FeatureOptions(**FAST))
    with pytest.raises(UserError, match="no object named 'Lamp'"):
        features_for_file(path, "Lamp", options=FeatureOptions(**FAST))
    result = features_for_file(path, "Crate", options=FeatureOptions(**FAST))
    assert 0.35 * 64 ** 3 < result.grid.occupancy.sum() < 0.6 * 64 ** 3  # subdivided: round (sphere: 0.52)
    assert np.allclose(result.normalisation.centre, (0, 7, 0), atol=1e-4)
    assert len(bpy.data.objects) == 0                                 # nothing left behind


@pytest.mark.blender
def test_features_command_writes_grid_and_pictures(blender, tmp_path, capsys, no_clip_env):
    import trimesh

    from unipixie.cli import main
    from unipixie.core.types import FeatureGrid, Views

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    mesh.update_faces(np.arange(len(mesh.faces))[4:])                  # open: a warning, not a failure
    mesh.export(tmp_path / "ball.ply")
    out = tmp_path / "grid.npz"
    status = main(["features", str(tmp_path / "ball.ply"), "--out", str(out), "--offline-features", "--views", "4",
                   "--resolution", "48", "--samples", "2", "--engine", "workbench", "--sheet", str(tmp_path / "s.png"),
                   "--slices", str(tmp_path / "g.png"), "--save-views", str(tmp_path / "v.npz")])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert "offline-random-vit-w32 (offline random ViT, not CLIP)" in captured.out
    assert "warning:" in captured.err and "open" in captured.err
    grid = FeatureGrid.load(out)
    assert grid.dim == 32 and grid.meta["engine"] == "workbench" and grid.meta["view_count"] == 4
    assert (tmp_path / "s.png").stat().st_size > 1000 and (tmp_path / "g.png").stat().st_size > 1000
    assert Views.load(tmp_path / "v.npz").count == 4
    assert "Saved:" not in captured.out                              # Blender's per-render chatter is hidden

    status = main(["features", str(tmp_path / "ball.ply"), "--out", str(tmp_path / "clip.npz")])
    assert status == 2 and "CLIP weights for ViT-B-16 not found" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("x")
    status = main(["features", str(tmp_path / "notes.txt"), "--out", str(out), "--offline-features"])
    assert status == 2 and "unsupported file type '.txt'" in capsys.readouterr().err
    status = main(["features", str(tmp_path / "ball.ply"), "--out", str(tmp_path / "grid.h5"), "--offline-features"])
    assert status == 2 and "….npz" in capsys.readouterr().err


@pytest.mark.blender
def test_panel_operators_leave_cached_files_and_properties(blender, tiny_checkpoint, monkeypatch):
    """The operators with a model trained on the offline features (the shipped model's render-pass features are
    tested through the pipeline: tests/test_bake_auto.py, tests/test_appearance_features.py)."""
    bpy = blender
    from pathlib import Path

    from unipixie.core.types import FeatureGrid
    from unipixie.unipixie_addon import preferences

    monkeypatch.setattr(preferences._Defaults, "checkpoint", str(tiny_checkpoint))

    bpy.ops.mesh.primitive_torus_add(major_radius=0.8, minor_radius=0.25)
    torus = bpy.context.active_object
    assert bpy.types.VIEW3D_PT_unipixie_features.bl_parent_id == "VIEW3D_PT_unipixie"
    assert bpy.ops.unipixie.render_views(view_count=4, resolution=48, engine="workbench") == {"FINISHED"}
    state = torus.unipixie_features
    assert state.view_count == 4 and Path(state.views_path).is_file() and Path(state.sheet_path).is_file()
    assert torus.unipixie.status == "4 views rendered"
    # a model trained on the offline features, no CLIP weights -> the offline extractor, named as such
    assert bpy.ops.unipixie.compute_features(view_count=4, resolution=48, engine="workbench") == {"FINISHED"}
    assert state.feature_model == "offline-random-vit-w32" and Path(state.slices_path).is_file()
    grid = FeatureGrid.load(state.grid_path)
    assert grid.occupancy.sum() == state.occupied_voxels > 1000
    assert grid.meta["views_file"] == Path(state.views_path).name          # reused the rendered views
    # no mesh selected: the operators are unavailable
    bpy.ops.object.select_all(action="DESELECT")
    bpy.context.view_layer.objects.active = None
    assert not bpy.ops.unipixie.compute_features.poll()


def test_benchmark_views_file_round_trips_and_is_checked(tmp_path):
    from unipixie.core.benchmarks import features as bench
    from unipixie.core.types import Views

    rng = np.random.default_rng(0)
    depth = np.where(rng.random((2, 16, 16)) > 0.5, 2.5, np.inf).astype(np.float32)
    views = Views(rng.random((2, 16, 16, 3)), depth, np.tile(np.eye(3), (2, 1, 1)), np.tile(np.eye(4), (2, 1, 1)),
                  meta={"engine": "cycles"})
    verts, faces = rng.random((10, 3)), rng.integers(0, 10, (6, 3))
    path = bench.save_bench_views(tmp_path / "bv.npz", views, verts, faces)
    again, v2, f2 = bench.load_bench_views(path)
    assert np.abs(again.images - views.images).max() <= 0.5 / 255 + 1e-6        # stored as uint8
    assert np.array_equal(again.depth, views.depth) and np.array_equal(f2, faces)
    assert np.allclose(v2, verts, atol=1e-6) and again.meta == {"engine": "cycles"}
    views.save(tmp_path / "plain.npz")
    with pytest.raises(UserError, match="not a views file of 'unipixie bench features"):
        bench.load_bench_views(tmp_path / "plain.npz")
