"""The material-field display: log E mapped to colours over the whole α sweep's range, and the voxels' surface.

:class:`FieldColourScale` maps log E through one colour map over the sweep's whole range (so moving α visibly
shifts the colours); :func:`voxel_surface` is the quad mesh of the occupied voxels' outer faces.  Shared by the
viewport (:mod:`unipixie.core.blender_io.field_view`) and the demo's pictures.  Needs only numpy (and matplotlib's
colour maps).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import UserError

FIELD_COLORMAP = "viridis"
"""Colour map of the material-field display (perceptually uniform; luminance rises with E)."""
FIELD_LUT_SIZE = 256


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _colormap_lut() -> np.ndarray:
    from matplotlib import colormaps

    return np.asarray(colormaps[FIELD_COLORMAP](np.linspace(0.0, 1.0, FIELD_LUT_SIZE)), dtype=np.float64)[:, :3]


def format_pascal(value: float) -> str:
    """``1.2e6`` → ``"1.2 MPa"``."""
    v = float(value)
    for unit, f in (("GPa", 1e9), ("MPa", 1e6), ("kPa", 1e3)):
        if abs(v) >= f:
            return f"{v / f:.3g} {unit}"
    return f"{v:.3g} Pa"


@dataclass
class FieldColourScale:
    """log10 E (Pa) → colour, over ``[log10_min, log10_max]`` (the whole α sweep's range of the
    simulated voxels, so one colour means one stiffness at every α).

    lut_srgb: (L, 3) float64 display colours in [0, 1]; ``lut_linear``: the same in scene-linear RGB
    (Blender colour attributes).
    """

    log10_min: float
    log10_max: float
    lut_srgb: np.ndarray = field(default_factory=_colormap_lut, repr=False)

    def __post_init__(self):
        lo, hi = float(self.log10_min), float(self.log10_max)
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise UserError("the material field has non-finite stiffness values")
        if hi - lo < 1e-3:          # a uniform field: a small band around its value
            lo, hi = lo - 0.05, hi + 0.05
        self.log10_min, self.log10_max = lo, hi
        self.lut_linear = _srgb_to_linear(self.lut_srgb).astype(np.float32)

    @classmethod
    def of_sweep(cls, sweep) -> "FieldColourScale":
        if sweep.log10_E is None:
            raise UserError("this α sweep has no MPM field (E per voxel) to show; predict with the MPM head")
        vals = np.asarray(sweep.log10_E, dtype=np.float64)
        return cls(float(vals.min()), float(vals.max()))

    def positions(self, log10_E) -> np.ndarray:
        """(K,) float64 positions in [0, 1] along the colour map."""
        return np.clip((np.asarray(log10_E, np.float64) - self.log10_min) / (self.log10_max - self.log10_min), 0.0, 1.0)

    def indices(self, log10_E) -> np.ndarray:
        return np.rint(self.positions(log10_E) * (len(self.lut_srgb) - 1)).astype(np.int64)

    def colours_linear(self, log10_E) -> np.ndarray:
        """(K, 4) float32 scene-linear RGBA."""
        rgb = self.lut_linear[self.indices(log10_E)]
        return np.concatenate([rgb, np.ones((len(rgb), 1), np.float32)], axis=1)

    def ticks(self, count: int = 5) -> list[tuple[float, float, str]]:
        """``count`` legend ticks, bottom to top: (position in [0, 1], E in Pa, label)."""
        out = []
        for t in np.linspace(0.0, 1.0, int(count)):
            e = 10.0 ** (self.log10_min + t * (self.log10_max - self.log10_min))
            out.append((float(t), float(e), format_pascal(e)))
        return out

    def to_dict(self) -> dict:
        return {"log10_min": self.log10_min, "log10_max": self.log10_max, "colormap": FIELD_COLORMAP}


_FACE_DIRECTIONS = (
    # (axis, sign, the face's 4 corners as offsets of the voxel's lower corner, counter-clockwise seen from outside)
    (0, -1, ((0, 0, 0), (0, 0, 1), (0, 1, 1), (0, 1, 0))),
    (0, +1, ((1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1))),
    (1, -1, ((0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1))),
    (1, +1, ((0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0))),
    (2, -1, ((0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0))),
    (2, +1, ((0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))),
)


def voxel_surface(geometry, occupancy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The outer faces of the occupied voxels as a quad mesh (what the field display draws).

    Returns vertices (V, 3) float64 in ``geometry``'s units (the normalised cube for model grids),
    quads (F, 4) int64 vertex indices (counter-clockwise seen from outside), and face_voxel (F,) int64:
    the occupied voxel (index into ``np.argwhere(occupancy)``) each face belongs to.
    """
    occ = np.asarray(occupancy, dtype=bool)
    R = occ.shape[0]
    if occ.ndim != 3 or occ.shape != (R, R, R):
        raise UserError(f"occupancy must be a cube of voxels, got shape {occ.shape}")
    voxel_id = np.full(occ.shape, -1, dtype=np.int64)
    idx = np.argwhere(occ)
    voxel_id[tuple(idx.T)] = np.arange(len(idx))
    padded = np.pad(occ, 1)
    corners, faces_voxel = [], []
    for axis, sign, offsets in _FACE_DIRECTIONS:
        shift = [slice(1, -1)] * 3
        shift[axis] = slice(1 + sign, R + 1 + sign)
        exposed = occ & ~padded[tuple(shift)]
        vox = np.argwhere(exposed)
        if len(vox) == 0:
            continue
        corners.append(vox[:, None, :] + np.asarray(offsets)[None, :, :])     # (n, 4, 3) lattice corners
        faces_voxel.append(voxel_id[tuple(vox.T)])
    if not corners:
        raise UserError("the feature grid has no occupied voxels to show")
    lattice = np.concatenate(corners)                                          # (F, 4, 3)
    keys = (lattice[..., 0] * (R + 1) + lattice[..., 1]) * (R + 1) + lattice[..., 2]
    unique, inverse = np.unique(keys.ravel(), return_inverse=True)
    ijk = np.stack([unique // ((R + 1) ** 2), (unique // (R + 1)) % (R + 1), unique % (R + 1)], axis=1)
    vertices = np.asarray(geometry.origin, np.float64) + ijk * float(geometry.voxel_size)
    return vertices, inverse.reshape(-1, 4).astype(np.int64), np.concatenate(faces_voxel)


def field_summary(sweep, alpha: float) -> str:
    """One line for the panel: the stiffness at ``alpha`` (median and 5–95 % range of E)."""
    logE = sweep.values_at("log10_E", alpha)
    lo, med, hi = np.percentile(logE, [5, 50, 95])
    return (f"E at α {float(alpha):.2f}: median {format_pascal(10 ** med)} "
            f"({format_pascal(10 ** lo)} – {format_pascal(10 ** hi)})")
