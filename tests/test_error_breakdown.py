"""training/error_breakdown.py: the scoring-only voxel facts and where the log E error lies (no Blender, no model)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from unipixie.core.errors import UserError
from unipixie.training import error_breakdown as eb
from unipixie.training import evaluate as ev

ALPHAS = np.array([0.0, 0.5, 1.0])


# --------------------------------------------------------------------------- the distance to a part boundary
def test_distance_on_a_two_part_bar_and_a_single_part_object():
    # a bar of 7 voxels along x, away from the grid's origin: part 0 at x = 4..6, part 1 at x = 7..10
    idx = np.array([[4 + i, 2, 3] for i in range(7)])
    parts = np.array([0, 0, 0, 1, 1, 1, 1])
    d = eb.part_boundary_distance(parts, idx)
    assert d.dtype == np.float32 and d.tolist() == [3, 2, 1, 1, 2, 3, 4]
    assert np.all(np.isinf(eb.part_boundary_distance(np.zeros(7, int), idx)))   # one part: no boundary
    with pytest.raises(UserError, match="6 part labels for 7"):
        eb.part_boundary_distance(parts[:6], idx)


def test_distance_is_euclidean_to_the_nearest_voxel_of_another_part():
    rng = np.random.default_rng(3)
    occ = rng.uniform(size=(7, 6, 5)) < 0.6
    idx = np.argwhere(occ)
    parts = (idx[:, 0] + idx[:, 1] >= 6).astype(int) + 2 * (rng.uniform(size=len(idx)) < 0.05)   # three parts
    d = eb.part_boundary_distance(parts, idx + 11)
    pair = np.linalg.norm(idx[:, None, :] - idx[None, :, :], axis=2)
    pair[parts[:, None] == parts[None, :]] = np.inf
    assert np.allclose(d, pair.min(axis=1), rtol=0, atol=1e-6)
    assert np.isclose(d.min(), 1.0) and np.any(np.isclose(d, np.sqrt(2)))       # diagonal neighbours: √2


def test_distance_bins():
    labels = eb.distance_bin_labels(np.array([1.0, np.sqrt(2), 3.0, 3.01, 7.0, 7.5, np.inf]))
    assert labels.tolist() == ["<=1", "(1,3]", "(1,3]", "(3,7]", "(3,7]", ">7", "single_part"]


# --------------------------------------------------------------------------- the facts stored with the targets
class _Dataset:
    def __init__(self, part_ids=None):
        self.part_ids = part_ids

    def annotation(self, oid):
        return SimpleNamespace(semantic_class="rubber_duck")

    def part_labels(self, oid):
        if self.part_ids is None:
            raise UserError(f"part labels of {oid!r} missing")
        return self.part_ids, ["body", "head"]


def test_scoring_facts_of_an_object_with_and_without_part_labels(tmp_path):
    occ = np.zeros((5, 5, 5), bool)
    occ[1:4, 1:4, 1:4] = True                       # 27 voxels, one interior
    grid = SimpleNamespace(occupancy=occ, indices=np.argwhere(occ))
    parts = (np.argwhere(occ)[:, 0] == 3).astype(np.int64)      # the top layer is another part
    facts = eb.scoring_facts(_Dataset(parts), "x", grid)
    assert set(facts) == {"surface", "semantic_class", "part_boundary_distance"}
    assert facts["surface"].shape == (27,) and int((~facts["surface"]).sum()) == 1
    assert str(facts["semantic_class"]) == "rubber_duck"
    assert sorted(set(facts["part_boundary_distance"].tolist())) == [1.0, 2.0]
    # written beside the targets and read back without pickle
    ev._save_npz(tmp_path / "t.npz", **facts)
    with np.load(tmp_path / "t.npz", allow_pickle=False) as z:
        assert str(z["semantic_class"]) == "rubber_duck"
    bare = eb.scoring_facts(_Dataset(None), "x", grid)
    assert "part_boundary_distance" not in bare and "surface" in bare
    assert "part labels of 'x' missing" in str(bare[eb.NOTE_KEY])


# --------------------------------------------------------------------------- the breakdown
def _targets(K, **facts):
    return {"E_min": np.full(K, 1e4), "E_max": np.full(K, 1e6), "nu_min": np.full(K, 0.3), "nu_max": np.full(K, 0.3),
            "density_min": np.full(K, 1e3), "density_max": np.full(K, 1e3), "material": np.zeros(K, np.int16), **facts}


def _prediction(errors):
    """A prediction whose log10 E misses the target 4 + 2 α by ``errors`` (A, K) or (K,) (the same at every α)."""
    errors = np.broadcast_to(np.asarray(errors, np.float64), (len(ALPHAS), np.shape(errors)[-1]))
    K = errors.shape[1]
    return {"alphas": ALPHAS, "log10_E": (4.0 + 2.0 * ALPHAS[:, None] + errors).astype(np.float32),
            "log10_density": np.full((3, K), 3.0, np.float32), "nu": np.full((3, K), 0.3, np.float32),
            "material": np.zeros((3, K), np.int16), "runtime_s": np.float64(0.1)}


A_SURFACE = np.array([1, 1, 1, 1, 1, 1, 0, 0, 0, 0], bool)
A_DISTANCE = np.array([1, 1, 2, 2, 4, 8, 1, 2.5, 5, 9], np.float32)


def _write(root, predictions: dict, b_facts=True):
    """Object a (chair, 10 voxels, 2 parts; 4 interior) and b (duck, 5 voxels, one part, all surface)."""
    ev._save_npz(root / "targets" / "a.npz", **_targets(10, surface=A_SURFACE, part_boundary_distance=A_DISTANCE,
                                                         semantic_class=np.array("chair")))
    facts = dict(surface=np.ones(5, bool), part_boundary_distance=np.full(5, np.inf, np.float32),
                 semantic_class=np.array("duck")) if b_facts else {}
    ev._save_npz(root / "targets" / "b.npz", **_targets(5, **facts))
    for method, (ea, eb_) in predictions.items():
        ev._save_npz(root / method / "a.npz", **_prediction(ea))
        ev._save_npz(root / method / "b.npz", **_prediction(eb_))


def test_breakdown_numbers_of_known_errors(tmp_path):
    root = tmp_path / "predictions"
    _write(root, {
        "interior": (np.where(A_SURFACE, 0.0, 1.0), np.zeros(5)),                  # error 1 on a's interior only
        "duck": (np.zeros(10), np.array([[2.0] * 5, [0.0] * 5, [0.0] * 5])),      # b only, at α = 0: 4/3 per voxel
        "everywhere": (np.ones(10), np.ones(5)),                                  # error 1 on every voxel
    })
    b = eb.error_breakdown(root)
    assert b["format"] == eb.BREAKDOWN_FORMAT and set(b["methods"]) == {"interior", "duck", "everywhere"}
    m = b["methods"]["interior"]
    assert m["objects"] == 2 and m["voxels"] == 15 and m["not_available"] == {}
    assert m["all"]["logE_mse_pooled"] == pytest.approx(4 / 15)
    assert m["all"]["logE_mse_object_mean"] == pytest.approx(0.2)                 # (4/10 + 0) / 2
    kind = m["by_voxel_kind"]
    assert (kind["surface"]["voxels"], kind["interior"]["voxels"]) == (11, 4)
    assert kind["surface"]["logE_mse_pooled"] == 0.0 and kind["interior"]["logE_mse_pooled"] == pytest.approx(1.0)
    assert m["interior_share_pooled"] == pytest.approx(1.0) and m["interior_share_object_weighted"] == pytest.approx(1.0)
    assert kind["interior"]["objects"] == 1 and kind["surface"]["objects"] == 2
    dist = m["by_boundary_distance"]
    assert [dist[k]["voxels"] for k in ("<=1", "(1,3]", "(3,7]", ">7", "single_part")] == [3, 3, 2, 2, 5]
    assert [dist[k]["logE_mse_pooled"] for k in ("<=1", "(1,3]", "(3,7]", ">7", "single_part")] == \
        pytest.approx([1 / 3, 1 / 3, 0.5, 0.5, 0.0])
    assert [dist[k]["share_pooled"] for k in ("<=1", "(1,3]", "(3,7]", ">7")] == pytest.approx([0.25] * 4)
    assert m["by_class"]["chair"]["logE_mse_pooled"] == pytest.approx(0.4) and m["by_class"]["duck"]["share_pooled"] == 0

    d = b["methods"]["duck"]                                                       # the α average: (4 + 0 + 0) / 3
    assert d["by_boundary_distance"]["single_part"]["logE_mse_pooled"] == pytest.approx(4 / 3)
    assert d["by_boundary_distance"]["single_part"]["share_pooled"] == pytest.approx(1.0)
    assert d["by_boundary_distance"]["<=1"]["share_pooled"] == 0.0 and d["interior_share_pooled"] == 0.0
    assert d["by_class"]["duck"]["share_object_weighted"] == pytest.approx(1.0)

    e = b["methods"]["everywhere"]                                                 # pooled vs object-weighted shares
    assert e["by_class"]["chair"]["share_pooled"] == pytest.approx(10 / 15)
    assert e["by_class"]["chair"]["share_object_weighted"] == pytest.approx(0.5)
    assert e["interior_share_pooled"] == pytest.approx(4 / 15)
    assert e["interior_share_object_weighted"] == pytest.approx((4 / 10) / 2)
    assert e["by_voxel_kind"]["interior"]["logE_mse_object_mean"] == pytest.approx(1.0)

    # the per-object mean over all voxels is Table 1's number
    t1 = ev.table1(root)
    for name, mm in b["methods"].items():
        assert mm["all"]["logE_mse_object_mean"] == pytest.approx(t1[name]["logE_mse"], rel=1e-6), name


def test_old_targets_without_the_facts_still_score(tmp_path):
    root = tmp_path / "predictions"
    _write(root, {"m": (np.ones(10), np.zeros(5))}, b_facts=False)                # b: targets of an older evaluation
    m = eb.error_breakdown(root)["methods"]["m"]
    assert m["objects"] == 2 and m["all"]["logE_mse_object_mean"] == pytest.approx(0.5)
    assert set(m["not_available"]) == set(eb.GROUPS)
    assert m["not_available"]["by_voxel_kind"].startswith("partial: 1 of 2 objects") and "b:" in \
        m["not_available"]["by_voxel_kind"]
    assert m["by_voxel_kind"]["interior"]["voxels"] == 4 and set(m["by_class"]) == {"chair"}

    old = tmp_path / "old"                                                         # no object has the facts
    for oid, K in (("a", 10), ("b", 5)):
        ev._save_npz(old / "targets" / f"{oid}.npz", **_targets(K))
        ev._save_npz(old / "m" / f"{oid}.npz", **_prediction(np.ones(K)))
    ev._save_npz(old / "targets" / "a.npz", **_targets(10, scoring_note=np.array("no part labels (missing)")))
    m = eb.error_breakdown(old)["methods"]["m"]
    assert m["by_voxel_kind"] == {} and m["by_boundary_distance"] == {} and m["interior_share_pooled"] is None
    assert m["not_available"]["by_class"].startswith("not available: 2 of 2")
    assert "a: no part labels (missing)" in m["not_available"]["by_boundary_distance"]
    assert m["all"]["logE_mse_pooled"] == pytest.approx(1.0)
    from unipixie.training.evaluation_report import breakdown_markdown

    text = "\n".join(breakdown_markdown(eb.error_breakdown(old)))
    assert "| m | 1.000 | – | – |" in text and "not available" in text


def test_damaged_or_missing_inputs_are_one_clear_error(tmp_path):
    with pytest.raises(UserError, match="no targets"):
        eb.error_breakdown(tmp_path)
    root = tmp_path / "predictions"
    _write(root, {"m": (np.ones(10), np.zeros(5))})
    ev._save_npz(root / "targets" / "b.npz", **_targets(5, surface=np.ones(4, bool)))
    with pytest.raises(UserError, match=r"surface has shape \(4,\), expected \(5,\)"):
        eb.error_breakdown(root)
    (root / "targets" / "b.npz").unlink()
    with pytest.raises(UserError, match="have no targets"):
        eb.error_breakdown(root)


def _report(root) -> dict:
    t1 = ev.table1(root / "predictions")
    return {"split": "test", "dataset": "d", "objects": 2, "checkpoint": None, "alphas": ALPHAS.tolist(),
            "table1": t1, "in_range": {k: v.get("in_range", {}) for k, v in t1.items()}, "table2": [],
            "references": {}}


def test_recompute_an_evaluation_dir(tmp_path, capsys):
    out = tmp_path / "eval"
    _write(out / "predictions", {"m": (np.where(A_SURFACE, 0.0, 1.0), np.zeros(5))})
    # no report yet: breakdown.json
    assert eb.main([str(out)]) == 0
    assert json.loads((out / "breakdown.json").read_text())["methods"]["m"]["voxels"] == 15
    assert "| m | 0.267 | 0.000 (0 %) | 1.000 (100 %) |" in capsys.readouterr().out
    from unipixie.training.evaluation_report import write_report

    write_report(out, _report(out))
    assert "Where the log E error lies" not in (out / "report.md").read_text()
    assert eb.main([str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["breakdown"]["methods"]["m"]["interior_share_pooled"] == pytest.approx(1.0)
    md = (out / "report.md").read_text()
    assert "## Where the log E error lies" in md and "| m | 0.267 | 0.000 (0 %) | 1.000 (100 %) |" in md
    assert "| voxels | 15 | 11 | 4 | 3 | 3 | 2 | 2 | 5 |" in md
    assert "| chair | 10 | 0.400 (100 %) |" in md and "| duck | 5 | 0.000 (0 %) |" in md
    assert eb.main([str(tmp_path / "nope")]) == 2
    assert "evaluation directory not found" in capsys.readouterr().err
    (out / "report.json").write_text("{}")
    assert eb.main([str(out)]) == 2 and "not an evaluation report" in capsys.readouterr().err


def test_an_older_evaluation_gets_its_facts_from_the_dataset(tmp_path, capsys, monkeypatch):
    occ = np.zeros((5, 5, 5), bool)
    occ[1:4, 1:4, 1:4] = True
    grid = SimpleNamespace(occupancy=occ, indices=np.argwhere(occ))
    ds = _Dataset((np.argwhere(occ)[:, 0] == 3).astype(np.int64))
    ds.sample = lambda oid: SimpleNamespace(grid=grid)
    root = tmp_path / "eval" / "predictions"
    ev._save_npz(root / "targets" / "x.npz", **_targets(27))                    # written before the facts existed
    ev._save_npz(root / "m" / "x.npz", **_prediction(np.where(np.argwhere(occ)[:, 0] == 2, 1.0, 0.0)))
    assert eb.error_breakdown(root)["methods"]["m"]["by_class"] == {}
    assert eb.add_missing_facts(root, ds) == 1 and eb.add_missing_facts(root, ds) == 0
    m = eb.error_breakdown(root)["methods"]["m"]
    assert m["not_available"] == {} and set(m["by_class"]) == {"rubber_duck"}
    assert m["by_boundary_distance"]["<=1"]["share_pooled"] == pytest.approx(1.0)   # the layer next to the top part
    assert m["interior_share_pooled"] == pytest.approx(1 / 9)                    # 1 of the 9 erring voxels is interior
    ev._save_npz(root / "targets" / "x.npz", **_targets(26))
    with pytest.raises(UserError, match="not the dataset this evaluation ran on"):
        eb.add_missing_facts(root, ds)
    assert eb.main([str(tmp_path / "eval"), "--data", str(tmp_path / "no_dataset")]) == 2
    assert "error_breakdown: error:" in capsys.readouterr().err
    # the command: the old targets get their facts from the dataset given
    from unipixie.training import dataset as D

    ev._save_npz(root / "targets" / "x.npz", **_targets(27))
    monkeypatch.setattr(D, "DatasetDir", lambda path: ds)
    assert eb.main([str(tmp_path / "eval"), "--data", "the_dataset"]) == 0
    assert json.loads((tmp_path / "eval" / "breakdown.json").read_text())["methods"]["m"]["not_available"] == {}


# --------------------------------------------------------------------------- Table 2 by semantic class
def test_table2_by_class_averages_objects_and_compares_heads_with_fits():
    from unipixie.training.evaluation_report import table2_by_class_markdown

    def row(oid, cls, solver, method, alpha, rel):
        return {"object_id": oid, "semantic_class": cls, "solver": solver, "method": method, "alpha": alpha,
                "relative_rmse": rel}

    rows = [row("a", "sand_pile", "lbs", "test_time_fit", 0.0, 0.30), row("a", "sand_pile", "lbs", "test_time_fit", 1.0, 0.10),
            row("b", "sand_pile", "lbs", "test_time_fit", 0.0, 0.40), row("b", "sand_pile", "lbs", "test_time_fit", 1.0, 0.40),
            row("c", "fruit", "lbs", "test_time_fit", 0.0, 0.02), row("c", "fruit", "lbs", "unipixie", 0.0, 0.06),
            row("a", "sand_pile", "lbs", "unipixie", 0.0, 0.30), row("b", "sand_pile", "lbs", "unipixie", 0.0, 0.30),
            row("c", "fruit", "mpm", "unipixie", 0.0, None)]               # a failed simulation is left out
    out = {(x["semantic_class"], x["solver"], x["method"]): x for x in ev.table2_by_class(rows)}
    sand = out[("sand_pile", "lbs", "test_time_fit")]
    # each object's mean over α first (a: 0.2, b: 0.4), then the mean over objects
    assert sand["objects"] == 2 and sand["relative_rmse"] == pytest.approx(0.3)
    assert sand["worst_object"] == "b" and sand["worst_relative_rmse"] == pytest.approx(0.4)
    assert ("fruit", "mpm", "unipixie") not in out
    md = "\n".join(table2_by_class_markdown(ev.table2_by_class(rows), {"unipixie": "unipixie"}))
    assert "| sand_pile | 2 | 0.300 | 0.300 |" in md and "| fruit | 1 | 0.020 | 0.060 |" in md
    # object-weighted over the classes that have both: (2 × 0.30 + 0.06) / (2 × 0.30 + 0.02)
    assert f"lbs: the learned head's error is {(0.66 / 0.62):.2f}× the test-time fit's" in md
