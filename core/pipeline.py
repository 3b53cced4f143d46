"""The object pipeline: Render views → Features → Predict → Simulate & bake, with per-object state.

One pipeline for the panel, the command line and the demo.  This module is the Blender-free part:

* :class:`PipelineSettings` — what the steps are run with (views, feature model, checkpoint, α sweep,
  seed, device).  :func:`resolve_checkpoint` / :func:`check_settings` turn a missing model, missing
  CLIP weights, an unwritable cache or an unavailable GPU into one clear message each.
* The per-object **record** (``unipixie.pipeline/1``, JSON; the Blender side keeps it in the object's
  ID property :data:`RECORD_KEY`, so it is saved with the .blend and follows undo): for each step the
  *inputs* it was run with and the cached files it produced.  The files themselves live in the cache,
  content-addressed, so reopening a .blend — or running a step again with the same inputs — finds them.
* :func:`step_states` — compares the recorded inputs with the current ones: each step is
  ``not done``, ``done``, ``stale`` (with the reason: "the mesh, its modifiers or materials changed",
  "α changed", ...) or ``running``.  Staleness flows downstream (stale features make the prediction
  stale, which makes a model-driven bake stale).
* :func:`predict_job` / :func:`refine_job` — the α sweep (K α values in one batched pass, cached) and
  the exact prediction at one α, each run in a worker thread as a job generator of
  ``(fraction, status)`` (Esc cancels).
* :func:`model_material` — the material a bake uses at α ("model" material source of
  :mod:`unipixie.core.bake`, registered with :func:`~unipixie.core.bake.register_material_predictor`):
  the sweep's own values when α is one of its α values, else an exact prediction at α (cached).
  The interpolated sweep is for the viewport only.
* :class:`FieldColourScale` and :func:`voxel_surface` — the material-field display: log E mapped
  through one colour map over the whole sweep's range (so moving α visibly shifts the colours),
  shared by the viewport (:mod:`unipixie.core.blender_io.field_view`) and the demo's pictures.

The Blender side (reading objects, fingerprints, running the steps on objects) is
:mod:`unipixie.core.blender_io.pipeline`.
"""

from __future__ import annotations

import json
import threading
from dataclasses import replace, asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Optional

import numpy as np

from ..solvers.registry import SOLVER_NAMES
from .errors import UserError
from .features import DEFAULT_RESOLUTION, DEFAULT_SAMPLES, DEFAULT_VIEW_COUNT, FeatureOptions

# --------------------------------------------------------------------------- steps and states
STEPS = ("render", "features", "predict", "bake")
"""The panel's steps, in order."""
STEP_LABELS = {"render": "Render views", "features": "Features", "predict": "Predict", "bake": "Simulate & bake"}

NOT_DONE = "not done"
DONE = "done"
STALE = "stale"
RUNNING = "running"
STATES = (NOT_DONE, DONE, STALE, RUNNING)

RECORD_KEY = "unipixie_pipeline"
"""ID property on an object holding its pipeline record (JSON)."""
RECORD_FORMAT = "unipixie.pipeline/1"

CHANGE_REASONS = {
    "fingerprint": "the mesh, its modifiers or materials changed",
    "view_count": "the number of views changed",
    "resolution": "the render resolution changed",
    "engine": "the render engine changed",
    "samples": "the render samples changed",
    "extractor": "the feature model changed (CLIP weights preference)",
    "grid": "the features changed",
    "checkpoint": "the model checkpoint changed",
    "count": "the number of α values of the sweep changed",
    "alphas": "the α values of the prediction changed",
    "seed": "the seed changed",
    "steps": "the number of inference steps changed",
    "precision": "the device changed (the model runs in bf16 on CUDA)",
    "solver": "the solver changed",
    "frames": "the frame range changed",
    "fps": "the frame rate changed",
    "alpha": "α changed",
    "material_source": "the material source changed",
    "effects": "the effects changed",
    "sweep": "the prediction changed",
}
"""Why a step is stale, by the input that differs."""

