"""`unipixie demo --quick` end to end (what CI runs of README's main job) and the demo command's errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytestmark = pytest.mark.blender


def _picture(path):
    from PIL import Image

    img = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)
    assert img.std() > 10.0, f"{path} is (nearly) one colour"
    return img.shape


@pytest.mark.slow
def test_quick_demo_bakes_objects_that_move_and_alpha_matters(tmp_path, tiny_checkpoint, capsys):
    pytest.importorskip("bpy")
    from unipixie.core import demo
    from unipixie.cli import main

    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out), "--checkpoint", str(tiny_checkpoint)]) == 0
    printed = capsys.readouterr().out
    assert "Blender file:" in printed and str(out / demo.BLEND_NAME) in printed

    summary = json.loads((out / demo.SUMMARY_NAME).read_text())
    assert summary["plan"] == "quick" and summary["failed"] == []
    assert (out / demo.BLEND_NAME).stat().st_size > 100_000
    assert len(summary["objects"]) == 2 and all(p.endswith(".glb") for p in summary["objects"])
    h, w, _ = _picture(summary["contact_sheet"])
    assert (h, w) == (2 * (demo.QUICK.sheet_size[1] + 22), 2 * demo.QUICK.sheet_size[0])
    assert len(summary["field_pictures"]) == 3
    for p in summary["field_pictures"]:
        _picture(p)
    bakes = {b["object"]: b for b in summary["bakes"]}
    assert sorted(b["solver"] for b in bakes.values()) == ["lbs", "mpm", "mpm", "mpm", "spring_mass"]
    for b in bakes.values():
        assert b["max_displacement"] > demo.MOVE_THRESHOLD, f"{b['object']} did not move"
    # each bake says how its solver stepped (spring-mass: from its network's highest frequency)
    (spring,) = [b for b in bakes.values() if b["solver"] == "spring_mass"]
    assert spring["solver_steps"]["step_bound"] == "spectral" and spring["solver_steps"]["substeps"] > 0
    assert 0.0 < spring["solver_steps"]["substep_s"] < 1.0 / demo.QUICK.fps
    mpm = sorted((b for b in bakes.values() if b["solver"] == "mpm"), key=lambda b: b["alpha"])
    assert [b["alpha"] for b in mpm] == [0.0, 0.5, 1.0]
    assert "at α 0 " in mpm[0]["material"] and "at α 1 " in mpm[-1]["material"]
    assert summary["alpha_difference"] > 1e-5          # the α = 0 and α = 1 bakes differ
    # MPM and spring-mass bake the same material at the same α: their plants' motions are compared
    size = summary["solver_difference"] / summary["solver_difference_over_size"]
    assert 0.0 < summary["solver_difference"] < 0.25 * size, summary["solver_difference"]

    # the saved file: baked motion, and every object's pipeline found again
    import bpy

    from unipixie.core.blender_io import bake as bio
    from unipixie.core.blender_io import pipeline as pio

    from unipixie.core.pipeline import DONE, PipelineSettings

    bpy.ops.wm.open_mainfile(filepath=summary["blend"])
    settings = PipelineSettings(view_count=demo.QUICK.views, checkpoint=str(tiny_checkpoint))  # the panel's sweep
    with bio.registered_properties():
        for name, b in bakes.items():
            obj = bpy.data.objects[name]
            assert bio.bake_record(obj)["solver"] == b["solver"]
            rec = pio.read_record(obj)
            assert rec.file("features", "grid") is not None and rec.file("predict", "sweep") is not None
            states = pio.states(obj, settings)       # copies too: the fingerprint ignores placement and the bake
            assert all(st.state == DONE for st in states.values()), (name, states)
            moved = np.linalg.norm(bio.evaluated_positions(obj, demo.QUICK.frames) - bio.evaluated_positions(obj, 1),
                                   axis=1)
            assert moved.max() > demo.MOVE_THRESHOLD
    a0, a1 = (bpy.data.objects[b["object"]] for b in (mpm[0], mpm[-1]))
    d0 = bio.evaluated_positions(a0, demo.QUICK.frames) - bio.evaluated_positions(a0, 1)
    d1 = bio.evaluated_positions(a1, demo.QUICK.frames) - bio.evaluated_positions(a1, 1)
    assert np.abs(d0 - d1).max() > 1e-5

    # bench demo_plant refines the demo's pair from the saved file (coarse levels here): the same-α MPM plant's
    # scene, exported once, gives every run; the finest MPM level is the reference
    scene_file = tmp_path / "plant_scene.pkl"
    assert main(["bench", "demo_plant", "--blend", summary["blend"], "--checkpoint", str(tiny_checkpoint),
                 "--export", str(scene_file)]) == 0
    assert main(["bench", "demo_plant", "--scene", str(scene_file), "--cells", "5,4", "--anchors", "32",
                 "--out", str(tmp_path / "demo_plant.json")]) == 0
    rows = json.loads((tmp_path / "demo_plant.json").read_text())["results"]
    rms = {r["case"]: r["value"] for r in rows if r["metric"] == "displacement_rms_over_size"}
    assert sorted(rms) == ["demo plant α 0.5, MPM 4 cells across", "demo plant α 0.5, spring-mass 32 anchors"]
    assert all(0.0 < v < 1.0 for v in rms.values())
    assert {r["metric"] for r in rows} == {"displacement_rms_over_size", "crown_sway_hz", "crown_last_swing_m",
                                           "crown_lean_m"}
    bpy.ops.wm.read_factory_settings(use_empty=True)


def test_demo_command_errors_are_one_line(tmp_path, monkeypatch, capsys, tiny_checkpoint):
    from unipixie.core.pipeline import checkpoint as pipeline
    from unipixie.cli import main

    monkeypatch.setattr(pipeline, "default_checkpoint", lambda: tmp_path / "models" / "default")
    assert main(["demo", "--quick", "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "unipixie demo: error: the default model is not installed" in err and "--checkpoint" in err
    assert main(["demo", "--diagnose", "--quick"]) == 2
    assert "--quick and --checkpoint apply to the pipeline demo" in capsys.readouterr().err

    # a checkpoint trained on other features than the demo extracts is refused before any work
    from unipixie.core.model import UniPixieModel, preset, save_model

    other = save_model(UniPixieModel(preset("tiny", feature_model="ViT-B-16", feature_dim=16, patch_size=4,
                                            spring_anchors=8)), tmp_path / "clip_model")
    assert main(["demo", "--quick", "--out", str(tmp_path / "d"), "--checkpoint", str(other)]) == 2
    assert "trained on 'ViT-B-16'" in capsys.readouterr().err
    assert not (tmp_path / "d" / "objects").exists()


def test_demo_takes_a_model_of_any_weight_free_features(tmp_path):
    """The demo extracts what the model names: the render-pass appearance features need no weights either."""
    from unipixie.core import extractors
    from unipixie.core.demo import check_checkpoint
    from unipixie.core.model import UniPixieModel, preset, save_model

    for name, width in (("appearance", 8), ("offline", 32)):
        ckpt = save_model(UniPixieModel(preset("tiny", feature_model=extractors.feature_model(name), feature_dim=width,
                                               patch_size=4, spring_anchors=8)), tmp_path / name)
        assert check_checkpoint(ckpt) == ckpt
