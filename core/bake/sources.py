"""Material sources — *where a bake's material comes from*: one homogeneous material
(:class:`HomogeneousSource`), a :class:`~unipixie.core.types.MaterialField` file in the object's normalised
cube (:class:`FieldFileSource`), or the model's prediction at α (:class:`ModelSource`).

Each is a :class:`MaterialSource` (``resolve(obj, alpha, solver) -> ResolvedMaterial``); a manifest's
``material`` value becomes one with :func:`material_source_from_dict`.  The model's material comes either from
a feature-grid file (:func:`predict_material`) or from the object's own prediction, which the source carries as
its ``plan`` (a :class:`~unipixie.core.model.plan.ModelPlan`, built by whoever starts the bake from the object's
pipeline record: the panel's bake step, ``unipixie bake --alpha``, a script) and which :func:`plan_material`
reads; both end in :func:`material_from_prediction`.  No process-wide state: a source holds all it needs.

Uses :mod:`.body` (the object), the model (:mod:`unipixie.core.model`, its plan and exact prediction),
normalisation, the data types and the solvers' material registry; nothing else of the bake.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import UserError
from ..model.plan import ModelPlan, exact_prediction
from .body import BakeObject


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
        from ...solvers.material_sampling import HomogeneousMaterial

        return HomogeneousMaterial(self.E, self.nu, self.density, self.material)

    def resolve(self, obj, alpha, solver):
        from ...solvers import materials

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
        from ..normalise import Normalisation
        from ..types import MaterialField

        if not self.path:
            raise UserError("no material field file given (set one in the panel or pass --material-file)")
        fieldd = MaterialField.load(self.path)
        from ...solvers.materials import NUM_CLASSES

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


@dataclass
class ModelSource(MaterialSource):
    """The model's material at α.

    features: a FeatureGrid file of the object (``unipixie features``); with it, the model in
        ``checkpoint`` (default: the shipped model) predicts the material here (:func:`predict_material`).
    plan: without ``features``, the object's own prediction (:class:`~unipixie.core.model.plan.ModelPlan`: its
        α sweep, feature grid and checkpoint), read by :func:`plan_material`.  With neither, a
        :class:`UserError` says what is missing.  The plan is run-time data: it is not part of :meth:`to_dict`
        (the bake record and manifests name the source, not the cache files).
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
    plan: Optional[ModelPlan] = field(default=None, compare=False, repr=False)
    kind = "model"

    def resolve(self, obj, alpha, solver):
        """``alpha``: a float in [0, 1] already checked by the bake's options (:func:`~unipixie.core.types.
        check_alpha`); ``None`` is refused here (a model material has no meaning without α)."""
        if alpha is None:
            raise UserError("the model's material needs α (a value in [0, 1]); pass --alpha or set α in the panel")
        alpha = float(alpha)
        if self.features:
            return predict_material(obj, self.features, alpha, solver, checkpoint=self.checkpoint or None,
                                    seed=self.seed, device=self.device, solver_heads=self.solver_heads)
        if self.plan is None:
            raise UserError(f"material prediction at α = {alpha:g} needs the UniPixie model and the object's feature "
                            "grid, and neither a feature grid (--features GRID.npz from 'unipixie features') nor a "
                            "prediction of the object is available ('unipixie bake --alpha' computes them unless "
                            "--no-auto); bake with a homogeneous material (--E/--nu/--density/--material-class) or a "
                            "material field file (--material-file) instead")
        return plan_material(obj, alpha, solver, self.plan, solver_heads=self.solver_heads)

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
    from ..model import predict
    from ..types import FeatureGrid

    grid = FeatureGrid.load(features)
    pred = predict(grid, [alpha], heads=MODEL_HEADS[solver], seed=seed, checkpoint=checkpoint, device=device)
    res = material_from_prediction(obj, pred, 0, solver, solver_heads=solver_heads)
    res.description = f"model at α {alpha:g} ({Path(str(checkpoint or 'default model')).name}, seed {seed})"
    return res


def no_prediction(object_name: str) -> UserError:
    """The error for a model material bake of an object that has no prediction (no plan) yet."""
    return UserError(f"object '{object_name}' has no predicted material yet: run Predict in the UniPixie panel "
                     "(after Render views and Features), or bake with a homogeneous material or a field file")


def plan_material(obj: BakeObject, alpha: float, solver: str, plan: Optional[ModelPlan],
                  solver_heads: bool = False) -> ResolvedMaterial:
    """The model's material for ``obj`` at ``alpha`` for ``solver`` from the object's own prediction ``plan``
    (the sweep's values on its α nodes, else the cached or computed exact prediction:
    :func:`~unipixie.core.model.plan.exact_prediction`).  No Blender access: it runs in the bake's worker thread.
    ``plan`` ``None`` (no prediction yet) is a :class:`UserError` naming the remedy; ``solver_heads``: see
    :func:`material_from_prediction`."""
    if plan is None:
        raise no_prediction(obj.name)
    pred, how, _ = exact_prediction(plan, alpha, MODEL_HEADS[solver])
    res = material_from_prediction(obj, pred, 0, solver, solver_heads=solver_heads)
    res.description = f"model at α {float(alpha):g} ({how}, {Path(plan.checkpoint).name}, seed {plan.seed})"
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
    from ..normalise import Normalisation

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
            from ...solvers.scenario import require_json_numbers

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
    from ...solvers.scenario import require_json_numbers

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