DEFAULT_HEADS = SOLVER_NAMES
"""Heads the panel's Predict runs (every solver can then be baked from the sweep)."""


@dataclass
class StepState:
    """The state of one step: one of :data:`STATES`, and why (for stale steps, missing files)."""

    state: str = NOT_DONE
    reason: str = ""

    def label(self) -> str:
        return f"{self.state}: {self.reason}" if self.reason else self.state


def input_changes(recorded: Optional[dict], current: Optional[dict]) -> list[str]:
    """Keys whose values differ between two input dicts (JSON-normalised), in ``current``'s order."""
    a = json.loads(json.dumps(recorded or {}, sort_keys=True, default=str))
    b = json.loads(json.dumps(current or {}, sort_keys=True, default=str))
    keys = list(b) + [k for k in a if k not in b]
    return [k for k in keys if a.get(k) != b.get(k)]


def _reason(changes: list[str]) -> str:
    seen = []
    for k in changes:
        r = CHANGE_REASONS.get(k, f"{k} changed")
        if r not in seen:
            seen.append(r)
    return "; ".join(seen)


# --------------------------------------------------------------------------- the record
@dataclass
class PipelineRecord:
    """What the pipeline produced for one object: ``steps[step] = {"inputs": {...}, <files and facts>}``.

    render: ``views`` (npz), ``sheet`` (png), ``count``.  features: ``grid`` (npz), ``slices`` (png),
    ``feature_model``, ``voxels``.  predict: ``sweep`` (npz), ``checkpoint``, ``heads``, ``seconds``.
    bake: ``fingerprint`` and ``sweep`` the bake was made from (the bake's own record, written by
    :mod:`unipixie.core.blender_io.bake`, holds the rest).
    """

    steps: dict = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps({"format": RECORD_FORMAT, "steps": self.steps}, sort_keys=True, default=str)

    @classmethod
    def from_json(cls, text) -> "PipelineRecord":
        """Parse a record; an absent, unreadable or foreign value gives an empty record (nothing done)."""
        if not text:
            return cls()
        try:
            d = json.loads(str(text))
        except (TypeError, ValueError):
            return cls()
        if not isinstance(d, dict) or d.get("format") != RECORD_FORMAT or not isinstance(d.get("steps"), dict):
            return cls()
        return cls({k: v for k, v in d["steps"].items() if k in STEPS and isinstance(v, dict)})

    def get(self, step: str) -> Optional[dict]:
        return self.steps.get(step)

    def set(self, step: str, entry: Optional[dict]) -> None:
        if step not in STEPS:
            raise ValueError(f"unknown step {step!r}")
        if entry is None:
            self.steps.pop(step, None)
        else:
            self.steps[step] = entry

    def file(self, step: str, key: str) -> Optional[Path]:
        """A recorded file of a step if it still exists."""
        e = self.steps.get(step) or {}
        p = e.get(key)
        return Path(p) if p and Path(p).is_file() else None


# --------------------------------------------------------------------------- settings
def default_checkpoint() -> Path:
    """Where the shipped model lives (``models/default/`` of the package)."""
    from .model.inference import DEFAULT_CHECKPOINT

    return Path(DEFAULT_CHECKPOINT)


