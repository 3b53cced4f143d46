"""What the pipeline's steps run with: :class:`PipelineSettings`, the devices, and the preference checks.

:class:`PipelineSettings` holds the views, the feature model, the checkpoint, the α sweep, the seed and the
device, and says which inputs each step depends on (recorded, compared for staleness by :mod:`.states`);
:func:`check_settings` and :func:`extractor_summary` turn the add-on's preferences (or the equivalent
command-line choices) into one message per problem.  May use :mod:`.checkpoint`, the feature options of
:mod:`unipixie.core.features` and the model's configuration.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Optional

import numpy as np

from ...solvers.registry import SOLVER_NAMES
from ..errors import UserError
from ..features import DEFAULT_RESOLUTION, DEFAULT_SAMPLES, DEFAULT_VIEW_COUNT, FeatureOptions
from .checkpoint import (checkpoint_feature_model, checkpoint_identity, feature_model_name, model_feature_model,
                         resolve_checkpoint)

DEFAULT_HEADS = SOLVER_NAMES
"""Heads the panel's Predict runs (every solver can then be baked from the sweep)."""


def cuda_available() -> bool:
    """Whether torch sees a CUDA GPU (the model's and, through Warp, the solvers' GPU path)."""
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def cuda_device_count() -> int:
    """Number of CUDA GPUs the NVIDIA driver reports, without importing torch or Warp (a quick probe for
    the panel's device choice; 0 when there is no driver or it fails)."""
    import ctypes
    import sys

    names = ("nvcuda.dll",) if sys.platform == "win32" else ("libcuda.so.1", "libcuda.so", "libcuda.dylib")
    for name in names:
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        try:
            if lib.cuInit(0) != 0:
                return 0
            count = ctypes.c_int(0)
            return int(count.value) if lib.cuDeviceGetCount(ctypes.byref(count)) == 0 else 0
        except (AttributeError, OSError):
            return 0
    return 0


def precision_of(device: str) -> str:
    """The model's precision on a device: bf16 on CUDA, fp32 on the CPU (as :class:`Predictor` chooses)."""
    return "bf16" if str(device).startswith("cuda") else "fp32"


