"""Loading a measurement file of either kind, chosen by its extension (:func:`load`).

Owns only the choice between the readers: ``.npz`` goes to :func:`~.npz.load_npz`, ``.csv`` to
:func:`~.csv_reader.load_csv`, anything else is refused.  It may use :mod:`unipixie.core.errors`, :mod:`.npz`,
:mod:`.csv_reader`, :mod:`.scenario_json` and :mod:`.types`.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import UserError
from .csv_reader import load_csv
from .npz import load_npz
from .scenario_json import MEASUREMENT_FORMAT
from .types import Measurement


def load(path, **kwargs) -> Measurement:
    """Load a measurement by extension: ``.npz`` (the spec's format) or ``.csv`` (t,id,x,y,z)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        if kwargs:
            raise UserError(f"{path}: options {sorted(kwargs)} apply to CSV files only")
        return load_npz(path)
    if suffix == ".csv":
        return load_csv(path, **kwargs)
    raise UserError(f"{path}: unknown measurement file type {suffix!r}; use .npz ({MEASUREMENT_FORMAT}) or .csv "
                    "(t,id,x,y,z)")
