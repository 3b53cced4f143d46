"""The scenario JSON of a measurement: its format name, its keys, and how it is read.

Owns the format's name (:data:`MEASUREMENT_FORMAT`), the side-car key of the CSV variant
(:data:`CSV_SIDECAR_KEY`), the reading of the scenario dict into a
:class:`~unipixie.solvers.scenario.Scenario` and an optional :class:`~.material.MeasuredMaterial`
(:func:`scenario_from_dict`), and the warnings for misspelt keys (:func:`scenario_key_warnings`).  It may use
:mod:`unipixie.core.errors`, :mod:`.arrays`, :mod:`.material` and, inside functions, :mod:`unipixie.solvers`
(the scenario and the material registry).
"""

from __future__ import annotations

from typing import Mapping

from ..errors import UserError
from .arrays import fail
from .material import MeasuredMaterial, check_material_values

MEASUREMENT_FORMAT = "unipixie.measurement/1"
CSV_SIDECAR_KEY = "csv_sidecar"
"""Key of the CSV side-car JSON holding what rows cannot carry (point ids, rest positions, faces, per-point material)."""


def scenario_from_dict(d: dict, src: str):
    """(Scenario, MeasuredMaterial | None) from the scenario JSON dict; errors name the key."""
    from ...solvers.scenario import Scenario

    try:
        scenario = Scenario.from_dict(d)
    except UserError as exc:
        raise fail(src, f"key 'scenario': {exc}") from None
    material = None
    mat = d.get("material")
    if mat is not None:
        if not isinstance(mat, Mapping):
            raise fail(src, f"scenario key 'material' must be {{\"E\": Pa, \"nu\": -, \"density\": kg/m³}}, got {mat!r}")
        missing = [k for k in ("E", "nu", "density") if k not in mat]
        if missing:
            raise fail(src, f"scenario key 'material' lacks {', '.join(repr(k) for k in missing)}")
        from ...solvers.scenario import require_json_numbers

        for k in ("E", "nu", "density"):
            try:
                require_json_numbers(mat[k], f"scenario key 'material' entry '{k}'")
            except UserError as exc:
                raise fail(src, str(exc)) from None
        try:
            E, nu, rho = (float(mat[k]) for k in ("E", "nu", "density"))
        except (TypeError, ValueError):
            raise fail(src, f"scenario key 'material' must hold numbers, got {mat!r}") from None
        check_material_values(E, nu, rho, f"{src}: scenario key 'material'" if src else "scenario key 'material'")
        cls = str(mat.get("class", mat.get("material", "jelly")))
        from ...solvers import materials

        try:
            materials.get(cls)
        except UserError as exc:
            raise fail(src, f"scenario key 'material': {exc}") from None
        material = MeasuredMaterial(E, nu, rho, cls)
    return scenario, material


MATERIAL_KEYS = ("E", "nu", "density", "class", "material")
"""The keys scenario key ``material`` may hold (``class`` / ``material``: the material class's name)."""


def scenario_key_warnings(d: dict) -> list[str]:
    """Warnings for scenario keys that look like misspellings of the format's own keys.

    The format keeps unknown keys and ignores them (``shared/specs/measurement-format.md`` §1), so a typo such
    as ``initial_velocty`` would silently leave the solid at rest; a key within a close spelling of a known one
    (``difflib``, ratio ≥ 0.8) is named with the key it probably meant.  Keys far from every known one (the
    user's own annotations) pass without a word.
    """
    import difflib

    from ...solvers.scenario import SCENARIO_KEYS

    out = []
    known_top = tuple(SCENARIO_KEYS) + (CSV_SIDECAR_KEY,)
    nested = [("", d, known_top)]
    if isinstance(d.get("material"), Mapping):
        nested.append(("material.", d["material"], MATERIAL_KEYS))
    for prefix, mapping, known in nested:
        for key in mapping:
            if key in known or not isinstance(key, str):
                continue
            close = difflib.get_close_matches(key, known, n=1, cutoff=0.8)
            if close:
                out.append(f"scenario key '{prefix}{key}' is not part of the format and is ignored — did you mean "
                           f"'{prefix}{close[0]}'?")
    return out

