"""`unipixie bake --alpha` from scratch: the missing pipeline steps run first (render views, features, the
prediction at the bakes' α values), each printed with its time, cached for the next run; ``--no-auto`` computes
nothing; manifests and shards take the same path."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

pytestmark = pytest.mark.blender

STEP_LINE = re.compile(r"^  (Render views|Features|Predict): (.+) \((\d+\.\d) s\)$", re.M)


def _fresh_block_scene(bpy, path):
    """A .blend with one mesh object 'Block' and nothing of UniPixie in it (a new user's file)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 0.0, 1.0))
    block = bpy.context.active_object
    block.name = "Block"
    block.scale = (0.6, 0.2, 0.2)
    bpy.ops.object.transform_apply(scale=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(path))


def _steps(printed: str) -> dict:
    return {m.group(1): (m.group(2), float(m.group(3))) for m in STEP_LINE.finditer(printed)}


@pytest.mark.slow
def test_readme_bake_line_works_on_a_fresh_blend_and_reuses_the_cache(blender, tmp_path, capsys):
    """README's line with the shipped model on a .blend with nothing precomputed (the MPM grid kept coarse,
    8 cells across, so that the test stays short on a CPU)."""
    bpy = blender
    from unipixie import cli
    from unipixie.core.blender_io import bake as bio
    from unipixie.core.blender_io import pipeline as pio
    from unipixie.core.pipeline import DONE, PipelineSettings

    scene = tmp_path / "scene.blend"
    _fresh_block_scene(bpy, scene)
    line = ["bake", str(scene), "--object", "Block", "--solver", "mpm", "--alpha", "0.5", "--frames", "1-12",
            "--out", str(tmp_path / "out.blend"), "--settings", json.dumps({"cells_across": 8})]
    assert cli.main(line) == 0
    printed = capsys.readouterr().out
    steps = _steps(printed)
    assert list(steps) == ["Render views", "Features", "Predict"], printed
    assert steps["Render views"][0].startswith("8 views (cycles, 224 px)")           # the shipped model's recipe
    assert "appearance-gbuffer-v1" in steps["Features"][0] and steps["Predict"][0].startswith("α 0.5 (mpm)")
    assert not any("from the cache" in text for text, _ in steps.values())
    assert "baked 'Block' with mpm (model at α 0.5 (from the α sweep" in printed

    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "out.blend"))
    with bio.registered_properties():
        block = bpy.data.objects["Block"]
        rec = bio.bake_record(block)
        assert rec["solver"] == "mpm" and rec["frames"] == [1, 12] and rec["alpha"] == 0.5
        assert rec["material_source"] == {"source": "model"}
        states = pio.states(block, PipelineSettings().with_model_recipe())   # the panel's view of the saved file
        assert all(states[k].state == DONE for k in ("render", "features", "predict")), states
        assert "at α 0.5 only" in states["predict"].reason
        moved = np.linalg.norm(bio.evaluated_positions(block, 12) - bio.evaluated_positions(block, 1), axis=1)
        assert moved.max() > 1e-3

    # the same line again: every step comes from the cache
    assert cli.main(line[:-4] + ["--out", str(tmp_path / "again.blend")] + line[-2:]) == 0
    again = _steps(capsys.readouterr().out)
    assert list(again) == ["Render views", "Features", "Predict"]
    assert all(text.endswith("from the cache") for text, _ in again.values()), again

    # --no-auto: nothing is computed; the prediction recorded in the baked file is used, a fresh file is refused
    assert cli.main(["bake", str(tmp_path / "out.blend"), "--object", "Block", "--alpha", "0.5", "--no-auto",
                     "--frames", "1-3", "--settings", json.dumps({"cells_across": 8}),
                     "--out", str(tmp_path / "rebaked.blend")]) == 0
    assert "Render views, Features, Predict: done (recorded in the scene)" in capsys.readouterr().out
    assert cli.main(["bake", str(scene), "--object", "Block", "--alpha", "0.5", "--no-auto",
                     "--out", str(tmp_path / "strict.blend")]) == 2
    err = capsys.readouterr().err
    assert "has no current prediction to bake with at α" in err and "--features GRID.npz" in err
    assert not (tmp_path / "strict.blend").exists()


def test_manifest_and_shards_compute_what_each_shard_lacks(blender, tmp_path, capsys):
    """A manifest with the model material and no feature files, split in two shards: each shard renders,
    extracts and predicts what its own jobs need; the second finds the views and features in the cache."""
    bpy = blender
    from unipixie.core import bake, cli
    from unipixie.core.blender_io import bake as bio
    from unipixie.core.demo import untrained_checkpoint
    from unipixie.core.model.checkpoint import write_feature_recipe

    ckpt = untrained_checkpoint(tmp_path / "tiny", "tiny", spring_anchors=16)
    write_feature_recipe(ckpt, {"engine": "workbench", "view_count": 4, "resolution": 96, "samples": 1})
    scene = tmp_path / "scene.blend"
    _fresh_block_scene(bpy, scene)
    manifest = {"format": bake.MANIFEST_FORMAT,
                "defaults": {"solver": "mpm", "settings": {"cells_across": 6}, "frames": "1-3"},
                "jobs": [{"scene": "scene.blend", "object": "Block", "alpha": [0, 1], "out": "out/block_{alpha}.blend",
                          "material": {"source": "model", "checkpoint": str(ckpt)}}]}
    (tmp_path / "jobs.json").write_text(json.dumps(manifest))

    assert cli.main(["bake", "--manifest", str(tmp_path / "jobs.json"), "--shard", "0/2"]) == 0
    first = capsys.readouterr().out
    assert "model material of 'Block' (α 0):" in first
    steps = _steps(first)
    assert steps["Render views"][0].startswith("4 views (workbench, 96 px)") and steps["Predict"][0].startswith("α 0 (mpm)")
    assert cli.main(["bake", "--manifest", str(tmp_path / "jobs.json"), "--shard", "1/2"]) == 0
    second = _steps(capsys.readouterr().out)
    assert second["Render views"][0].endswith("from the cache") and second["Features"][0].endswith("from the cache")
    assert second["Predict"][0] == "α 1 (mpm)"                 # a new α: predicted now
    for a in ("0", "1"):
        bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "out" / f"block_{a}.blend"))
        assert bio.bake_record(bpy.data.objects["Block"])["alpha"] == float(a)

    # α with a homogeneous material in a manifest: refused, naming the job and the rule
    manifest["jobs"][0]["material"] = {"E": 2e5}
    (tmp_path / "jobs.json").write_text(json.dumps(manifest))
    assert cli.main(["bake", "--manifest", str(tmp_path / "jobs.json")]) == 2
    assert "jobs[0]: 'alpha' with a homogeneous 'material'" in capsys.readouterr().err