@dataclass
class PipelineSettings:
    """How the steps run.

    view_count / resolution / engine / samples / render_device: the views (see ``core.features``).
    clip_weights: local OpenCLIP weights (file or folder) for a model trained on CLIP features; empty:
        ``$UNIPIXIE_CLIP_WEIGHTS`` or the default weights folder (``unipixie weights fetch`` fills it).
    checkpoint: the model (directory or its model.safetensors); empty: the shipped ``models/default``.
    The feature model Features extracts with is the one the checkpoint was trained on
    (:meth:`resolved_extractor`).
    sweep_count: α values of the Predict sweep (``None``: the model's default, 11).
    alphas: predict at exactly these α values instead of the sweep (what bakes at those α need: the
        command line's and the demo's prediction); ``None``: the sweep.
    seed: the model's noise seed.  steps: Heun steps (``None``: the model's default, 15).
    heads: model heads Predict runs.  device: ``cpu`` / ``cuda`` (model, features, solvers).
    """

    view_count: int = DEFAULT_VIEW_COUNT
    resolution: int = DEFAULT_RESOLUTION
    engine: str = "cycles"
    samples: int = DEFAULT_SAMPLES
    render_device: str = "auto"
    clip_weights: str = ""
    checkpoint: str = ""
    sweep_count: Optional[int] = None
    seed: int = 0
    steps: Optional[int] = None
    heads: tuple = DEFAULT_HEADS
    device: str = "cpu"
    alphas: Optional[tuple] = None

    def __post_init__(self):
        from ..model.config import HEADS

        self.view_count = int(self.view_count)
        if self.view_count < 1:
            raise UserError(f"the view count must be at least 1, got {self.view_count}")
        self.heads = tuple(self.heads)
        unknown = [h for h in self.heads if h not in HEADS]
        if unknown or not self.heads:
            raise UserError(f"unknown model head(s) {unknown}; choose from {', '.join(HEADS)}")
        if self.sweep_count is not None and int(self.sweep_count) < 2:
            raise UserError(f"an α sweep needs at least 2 values, got {self.sweep_count}")
        self.clip_weights = str(self.clip_weights or "")
        self.checkpoint = str(self.checkpoint or "")
        if self.alphas is not None:
            try:
                values = sorted({round(float(a), 6) for a in self.alphas})
            except (TypeError, ValueError):
                raise UserError(f"α values must be numbers in [0, 1], got {self.alphas!r}") from None
            if not values or not all(0.0 <= a <= 1.0 for a in values):
                raise UserError(f"α values must be numbers in [0, 1], got {self.alphas!r}")
            self.alphas = tuple(values)

    # -- the steps' options ----------------------------------------------------------------
    def resolved_extractor(self) -> str:
        """The feature model Features extracts with: the one the checkpoint was trained on (its
        ``feature_recipe.json``'s ``extractor``, else its config's ``feature_model``), so the model always sees
        the features it was trained on.  Without an installed checkpoint: CLIP ViT-B-16 when CLIP weights are
        set, else the offline extractor (``offline-random-vit-w32``, not CLIP).  A model trained on the
        appearance features (``appearance-gbuffer-v1``, alone or with the offline ViT) gets them, rendered with
        Cycles' passes."""
        try:
            ckpt = resolve_checkpoint(self.checkpoint)
        except UserError:
            return feature_model_name(self.clip_weights)
        return model_feature_model(ckpt)

    def feature_options(self) -> FeatureOptions:
        from .. import clip_features as cf
        from .. import extractors

        extractor = self.resolved_extractor()
        name = extractors.name_of(extractor)
        return FeatureOptions(view_count=self.view_count, resolution=self.resolution, engine=self.engine,
                              samples=self.samples, render_device=self.render_device, offline=name == "offline",
                              extractor=name, clip_weights=self.clip_weights or None,
                              clip_model=extractor if name == "clip" else cf.CLIP_MODEL, device=self.device)

    def resolved_sweep_count(self) -> int:
        from ..model.inference import DEFAULT_SWEEP_COUNT

        return int(self.sweep_count or DEFAULT_SWEEP_COUNT)

    def resolved_steps(self) -> int:
        from ..model.inference import DEFAULT_STEPS

        return int(self.steps or DEFAULT_STEPS)

    def resolved_alphas(self) -> np.ndarray:
        """(A,) float64 ascending: the α values Predict runs at (``alphas``, else the evenly spaced sweep)."""
        from ..model.sweep import sweep_alphas

        if self.alphas is not None:
            return np.asarray(self.alphas, dtype=np.float64)
        return sweep_alphas(self.resolved_sweep_count())

    # -- the inputs each step depends on (recorded, compared for staleness) ------------------------
    def render_inputs(self, fingerprint: str) -> dict:
        return {"fingerprint": fingerprint, "view_count": self.view_count, "resolution": int(self.resolution),
                "engine": str(self.engine).lower(), "samples": int(self.samples)}

    def feature_inputs(self, fingerprint: str) -> dict:
        from ..features import extractor_identity

        return {**self.render_inputs(fingerprint), "extractor": extractor_identity(self.feature_options())}

    def predict_inputs(self, grid_path) -> dict:
        """What a sweep depends on.  The heads are not part of it: a sweep without a solver's head is not
        wrong, a bake with that solver predicts the head exactly at its α (:func:`exact_prediction`)."""
        from ..model.inference import DEFAULT_TEMPERATURE

        ckpt = resolve_checkpoint(self.checkpoint)
        inputs = {"grid": Path(grid_path).name, "checkpoint": checkpoint_identity(ckpt)}
        if self.alphas is None:
            inputs["count"] = self.resolved_sweep_count()
        else:
            inputs["alphas"] = list(self.alphas)
        inputs.update({"seed": int(self.seed), "steps": self.resolved_steps(), "temperature": DEFAULT_TEMPERATURE,
                       "precision": precision_of(self.device)})
        return inputs

    def to_dict(self) -> dict:
        return asdict(self)

    def with_model_recipe(self) -> "PipelineSettings":
        """These settings with the views rendered as the model's training objects were (engine, view count,
        resolution, samples from the checkpoint's ``feature_recipe.json``), so the model sees features from
        its training distribution.  Unchanged when the checkpoint has no recipe or is not installed."""
        from ..model.checkpoint import read_feature_recipe

        try:
            ckpt = resolve_checkpoint(self.checkpoint)
        except UserError:
            return self
        recipe = read_feature_recipe(ckpt)
        if recipe is None:
            return self
        return replace(self, engine=recipe["engine"], view_count=recipe["view_count"],
                       resolution=recipe["resolution"], samples=recipe["samples"])


