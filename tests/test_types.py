"""Shared data types: validation and .npz round trips; material sampling."""

from __future__ import annotations

import numpy as np
import pytest

from unipixie.core.errors import UserError
from unipixie.core.types import FeatureGrid, GridGeometry, MaterialField, Trajectory, Views
from unipixie.solvers.material_sampling import HomogeneousMaterial, PointMaterial, sample_material


def _grid(R=8):
    occ = np.zeros((R, R, R), bool)
    occ[2:6, 2:6, 2:6] = True
    return GridGeometry(R, origin=[-0.5, -0.5, -0.5], voxel_size=1.0 / R), occ


def test_feature_grid_roundtrip(tmp_path):
    geo, occ = _grid()
    feats = np.random.default_rng(0).normal(size=(occ.sum(), 5)).astype(np.float16)
    g = FeatureGrid(geo, occ, feats, feature_model="test")
    g2 = FeatureGrid.load(g.save(tmp_path / "g.npz"))
    assert np.array_equal(g2.occupancy, occ) and np.array_equal(g2.features, feats) and g2.feature_model == "test"
    with pytest.raises(UserError, match="features must be"):
        FeatureGrid(geo, occ, feats[:-1])


def test_material_field_roundtrip_and_validation(tmp_path):
    geo, occ = _grid()
    m = MaterialField.homogeneous(geo, occ, 1e5, 0.3, 1000, material=0, alpha=0.5)
    m2 = MaterialField.load(m.save(tmp_path / "m.npz"))
    assert m2.alpha == 0.5 and np.allclose(m2.E, 1e5)
    with pytest.raises(UserError, match="nu"):
        MaterialField.homogeneous(geo, occ, 1e5, 0.6, 1000)


def test_trajectory_and_views_roundtrip(tmp_path):
    t = Trajectory(np.linspace(0, 1, 4), np.zeros((4, 3, 3)), solver="mpm", particle_positions=np.zeros((4, 7, 3)),
                   particle_attributes={"E": np.ones(7)}, meta={"dt": 1e-4})
    t2 = Trajectory.load(t.save(tmp_path / "t.npz"))
    assert t2.solver == "mpm" and t2.particle_positions.shape == (4, 7, 3) and t2.meta["dt"] == 1e-4
    with pytest.raises(UserError, match="strictly increasing"):
        Trajectory(np.array([0, 0.1, 0.1]), np.zeros((3, 2, 3)))
    v = Views(np.random.rand(2, 4, 5, 3), np.ones((2, 4, 5)), np.tile(np.eye(3), (2, 1, 1)), np.tile(np.eye(4), (2, 1, 1)))
    v2 = Views.load(v.save(tmp_path / "v.npz"))
    assert np.allclose(v2.images, v.images, atol=1e-4)
    with pytest.raises(UserError, match="not found"):
        Views.load(tmp_path / "missing.npz")


def test_material_sampling_modes():
    geo, occ = _grid()
    K = occ.sum()
    idx = np.argwhere(occ)
    E = np.where(idx[:, 0] < 4, 1e4, 1e6)
    field = MaterialField(geo, occ, E, np.full(K, 0.3), np.full(K, 1000.0), np.zeros(K))
    pts = np.array([[-0.5 + 2.5 / 8, 0, 0], [-0.5 + 5.5 / 8, 0, 0], [-0.5 + 4.0 / 8, 0.0, 0.0]])
    near = sample_material(field, pts, "nearest")
    assert near.E[0] == 1e4 and near.E[1] == 1e6
    tri = sample_material(field, pts, "trilinear")
    assert tri.E[2] == pytest.approx(1e5, rel=1e-6)  # geometric mean halfway between 1e4 and 1e6
    h = sample_material(HomogeneousMaterial(2e5, 0.3, 900, "metal"), pts)
    assert np.all(h.material == 1) and np.all(h.E == 2e5)
    p = sample_material(PointMaterial(pts[:2], [1, 2], [0.3, 0.3], [1, 1]), pts[:2] + 0.01)
    assert p.E.tolist() == [1, 2]
    mu, lam = h.lame()
    assert mu[0] == pytest.approx(2e5 / 2.6) and lam[0] == pytest.approx(2e5 * 0.3 / (1.3 * 0.4))
