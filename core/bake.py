"""Baking simulations into keyframes: everything that does not touch Blender.

The Blender side (:mod:`unipixie.core.blender_io.bake`) reads an object into a
:class:`BakeObject` (plain numpy arrays), asks this module for the physics, and
writes what comes back as Blender data.  This module holds:

* :class:`BakeObject` — a mesh object as arrays: rest vertices in the object's
  local space (Blender units), triangles, ``matrix_world`` and the scene's unit
  scale; it converts between local coordinates and world metres.
* :func:`build_body` — the :class:`~unipixie.solvers.body.Body` a solver needs,
  with the checks a user needs (empty mesh, open mesh, zero-area faces, absurd
  sizes) as :class:`~unipixie.core.errors.UserError` or warnings.
* Material sources — *where the material comes from*: a homogeneous material,
  a :class:`~unipixie.core.types.MaterialField` file in the object's normalised
  cube, or the model's prediction at α.  Each is a :class:`MaterialSource`
  (``resolve(obj, alpha, solver) -> ResolvedMaterial``); the model plugs in with
  :func:`register_material_predictor`.
* :func:`simulate` — runs the chosen solver with progress and cancellation and
  returns a :class:`SimulationResult` (the trajectory plus what the writer needs).
* :class:`BackgroundRun` — runs :func:`simulate` in a worker thread so that the
  Blender UI stays responsive (Esc cancels through the shared ``Progress``).
* Output planning (:func:`choose_output`), the armature decomposition of LBS
  handle transforms (:func:`plan_armature`), the PC2 point-cache reader/writer,
  bake jobs, ``--shard`` splitting and job manifests.

Units: world positions are metres; Blender-local positions are Blender units
(metres divided by the scene's unit scale, in the object's own frame).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Optional, Sequence

import numpy as np

from .errors import UserError, read_json
from .progress import Progress, silent

# --------------------------------------------------------------------------- constants
BAKE_RECORD_KEY = "unipixie_bake"
"""ID property on a baked object holding the JSON record of everything the bake added."""
BAKE_RECORD_FORMAT = "unipixie.bake/1"
MANIFEST_FORMAT = "unipixie.bake-manifest/1"

OUTPUT_MODES = ("auto", "shape_keys", "mesh_cache", "armature")
"""How the motion is stored: ``auto`` picks per solver and size (see :func:`choose_output`)."""
OUTPUT_LABELS = {
    "auto": ("Automatic", "Armature for LBS when exact enough, else shape keys; a Mesh Cache (PC2) for large bakes"),
    "shape_keys": ("Shape keys", "One keyframed shape key per frame (stored in the .blend)"),
    "mesh_cache": ("Mesh Cache (PC2)", "A Mesh Cache modifier reading a PC2 file written next to the .blend"),
    "armature": ("Armature (LBS)", "One bone per LBS handle, vertex groups and an Armature modifier"),
}
INTERPOLATIONS = ("LINEAR", "CONSTANT")
"""Keyframe interpolation between frames; both give the exact trajectory at integer frames."""

SHAPE_KEY_VERTEX_FRAME_LIMIT = 2_000_000
"""``auto`` switches from shape keys to a Mesh Cache above this many vertices × frames (24 MB of keys)."""
MESH_CACHE_FRAME_LIMIT = 1000
"""``auto`` also uses a Mesh Cache above this many frames (a thousand shape keys is unwieldy in the UI)."""

SIZE_WARN_RANGE = (1e-3, 1e3)
"""Objects whose largest world extent (m) falls outside this range get a warning (real-world physics)."""
SIZE_REFUSE_RANGE = (1e-6, 1e5)
"""Outside this range (m) the bake is refused: almost certainly a unit or scale mistake."""

ARMATURE_TOLERANCE = 1e-4
"""Default largest allowed armature error, as a fraction of the object's size (0.1 mm for a 1 m object)."""

MATERIAL_SOURCES = ("homogeneous", "field", "model")
MATERIAL_SOURCE_LABELS = {
    "homogeneous": ("Homogeneous", "One material (class, E, ν, density) for the whole object"),
    "field": ("Field file", "A per-voxel material field (.npz, unipixie.material_field/1) in the object's normalised cube"),
    "model": ("Model at α", "The UniPixie model's prediction at the object's α"),
}
MATERIAL_RULE = ("a bake's material comes from exactly one source: the model at α (--alpha, with --features, "
                 "--checkpoint, --seed; manifest 'alpha' with material \"model\"), a material field file "
                 "(--material-file) or one homogeneous material (--E, --nu, --density, --material-class); a field or "
                 "homogeneous material has no α")
"""The rule the command line and manifests state when material options of several sources are mixed."""
DEFAULT_HOMOGENEOUS = {"E": 1.0e5, "nu": 0.3, "density": 1000.0, "material": "jelly"}
"""The panel's default homogeneous material (a soft jelly: E 100 kPa, ν 0.3, 1000 kg/m³)."""


# --------------------------------------------------------------------------- frames
@dataclass(frozen=True)
class FrameRange:
    """Scene frames ``start`` … ``end`` inclusive; ``start`` is the rest state (time 0)."""

    start: int
    end: int

    def __post_init__(self):
        if self.end < self.start:
            raise UserError(f"the frame range {self.start}-{self.end} is empty (end before start)")
        if self.end == self.start:
            raise UserError(f"the frame range {self.start}-{self.end} has a single frame: nothing moves; "
                            "give at least two frames")

    @property
    def count(self) -> int:
        return self.end - self.start + 1

    @property
    def frames(self) -> np.ndarray:
        """(T,) int64 frame numbers."""
        return np.arange(self.start, self.end + 1, dtype=np.int64)

    def times(self, fps: float) -> np.ndarray:
        """(T,) float64 seconds since ``start`` at ``fps`` frames per second."""
        if not (np.isfinite(fps) and fps > 0):
            raise UserError(f"frames per second must be positive, got {fps!r}")
        return (self.frames - self.start).astype(np.float64) / float(fps)

    def __str__(self) -> str:
        return f"{self.start}-{self.end}"


def parse_frames(text: str) -> FrameRange:
    """``"1-120"`` → FrameRange(1, 120) (negative frames allowed: ``"-10-20"``)."""
    m = re.fullmatch(r"\s*(-?\d+)\s*(?:-|:|\.\.)\s*(-?\d+)\s*", str(text))
    if not m:
        raise UserError(f"frame range {text!r}: expected START-END, e.g. 1-120")
    return FrameRange(int(m.group(1)), int(m.group(2)))


def parse_frame_list(text: str) -> list[FrameRange]:
    """``"1-120,200-260"`` → a batch of frame ranges (each baked as its own simulation)."""
    parts = str(text).split(",")
    if not any(p.strip() for p in parts):
        raise UserError("no frame range given")
    if not all(p.strip() for p in parts):
        raise UserError(f"frame ranges {text!r}: an empty range between commas; expected START-END[,START-END...], "
                        "e.g. 1-120,200-260")
    return [parse_frames(p) for p in parts]


