"""Object ``index`` of the dataset: its class, variant, parts, appearance, annotation and scenario, from
``(seed, index)`` alone (:func:`generate` is deterministic and independent of other objects).

May use every module of this package and :mod:`unipixie.core.annotation` (the class priors).
"""

from __future__ import annotations

import numpy as np

from .. import annotation as ann_mod
from ..errors import UserError
from .appearance import look_for, part_appearance
from .geometry import GEOMETRY
from .objects import Part, ProceduralObject
from .textures import stable_hash


def _rest_on_ground(parts: dict) -> dict:
    """Translate every component so the whole object's lowest point is at z = 0 and it is centred in x, y."""
    verts = np.concatenate([np.asarray(c.vertices) for comps in parts.values() for c in comps])
    shift = np.array([-(verts[:, 0].min() + verts[:, 0].max()) / 2, -(verts[:, 1].min() + verts[:, 1].max()) / 2,
                      -verts[:, 2].min()])
    for comps in parts.values():
        for c in comps:
            c.apply_translation(shift)
    return parts


def make_scenario(prior: ann_mod.ScenarioPrior, parts: dict, part_names: list, rng):
    """The ground-truth clip's :class:`~unipixie.solvers.scenario.Scenario` (metres, z up, ground below)."""
    from ...solvers.scenario import Scenario

    verts = np.concatenate([np.asarray(c.vertices) for comps in parts.values() for c in comps])
    height = float(np.ptp(verts[:, 2]))
    size = float(np.max(np.ptp(verts, axis=0)))
    if prior.kind == "drop":
        h = rng.uniform(*prior.drop_height) * max(height, 0.3 * size)
        axis = rng.normal(size=3)
        axis[2] = 0.0
        axis /= max(np.linalg.norm(axis), 1e-9)
        omega = axis * rng.uniform(0.5, 2.0)
        return Scenario(ground_height=-float(h), initial_angular_velocity=omega,
                        notes=f"drop from {h:.4f} m with a tilt of {np.linalg.norm(omega):.2f} rad/s")
    if prior.kind == "anchored":
        comps = parts[prior.pinned_part]
        pv = np.concatenate([np.asarray(c.vertices) for c in comps])
        margin = 1e-3 * size
        box = np.stack([pv.min(0) - margin, pv.max(0) + margin])
        a = rng.uniform(0, 2 * np.pi)
        speed = rng.uniform(*prior.push_speed)
        return Scenario(ground_height=-margin, pinned_box=box,
                        initial_velocity=[speed * np.cos(a), speed * np.sin(a), 0.0],
                        notes=f"{prior.pinned_part} clamped; the rest pushed sideways at {speed:.2f} m/s")
    raise UserError(f"unknown scenario kind {prior.kind!r}")


def class_of_index(index: int, classes=None) -> str:
    """The semantic class of object ``index``: the classes in turn (balanced counts)."""
    classes = tuple(classes or ann_mod.SEMANTIC_CLASSES)
    return classes[int(index) % len(classes)]


def object_id(index: int, semantic_class: str) -> str:
    return f"{int(index):06d}_{semantic_class}"


def generate(index: int, seed: int = 0, semantic_class: str | None = None, classes=None) -> ProceduralObject:
    """Object ``index`` of the dataset with base ``seed`` (deterministic; independent of other objects)."""
    semantic_class = semantic_class or class_of_index(index, classes)
    prior = ann_mod.class_prior(semantic_class)
    if semantic_class not in GEOMETRY:
        raise UserError(f"no geometry generator for class {semantic_class!r}")
    rng = np.random.default_rng([int(seed), int(index), stable_hash(semantic_class)])
    variant = ann_mod.choose_variant(prior, rng)
    names = ann_mod.parts_of(prior, variant)
    raw = GEOMETRY[semantic_class](rng, variant)
    missing = [p for p in names if p not in raw or not raw[p]]
    extra = [p for p in raw if p not in names]
    if missing or extra:
        raise RuntimeError(f"{semantic_class}/{variant}: generator parts {sorted(raw)} differ from prior parts {names}")
    for p in names:
        for c in raw[p]:
            if not c.is_watertight:
                raise RuntimeError(f"{semantic_class}/{variant}: a component of part {p!r} is not closed")
            if c.volume < 0:
                c.invert()
    raw = _rest_on_ground({p: raw[p] for p in names})
    codes = {p: float(rng.uniform()) for p in names}
    parts = [Part(p, raw[p], part_appearance(look_for(semantic_class, variant, p), codes[p], rng)) for p in names]
    annotation = ann_mod.sample_annotation(semantic_class, variant, codes, rng)
    scenario = make_scenario(prior.scenario, raw, names, rng)
    oid = object_id(index, semantic_class)
    annotation.meta.update({"object_id": oid, "index": int(index), "seed": int(seed)})
    return ProceduralObject(oid, int(index), int(seed), semantic_class, variant, parts, annotation, scenario,
                            {"appearance": {p.name: p.appearance.to_dict() for p in parts}})