def check_settings(checkpoint: str = "", clip_weights: str = "", cache_dir: str = "", device: str = "cpu",
                   view_count: int = DEFAULT_VIEW_COUNT) -> list[str]:
    """Problems with the add-on preferences (or the equivalent command-line choices), one message each
    naming the preference and the remedy; empty when everything is usable."""
    import os

    from .. import clip_features as cf
    from .. import extractors

    problems = []
    try:
        ckpt = resolve_checkpoint(checkpoint)
    except UserError as exc:
        problems.append(f"Model checkpoint: {exc}")
    else:
        try:
            trained_on, width = checkpoint_feature_model(ckpt)
        except UserError as exc:
            problems.append(f"Model checkpoint: {exc}")
        else:
            try:
                extracting = model_feature_model(ckpt)    # Features extracts what the model was trained on
            except UserError as exc:
                problems.append(f"Model checkpoint: {exc}")
                extracting = trained_on
            if not extractors.needs_weights(extracting):
                if clip_weights:
                    problems.append(f"Model checkpoint: it was trained on {trained_on!r} features (D = {width}), which "
                                    "need no CLIP weights, so the 'CLIP weights' set are not used; clear 'CLIP weights' "
                                    "(or choose a checkpoint trained on CLIP features)")
            elif not clip_weights:
                try:
                    cf.resolve_clip_weights(None, model=extracting)
                except UserError:
                    problems.append(f"CLIP weights: the model was trained on {extracting!r} features (D = {width}) and "
                                    f"no {extracting} weights were found in {cf.default_weights_dir(extracting)}; "
                                    "fetch them ('Fetch CLIP weights' below, or 'unipixie weights fetch') or set "
                                    "'CLIP weights' to a local copy")
    if clip_weights:
        try:
            cf.resolve_clip_weights(clip_weights)
        except UserError as exc:
            problems.append(f"CLIP weights: {exc}")
    if cache_dir:
        d = Path(str(cache_dir)).expanduser()
        if d.exists() and not d.is_dir():
            problems.append(f"Cache directory: {d} is a file, not a directory; choose a folder")
        elif d.exists() and not os.access(d, os.W_OK):
            problems.append(f"Cache directory: {d} is not writable; choose a folder you can write to")
        elif not d.exists():
            parent = next((p for p in d.parents if p.exists()), None)
            if parent is None or not os.access(parent, os.W_OK):
                problems.append(f"Cache directory: {d} does not exist and cannot be created; choose a writable folder")
    if str(device).startswith("cuda") and not cuda_available():
        problems.append("Device: CUDA is selected but no CUDA GPU is available (torch sees none); choose CPU")
    if int(view_count) < MIN_USEFUL_VIEWS:
        problems.append(f"Default views: {int(view_count)} views leave parts of most objects unseen (their features "
                        f"are copied from the nearest seen voxel); use at least {MIN_USEFUL_VIEWS} "
                        f"({DEFAULT_VIEW_COUNT} recommended)")
    return problems


def extractor_summary(checkpoint: str = "", clip_weights: str = "") -> tuple[str, str]:
    """What the Features step extracts for a model, for the panel: ``(text, fetch)`` where ``text`` says which
    extractor the model expects and whether its weights are there, and ``fetch`` is the CLIP feature model whose
    weights are missing and can be fetched (``""`` when nothing is to fetch)."""
    from .. import clip_features as cf
    from .. import extractors

    try:
        ckpt = resolve_checkpoint(checkpoint)
        name = model_feature_model(ckpt)
        _, width = checkpoint_feature_model(ckpt)
    except UserError as exc:
        return f"model: {exc}", ""
    if name == cf.OFFLINE_FEATURE_MODEL:
        return f"{ckpt.name} expects {name} features (D = {width}): the offline ViT, no weights needed, not CLIP", ""
    if not extractors.needs_weights(name):
        return f"{ckpt.name} expects {name} features (D = {width}): {extractors.description(name)}, no weights needed", ""
    try:
        where = cf.resolve_clip_weights(clip_weights or None, model=name)
    except UserError:
        fetch = name if (not clip_weights and name in cf.OPENCLIP_PRETRAINED) else ""
        return f"{ckpt.name} expects {name} CLIP features (D = {width}); weights missing", fetch
    return f"{ckpt.name} expects {name} CLIP features (D = {width}); weights: {where}", ""


MIN_USEFUL_VIEWS = 8
"""Fewer rendered views than this leave much of an object's surface unseen (a preference warning)."""
