"""The referee's inputs checked against the spec: effects (names, parameters, ranges), materials and vectors.

Independent of ``solvers/`` (it shares only :mod:`unipixie.core.errors`); a :class:`UserError` names what is
wrong.  The effects are the spec's vocabulary (:data:`EFFECT_NAMES`) and the project's ``contact_damping``
(:data:`EXTRA_EFFECT_NAMES`), each implemented by :class:`.FEMModel` from its own reading of the law.
"""

from __future__ import annotations

import math

import numpy as np

from ...core.errors import UserError

EFFECT_NAMES = ("linear_drag", "quadratic_drag", "material_damping", "ground_friction", "plasticity", "wind",
                "stiffness_region")
"""The spec's effect vocabulary (shared/specs/measurement-format.md §2)."""
EXTRA_EFFECT_NAMES = ("contact_damping",)
"""Effects of the project's registry beyond the spec that the referee also implements: ``contact_damping`` (c
Pa·s/m, k Pa/m), a floor that gives and damps (the normal traction k·d + c·ḋ per unit contact area, never
pulling), so the solvers' damped contact can be judged against a simulator that shares none of their code."""


def _effect_params(effects) -> dict:
    """{name: params dict} from ``[{"effect": name, "params": {...}}]``, ``{name: params}`` or
    ``"name:key=value,..."`` strings (vectors as ``a,b,c``; ``stiffness_region`` takes ``box=x0,y0,z0,x1,y1,z1``)."""
    out: dict = {}
    if isinstance(effects, dict):
        items = list(effects.items())
    else:
        items = []
        for e in effects:
            if isinstance(e, str):
                name, _, rest = e.partition(":")
                params: dict = {}
                key = None
                for tok in rest.split(","):
                    if not tok:
                        continue
                    if "=" in tok:
                        key, val = tok.split("=", 1)
                        key = key.strip()
                        params[key] = [_number(val, e)]
                    elif key is not None:
                        params[key].append(_number(tok, e))
                    else:
                        raise UserError(f"effect {e!r}: expected 'name:key=value,...', got {tok!r}")
                params = {k: (v[0] if len(v) == 1 else v) for k, v in params.items()}
                if "box" in params:
                    params["region"] = {"box": np.asarray(params.pop("box"), float).reshape(2, 3).tolist()}
                items.append((name.strip(), params))
            elif isinstance(e, dict) and "effect" in e:
                items.append((e["effect"], dict(e.get("params") or {})))
            else:
                raise UserError(f"effect {e!r}: expected 'name:key=value,...' or {{'effect': name, 'params': {{...}}}}")
    for name, params in items:
        if name not in EFFECT_NAMES + EXTRA_EFFECT_NAMES:
            raise UserError(f"unknown effect {name!r}; the referee's effects are "
                            f"{', '.join(EFFECT_NAMES + EXTRA_EFFECT_NAMES)}")
        if name in out:
            raise UserError(f"effect {name!r} is given twice")
        out[name] = _check_effect(name, dict(params))
    return out


_EFFECT_PARAMS = {"linear_drag": ("c",), "quadratic_drag": ("k",), "material_damping": ("eta",),
                  "ground_friction": ("mu",), "plasticity": ("yield_stress",), "wind": ("acceleration",),
                  "stiffness_region": ("factor", "region"), "contact_damping": ("c", "k")}
"""The parameters each effect takes (``stiffness_region`` also accepts ``rel_box`` in :class:`Case`)."""


def _number(text: str, where) -> float:
    try:
        return float(text)
    except ValueError:
        raise UserError(f"effect {where!r}: {text!r} is not a number") from None


def _check_effect(name: str, params: dict) -> dict:
    """``params`` checked against the spec (names, ranges, shapes); a :class:`UserError` names what is wrong."""
    allowed = set(_EFFECT_PARAMS[name]) | ({"rel_box"} if name == "stiffness_region" else set())
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise UserError(f"effect {name!r}: unknown parameter(s) {unknown}; it takes {', '.join(_EFFECT_PARAMS[name])}")
    required = ("factor",) if name == "stiffness_region" else _EFFECT_PARAMS[name]
    missing = [k for k in required if k not in params]
    if missing:
        raise UserError(f"effect {name!r}: missing parameter(s) {missing}")
    if name == "stiffness_region":
        if ("region" in params) == ("rel_box" in params):
            raise UserError("effect 'stiffness_region': give exactly one of 'region' ({'box': [[x0,y0,z0],[x1,y1,z1]]}, "
                            "metres) or 'rel_box' (the same in [0, 1]³ of the solid's bounds)")
        box = params["region"].get("box") if isinstance(params.get("region"), dict) else params.get("rel_box")
        try:
            b = np.asarray(box, dtype=np.float64).reshape(2, 3)
        except (TypeError, ValueError):
            raise UserError(f"effect 'stiffness_region': the region box must be [[x0,y0,z0],[x1,y1,z1]], got {box!r}") from None
        if not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
            raise UserError(f"effect 'stiffness_region': the region box {b.tolist()} is not finite or has max < min")
    for k in params:
        if k in ("region", "rel_box"):
            continue
        try:
            v = np.asarray(params[k], dtype=np.float64)
        except (TypeError, ValueError):
            raise UserError(f"effect {name!r}: parameter {k!r} must be a number, got {params[k]!r}") from None
        if name == "wind":
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise UserError(f"effect 'wind': 'acceleration' must be a finite 3-vector (m/s²), got {params[k]!r}")
            continue
        if v.shape != () or not math.isfinite(float(v)):
            raise UserError(f"effect {name!r}: parameter {k!r} must be one finite number, got {params[k]!r}")
        if (name in ("plasticity", "stiffness_region") or (name, k) == ("contact_damping", "k")) and float(v) <= 0:
            raise UserError(f"effect {name!r}: parameter {k!r} must be positive, got {float(v)}")
        if float(v) < 0:
            raise UserError(f"effect {name!r}: parameter {k!r} must be 0 or more, got {float(v)}")
    return params


def _vector3(value, key: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        v = None
    if v is None or v.shape != (3,) or not np.all(np.isfinite(v)):
        raise UserError(f"scenario key {key!r} must be a finite 3-vector, got {value!r}")
    return v


def _check_material(material: dict) -> tuple[float, float, float]:
    """(E Pa, ν, ρ kg/m³) of a material dict; a :class:`UserError` for a missing key or a value out of range."""
    try:
        E, nu, rho = (float(material[k]) for k in ("E", "nu", "density"))
    except KeyError as exc:
        raise UserError(f"material: missing key {exc.args[0]!r} (need 'E' Pa, 'nu', 'density' kg/m³)") from None
    except (TypeError, ValueError):
        raise UserError(f"material: 'E', 'nu' and 'density' must be numbers, got {material!r}") from None
    if not (math.isfinite(E) and E > 0):
        raise UserError(f"material: 'E' must be a positive number of pascals, got {E}")
    if not (-1.0 < nu < 0.5):
        raise UserError(f"material: 'nu' must lie in (-1, 0.5), got {nu}")
    if not (math.isfinite(rho) and rho > 0):
        raise UserError(f"material: 'density' must be a positive number of kg/m³, got {rho}")
    return E, nu, rho
