"""How a procedural object's parts look: the palette of each class and part, and a part's appearance code.

Every part gets an *appearance code* u ∈ [0, 1] that sets its colour between the palette's "soft-looking" and
"stiff-looking" colours and its texture's contrast and frequency (the same u places the part's stiffness range
inside the class prior, :func:`unipixie.core.annotation.sample_annotation`).  Plain data and numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Appearance:
    """How one part looks.

    pattern: texture pattern name (see :data:`.textures.PATTERNS`).
    colour / secondary: sRGB in [0, 1] (base colour and the pattern's second colour).
    frequency: pattern features across the texture; contrast: 0 (plain) .. 1 (full).
    roughness / metallic: glTF PBR factors.  code: the appearance code u ∈ [0, 1].
    uv: ``"spherical"``, ``"cylindrical"`` or ``"box"`` projection.
    """

    pattern: str
    colour: tuple
    secondary: tuple
    frequency: float
    contrast: float
    roughness: float
    metallic: float
    code: float
    uv: str = "spherical"

    def to_dict(self) -> dict:
        return {"pattern": self.pattern, "colour": list(self.colour), "secondary": list(self.secondary),
                "frequency": self.frequency, "contrast": self.contrast, "roughness": self.roughness,
                "metallic": self.metallic, "code": self.code, "uv": self.uv}


def _rgb(h: str) -> tuple:
    return tuple(int(h[i:i + 2], 16) / 255.0 for i in (1, 3, 5))


@dataclass(frozen=True)
class Look:
    """Palette entry: pattern, colour of a soft-looking (u = 0) and a stiff-looking (u = 1) part, secondary colour."""

    pattern: str
    soft: str
    stiff: str
    secondary: str
    roughness: float = 0.7
    metallic: float = 0.0
    uv: str = "spherical"
    frequency: float = 6.0


PALETTES: dict = {
    ("potted_plant", "pot"): Look("noise", "#c9825a", "#8a4b32", "#6f3a25", 0.8, 0.0, "cylindrical", 3),
    ("potted_plant", "soil"): Look("speckle", "#5a4030", "#2e2018", "#9a7b5a", 0.95, 0.0, "cylindrical", 20),
    ("potted_plant", "trunk"): Look("grain", "#9b7a55", "#5b3a22", "#3c2616", 0.9, 0.0, "cylindrical", 8),
    ("potted_plant", "leaves"): Look("noise", "#8fd16a", "#2f6a2a", "#1f4a1c", 0.7, 0.0, "spherical", 10),
    ("potted_plant", "succulent", "leaves"): Look("stripes", "#a8d8b0", "#4f8f6a", "#d8e8c8", 0.5, 0.0, "spherical", 4),
    ("sport_ball", "soccer", "cover"): Look("panels", "#f4f4f0", "#d8d8d0", "#1a1a1a", 0.5, 0.0, "spherical", 5),
    ("sport_ball", "basketball", "cover"): Look("stripes", "#f08a3c", "#b5501e", "#1c1410", 0.8, 0.0, "spherical", 4),
    ("sport_ball", "tennis", "cover"): Look("fur", "#e6f55a", "#b9cc2e", "#f8f8f0", 0.95, 0.0, "spherical", 24),
    ("sport_ball", "volleyball", "cover"): Look("stripes", "#f6f2e0", "#e8d070", "#2856a8", 0.6, 0.0, "spherical", 3),
    ("sport_ball", "core"): Look("plain", "#e8e0d0", "#b8b0a0", "#a09888", 0.8, 0.0, "spherical", 2),
    ("stuffed_toy", "bear", "*"): Look("fur", "#d9b27c", "#8a5a32", "#f2dcb8", 0.95, 0.0, "spherical", 28),
    ("stuffed_toy", "bunny", "*"): Look("fur", "#f4eee8", "#b8aea6", "#f0c0c8", 0.95, 0.0, "spherical", 28),
    ("stuffed_toy", "cat", "*"): Look("stripes", "#f0b060", "#9a6a40", "#5a3a20", 0.95, 0.0, "spherical", 7),
    ("stuffed_toy", "eyes"): Look("plain", "#303030", "#050505", "#ffffff", 0.15, 0.0, "spherical", 2),
    ("rubber_duck", "*"): Look("plain", "#ffe45a", "#f0b800", "#ffffff", 0.25, 0.0, "spherical", 2),
    ("rubber_duck", "squeaky_soft", "*"): Look("noise", "#fff08a", "#f5cc30", "#ffffff", 0.5, 0.0, "spherical", 4),
    ("rubber_duck", "beak"): Look("plain", "#ffa040", "#e05010", "#ffffff", 0.3, 0.0, "spherical", 2),
    ("rubber_duck", "eyes"): Look("plain", "#202020", "#000000", "#ffffff", 0.1, 0.0, "spherical", 2),
    ("jelly_pudding", "plate"): Look("bands", "#f4f4f4", "#d8dde8", "#3050a0", 0.2, 0.0, "cylindrical", 2),
    ("jelly_pudding", "gelatin", "jelly"): Look("noise", "#ff6a8a", "#b0102a", "#ffffff", 0.1, 0.0, "cylindrical", 4),
    ("jelly_pudding", "panna_cotta", "jelly"): Look("noise", "#fff6e6", "#eadcc0", "#ffffff", 0.3, 0.0, "cylindrical", 3),
    ("jelly_pudding", "flan", "jelly"): Look("noise", "#ffe08a", "#e0b040", "#c07020", 0.2, 0.0, "cylindrical", 3),
    ("jelly_pudding", "topping"): Look("noise", "#fffaf0", "#8a3a10", "#c02040", 0.2, 0.0, "spherical", 5),
    ("metal_tool", "handle"): Look("grain", "#d8b080", "#7a4a28", "#5a3418", 0.7, 0.0, "cylindrical", 10),
    ("metal_tool", "body"): Look("brushed", "#c8ccd2", "#50545a", "#8a8e94", 0.35, 1.0, "box", 20),
    ("metal_tool", "can", "body"): Look("label", "#d8dde2", "#9aa0a8", "#c01820", 0.3, 1.0, "cylindrical", 3),
    ("metal_tool", "contents"): Look("plain", "#402010", "#200800", "#603010", 0.3, 0.0, "cylindrical", 2),
    ("sand_pile", "sand"): Look("speckle", "#f0dca0", "#b89060", "#806040", 0.95, 0.0, "cylindrical", 30),
    ("sand_pile", "pebbles"): Look("noise", "#b0aca8", "#5a5654", "#3a3634", 0.8, 0.0, "spherical", 6),
    ("snow_pile", "snow"): Look("speckle", "#ffffff", "#dce6f0", "#b8c8e0", 0.8, 0.0, "spherical", 30),
    ("snow_pile", "ice"): Look("noise", "#d8f0ff", "#7ab8e0", "#ffffff", 0.05, 0.0, "spherical", 4),
    ("snow_pile", "nose"): Look("stripes", "#ff9a40", "#d05a10", "#a04008", 0.6, 0.0, "cylindrical", 6),
    ("snow_pile", "arms"): Look("grain", "#8a6a4a", "#4a3020", "#2a1a10", 0.9, 0.0, "cylindrical", 6),
    ("fruit", "apple", "flesh"): Look("stripes", "#e8d050", "#b01818", "#f0e080", 0.35, 0.0, "spherical", 12),
    ("fruit", "orange", "flesh"): Look("speckle", "#ffb040", "#e07010", "#ffd080", 0.6, 0.0, "spherical", 40),
    ("fruit", "pear", "flesh"): Look("speckle", "#d8e070", "#98a030", "#7a6030", 0.5, 0.0, "spherical", 30),
    ("fruit", "plum", "flesh"): Look("noise", "#a05090", "#401040", "#8070a0", 0.3, 0.0, "spherical", 4),
    ("fruit", "core"): Look("plain", "#f4ecc0", "#d8c890", "#604020", 0.8, 0.0, "spherical", 2),
    ("fruit", "stem"): Look("grain", "#8a7040", "#4a3018", "#2a1a08", 0.9, 0.0, "cylindrical", 4),
    ("fruit", "leaf"): Look("stripes", "#9ad060", "#3a7a28", "#c0e090", 0.6, 0.0, "box", 6),
    ("wooden_furniture", "cushion"): Look("fur", "#d0c8e8", "#803040", "#f0e8f0", 0.95, 0.0, "box", 16),
    ("wooden_furniture", "*"): Look("grain", "#e0c090", "#6a4020", "#4a2a10", 0.6, 0.0, "box", 8),
    ("wooden_furniture", "padded_chair", "*"): Look("grain", "#c8a070", "#5a3418", "#3a2008", 0.4, 0.0, "box", 8),
}
"""(class, part) / (class, variant, part) / (class, "*") / (class, variant, "*") -> :class:`Look` (most specific wins)."""


def look_for(semantic_class: str, variant: str, part: str) -> Look:
    for key in ((semantic_class, variant, part), (semantic_class, part), (semantic_class, variant, "*"),
                (semantic_class, "*")):
        if key in PALETTES:
            return PALETTES[key]
    raise KeyError(f"no palette entry for {semantic_class}/{variant}/{part}")


def part_appearance(look: Look, u: float, rng) -> Appearance:
    """The appearance of a part with palette entry ``look`` and appearance code ``u`` (colour, contrast and
    roughness jittered by ``rng``)."""
    a, b = np.array(_rgb(look.soft)), np.array(_rgb(look.stiff))
    colour = np.clip((1 - u) * a + u * b + rng.normal(0, 0.03, 3), 0, 1)
    return Appearance(look.pattern, tuple(float(x) for x in colour), _rgb(look.secondary),
                      float(look.frequency * rng.uniform(0.8, 1.25)), float(np.clip(0.35 + 0.5 * u + rng.normal(0, 0.05), 0.1, 1.0)),
                      float(np.clip(look.roughness + 0.15 * (0.5 - u) + rng.normal(0, 0.03), 0.02, 1.0)), look.metallic,
                      float(u), look.uv)
