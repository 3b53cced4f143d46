"""Each step's state for one object: ``not done``, ``done``, ``stale`` (and why) or ``running``.

:func:`step_states` compares the inputs a :class:`~.record.PipelineRecord` recorded with the current ones
(:class:`CurrentInputs`): a changed input makes a step stale with a reason the panel shows ("the mesh, its
modifiers or materials changed", "α changed", ...), and staleness flows downstream (stale features make the
prediction stale, which makes a model-driven bake stale).  May use :mod:`.record` and :mod:`.settings`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Optional

from ..errors import UserError
from .record import DONE, NOT_DONE, RUNNING, STALE, STEPS, PipelineRecord, StepState
from .settings import PipelineSettings

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


def _missing_result(record: PipelineRecord, step: str, key: str, gone_reason: str) -> Optional[StepState]:
    """``not done`` when ``step`` has no record, or (with ``gone_reason``) when the file it recorded under ``key`` is
    no longer in the cache; ``None`` when both are there."""
    if not record.get(step):
        return StepState(NOT_DONE)
    if record.file(step, key) is None:
        return StepState(NOT_DONE, gone_reason)
    return None


def _compared(recorded: Optional[dict], current_inputs: Optional[dict], note: str = "") -> StepState:
    """``stale`` with the reasons of :data:`CHANGE_REASONS` where the recorded inputs and the current ones differ,
    else ``done`` (with ``note``)."""
    changes = input_changes(recorded, current_inputs)
    return StepState(STALE, _reason(changes)) if changes else StepState(DONE, note)


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
    elif (missing := _missing_result(record, "render", "views",
                                     "the rendered views are no longer in the cache")) is not None:
        out["render"] = missing
    else:
        out["render"] = _compared(rec.get("inputs"), s.render_inputs(current.fingerprint))

    # features
    rec = record.get("features")
    missing = _missing_result(record, "features", "grid", "the feature grid is no longer in the cache")
    if missing is not None:
        out["features"] = missing
    elif current.fingerprint is None:
        out["features"] = StepState(STALE, current.error)
    else:
        try:
            current_inputs = s.feature_inputs(current.fingerprint)
        except UserError as exc:
            out["features"] = StepState(STALE, str(exc))
        else:
            out["features"] = _compared(rec.get("inputs"), current_inputs)

    # predict
    rec = record.get("predict")
    missing = _missing_result(record, "predict", "sweep", "the α sweep is no longer in the cache")
    if missing is not None:
        out["predict"] = missing
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
            out["predict"] = _compared(recorded, current_inputs, note)

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