def resolve_checkpoint(checkpoint=None) -> Path:
    """The checkpoint directory to use: ``checkpoint`` (a directory, or its ``model.safetensors`` /
    ``config.json``) or, when empty, the shipped default model.  Raises :class:`UserError` saying what
    is missing and what to do."""
    from .model.checkpoint import CONFIG_FILE, MODEL_FILE, is_checkpoint

    if not checkpoint:
        d = default_checkpoint()
        if not is_checkpoint(d):
            raise UserError(f"the default model is not installed: {d} has no {MODEL_FILE} + {CONFIG_FILE}. "
                            "Put the shipped model there, or choose a checkpoint directory made by 'unipixie train' "
                            "(add-on preferences > Model checkpoint, or --checkpoint DIR)")
        return d
    p = Path(str(checkpoint)).expanduser()
    if p.is_file() and p.name in (MODEL_FILE, CONFIG_FILE):
        p = p.parent
    if not p.exists():
        raise UserError(f"model checkpoint {p} does not exist; choose a checkpoint directory made by 'unipixie train'")
    if not is_checkpoint(p):
        raise UserError(f"{p} is not a UniPixie checkpoint (it needs {CONFIG_FILE} and {MODEL_FILE}); choose the "
                        "directory 'unipixie train --out DIR' wrote")
    return p


