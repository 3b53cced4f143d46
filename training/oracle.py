"""What the best possible predictor reaches on a procedural dataset: reference predictions from its own priors.

A procedural object's annotated ranges are drawn by :func:`.annotation.sample_annotation` from its class
prior, placed by each part's *appearance code* ``u`` (which also set the part's colour) plus noise that
nothing in the images carries: a jitter of the E range's centre, a random E half-width, a Poisson's ratio
drawn independently of appearance, a half-random density.  So no model, however well trained, predicts
the labels exactly.  This module computes two *reference predictors* that know everything an image could
tell and nothing more, and writes their predictions in the evaluation's format, so that every metric of
:mod:`.evaluate` (Table 1, the in-range fractions) is computed for them by the same code as for the
models:

``oracle_appearance``
    Knows the object's class and variant, which part every voxel belongs to, and the appearance code
    of every *visible* part (one with a voxel on the object's outer surface); the codes of hidden parts
    (a ball's core, a can's contents) it knows only as the generator draws them, uniform on [0, 1].
    It predicts, per part and α, the conditional mean of the label at α given that knowledge — the
    minimum-MSE prediction of any method trained on these labels (the paper's flow objective and the
    one-step mean included).  Its log E MSE is therefore the floor of Table 1, and its in-range
    fractions are those of a perfectly trained model of this kind.
``oracle_appearance_midpoint``
    The same knowledge, but blind to α: it predicts the conditional mean of the range's midpoint at
    every α — the best that any deterministic α = 0.5 predictor (the PIXIE-style U-Net) can do.
``oracle_surface_parts``
    Knows what ``oracle_appearance`` knows except the part layout *inside* the solid, which no render shows:
    every voxel takes the part of the nearest voxel on the outer surface (a hidden part is never predicted),
    and that part's conditional mean at α.  Not a floor — a model may learn the generator's layouts (a
    ball's core, a pot's soil) from the shapes and do better — but what reading the renders' parts straight
    inward reaches: the gap between it and ``oracle_appearance`` is the part of the floor that needs knowledge
    of the interior.

The conditional means are Monte-Carlo averages over ``draws`` fresh annotations from the generator's own
:func:`.annotation.sample_annotation` (constraint re-draws included), with the hidden parts' codes drawn
anew each time; the standard error this adds to an MSE is about ``1/draws`` of the label variance.

Only objects built by :mod:`.procedural` qualify: the annotation must carry the generator's ``index``
and ``seed``, and regenerating the object must reproduce the stored ranges (otherwise the dataset was
built by another version of the generator, and the oracle refuses rather than guessing).

Channels are the evaluation's: log10 E (Pa), log10 ρ (kg/m³), ν.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..core.errors import UserError
from ..core import annotation as ann_mod

ORACLE = "oracle_appearance"
ORACLE_MIDPOINT = "oracle_appearance_midpoint"
ORACLE_SURFACE = "oracle_surface_parts"
REFERENCES = {
    ORACLE: "knows each voxel's part, the class and every visible part's appearance code; predicts the "
            "conditional mean of the label at α (the lowest MSE any model trained on these labels can reach)",
    ORACLE_MIDPOINT: "the same knowledge, blind to α: the conditional mean of the range's midpoint (the best "
                     "any deterministic α = 0.5 predictor can do)",
    ORACLE_SURFACE: "the same knowledge except the parts inside the solid: each voxel takes the part of the "
                    "nearest outer-surface voxel (what the renders show, read straight inward; not a floor)",
}
"""Reference name -> what it knows and predicts (shown in the evaluation report)."""

_CHANNELS = {"E": "log10_E", "density": "log10_density", "nu": "nu"}
"""Annotated quantity -> the prediction array it fills (evaluation channels)."""


@dataclass(frozen=True)
class OracleSettings:
    """draws: annotations drawn per object for the conditional means.  seed: their random seed."""

    draws: int = 1000
    seed: int = 0

    def __post_init__(self):
        if int(self.draws) < 10:
            raise UserError(f"oracle draws must be at least 10, got {self.draws}")


def visible_parts(part_ids: np.ndarray, indices: np.ndarray, resolution: int) -> np.ndarray:
    """(P,) bool: parts with at least one voxel on the occupied grid's outer surface.

    part_ids: (K,) int part of each occupied voxel; indices: (K, 3) int voxel indices of the occupied
    voxels; resolution: grid side.  A part none of whose voxels touches empty space (or the grid's edge)
    cannot be seen in any view.
    """
    on_surface = on_outer_surface(indices, resolution)
    count = int(part_ids.max()) + 1 if len(part_ids) else 0
    return np.bincount(part_ids[on_surface], minlength=count) > 0


def on_outer_surface(indices: np.ndarray, resolution: int) -> np.ndarray:
    """(K,) bool: which of the occupied voxels ``indices`` (K, 3) int lie on the occupied grid's outer surface (a face
    towards empty space or the grid's edge; :func:`unipixie.core.lift.surface_mask`).  resolution: grid side."""
    from ..core.lift import surface_mask

    idx = np.asarray(indices, np.int64)
    occ = np.zeros((resolution,) * 3, bool)
    occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return surface_mask(occ)[idx[:, 0], idx[:, 1], idx[:, 2]]


def nearest_surface_parts(part_ids: np.ndarray, indices: np.ndarray, resolution: int) -> np.ndarray:
    """(K,) int: for each occupied voxel, the part of the nearest voxel on the occupied grid's outer surface (itself
    when it is on the surface; among equally near ones, the one the k-d tree returns — the same every time).

    part_ids: (K,) int part of each occupied voxel; indices: (K, 3) int voxel indices; resolution: grid side.
    """
    from scipy.spatial import cKDTree

    idx = np.asarray(indices, np.int64)
    part_ids = np.asarray(part_ids, np.int64)
    if len(idx) == 0:
        return part_ids.copy()
    on_surface = on_outer_surface(idx, resolution)
    _, nearest = cKDTree(idx[on_surface]).query(idx)
    return part_ids[on_surface][nearest]


def generator_codes(annotation) -> tuple[str, str, dict]:
    """(semantic class, variant, part -> appearance code) of a procedural object, by regenerating it.

    Raises :class:`UserError` if the annotation was not written by :mod:`.procedural` or if the
    regenerated object's ranges differ from the stored ones (another generator version).
    """
    from ..core import procedural

    meta = annotation.meta or {}
    if "index" not in meta or "seed" not in meta:
        raise UserError("the annotation carries no generator index / seed: not a procedural object, so there is "
                        "no prior to compute the oracle from")
    try:
        obj = procedural.generate(int(meta["index"]), int(meta["seed"]), annotation.semantic_class)
    except (KeyError, ValueError) as exc:
        raise UserError(f"object {meta.get('object_id', '?')}: the generator cannot rebuild it ({exc})") from exc
    stored, again = ann_mod.part_table(annotation), ann_mod.part_table(obj.annotation)
    same = (obj.variant == annotation.variant and annotation.part_names == obj.annotation.part_names
            and all(np.allclose(stored[k], again[k], rtol=1e-9, atol=0) for k in stored))
    if not same:
        raise UserError(f"object {meta.get('object_id', '?')}: regenerating it (index {meta['index']}, seed "
                        f"{meta['seed']}) does not reproduce its stored ranges; the dataset was built by another "
                        "version of the generator, whose prior this code does not have")
    return obj.semantic_class, obj.variant, {p.name: float(p.appearance.code) for p in obj.parts}


def part_label_moments(semantic_class: str, variant: str, codes: dict, hidden: set, draws: int,
                       rng: np.random.Generator) -> dict:
    """Conditional means of each part's range ends, in evaluation channels, by Monte Carlo.

    codes: part -> appearance code (those of ``hidden`` parts are ignored and drawn uniform on [0, 1] per
    draw).  Returns quantity -> (lo, hi), each (P,) float64 in the annotation's part order (the mean of
    log10 of the lower / upper end for E and ρ, of the end itself for ν), plus ``"material"`` (P,) class ids.
    """
    lo = {q: [] for q in ann_mod.QUANTITIES}
    hi = {q: [] for q in ann_mod.QUANTITIES}
    material = None
    for _ in range(int(draws)):
        c = {p: (float(rng.uniform()) if p in hidden else u) for p, u in codes.items()}
        table = ann_mod.part_table(ann_mod.sample_annotation(semantic_class, variant, c, rng))
        material = table["material"]
        for q in ann_mod.QUANTITIES:
            lo[q].append(ann_mod.channel(table[f"{q}_min"], q))
            hi[q].append(ann_mod.channel(table[f"{q}_max"], q))
    out = {q: (np.mean(lo[q], axis=0), np.mean(hi[q], axis=0)) for q in ann_mod.QUANTITIES}
    out["material"] = material
    return out


def visible_part_moments(annotation, part_ids: np.ndarray, indices: np.ndarray, resolution: int,
                         settings: OracleSettings | None = None, codes: dict | None = None) -> dict:
    """The references' per-part conditional means (:func:`part_label_moments`) for one procedural object: the codes
    of the parts with a voxel on the outer surface known, those of the others drawn, ``settings.draws`` draws seeded
    by ``settings.seed`` and the object's index.

    part_ids: (K,) int part of each occupied voxel; indices: (K, 3) int voxel indices; resolution: grid side;
    codes: part -> appearance code used in place of the generator's for those parts (None: the generator's own).
    Returns what :func:`part_label_moments` returns, (P,) per part in the annotation's order.
    """
    settings = settings or OracleSettings()
    names = annotation.part_names
    semantic_class, variant, true_codes = generator_codes(annotation)
    codes = {**true_codes, **(codes or {})}
    seen = visible_parts(np.asarray(part_ids, np.int64), indices, resolution)
    hidden = {n for i, n in enumerate(names) if i >= len(seen) or not seen[i]}
    rng = np.random.default_rng([int(settings.seed), int((annotation.meta or {}).get("index", 0))])
    return part_label_moments(semantic_class, variant, codes, hidden, settings.draws, rng)


def oracle_predictions(annotation, part_ids: np.ndarray, indices: np.ndarray, resolution: int, alphas,
                       settings: OracleSettings | None = None, codes: dict | None = None) -> dict:
    """The references' predictions for one procedural object, in the evaluation's saved format.

    annotation: the object's stored :class:`~.annotation.Annotation`; part_ids: (K,) part of each occupied
    voxel (index into ``annotation.part_names``); indices: (K, 3) voxel indices; alphas: (A,) values.
    Returns {reference name: {"alphas" (A,), "log10_E" / "log10_density" / "nu" (A, K) float32,
    "material" (A, K) int16, "runtime_s"}}.  codes: part -> appearance code used in place of the generator's
    for those parts (a reader's estimate, :mod:`.part_code_probe`); None: the generator's own.
    """
    settings = settings or OracleSettings()
    part_ids = np.asarray(part_ids, np.int64)
    names = annotation.part_names
    if len(part_ids) != len(indices):
        raise UserError(f"{len(part_ids)} part labels for {len(indices)} occupied voxels")
    if len(part_ids) and (part_ids.min() < 0 or part_ids.max() >= len(names)):
        raise UserError(f"part labels outside 0..{len(names) - 1} (the annotation has parts {', '.join(names)})")
    t0 = time.perf_counter()
    moments = visible_part_moments(annotation, part_ids, indices, resolution, settings, codes)
    a = np.asarray(alphas, np.float64)
    seconds = time.perf_counter() - t0
    seen_from_outside = nearest_surface_parts(part_ids, indices, resolution)
    out = {}
    for name in (ORACLE, ORACLE_MIDPOINT, ORACLE_SURFACE):
        voxel_part = seen_from_outside if name == ORACLE_SURFACE else part_ids
        d = {"alphas": a, "material": np.tile(moments["material"][voxel_part], (len(a), 1)).astype(np.int16),
             "runtime_s": np.float64(seconds)}
        for q, key in _CHANNELS.items():
            lo, hi = moments[q]
            if name == ORACLE_MIDPOINT:
                per_part = np.tile(0.5 * (lo + hi), (len(a), 1))
            else:
                per_part = (1.0 - a)[:, None] * lo[None] + a[:, None] * hi[None]        # (A, P)
            d[key] = per_part[:, voxel_part].astype(np.float32)
        out[name] = d
    return out
