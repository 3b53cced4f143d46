"""The appearance extractor (``appearance-gbuffer-v1``): render passes lifted at pixel accuracy, honest names,
refusals, and that nothing but what the renderer shows reaches it."""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("open_clip")

from unipixie.core import appearance_features as af  # noqa: E402
from unipixie.core import extractors  # noqa: E402
from unipixie.core.errors import UserError  # noqa: E402



# --------------------------------------------------------------------------- names, identities, refusals
def test_names_identities_and_labels_are_honest_and_distinct():
    from unipixie.core import clip_features as cf
    from unipixie.core.features import FeatureOptions, grid_cache_path
    from pathlib import Path

    assert extractors.feature_model("appearance") == af.APPEARANCE_FEATURE_MODEL == "appearance-gbuffer-v1"
    assert extractors.feature_model("appearance+vit") == "appearance-gbuffer-v1+offline-random-vit-w32"
    for name in ("offline", "appearance", "appearance+vit"):
        assert extractors.name_of(extractors.feature_model(name)) == name
        assert not extractors.needs_weights(extractors.feature_model(name))
        assert "not CLIP" in extractors.label(extractors.feature_model(name))
        assert "not CLIP" in extractors.description(extractors.feature_model(name))
    assert extractors.name_of("ViT-B-16") == "clip" and extractors.needs_weights("ViT-B-16")
    assert extractors.label("offline-random-vit-w32") == "offline-random-vit-w32 (offline random ViT, not CLIP)"
    # the cache keys of the three weight-free extractors differ (and from the offline ViT's)
    ids = [extractors.identity(n) for n in ("offline", "appearance", "appearance+vit")]
    assert ids[0] == cf.offline_identity() and ids[1]["appearance"]["version"] == af.APPEARANCE_VERSION
    keys = {grid_cache_path(Path("views.npz"), i).name for i in ids}
    assert len(keys) == 3
    options = FeatureOptions(extractor="appearance+vit")
    assert options.extractor_name == "appearance+vit" and options.needs_passes
    assert FeatureOptions(offline=True).extractor_name == "offline" and not FeatureOptions(offline=True).needs_passes
    ext = af.appearance_extractor(with_vit=True)
    assert ext.name == extractors.feature_model(options.extractor_name) and ext.dim == 8 + 32 and not ext.is_clip
    assert af.appearance_extractor().dim == len(af.CHANNELS) == 8


def test_bad_extractor_choices_are_one_clear_line(capsys):
    from unipixie.cli import main
    from unipixie.core.features import FeatureOptions

    for bad in (lambda: extractors.check_name("clip2"), lambda: FeatureOptions(extractor="bogus")):
        with pytest.raises(UserError) as err:
            bad()
        assert "unknown feature extractor" in str(err.value) and "\n" not in str(err.value)
        assert "appearance+vit" in str(err.value)
    with pytest.raises(UserError, match="Workbench does not render.*--engine cycles"):
        FeatureOptions(extractor="appearance", engine="workbench")
    with pytest.raises(UserError, match="choose one"):
        FeatureOptions(offline=True, extractor="appearance")
    with pytest.raises(SystemExit) as exit_:
        main(["features", __file__, "--out", "x.npz", "--extractor", "bogus"])
    status = exit_.value.code
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "invalid choice: 'bogus'" in err[0]
    from unipixie.training.dataset import BuildSettings

    with pytest.raises(UserError, match="--engine cycles"):
        BuildSettings(extractor="appearance")              # the dataset's default engine is Workbench
    s = BuildSettings(extractor="appearance", engine="cycles")
    assert s.extractor_name == "appearance" and BuildSettings().extractor_name == "offline"


