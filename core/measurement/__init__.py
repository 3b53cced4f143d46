"""Measured motion of tracked points: the ``unipixie.measurement/1`` file and its CSV variant.

The contract is ``shared/specs/measurement-format.md`` §1.  A measurement is

* ``positions``: (T, N, 3) float64 metres; NaN marks a point not observed at an instant
  (occlusion).  A sample with any NaN coordinate counts as unobserved as a whole and is
  skipped in every error, never treated as zero;
* ``times``: (T,) float64 seconds, strictly increasing; ``times[0]`` is the initial state;
* ``rest_positions``: (N, 3) metres, the undeformed state (default ``positions[0]``);
* ``faces``: optional (F, 3) int64, a closed, outward-oriented surface whose vertices are
  the tracked points (without it the solid is the convex hull of ``rest_positions``);
* ``scenario``: gravity, ground, initial motion, clamp (:class:`~unipixie.solvers.scenario.Scenario`)
  and the material the model currently believes (homogeneous in the scenario JSON, or a
  per-point field as extra archive keys ``E``, ``nu``, ``density`` of shape (N,)).

A file that breaks the contract is refused with a :class:`~unipixie.core.errors.UserError`
that names the offending key; nothing is written in its place.  Files are written
atomically (a temporary file renamed into place), so a failed save never leaves half a file.

CSV (``t,id,x,y,z``, one observed sample per row, header optional) is read by
:func:`load_csv`; its scenario comes from a side-car JSON file (``name.json`` next to
``name.csv``) or the ``scenario`` argument.

The package splits that job, each module owning one part and importing only those before it in this list
(no cycles):

* :mod:`.arrays`: the checks and repairs of the arrays (coordinates, faces, rest positions);
* :mod:`.material`: :class:`MeasuredMaterial` and the check of its values;
* :mod:`.scenario_json`: the scenario JSON (format name, side-car key, reading, misspelt-key warnings);
* :mod:`.writing`: the ``.npz`` and CSV writers behind :meth:`Measurement.save` and :meth:`Measurement.save_csv`;
* :mod:`.types`: :class:`Measurement` and the checks it runs on every field;
* :mod:`.npz` and :mod:`.csv_reader`: the two readers (:func:`load_npz`, :func:`load_csv`);
* :mod:`.loading`: :func:`load`, the choice of reader by extension.

Import the names from this package (``from unipixie.core.measurement import Measurement, load``).
"""

from __future__ import annotations

from .arrays import COORDINATE_LIMIT
from .csv_reader import CSV_COLUMNS, load_csv
from .loading import load
from .material import MeasuredMaterial
from .npz import OPTIONAL_KEYS, REQUIRED_KEYS, load_npz
from .scenario_json import CSV_SIDECAR_KEY, MATERIAL_KEYS, MEASUREMENT_FORMAT, scenario_key_warnings
from .types import Measurement

__all__ = ["COORDINATE_LIMIT", "CSV_COLUMNS", "CSV_SIDECAR_KEY", "MATERIAL_KEYS", "MEASUREMENT_FORMAT", "OPTIONAL_KEYS",
           "REQUIRED_KEYS", "MeasuredMaterial", "Measurement", "load", "load_csv", "load_npz", "scenario_key_warnings"]
