"""The measurement noise estimated from the tracks: within 20 % of the true σ on bounces, slides and vibrations.

Synthetic tracks with a known white noise σ (0.5 and 1 mm), 10 % occluded samples, 50 frames/s: a spinning
cube bouncing on the ground (velocity jumps at every impact), a cube thrown down onto the ground that then
slides to rest with Coulomb friction, and a clamped bar vibrating in its first bending mode at 18 Hz (near the
frame rate's Nyquist limit: frame-scale motion a track alone cannot tell from noise).  Issue 18 measured the
time-difference estimator alone at 2.4–2.9 mm on drops with a true 0.87 mm.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from unipixie.core.diagnosis import compare as cmp

FPS = 50.0
T = 50
G = 9.81


def _cube_points(n: int, rng, size: float = 0.2) -> np.ndarray:
    """(n, 3) points on the surface of a cube of edge ``size`` centred at the origin."""
    p = rng.uniform(-0.5, 0.5, (n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.sign(p[np.arange(n), axis]) * 0.5
    return p * size


def _rotation_z(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def bouncing(rng) -> tuple[np.ndarray, np.ndarray]:
    """A cube dropped from 0.5 m, restitution 0.6, spinning at 6 rad/s; its centre bounces (ballistic arcs)."""
    rest = _cube_points(150, rng)
    t = np.arange(T) / FPS
    z, vz, zs, t_hits = 0.5, 0.0, [], []
    fine = 200
    for i in range(T):
        zs.append(z)
        for j in range(fine):  # fine sub-steps: the impacts fall between frames
            vz -= G / (FPS * fine)
            z += vz / (FPS * fine)
            if z < 0.1 and vz < 0:
                z, vz = 0.1, -0.6 * vz
                t_hits.append((i + (j + 1) / fine) / FPS)
    com = np.stack([0.4 * t, 0.1 * t, np.array(zs)], axis=1)
    R = _rotation_z(6.0 * t)
    pos = com[:, None] + np.einsum("tij,nj->tni", R, rest)
    # a soft cube rings after every impact: a decaying squash (volume-keeping, 22 Hz) started at each landing
    squash = np.zeros(T)
    for th in t_hits:
        squash += np.where(t >= th, 0.15 * np.exp(-(t - th) / 0.1) * np.sin(2 * np.pi * 22 * (t - th)), 0.0)
    pos[..., 2] -= squash[:, None] * (pos[..., 2] - com[:, None, 2])
    pos[..., :2] += 0.5 * squash[:, None, None] * (pos[..., :2] - com[:, None, :2])
    return pos, rest


def sliding(rng) -> tuple[np.ndarray, np.ndarray]:
    """A cube thrown down at 1.5 m/s onto the ground (it stops dead at the impact) sliding at 2 m/s to rest
    with μ = 0.4, ringing (a decaying 20 Hz squash) after the impact."""
    rest = _cube_points(150, rng)
    t = np.arange(T) / FPS
    t_hit = 0.1
    z = np.where(t < t_hit, 0.1 + 1.5 * (t_hit - t) + 0.5 * G * (t_hit - t) ** 2, 0.1)
    v0, a = 2.0, 0.4 * G
    ts = np.clip(t - t_hit, 0.0, v0 / a)
    x = np.where(t < t_hit, v0 * (t - t_hit), v0 * ts - 0.5 * a * ts ** 2)
    com = np.stack([x, np.zeros_like(t), z], axis=1)
    squash = np.where(t >= t_hit, 0.25 * np.exp(-(t - t_hit) / 0.15) * np.sin(2 * np.pi * 20 * (t - t_hit)), 0.0)
    pos = com[:, None] + rest[None]
    pos[..., 2] -= squash[:, None] * (rest[None, :, 2] + 0.1)  # the top moves, the bottom stays on the ground
    return pos, rest


def vibrating_bar(rng) -> tuple[np.ndarray, np.ndarray]:
    """A clamped bar 0.4 × 0.06 × 0.04 m in its first bending mode, 18 Hz, 2 cm tip amplitude
    (the rotation of the sections neglected)."""
    n = 150
    rest = np.stack([rng.uniform(0, 0.4, n), rng.uniform(-0.03, 0.03, n), rng.uniform(-0.02, 0.02, n)], axis=1)
    t = np.arange(T) / FPS
    L, beta = 0.4, 1.875 / 0.4
    s = beta * rest[:, 0]
    sigma_m = (math.cosh(beta * L) + math.cos(beta * L)) / (math.sinh(beta * L) + math.sin(beta * L))
    shape = np.cosh(s) - np.cos(s) - sigma_m * (np.sinh(s) - np.sin(s))
    shape = shape / np.max(np.abs(shape))
    w = 0.02 * np.cos(2 * np.pi * 18 * t)[:, None] * shape[None]  # (T, n)
    pos = np.repeat(rest[None], T, axis=0)
    pos[..., 2] += w
    return pos, rest


MOTIONS = {"bouncing": bouncing, "sliding": sliding, "vibrating_bar": vibrating_bar}


@pytest.mark.parametrize("sigma", [0.0005, 0.001])
@pytest.mark.parametrize("motion", list(MOTIONS))
def test_noise_estimate_within_20_percent(motion, sigma):
    rng = np.random.default_rng(7)
    clean, rest = MOTIONS[motion](rng)
    noisy = clean + rng.normal(scale=sigma, size=clean.shape)
    noisy[rng.random(noisy.shape[:2]) < 0.1] = np.nan
    est = cmp.estimate_noise(noisy, rest)
    assert est == pytest.approx(sigma, rel=0.2), (motion, sigma, est)


def test_these_motions_defeat_the_time_differences_alone():
    """The cases are hard: the time-difference estimator alone is more than 20 % off on each of them
    (so the test above can fail)."""
    rng = np.random.default_rng(7)
    for motion, make in MOTIONS.items():
        clean, rest = make(rng)
        noisy = clean + rng.normal(scale=0.0005, size=clean.shape)
        assert cmp.estimate_noise(noisy) > 1.2 * 0.0005, motion


def test_rest_positions_must_match():
    from unipixie.core.errors import UserError

    with pytest.raises(UserError, match="rest positions"):
        cmp.estimate_noise(np.zeros((10, 20, 3)), np.zeros((19, 3)))


def bending_ringing(rng, amplitude: float = 0.006) -> tuple[np.ndarray, np.ndarray]:
    """A cube at rest on the ground ringing in a bending mode after a bounce: a 22 Hz standing wave of wavelength
    0.15 m across the 0.2 m cube (``amplitude`` m), which no local affine motion describes."""
    rest = _cube_points(150, rng)
    t = (np.arange(T) / FPS)[:, None]
    k = 2 * np.pi / 0.15
    pos = np.repeat(rest[None], T, axis=0).copy()
    pos[..., 2] += amplitude * np.sin(k * rest[:, 0]) * np.cos(k * rest[:, 1]) * np.sin(2 * np.pi * 22 * t)
    return pos, rest


@pytest.mark.parametrize("sigma", [0.0005, 0.001])
def test_a_bending_ringing_needs_the_quadratic_neighbourhood(sigma, monkeypatch):
    """The local quadratic estimate keeps a ringing solid's bending out of σ (within 20 %), where the affine one
    alone is more than 20 % high."""
    rng = np.random.default_rng(11)
    clean, rest = bending_ringing(rng)
    noisy = clean + rng.normal(scale=sigma, size=clean.shape)
    noisy[rng.random(noisy.shape[:2]) < 0.1] = np.nan
    assert cmp.estimate_noise(noisy, rest) == pytest.approx(sigma, rel=0.2)
    monkeypatch.setattr(cmp, "NOISE_NEIGHBOURS_QUADRATIC", 10 ** 6)  # too few points: the quadratic one is skipped
    assert cmp.estimate_noise(noisy, rest) > 1.2 * sigma
