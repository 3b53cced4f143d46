"""Target normalisation: the one definition of how physical quantities become model channels.

The flow-matching decoders work on channels of roughly unit scale.  Each
physical quantity is mapped by a :class:`ChannelNorm`::

    channel = (f(value) - centre) / scale,   f = log10 (E, density, stiffness) or identity (nu, softness)

so E and ρ are modelled (and α-interpolated) in log space.  The constants
below are the defaults; a model's config carries the constants it was
trained with (they are saved in every checkpoint), so changing a default
never silently changes an existing model.

Defaults (chosen from the material-class registry's typical ranges):

* ``log10 E``: centre 6.5, scale 2.5 (1e4 Pa -> -1, 1e9 Pa -> +1, 2.5e11 Pa -> +1.96);
* ``log10 ρ``: centre 3.0, scale 0.5 (100 kg/m³ -> -2, 9000 kg/m³ -> +0.95);
* ``nu``: centre 0.3, scale 0.1 (0.2 -> -1, 0.49 -> +1.9);
* spring ``log10 k``: centre 3.0, scale 2.0 (k per anchor in the spring-mass solver's units, N);
* spring softness ``eta``: centre 0.0, scale 1.0 (dimensionless);
* LBS skinning parameters: centre 0.0, scale 1.0.

The last three depend on how the dataset's fits come out, so training fits them to the data by
default (:func:`fitted_norm`, ``unipixie train --fixed-normalisation`` keeps these defaults).

Works on numpy arrays and torch tensors alike.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

NU_MIN = -0.99
"""Smallest Poisson's ratio a decoded prediction may take (MaterialField needs nu > -1)."""
NU_MAX = 0.499
"""Largest Poisson's ratio a decoded prediction may take (MaterialField needs nu < 0.5)."""
LOG10_MIN = -6.0
LOG10_MAX = 14.0
"""Decoded log10 values are clipped to [LOG10_MIN, LOG10_MAX] so that 10**x stays finite in float32."""


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


@dataclass(frozen=True)
class ChannelNorm:
    """How one physical quantity maps to one model channel.

    name: channel name (``"log10_E"``); quantity: what it is (``"E"``); unit: SI unit of the quantity;
    log10: model the base-10 logarithm; centre, scale: affine normalisation of f(value);
    lower / upper: physical clipping range applied on decoding (``None`` = none).
    """

    name: str
    quantity: str
    unit: str
    log10: bool
    centre: float
    scale: float
    lower: float | None = None
    upper: float | None = None

    def encode(self, value):
        """Physical values -> normalised channel values (numpy or torch, same shape)."""
        if self.log10:
            v = value.log10() if _is_torch(value) else np.log10(np.asarray(value, dtype=np.float64))
        else:
            v = value
        return (v - self.centre) / self.scale

    def decode(self, channel):
        """Normalised channel values -> physical values (clipped to the physical range)."""
        v = channel * self.scale + self.centre
        if self.log10:
            v = v.clamp(LOG10_MIN, LOG10_MAX) if _is_torch(v) else np.clip(v, LOG10_MIN, LOG10_MAX)
            v = 10.0 ** v
        if self.lower is not None or self.upper is not None:
            v = v.clamp(self.lower, self.upper) if _is_torch(v) else np.clip(v, self.lower, self.upper)
        return v

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ChannelNorm":
        return cls(**d)


LOG10_E = ChannelNorm("log10_E", "E", "Pa", True, 6.5, 2.5)
LOG10_DENSITY = ChannelNorm("log10_density", "density", "kg/m^3", True, 3.0, 0.5)
NU = ChannelNorm("nu", "nu", "1", False, 0.3, 0.1, NU_MIN, NU_MAX)
LOG10_STIFFNESS = ChannelNorm("log10_stiffness", "stiffness", "N", True, 3.0, 2.0)
SOFTNESS = ChannelNorm("softness", "softness", "1", False, 0.0, 1.0)
LBS_PARAMS = ChannelNorm("lbs_params", "lbs_params", "1", False, 0.0, 1.0)

DEFAULT_NORMALISATION: dict[str, ChannelNorm] = {
    "E": LOG10_E,
    "density": LOG10_DENSITY,
    "nu": NU,
    "stiffness": LOG10_STIFFNESS,
    "softness": SOFTNESS,
    "lbs_params": LBS_PARAMS,
}
"""Quantity -> its default channel normalisation."""

MPM_CHANNELS = ("E", "density", "nu")
"""The MPM head's continuous channels, in order (log10 E, log10 ρ, ν)."""
LBS_CHANNELS = ("E", "nu")
"""The LBS material head's channels, in order (log10 E, ν)."""


def normalisation_to_dict(norms: dict[str, ChannelNorm]) -> dict:
    return {k: v.to_dict() for k, v in norms.items()}


def normalisation_from_dict(d: dict) -> dict[str, ChannelNorm]:
    out = dict(DEFAULT_NORMALISATION)
    out.update({k: ChannelNorm.from_dict(v) for k, v in d.items()})
    return out


def fitted_norm(base: ChannelNorm, values: np.ndarray) -> ChannelNorm:
    """``base`` with centre and scale fitted to observed physical ``values`` (mean and std of f(values)).

    Used by ``unipixie train`` (unless ``--fixed-normalisation``) for the quantities whose ranges come
    from the dataset's fits (spring stiffness and softness, LBS parameters).  A degenerate spread keeps the base scale.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    v = v[np.isfinite(v)]
    if base.log10:
        v = np.log10(v[v > 0])
    if v.size == 0:
        return base
    centre = float(v.mean())
    spread = float(v.std())
    scale = spread if spread > 1e-6 else base.scale
    return ChannelNorm(base.name, base.quantity, base.unit, base.log10, centre, scale, base.lower, base.upper)
