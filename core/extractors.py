"""The feature extractors by name — the one registry the command line, the pipeline, the dataset builder and the
add-on choose from.

========================  ==========================================  ====  ========  =================
``--extractor``            feature model (recorded in grids)            D     weights   render passes
========================  ==========================================  ====  ========  =================
``clip``                   ``ViT-B-16`` (CLIP, the paper's)             768   local     no
``offline``                ``offline-random-vit-w32`` (untrained ViT)   32    none      no
``appearance``             ``appearance-gbuffer-v1``                    8     none      Cycles
``appearance+vit``         ``appearance-gbuffer-v1+offline-…-w32``      40    none      Cycles
========================  ==========================================  ====  ========  =================

(:mod:`.clip_features`, :mod:`.appearance_features`.)
"""

from __future__ import annotations

import os
from typing import Optional

from .errors import UserError

EXTRACTORS = {
    "clip": ("CLIP", "CLIP ViT patch features (pretrained weights from a local file)"),
    "offline": ("offline random ViT, not CLIP", "offline random ViT features (not CLIP)"),
    "appearance": ("render-pass appearance, no network, not CLIP",
                   "render-pass appearance features: base colour, roughness, metallic, normal (not CLIP)"),
    "appearance+vit": ("render-pass appearance + offline random ViT, not CLIP",
                       "render-pass appearance features + offline random ViT features (not CLIP)"),
}
"""Extractor name -> (short label, one-line description): what the panel, the command line and reports say
the features are."""
NEEDS_PASSES = ("appearance", "appearance+vit")
"""Extractors that read the views' render passes (Cycles only)."""
PASSES_NEED_CYCLES = ("the appearance features read Cycles' render passes (base colour, roughness, metallic, normal), "
                      "which Workbench does not render; use the Cycles engine (--engine cycles)")
"""The refusal when an appearance extractor is asked for with another engine."""


def check_name(name: str) -> str:
    """``name`` lower-cased when it is a known extractor, else a one-line :class:`UserError`."""
    n = str(name or "").strip().lower()
    if n not in EXTRACTORS:
        raise UserError(f"unknown feature extractor {name!r}; choose one of {', '.join(EXTRACTORS)}")
    return n


def feature_model(name: str, clip_model: Optional[str] = None) -> str:
    """The feature-model name extractor ``name`` records in feature grids (``clip_model`` for ``clip``)."""
    from . import appearance_features as af
    from . import clip_features as cf

    return {"clip": clip_model or cf.CLIP_MODEL, "offline": cf.OFFLINE_FEATURE_MODEL,
            "appearance": af.APPEARANCE_FEATURE_MODEL,
            "appearance+vit": af.APPEARANCE_VIT_FEATURE_MODEL}[check_name(name)]


def name_of(feature_model_name: str) -> str:
    """The extractor that makes features named ``feature_model_name``: one of :data:`EXTRACTORS`; any other
    name is a CLIP architecture (``clip``)."""
    for name in ("offline", "appearance", "appearance+vit"):
        if feature_model_name == feature_model(name):
            return name
    return "clip"


def needs_weights(feature_model_name: str) -> bool:
    """Whether features named ``feature_model_name`` need downloaded weights (only CLIP's do)."""
    return name_of(feature_model_name) == "clip"


def label(feature_model_name: str) -> str:
    """``"<feature model> (<short label>)"`` for messages; a CLIP model by its name alone."""
    name = name_of(feature_model_name)
    if name == "clip":
        return feature_model_name
    return f"{feature_model_name} ({EXTRACTORS[name][0]})"


def description(feature_model_name: str) -> str:
    """One line saying what features named ``feature_model_name`` are (the panel's note)."""
    return EXTRACTORS[name_of(feature_model_name)][1]


def identity(name: str, clip_weights: Optional[str | os.PathLike] = None, clip_model: Optional[str] = None) -> dict:
    """What determines extractor ``name``'s features, without loading anything (for cache keys)."""
    from . import appearance_features as af
    from . import clip_features as cf

    name = check_name(name)
    if name == "offline":
        return cf.offline_identity()
    if name in NEEDS_PASSES:
        return af.appearance_identity(with_vit=name == "appearance+vit")
    return cf.clip_identity(clip_weights, clip_model or cf.CLIP_MODEL)


def make(name: str, clip_weights: Optional[str | os.PathLike] = None, device: str = "cpu",
         clip_model: Optional[str] = None):
    """Extractor ``name`` (CLIP and the offline ViT are loaded once per process, :func:`.clip_features.make_extractor`)."""
    from . import appearance_features as af
    from . import clip_features as cf

    name = check_name(name)
    if name in NEEDS_PASSES:
        return af.appearance_extractor(with_vit=name == "appearance+vit", device=device)
    return cf.make_extractor(offline=name == "offline", clip_weights=clip_weights, device=device,
                             model=clip_model or cf.CLIP_MODEL)


def feature_maps(extractor, views):
    """The maps ``extractor`` makes of ``views`` for :func:`.lift.lift_features`: a CLIP / offline ViT reads the
    images, the appearance extractors the render passes (their ``maps(views)``)."""
    if getattr(extractor, "needs_passes", False):
        return extractor.maps(views)
    return extractor(views.images)
