"""A part's texture and its UVs: procedural images (noise, speckle, stripes, wood grain, brushed metal, panels,
fur) baked into one image per part and mapped with spherical, cylindrical or box projections.

:func:`textured_mesh` turns a part into the textured trimesh the ``.glb`` export writes.  May use
:mod:`.appearance` (and trimesh and Pillow, imported when called).
"""

from __future__ import annotations

import numpy as np

from .appearance import Appearance

TEXTURE_SIZE = 128
"""Edge of each part's baked texture image in pixels."""


def _periodic_noise(rng, size: int, freq: float, aniso: tuple = (1.0, 1.0)) -> np.ndarray:
    """Tileable smooth noise in [0, 1], feature size ≈ size / freq (Gaussian-filtered white noise via FFT)."""
    white = rng.normal(size=(size, size))
    ky = np.fft.fftfreq(size)[:, None] * size
    kx = np.fft.fftfreq(size)[None, :] * size
    sigma = max(freq, 0.5)
    filt = np.exp(-0.5 * ((kx / (sigma * aniso[1])) ** 2 + (ky / (sigma * aniso[0])) ** 2))
    n = np.real(np.fft.ifft2(np.fft.fft2(white) * filt))
    n -= n.min()
    return n / max(n.max(), 1e-12)


def _pattern_mask(app: Appearance, rng, size: int) -> np.ndarray:
    """(size, size) float in [0, 1]: 0 = base colour, 1 = secondary colour (before contrast)."""
    f = app.frequency
    v, u = np.meshgrid(np.arange(size) / size, np.arange(size) / size, indexing="ij")  # v rows, u columns
    p = app.pattern
    if p == "plain":
        return 0.15 * _periodic_noise(rng, size, 3)
    if p == "noise":
        return _periodic_noise(rng, size, f)
    if p == "speckle":
        return (rng.random((size, size)) < 0.12).astype(float) * rng.uniform(0.5, 1.0, (size, size))
    if p == "fur":
        return 0.6 * rng.random((size, size)) + 0.4 * _periodic_noise(rng, size, f)
    if p == "stripes":
        warp = 0.08 * (_periodic_noise(rng, size, 3) - 0.5)
        return (np.sin(2 * np.pi * (round(f) * u + warp)) > 0.75).astype(float)
    if p == "grain":
        warp = 0.5 * _periodic_noise(rng, size, 2)
        return 0.5 + 0.5 * np.sin(2 * np.pi * (round(f) * u + 2.0 * warp) + 3 * _periodic_noise(rng, size, 8))
    if p == "brushed":
        return _periodic_noise(rng, size, f, aniso=(4.0, 0.25))
    if p == "bands":
        return ((v > 0.8) & (v < 0.9)).astype(float)
    if p == "label":
        return ((v > 0.25) & (v < 0.75)).astype(float) * (0.7 + 0.3 * (np.sin(2 * np.pi * round(f) * u) > 0))
    if p == "panels":
        n = max(int(f * f), 6)
        seeds = rng.random((n, 2))
        d = np.full((size, size), np.inf)
        lab = np.zeros((size, size), dtype=int)
        for i, (sv, su) in enumerate(seeds):  # periodic Voronoi cells
            dv = np.minimum(np.abs(v - sv), 1 - np.abs(v - sv))
            du = np.minimum(np.abs(u - su), 1 - np.abs(u - su))
            di = dv ** 2 + du ** 2
            lab = np.where(di < d, i, lab)
            d = np.minimum(d, di)
        dark = rng.random(n) < 0.35
        return dark[lab].astype(float)
    raise KeyError(f"unknown texture pattern {p!r}")


PATTERNS = ("plain", "noise", "speckle", "fur", "stripes", "grain", "brushed", "bands", "label", "panels")