# --------------------------------------------------------------------------- the object as arrays
@dataclass
class BakeObject:
    """A Blender mesh object as plain arrays.

    name: the object's name.
    rest_local: (N, 3) float64 rest vertex positions in the object's local space (Blender units).
    triangles: (F, 3) int64 vertex indices of the triangulated faces.
    matrix_world: (4, 4) float64 the object's world matrix (Blender units).
    unit_scale: metres per Blender unit (the scene's unit scale).
    properties: the object's bake settings as plain values (material, etc.; free-form).
    """

    name: str
    rest_local: np.ndarray
    triangles: np.ndarray
    matrix_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    unit_scale: float = 1.0
    properties: dict = field(default_factory=dict)

    def __post_init__(self):
        self.rest_local = np.asarray(self.rest_local, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        self.matrix_world = np.asarray(self.matrix_world, dtype=np.float64).reshape(4, 4)
        self.unit_scale = float(self.unit_scale)
        if len(self.rest_local) == 0:
            raise UserError(f"object '{self.name}': the mesh has no vertices")
        if len(self.triangles) == 0:
            raise UserError(f"object '{self.name}': the mesh has no faces (only loose vertices or edges); "
                            "a solid needs a closed surface")
        if not np.all(np.isfinite(self.rest_local)):
            raise UserError(f"object '{self.name}': the mesh has NaN or infinite vertex positions")
        if self.triangles.min() < 0 or self.triangles.max() >= len(self.rest_local):
            raise UserError(f"object '{self.name}': face indices out of range")
        if not (np.isfinite(self.unit_scale) and self.unit_scale > 0):
            raise UserError(f"the scene's unit scale must be positive, got {self.unit_scale!r}")
        if not np.all(np.isfinite(self.matrix_world)):
            raise UserError(f"object '{self.name}': its transform contains NaN/inf")
        det = float(np.linalg.det(self.matrix_world[:3, :3]))
        if abs(det) < 1e-30:
            raise UserError(f"object '{self.name}' has a zero scale on some axis (its transform is singular); "
                            "set its scale to non-zero values")

    @property
    def vertex_count(self) -> int:
        return int(self.rest_local.shape[0])

    @property
    def world_from_local(self) -> np.ndarray:
        """(4, 4) float64: Blender-local coordinates → world metres."""
        s = np.diag([self.unit_scale] * 3 + [1.0])
        return s @ self.matrix_world

    @property
    def local_from_world(self) -> np.ndarray:
        """(4, 4) float64: world metres → Blender-local coordinates."""
        return np.linalg.inv(self.world_from_local)

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """(..., 3) local (Blender units) → (..., 3) float64 world metres."""
        m = self.world_from_local
        return np.asarray(local, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]

    def to_local(self, world: np.ndarray) -> np.ndarray:
        """(..., 3) world metres → (..., 3) float64 local Blender units."""
        m = self.local_from_world
        return np.asarray(world, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]

    @property
    def rest_world(self) -> np.ndarray:
        """(N, 3) float64 rest vertex positions in world metres."""
        return self.to_world(self.rest_local)

    @property
    def size(self) -> float:
        """Largest extent of the world-space bounding box, metres."""
        w = self.rest_world
        return float(np.max(w.max(0) - w.min(0)))


def check_size(obj: BakeObject) -> list[str]:
    """Refuse absurd sizes, warn about unusual ones (returns the warnings)."""
    size = obj.size
    lo, hi = SIZE_REFUSE_RANGE
    if size <= 0:
        raise UserError(f"object '{obj.name}' has zero size (all its vertices coincide)")
    if size < lo or size > hi:
        raise UserError(f"object '{obj.name}' is {size:.3g} m across in the world, outside the range UniPixie "
                        f"simulates ({lo:g} m to {hi:g} m): check the object's scale and the scene's unit scale "
                        "(Scene Properties > Units)")
    wlo, whi = SIZE_WARN_RANGE
    if size < wlo or size > whi:
        return [f"object '{obj.name}' is {size:.3g} m across: the physics is simulated at this real-world size "
                "(object scale and scene unit scale applied); if that is not intended, change the scale"]
    return []


def build_body(obj: BakeObject, solver: str = "mpm", repair: bool = True):
    """The solid to simulate: a closed world-space mesh whose vertices are the tracked points.

    Returns ``(body, warnings)``.  Zero-area faces are removed and small holes filled (with a
    warning); a mesh that stays open after repair is refused (every solver fills the inside of
    the surface with material), with a message that says how to close it.
    """
    import trimesh

    from ..solvers.body import Body

    warnings = check_size(obj)
    world = obj.rest_world
    mesh = trimesh.Trimesh(vertices=world, faces=obj.triangles, process=False)
    area = mesh.area_faces
    if not np.any(area > 0):
        raise UserError(f"object '{obj.name}': every face has zero area (the mesh is flat to a line or point)")
    body = Body.from_mesh(mesh, tracked_points=world, repair=repair)
    open_note = [w for w in body.warnings if "not closed" in w]
    if open_note:
        boundary, non_manifold = _edge_defects(body.mesh)
        what = (f"open ({boundary} boundary edges remain after filling holes)" if boundary else
                f"not a closed surface ({non_manifold} edges are shared by more than two faces, or it is flat)")
        raise UserError(f"object '{obj.name}': the mesh is {what}, so it has no inside for the {solver} solver to "
                        "fill with material; close it (Edit Mode > Select All > Mesh > Clean Up > Fill Holes / "
                        "Merge by Distance, or add a Solidify modifier and apply it)")
    if float(body.mesh.volume) <= 0:
        raise UserError(f"object '{obj.name}': the closed mesh encloses no volume")
    return body, warnings + [f"object '{obj.name}': {w}" for w in body.warnings]


def _edge_defects(mesh) -> tuple[int, int]:
    """(boundary edges, edges shared by more than two faces) of a triangle mesh."""
    edges = np.sort(mesh.edges, axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int(np.sum(counts == 1)), int(np.sum(counts > 2))


# --------------------------------------------------------------------------- material sources
@dataclass
class ResolvedMaterial:
    """A material for one bake.

    spec: what the solver's ``prepare`` takes (HomogeneousMaterial, PointMaterial or a world-space
        MaterialField).
    settings: solver settings the source supplies (e.g. predicted LBS skinning parameters); merged
        under the user's explicit settings.
    description: one line for reports and the bake record.
    warnings: things the user should know.
    """

    spec: object
    settings: dict = field(default_factory=dict)
    description: str = ""
    warnings: list = field(default_factory=list)


class MaterialSource:
    """Where a bake's material comes from.  Subclasses implement :meth:`resolve`."""

    kind: str = ""

    def resolve(self, obj: BakeObject, alpha: Optional[float], solver: str) -> ResolvedMaterial:  # pragma: no cover
        raise NotImplementedError

    def to_dict(self) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError


@dataclass
class HomogeneousSource(MaterialSource):
    """One material for the whole object: E Pa, ν, density kg/m³ and a class from the registry.

    α does not change a homogeneous material (it is recorded only)."""

    E: float = DEFAULT_HOMOGENEOUS["E"]
    nu: float = DEFAULT_HOMOGENEOUS["nu"]
    density: float = DEFAULT_HOMOGENEOUS["density"]
    material: str = DEFAULT_HOMOGENEOUS["material"]
    kind = "homogeneous"

    def spec(self):
        from ..solvers.material_sampling import HomogeneousMaterial

        return HomogeneousMaterial(self.E, self.nu, self.density, self.material)

    def resolve(self, obj, alpha, solver):
        from ..solvers import materials

        spec = self.spec()
        cls = materials.get(spec.material)
        if not cls.simulated:
            raise UserError(f"material class '{cls.name}' carries no mass and cannot be simulated; choose another class")
        return ResolvedMaterial(spec, description=f"homogeneous {cls.name}: E {spec.E:.4g} Pa, ν {spec.nu:.3g}, "
                                                  f"density {spec.density:.4g} kg/m³")

    def to_dict(self) -> dict:
        return {"source": "homogeneous", "E": self.E, "nu": self.nu, "density": self.density, "class": self.material}


@dataclass
class FieldFileSource(MaterialSource):
    """A :class:`~unipixie.core.types.MaterialField` file.

    The field lives in the object's normalised cube (:mod:`unipixie.core.normalise`) unless its
    ``meta["space"]`` says ``"world"``; it is mapped onto the object's current world-space bounding box.
    """

    path: str = ""
    kind = "field"

    def resolve(self, obj, alpha, solver):
        from .normalise import Normalisation
        from .types import MaterialField

        if not self.path:
            raise UserError("no material field file given (set one in the panel or pass --material-file)")
        fieldd = MaterialField.load(self.path)
        from ..solvers.materials import NUM_CLASSES

        bad = fieldd.material[(fieldd.material < 0) | (fieldd.material >= NUM_CLASSES)]
        if bad.size:
            raise UserError(f"{self.path}: key 'material' holds class id(s) {sorted(set(bad.tolist()))[:5]} outside "
                            f"0..{NUM_CLASSES - 1} (the material classes of solvers/materials.py); the file is damaged "
                            "or was made by another version")
        warnings = []
        if fieldd.meta.get("space") == "world":
            world = fieldd
        else:
            norm = Normalisation.from_points(obj.rest_world)
            recorded = fieldd.meta.get("normalisation")
            if recorded:
                rec = Normalisation.from_dict(recorded)
                if (abs(rec.scale - norm.scale) > 1e-3 * norm.scale
                        or np.linalg.norm(np.subtract(rec.centre, norm.centre)) > 1e-3 * norm.scale):
                    warnings.append(f"the material field {Path(self.path).name} was made for a different placement "
                                    "or size of the object; it is mapped onto the object's current bounding box")
            world = norm.field_to_world(fieldd)
        if alpha is not None and np.isfinite(fieldd.alpha) and abs(float(alpha) - fieldd.alpha) > 1e-6:
            warnings.append(f"the material field was predicted for α = {fieldd.alpha:g}, not the requested "
                            f"α = {float(alpha):g}; the file is used as it is")
        desc = (f"field {Path(self.path).name}: {int(fieldd.occupancy.sum())} voxels, E {float(np.min(fieldd.E)):.3g}"
                f"–{float(np.max(fieldd.E)):.3g} Pa" + (f", α {fieldd.alpha:g}" if np.isfinite(fieldd.alpha) else ""))
        return ResolvedMaterial(world, description=desc, warnings=warnings)

    def to_dict(self) -> dict:
        return {"source": "field", "file": str(self.path)}


MaterialPredictor = Callable[[BakeObject, float, str], ResolvedMaterial]
"""``predictor(obj, alpha, solver) -> ResolvedMaterial``: the model's material for an object at α."""

_PREDICTORS: list[MaterialPredictor] = []


def register_material_predictor(predictor: MaterialPredictor) -> MaterialPredictor:
    """Make the model's prediction available to bakes (``material source = model``).

    The predictor receives the object as arrays, α in [0, 1] and the solver name, and returns a
    :class:`ResolvedMaterial` (a world-space material spec plus solver settings such as LBS
    skinning parameters).  The latest registration wins.  Usable as a decorator.  In Blender the
    predictor runs in the bake's worker thread: it must not touch ``bpy`` (read what it needs from
    Blender before the bake, e.g. into a cache keyed by the object's name).
    """
    if not callable(predictor):
        raise TypeError("a material predictor must be callable")
    _PREDICTORS.append(predictor)
    return predictor


def unregister_material_predictor(predictor: MaterialPredictor) -> None:
    if predictor in _PREDICTORS:
        _PREDICTORS.remove(predictor)


@dataclass
class ModelSource(MaterialSource):
    """The model's material at α.

    features: a FeatureGrid file of the object (``unipixie features``); with it, the model in
        ``checkpoint`` (default: the shipped model) predicts the material here
        (:func:`material_from_prediction`).  Without it, the predictor registered with
        :func:`register_material_predictor` is asked (the add-on's cached prediction); with neither,
        a :class:`UserError` says what is missing.
    seed: the model's noise seed (same seed, same material); device: torch device for the model.
    solver_heads: give LBS and spring-mass the material of their own heads (the LBS head's E, ν; the spring
        head's stiffnesses and softness) instead of the MPM head's continuum field, which all three solvers
        discretise the same way by default (:func:`material_from_prediction`).
    """

    features: str = ""
    checkpoint: str = ""
    seed: int = 0
    device: str = "cpu"
    solver_heads: bool = False
    kind = "model"

    def resolve(self, obj, alpha, solver):
        if alpha is None:
            raise UserError("the model's material needs α (a value in [0, 1]); pass --alpha or set α in the panel")
        alpha = float(alpha)
        if not 0.0 <= alpha <= 1.0:
            raise UserError(f"α must lie in [0, 1], got {alpha:g}")
        if self.features:
            return predict_material(obj, self.features, alpha, solver, checkpoint=self.checkpoint or None,
                                    seed=self.seed, device=self.device, solver_heads=self.solver_heads)
        if not _PREDICTORS:
            raise UserError(f"material prediction at α = {alpha:g} needs the UniPixie model and the object's feature "
                            "grid, and neither a feature grid (--features GRID.npz from 'unipixie features') nor a "
                            "prediction of the object is available ('unipixie bake --alpha' computes them unless "
                            "--no-auto); bake with a homogeneous material (--E/--nu/--density/--material-class) or a "
                            "material field file (--material-file) instead")
        predictor = _PREDICTORS[-1]
        resolved = (predictor(obj, alpha, solver, solver_heads=True) if self.solver_heads
                    else predictor(obj, alpha, solver))
        if not isinstance(resolved, ResolvedMaterial):
            raise TypeError(f"material predictor returned {type(resolved).__name__}, expected ResolvedMaterial")
        return resolved

    def to_dict(self) -> dict:
        d = {"source": "model"}
        if self.features:
            d.update(features=str(self.features), checkpoint=str(self.checkpoint), seed=self.seed)
        if self.solver_heads:
            d["solver_heads"] = True
        return d


MODEL_HEADS = {"mpm": ("mpm",), "lbs": ("mpm", "lbs"), "spring_mass": ("mpm", "spring_mass")}
"""Model heads each solver's material needs (the MPM head gives density and class to all)."""


def predict_material(obj: BakeObject, features, alpha: float, solver: str, checkpoint=None, seed: int = 0,
                     device: str = "cpu", solver_heads: bool = False) -> ResolvedMaterial:
    """Run the model on the object's feature grid at one α and turn its output into the solver's material."""
    from .model import predict
    from .types import FeatureGrid

    grid = FeatureGrid.load(features)
    pred = predict(grid, [alpha], heads=MODEL_HEADS[solver], seed=seed, checkpoint=checkpoint, device=device)
    res = material_from_prediction(obj, pred, 0, solver, solver_heads=solver_heads)
    res.description = f"model at α {alpha:g} ({Path(str(checkpoint or 'default model')).name}, seed {seed})"
    return res


def material_from_prediction(obj: BakeObject, prediction, index: int, solver: str,
                             solver_heads: bool = False) -> ResolvedMaterial:
    """The material for ``solver`` from a model prediction (``core.model.Prediction``) at ``prediction.alphas[index]``.

    Every solver gets the MPM head's continuum field (E, ν, ρ, class), mapped from the normalised cube onto the
    object's world bounding box, and discretises it its own way: one material, one motion whichever solver
    bakes it (docs/fidelity.md).  LBS also takes the LBS head's 650 skinning parameters (its handles' weights,
    a deformation basis, not a material).  With ``solver_heads`` LBS takes the LBS head's E, ν field instead
    (density and class from the MPM head) and spring-mass the spring head's per-anchor stiffness and softness
    as its explicit ``stiffness`` / ``softness`` — the paper's heads, fitted to imitate MPM motion with each
    solver's former discretisation (measured: the demo plant's spring-mass bake moved 84 cm with them, 15 cm
    with the continuum field, MPM 12 cm).
    """
    from .normalise import Normalisation

    if prediction.mpm is None:
        raise UserError("the prediction has no MPM head output (density and class are needed by every solver)")
    field_n = prediction.mpm[index]
    norm = Normalisation.from_points(obj.rest_world)
    alpha = float(prediction.alphas[index])
    if solver == "mpm":
        return ResolvedMaterial(norm.field_to_world(field_n), description=f"model at α {alpha:g}")
    if solver == "lbs":
        if prediction.lbs is None:
            raise UserError("the prediction has no LBS head output")
        lp = prediction.lbs[index]
        if not solver_heads:
            return ResolvedMaterial(norm.field_to_world(field_n), settings={"skinning_params": np.asarray(lp.params)},
                                    description=f"model at α {alpha:g} (LBS head's skinning)")
        lbs_field = dataclasses.replace(field_n, E=np.asarray(lp.E, np.float32), nu=np.asarray(lp.nu, np.float32))
        return ResolvedMaterial(norm.field_to_world(lbs_field), settings={"skinning_params": np.asarray(lp.params)},
                                description=f"model at α {alpha:g} (LBS head)")
    if solver == "spring_mass":
        if not solver_heads:
            return ResolvedMaterial(norm.field_to_world(field_n), description=f"model at α {alpha:g}")
        if prediction.spring_mass is None:
            raise UserError("the prediction has no spring-mass head output")
        sp = prediction.spring_mass[index]
        k = np.asarray(sp.stiffness, np.float64)
        return ResolvedMaterial(norm.field_to_world(field_n),
                                settings={"stiffness": k, "softness": float(sp.softness), "anchors": int(len(k))},
                                description=f"model at α {alpha:g} (spring head)")
    raise UserError(f"unknown solver {solver!r}")


def material_source_from_dict(d) -> MaterialSource:
    """Parse a manifest's ``material`` value: ``"model"``, ``{"file": path}`` or
    ``{"E": .., "nu": .., "density": .., "class": ..}`` (missing keys take the panel defaults)."""
    if d is None or d == "model":
        return ModelSource()
    if isinstance(d, dict) and (d.get("source") == "model" or "features" in d):
        unknown = set(d) - {"source", "features", "checkpoint", "seed", "solver_heads"}
        if unknown:
            raise UserError(f"'material' (model) has unknown key(s) {sorted(unknown)}; use features, checkpoint, seed, "
                            "solver_heads")
        if "seed" in d:
            from ..solvers.scenario import require_json_numbers

            require_json_numbers(d["seed"], "'material' (model) key 'seed'")
        if not isinstance(d.get("solver_heads", False), bool):
            raise UserError(f"'material' (model): solver_heads must be true or false, got {d['solver_heads']!r}")
        return ModelSource(features=str(d.get("features", "")), checkpoint=str(d.get("checkpoint", "") or ""),
                           seed=int(d.get("seed", 0)), solver_heads=d.get("solver_heads", False))
    if isinstance(d, str):
        return FieldFileSource(d)
    if not isinstance(d, dict):
        raise UserError(f"'material' must be \"model\", a field file path or an object with E/nu/density/class, got {d!r}")
    if "file" in d or d.get("source") == "field":
        if not d.get("file"):
            raise UserError("'material': a field source needs 'file'")
        return FieldFileSource(str(d["file"]))
    unknown = set(d) - {"source", "E", "nu", "density", "class", "material"}
    if unknown:
        raise UserError(f"'material' has unknown key(s) {sorted(unknown)}; use E, nu, density, class or file")
    from ..solvers.scenario import require_json_numbers

    for k in ("E", "nu", "density"):
        if k in d:
            require_json_numbers(d[k], f"'material' key '{k}'")
    try:
        return HomogeneousSource(E=float(d.get("E", DEFAULT_HOMOGENEOUS["E"])),
                                 nu=float(d.get("nu", DEFAULT_HOMOGENEOUS["nu"])),
                                 density=float(d.get("density", DEFAULT_HOMOGENEOUS["density"])),
                                 material=str(d.get("class", d.get("material", DEFAULT_HOMOGENEOUS["material"]))))
    except (TypeError, ValueError):
        raise UserError(f"'material': E, nu and density must be numbers, got {d!r}") from None


# --------------------------------------------------------------------------- the request and its simulation
@dataclass
class BakeOptions:
    """Everything a bake needs besides the object and the scenario.

    solver: ``"mpm"``, ``"lbs"`` or ``"spring_mass"``.
    frames: the scene frames to bake; fps: frames per second of the scene.
    material: a :class:`MaterialSource`; alpha: the soft-to-stiff control in [0, 1] (or ``None``).
    effects: registry effects (``solvers.effects.Effect``) or their CLI specs (``"linear_drag:c=0.5"``).
    device: ``cpu`` / ``cuda`` / ``cuda:N`` / ``auto``.
    output: one of :data:`OUTPUT_MODES`.  interpolation: one of :data:`INTERPOLATIONS`.
    particles: MPM only — also make a point-cloud object of the particles with attributes.
    armature_tolerance: LBS armature error allowed, as a fraction of the object's size.
    solver_settings: passed to the solver's ``prepare(settings=...)`` (dict or settings object).
    cache_dir: where Mesh Cache PC2 files go (``None``: next to the .blend).
    """

    solver: str = "mpm"
    frames: FrameRange = field(default_factory=lambda: FrameRange(1, 48))
    fps: float = 24.0
    material: MaterialSource = field(default_factory=HomogeneousSource)
    alpha: Optional[float] = None
    effects: list = field(default_factory=list)
    device: str = "cpu"
    output: str = "auto"
    interpolation: str = "LINEAR"
    particles: bool = False
    armature_tolerance: float = ARMATURE_TOLERANCE
    solver_settings: object = None
    cache_dir: Optional[str] = None
    allow_long: bool = False
    """Run even when the up-front cost estimate (:mod:`unipixie.core.cost`) passes the long-job limit."""

    def __post_init__(self):
        from ..solvers import effects as effects_mod
        from ..solvers.api import canonical_solver

        self.solver = canonical_solver(self.solver)
        if isinstance(self.frames, str):
            self.frames = parse_frames(self.frames)
        elif not isinstance(self.frames, FrameRange):
            a, b = self.frames
            self.frames = FrameRange(int(a), int(b))
        self.fps = float(self.fps)
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise UserError(f"frames per second must be positive, got {self.fps!r}")
        if self.alpha is not None:
            self.alpha = float(self.alpha)
            if not 0.0 <= self.alpha <= 1.0:
                raise UserError(f"α must lie in [0, 1], got {self.alpha:g}")
        parsed = []
        for e in self.effects or []:
            if isinstance(e, str):
                parsed.append(effects_mod.parse(e))
            elif isinstance(e, dict):
                parsed.append(effects_mod.from_dict(e))
            else:
                parsed.append(e)
        effects_mod.check_supported(parsed, self.solver)
        self.effects = parsed
        if self.output not in OUTPUT_MODES:
            raise UserError(f"unknown output {self.output!r}; choose one of {', '.join(OUTPUT_MODES)}")
        if self.output == "armature" and self.solver != "lbs":
            raise UserError(f"an armature bake needs the LBS solver (its handles become bones), not {self.solver}")
        self.interpolation = str(self.interpolation).upper()
        if self.interpolation not in INTERPOLATIONS:
            raise UserError(f"unknown interpolation {self.interpolation!r}; choose LINEAR or CONSTANT")
        if self.particles and self.solver != "mpm":
            raise UserError("a particle object is made for MPM bakes only (other solvers have no particles)")
        self.armature_tolerance = float(self.armature_tolerance)
        if not self.armature_tolerance >= 0:
            raise UserError("the armature tolerance must be a non-negative fraction of the object's size")

    def times(self) -> np.ndarray:
        return self.frames.times(self.fps)


@dataclass
class SimulationResult:
    """What the Blender writer needs from a simulation.

    trajectory: the solver's Trajectory (world metres; positions of the object's vertices).
    skinning_weights: LBS only — (N, H+1) float64 handle weights of the vertices, the constant handle
        last, as the LBS solver defines them (see :func:`lbs_blend_form`).
    material_description / warnings / seconds: for the report and the bake record.
    ground_height: world z (metres) of the ground plane the run used, or None; an armature bake
        keeps the skinned vertices above it as the solver's tracked points are (:func:`plan_armature`).
    """

    trajectory: object
    skinning_weights: Optional[np.ndarray] = None
    material_description: str = ""
    warnings: list = field(default_factory=list)
    seconds: float = 0.0
    ground_height: Optional[float] = None


def simulate(obj: BakeObject, scenario, options: BakeOptions, progress: Optional[Progress] = None) -> SimulationResult:
    """Resolve the material, build the body, run the solver (cancellable through ``progress``).

    Raises :class:`UserError` for bad input and
    :class:`~unipixie.core.errors.CancelledError` when ``progress`` is cancelled.
    """
    from ..solvers import api
    from ..solvers.warp_runtime import resolve_device

    progress = progress or silent()
    t0 = time.perf_counter()
    progress.set_status("checking the mesh")
    body, warnings = build_body(obj, options.solver)
    if scenario.ground_height is not None:
        lowest = float(body.rest_points[:, 2].min())
        if lowest < scenario.ground_height - 1e-6 * max(obj.size, 1e-9):
            warnings.append(f"object '{obj.name}' starts {scenario.ground_height - lowest:.3g} m below the ground "
                            "plane; the ground will push it up")
    progress.set_status("resolving the material")
    resolved = options.material.resolve(obj, options.alpha, options.solver)
    warnings.extend(resolved.warnings)
    settings = _merge_settings(resolved.settings, options.solver_settings)
    from .cost import estimate

    est = estimate(f"baking '{obj.name}'", options.solver, size=max(float(obj.size), 1e-9), times=options.times(),
                   material_spec=resolved.spec, points=obj.vertex_count, settings=settings)
    est.check(options.allow_long, remedy="bake fewer frames or use a coarser solver setting")
    progress.set_status(f"estimated cost: {est.describe()}")
    device = resolve_device(options.device)
    progress.set_status(f"preparing the {options.solver} simulation")
    sim = api.prepare(options.solver, body, resolved.spec, scenario, options.times(), device=device,
                      settings=settings, progress=progress)
    progress.set_status(f"simulating {options.frames.count} frames")
    traj = sim.run(options.effects, progress=FrameProgress(progress, options.frames.count - 1),
                   particle_states=bool(options.particles))
    check_trajectory(traj, obj.vertex_count, options.frames.count, obj.name)
    weights = None
    if options.solver == "lbs":
        weights = lbs_vertex_weights(sim, traj, obj)
    return SimulationResult(traj, skinning_weights=weights, material_description=resolved.description,
                            warnings=warnings, seconds=time.perf_counter() - t0,
                            ground_height=scenario.ground_height)


class FrameProgress(Progress):
    """Forwards a solver's per-frame ``step`` calls to ``parent`` as a fraction of ``frames``.

    Solvers advance their progress once per simulated frame but in different units (one step, or
    1/(T−1)); counting the calls gives the same fraction for all.  Status text and cancellation are
    passed through.
    """

    def __init__(self, parent: Progress, frames: int):
        super().__init__(total=1.0, description=parent.description, show_bar=False)
        self.parent = parent
        self._cancel = parent._cancel
        self.frames = max(int(frames), 1)
        self.calls = 0

    def step(self, amount: float = 1.0, status: str | None = None) -> None:
        if amount > 0:
            self.calls += 1
        target = min(self.calls, self.frames) / self.frames * self.parent.total
        self.parent.step(max(0.0, target - self.parent.done), status)


def _merge_settings(source_settings, user_settings):
    if not source_settings:
        return user_settings
    if user_settings is None:
        return dict(source_settings)
    if isinstance(user_settings, dict):
        return {**source_settings, **user_settings}
    for k, v in source_settings.items():  # a settings object: fill what the user left at its default
        if hasattr(user_settings, k):
            setattr(user_settings, k, v)
    return user_settings


def check_trajectory(traj, n_vertices: int, n_frames: int, name: str = "") -> None:
    """Refuse a trajectory that does not fit the object (wrong shapes, NaN): never write garbage."""
    pos = np.asarray(traj.positions)
    if pos.shape != (n_frames, n_vertices, 3):
        raise UserError(f"object '{name}': the solver returned positions of shape {pos.shape}, expected "
                        f"{(n_frames, n_vertices, 3)} (frames, vertices, 3)")
    if not np.all(np.isfinite(pos)):
        from .errors import SimulationDiverged

        bad_t = int(np.argmax(~np.all(np.isfinite(pos), axis=(1, 2))))
        raise SimulationDiverged(f"object '{name}': the simulation produced NaN/inf positions at frame index {bad_t}; "
                                 "try a smaller time step or a softer material")


def lbs_vertex_weights(sim, traj, obj: BakeObject) -> Optional[np.ndarray]:
    """(N, H+1) skinning weights of the vertices (the constant handle last) from the LBS simulation
    (``sim.weights(points)``, :mod:`unipixie.solvers.lbs`); ``None`` if it has none that fit the
    handles (the bake then stores the motion per vertex)."""
    fn = getattr(sim, "weights", None)
    if traj.handle_transforms is None or not callable(fn):
        return None
    w = np.asarray(fn(np.asarray(sim.tracked_rest, dtype=np.float64)), dtype=np.float64)
    return w if w.shape == (obj.vertex_count, traj.handle_transforms.shape[1]) else None


class BackgroundRun:
    """Run ``work(progress)`` in a daemon thread; the caller polls and may cancel.

    The Blender operator yields between polls so the UI stays responsive; cancelling sets the
    shared :class:`Progress`'s flag, which the solver checks at every step.
    """

    def __init__(self, work: Callable[[Progress], object], description: str = ""):
        self.progress = Progress(description=description, show_bar=False)
        self._work = work
        self._result = None
        self._error: Optional[BaseException] = None
        self._thread = threading.Thread(target=self._main, name="unipixie-bake", daemon=True)

    def _main(self):
        try:
            self._result = self._work(self.progress)
        except BaseException as exc:  # handed to the caller's thread
            self._error = exc

    def start(self) -> "BackgroundRun":
        self._thread.start()
        return self

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: Optional[float] = None) -> bool:
        self._thread.join(timeout)
        return self.done

    @property
    def fraction(self) -> float:
        return self.progress.fraction

    @property
    def status(self) -> str:
        return self.progress.status or ""

    def cancel(self, wait: bool = True) -> None:
        self.progress.cancel()
        if wait and self._thread.is_alive():
            self._thread.join()

    def result(self):
        """The work's return value; re-raises its exception in the caller's thread."""
        if not self.done:
            raise RuntimeError("the background run has not finished")
        if self._error is not None:
            raise self._error
        return self._result


# --------------------------------------------------------------------------- output planning
def choose_output(solver: str, requested: str, n_vertices: int, n_frames: int, *, has_other_shape_keys: bool = False,
                  mesh_shared: bool = False) -> tuple[str, list[str]]:
    """Pick how to store the motion; returns ``(mode, notes)``.

    ``auto``: LBS → ``armature`` (the writer falls back to shape keys/Mesh Cache when the handle
    transforms are not representable); otherwise shape keys unless the bake is large
    (> :data:`SHAPE_KEY_VERTEX_FRAME_LIMIT` vertex-frames or > :data:`MESH_CACHE_FRAME_LIMIT` frames),
    the mesh already has shape keys of its own, or the mesh data is shared by several objects —
    those use a Mesh Cache modifier, which leaves the mesh data untouched.
    """
    notes: list[str] = []
    if requested not in OUTPUT_MODES:
        raise UserError(f"unknown output {requested!r}; choose one of {', '.join(OUTPUT_MODES)}")
    if requested == "armature" and solver != "lbs":
        raise UserError(f"an armature bake needs the LBS solver, not {solver}")
    if requested == "shape_keys":
        if has_other_shape_keys:
            raise UserError("the mesh already has shape keys of its own; a shape-key bake would mix with them — "
                            "choose the Mesh Cache output (or remove the mesh's shape keys)")
        if mesh_shared:
            raise UserError("the mesh data is shared by several objects; shape keys would move all of them — "
                            "choose the Mesh Cache output (or make the mesh single-user)")
        return "shape_keys", notes
    if requested in ("mesh_cache", "armature"):
        return requested, notes
    if solver == "lbs":
        return "armature", notes
    return vertex_output(n_vertices, n_frames, has_other_shape_keys, mesh_shared, notes), notes


def vertex_output(n_vertices: int, n_frames: int, has_other_shape_keys: bool, mesh_shared: bool,
                  notes: list[str]) -> str:
    """Shape keys or Mesh Cache for per-vertex motion (the ``auto`` rule of :func:`choose_output`)."""
    if has_other_shape_keys:
        notes.append("the mesh has shape keys of its own: the motion is stored in a Mesh Cache (PC2) instead")
        return "mesh_cache"
    if mesh_shared:
        notes.append("the mesh data is shared by several objects: the motion is stored in a Mesh Cache (PC2) instead")
        return "mesh_cache"
    if n_vertices * n_frames > SHAPE_KEY_VERTEX_FRAME_LIMIT or n_frames > MESH_CACHE_FRAME_LIMIT:
        notes.append(f"{n_vertices} vertices × {n_frames} frames is a large bake: stored in a Mesh Cache (PC2)")
        return "mesh_cache"
    return "shape_keys"


def trajectory_to_local(obj: BakeObject, positions: np.ndarray) -> np.ndarray:
    """(T, N, 3) world metres → (T, N, 3) float32 object-local Blender units."""
    return obj.to_local(np.asarray(positions, dtype=np.float64)).astype(np.float32)


# --------------------------------------------------------------------------- LBS handles → bones
def _safe_scale(A: np.ndarray, D: np.ndarray, margin: float = 0.5) -> float:
    """Largest s ≥ 0 (times ``margin``) such that det(A_t + s' D_t) stays positive for all s' ≤ s and all t.

    A, D: (T, 3, 3).  det(A + sD) = det A · det(I + sM), M = A⁻¹D, a cubic in s whose smallest positive
    real root is where the bone map would collapse.
    """
    try:
        M = np.linalg.solve(A, D)
    except np.linalg.LinAlgError:
        return np.inf  # a singular constant handle: refused by the caller anyway
    c1 = np.trace(M, axis1=-2, axis2=-1)
    c2 = 0.5 * (c1 ** 2 - np.trace(M @ M, axis1=-2, axis2=-1))
    c3 = np.linalg.det(M)
    # 1 + c1 s + c2 s² + c3 s³ = 0  ⇔  u³ + c1 u² + c2 u + c3 = 0 with u = 1/s (monic: batched companion eigenvalues)
    comp = np.zeros((len(M), 3, 3))
    comp[:, 0, :] = -np.stack([c1, c2, c3], axis=1)
    comp[:, 1, 0] = 1.0
    comp[:, 2, 1] = 1.0
    u = np.linalg.eigvals(comp)
    real = (np.abs(u.imag) <= 1e-9 * np.maximum(1.0, np.abs(u))) & (u.real > 0)
    if not np.any(real):
        return np.inf
    return margin / float(np.max(u.real[real]))


def lbs_blend_form(weights: np.ndarray, handle_transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
    """Rewrite the LBS solver's motion as a convex blend of absolute affine maps (what an armature does).

    The LBS solver (:mod:`unipixie.solvers.lbs`) moves a rest point X (world metres) as
    ``x = A [X; 1] + Σ_{h<H} w_h(X) D_h [X; 1]`` with ``A = handle_transforms[:, H]`` (the constant
    handle, a full affine map) and ``D_h = handle_transforms[:, h]`` displacement maps; ``weights``
    are (N, H+1) with the last column 1.  This equals ``Σ_b ω_b(X) M_b [X; 1]`` for the bones
    ``M_const = A`` and ``M_h± = A ± k_h± D_h`` with weights ``ω_h± = w_h±(X) / k_h±`` (the positive
    and negative parts of w_h) and ``ω_const = 1 − Σ ω_h±``: weights in [0, 1] summing to 1, as
    Blender's Armature modifier needs, for any scales k with ``Σ_h w_h±/k_h± ≤ 1`` at every vertex.
    The scales are chosen as small as that allows but proportional to the largest scale at which
    each bone map stays orientation-preserving over the whole motion (half the distance to
    collapse), so that the bones are proper (rotation × stretch) maps whenever that is possible.
    Bones whose weight is zero everywhere are dropped.

    Returns ``(maps (T, B, 4, 4) world-space, bone_weights (N, B), labels)`` with labels such as
    ``"constant"``, ``"03+"``, ``"03-"``; a bone map may still have det ≤ 0 when the motion is too
    large for any choice (the caller refuses those).
    """
    W = np.asarray(weights, dtype=np.float64)
    HT = np.asarray(handle_transforms, dtype=np.float64)
    T, H1 = HT.shape[:2]
    H = H1 - 1
    if W.ndim != 2 or W.shape[1] != H1:
        raise ValueError(f"weights must be (N, {H1}), got {W.shape}")

    def affine(m):
        out = np.zeros(m.shape[:-2] + (4, 4))
        out[..., :3, :] = m
        out[..., 3, 3] = 1.0
        return out

    A = affine(HT[:, H])
    parts, limits = [], []
    for h in range(H):
        for sign in (1.0, -1.0):
            part = np.clip(sign * W[:, h], 0.0, None)
            if np.any(part > 0):
                lim = _safe_scale(A[:, :3, :3], sign * HT[:, h, :, :3])
                parts.append((h, sign, part))
                limits.append(lim if np.isfinite(lim) else None)
    finite = [x for x in limits if x is not None]
    fallback = max(finite) if finite else 1.0
    scales = np.array([x if x is not None else fallback for x in limits])
    if parts:
        load = sum(p / sc for (_, _, p), sc in zip(parts, scales))  # (N,) Σ w±/s± per vertex
        lam = float(np.max(load))
        scales = scales * max(lam, 1e-12)  # smallest scales keeping the constant weight ≥ 0
    maps = [A]
    bone_w = [np.ones(len(W))]
    labels = ["constant"]
    for (h, sign, part), k in zip(parts, scales):
        D = np.zeros((T, 4, 4))
        D[:, :3, :] = HT[:, h]
        maps.append(A + sign * k * D)
        bone_w.append(part / k)
        bone_w[0] = bone_w[0] - part / k
        labels.append(f"{h:02d}{'+' if sign > 0 else '-'}")
    return np.stack(maps, axis=1), np.clip(np.stack(bone_w, axis=1), 0.0, 1.0), labels


@dataclass
class ArmaturePlan:
    """Bones that reproduce an LBS motion in Blender's Armature modifier (object-local space).

    Each bone b of the blend (:func:`lbs_blend_form`) is a chain of two bones with the same head
    ``heads[b]`` and identity rest orientation (pointing along +Y): a non-deforming *parent* keyed
    with location ``parent_location``, rotation ``parent_rotation`` (U) and scale ``parent_scale`` (Σ),
    and a deforming *child* (inherits rotation and scale) keyed with rotation ``child_rotation``
    (Vᵀ).  Their product is ``U Σ Vᵀ``, the singular value decomposition of the bone's affine map,
    so any orientation-preserving affine map — shear and stretch along turning axes included — is
    exact at every frame.

    heads: (B, 3) object-local; quaternions are (T, B, 4) w-x-y-z; scales (T, B, 3).
    local_maps: (T, B, 4, 4) the bones' affine maps in object-local coordinates.
    weights: (N, B) float32 vertex-group weights in [0, 1], summing to 1 per vertex.
    labels: which LBS handle each bone comes from.
    max_error: largest distance (metres) between the armature's result and the trajectory.
    bone_length: display length of the bones, Blender units.
    ground_height: world z (metres) below which no vertex may go (a ground modifier after the
        Armature lifts them onto it), or None when no vertex dips below the ground.
    """

    heads: np.ndarray
    local_maps: np.ndarray
    parent_location: np.ndarray
    parent_rotation: np.ndarray
    parent_scale: np.ndarray
    child_rotation: np.ndarray
    weights: np.ndarray
    labels: list
    max_error: float
    bone_length: float
    ground_height: Optional[float] = None

    @property
    def bone_count(self) -> int:
        return int(self.heads.shape[0])


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(…, 3, 3) rotation matrices → (…, 4) unit quaternions (w, x, y, z), Blender's order."""
    from scipy.spatial.transform import Rotation

    shape = R.shape[:-2]
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()  # x, y, z, w
    return np.concatenate([q[:, 3:4], q[:, :3]], axis=1).reshape(*shape, 4)


def _matrix_from_quat(q: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    shape = q.shape[:-1]
    q = q.reshape(-1, 4)
    return Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], axis=1)).as_matrix().reshape(*shape, 3, 3)