# --------------------------------------------------------------------------- channels and lifting (no Blender)
def _synthetic_views(V=2, H=8, W=8):
    from unipixie.core.types import Views

    depth = np.full((V, H, W), 2.0, np.float32)
    depth[:, :, :2] = np.inf                                   # background columns
    base = np.zeros((V, H, W, 3), np.float32)
    base[..., 0] = 1.0
    passes = {"base_color": base, "roughness": np.full((V, H, W), 0.25, np.float32),
              "metallic": np.ones((V, H, W), np.float32), "normal": np.tile([0.0, 0.0, 1.0], (V, H, W, 1))}
    for p in passes.values():
        p[:, :, :2] = np.nan
    return Views(np.zeros((V, H, W, 3)), depth, np.tile(np.eye(3), (V, 1, 1)), np.tile(np.eye(4), (V, 1, 1)),
                 passes=passes)


def test_channels_are_standardised_by_fixed_scales_and_background_is_filled(tmp_path):
    from unipixie.core.types import Views

    views = _synthetic_views()
    ch = af.standardised_channels(views)
    assert ch.shape == (2, 8, 8, 8) and np.all(np.isfinite(ch))
    expected = (np.array([1, 0, 0, 0.25, 1, 0, 0, 1], np.float32) - af.CHANNEL_CENTRE) / af.CHANNEL_SCALE
    assert np.allclose(ch[0, 3, 0], expected, atol=1e-6)      # a background pixel takes its neighbour's value
    assert np.allclose(ch, expected, atol=1e-6)
    assert np.allclose(af.CHANNEL_SCALE[:5], np.sqrt(1 / 12)) and np.allclose(af.CHANNEL_SCALE[5:], np.sqrt(1 / 3))
    # passes round-trip through the views file (float16)
    back = Views.load(views.save(tmp_path / "v.npz"))
    assert set(back.passes) == set(views.passes) and back.passes["roughness"].shape == (2, 8, 8, 1)
    assert np.allclose(back.passes["base_color"][:, :, 2:], views.passes["base_color"][:, :, 2:])
    with pytest.raises(UserError, match="render passes .*missing"):
        af.standardised_channels(Views(views.images, views.depth, views.intrinsics, views.cam_to_world))
    with pytest.raises(UserError, match="not from images alone"):
        af.appearance_extractor()(views.images)


def test_several_maps_are_lifted_each_at_its_resolution_and_concatenated():
    from unipixie.core.lift import camera_rig, lift_features
    from unipixie.core.types import Views

    occ = np.zeros((64, 64, 64), bool)
    occ[16:48, 16:48, 16:48] = True
    c2w, K, distance, _, _ = camera_rig(4, 0.87, 32, 40.0)
    # every voxel within ±0.5 of the origin along the view axis passes a depth test of ±64 voxels at the centre
    views = Views(np.zeros((4, 32, 32, 3)), np.full((4, 32, 32), distance), K, c2w)
    rng = np.random.default_rng(0)
    full = rng.random((4, 32, 32, 3)).astype(np.float32)
    tokens = rng.random((4, 2, 2, 5)).astype(np.float32)
    both = lift_features(views, [full, tokens], occ, depth_tolerance_voxels=64)
    a = lift_features(views, full, occ, depth_tolerance_voxels=64)
    b = lift_features(views, tokens, occ, depth_tolerance_voxels=64)
    assert both.features.shape[1] == 8
    assert np.array_equal(both.features, np.concatenate([a.features, b.features], axis=1))


