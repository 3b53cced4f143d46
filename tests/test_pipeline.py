"""The object pipeline without Blender: records, staleness, checkpoint and preference checks, the α sweep and
the model's material at α, the field display's geometry and colours, the demo's MPM budget."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from unipixie.core import pipeline as core
from unipixie.core.errors import UserError


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def blob_grid(tmp_path_factory):
    """A feature grid of an ellipsoid (~2.4k voxels) with deterministic offline-width features, saved to disk."""
    from unipixie.core import clip_features as cf
    from unipixie.core.normalise import unit_cube_grid
    from unipixie.core.types import FeatureGrid

    geo = unit_cube_grid()
    R = geo.resolution
    c = (np.stack(np.meshgrid(*[np.arange(R)] * 3, indexing="ij"), -1) + 0.5) / R - 0.5
    occ = (c[..., 0] / 0.2) ** 2 + (c[..., 1] / 0.12) ** 2 + (c[..., 2] / 0.1) ** 2 < 1
    feats = np.random.default_rng(0).normal(size=(int(occ.sum()), cf.OFFLINE_VISION_CFG["width"])).astype(np.float16)
    grid = FeatureGrid(geo, occ, feats, cf.OFFLINE_FEATURE_MODEL, meta={"normalisation": {"centre": [0, 0, 0], "scale": 1.0}})
    path = tmp_path_factory.mktemp("grid") / "grid.npz"
    grid.save(path)
    return path


def _settings(ckpt, **kw):
    return core.PipelineSettings(checkpoint=str(ckpt), sweep_count=3, steps=4, **kw)


def _run(job):
    from unipixie.core.jobs import run_job

    return run_job(job)


# --------------------------------------------------------------------------- record and states
def test_record_round_trip_and_foreign_values_mean_nothing_done():
    rec = core.PipelineRecord()
    rec.set("render", {"inputs": {"fingerprint": "a"}, "views": "/x.npz"})
    back = core.PipelineRecord.from_json(rec.to_json())
    assert back.steps == rec.steps
    for bad in ("", None, "not json", json.dumps({"format": "other/1", "steps": {}}), json.dumps([1, 2])):
        assert core.PipelineRecord.from_json(bad).steps == {}
    with pytest.raises(ValueError):
        rec.set("paint", {})


def _done_record(tmp_path, settings, fp="fp1"):
    files = {k: tmp_path / f"{k}.npz" for k in ("views", "grid", "sweep")}
    for f in files.values():
        f.write_bytes(b"x")
    rec = core.PipelineRecord()
    rec.set("render", {"inputs": settings.render_inputs(fp), "views": str(files["views"])})
    rec.set("features", {"inputs": settings.feature_inputs(fp), "grid": str(files["grid"])})
    rec.set("predict", {"inputs": settings.predict_inputs(files["grid"]), "sweep": str(files["sweep"])})
    return rec, files


def _bake_rec(**kw):
    d = {"format": "unipixie.bake/1", "solver": "mpm", "frames": [1, 48], "fps": 24.0, "alpha": 0.5,
         "material_source": {"source": "model"}, "effects": []}
    d.update(kw)
    return d


def test_states_done_stale_with_reasons_and_downstream(tmp_path, tiny_checkpoint):
    s = _settings(tiny_checkpoint)
    rec, files = _done_record(tmp_path, s)
    bake = _bake_rec()
    cur = core.CurrentInputs("fp1", s, bake_options=dict(bake), bake_record=bake)
    rec.set("bake", {"fingerprint": "fp1", "sweep": str(files["sweep"])})
    st = core.step_states(rec, cur)
    assert {k: v.state for k, v in st.items()} == {k: core.DONE for k in core.STEPS}

    # the mesh changed: render and features stale, prediction and the model-driven bake follow
    st = core.step_states(rec, core.CurrentInputs("fp2", s, bake_options=dict(bake), bake_record=bake))
    assert st["render"].state == st["features"].state == core.STALE
    assert "mesh" in st["features"].reason
    assert st["predict"].state == core.STALE and "features are stale" in st["predict"].reason
    assert st["bake"].state == core.STALE

    # α moved: only the bake is stale, and says why
    st = core.step_states(rec, core.CurrentInputs("fp1", s, bake_options=_bake_rec(alpha=0.7), bake_record=bake))
    assert [st[k].state for k in core.STEPS] == [core.DONE, core.DONE, core.DONE, core.STALE]
    assert st["bake"].reason == "α changed"
    # ... which does not matter for a homogeneous material
    homog = _bake_rec(material_source={"source": "homogeneous", "E": 1e5})
    st = core.step_states(rec, core.CurrentInputs("fp1", s, bake_options=dict(homog, alpha=0.9), bake_record=homog))
    assert st["bake"].state == core.DONE

    # other view count: render stale; other sweep size: predict stale; a running step shows as running
    st = core.step_states(rec, core.CurrentInputs("fp1", _settings(tiny_checkpoint, view_count=12), bake_record=bake))
    assert st["render"].state == core.STALE and "views" in st["render"].reason
    st = core.step_states(rec, core.CurrentInputs("fp1", core.PipelineSettings(checkpoint=str(tiny_checkpoint),
                                                                               sweep_count=5, steps=4)))
    assert st["predict"].state == core.STALE and "sweep" in st["predict"].reason
    assert st["bake"].state == core.NOT_DONE
    st = core.step_states(rec, core.CurrentInputs("fp1", s, running="predict"))
    assert st["predict"].state == core.RUNNING

    # a cached file removed from the cache: the step is not done (and says so)
    files["sweep"].unlink()
    st = core.step_states(rec, core.CurrentInputs("fp1", s))
    assert st["predict"].state == core.NOT_DONE and "no longer in the cache" in st["predict"].reason
    assert core.first_pending(st) == "predict"


def test_a_prediction_at_the_bakes_alpha_values_is_done_and_says_so(tmp_path, tiny_checkpoint):
    """The command line and the demo predict at the α values they bake: done for the panel (with a note), and a
    panel sweep is done for them; another seed still makes either stale."""
    explicit = _settings(tiny_checkpoint, alphas=(1.0, 0.5, 0.5))
    assert explicit.alphas == (0.5, 1.0) and list(explicit.resolved_alphas()) == [0.5, 1.0]
    with pytest.raises(UserError, match="α values must be numbers in"):
        _settings(tiny_checkpoint, alphas=(0.5, 1.5))
    panel = _settings(tiny_checkpoint)
    rec, _ = _done_record(tmp_path, explicit)
    assert rec.get("predict")["inputs"]["alphas"] == [0.5, 1.0] and "count" not in rec.get("predict")["inputs"]
    st = core.step_states(rec, core.CurrentInputs("fp1", panel))
    assert st["predict"].state == core.DONE and st["predict"].reason.startswith("at α 0.5, 1 only")
    swept, _ = _done_record(tmp_path, panel)
    st = core.step_states(swept, core.CurrentInputs("fp1", explicit))
    assert st["predict"].state == core.DONE and st["predict"].reason == ""
    st = core.step_states(rec, core.CurrentInputs("fp1", _settings(tiny_checkpoint, seed=3)))
    assert st["predict"].state == core.STALE and st["predict"].reason == "the seed changed"


def test_prediction_at_chosen_alphas_is_one_pass_cached_and_matches_the_sweep(tiny_checkpoint, blob_grid):
    s = _settings(tiny_checkpoint, alphas=(0.5,), heads=("mpm",))
    one, path, inputs = _run(core.predict_job(blob_grid, s))
    assert list(one.alphas) == [0.5] and inputs["alphas"] == [0.5] and path.is_file()
    sweep, _, _ = _run(core.predict_job(blob_grid, _settings(tiny_checkpoint, heads=("mpm",))))   # 0, 0.5, 1
    assert np.allclose(one.log10_E[0], sweep.log10_E[1], atol=1e-4)     # same noise: the same prediction at 0.5
    job = core.predict_job(blob_grid, s)
    statuses = []
    try:
        while True:
            statuses.append(next(job)[1])
    except StopIteration:
        pass
    assert statuses[-1] == "α 0.5 (mpm) from the cache"


# --------------------------------------------------------------------------- checkpoint and preference checks
def test_checkpoint_resolution_and_clear_messages(tmp_path, tiny_checkpoint, monkeypatch):
    assert core.resolve_checkpoint(tiny_checkpoint) == tiny_checkpoint
    assert core.resolve_checkpoint(tiny_checkpoint / "model.safetensors") == tiny_checkpoint
    monkeypatch.setattr(core.checkpoint, "default_checkpoint", lambda: tmp_path / "models" / "default")
    with pytest.raises(UserError, match="default model is not installed.*Model checkpoint"):
        core.resolve_checkpoint(None)
    with pytest.raises(UserError, match="does not exist"):
        core.resolve_checkpoint(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="not a UniPixie checkpoint"):
        core.resolve_checkpoint(tmp_path / "empty")
    assert core.checkpoint_feature_model(tiny_checkpoint) == ("offline-random-vit-w32", 32)


def test_check_settings_names_each_problem(tmp_path, tiny_checkpoint, monkeypatch):
    assert core.check_settings(checkpoint=str(tiny_checkpoint), cache_dir=str(tmp_path)) == []
    monkeypatch.setattr(core.checkpoint, "default_checkpoint", lambda: tmp_path / "models" / "default")
    monkeypatch.setattr(core.settings, "cuda_available", lambda: False)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    problems = core.check_settings(checkpoint="", clip_weights=str(tmp_path / "no_clip"), cache_dir=str(a_file),
                                   device="cuda", view_count=4)
    assert len(problems) == 5
    text = "\n".join(problems)
    assert "Model checkpoint: the default model is not installed" in text
    assert "CLIP weights:" in text and "no_clip" in text
    assert "Cache directory:" in text and "not a directory" in text
    assert "Device: CUDA is selected but no CUDA GPU" in text
    assert "Default views: 4 views" in text
    # CLIP weights set while the model was trained on the offline features: say which to clear
    weights = tmp_path / "clip.safetensors"
    weights.write_bytes(b"0")
    (msg,) = core.check_settings(checkpoint=str(tiny_checkpoint), clip_weights=str(weights))
    assert "trained on 'offline-random-vit-w32'" in msg and "clear 'CLIP weights'" in msg


# --------------------------------------------------------------------------- sweep and the material at α
def test_predict_sweep_refine_and_model_material(tmp_path, tiny_checkpoint, blob_grid):
    from unipixie.core.bake import BakeObject, ModelSource, plan_material
    from unipixie.core.model.inference import get_predictor
    from unipixie.core.types import FeatureGrid, MaterialField

    s = _settings(tiny_checkpoint)
    sweep, path, inputs = _run(core.predict_job(blob_grid, s))
    assert np.allclose(sweep.alphas, [0.0, 0.5, 1.0]) and path.is_file()
    assert inputs == s.predict_inputs(blob_grid)
    assert core.sweep_heads(sweep) == ("mpm", "lbs", "spring_mass")
    t = time.perf_counter()
    again, path2, _ = _run(core.predict_job(blob_grid, s))       # from the cache
    assert path2 == path and time.perf_counter() - t < 2.0 and np.array_equal(again.log10_E, sweep.log10_E)

    plan = core.ModelPlan(grid=str(blob_grid), sweep=str(path), checkpoint=str(tiny_checkpoint), steps=4)
    grid = FeatureGrid.load(blob_grid)
    predictor = get_predictor(tiny_checkpoint, device="cpu")
    # α on the sweep: its own values (exact: the same as a one-α prediction with the same seed)
    pred, how, _ = core.exact_prediction(plan, 0.5, ("mpm", "spring_mass"))
    direct = predictor.predict(grid, [0.5], heads=("mpm", "spring_mass"), seed=0, steps=4)
    assert how == "from the α sweep"
    np.testing.assert_allclose(pred.mpm[0].E, direct.mpm[0].E, rtol=1e-5)
    np.testing.assert_allclose(pred.spring_mass[0].stiffness, direct.spring_mass[0].stiffness, rtol=1e-5)
    # between sweep values: exact inference, then the cached file
    pred, how, refined = core.exact_prediction(plan, 0.37, ("mpm",))
    assert how == "exact inference" and refined.is_file()
    direct = predictor.predict(grid, [0.37], heads=("mpm", "lbs", "spring_mass"), seed=0, steps=4)
    np.testing.assert_allclose(pred.mpm[0].E, direct.mpm[0].E, rtol=1e-5)
    assert core.exact_prediction(plan, 0.37, ("mpm",))[1] == "refined"
    # an exact prediction follows its sweep's sampler: a sweep drawn at temperature 1 — or saved before temperatures
    # were recorded, when every sweep was a draw — gives draws at temperature 1 between its α values
    from unipixie.core.model.sweep import AlphaSweep, predict_sweep

    drawn = predict_sweep(predictor, grid, alphas=[0.0, 1.0], seed=0, steps=4, temperature=1.0, use_cache=False)
    old = AlphaSweep.load(drawn.save(tmp_path / "old_sweep.npz"))
    del old.meta["temperature"]
    for i, sw in enumerate((drawn, old)):
        sw_path = sw.save(tmp_path / f"sweep_t1_{i}.npz")
        p1 = core.ModelPlan(grid=str(blob_grid), sweep=str(sw_path), checkpoint=str(tiny_checkpoint), steps=4)
        pred1, how1, _ = core.exact_prediction(p1, 0.37, ("mpm",))
        want = predictor.predict(grid, [0.37], heads=("mpm", "lbs", "spring_mass"), seed=0, steps=4, temperature=1.0)
        assert how1 == "exact inference"
        np.testing.assert_allclose(pred1.mpm[0].E, want.mpm[0].E, rtol=1e-5)
        assert not np.allclose(pred1.mpm[0].E, direct.mpm[0].E, rtol=1e-3)   # not the default path's
    with pytest.raises(UserError, match="α must lie in"):                # checked where α comes in: the Refine
        _run(core.refine_job(plan, 1.5))

    # the bake's model material: world-space field on the object's bounding box, solver settings per head
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * [0.4, 0.24, 0.2]
    tris = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                     [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    obj = BakeObject("Blob", v, tris)
    with pytest.raises(UserError, match="run Predict"):
        plan_material(obj, 0.5, "mpm", None)                              # no prediction: no plan
    source = ModelSource(plan=plan)                                        # the bake's source carries its plan
    res = source.resolve(obj, 0.5, "mpm")
    assert isinstance(res.spec, MaterialField) and res.spec.meta["space"] == "world"
    assert res.spec.geometry.voxel_size == pytest.approx(0.4 / 64)
    assert "from the α sweep" in res.description
    assert source.resolve(obj, 0.5, "lbs").settings["skinning_params"].shape == (650,)
    assert "stiffness" not in source.resolve(obj, 1.0, "spring_mass").settings  # the continuum field
    heads = ModelSource(plan=plan, solver_heads=True).resolve(obj, 1.0, "spring_mass")
    assert heads.settings["stiffness"].shape == (64,)
    assert source.to_dict() == {"source": "model"}                          # the plan is run-time data only

    # the panel's refine keeps a file at its α even on a sweep value
    pred, how, p = _run(core.refine_job(plan, 0.5))
    assert how == "exact inference" and p.is_file() and pred.mpm is not None


def test_closing_a_background_job_cancels_its_worker():
    seen = []

    def work(progress):
        for i in range(400):
            time.sleep(0.005)
            progress.step(1, f"step {i}")
        seen.append("finished")

    job = core.jobs._background(work, "test")
    next(job)
    next(job)
    job.close()     # Esc: the worker is cancelled at its next step and joined
    assert seen == []
    time.sleep(0.05)
    assert seen == []


def test_predict_job_refuses_a_missing_model_before_working(tmp_path, blob_grid, monkeypatch):
    monkeypatch.setattr(core.checkpoint, "default_checkpoint", lambda: tmp_path / "models" / "default")
    with pytest.raises(UserError, match="default model is not installed"):
        next(core.predict_job(blob_grid, core.PipelineSettings()))


# --------------------------------------------------------------------------- the field display
def test_voxel_surface_of_boxes_and_orientation():
    from unipixie.core.types import GridGeometry

    geo = GridGeometry(8, np.zeros(3), 1.0)
    occ = np.zeros((8, 8, 8), bool)
    occ[2, 3, 4] = True
    v, q, fv = core.voxel_surface(geo, occ)
    assert v.shape == (8, 3) and q.shape == (6, 4) and np.all(fv == 0)
    occ[1:4, 1:3, 1:5] = True                  # a 3 × 2 × 4 box (plus the voxel above it)
    occ[2, 3, 4] = False
    v, q, fv = core.voxel_surface(geo, occ)
    assert len(q) == 2 * (3 * 2 + 3 * 4 + 2 * 4)
    assert len(v) == 4 * 3 * 5 - 2 * 1 * 3     # the box's lattice corners minus the interior ones
    centres = geo.centres(np.argwhere(occ))[fv]
    quad = v[q]
    normal = np.cross(quad[:, 1] - quad[:, 0], quad[:, 2] - quad[:, 0])
    assert np.all(np.einsum("ij,ij->i", normal, quad.mean(1) - centres) > 0)    # counter-clockwise from outside
    with pytest.raises(UserError):
        core.voxel_surface(geo, np.zeros((8, 8, 8), bool))


def test_colour_scale_is_monotone_and_labelled():
    scale = core.FieldColourScale(4.0, 7.0)
    lum = scale.lut_linear @ np.array([0.2126, 0.7152, 0.0722])
    assert np.all(np.diff(lum) > 0)                   # higher E, brighter colour
    ticks = scale.ticks(5)
    assert [t[0] for t in ticks] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert ticks[0][1] == pytest.approx(1e4) and ticks[-1][1] == pytest.approx(1e7)
    assert ticks[0][2] == "10 kPa" and ticks[-1][2] == "10 MPa"
    assert np.all(np.diff([t[1] for t in ticks]) > 0)
    np.testing.assert_allclose(scale.positions([3.0, 5.5, 9.0]), [0.0, 0.5, 1.0])
    c = scale.colours_linear([4.0, 7.0])
    assert c.shape == (2, 4) and c.dtype == np.float32 and np.all(c[:, 3] == 1)
    flat = core.FieldColourScale(5.0, 5.0)            # a uniform field still gets a usable scale
    assert flat.log10_max > flat.log10_min


# --------------------------------------------------------------------------- the demo's sizing
def test_mpm_grid_fits_the_budget():
    from unipixie.core.demo import mpm_cells_for_budget
    from unipixie.solvers.mpm import MPMSettings

    s = MPMSettings()
    n, cost = mpm_cells_for_budget(100.0, 1.0, 0.2, 25, 24.0, 5e7, (8, 32))
    assert 8 <= n <= 32 and cost <= 5e7
    dx = 1.0 / (n + 1)       # one cell finer would not fit
    finer = 24 * np.ceil(100.0 / 24.0 / (s.cfl * dx)) * 0.2 / dx ** 3 * s.particles_per_cell_axis ** 3
    assert n == 32 or finer > 5e7
    assert mpm_cells_for_budget(1e5, 1.0, 0.2, 25, 24.0, 1e3, (8, 32))[0] == 8      # never below the minimum


def test_wave_speed_ignores_held_and_empty_material():
    from unipixie.core.demo import max_wave_speed
    from unipixie.core.normalise import unit_cube_grid
    from unipixie.core.types import MaterialField
    from unipixie.solvers import materials

    occ = np.zeros((64,) * 3, bool)
    occ[:2, 0, 0] = True
    E, nu, rho = 2e6, 0.3, 800.0
    jelly, held = materials.get("jelly").id, materials.get("stationary").id
    f = MaterialField(unit_cube_grid(), occ, [E, 1e11], [nu, nu], [rho, rho], [jelly, held])
    expect = np.sqrt(E * (1 - nu) / ((1 + nu) * (1 - 2 * nu)) / rho)
    assert max_wave_speed(f) == pytest.approx(expect, rel=1e-6)


def test_jobs_side_by_side_share_the_cores_keep_order_and_errors(tmp_path):
    """core.features.run_side_by_side (the demo's bakes): at most N jobs started at once, each job's worker
    thread runs while the others are polled; results in order, an error in one job leaves the others going."""
    from unipixie.core.bake import BackgroundRun
    from unipixie.core.errors import CancelledError
    from unipixie.core.jobs import run_side_by_side
    from unipixie.core.progress import Progress

    def job(k, seconds=0.3, fail=False):
        run = BackgroundRun(lambda progress: (time.sleep(seconds), k)[1]).start()
        try:
            while not run.wait(0.01):
                yield 0.5, f"job {k}"
        finally:
            if not run.done:
                run.cancel(wait=True)
        if fail:
            raise UserError(f"job {k} failed")
        return run.result()

    done = []
    t0 = time.perf_counter()
    out = run_side_by_side([(lambda k=k: job(k, fail=k == 2), None) for k in range(4)], max_running=2,
                           on_done=lambda i, r: done.append(i))
    two = time.perf_counter() - t0
    assert out[:2] == [0, 1] and isinstance(out[2], UserError) and out[3] == 3 and sorted(done) == [0, 1, 2, 3]
    t0 = time.perf_counter()
    assert run_side_by_side([(lambda k=k: job(k), None) for k in range(4)], max_running=1) == [0, 1, 2, 3]
    one = time.perf_counter() - t0
    assert one >= 1.2 and two < 0.8 * one

    progress = Progress(show_bar=False)
    progress.cancel()
    with pytest.raises(CancelledError):
        run_side_by_side([(lambda: job(0), progress.sub(1.0, 1.0))], max_running=1)
