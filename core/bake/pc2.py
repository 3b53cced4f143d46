"""PC2 point caches (the file format of Blender's Mesh Cache modifier and 3ds Max): :func:`write_pc2` writes one
atomically, :func:`read_pc2` reads one back into a :class:`PointCache`; a malformed file is a
:class:`~unipixie.core.errors.UserError` naming what is wrong.

Uses numpy, :mod:`unipixie.core.atomic_io` and :mod:`unipixie.core.errors` only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UserError


PC2_SIGNATURE = b"POINTCACHE2\0"
PC2_VERSION = 1
_PC2_HEADER = np.dtype([("signature", "S12"), ("version", "<i4"), ("points", "<i4"), ("start", "<f4"),
                        ("rate", "<f4"), ("samples", "<i4")])


def write_pc2(path, positions: np.ndarray, start_frame: float = 0.0, sample_rate: float = 1.0) -> Path:
    """Write a PC2 point cache (the format of Blender's Mesh Cache modifier and 3ds Max).

    positions: (T, N, 3) float32, object-local coordinates.  start_frame / sample_rate: header fields
    (frame of the first sample, frames between samples).  The file is written to a temporary name and
    renamed (:mod:`unipixie.core.atomic_io`, size checked), so a reader never sees a half-written cache.
    """
    pos = np.ascontiguousarray(np.asarray(positions, dtype="<f4"))
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] < 1 or pos.shape[1] < 1:
        raise UserError(f"a PC2 cache needs positions of shape (samples, points, 3), got {pos.shape}")
    if not np.all(np.isfinite(pos)):
        raise UserError("refusing to write NaN/inf positions into a PC2 cache")
    path = Path(path)
    header = np.zeros((), dtype=_PC2_HEADER)
    header["signature"] = PC2_SIGNATURE
    header["version"] = PC2_VERSION
    header["points"] = pos.shape[1]
    header["start"] = float(start_frame)
    header["rate"] = float(sample_rate)
    header["samples"] = pos.shape[0]
    from ..atomic_io import write_stream

    def write(f) -> None:
        f.write(header.tobytes())
        f.write(pos.tobytes())

    write_stream(path, write, expected_size=header.nbytes + pos.nbytes)
    return path


@dataclass
class PointCache:
    """A PC2 file's content: positions (T, N, 3) float32, start frame and sample rate."""

    positions: np.ndarray
    start_frame: float
    sample_rate: float


def read_pc2(path) -> PointCache:
    """Read a PC2 point cache; a malformed file is a :class:`UserError` naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: PC2 file not found")
    size = path.stat().st_size
    if size < _PC2_HEADER.itemsize:
        raise UserError(f"{path}: too short for a PC2 header ({size} bytes)")
    with open(path, "rb") as f:
        header = np.frombuffer(f.read(_PC2_HEADER.itemsize), dtype=_PC2_HEADER)[0]
        if bytes(header["signature"]).rstrip(b"\0") != PC2_SIGNATURE.rstrip(b"\0"):
            raise UserError(f"{path}: not a PC2 file (signature {bytes(header['signature'])!r})")
        n, t = int(header["points"]), int(header["samples"])
        if n < 1 or t < 1:
            raise UserError(f"{path}: PC2 header says {t} samples of {n} points")
        expected = _PC2_HEADER.itemsize + 12 * n * t
        if size != expected:
            raise UserError(f"{path}: PC2 file is {size} bytes, its header promises {expected} ({t} × {n} points)")
        data = np.frombuffer(f.read(), dtype="<f4").reshape(t, n, 3).astype(np.float32)
    return PointCache(data, float(header["start"]), float(header["rate"]))
