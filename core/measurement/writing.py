"""Writing a measurement: the ``unipixie.measurement/1`` archive and the CSV variant with its side-car JSON.

Owns the layout of what is written (which arrays go into the ``.npz``, the ``t,id,x,y,z`` rows and the side-car
keys) for :meth:`~.types.Measurement.save` and :meth:`~.types.Measurement.save_csv`.  Every file goes through
:mod:`unipixie.core.atomic_io` (atomic and verified).  It works on a measurement it is given and never imports
:mod:`.types`; it may use :mod:`unipixie.core.errors`, :mod:`unipixie.core.atomic_io` and :mod:`.scenario_json`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic_io import save_npz, write_json, write_text
from ..errors import UserError
from .scenario_json import CSV_SIDECAR_KEY


def write_npz(measurement, path) -> Path:
    """Write ``measurement`` (:class:`~.types.Measurement`) as a compressed ``.npz`` at ``path``; returns the path.

    A path not ending in ``.npz`` is refused (:class:`UserError`)."""
    path = Path(path)
    m = measurement
    arrays: dict[str, Any] = dict(m.extra_arrays)
    arrays["positions"] = m.positions
    arrays["times"] = m.times
    arrays["scenario"] = np.array(json.dumps(m.scenario_dict()))
    if m.rest_positions is not None:
        arrays["rest_positions"] = m.rest_positions
    if m.faces is not None:
        arrays["faces"] = m.faces
    if m.material is not None and not m.material.homogeneous:
        n = m.point_count
        for k in ("E", "nu", "density"):
            arrays[k] = np.broadcast_to(np.asarray(getattr(m.material, k), dtype=np.float64), (n,)).copy()
    if path.suffix != ".npz":
        raise UserError(f"{path}: a measurement file must end in .npz")
    save_npz(path, **arrays)
    return path


def write_csv(measurement, path) -> tuple[Path, list[str]]:
    """Write ``measurement``'s observed samples as ``t,id,x,y,z`` rows at ``path`` and its side-car ``.json``
    beside it; returns ``(path, dropped)`` (see :meth:`~.types.Measurement.save_csv`)."""
    path = Path(path)
    m = measurement
    obs = m.observed
    ti, pi = np.nonzero(obs)
    ids = point_ids(m)
    lines = ["t,id,x,y,z\n"]
    pos = m.positions
    times = m.times
    lines += [f"{times[t]:.17g},{ids[p]},{pos[t, p, 0]:.17g},{pos[t, p, 1]:.17g},{pos[t, p, 2]:.17g}\n"
              for t, p in zip(ti.tolist(), pi.tolist())]
    side = m.scenario_dict()
    extra: dict[str, Any] = {"point_ids": list(ids)}
    if m.rest_positions is not None:
        extra["rest_positions"] = np.asarray(m.rest_positions, dtype=np.float64).tolist()
    if m.faces is not None:
        extra["faces"] = np.asarray(m.faces, dtype=np.int64).tolist()
    if m.material is not None and not m.material.homogeneous:
        n = m.point_count
        for k in ("E", "nu", "density"):
            extra[k] = np.broadcast_to(np.asarray(getattr(m.material, k), dtype=np.float64), (n,)).tolist()
    side[CSV_SIDECAR_KEY] = extra
    dropped = sorted(k for k in m.extra_arrays if k != "point_ids")
    side_path = path.with_suffix(".json")
    write_text(path, "".join(lines))
    write_json(side_path, side)
    return path, dropped


def point_ids(measurement) -> list[str]:
    """The points' ids as text (the CSV's ``id`` column): the ids read from a CSV, else 0..N-1."""
    m = measurement
    ids = m.extra_arrays.get("point_ids")
    if ids is not None and np.asarray(ids).shape == (m.point_count,):
        out = [str(x) for x in np.asarray(ids).tolist()]
        if len(set(out)) == len(out) and all(out) and not any("," in x or "\n" in x for x in out):
            return out
    return [str(i) for i in range(m.point_count)]
