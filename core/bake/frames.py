"""The frames of a bake: :class:`FrameRange` (scene frames ``start`` … ``end``, ``start`` the rest state) and the
parsers of its command-line and manifest forms (``"1-120"``, ``"1-120,200-260"``).

Owns frame ranges and their times in seconds.  Uses only numpy and :mod:`unipixie.core.errors`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..errors import UserError


@dataclass(frozen=True)
class FrameRange:
    """Scene frames ``start`` … ``end`` inclusive; ``start`` is the rest state (time 0)."""

    start: int
    end: int

    def __post_init__(self):
        if self.end < self.start:
            raise UserError(f"the frame range {self.start}-{self.end} is empty (end before start)")
        if self.end == self.start:
            raise UserError(f"the frame range {self.start}-{self.end} has a single frame: nothing moves; "
                            "give at least two frames")

    @property
    def count(self) -> int:
        return self.end - self.start + 1

    @property
    def frames(self) -> np.ndarray:
        """(T,) int64 frame numbers."""
        return np.arange(self.start, self.end + 1, dtype=np.int64)

    def times(self, fps: float) -> np.ndarray:
        """(T,) float64 seconds since ``start`` at ``fps`` frames per second."""
        if not (np.isfinite(fps) and fps > 0):
            raise UserError(f"frames per second must be positive, got {fps!r}")
        return (self.frames - self.start).astype(np.float64) / float(fps)

    def __str__(self) -> str:
        return f"{self.start}-{self.end}"


def parse_frames(text: str) -> FrameRange:
    """``"1-120"`` → FrameRange(1, 120) (negative frames allowed: ``"-10-20"``)."""
    m = re.fullmatch(r"\s*(-?\d+)\s*(?:-|:|\.\.)\s*(-?\d+)\s*", str(text))
    if not m:
        raise UserError(f"frame range {text!r}: expected START-END, e.g. 1-120")
    return FrameRange(int(m.group(1)), int(m.group(2)))


def parse_frame_list(text: str) -> list[FrameRange]:
    """``"1-120,200-260"`` → a batch of frame ranges (each baked as its own simulation)."""
    parts = str(text).split(",")
    if not any(p.strip() for p in parts):
        raise UserError("no frame range given")
    if not all(p.strip() for p in parts):
        raise UserError(f"frame ranges {text!r}: an empty range between commas; expected START-END[,START-END...], "
                        "e.g. 1-120,200-260")
    return [parse_frames(p) for p in parts]
