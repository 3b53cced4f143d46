"""The appearance extractor: per-pixel surface appearance read from the render passes of the views.

No weights, no network: what a renderer shows of each surface point, from the G-buffer Cycles writes with
the views (:mod:`.blender_io.render_passes`, :attr:`.types.Views.passes`):

=========  ==========================================  ==========  =========
channels   what                                         centre      scale
=========  ==========================================  ==========  =========
0–2        base colour, scene-linear RGB (0–1)          0.5         0.2887
3          roughness (0–1)                              0.5         0.2887
4          metallic (0–1)                               0.5         0.2887
5–7        surface normal, normalised-cube axes         0           0.5774
=========  ==========================================  ==========  =========

Every channel is standardised by a *fixed* centre and scale (:data:`CHANNEL_CENTRE`, :data:`CHANNEL_SCALE`:
a quantity uniformly distributed over its range — [0, 1] for the first five, a component of a direction
uniform on the sphere for the normal — gets mean 0 and standard deviation 1); nothing is estimated from the
object or a dataset.  The normal is in the normalised cube's frame (world axes of the object, not the
camera's), so it does not depend on the camera rig; the cube has no rotation, so this is also the object's
world frame.

The maps are full resolution (one value per pixel), so :func:`.lift.lift_features` samples them at the
voxels' projections with pixel accuracy — at the surface point half a voxel outwards of each voxel centre
(:data:`.lift.SURFACE_SAMPLE_OFFSET`; the ViT part of ``appearance+vit`` too), which keeps a part boundary
within about one voxel (the centre's own projection smears it by up to half a voxel times tan θ).  Pixels without a value (background, silhouette pixels less than
half covered) take the value of the nearest pixel that has one, so bilinear taps at a silhouette do not mix
in the background.

:data:`APPEARANCE_FEATURE_MODEL` (D = 8) is these channels alone; :data:`APPEARANCE_VIT_FEATURE_MODEL`
(D = 8 + 32) concatenates the offline untrained ViT's patch features (:mod:`.clip_features`; not CLIP) after
them.  Neither reads anything but the rendered passes and images: no labels, part ids or annotations.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .clip_features import OFFLINE_FEATURE_MODEL
from .errors import UserError

APPEARANCE_VERSION = 1
"""Bumped when what the appearance channels mean or how they are scaled changes (part of names and cache keys)."""
APPEARANCE_FEATURE_MODEL = f"appearance-gbuffer-v{APPEARANCE_VERSION}"
"""Feature-model name of the appearance channels alone (recorded in grids and checkpoints)."""
APPEARANCE_VIT_FEATURE_MODEL = f"{APPEARANCE_FEATURE_MODEL}+{OFFLINE_FEATURE_MODEL}"
"""Feature-model name of the appearance channels followed by the offline ViT's patch features."""

CHANNELS = ("base_r", "base_g", "base_b", "roughness", "metallic", "normal_x", "normal_y", "normal_z")
"""The appearance channels in order (D = 8)."""
_PASS_ORDER = ("base_color", "roughness", "metallic", "normal")
"""The render passes the channels come from, in order (3 + 1 + 1 + 3 channels)."""
_UNIFORM_01_STD = float(np.sqrt(1.0 / 12.0))
_SPHERE_COMPONENT_STD = float(np.sqrt(1.0 / 3.0))
CHANNEL_CENTRE = np.array([0.5] * 5 + [0.0] * 3, dtype=np.float32)
"""Fixed centre subtracted from each channel (see module docstring)."""
CHANNEL_SCALE = np.array([_UNIFORM_01_STD] * 5 + [_SPHERE_COMPONENT_STD] * 3, dtype=np.float32)
"""Fixed scale each centred channel is divided by: the standard deviation of a uniform quantity over the range."""


def appearance_identity(with_vit: bool = False) -> dict:
    """What determines the appearance features (for cache keys): name, version, channels and scaling,
    and the offline ViT's identity when concatenated."""
    from .clip_features import offline_identity
    from .lift import SURFACE_SAMPLE_OFFSET

    identity = {"model": APPEARANCE_VIT_FEATURE_MODEL if with_vit else APPEARANCE_FEATURE_MODEL,
                "appearance": {"version": APPEARANCE_VERSION, "channels": list(CHANNELS),
                               "centre": CHANNEL_CENTRE.tolist(), "scale": CHANNEL_SCALE.tolist(),
                               "sample_offset_voxels": SURFACE_SAMPLE_OFFSET}}
    if with_vit:
        identity["vit"] = offline_identity()
    return identity


def standardised_channels(views) -> np.ndarray:
    """(V, H, W, 8) float32: the views' render passes as standardised appearance channels, pixels without a
    value (NaN: background) filled from the nearest pixel with one.  Raises :class:`UserError` when the views
    have no passes."""
    from scipy import ndimage

    missing = [p for p in _PASS_ORDER if p not in views.passes]
    if missing:
        raise UserError(f"the appearance features need the views' render passes ({', '.join(missing)} missing): "
                        "render with Cycles and passes on (features from views saved without them cannot be made; "
                        "render again)")
    raw = np.concatenate([views.passes[p] for p in _PASS_ORDER], axis=-1).astype(np.float32)   # (V, H, W, 8)
    out = (raw - CHANNEL_CENTRE) / CHANNEL_SCALE
    for v in range(views.count):
        background = ~np.all(np.isfinite(out[v]), axis=-1)
        if background.all():
            out[v] = 0.0
            continue
        if not background.any():
            continue
        _, (ri, ci) = ndimage.distance_transform_edt(background, return_distances=True, return_indices=True)
        out[v] = out[v][ri, ci]
    return out


@dataclass
class AppearanceExtractor:
    """Per-pixel appearance channels from the views' render passes (module docstring), optionally followed by
    the offline ViT's patch features.

    name: the feature-model name recorded in grids.  vit: the offline ViT (``None`` for the channels alone).
    device: torch device of the maps.  identity: what determines the features (cache keys).
    """

    name: str
    vit: Optional[object] = None
    device: str = "cpu"
    identity: dict = field(default_factory=dict)
    is_clip: bool = False
    needs_passes: bool = True
    sample_offset_voxels: float = 0.0

    @property
    def dim(self) -> int:
        return len(CHANNELS) + (int(self.vit.dim) if self.vit is not None else 0)

    def maps(self, views) -> list:
        """The feature maps of ``views`` for :func:`.lift.lift_features`: ``[(V, H, W, 8)]`` at full
        resolution, followed by the ViT's ``(V, 14, 14, 32)`` token grid when concatenated (torch tensors)."""
        import torch

        out = [torch.from_numpy(standardised_channels(views)).to(self.device)]
        if self.vit is not None:
            out.append(self.vit(views.images))
        return out

    def __call__(self, images, *args, **kwargs):
        raise UserError(f"{self.name} features are made from the views' render passes, not from images alone; "
                        "use features_from_views(views, ...)")


def appearance_extractor(with_vit: bool = False, device: str = "cpu") -> AppearanceExtractor:
    """The appearance extractor (``with_vit``: followed by the offline ViT's features)."""
    from .clip_features import _device, offline_extractor

    device = _device(device)
    vit = offline_extractor(device=device) if with_vit else None
    from .lift import SURFACE_SAMPLE_OFFSET

    identity = appearance_identity(with_vit)
    return AppearanceExtractor(name=identity["model"], vit=vit, device=device, identity=identity,
                               sample_offset_voxels=SURFACE_SAMPLE_OFFSET)
