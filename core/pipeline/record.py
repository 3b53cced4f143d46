"""The pipeline's steps, their states and the per-object record of what each step produced.

The steps (:data:`STEPS`: Render views → Features → Predict → Simulate & bake), the four states a step can be
in, and :class:`PipelineRecord` (``unipixie.pipeline/1``, JSON; the Blender side keeps it in the object's ID
property :data:`RECORD_KEY`): for each step the *inputs* it was run with and the cached files it produced.
Plain data; imports nothing of UniPixie.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

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


@dataclass
class StepState:
    """The state of one step: one of :data:`STATES`, and why (for stale steps, missing files)."""

    state: str = NOT_DONE
    reason: str = ""

    def label(self) -> str:
        return f"{self.state}: {self.reason}" if self.reason else self.state


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
