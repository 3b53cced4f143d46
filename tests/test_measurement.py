"""Measurement files (unipixie.measurement/1): validation naming the key, NaN occlusions, CSV, round trips;
comparison metrics and the noise estimate against known answers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from unipixie.core import measurement as meas
from unipixie.core.diagnosis import compare as cmp
from unipixie.core.errors import UserError

SCEN = {"format": "unipixie.measurement/1", "gravity": [0, 0, -9.81], "ground": {"height": 0.0},
        "material": {"E": 2e5, "nu": 0.3, "density": 1000.0}, "my_extra_key": {"kept": True}}


def _cube():
    rest = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * 0.1
    import trimesh

    hull = trimesh.convex.convex_hull(rest)
    # faces indexing ``rest`` (the hull may reorder vertices)
    idx = [int(np.argmin(np.linalg.norm(rest - v, axis=1))) for v in hull.vertices]
    return rest, np.asarray(idx)[hull.faces]


def _arrays(T=6, occlude=True):
    rest, faces = _cube()
    t = np.linspace(0, 0.5, T)
    pos = rest[None] + np.array([0.1, 0, 0])[None, None] * t[:, None, None]
    if occlude:
        pos[2, 3] = np.nan
        pos[4, 5, 1] = np.nan  # one NaN coordinate hides the whole sample
    return rest, faces, t, pos


def _write(path, **arrays):
    np.savez(path, **arrays)
    return path


def test_roundtrip_keeps_everything(tmp_path):
    rest, faces, t, pos = _arrays()
    p = _write(tmp_path / "m.npz", positions=pos, times=t, rest_positions=rest, faces=faces,
               scenario=np.array(json.dumps(SCEN)), my_array=np.arange(3))
    m = meas.load(p)
    assert m.point_count == 8 and m.frame_count == 6
    assert np.isnan(m.positions[4, 5]).all() and m.observed.sum() == 6 * 8 - 2
    assert m.material.E == 2e5 and m.scenario.ground_height == 0.0
    assert m.scenario.extras == {"my_extra_key": {"kept": True}}
    q = m.save(tmp_path / "again.npz")
    m2 = meas.load(q)
    assert np.array_equal(np.isnan(m2.positions), np.isnan(m.positions))
    assert np.allclose(np.nan_to_num(m2.positions), np.nan_to_num(m.positions))
    assert np.array_equal(m2.faces, m.faces) and np.array_equal(m2.extra_arrays["my_array"], np.arange(3))
    assert json.loads(str(np.load(q)["scenario"]))["my_extra_key"] == {"kept": True}


@pytest.mark.parametrize("change, key", [
    (lambda a: a.pop("positions"), "'positions' is missing"),
    (lambda a: a.pop("times"), "'times' is missing"),
    (lambda a: a.pop("scenario"), "'scenario' is missing"),
    (lambda a: a.update(times=a["times"][:-1]), "'times' has 5 entries"),
    (lambda a: a.update(times=a["times"][::-1].copy()), "'times' must be strictly increasing"),
    (lambda a: a.update(positions=a["positions"][..., :2]), "'positions' must have shape"),
    (lambda a: a.update(positions=np.where(np.isnan(a["positions"]), np.inf, a["positions"])), "'positions' contains infinite"),
    (lambda a: a.update(rest_positions=a["rest_positions"][:-1]), "'rest_positions' must have shape"),
    (lambda a: a.update(faces=a["faces"][:-1]), "'faces' is not a closed surface"),
    (lambda a: a.update(faces=a["faces"] + 100), "'faces' refers to vertex"),
    (lambda a: a.update(faces=a["faces"][:, ::-1][[0, 1, 2]].tolist() and np.concatenate([a["faces"][:1, ::-1], a["faces"][1:]])),
     "'faces' is not consistently oriented"),
    (lambda a: a.update(scenario=np.array("{not json")), "'scenario' is not valid JSON"),
    (lambda a: a.update(scenario=np.array(json.dumps({**SCEN, "format": "x"}))), "'format'"),
    (lambda a: a.update(scenario=np.array(json.dumps({**SCEN, "gravity": [0, 1]}))), "'gravity'"),
    (lambda a: a.update(scenario=np.array(json.dumps({**SCEN, "material": {"E": 1e5}}))), "'material' lacks 'nu', 'density'"),
    (lambda a: a.update(scenario=np.array(json.dumps({**SCEN, "material": {"E": -1, "nu": 0.3, "density": 1}}))), "'E'"),
    (lambda a: a.update(scenario=np.array(json.dumps({**SCEN, "material": {"E": 1e5, "nu": 0.5, "density": 1}}))),
     "'nu' must lie in"),
    (lambda a: a.update(scenario=np.array(json.dumps({**SCEN, "material": {"E": 1e5, "nu": 0.3, "density": 0}}))),
     "'density' must be a positive"),
    (lambda a: a.update(E=np.ones(3)), "key 'E' must be a float array of shape \\(8,\\)"),
    (lambda a: (a.pop("rest_positions"), a["positions"].__setitem__((slice(None), 1), np.nan)),
     "'rest_positions' is missing"),
])
def test_broken_files_are_refused_naming_the_key(tmp_path, change, key):
    rest, faces, t, pos = _arrays()
    arrays = dict(positions=pos, times=t, rest_positions=rest, faces=faces, scenario=np.array(json.dumps(SCEN)))
    change(arrays)
    p = _write(tmp_path / "bad.npz", **arrays)
    with pytest.raises(UserError, match=key):
        meas.load(p)


def test_not_an_archive_and_missing_file(tmp_path):
    (tmp_path / "x.npz").write_text("hello")
    with pytest.raises(UserError, match="not a readable .npz"):
        meas.load(tmp_path / "x.npz")
    with pytest.raises(UserError, match="file not found"):
        meas.load(tmp_path / "nope.npz")
    with pytest.raises(UserError, match="unknown measurement file type"):
        meas.load(tmp_path / "x.txt")


def test_failed_save_leaves_no_file(tmp_path):
    rest, faces, t, pos = _arrays()
    m = meas.Measurement(pos, t, scenario=SCEN, rest_positions=rest)
    with pytest.raises(UserError, match="must end in .npz"):
        m.save(tmp_path / "m.txt")
    assert list(tmp_path.iterdir()) == []


def test_rest_shape_reconstructed_when_first_frame_is_occluded(tmp_path):
    """No rest_positions and a point hidden at t0: carried back rigidly from its first observation."""
    rest, faces, t, pos = _arrays(occlude=False)
    theta = 0.3 * t  # rotating about z and translating
    moved = np.empty_like(pos)
    for k, a in enumerate(theta):
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        moved[k] = rest @ R.T + [0.2 * t[k], 0, -0.1 * t[k]]
    moved[:3, 2] = np.nan
    p = _write(tmp_path / "r.npz", positions=moved, times=t, scenario=np.array(json.dumps(SCEN)))
    m = meas.load(p)
    assert np.allclose(m.rest, rest, atol=1e-9) and any("carried back" in w for w in m.warnings)


def test_per_point_material_and_defaults(tmp_path):
    rest, faces, t, pos = _arrays(occlude=False)
    E = np.linspace(1e5, 3e5, 8)
    p = _write(tmp_path / "pp.npz", positions=pos, times=t, scenario=np.array(json.dumps(SCEN)), E=E)
    m = meas.load(p)
    assert not m.material.homogeneous and np.allclose(m.material.E, E) and m.material.density == 1000.0
    assert np.array_equal(m.rest, pos[0])  # rest defaults to positions[0]
    spec = m.material.to_spec(m.rest)
    assert type(spec).__name__ == "PointMaterial" and np.allclose(spec.E, E)
    m2 = meas.load(m.save(tmp_path / "pp2.npz"))
    assert np.allclose(m2.material.E, E)


def test_csv_with_gaps_header_and_sidecar_scenario(tmp_path):
    rows = ["t,id,x,y,z", "0.0,7,0,0,0", "0.0,3,1,0,0", "0.1,7,0,0,-0.05", "0.1,3,,,",  # empty = occluded
            "0.2,7,0,0,-0.2", "0.2,3,1,0,-0.2"]
    (tmp_path / "tr.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "tr.json").write_text(json.dumps(SCEN))
    m = meas.load(tmp_path / "tr.csv")
    assert m.times.tolist() == [0.0, 0.1, 0.2] and m.point_count == 2
    assert m.extra_arrays["point_ids"].tolist() == ["3", "7"]  # numeric order of the ids
    assert np.isnan(m.positions[1, 0]).all() and m.positions[1, 1, 2] == pytest.approx(-0.05)
    assert m.material.E == 2e5
    # missing rows are occlusions too; duplicate rows are refused naming the id
    (tmp_path / "dup.csv").write_text("0,1,0,0,0\n0,1,0,0,0\n")
    with pytest.raises(UserError, match="point id '1' appears twice"):
        meas.load(tmp_path / "dup.csv")
    (tmp_path / "bad.csv").write_text("0,1,0,0,0\n0.1,1,0,abc,0\n")
    with pytest.raises(UserError, match="line 2: column 'y' is not a number"):
        meas.load(tmp_path / "bad.csv")
    # CSV -> npz -> CSV
    back = meas.load(m.save(tmp_path / "tr.npz"))
    assert np.array_equal(np.isnan(back.positions), np.isnan(m.positions))
    back.save_csv(tmp_path / "out.csv")
    again = meas.load(tmp_path / "out.csv")
    assert np.allclose(np.nan_to_num(again.positions), np.nan_to_num(m.positions))


def test_body_from_faces_and_from_convex_hull():
    rest, faces, t, pos = _arrays(occlude=False)
    with_faces = meas.Measurement(pos, t, scenario=SCEN, rest_positions=rest, faces=faces).body()
    assert with_faces.mesh.is_watertight and with_faces.mesh.volume == pytest.approx(1e-3)
    assert np.array_equal(with_faces.tracked_points, rest)
    hull = meas.Measurement(pos, t, scenario=SCEN, rest_positions=rest).body()
    assert hull.mesh.volume == pytest.approx(1e-3) and any("convex hull" in w for w in hull.warnings)
    flat = rest.copy()
    flat[:, 2] = 0
    with pytest.raises(UserError, match="no volume|degenerate"):
        meas.Measurement(flat[None].repeat(2, 0), t[:2], scenario=SCEN).body()


# --------------------------------------------------------------------------- comparison metrics
def test_compare_skips_unobserved_samples_and_finds_the_worst():
    rng = np.random.default_rng(0)
    T, N = 20, 30
    t = np.linspace(0, 1, T)
    sim = rng.normal(size=(T, N, 3))
    err = np.zeros((T, N, 3))
    err[:, 4, 0] = 0.05          # point 4 is off by 5 cm all the time
    err[13, :, 2] = 0.02         # instant 13 is off by 2 cm for every point
    measured = sim + err
    measured[:, 9] = np.nan      # point 9 never observed
    measured[5, 4] = np.nan      # one occluded sample of point 4
    c = cmp.compare(sim, measured, t, rest_positions=rng.normal(size=(N, 3)), region_count=3)
    d = np.sqrt((err ** 2).sum(-1))
    mask = np.isfinite(measured[..., 0])
    assert c.rmse == pytest.approx(np.sqrt(np.mean(d[mask] ** 2)), rel=1e-12)
    assert c.observed == mask.sum()
    assert c.worst_points[0] == 4 and c.per_point[4] == pytest.approx(np.sqrt((18 * 0.05 ** 2 + 0.05 ** 2 + 0.02 ** 2) / 19))
    assert math.isnan(c.per_point[9]) and 9 not in c.worst_points
    assert c.worst_times[0] == pytest.approx(t[13])
    assert sum(len(r.indices) for r in c.regions) == N
    assert cmp.rmse(sim, measured) == pytest.approx(c.rmse)
    assert cmp.residual_vector(sim, measured).size == 3 * mask.sum()
    with pytest.raises(UserError, match="no observed samples"):
        cmp.compare(sim, np.full_like(sim, np.nan), t)


@pytest.mark.parametrize("sigma", [2e-4, 1e-3, 3e-3])
def test_noise_estimate_recovers_sigma_under_motion_impacts_and_gaps(sigma):
    """White noise σ on smooth motion (free fall + 3–12 Hz wobble, one impact): within 10 %."""
    rng = np.random.default_rng(1)
    T, N = 100, 150
    t = np.arange(T) / 100.0
    base = rng.normal(size=(N, 3)) * 0.05
    f = rng.uniform(3, 12, N)
    z = np.where(t < 0.4, -4.905 * t ** 2, -4.905 * 0.16 + 1.5 * (t - 0.4) - 4.905 * (t - 0.4) ** 2)  # a bounce
    clean = base[None] + 0.005 * np.sin(2 * np.pi * f[None, :, None] * t[:, None, None])
    clean[..., 2] += z[:, None]
    noisy = clean + rng.normal(scale=sigma, size=clean.shape)
    noisy[rng.random((T, N)) < 0.15] = np.nan
    assert cmp.estimate_noise(noisy) == pytest.approx(sigma, rel=0.1)


def test_regions_are_deterministic_and_cover_every_point():
    pts = np.random.default_rng(2).uniform(size=(200, 3))
    a = cmp.kmeans_regions(pts, 6)
    assert np.array_equal(a, cmp.kmeans_regions(pts, 6)) and set(a.tolist()) == set(range(6))
    o = cmp.octant_regions(pts)
    assert set(o.tolist()) == set(range(8))
