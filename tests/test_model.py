"""The model: patch layout, masking of unoccupied voxels, prediction shapes and determinism,
checkpoints (round trip, mismatch errors), bad input, the α-sweep cache and the predict command."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch

from unipixie.core.errors import UserError
from unipixie.core.model.checkpoint import load_model, save_model
from unipixie.core.model.config import ModelConfig, preset
from unipixie.core.model.inference import Prediction, Predictor
from unipixie.core.model.layout import PatchLayout, VoxelBatch
from unipixie.core.model.network import UniPixieModel
from unipixie.core.model.sweep import AlphaSweep, predict_sweep
from unipixie.core.types import FeatureGrid, GridGeometry, MaterialField
from unipixie.solvers.materials import NUM_CLASSES, names
from unipixie.solvers.skinning import LBS_PARAM_COUNT

pytestmark = pytest.mark.usefixtures("one_torch_thread")

R, D, ANCHORS = 8, 12, 10


def _config(**kw):
    return preset("tiny", feature_model="test-features", feature_dim=D, grid_resolution=R, spring_anchors=ANCHORS, **kw)


def _model(seed=0, **kw):
    torch.manual_seed(seed)
    m = UniPixieModel(_config(**kw))
    with torch.no_grad():  # AdaLN-Zero starts every block at the identity; give all weights values
        for p in m.parameters():
            if p.dim() >= 2 and torch.count_nonzero(p) == 0:
                p.normal_(0.0, 0.05)
    return m.eval()


def _occupancy(seed=0, R=R):
    rng = np.random.default_rng(seed)
    occ = rng.random((R, R, R)) < 0.35
    occ[R // 2, R // 2, R // 2] = True
    return occ


def _grid(seed=0, feature_model="test-features", dim=D):
    occ = _occupancy(seed)
    feats = np.random.default_rng(seed + 1).normal(size=(occ.sum(), dim)).astype(np.float16)
    return FeatureGrid(GridGeometry(R, [-0.5] * 3, 1.0 / R), occ, feats, feature_model=feature_model)


# ---------------------------------------------------------------------------- shapes and masking
@pytest.mark.parametrize("P", [1, 2, 4])
def test_patch_layout_round_trip(P):
    occs = [_occupancy(0), _occupancy(1)]
    batch = VoxelBatch.from_grids(occs, [np.zeros((o.sum(), 1)) for o in occs])
    lay = PatchLayout(batch.voxels, 2, R, P)
    vals = torch.randn(batch.voxels.shape[0], 3)
    tok = lay.to_tokens(vals)
    assert tok.shape == (2, lay.tokens, P ** 3, 3)
    assert torch.equal(lay.from_tokens(tok), vals)
    assert int(lay.slot_mask.sum()) == batch.voxels.shape[0]
    for b, occ in enumerate(occs):  # one valid token per occupied patch; centres inside the unit cube
        G = R // P
        n_patches = int(occ.reshape(G, P, G, P, G, P).any(axis=(1, 3, 5)).sum())
        assert int(lay.token_valid[b].sum()) == n_patches
        assert not lay.slot_mask[b][~lay.token_valid[b]].any()
    assert float(lay.centres.min()) >= 0.0 and float(lay.centres.max()) <= 1.0


def test_encoder_ignores_features_outside_the_occupancy():
    m = _model()
    occ = torch.from_numpy(np.stack([_occupancy(0), _occupancy(3)]))
    dense = torch.randn(2, D, R, R, R)
    z1, proj1 = m.encoder.encode_dense(dense, occ)
    garbage = dense.clone()
    garbage.permute(1, 0, 2, 3, 4)[:, ~occ] = torch.randn(D, int((~occ).sum())) * 1e4  # every unoccupied voxel
    z2, proj2 = m.encoder.encode_dense(garbage, occ)
    assert torch.equal(z1, z2) and torch.equal(proj1, proj2)
    changed = dense.clone()
    i, j, k = np.argwhere(occ[0].numpy())[0]
    changed[0, :, i, j, k] += 3.0  # one occupied voxel does change the latents
    z3, _ = m.encoder.encode_dense(changed, occ)
    assert not torch.allclose(z1[0], z3[0]) and torch.allclose(z1[1], z3[1], atol=1e-6)
    # the dense stem input is zero outside the occupancy
    batch = VoxelBatch(torch.nonzero(occ), torch.randn(int(occ.sum()), D), 2, R)
    with torch.no_grad():
        stem = m.encoder.dense_stem_input(batch, m.encoder.project_voxels(batch.features))
    assert float(stem.permute(1, 0, 2, 3, 4)[:, ~occ].abs().max()) == 0.0


def test_decoder_ignores_noisy_targets_at_unoccupied_slots_and_padding():
    m = _model(patch_size=2)
    occs = [_occupancy(0), _occupancy(5)]
    rng = np.random.default_rng(0)
    feats = [rng.normal(size=(o.sum(), D)) for o in occs]
    with torch.no_grad():
        enc = m.encode(VoxelBatch.from_grids(occs, feats))
        ctx = m.grid_context(m.mpm, enc)
        lay = enc.layout
        x = torch.randn(2, lay.tokens, lay.slots, 3)
        t, a = torch.tensor([0.3, 0.6]), torch.tensor([0.2, 0.9])
        out = m.mpm(x, t, a, ctx)
        x2 = x.clone()
        x2[~lay.slot_mask] = torch.randn(int((~lay.slot_mask).sum()), 3) * 100.0  # unoccupied slots + padding
        out2 = m.mpm(x2, t, a, ctx)
        assert torch.equal(out, out2)
        assert float(out[~lay.slot_mask].abs().max()) == 0.0  # outputs masked
        assert out.shape == (2, lay.tokens, lay.slots, 3 + NUM_CLASSES)
        # object 0 alone gives the same voxels as object 0 inside a padded batch of two
        enc0 = m.encode(VoxelBatch.from_grids(occs[:1], feats[:1]))
        ctx0 = m.grid_context(m.mpm, enc0)
        n0 = int(enc0.layout.token_valid.sum())
        out0 = m.mpm(x[:1, :n0], t[:1], a[:1], ctx0)
        v_batch = lay.from_tokens(out)[: int(occs[0].sum())]
        assert torch.allclose(enc0.layout.from_tokens(out0), v_batch, atol=1e-5)


def test_prediction_shapes_determinism_and_shared_noise():
    """Draws from the model (temperature 1): deterministic for a seed, another seed another draw, one noise for
    every α of a request."""
    p = Predictor(_model())
    g = _grid()
    K = int(g.occupancy.sum())
    pred = p.predict(g, [0.0, 0.5, 1.0], seed=3, steps=4, temperature=1.0)
    assert len(pred.mpm) == len(pred.lbs) == len(pred.spring_mass) == 3
    for i, m in enumerate(pred.mpm):
        assert isinstance(m, MaterialField) and m.E.shape == (K,) and m.alpha == [0.0, 0.5, 1.0][i]
        assert np.all((m.material >= 0) & (m.material < NUM_CLASSES))
    assert pred.lbs[0].params.shape == (LBS_PARAM_COUNT,) and pred.lbs[0].E.shape == (K,)
    assert pred.spring_mass[2].stiffness.shape == (ANCHORS,) and np.isfinite(pred.spring_mass[2].softness)
    again = p.predict(g, [0.0, 0.5, 1.0], seed=3, steps=4, temperature=1.0)
    assert np.array_equal(again.mpm[1].E, pred.mpm[1].E) and np.array_equal(again.spring_mass[0].stiffness,
                                                                             pred.spring_mass[0].stiffness)
    other = p.predict(g, [0.5], seed=4, steps=4, heads="mpm", temperature=1.0)
    assert not np.allclose(other.mpm[0].E, pred.mpm[1].E)
    # one α alone == the same α inside the batch (shared noise)
    single = p.predict(g, [0.5], seed=3, steps=4, temperature=1.0)
    assert np.allclose(np.log10(single.mpm[0].E), np.log10(pred.mpm[1].E), atol=1e-4)
    assert np.allclose(single.spring_mass[0].stiffness, pred.spring_mass[1].stiffness, rtol=1e-4)
    only = p.predict(g, [0.5], seed=3, steps=4, heads=("lbs",))
    assert only.mpm is None and only.spring_mass is None and only.lbs is not None


def test_averaged_samples_are_the_mean_of_the_draws_in_log_units():
    """``samples`` = K: the average, in the network's normalised units (log10 E, log10 ρ, ν, the spring stiffness'
    log), of the K one-draw predictions with seeds seed … seed + K − 1; K = 1 is the one-draw prediction itself."""
    p = Predictor(_model())
    g = _grid()
    draws = [p.predict(g, [0.0, 1.0], seed=3 + j, steps=3, temperature=1.0) for j in range(3)]
    one = p.predict(g, [0.0, 1.0], seed=3, steps=3, samples=1, temperature=1.0)
    assert np.array_equal(one.mpm[1].E, draws[0].mpm[1].E) and one.meta["samples"] == 1
    avg = p.predict(g, [0.0, 1.0], seed=3, steps=3, samples=3, temperature=1.0)
    assert avg.meta["samples"] == 3
    for i in range(2):
        logE = np.mean([np.log10(d.mpm[i].E) for d in draws], axis=0)
        assert np.allclose(np.log10(avg.mpm[i].E), logE, atol=2e-4)
        assert np.allclose(avg.mpm[i].nu, np.mean([d.mpm[i].nu for d in draws], axis=0), atol=1e-4)
        assert np.allclose(np.log10(avg.lbs[i].E), np.mean([np.log10(d.lbs[i].E) for d in draws], axis=0), atol=2e-4)
        k = np.mean([np.log10(d.spring_mass[i].stiffness) for d in draws], axis=0)
        assert np.allclose(np.log10(avg.spring_mass[i].stiffness), k, atol=2e-4)
    spread = np.std([np.log10(d.mpm[1].E) for d in draws], axis=0)
    assert spread.max() > 1e-3                     # the draws differ, so the average is not any one of them
    for bad in (0, -1, 2.5, True, 10 ** 6):
        with pytest.raises(UserError, match="samples"):
            p.predict(g, [0.5], samples=bad, temperature=1.0)


def test_temperature_scales_the_starting_noise_and_zero_is_one_deterministic_path():
    """x(0) = τ·ε for the per-voxel heads: at τ = 0 every seed gives the same MPM and LBS fields, the flow
    integrated from the noise's mean (a zero start); at τ = 1 seeds differ; in between the start is the scaled draw.  The spring
    head draws whatever τ is.  τ is recorded, checked, and averaging draws at τ = 0 is refused."""
    from unipixie.core.model import inference

    p = Predictor(_model())
    g = _grid()
    zero = [p.predict(g, [0.0, 1.0], seed=s, steps=3, temperature=0.0) for s in (3, 4)]
    for head in ("mpm", "lbs"):
        assert np.array_equal(getattr(zero[0], head)[1].E, getattr(zero[1], head)[1].E)
    assert zero[0].meta["temperature"] == 0.0
    # the spring head always draws (SPRING_TEMPERATURE): seeds differ, and τ does not change it
    assert inference.SPRING_TEMPERATURE == 1.0
    assert not np.allclose(zero[0].spring_mass[1].stiffness, zero[1].spring_mass[1].stiffness, rtol=1e-3)
    drawn = p.predict(g, [0.0, 1.0], seed=3, steps=3, temperature=1.0)
    assert np.array_equal(zero[0].spring_mass[1].stiffness, drawn.spring_mass[1].stiffness)
    assert inference.DEFAULT_TEMPERATURE == 0.0                       # the product's sampler (models/default card)
    default = p.predict(g, [0.0, 1.0], seed=9, steps=3)
    assert np.array_equal(default.mpm[1].E, zero[0].mpm[1].E)
    ones = [p.predict(g, [1.0], seed=s, steps=3, temperature=1.0, heads="mpm") for s in (3, 4)]
    assert not np.allclose(np.log10(ones[0].mpm[0].E), np.log10(ones[1].mpm[0].E), atol=1e-3)
    # τ = ½ is the τ = 1 draw's noise halved: the same as scaling the generator's noise by hand
    half = p.predict(g, [1.0], seed=3, steps=3, temperature=0.5, heads="mpm")
    orig = Predictor._noise
    try:
        Predictor._noise = lambda self, seed, head, shape: orig(self, seed, head, shape) * 0.5
        by_hand = p.predict(g, [1.0], seed=3, steps=3, temperature=1.0, heads="mpm")
    finally:
        Predictor._noise = orig
    assert np.allclose(np.log10(half.mpm[0].E), np.log10(by_hand.mpm[0].E), atol=1e-5)
    assert not np.allclose(np.log10(half.mpm[0].E), np.log10(ones[0].mpm[0].E), atol=1e-3)
    for bad in (-0.1, 1.5, float("nan"), "hot", True):
        with pytest.raises(UserError, match="temperature"):
            p.predict(g, [0.5], temperature=bad)
    with pytest.raises(UserError, match="temperature > 0"):
        p.predict(g, [0.5], samples=2, temperature=0.0)


def test_bf16_autocast_path_matches_fp32():
    """The GPU precision path (bf16 autocast, float32 ODE state), run on the CPU."""
    m = _model(patch_size=2)
    g = _grid()
    a = Predictor(m, precision="fp32").predict(g, [0.0, 1.0], steps=3)
    b = Predictor(m, precision="bf16").predict(g, [0.0, 1.0], steps=3)
    assert np.abs(np.log10(a.mpm[1].E) - np.log10(b.mpm[1].E)).max() < 0.1
    assert np.abs(a.spring_mass[0].stiffness / b.spring_mass[0].stiffness - 1).max() < 0.5


def test_config_uses_the_shared_contracts():
    cfg = ModelConfig()
    assert cfg.num_classes == NUM_CLASSES and list(cfg.class_names) == names()
    assert cfg.lbs_param_count == LBS_PARAM_COUNT == 650
    assert cfg.spring_dim == cfg.spring_anchors + 1
    with pytest.raises(UserError, match="patch_size"):
        ModelConfig(grid_resolution=64, patch_size=6)
    with pytest.raises(UserError, match="unknown field"):
        ModelConfig.from_dict({"width": 64, "colour": "red"})


# ---------------------------------------------------------------------------- checkpoints and bad input
def test_checkpoint_round_trip_without_pickle(tmp_path):
    m = _model(seed=1)
    save_model(m, tmp_path / "ck", info={"step": 7})
    assert sorted(f.name for f in (tmp_path / "ck").iterdir()) == ["config.json", "model.safetensors"]
    raw = (tmp_path / "ck" / "model.safetensors").read_bytes()
    header_len = int.from_bytes(raw[:8], "little")
    assert raw[8:9] == b"{" and json.loads(raw[8:8 + header_len])["__metadata__"]["format"] == "unipixie.model_weights/1"
    loaded, info = load_model(tmp_path / "ck")
    assert info["step"] == 7
    g = _grid()
    a = Predictor(m).predict(g, [0.3], steps=3)
    b = Predictor.load(tmp_path / "ck", device="cpu").predict(g, [0.3], steps=3)
    assert np.array_equal(a.mpm[0].E, b.mpm[0].E) and np.array_equal(a.lbs[0].params, b.lbs[0].params)


def test_mismatched_checkpoints_and_inputs_are_refused(tmp_path):
    m = _model()
    ck = tmp_path / "ck"
    save_model(m, ck)
    p = Predictor.load(ck, device="cpu")
    with pytest.raises(UserError, match=r"'other-extractor'.*'test-features'"):
        p.predict(_grid(feature_model="other-extractor"), [0.5])
    with pytest.raises(UserError, match="7 feature channels.*expects 12"):
        p.predict(_grid(dim=7), [0.5])
    bad = _grid()
    bad.features[3, 2] = np.nan
    with pytest.raises(UserError, match="NaN"):
        p.predict(bad, [0.5])
    with pytest.raises(UserError, match="alpha"):
        p.predict(_grid(), [1.5])
    with pytest.raises(UserError, match="another model config: width"):
        load_model(ck, expect=_config(width=32))
    doc = json.loads((ck / "config.json").read_text())  # config.json of another architecture
    doc["config"]["width"] = 32
    (ck / "config.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match="config.json does not describe model.safetensors.*width"):
        load_model(ck)
    other = tmp_path / "other"  # weights of another architecture (3 MPM blocks) under this config (2 blocks)
    save_model(_model(mpm_blocks=3), other)
    _config().save(other / "config.json")
    (other / "model.safetensors").write_bytes(_strip_metadata(other / "model.safetensors"))
    with pytest.raises(UserError, match="unexpected weights.*mpm.blocks.2"):
        load_model(other)
    with pytest.raises(UserError, match="not a UniPixie checkpoint"):
        Predictor.load(tmp_path / "nowhere", device="cpu")
    with pytest.raises(UserError, match="do not match the registry"):  # classes in another order
        Predictor(UniPixieModel(_config(class_names=tuple(reversed(names())))))


def _strip_metadata(path):
    """The same weights with only the format in the metadata (as an older writer would leave them)."""
    from safetensors.torch import load_file, save_file

    tensors = load_file(str(path))
    tmp = path.with_name("stripped.safetensors")
    save_file(tensors, str(tmp), metadata={"format": "unipixie.model_weights/1"})
    return tmp.read_bytes()


# ---------------------------------------------------------------------------- the α slider
def _field(occ, logE, alpha, cls=0):
    K = int(occ.sum())
    return MaterialField(GridGeometry(occ.shape[0], [0, 0, 0], 0.01), occ, np.full(K, 10.0 ** logE),
                         np.full(K, 0.3), np.full(K, 1000.0 * (1 + alpha)), np.full(K, cls), alpha)


def test_alpha_sweep_interpolates_in_log_space_and_is_fast(tmp_path):
    occ = np.zeros((R, R, R), bool)
    occ[1:7, 1:7, 1:6] = True
    alphas = np.linspace(0, 1, 11)
    pred = Prediction(alphas=alphas, mpm=[_field(occ, 3.0 + 4.0 * a, a, cls=0 if a < 0.5 else 1) for a in alphas])
    grid = FeatureGrid(GridGeometry(R, [0, 0, 0], 0.01), occ, np.zeros((occ.sum(), 2)))
    sweep = AlphaSweep.from_prediction(pred, grid)
    f = sweep.field_at(0.25)  # halfway between 0.2 and 0.3: log10 E = 4.0, geometric mean of E
    assert np.allclose(np.log10(f.E), 4.0, atol=1e-5)
    assert np.allclose(f.density, 1000.0 * np.sqrt(1.2 * 1.3), rtol=1e-4)  # log-space interpolation of ρ
    assert np.allclose(sweep.field_at(0.3).E, 10.0 ** 4.2, rtol=1e-5)
    assert sweep.field_at(0.44).material[0] == 0 and sweep.field_at(0.46).material[0] == 1  # nearer cached α
    loaded = AlphaSweep.load(sweep.save(tmp_path / "s.npz"))
    assert np.array_equal(loaded.log10_E, sweep.log10_E) and np.array_equal(loaded.occupancy, occ)
    with pytest.raises(UserError, match="alpha"):
        sweep.field_at(1.2)
    # 30k voxels, 11 cached α: moving the slider takes well under 50 ms
    R2 = 40
    big = np.zeros((R2, R2, R2), bool)
    big.reshape(-1)[:30000] = True
    pred = Prediction(alphas=alphas, mpm=[_field(big, 3.0 + 4.0 * a, a) for a in alphas])
    sweep = AlphaSweep.from_prediction(pred, FeatureGrid(GridGeometry(R2, [0, 0, 0], 0.01), big, np.zeros((30000, 1))))
    times = []
    for a in np.linspace(0.01, 0.99, 9):
        t0 = time.perf_counter()
        sweep.field_at(a)
        times.append(time.perf_counter() - t0)
    assert float(np.median(times)) < 0.05, times


def test_predict_sweep_is_cached_and_refine_matches_exact(tmp_path):
    m = _model()
    save_model(m, tmp_path / "ck")
    p = Predictor.load(tmp_path / "ck", device="cpu")
    g = _grid()
    calls = []
    original = p.predict
    p.predict = lambda *a, **k: calls.append(1) or original(*a, **k)
    s1 = predict_sweep(p, g, count=5, seed=2, steps=3)
    s2 = predict_sweep(p, g, count=5, seed=2, steps=3)
    assert len(calls) == 1 and np.array_equal(s1.log10_E, s2.log10_E)
    s3 = predict_sweep(p, g, count=5, seed=2, steps=3, samples=2, temperature=1.0)  # another estimate: not cached
    assert len(calls) == 2 and not np.array_equal(s3.log10_E, s1.log10_E)
    s4 = predict_sweep(p, g, count=5, seed=2, steps=3, temperature=1.0)  # a draw, not the deterministic path
    assert len(calls) == 3 and not np.array_equal(s4.log10_E, s1.log10_E)
    assert s1.meta["temperature"] == 0.0 and s4.meta["temperature"] == 1.0
    exact = s1.refine(p, g, 0.5, heads=("mpm",))  # 0.5 is a cached α: refine reproduces it
    assert np.allclose(np.log10(exact.mpm[0].E), s1.log10_E[2], atol=1e-4)
    drawn = s4.refine(p, g, 0.5, heads=("mpm",))  # with the sweep's own temperature
    assert np.allclose(np.log10(drawn.mpm[0].E), s4.log10_E[2], atol=1e-4)
    assert s1.spring_at(0.6).stiffness.shape == (ANCHORS,) and s1.lbs_at(0.6).params.shape == (LBS_PARAM_COUNT,)


def test_predict_command(tmp_path):
    from unipixie.cli import main

    save_model(_model(), tmp_path / "ck")
    gpath = _grid().save(tmp_path / "grid.npz")
    out = tmp_path / "pred"
    assert main(["predict", str(gpath), "--checkpoint", str(tmp_path / "ck"), "--alphas", "0,1", "--steps", "2",
                 "--device", "cpu", "--out", str(out)]) == 0
    summary = json.loads((out / "prediction.json").read_text())
    assert [e["alpha"] for e in summary["alphas"]] == [0.0, 1.0]
    avg = tmp_path / "avg"
    assert main(["predict", str(gpath), "--checkpoint", str(tmp_path / "ck"), "--alpha", "1", "--steps", "2",
                 "--samples", "2", "--device", "cpu", "--out", str(avg)]) == 0
    assert json.loads((avg / "prediction.json").read_text())["samples"] == 2
    assert json.loads((avg / "prediction.json").read_text())["temperature"] == 1.0  # K draws: draws from the model
    assert json.loads((out / "prediction.json").read_text())["temperature"] == 0.0  # the default path
    for bad in (["--temperature", "2"], ["--samples", "2", "--temperature", "0"]):  # a clear error, exit 2
        assert main(["predict", str(gpath), "--checkpoint", str(tmp_path / "ck"), "--alpha", "1", "--steps", "2",
                     "--device", "cpu", "--out", str(tmp_path / "bad")] + bad) == 2
    one_draw = MaterialField.load(out / "material_field_a1.000.npz")
    assert not np.array_equal(MaterialField.load(avg / "material_field_a1.000.npz").E, one_draw.E)
    field = MaterialField.load(out / "material_field_a1.000.npz")
    assert field.E.shape == (int(_grid().occupancy.sum()),)
    assert (out / "spring_a0.000.npz").is_file() and (out / "lbs_a0.000.npz").is_file()
    _grid(feature_model="other").save(tmp_path / "other.npz")
    assert main(["predict", str(tmp_path / "other.npz"), "--checkpoint", str(tmp_path / "ck"), "--out", str(out),
                 "--device", "cpu"]) == 2


def test_local_context_sees_its_receptive_field_and_reaches_the_decoders():
    """With ``local_context_layers`` the decoders' per-voxel local features gain the context channels; a
    voxel's context changes with a voxel inside its receptive field (1 + 2·(2^L − 1) voxels per side) and
    not with one outside it; the old behaviour (0 layers) is unchanged in shape."""
    Rl = 16
    cfg = dict(grid_resolution=Rl, local_context_layers=2, local_context_channels=5)
    torch.manual_seed(0)
    m = UniPixieModel(preset("tiny", feature_model="test-features", feature_dim=D, spring_anchors=ANCHORS, **cfg)).eval()
    assert m.cfg.local_channels == m.cfg.voxel_channels + 5
    occ = np.ones((Rl, Rl, Rl), bool)
    feats = np.random.default_rng(0).normal(size=(occ.sum(), D))
    batch = VoxelBatch.from_grids([occ], [feats])
    with torch.no_grad():
        _, local = m.encoder(batch)
    assert local.shape == (Rl ** 3, m.cfg.local_channels)
    # receptive field of 2 layers (dilations 1, 2): 1 + 2·3 = 7 voxels, i.e. ±3 voxels per axis
    centre = (8, 8, 8)
    row = lambda ijk: int(np.ravel_multi_index(ijk, occ.shape))  # noqa: E731  (C order = argwhere order)
    for offset, should_change in ((3, True), (4, False)):
        changed = feats.copy()
        changed[row((8 + offset, 8, 8))] += 5.0 * np.arange(D)  # not a constant: LayerNorm removes those
        with torch.no_grad():
            _, local2 = m.encoder(VoxelBatch.from_grids([occ], [changed]))
        ctx_delta = float((local2[row(centre), m.cfg.voxel_channels:] - local[row(centre), m.cfg.voxel_channels:]).abs().max())
        assert (ctx_delta > 1e-6) == should_change, (offset, ctx_delta)
    with pytest.raises(UserError, match="local_context_layers needs local_features"):
        preset("tiny", local_context_layers=2, local_features=False)
    with pytest.raises(UserError, match="local_context_layers must be an integer"):
        preset("tiny", local_context_layers=-1)
    # and the full model runs with it (decoder local projection sized for the extra channels)
    with torch.no_grad():
        pred = Predictor(m).predict(FeatureGrid(GridGeometry(Rl, [-0.5] * 3, 1.0 / Rl), occ, feats.astype(np.float16),
                                                feature_model="test-features"), alphas=[0.0, 1.0], steps=2)
    assert np.all(np.isfinite(pred.mpm[0].E))


def test_flow_times_are_the_training_quantiles_and_the_sampler_uses_them():
    """The sampler's step times are the quantiles of the logit-normal training distribution of t: 0 and 1
    at the ends, increasing, each step holding 1/steps of the training draws; the network is evaluated at
    exactly those times (the last step is Euler for data prediction), never above the last quantile."""
    from statistics import NormalDist

    from unipixie.core.model.inference import flow_times
    from unipixie.core.model.objective import SamplingSettings

    ts = flow_times(15)
    assert ts[0] == 0.0 and ts[-1] == 1.0 and np.all(np.diff(ts) > 0) and len(ts) == 16
    d = SamplingSettings()
    logit = np.log(ts[1:-1] / (1 - ts[1:-1]))
    shares = np.diff([0.0] + [NormalDist(d.t_mean, d.t_std).cdf(x) for x in logit] + [1.0])
    assert np.allclose(shares, 1 / 15)
    assert 0.59 < ts[-2] < 0.61  # the default N(-0.8, 0.8): last time before 1 is 0.60
    assert flow_times(1).tolist() == [0.0, 1.0]
    assert flow_times(4, 0.0, 1.0)[2] == pytest.approx(0.5)  # the median of a centred logit-normal
    with pytest.raises(UserError, match="steps must be >= 1"):
        flow_times(0)
    with pytest.raises(UserError, match="positive spread"):
        flow_times(4, 0.0, 0.0)
    # the predictor asks the network at exactly these times
    m = _model()
    seen = []
    original = m.mpm.forward

    def spy(x, t, alpha, ctx):
        seen.append(float(t[0]))
        return original(x, t, alpha, ctx)

    m.mpm.forward = spy
    p = Predictor(m, sampling={"t_mean": 0.3, "t_std": 1.2})
    p.predict(_grid(), [0.2, 0.7], heads=("mpm",), steps=4)
    want = flow_times(4, 0.3, 1.2)
    heun_times = [want[0], want[1], want[1], want[2], want[2], want[3], want[3]]  # last step Euler: no t = 1
    assert seen == pytest.approx(heun_times)
    assert p.sampler_id != Predictor(m).sampler_id  # cache keys tell the two samplers apart