def test_the_extractor_code_path_loads_no_labels_or_generator():
    """Hard rule: features are made from what the renderer shows.  Computing appearance(+ViT) features from views
    imports nothing of the procedural generator, its annotations or the training code."""
    code = """
import sys, numpy as np
from unipixie.core import extractors
from unipixie.core.features import features_from_views
sys.path.insert(0, %r)
from test_appearance_features import _synthetic_views
occ = np.zeros((64, 64, 64), bool); occ[20:44, 20:44, 20:44] = True
views = _synthetic_views()
for name in ("appearance", "appearance+vit"):
    extractors.make(name)
    extractors.feature_maps(extractors.make(name), views)
bad = sorted(m for m in sys.modules if m.startswith(("unipixie.core.procedural", "unipixie.core.annotation",
                                                     "unipixie.training")))
print("LOADED", bad)
"""
    import os

    here = os.path.dirname(os.path.abspath(__file__))
    out = subprocess.run([sys.executable, "-c", code % here], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "LOADED []" in out.stdout, out.stdout
    # and none of the modules on the path imports them
    from pathlib import Path

    root = Path(af.__file__).resolve().parent
    for mod in ("appearance_features.py", "extractors.py", "lift.py", "features.py", "blender_io/render_passes.py",
                "blender_io/render.py"):
        for line in (root / mod).read_text().splitlines():
            m = re.match(r"\s*(?:from\s+(\S+)\s+)?import\s+(.+)", line)
            if m is None:
                continue
            names = re.split(r"[.\s,()]+", f"{m.group(1) or ''} {m.group(2)}")
            assert not {"procedural", "annotation", "training"} & set(names), (mod, line)


# --------------------------------------------------------------------------- through Blender
@pytest.mark.blender
def test_two_materials_are_recovered_per_side_with_a_sharp_boundary(blender):
    bpy = blender
    from unipixie.core.blender_io.render_passes import SPLIT_BOX_LOOKS, split_box
    from unipixie.core.blender_io.scene_import import snapshot_ids
    from unipixie.core.features import FeatureOptions, compute_features
    from unipixie.training.feature_probe import transition_width

    obj = split_box(bpy.context.scene)       # built by hand: no generator, no labels
    (_, red, red_rough, red_metal), (_, blue, blue_rough, blue_metal) = SPLIT_BOX_LOOKS
    assert red == (0.8, 0.05, 0.05) and (red_rough, red_metal, blue_rough, blue_metal) == (0.9, 0.0, 0.2, 1.0)
    nodes_before = [len(m.node_tree.nodes) for m in bpy.data.materials]
    before = snapshot_ids()
    fast = dict(view_count=6, resolution=128, samples=2, use_cache=False)
    grids = {name: compute_features(obj, FeatureOptions(extractor=name, **fast)).grid
             for name in ("appearance", "offline", "appearance+vit")}
    assert snapshot_ids() == before                               # the material copies are gone
    assert [len(m.node_tree.nodes) for m in bpy.data.materials] == nodes_before   # the user's materials untouched

    g = grids["appearance"]
    assert g.feature_model == "appearance-gbuffer-v1" and g.dim == 8 and g.meta["is_clip"] is False
    raw = g.features.astype(np.float32) * af.CHANNEL_SCALE + af.CHANNEL_CENTRE
    idx = g.indices
    for side, (_, colour, roughness, metallic) in zip((idx[:, 0] <= 29, idx[:, 0] >= 34), SPLIT_BOX_LOOKS):
        want = np.array([*colour, roughness, metallic], np.float32)
        err = np.abs(raw[side, :5] - want)
        assert np.all(err.mean(axis=0) < 0.01), err.mean(axis=0)           # mean per channel
        assert np.all(np.percentile(err, 95, axis=0) < 0.03), np.percentile(err, 95, axis=0)
    # normals in the normalised cube's frame: the end faces point along ∓x
    ends = {0: -1.0, 63: 1.0}
    for i, sign in ends.items():
        n = raw[(idx[:, 0] == i) & (idx[:, 1] > 20) & (idx[:, 1] < 44) & (idx[:, 2] > 20) & (idx[:, 2] < 44), 5:]
        assert np.allclose(np.median(n, axis=0), (sign, 0.0, 0.0), atol=0.05)
    # the boundary at x = 0 lies between voxels 31 and 32: its 10-90 % width in voxels
    widths = {name: transition_width(gr.indices, gr.features.astype(np.float32), gr.occupancy, axis=0)
              for name, gr in grids.items()}
    assert widths["appearance"] <= 1.5, widths
    assert widths["offline"] > 3.0 * widths["appearance"], widths   # 16-px patches smear it over many voxels
    assert np.allclose(grids["appearance+vit"].features[:, :8], g.features, atol=2e-3)
    assert grids["appearance+vit"].dim == 40