def _continuous_quaternions(q: np.ndarray) -> np.ndarray:
    """(T, …, 4): flip signs so consecutive frames lie on one hemisphere (interpolation takes the short way)."""
    q = q.copy()
    for t in range(1, q.shape[0]):
        flip = np.sum(q[t] * q[t - 1], axis=-1) < 0
        q[t][flip] *= -1.0
    return q


def continuous_svd(L: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, 3, 3) with det > 0 → (U, s, V) with L = U diag(s) Vᵀ, U and V proper rotations, s > 0, and the
    columns of V matched frame to frame (order and sign) so that the keyed rotations change smoothly."""
    import itertools

    T = L.shape[0]
    U, s, Vt = np.linalg.svd(L)
    V = np.swapaxes(Vt, -1, -2)
    fix = np.linalg.det(V) < 0  # det L > 0: det U = det V; make both proper
    V[fix, :, 2] *= -1
    U[fix, :, 2] *= -1
    perms = np.array(list(itertools.permutations(range(3))))
    rows = np.arange(3)
    for t in range(1, T):
        M = np.abs(V[t - 1].T @ V[t])
        best = perms[int(np.argmax(M[rows, perms].sum(1)))]
        V[t], U[t], s[t] = V[t][:, best], U[t][:, best], s[t][best]
        signs = np.sign(np.sum(V[t - 1] * V[t], axis=0))
        signs[signs == 0] = 1.0
        if np.prod(signs) < 0:  # keep V proper: leave the least aligned axis unflipped
            k = int(np.argmin(np.abs(np.sum(V[t - 1] * V[t], axis=0))))
            signs[k] *= -1
        V[t] *= signs
        U[t] *= signs
        if np.linalg.det(V[t]) < 0:  # an odd permutation: flip the least aligned axis of both
            k = int(np.argmin(np.abs(np.sum(V[t - 1] * V[t], axis=0))))
            V[t][:, k] *= -1
            U[t][:, k] *= -1
    return U, s, V


def chain_channels(local_maps: np.ndarray, heads: np.ndarray):
    """Pose channels of the parent/child bone chains (see :class:`ArmaturePlan`).

    local_maps: (T, B, 4, 4) object-local affine maps (det > 0); heads: (B, 3) the bones' rest heads.
    Returns parent location (T, B, 3), parent rotation (T, B, 4), parent scale (T, B, 3), child rotation (T, B, 4).
    """
    T, B = local_maps.shape[:2]
    loc = np.zeros((T, B, 3))
    scale = np.zeros((T, B, 3))
    Uq = np.zeros((T, B, 4))
    Vq = np.zeros((T, B, 4))
    for b in range(B):
        A = local_maps[:, b, :3, :3]
        U, s, V = continuous_svd(A)
        h = heads[b]
        # child: x → Vᵀ(x − h) + h; parent: y → U Σ (y − h) + h + t  ⇒  t = b + A h − h
        loc[:, b] = local_maps[:, b, :3, 3] + A @ h - h
        scale[:, b] = s
        Uq[:, b] = _quat_from_matrix(U)
        Vq[:, b] = _quat_from_matrix(np.swapaxes(V, -1, -2))
    return loc, _continuous_quaternions(Uq), scale, _continuous_quaternions(Vq)


def chain_deform(heads: np.ndarray, loc: np.ndarray, Uq: np.ndarray, scale: np.ndarray, Vq: np.ndarray) -> np.ndarray:
    """(T, B, 4, 4) deform matrices Blender builds from the chain channels (parent ∘ child, rest = Tr(head))."""
    T, B = loc.shape[:2]
    U = _matrix_from_quat(Uq)
    Vt = _matrix_from_quat(Vq)
    lin = U * scale[..., None, :] @ Vt
    out = np.zeros((T, B, 4, 4))
    out[..., :3, :3] = lin
    # x → U Σ (Vᵀ(x − h) + h − h) + h + t = lin x − lin h + h + t
    out[..., :3, 3] = -np.einsum("tbij,bj->tbi", lin, heads) + heads[None] + loc
    out[..., 3, 3] = 1.0
    return out


def armature_deform(rest_local: np.ndarray, weights: np.ndarray, deform: np.ndarray) -> np.ndarray:
    """What Blender's Armature modifier computes (linear blending, vertex groups, no preserve-volume).

    rest_local: (N, 3); weights: (N, B) ≥ 0; deform: (T, B, 4, 4) bone deform matrices
    (pose matrix × rest matrix⁻¹).  Weights are normalised per vertex; vertices with total weight
    ≤ 1e-4 stay at rest (as in Blender).  Returns (T, N, 3) float64.
    """
    x = np.asarray(rest_local, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    total = w.sum(1)
    ok = total > 1e-4
    wn = np.where(ok[:, None], w / np.where(ok, total, 1.0)[:, None], 0.0)
    T, B = deform.shape[:2]
    x1 = np.concatenate([x, np.ones((len(x), 1))], axis=1)
    moved = np.empty((T, len(x), 3))
    for t in range(T):  # per frame: blended (N, 3, 4) matrices by one GEMM, then applied per vertex
        blended = (wn @ deform[t, :, :3, :].reshape(B, 12)).reshape(len(x), 3, 4)
        moved[t] = (blended * x1[:, None, :]).sum(-1)
    return np.where(ok[None, :, None], moved, x[None])


def plan_armature(obj: BakeObject, weights: np.ndarray, handle_transforms: np.ndarray, positions: np.ndarray,
                  tolerance: float = ARMATURE_TOLERANCE,
                  ground_height: Optional[float] = None) -> tuple[Optional[ArmaturePlan], str]:
    """Map an LBS motion to bones, or explain why it cannot be done.

    weights: (N, H+1) vertex weights (last = the constant handle); handle_transforms: (T, H+1, 3, 4)
    in the LBS solver's form (:func:`lbs_blend_form`); positions: (T, N, 3) the trajectory (world
    metres) the armature must reproduce; tolerance: allowed error as a fraction of the object's size.

    The blend's bone maps are conjugated into the object's local space (``L = S⁻¹ M S``, S the
    world-from-local matrix) and each becomes a parent/child bone chain keyed with its singular
    value decomposition (:class:`ArmaturePlan`).  Refused (``(None, reason)``) when a bone map
    mirrors or collapses space (det ≤ 0: no rotation and positive scale can make it), or when the
    motion evaluated exactly as the Armature modifier does misses the trajectory by more than
    ``tolerance × size``.

    ground_height: world z (metres) of the ground plane, or None.  The contact law lets the skinned
    surface dip into the ground between its contact samples; the solver lifts its tracked points back
    onto the plane (:mod:`unipixie.solvers.contact`), which no bone can do.  The armature's result is
    then evaluated with the same lift, done in Blender by a ground modifier after the Armature
    (``ArmaturePlan.ground_height``; set only when some vertex needs it).
    """
    W = np.asarray(weights, dtype=np.float64)
    N = obj.vertex_count
    if W.ndim != 2 or W.shape[0] != N or handle_transforms is None or W.shape[1] != np.shape(handle_transforms)[1]:
        return None, f"the skinning weights have shape {W.shape}, which does not fit {N} vertices and the handles"
    maps, bone_w, labels = lbs_blend_form(W, handle_transforms)
    S = obj.world_from_local
    L = np.linalg.inv(S) @ maps @ S
    det = np.linalg.det(L[..., :3, :3])
    if np.any(det <= 0):
        return None, ("the deformation is too large for bones: a handle's map, scaled by the range of its weights, "
                      "would mirror or collapse space, which no rotation and scale can do")
    x0 = obj.rest_local
    wsum = bone_w.sum(0)
    heads = np.where(wsum[:, None] > 1e-9, (bone_w.T @ x0) / np.maximum(wsum, 1e-12)[:, None], x0.mean(0))
    loc, Uq, scale, Vq = chain_channels(L, heads)
    moved = obj.to_world(armature_deform(x0, bone_w, chain_deform(heads, loc, Uq, scale, Vq)))
    lifted = None
    if ground_height is not None and float(moved[..., 2].min()) < ground_height:
        lifted = float(ground_height)
        np.maximum(moved[..., 2], lifted, out=moved[..., 2])
    err = float(np.max(np.linalg.norm(moved - np.asarray(positions, dtype=np.float64), axis=-1)))
    limit = tolerance * max(obj.size, 1e-12)
    if not err <= limit:
        return None, (f"the armature misses the LBS motion by {err:.3g} m (allowed {limit:.3g} m): the vertex "
                      "weights do not reproduce the solver's skinning")
    bone_length = 0.1 * float(np.max(x0.max(0) - x0.min(0)) or 1.0)
    return ArmaturePlan(heads=heads, local_maps=L, parent_location=loc, parent_rotation=Uq, parent_scale=scale,
                        child_rotation=Vq, weights=bone_w.astype(np.float32), labels=labels, max_error=err,
                        bone_length=bone_length, ground_height=lifted), ""


# --------------------------------------------------------------------------- PC2 point caches
PC2_SIGNATURE = b"POINTCACHE2\0"
PC2_VERSION = 1
_PC2_HEADER = np.dtype([("signature", "S12"), ("version", "<i4"), ("points", "<i4"), ("start", "<f4"),
                        ("rate", "<f4"), ("samples", "<i4")])


def write_pc2(path, positions: np.ndarray, start_frame: float = 0.0, sample_rate: float = 1.0) -> Path:
    """Write a PC2 point cache (the format of Blender's Mesh Cache modifier and 3ds Max).

    positions: (T, N, 3) float32, object-local coordinates.  start_frame / sample_rate: header fields
    (frame of the first sample, frames between samples).  The file is written to a temporary name and
    renamed (:mod:`unipixie.core.atomic_io`, size checked), so a reader never sees a half-written cache.
    """
    pos = np.ascontiguousarray(np.asarray(positions, dtype="<f4"))
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] < 1 or pos.shape[1] < 1:
        raise UserError(f"a PC2 cache needs positions of shape (samples, points, 3), got {pos.shape}")
    if not np.all(np.isfinite(pos)):
        raise UserError("refusing to write NaN/inf positions into a PC2 cache")
    path = Path(path)
    header = np.zeros((), dtype=_PC2_HEADER)
    header["signature"] = PC2_SIGNATURE
    header["version"] = PC2_VERSION
    header["points"] = pos.shape[1]
    header["start"] = float(start_frame)
    header["rate"] = float(sample_rate)
    header["samples"] = pos.shape[0]
    from .atomic_io import write_stream

    def write(f) -> None:
        f.write(header.tobytes())
        f.write(pos.tobytes())

    write_stream(path, write, expected_size=header.nbytes + pos.nbytes)
    return path


@dataclass
class PointCache:
    """A PC2 file's content: positions (T, N, 3) float32, start frame and sample rate."""

    positions: np.ndarray
    start_frame: float
    sample_rate: float


def read_pc2(path) -> PointCache:
    """Read a PC2 point cache; a malformed file is a :class:`UserError` naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: PC2 file not found")
    size = path.stat().st_size
    if size < _PC2_HEADER.itemsize:
        raise UserError(f"{path}: too short for a PC2 header ({size} bytes)")
    with open(path, "rb") as f:
        header = np.frombuffer(f.read(_PC2_HEADER.itemsize), dtype=_PC2_HEADER)[0]
        if bytes(header["signature"]).rstrip(b"\0") != PC2_SIGNATURE.rstrip(b"\0"):
            raise UserError(f"{path}: not a PC2 file (signature {bytes(header['signature'])!r})")
        n, t = int(header["points"]), int(header["samples"])
        if n < 1 or t < 1:
            raise UserError(f"{path}: PC2 header says {t} samples of {n} points")
        expected = _PC2_HEADER.itemsize + 12 * n * t
        if size != expected:
            raise UserError(f"{path}: PC2 file is {size} bytes, its header promises {expected} ({t} × {n} points)")
        data = np.frombuffer(f.read(), dtype="<f4").reshape(t, n, 3).astype(np.float32)
    return PointCache(data, float(header["start"]), float(header["rate"]))


# --------------------------------------------------------------------------- jobs, shards, manifests
@dataclass
class BakeJob:
    """One object of one scene baked with one set of options, saved to ``out``.

    scene: the .blend to open; object: the object's name; out: the .blend to save (several jobs
    may share one ``out`` when they bake different objects of the same scene).
    options: everything else (:class:`BakeOptions` fields except ``frames``/``fps``, which come
    from ``frames`` here or the scene).
    frames: ``None`` = the scene's frame range.
    """

    scene: str
    object: str
    out: str
    solver: str = "mpm"
    alpha: Optional[float] = None
    frames: Optional[FrameRange] = None
    effects: list = field(default_factory=list)
    device: str = "cpu"
    material: Optional[MaterialSource] = None
    output: str = "auto"
    interpolation: str = "LINEAR"
    particles: bool = False
    armature_tolerance: float = ARMATURE_TOLERANCE
    solver_settings: Optional[dict] = None
    scenario: dict = field(default_factory=dict)

    def describe(self) -> str:
        fr = f" frames {self.frames}" if self.frames else ""
        a = f" α {self.alpha:g}" if self.alpha is not None else ""
        return f"{Path(self.scene).name}:{self.object} {self.solver}{a}{fr} → {self.out}"

    def to_dict(self) -> dict:
        d = {"scene": self.scene, "object": self.object, "out": self.out, "solver": self.solver,
             "alpha": self.alpha, "frames": str(self.frames) if self.frames else None,
             "effects": [e if isinstance(e, str) else e.to_dict() for e in self.effects], "device": self.device,
             "material": None if self.material is None else self.material.to_dict(), "output": self.output,
             "interpolation": self.interpolation, "particles": self.particles,
             "armature_tolerance": self.armature_tolerance, "settings": self.solver_settings,
             "scenario": self.scenario}
        return d


JOB_KEYS = {"scene", "object", "objects", "out", "solver", "alpha", "frames", "effects", "device", "material",
            "output", "interpolation", "particles", "armature_tolerance", "settings", "scenario"}
SCENARIO_OVERRIDE_KEYS = {"gravity", "ground", "initial_velocity", "initial_angular_velocity", "pinned_box", "clamp",
                          "clamp_group"}
"""A job's ``scenario`` may set: gravity [x,y,z] m/s²; ground: an object name, ``{"height": z}`` or ``null``
(no ground); clamp: an object name; clamp_group: a vertex group; pinned_box [[x0,y0,z0],[x1,y1,z1]] m;
initial_velocity / initial_angular_velocity [x,y,z].  Unset keys come from the scene and the object."""


def expand_out(pattern: str, *, scene: str, obj: str, solver: str, alpha: Optional[float],
               frames: Optional[FrameRange], index: int) -> str:
    """Fill ``{scene}``, ``{object}``, ``{solver}``, ``{alpha}``, ``{frames}``, ``{start}``, ``{end}``, ``{job}``."""
    values = {"scene": Path(scene).stem, "object": _safe_name(obj), "solver": solver,
              "alpha": "" if alpha is None else f"{alpha:g}", "frames": str(frames) if frames else "scene",
              "start": str(frames.start) if frames else "", "end": str(frames.end) if frames else "",
              "job": f"{index:04d}"}
    try:
        return str(pattern).format(**values)
    except (KeyError, IndexError, ValueError) as exc:
        raise UserError(f"output name {pattern!r}: unknown placeholder {exc}; use {{{'}, {'.join(values)}}}") from None


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "object"


def expand_jobs(scene: str, objects: Sequence[str], out: str, *, solver: str = "mpm",
                alphas: Sequence[Optional[float]] = (None,), frame_ranges: Sequence[Optional[FrameRange]] = (None,),
                resolve: Optional[Callable[[str], Sequence[str]]] = None, **common) -> list[BakeJob]:
    """The batch objects × frame ranges × α values, in that order (a stable order: shards rely on it).

    resolve: ``resolve(scene) -> object names`` to expand wildcards (``Rock*``) now, so that each
    object gets its own job and output name; without it a pattern stays one job (expanded when the
    scene is opened) and may not be combined with ``{object}`` in the output name.
    """
    if not objects:
        raise UserError("no object to bake: give --object NAME (repeatable, wildcards allowed)")
    if resolve is not None:
        objects = select_objects(objects, list(resolve(str(scene))))
    elif "{object}" in str(out) and any(any(c in o for c in "*?[") for o in objects):
        raise UserError("a wildcard object name with {object} in the output name needs the scene's object list")
    jobs = []
    for obj in objects:
        for fr in frame_ranges:
            for a in alphas:
                jobs.append(BakeJob(scene=str(scene), object=obj, out=expand_out(out, scene=scene, obj=obj, solver=solver,
                                                                                alpha=a, frames=fr, index=len(jobs)),
                                    solver=solver, alpha=a, frames=fr, **common))
    check_job_outputs(jobs)
    return jobs


def check_job_outputs(jobs: Sequence[BakeJob]) -> None:
    """Two jobs writing the same object into the same output file would overwrite each other: refuse.
    An output that is its input scene or material file — also through a symbolic link or a hard link —
    is refused too."""
    from .atomic_io import output_path, refuse_overwriting_inputs, same_file

    seen: dict = {}
    for j in jobs:
        key = (str(output_path(j.out)), j.object)
        if key in seen:
            raise UserError(f"jobs '{seen[key].describe()}' and '{j.describe()}' both write object '{j.object}' into "
                            f"{j.out}; put a placeholder such as {{alpha}}, {{frames}} or {{job}} in the output name")
        seen[key] = j
        if same_file(j.out, j.scene):
            how = " (through a link)" if os.path.abspath(j.out) != os.path.abspath(j.scene) else ""
            raise UserError(f"job '{j.describe()}' would overwrite its input scene {j.scene}{how}: the output {j.out} "
                            "is the same file; choose another --out")
        inputs = [getattr(j.material, a, None) for a in ("path", "features")] if j.material is not None else []
        refuse_overwriting_inputs(j.out, [i for i in inputs if i], what="output")


def group_jobs(jobs: Sequence[BakeJob]) -> list[list[BakeJob]]:
    """Jobs grouped by (scene, out) — one group = open the scene once, bake, save once — in first-seen order."""
    groups: dict = {}
    for j in jobs:
        key = (os.path.abspath(j.scene), os.path.abspath(j.out))
        groups.setdefault(key, []).append(j)
    outs: dict = {}
    for (scene, out), g in groups.items():
        if out in outs and outs[out] != scene:
            raise UserError(f"two different scenes ({outs[out]} and {scene}) would be saved into the same file {out}")
        outs[out] = scene
    return list(groups.values())


def shard_groups(groups: Sequence, shard: Optional[tuple[int, int]]) -> list:
    """The part of a batch that shard ``(i, n)`` runs: groups ``i, i+n, i+2n, …`` (round-robin, stable).

    Jobs are grouped by output file first (:func:`group_jobs`) so no two shards write the same file.
    """
    if shard is None:
        return list(groups)
    i, n = shard
    if n <= 0 or not 0 <= i < n:
        raise UserError(f"shard {i}/{n}: need 0 <= i < n")
    return list(groups)[i::n]


def select_objects(patterns: Sequence[str], available: Sequence[str]) -> list[str]:
    """Object names matching the given names or shell wildcards (``Rock*``), in the order given; each must match."""
    chosen: list[str] = []
    for pat in patterns:
        if any(c in pat for c in "*?["):
            hits = sorted(n for n in available if fnmatch.fnmatchcase(n, pat))
            if not hits:
                raise UserError(f"no object matches {pat!r}; objects in the scene: {', '.join(sorted(available)) or 'none'}")
        else:
            if pat not in available:
                raise UserError(f"no object named {pat!r} in the scene; objects: {', '.join(sorted(available)) or 'none'}")
            hits = [pat]
        chosen.extend(h for h in hits if h not in chosen)
    return chosen


def load_manifest(path, resolve: Optional[Callable[[str], Sequence[str]]] = None) -> list[BakeJob]:
    """Read a job manifest (format ``unipixie.bake-manifest/1``; schema in ``docs/baking.md``).

    Relative paths (scene, out, material files) are relative to the manifest's folder.  A job may
    name several objects (``"objects": [...]``, wildcards resolved when the scene is opened) and
    may give ``"alpha"`` or ``"frames"`` as lists (a batch).  Errors name the job and key.
    ``resolve``: see :func:`expand_jobs`.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: manifest not found")
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise UserError(f"{path}: a manifest is a JSON object with 'format' and 'jobs'")
    if doc.get("format") != MANIFEST_FORMAT:
        raise UserError(f"{path}: key 'format' is {doc.get('format')!r}, expected {MANIFEST_FORMAT!r}")
    defaults = doc.get("defaults", {}) or {}
    jobs_in = doc.get("jobs")
    if not isinstance(jobs_in, list) or not jobs_in:
        raise UserError(f"{path}: key 'jobs' must be a non-empty list")
    if not isinstance(defaults, dict):
        raise UserError(f"{path}: key 'defaults' must be an object")
    base = path.parent
    jobs: list[BakeJob] = []
    for k, raw in enumerate(jobs_in):
        if not isinstance(raw, dict):
            raise UserError(f"{path}: jobs[{k}] must be an object")
        d = {**defaults, **raw}
        where = f"{path}: jobs[{k}]"
        unknown = set(d) - JOB_KEYS
        if unknown:
            raise UserError(f"{where}: unknown key(s) {sorted(unknown)}; known keys: {', '.join(sorted(JOB_KEYS))}")
        for key in ("scene", "out"):
            if not d.get(key):
                raise UserError(f"{where}: key '{key}' is missing")
        objects = d.get("objects", d.get("object"))
        if isinstance(objects, str):
            objects = [objects]
        if not objects or not all(isinstance(o, str) for o in objects):
            raise UserError(f"{where}: key 'object' (a name) or 'objects' (a list of names) is missing")
        scene = str(_rel(base, d["scene"]))
        alphas = d.get("alpha")
        alphas = alphas if isinstance(alphas, list) else [alphas]
        frames = d.get("frames")
        if isinstance(frames, list):
            frame_ranges = [parse_frames(f) for f in frames]
        elif frames is None:
            frame_ranges = [None]
        else:
            frame_ranges = parse_frame_list(str(frames))
        material = d.get("material")
        if isinstance(material, dict):
            material = {**material, **{k: str(_rel(base, material[k])) for k in ("file", "features", "checkpoint")
                                       if material.get(k)}}
        elif isinstance(material, str) and material != "model":
            material = str(_rel(base, material))
        scen = d.get("scenario") or {}
        if not isinstance(scen, dict) or set(scen) - SCENARIO_OVERRIDE_KEYS:
            raise UserError(f"{where}: 'scenario' may set only {', '.join(sorted(SCENARIO_OVERRIDE_KEYS))}")
        from ..solvers.scenario import require_json_numbers

        try:
            require_json_numbers([a for a in alphas if a is not None], f"{where}: 'alpha'")
            if "armature_tolerance" in d:
                require_json_numbers(d["armature_tolerance"], f"{where}: 'armature_tolerance'")
        except UserError as exc:
            raise UserError(str(exc)) from None
        try:
            for a in alphas:
                if a is not None and not 0.0 <= float(a) <= 1.0:
                    raise ValueError
            alphas = [None if a is None else float(a) for a in alphas]
        except (TypeError, ValueError):
            raise UserError(f"{where}: 'alpha' must be a number in [0, 1] or a list of them") from None
        source = material_source_from_dict(material) if "material" in d else None
        if any(a is not None for a in alphas) and source is not None and source.kind != "model":
            raise UserError(f"{where}: 'alpha' with a {source.kind} 'material': {MATERIAL_RULE}")
        common = dict(effects=list(d.get("effects", []) or []), device=str(d.get("device", "cpu")),
                      material=source,
                      output=str(d.get("output", "auto")), interpolation=str(d.get("interpolation", "LINEAR")),
                      particles=bool(d.get("particles", False)),
                      armature_tolerance=float(d.get("armature_tolerance", ARMATURE_TOLERANCE)),
                      solver_settings=d.get("settings"), scenario=scen)
        try:
            new = expand_jobs(scene, objects, str(_rel(base, d["out"])), solver=str(d.get("solver", "mpm")),
                              alphas=alphas, frame_ranges=frame_ranges, resolve=resolve, **common)
        except UserError as exc:
            raise UserError(f"{where}: {exc}") from None
        jobs.extend(new)
    check_job_outputs(jobs)
    return jobs


def _rel(base: Path, p) -> Path:
    p = Path(os.path.expanduser(str(p)))
    return p if p.is_absolute() else (base / p)


# --------------------------------------------------------------------------- the bake record
def make_record(**fields) -> str:
    """The JSON stored on a baked object (:data:`BAKE_RECORD_KEY`): what was made, so clear_bake can undo it."""
    doc = {"format": BAKE_RECORD_FORMAT}
    doc.update(fields)
    return json.dumps(doc, default=_json_default)


def parse_record(text) -> Optional[dict]:
    if not text:
        return None
    try:
        doc = json.loads(str(text))
    except json.JSONDecodeError:
        return None
    if not isinstance(doc, dict) or doc.get("format") != BAKE_RECORD_FORMAT:
        return None
    return doc


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    return str(o)


def effects_to_json(effects: Iterable) -> list:
    return [e.to_dict() if hasattr(e, "to_dict") else e for e in effects]