def texture_image(app: Appearance, rng, size: int = TEXTURE_SIZE) -> np.ndarray:
    """(size, size, 3) uint8 sRGB texture of a part: base colour, pattern towards the secondary colour."""
    m = np.clip(_pattern_mask(app, rng, size) * app.contrast, 0, 1)[..., None]
    img = (1 - m) * np.asarray(app.colour)[None, None] + m * np.asarray(app.secondary)[None, None]
    img = img * (1.0 + 0.06 * (_periodic_noise(rng, size, 10)[..., None] - 0.5))
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def _uv(part):
    """Unmerged per-face vertices (F*3, 3), smooth normals (F*3, 3) and UVs (F*3, 2) of a part's components
    (``part``: a :class:`~.objects.Part`)."""
    verts, norms, uvs = [], [], []
    for comp, rest in zip(part.components, part.rest or part.components):
        F = np.asarray(comp.faces)
        N = np.asarray(comp.vertex_normals, dtype=np.float64)
        verts.append(np.asarray(comp.vertices, dtype=np.float64)[F].reshape(-1, 3))
        V = np.asarray(rest.vertices, dtype=np.float64)      # UVs from the rest shape
        comp = rest
        P = V[F]                                   # (F, 3, 3)
        c = V.mean(0)
        lo, hi = V.min(0), V.max(0)
        size = max(float(np.max(hi - lo)), 1e-9)
        mode = part.appearance.uv
        if mode == "box":
            fn = np.asarray(comp.face_normals)
            ax = np.argmax(np.abs(fn), axis=1)
            other = np.array([[1, 2], [0, 2], [0, 1]])[ax]    # (F, 2)
            q = (P - lo) / size
            uv = np.stack([np.take_along_axis(q, other[:, None, 0:1].repeat(3, 1), 2)[..., 0],
                           np.take_along_axis(q, other[:, None, 1:2].repeat(3, 1), 2)[..., 0]], axis=-1)
        else:
            d = P - c
            u = np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi) + 0.5
            if mode == "cylindrical":
                v = (P[..., 2] - lo[2]) / max(hi[2] - lo[2], 1e-9)
            else:
                r = np.linalg.norm(d, axis=-1)
                v = np.arccos(np.clip(d[..., 2] / np.maximum(r, 1e-12), -1, 1)) / np.pi
            # faces across the seam: move their small-u corners by one turn (textures repeat)
            span = u.max(1) - u.min(1)
            wrap = span > 0.5
            u = np.where(wrap[:, None] & (u < 0.5), u + 1.0, u)
            # corners on the axis have no azimuth: take the mean of the face's other corners
            rxy = np.linalg.norm(d[..., :2], axis=-1)
            pole = rxy < 1e-9 * size
            if pole.any():
                fill = (u * ~pole).sum(1) / np.maximum((~pole).sum(1), 1)
                u = np.where(pole, fill[:, None], u)
            uv = np.stack([u, v], axis=-1)
        norms.append(N[F].reshape(-1, 3))
        uvs.append(uv.reshape(-1, 2))
    return np.concatenate(verts), np.concatenate(norms), np.concatenate(uvs)


def textured_mesh(part, seed: int):
    """A :class:`~.objects.Part` as one trimesh with UVs and a PBR material textured by :func:`texture_image`
    (the texture seeded by ``seed`` and the part's name)."""
    import trimesh
    from PIL import Image

    V, N, UV = _uv(part)
    faces = np.arange(len(V)).reshape(-1, 3)
    rng = np.random.default_rng([seed, stable_hash(part.name)])
    img = Image.fromarray(texture_image(part.appearance, rng))
    app = part.appearance
    mat = trimesh.visual.material.PBRMaterial(name=part.name, baseColorTexture=img, metallicFactor=app.metallic,
                                              roughnessFactor=app.roughness)
    visual = trimesh.visual.TextureVisuals(uv=UV, material=mat)
    return trimesh.Trimesh(V, faces, vertex_normals=N, visual=visual, process=False)


def stable_hash(text: str) -> int:
    """A 31-bit hash of ``text`` (FNV-1a), the same in every process (unlike the salted ``hash``): seeds the
    random generators of an object and of its textures."""
    h = 2166136261
    for ch in text.encode():
        h = ((h ^ ch) * 16777619) & 0x7FFFFFFF
    return h
