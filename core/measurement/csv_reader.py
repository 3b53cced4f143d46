"""Reading the CSV variant of a measurement (``t,id,x,y,z`` rows and an optional side-car JSON).

Owns the CSV's columns and their header names (:data:`CSV_COLUMNS`), the reading of point ids and rows, the
gathering of rows into instants and points, and the side-car JSON (the scenario, and under
:data:`~.scenario_json.CSV_SIDECAR_KEY` what rows cannot carry); the measurement's own checks then run in
:class:`~.types.Measurement`.  It may use :mod:`unipixie.core.errors`, :mod:`.arrays`, :mod:`.material`,
:mod:`.scenario_json`, :mod:`.types` and, inside functions, :mod:`unipixie.solvers.scenario`.  Writing the CSV
is :mod:`.writing`'s job.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Mapping, Optional

import numpy as np

from ..errors import UserError
from .arrays import float_array
from .material import MeasuredMaterial
from .scenario_json import CSV_SIDECAR_KEY, MEASUREMENT_FORMAT, scenario_from_dict, scenario_key_warnings
from .types import Measurement

CSV_COLUMNS = {"t": ("t", "time", "time_s", "t_s", "seconds"), "id": ("id", "point", "point_id", "track", "track_id"),
               "x": ("x", "x_m"), "y": ("y", "y_m"), "z": ("z", "z_m")}
"""The CSV columns and the header names (case-insensitive, any order) each may have."""


def _csv_columns(row: list, src: str, lineno: int) -> Optional[dict]:
    """``{"t": index, "id": ..., "x": ..., "y": ..., "z": ...}`` from a header row (names as
    :data:`CSV_COLUMNS`, case-insensitive, any order), or ``None`` when ``row`` is data (its first
    cell a number)."""
    cells = [c.strip().lower() for c in row]
    try:
        float(cells[0])
        return None  # data, no header
    except ValueError:
        pass
    cols: dict = {}
    for i, c in enumerate(cells):
        for name, aliases in CSV_COLUMNS.items():
            if c in aliases:
                if name in cols:
                    raise UserError(f"{src}: line {lineno}: the header names column '{name}' twice "
                                    f"({row[cols[name]]!r} and {row[i]!r})")
                cols[name] = i
    missing = [n for n in CSV_COLUMNS if n not in cols]
    if missing:
        raise UserError(f"{src}: line {lineno}: the header {','.join(row)!r} lacks column(s) {', '.join(missing)}; "
                        "a measurement CSV has columns t (s), id, x, y, z (m) — named in the header in any order "
                        "(case-insensitive), or in that order without a header")
    return cols


def _csv_id(text: str, src: str, lineno: int) -> str:
    """A point id as written: an integer (``"7"``, also ``"7.0"`` → ``"7"``) or a name; a number that is
    not whole (``"1.5"``) is refused rather than read as a new point."""
    t = text.strip()
    if not t:
        raise UserError(f"{src}: line {lineno}: column 'id' is empty")
    try:
        return str(int(t))
    except ValueError:
        pass
    try:
        v = float(t)
    except ValueError:
        return t  # a name
    if math.isfinite(v) and v == round(v):
        return str(int(v))
    raise UserError(f"{src}: line {lineno}: point id {t!r} is not a whole number; ids are integers (or names), "
                    "one per tracked point")


def load_csv(path, scenario=None, rest_positions=None, faces=None) -> Measurement:
    """Read ``t,id,x,y,z`` rows (seconds, point id, metres) into a measurement.

    The columns are found by the header's names (:data:`CSV_COLUMNS`: ``t``/``time``, ``id``/``point``,
    ``x``, ``y``, ``z``; case-insensitive, any order, other columns ignored with a warning); a file
    without a header is read in the order ``t,id,x,y,z``.  Missing (t, id) pairs and empty/``nan``
    coordinates become NaN (unobserved).  Point ids are whole numbers or names (``"1.5"`` is refused);
    they are sorted (numerically when all are integers); instants are the sorted distinct ``t``.
    scenario: dict / JSON path / ``None`` (then ``<name>.json`` beside the CSV if it exists, else the
    default scenario with no material).  A side-car written by :meth:`Measurement.save_csv` also gives
    back the point ids never observed, the rest positions, the faces and a per-point material.
    """
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise UserError(f"{src}: file not found")
    ts: list[float] = []
    ids: list[str] = []
    xyz: list[tuple[float, float, float]] = []
    cols: Optional[dict] = None
    header_seen = False
    warnings: list[str] = []
    try:
        f = open(path, newline="", encoding="utf-8-sig")  # -sig: a byte-order mark (Excel's "CSV UTF-8") is not a name
    except OSError as exc:
        raise UserError(f"{src}: cannot read it ({exc.strerror or exc})") from None
    try:
        with f:
            reader = csv.reader(f)
            for lineno, row in enumerate(reader, start=1):
                if not row or all(not c.strip() for c in row) or row[0].lstrip().startswith("#"):
                    continue
                if not header_seen:
                    header_seen = True
                    cols = _csv_columns(row, src, lineno)
                    named = cols is not None
                    width = len(row)
                    if cols is not None:
                        ignored = [row[i] for i in range(len(row)) if i not in cols.values()]
                        if ignored:
                            warnings.append(f"CSV columns {', '.join(repr(c) for c in ignored)} are ignored")
                        continue
                    if len(row) != 5:
                        raise UserError(f"{src}: line {lineno}: expected 5 columns t,id,x,y,z (or a header naming "
                                        f"them), got {len(row)}")
                    cols = {"t": 0, "id": 1, "x": 2, "y": 3, "z": 4}
                    warnings.append("the CSV has no header: its columns are read in the order t,id,x,y,z (name them "
                                    "in a first line, in any order, to read them by name)")
                if len(row) <= max(cols.values()):
                    raise UserError(f"{src}: line {lineno}: expected {max(cols.values()) + 1} columns, got {len(row)}")
                if len(row) > width and any(c.strip() for c in row[width:]):
                    raise UserError(f"{src}: line {lineno}: {len(row)} cells where the "
                                    f"{'header names' if named else 'rows t,id,x,y,z have'} {width}: the row does "
                                    "not belong to this table (a stray separator or a joined line)")
                try:
                    t = float(row[cols["t"]])
                except ValueError:
                    raise UserError(f"{src}: line {lineno}: column 't' is not a number: {row[cols['t']]!r}") from None
                vals = []
                for name in "xyz":
                    c = row[cols[name]].strip()
                    try:
                        vals.append(float(c) if c else math.nan)
                    except ValueError:
                        raise UserError(f"{src}: line {lineno}: column '{name}' is not a number: {c!r}") from None
                if not math.isfinite(t):
                    raise UserError(f"{src}: line {lineno}: column 't' must be finite")
                ts.append(t)
                ids.append(_csv_id(row[cols["id"]], src, lineno))
                xyz.append(tuple(vals))
    except UnicodeDecodeError:
        raise UserError(f"{src}: not a text CSV file (not UTF-8)") from None
    except csv.Error as exc:
        raise UserError(f"{src}: not a readable CSV file ({exc})") from None
    if not ts:
        raise UserError(f"{src}: no data rows (expected t,id,x,y,z)")
    sdict = None
    if scenario is None:
        side = path.with_suffix(".json")
        if side.is_file():
            scenario = side
    if isinstance(scenario, (str, os.PathLike)):
        sp = Path(scenario)
        from ..errors import read_json

        if not sp.is_file():
            raise UserError(f"{sp}: scenario file not found")
        sdict = read_json(sp)
        if not isinstance(sdict, dict):
            raise UserError(f"{sp}: the scenario must be a JSON object")
        src_sc = str(sp)
    elif isinstance(scenario, Mapping):
        sdict, src_sc = dict(scenario), src
    else:
        sdict, src_sc = {"format": MEASUREMENT_FORMAT}, src
        warnings.append(f"no scenario for this CSV (no {path.with_suffix('.json').name} beside it, no --scenario): "
                        "the default is assumed — gravity (0, 0, -9.81) m/s², ground at z = 0 m, starting at rest, no "
                        "clamp, no material stated")
    sidecar = sdict.pop(CSV_SIDECAR_KEY, None) if isinstance(sdict, dict) else None
    if sidecar is not None and not isinstance(sidecar, Mapping):
        raise UserError(f"{src_sc}: key '{CSV_SIDECAR_KEY}' must be a JSON object")
    sidecar = dict(sidecar or {})
    t_arr = np.asarray(ts)
    # distinct instants, merging times equal to within a nanosecond
    order = np.argsort(t_arr, kind="stable")
    uniq: list[float] = []
    for v in t_arr[order]:
        if not uniq or v - uniq[-1] > 1e-9:
            uniq.append(float(v))
    times = np.asarray(uniq)
    t_index = np.clip(np.searchsorted(times, t_arr - 1e-9), 0, len(times) - 1)
    all_ids = set(ids)
    side_ids = sidecar.get("point_ids")
    if side_ids is not None:
        if not isinstance(side_ids, list) or len(set(map(str, side_ids))) != len(side_ids):
            raise UserError(f"{src_sc}: key '{CSV_SIDECAR_KEY}.point_ids' must be a list of distinct ids")
        side_ids = [str(x) for x in side_ids]
        unknown = sorted(all_ids - set(side_ids))
        if unknown:
            raise UserError(f"{src}: point id(s) {', '.join(unknown[:5])} are not in the side-car's point_ids; the "
                            "CSV and its side-car JSON do not belong together")
        keys = side_ids
    else:
        try:
            keys = sorted(all_ids, key=int)
        except ValueError:
            keys = sorted(all_ids)
    p_index_of = {k: i for i, k in enumerate(keys)}
    positions = np.full((len(times), len(keys), 3), np.nan)
    seen = np.zeros((len(times), len(keys)), dtype=bool)
    for t_i, pid, v in zip(t_index, ids, xyz):
        p_i = p_index_of[pid]
        if seen[t_i, p_i]:
            raise UserError(f"{src}: point id {pid!r} appears twice at t = {times[t_i]:g} s")
        seen[t_i, p_i] = True
        positions[t_i, p_i] = v
    from ...solvers.scenario import require_json_numbers

    for key in ("rest_positions", "faces", "E", "nu", "density"):
        if sidecar.get(key) is not None:
            try:
                require_json_numbers(sidecar[key], f"key '{CSV_SIDECAR_KEY}.{key}'")
            except UserError as exc:
                raise UserError(f"{src_sc}: {exc}") from None
    if rest_positions is None and sidecar.get("rest_positions") is not None:
        rest_positions = float_array(sidecar["rest_positions"], f"{CSV_SIDECAR_KEY}.rest_positions", src_sc)
    if faces is None and sidecar.get("faces") is not None:
        faces = np.asarray(sidecar["faces"])
    sc, material = scenario_from_dict(sdict, src_sc)
    per_point = {k: sidecar[k] for k in ("E", "nu", "density") if sidecar.get(k) is not None}
    if per_point:
        base = material or MeasuredMaterial(0, 0, 0)
        vals = []
        for k in ("E", "nu", "density"):
            if k in per_point:
                arr = float_array(per_point[k], f"{CSV_SIDECAR_KEY}.{k}", src_sc)
                if arr.shape != (len(keys),):
                    raise UserError(f"{src_sc}: key '{CSV_SIDECAR_KEY}.{k}' must hold one value per point "
                                    f"({len(keys)}), got shape {arr.shape}")
                vals.append(arr)
            else:
                vals.append(getattr(base, k))
        material = MeasuredMaterial(*vals, base.material_class)
    m = Measurement(positions=positions, times=times, scenario=sc, rest_positions=rest_positions, faces=faces,
                    material=material, source=src)
    m.warnings.extend(warnings + scenario_key_warnings(sdict))
    if keys != [str(i) for i in range(len(keys))]:  # ids 0..N-1 are the positions themselves: nothing to keep
        m.extra_arrays["point_ids"] = np.asarray(keys)
    return m
