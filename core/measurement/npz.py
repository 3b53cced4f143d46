"""Reading the ``unipixie.measurement/1`` archive (``.npz``) into a :class:`~.types.Measurement`.

Owns the archive's keys (:data:`REQUIRED_KEYS`, :data:`OPTIONAL_KEYS`) and their reading: the scenario JSON
string, the per-point material keys and the extra keys kept as they are; the measurement's own checks then
run in :class:`~.types.Measurement`.  It may use :mod:`unipixie.core.errors`, :mod:`.material`,
:mod:`.scenario_json` and :mod:`.types`.  Writing the archive is :mod:`.writing`'s job.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import UserError, read_npz
from .material import MeasuredMaterial
from .scenario_json import scenario_from_dict, scenario_key_warnings
from .types import Measurement

REQUIRED_KEYS = ("positions", "times", "scenario")
OPTIONAL_KEYS = ("rest_positions", "faces", "E", "nu", "density")


def load_npz(path) -> Measurement:
    """Read and validate a ``unipixie.measurement/1`` archive; a :class:`UserError` names any broken key."""
    path = Path(path)
    src = str(path)
    data = read_npz(path)
    for key in REQUIRED_KEYS:
        if key not in data:
            raise UserError(f"{src}: key '{key}' is missing (a measurement needs {', '.join(REQUIRED_KEYS)})")
    sc = data["scenario"]
    if sc.dtype.kind not in "US" or sc.ndim != 0:
        raise UserError(f"{src}: key 'scenario' must be a 0-d string array holding JSON, got dtype {sc.dtype} "
                        f"shape {sc.shape}")
    try:
        sdict = json.loads(str(sc))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise UserError(f"{src}: key 'scenario' is not valid JSON ({exc})") from None
    if not isinstance(sdict, dict):
        raise UserError(f"{src}: key 'scenario' must be a JSON object")
    scenario, material = scenario_from_dict(sdict, src)
    positions = data["positions"]
    n = positions.shape[1] if positions.ndim == 3 else None
    per_point = {k: data[k] for k in ("E", "nu", "density") if k in data}
    if per_point:
        for k, v in per_point.items():
            if v.dtype.kind not in "fiu" or (n is not None and v.shape != (n,)):
                raise UserError(f"{src}: key '{k}' must be a float array of shape ({n},) (one value per tracked point), "
                                f"got dtype {v.dtype} shape {v.shape}")
        if material is None and len(per_point) < 3:
            lacking = [k for k in ("E", "nu", "density") if k not in per_point]
            raise UserError(f"{src}: per-point material keys given but {', '.join(repr(k) for k in lacking)} missing "
                            "and the scenario states no 'material' to fill them")
        base = material or MeasuredMaterial(0, 0, 0)
        material = MeasuredMaterial(*(per_point[k].astype(np.float64) if k in per_point else getattr(base, k)
                                      for k in ("E", "nu", "density")), base.material_class)
    extras = {k: v for k, v in data.items() if k not in REQUIRED_KEYS + OPTIONAL_KEYS}
    m = Measurement(positions=positions, times=data["times"], scenario=scenario,
                    rest_positions=data.get("rest_positions"), faces=data.get("faces"), material=material,
                    extra_arrays=extras, source=src)
    m.warnings.extend(scenario_key_warnings(sdict))
    return m