def checkpoint_feature_model(checkpoint_dir: Path) -> tuple[str, int]:
    """(feature model name, feature width D) a checkpoint was trained on, read from its config.json."""
    from .model.checkpoint import CONFIG_FILE

    path = Path(checkpoint_dir) / CONFIG_FILE
    try:
        doc = json.loads(path.read_text())
        cfg = doc.get("config", doc)
        return str(cfg["feature_model"]), int(cfg["feature_dim"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{path}: not a readable model config ({exc})") from None


_FEATURE_MODELS: dict = {}


def model_feature_model(checkpoint_dir) -> str:
    """The feature model (extractor) a checkpoint expects: its ``feature_recipe.json``'s ``extractor`` when the
    recipe names one, else its config's ``feature_model`` (they must agree).  Memoised on the files' mtimes."""
    from .model.checkpoint import CONFIG_FILE, RECIPE_FILE, read_feature_recipe

    d = Path(checkpoint_dir).resolve()
    stamp = tuple(f.stat().st_mtime_ns if f.is_file() else 0 for f in (d / CONFIG_FILE, d / RECIPE_FILE))
    with _CKPT_LOCK:
        hit = _FEATURE_MODELS.get(str(d))
        if hit is not None and hit[0] == stamp:
            return hit[1]
    trained_on, _ = checkpoint_feature_model(d)
    recipe = read_feature_recipe(d) or {}
    named = recipe.get("extractor")
    if named and named != trained_on:
        raise UserError(f"{d / RECIPE_FILE} names the extractor {named!r} but {d / CONFIG_FILE} says the model was "
                        f"trained on {trained_on!r} features; the checkpoint is inconsistent (retrain or fix the recipe)")
    name = named or trained_on
    with _CKPT_LOCK:
        _FEATURE_MODELS[str(d)] = (stamp, name)
    return name


def feature_model_name(clip_weights: str = "") -> str:
    """The feature model the pipeline extracts with: CLIP ViT-B-16 when CLIP weights are set, else the
    offline extractor (``offline-random-vit-w32``, an untrained ViT: not CLIP)."""
    from . import clip_features as cf

    return cf.CLIP_MODEL if clip_weights else cf.OFFLINE_FEATURE_MODEL


_CKPT_KEYS: dict = {}
_CKPT_LOCK = threading.Lock()


def checkpoint_identity(checkpoint_dir: Path) -> str:
    """The content key of a checkpoint (hash of its weights and config), memoised on size and mtime."""
    from .model.checkpoint import CONFIG_FILE, MODEL_FILE, checkpoint_key

    d = Path(checkpoint_dir).resolve()
    stamp = tuple((f.stat().st_size, f.stat().st_mtime_ns) for f in (d / MODEL_FILE, d / CONFIG_FILE))
    with _CKPT_LOCK:
        hit = _CKPT_KEYS.get(str(d))
        if hit is not None and hit[0] == stamp:
            return hit[1]
    key = checkpoint_key(d)
    with _CKPT_LOCK:
        _CKPT_KEYS[str(d)] = (stamp, key)
    return key


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
        from .model.config import HEADS

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
        set, else the offline extractor (``offline-random-vit-w32``, not CLIP)."""
        try:
            ckpt = resolve_checkpoint(self.checkpoint)
        except UserError:
            return feature_model_name(self.clip_weights)
        return model_feature_model(ckpt)

    def feature_options(self) -> FeatureOptions:
        from . import clip_features as cf

        extractor = self.resolved_extractor()
        offline = extractor == cf.OFFLINE_FEATURE_MODEL
        return FeatureOptions(view_count=self.view_count, resolution=self.resolution, engine=self.engine,
                              samples=self.samples, render_device=self.render_device, offline=offline,
                              clip_weights=self.clip_weights or None, clip_model=cf.CLIP_MODEL if offline else extractor,
                              device=self.device)

    def resolved_sweep_count(self) -> int:
        from .model.inference import DEFAULT_SWEEP_COUNT

        return int(self.sweep_count or DEFAULT_SWEEP_COUNT)

    def resolved_steps(self) -> int:
        from .model.inference import DEFAULT_STEPS

        return int(self.steps or DEFAULT_STEPS)

    def resolved_alphas(self) -> np.ndarray:
        """(A,) float64 ascending: the α values Predict runs at (``alphas``, else the evenly spaced sweep)."""
        from .model.sweep import sweep_alphas

        if self.alphas is not None:
            return np.asarray(self.alphas, dtype=np.float64)
        return sweep_alphas(self.resolved_sweep_count())

    # -- the inputs each step depends on (recorded, compared for staleness) ------------------------
    def render_inputs(self, fingerprint: str) -> dict:
        return {"fingerprint": fingerprint, "view_count": self.view_count, "resolution": int(self.resolution),
                "engine": str(self.engine).lower(), "samples": int(self.samples)}

    def feature_inputs(self, fingerprint: str) -> dict:
        from .features import extractor_identity

        return {**self.render_inputs(fingerprint), "extractor": extractor_identity(self.feature_options())}

    def predict_inputs(self, grid_path) -> dict:
        """What a sweep depends on.  The heads are not part of it: a sweep without a solver's head is not
        wrong, a bake with that solver predicts the head exactly at its α (:func:`exact_prediction`)."""
        ckpt = resolve_checkpoint(self.checkpoint)
        inputs = {"grid": Path(grid_path).name, "checkpoint": checkpoint_identity(ckpt)}
        if self.alphas is None:
            inputs["count"] = self.resolved_sweep_count()
        else:
            inputs["alphas"] = list(self.alphas)
        inputs.update({"seed": int(self.seed), "steps": self.resolved_steps(), "precision": precision_of(self.device)})
        return inputs

    def to_dict(self) -> dict:
        return asdict(self)

    def with_model_recipe(self) -> "PipelineSettings":
        """These settings with the views rendered as the model's training objects were (engine, view count,
        resolution, samples from the checkpoint's ``feature_recipe.json``), so the model sees features from
        its training distribution.  Unchanged when the checkpoint has no recipe or is not installed."""
        from .model.checkpoint import read_feature_recipe

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

    from . import clip_features as cf

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
            if extracting == cf.OFFLINE_FEATURE_MODEL:
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
    from . import clip_features as cf

    try:
        ckpt = resolve_checkpoint(checkpoint)
        name = model_feature_model(ckpt)
        _, width = checkpoint_feature_model(ckpt)
    except UserError as exc:
        return f"model: {exc}", ""
    if name == cf.OFFLINE_FEATURE_MODEL:
        return f"{ckpt.name} expects {name} features (D = {width}): the offline ViT, no weights needed, not CLIP", ""
    try:
        where = cf.resolve_clip_weights(clip_weights or None, model=name)
    except UserError:
        fetch = name if (not clip_weights and name in cf.OPENCLIP_PRETRAINED) else ""
        return f"{ckpt.name} expects {name} CLIP features (D = {width}); weights missing", fetch
    return f"{ckpt.name} expects {name} CLIP features (D = {width}); weights: {where}", ""


MIN_USEFUL_VIEWS = 8
"""Fewer rendered views than this leave much of an object's surface unseen (a preference warning)."""


# --------------------------------------------------------------------------- states
@dataclass
class CurrentInputs:
    """What the steps would be run with now, for one object.

    fingerprint: the object's placement-invariant fingerprint (``None`` when it could not be read:
        ``error`` says why).  settings: the :class:`PipelineSettings`.
    bake_options: the bake's current inputs as the bake record stores them (``solver``, ``frames``,
        ``fps``, ``alpha``, ``material_source``, ``effects``), or ``None``.
    bake_record: the object's bake record (``core.blender_io.bake.bake_record``) or ``None``.
    running: the step being run now, if any.
    """

    fingerprint: Optional[str]
    settings: PipelineSettings
    bake_options: Optional[dict] = None
    bake_record: Optional[dict] = None
    running: str = ""
    error: str = ""


BAKE_COMPARED = ("solver", "frames", "fps", "alpha", "material_source", "effects")
"""Fields of the bake record compared with the current bake settings (α only for the model source)."""


def bake_inputs_of(record_or_options: dict) -> dict:
    """The compared bake inputs of a bake record or of the current settings (:data:`BAKE_COMPARED`)."""
    d = {k: record_or_options.get(k) for k in BAKE_COMPARED}
    src = d.get("material_source") or {}
    if not isinstance(src, dict) or src.get("source") != "model":
        d.pop("alpha")   # α changes nothing for a homogeneous or file material
    if d.get("frames") is not None:
        d["frames"] = [int(x) for x in d["frames"]]
    if d.get("fps") is not None:
        d["fps"] = round(float(d["fps"]), 6)
    if d.get("alpha") is not None:
        d["alpha"] = round(float(d["alpha"]), 6)
    return d


def step_states(record: PipelineRecord, current: CurrentInputs) -> dict:
    """The :class:`StepState` of every step of :data:`STEPS` (see the module docstring)."""
    out: dict = {}
    s = current.settings

    # render
    rec = record.get("render")
    if current.fingerprint is None:
        out["render"] = StepState(STALE if rec else NOT_DONE, current.error)
    elif not rec:
        out["render"] = StepState(NOT_DONE)
    elif record.file("render", "views") is None:
        out["render"] = StepState(NOT_DONE, "the rendered views are no longer in the cache")
    else:
        ch = input_changes(rec.get("inputs"), s.render_inputs(current.fingerprint))
        out["render"] = StepState(STALE, _reason(ch)) if ch else StepState(DONE)

    # features
    rec = record.get("features")
    if not rec:
        out["features"] = StepState(NOT_DONE)
    elif record.file("features", "grid") is None:
        out["features"] = StepState(NOT_DONE, "the feature grid is no longer in the cache")
    elif current.fingerprint is None:
        out["features"] = StepState(STALE, current.error)
    else:
        try:
            ch = input_changes(rec.get("inputs"), s.feature_inputs(current.fingerprint))
        except UserError as exc:
            out["features"] = StepState(STALE, str(exc))
        else:
            out["features"] = StepState(STALE, _reason(ch)) if ch else StepState(DONE)

    # predict
    rec = record.get("predict")
    if not rec:
        out["predict"] = StepState(NOT_DONE)
    elif record.file("predict", "sweep") is None:
        out["predict"] = StepState(NOT_DONE, "the α sweep is no longer in the cache")
    elif out["features"].state != DONE:
        out["predict"] = StepState(STALE, "the features are " + out["features"].state)
    else:
        try:
            recorded, current_inputs = dict(rec.get("inputs") or {}), s.predict_inputs(record.get("features")["grid"])
        except UserError as exc:
            out["predict"] = StepState(STALE, str(exc))
        else:
            note = ""
            if "alphas" in recorded or "alphas" in current_inputs:
                # a prediction made at the α values of bakes (command line, demo) is complete for them, and any
                # prediction serves a bake that asks for α values (bakes at other α predict exactly there): which
                # α values were predicted does not make it stale; the α slider shows the values there are
                for k in ("count", "alphas"):
                    recorded.pop(k, None)
                    current_inputs.pop(k, None)
            if "alphas" in (rec.get("inputs") or {}):
                note = (f"at α {', '.join(f'{float(a):g}' for a in rec['inputs']['alphas'])} only (for bakes); "
                        "Predict again for the α sweep")
            ch = input_changes(recorded, current_inputs)
            out["predict"] = StepState(STALE, _reason(ch)) if ch else StepState(DONE, note)

    # bake
    brec = current.bake_record
    if not brec:
        out["bake"] = StepState(NOT_DONE)
    else:
        changes = []
        if current.bake_options is not None:
            changes += input_changes(bake_inputs_of(brec), bake_inputs_of(current.bake_options))
        mine = record.get("bake") or {}
        if mine.get("fingerprint") and current.fingerprint and mine["fingerprint"] != current.fingerprint:
            changes.append("fingerprint")
        model = (brec.get("material_source") or {}).get("source") == "model"
        if model and mine.get("sweep") and (record.get("predict") or {}).get("sweep") != mine.get("sweep"):
            changes.append("sweep")
        if changes:
            out["bake"] = StepState(STALE, _reason(changes))
        elif model and out["predict"].state != DONE:
            out["bake"] = StepState(STALE, "the prediction is " + out["predict"].state)
        else:
            out["bake"] = StepState(DONE)

    if current.running in out:
        out[current.running] = StepState(RUNNING)
    return out


def first_pending(states: dict) -> Optional[str]:
    """The first step that is not done (what *Run all* starts with), or ``None``."""
    return next((k for k in STEPS if states[k].state != DONE), None)


# --------------------------------------------------------------------------- predict / refine jobs
def _background(work: Callable, description: str) -> Iterator[tuple[float, str]]:
    """Run ``work(progress)`` in a worker thread, yielding ``(fraction, status)``; closing cancels it."""
    from .bake import BackgroundRun

    run = BackgroundRun(work, description=description).start()
    try:
        while not run.wait(0.05):
            yield run.fraction, run.status or description
    finally:
        if not run.done:
            run.cancel(wait=True)
    return run.result()


def predict_job(grid_path, settings: PipelineSettings) -> Iterator[tuple[float, str]]:
    """Predict the α sweep for a feature grid (:func:`unipixie.core.model.predict_sweep`, cached on disk).

    A job generator; returns ``(AlphaSweep, sweep_path, inputs)`` where ``inputs`` is what the record
    keeps to tell when the sweep becomes stale.  The model is loaded (once per process) and run in a
    worker thread; closing the generator cancels it.
    """
    from .types import FeatureGrid

    grid_path = Path(grid_path)
    inputs = settings.predict_inputs(grid_path)           # a missing checkpoint fails here, before any work
    ckpt = resolve_checkpoint(settings.checkpoint)
    alphas = settings.resolved_alphas()
    yield 0.0, "loading the model"

    def work(progress):
        from .model.inference import get_predictor
        from .model.sweep import predict_sweep, sweep_cache_key
        from .paths import cache_dir

        predictor = get_predictor(ckpt, device=settings.device)
        grid = FeatureGrid.load(grid_path)
        key = sweep_cache_key(predictor, grid, alphas, settings.seed, settings.resolved_steps(), settings.heads)
        path = cache_dir("alpha_sweeps") / f"{key}.npz"
        cached = bool(predictor.key) and path.is_file()
        progress.set_status(f"predicting {len(alphas)} α value(s)")
        sweep = predict_sweep(predictor, grid, alphas=alphas, seed=settings.seed, heads=settings.heads,
                              steps=settings.resolved_steps(), progress=progress)
        if not path.is_file():       # a predictor without a content key: keep the sweep under ours
            path = cache_dir("alpha_sweeps") / f"pipeline-{_key('sweep', inputs, list(settings.heads))}.npz"
            _atomic_save(sweep, path)
        return sweep, path, cached

    sweep, path, cached = yield from _background(work, "predict")
    what = (f"α sweep of {len(sweep.alphas)} values" if settings.alphas is None
            else f"α {', '.join(f'{a:g}' for a in sweep.alphas)}")
    yield 1.0, f"{what} ({', '.join(sweep_heads(sweep))})" + (" from the cache" if cached else "")
    return sweep, path, inputs


def _key(*parts) -> str:
    from .paths import content_key

    return content_key(*parts)


def _atomic_save(sweep, path: Path) -> Path:
    return sweep.save(path)  # atomic (core/atomic_io.py), with a unique temporary name


# --------------------------------------------------------------------------- the model's material at α
@dataclass
class ModelPlan:
    """Where an object's model material comes from (set by the Blender side before a bake; read in the
    bake's worker thread, so it holds plain values only).

    grid / sweep: the feature grid and α-sweep files.  checkpoint: the checkpoint directory.
    seed / steps: the sweep's inference settings.  device: torch device for exact predictions.
    """

    grid: str
    sweep: str
    checkpoint: str
    seed: int = 0
    steps: int = 15
    device: str = "cpu"


_PLANS: dict = {}
_SWEEPS: dict = {}
_LOCK = threading.Lock()


def set_plan(object_name: str, plan: Optional[ModelPlan]) -> None:
    """Make ``plan`` the model material of the object named ``object_name`` (``None`` forgets it)."""
    with _LOCK:
        if plan is None:
            _PLANS.pop(object_name, None)
        else:
            _PLANS[object_name] = plan


def get_plan(object_name: str) -> Optional[ModelPlan]:
    with _LOCK:
        return _PLANS.get(object_name)


def load_sweep(path):
    """An :class:`~unipixie.core.model.sweep.AlphaSweep` from disk, kept in memory (keyed by path and mtime)."""
    from .model.sweep import AlphaSweep

    p = Path(path)
    try:
        stamp = p.stat().st_mtime_ns
    except OSError:
        raise UserError(f"the α sweep {p} is no longer in the cache; run Predict again") from None
    with _LOCK:
        hit = _SWEEPS.get(str(p))
        if hit is not None and hit[0] == stamp:
            return hit[1]
    sweep = AlphaSweep.load(p)
    with _LOCK:
        if len(_SWEEPS) > 16:
            _SWEEPS.clear()
        _SWEEPS[str(p)] = (stamp, sweep)
    return sweep


def sweep_heads(sweep) -> tuple:
    """The heads an α sweep holds."""
    heads = []
    if sweep.log10_E is not None:
        heads.append("mpm")
    if sweep.lbs_log10_E is not None:
        heads.append("lbs")
    if sweep.spring_log10_stiffness is not None:
        heads.append("spring_mass")
    return tuple(heads)


def prediction_from_sweep(sweep, alpha: float):
    """A one-α :class:`~unipixie.core.model.inference.Prediction` read from a sweep (exact at its own α
    values, interpolated between them)."""
    from .model.inference import Prediction

    a = float(alpha)
    return Prediction(alphas=np.array([a]),
                      mpm=[sweep.field_at(a)] if sweep.log10_E is not None else None,
                      lbs=[sweep.lbs_at(a)] if sweep.lbs_log10_E is not None else None,
                      spring_mass=[sweep.spring_at(a)] if sweep.spring_log10_stiffness is not None else None,
                      meta=dict(sweep.meta))


def refined_path(plan: ModelPlan, alpha: float, heads) -> Path:
    """Where the exact prediction at ``alpha`` for ``plan`` is cached."""
    from .paths import cache_dir

    return cache_dir("alpha_refined") / f"{_key('refined', Path(plan.sweep).stem, round(float(alpha), 6), sorted(heads))}.npz"


def exact_prediction(plan: ModelPlan, alpha: float, heads, progress=None, from_sweep: bool = True):
    """The model's exact prediction at ``alpha`` with at least ``heads``.

    Returns ``(Prediction, how, path)``: a one-α ``Prediction``; how it was obtained — ``"from the α
    sweep"`` (α is one of the sweep's values and the sweep has the heads), ``"refined"`` (a cached exact
    prediction) or ``"exact inference"`` (computed now and cached); and the file it came from.
    ``from_sweep=False`` skips the sweep (the panel's "refine" always keeps a file at its α).
    """
    from .model.sweep import AlphaSweep
    from .types import FeatureGrid

    alpha = float(alpha)
    if not 0.0 <= alpha <= 1.0:
        raise UserError(f"α must lie in [0, 1], got {alpha:g}")
    sweep = load_sweep(plan.sweep)
    heads = tuple(heads)
    have = sweep_heads(sweep)
    on_node = np.isclose(sweep.alphas, alpha, rtol=0.0, atol=1e-9)
    if from_sweep and on_node.any() and all(h in have for h in heads):
        node = float(sweep.alphas[int(np.argmax(on_node))])
        return prediction_from_sweep(sweep, node), "from the α sweep", Path(plan.sweep)
    want = tuple(h for h in SOLVER_NAMES if h in set(heads) | set(have))
    path = refined_path(plan, alpha, want)
    if path.is_file():
        try:
            return prediction_from_sweep(AlphaSweep.load(path), alpha), "refined", path
        except UserError:
            path.unlink(missing_ok=True)
    from .model.inference import get_predictor

    predictor = get_predictor(plan.checkpoint, device=plan.device)
    grid = FeatureGrid.load(plan.grid)
    pred = predictor.predict(grid, [alpha], heads=want, seed=plan.seed, steps=plan.steps, progress=progress)
    one = AlphaSweep.from_prediction(pred, grid)
    one.meta.update({"checkpoint": str(plan.checkpoint), "seconds": pred.seconds})
    _atomic_save(one, path)
    return pred, "exact inference", path


def refine_job(plan: ModelPlan, alpha: float, heads=()) -> Iterator[tuple[float, str]]:
    """The panel's "Refine at this α": exact inference at ``alpha`` with the sweep's heads (plus ``heads``),
    cached, as a job generator run in a worker thread; returns ``(Prediction, how, path)``."""
    yield 0.0, "loading the model"
    heads = tuple(set(heads) | set(sweep_heads(load_sweep(plan.sweep))))
    result = yield from _background(lambda progress: exact_prediction(plan, alpha, heads, progress, from_sweep=False),
                                    "refine")
    return result


def model_material(obj, alpha: float, solver: str, solver_heads: bool = False):
    """The model's material for ``obj`` (a :class:`~unipixie.core.bake.BakeObject`) at ``alpha`` for ``solver``
    (registered as the bake's material predictor; no Blender access: runs in the bake's worker thread);
    ``solver_heads``: see :func:`~unipixie.core.bake.material_from_prediction`."""
    from .bake import MODEL_HEADS, material_from_prediction

    plan = get_plan(obj.name)
    if plan is None:
        raise UserError(f"object '{obj.name}' has no predicted material yet: run Predict in the UniPixie panel "
                        "(after Render views and Features), or bake with a homogeneous material or a field file")
    pred, how, _ = exact_prediction(plan, alpha, MODEL_HEADS[solver])
    res = material_from_prediction(obj, pred, 0, solver, solver_heads=solver_heads)
    res.description = f"model at α {float(alpha):g} ({how}, {Path(plan.checkpoint).name}, seed {plan.seed})"
    return res


# --------------------------------------------------------------------------- the field display
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
