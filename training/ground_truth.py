"""Cross-solver ground truth of one object, as the paper makes it (appendix "Cross-Solver Parameter Generation").

1. **MPM at the range ends.**  The object's solid (the union of its parts, filled
   with particles on a lattice) is simulated by the MPM solver with the annotated
   material at α = 0 (every part at its range minimum) and at α = 1 (maximum) in
   the class's short clip (a drop onto the ground, or a clamped base pushed
   sideways): :data:`GroundTruthSettings.frames` frames at ``fps``.  The tracked
   points are the object's mesh vertices (a deterministic subset of at most
   ``tracked_points``).
2. **LBS parameters fitted to those motions.**  The 650 skinning parameters come
   from the data-free (Simplicits) fit on the soft end's material, one set for
   both ends as the paper does; the E field at each end is the simulated material's
   E times one scale ``s`` found by test-time optimisation of the tracked-point
   RMSE against the MPM motion (ν from the annotation).  The fitted E, ν are stored
   per voxel (the model's LBS material head predicts a voxel field).
3. **Spring-mass parameters fitted to those motions.**  The anchor network's
   stiffness vector at each end is the solver's E → k mapping of the simulated
   material times one scale ``s`` fitted the same way; the softness η is held at
   Spring-Gaus's initial value (:data:`unipixie.solvers.spring_mass.DEFAULT_SOFTNESS`)
   for both ends — the paper fixes the extrinsic parameters globally — so the
   soft-to-stiff range is carried by k.

The fitters (:func:`fit_scale`) are also the *specialist test-time optimisation
baselines* of the evaluation's Table 2: they are timed, and their motion error is
reported next to the model's.

**Wave-speed cap.**  An explicit MPM step must resolve the elastic wave speed
c = sqrt(M/ρ) (M the P-wave modulus), so a steel hammer at realistic E would need
~10⁵ steps for half a second.  The simulations therefore cap E per particle so that
c ≤ ``wave_speed_per_size`` × the object's size (an elastic wave crosses it at most
that many times a second: faster objects look rigid at 60 frames per second).
Labels (the annotated ranges) are never capped; every record says how much of the
free (not held) solid's mass was simulated at the cap (``capped_mass_fraction``).
Held material (stationary class, the clamp box) is capped too — MPM does not step it,
but the spring-mass network joins it to free anchors and the LBS clamp penalty
scales with the largest E.

Everything is deterministic for a given object and settings (CPU); SI units.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional

import numpy as np

from ..core.errors import SimulationDiverged, UserError
from ..core.progress import Progress
from ..core.types import Trajectory
from ..solvers import materials
from ..solvers.materials import p_wave_factor
from ..solvers.lbs_settings import DEFAULT_MAX_DT as DEFAULT_LBS_MAX_DT
from ..core import annotation as ann_mod

GROUND_TRUTH_VERSION = 1
"""Bumped when the ground-truth protocol changes (recorded in every object's record)."""


@dataclass
class GroundTruthSettings:
    """How ground truth is simulated and fitted (SI units).

    frames / fps: the clip has ``frames`` intervals at ``fps`` (30 at 60 fps = 0.5 s; the paper fits to
        30-frame videos).
    cells_across: MPM grid cells across the object's largest extent; particles_per_cell_axis: 2 → 8 per cell.
    min_particles: thin objects get a finer lattice (and grid) until they have at least this many particles.
    wave_speed_per_size: cap on the elastic wave speed as a multiple of the object's size (1/s), see the
        module docstring.
    tracked_points: at most this many mesh vertices are tracked (0 = all).
    spring_anchors: N_a of the spring-mass network (the model's spring head must be configured alike).
    lbs_cubature_points / lbs_mass_samples: LBS solver sample counts; lbs_max_dt: its largest (implicit) step, s
        (the solver's default; datasets built before 2026-11-27 record 5 ms, whose step-capped floor was soft).
    fit_step / fit_bound / fit_evaluations: the scale fit searches log10 s in [-fit_bound, fit_bound],
        first at 0 and ±fit_step, with at most ``fit_evaluations`` simulations per end.
    extra_alphas: further α values simulated with MPM (the evaluation compares solvers at α = 0.5).
    device: Warp device (``"cpu"``, ``"cuda"``).
    """

    frames: int = 30
    fps: float = 60.0
    cells_across: int = 12
    particles_per_cell_axis: int = 2
    wave_speed_per_size: float = 400.0
    min_particles: int = 800
    tracked_points: int = 1024
    spring_anchors: int = 256
    lbs_cubature_points: int = 200
    lbs_mass_samples: int = 2000
    lbs_max_dt: float = DEFAULT_LBS_MAX_DT
    fit_step: float = 0.4
    fit_bound: float = 1.6
    fit_evaluations: int = 5
    extra_alphas: tuple = ()
    device: str = "cpu"

    def __post_init__(self):
        for name in ("frames", "cells_across", "particles_per_cell_axis", "min_particles", "spring_anchors",
                     "lbs_cubature_points",
                     "lbs_mass_samples", "fit_evaluations"):
            v = getattr(self, name)
            if int(v) != v or int(v) < 1:
                raise UserError(f"ground-truth setting '{name}' must be a positive whole number, got {v!r}")
            setattr(self, name, int(v))
        for name in ("fps", "wave_speed_per_size", "fit_step", "fit_bound", "lbs_max_dt"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise UserError(f"ground-truth setting '{name}' must be a positive number, got {getattr(self, name)!r}")
            setattr(self, name, v)
        if int(self.tracked_points) < 0:
            raise UserError("ground-truth setting 'tracked_points' must be >= 0 (0 = every vertex)")
        self.tracked_points = int(self.tracked_points)
        self.extra_alphas = tuple(float(a) for a in self.extra_alphas)
        if any(not 0.0 <= a <= 1.0 for a in self.extra_alphas):
            raise UserError(f"ground-truth extra_alphas must lie in [0, 1], got {self.extra_alphas}")

    @property
    def frame_times(self) -> np.ndarray:
        """(frames + 1,) float64 seconds."""
        return np.arange(self.frames + 1, dtype=np.float64) / self.fps

    def to_dict(self) -> dict:
        d = asdict(self)
        d["extra_alphas"] = list(self.extra_alphas)
        d["version"] = GROUND_TRUTH_VERSION
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "GroundTruthSettings":
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**known)


# =========================================================================== the simulated solid
@dataclass
class Solid:
    """What the three solvers simulate for one object (world metres).

    points: (P, 3) lattice points filling the solid; spacing: their lattice pitch (m); part: (P,) part ids.
    dx: MPM grid cell (m).  tracked: (N, 3) tracked rest points (mesh vertices); tracked_index: (N,) their
    indices into the object's concatenated vertex list.  table: :func:`.annotation.part_table` of the
    object.  scenario / frame_times: the clip.  size: largest extent (m).
    """

    points: np.ndarray
    spacing: float
    part: np.ndarray
    dx: float
    tracked: np.ndarray
    tracked_index: np.ndarray
    table: dict
    scenario: object
    frame_times: np.ndarray
    size: float
    wave_speed_cap: float

    @property
    def point_volume(self) -> float:
        return self.spacing ** 3

    def body(self):
        from ..solvers.body import Body

        return Body(points=self.points, point_volume=self.point_volume, tracked_points=self.tracked)

    def held(self) -> np.ndarray:
        """(P,) bool: points held fixed (clamp box or a held-fixed material class)."""
        held_cls = np.array([c.held_fixed for c in materials.MATERIAL_CLASSES])
        return self.scenario.pinned_mask(self.points) | held_cls[self.table["material"][self.part]]

    def labels(self, alpha: float) -> dict:
        """Annotated values per part at ``alpha``: E, nu, density (P_parts,) and material ids."""
        t = self.table
        return {q: ann_mod.interpolate(t[f"{q}_min"], t[f"{q}_max"], alpha, q) for q in ann_mod.QUANTITIES} | {
            "material": t["material"]}

    def part_E_cap(self) -> np.ndarray:
        """(parts,) Pa: the largest E simulated for each part, the same at every α so that the simulated E
        stays monotone in α: ρ_min c² / f(ν_max) (``f`` = :func:`p_wave_factor`).  Held parts (clamp,
        stationary class) are capped too: MPM does not step them, but the spring-mass network joins them to
        free anchors and the LBS clamp penalty scales with the largest E."""
        t = self.table
        return t["density_min"] * self.wave_speed_cap ** 2 / p_wave_factor(t["nu_max"], t["material"])

    def simulated_part_E(self, alpha: float) -> np.ndarray:
        """(parts,) Pa: the annotated E at ``alpha`` limited by :meth:`part_E_cap`."""
        return np.minimum(self.labels(alpha)["E"], self.part_E_cap())

    def capped_material(self, E, nu, rho, cls):
        """Per-particle values (P,) -> (PointMaterial with E capped so that each particle's wave speed is at most
        the cap, info dict) — the rule applied to predicted materials, whose density and ν vary per particle."""
        from ..solvers.material_sampling import PointMaterial

        E, nu, rho = (np.asarray(a, np.float64) for a in (E, nu, rho))
        cls = np.asarray(cls, np.int32)
        held_cls = np.array([c.held_fixed for c in materials.MATERIAL_CLASSES])
        free = ~(self.scenario.pinned_mask(self.points) | held_cls[cls])
        cap = rho * self.wave_speed_cap ** 2 / p_wave_factor(nu, cls)
        capped = E > cap
        mass = rho * self.point_volume
        info = {"capped_mass_fraction": float(mass[capped & free].sum() / max(mass[free].sum(), 1e-30)) if free.any() else 0.0,
                "wave_speed_cap": self.wave_speed_cap}
        return PointMaterial(self.points, np.where(capped, cap, E), nu, rho, cls), info

    def material(self, alpha: float):
        """(PointMaterial with E capped at the wave-speed cap, info dict) at ``alpha``."""
        from ..solvers.material_sampling import PointMaterial

        lab = self.labels(alpha)
        E = lab["E"][self.part]
        nu = lab["nu"][self.part]
        rho = lab["density"][self.part]
        cls = lab["material"][self.part].astype(np.int32)
        cap = self.part_E_cap()[self.part]
        free = ~self.held()
        capped = E > cap
        E_sim = np.where(capped, cap, E)
        mass = rho * self.point_volume
        info = {"capped_mass_fraction": float(mass[capped & free].sum() / max(mass[free].sum(), 1e-30)) if free.any() else 0.0,
                "wave_speed_cap": self.wave_speed_cap}
        return PointMaterial(self.points, E_sim, nu, rho, cls), info


def build_solid(obj, settings: GroundTruthSettings) -> Solid:
    """The :class:`Solid` of a :class:`~.procedural.ProceduralObject` (or anything with ``parts`` of closed
    trimesh ``components``, ``annotation`` and ``scenario``)."""
    size = float(np.max(np.ptp(obj.bounds, axis=0)))
    dx = size / settings.cells_across
    spacing = dx / settings.particles_per_cell_axis
    # thin objects (a spanner lying flat) get a finer lattice until they have min_particles
    for attempt in range(6):
        try:
            points, part = obj.fill(spacing)
        except UserError:
            points, part = np.zeros((0, 3)), np.zeros(0, np.int16)
        if len(points) >= settings.min_particles:
            break
        spacing /= 2.0 ** (1.0 / 3.0)
    if len(points) == 0:
        raise UserError(f"{getattr(obj, 'object_id', 'object')}: no particle falls inside the solid even at "
                        f"{spacing:.3g} m spacing")
    dx = spacing * settings.particles_per_cell_axis
    verts = np.concatenate([np.asarray(c.vertices, np.float64) for p in obj.parts for c in p.components])
    n = len(verts)
    if settings.tracked_points and n > settings.tracked_points:
        idx = np.sort(np.random.default_rng(0).choice(n, settings.tracked_points, replace=False))
    else:
        idx = np.arange(n)
    table = ann_mod.part_table(obj.annotation)
    if len(table["material"]) != len(obj.parts):
        raise UserError(f"{getattr(obj, 'object_id', 'object')}: the annotation has {len(table['material'])} parts, "
                        f"the mesh {len(obj.parts)}")
    return Solid(points, spacing, part.astype(np.int64), dx, verts[idx], idx, table, obj.scenario,
                 settings.frame_times, size, settings.wave_speed_per_size * size)


# =========================================================================== simulations
def motion_rmse(a, b, frames: Optional[slice] = None) -> float:
    """RMSE in metres between two (T, N, 3) tracked-point motions (or Trajectories), frame 0 excluded."""
    pa = a.positions if isinstance(a, Trajectory) else np.asarray(a)
    pb = b.positions if isinstance(b, Trajectory) else np.asarray(b)
    if pa.shape != pb.shape:
        raise UserError(f"motions differ in shape: {pa.shape} vs {pb.shape}")
    sl = frames or slice(1, None)
    d = pa[sl].astype(np.float64) - pb[sl].astype(np.float64)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))


def simulate_mpm(solid: Solid, alpha: float, settings: GroundTruthSettings, progress: Optional[Progress] = None):
    """MPM trajectory of the solid with the annotated material at ``alpha`` (capped); returns (Trajectory, info)."""
    from ..solvers import mpm

    mat, info = solid.material(alpha)
    t = time.perf_counter()
    sim = mpm.prepare(solid.body(), mat, solid.scenario, solid.frame_times, device=settings.device,
                      settings={"dx": solid.dx, "particles_per_cell_axis": settings.particles_per_cell_axis})
    traj = sim.run([], progress=progress)
    info.update(seconds=time.perf_counter() - t, substeps=int(traj.meta.get("substeps_total", 0)),
                particles=int(sim.particle_count))
    return traj, info


@dataclass
class ScaleFit:
    """Result of a one-parameter test-time fit: log10 scale, its RMSE (m), all evaluations, seconds."""

    log_scale: float
    rmse: float
    evaluations: list = field(default_factory=list)
    seconds: float = 0.0

    @property
    def scale(self) -> float:
        return 10.0 ** self.log_scale


def fit_scale(evaluate: Callable[[float], float], step: float, bound: float, max_evaluations: int,
              progress: Optional[Progress] = None) -> ScaleFit:
    """Minimise ``evaluate(log10 s)`` (an RMSE) over log10 s ∈ [−bound, bound].

    Evaluates 0 and ±step, walks downhill by ``step`` while the minimum is at an end, then takes the
    vertex of the parabola through the best point and its neighbours; at most ``max_evaluations`` calls.
    Diverged simulations count as +inf.  Deterministic.
    """
    t0 = time.perf_counter()
    seen: dict = {}

    def f(x: float) -> float:
        x = float(np.clip(round(x, 6), -bound, bound))
        if x not in seen:
            if len(seen) >= max_evaluations:
                return math.inf
            try:
                seen[x] = float(evaluate(x))
            except SimulationDiverged:
                seen[x] = math.inf
            if progress is not None:
                progress.check()
        return seen[x]

    for x in (0.0, -step, step):
        f(x)
    while len(seen) < max_evaluations:
        xs = sorted(seen)
        best = min(xs, key=lambda x: seen[x])
        if best == xs[0] and best > -bound + 1e-9:
            f(best - step)
        elif best == xs[-1] and best < bound - 1e-9:
            f(best + step)
        else:
            break
    xs = sorted(seen)
    best = min(xs, key=lambda x: seen[x])
    i = xs.index(best)
    if 0 < i < len(xs) - 1 and len(seen) < max_evaluations:
        x0, x1, x2 = xs[i - 1], xs[i], xs[i + 1]
        y0, y1, y2 = seen[x0], seen[x1], seen[x2]
        if all(map(math.isfinite, (y0, y1, y2))):
            den = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
            if abs(den) > 1e-15:
                xv = x1 - 0.5 * ((x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)) / den
                if x0 < xv < x2:
                    f(xv)
    best = min(seen, key=lambda x: seen[x])
    if not math.isfinite(seen[best]):
        raise SimulationDiverged("every simulation of the scale fit diverged")
    return ScaleFit(float(best), float(seen[best]), sorted(seen.items()), time.perf_counter() - t0)


def _whole_body_box(solid: Solid) -> dict:
    lo = solid.points.min(0) - solid.size
    hi = solid.points.max(0) + solid.size
    return {"box": np.stack([lo, hi])}


def _scale_effect(solid: Solid, log_scale: float):
    from ..solvers import effects

    factor = float(10.0 ** log_scale)
    if abs(log_scale) < 1e-12:
        return []
    return [effects.make("stiffness_region", factor=factor, region=_whole_body_box(solid))]


def _evaluator(sim, solid: Solid, target: Trajectory, keep: dict):
    def evaluate(log_scale: float) -> float:
        traj = sim.run(_scale_effect(solid, log_scale))
        keep[round(float(log_scale), 6)] = traj.positions
        return motion_rmse(traj, target)

    return evaluate


def fit_spring(solid: Solid, alpha: float, target: Trajectory, settings: GroundTruthSettings,
               progress: Optional[Progress] = None, keep_best: bool = False) -> dict:
    """Spring-mass stiffness (N_a,) N and softness η at ``alpha`` fitted to the ``target`` MPM motion
    (``keep_best``: also return the best fit's tracked motion as ``best_positions``)."""
    from ..solvers import spring_mass

    mat, _ = solid.material(alpha)
    t = time.perf_counter()
    sim = spring_mass.prepare(solid.body(), mat, solid.scenario, solid.frame_times, device=settings.device,
                              settings=spring_solver_settings(settings))
    keep: dict = {}
    fit = fit_scale(_evaluator(sim, solid, target, keep), settings.fit_step, settings.fit_bound,
                    settings.fit_evaluations, progress)
    out = {"stiffness": (sim.stiffness * fit.scale).astype(np.float64), "softness": float(sim.softness),
           "anchors": sim.network.anchors.copy(), "fit": fit, "seconds": time.perf_counter() - t,
           "anchor_count": int(sim.network.count)}
    if keep_best:
        out["best_positions"] = keep[round(fit.log_scale, 6)]
    return out


def fit_lbs(solid: Solid, alpha: float, target: Trajectory, settings: GroundTruthSettings,
            skinning_params: Optional[np.ndarray] = None, progress: Optional[Progress] = None,
            keep_best: bool = False) -> dict:
    """LBS skinning parameters (650,) and the E scale at ``alpha`` fitted to the ``target`` MPM motion.

    ``skinning_params`` None fits them data-free on this end's material (the soft end); otherwise they are
    reused (one deformation basis for all α, as the paper does).
    """
    from ..solvers import lbs

    mat, _ = solid.material(alpha)
    t = time.perf_counter()
    lbs_settings = lbs_solver_settings(settings)
    if skinning_params is not None:
        lbs_settings["skinning_params"] = np.asarray(skinning_params, np.float64)
    sim = lbs.prepare(solid.body(), mat, solid.scenario, solid.frame_times, device=settings.device,
                      settings=lbs_settings)
    keep: dict = {}
    fit = fit_scale(_evaluator(sim, solid, target, keep), settings.fit_step, settings.fit_bound,
                    settings.fit_evaluations, progress)
    out = {"skinning_params": np.asarray(sim.skinning_params, np.float32), "E_scale": fit.scale, "fit": fit,
           "cubature": sim.cubature_rest.copy(), "cubature_E": sim.cubature_E * fit.scale,
           "cubature_nu": sim.cubature_nu.copy(), "seconds": time.perf_counter() - t}
    if keep_best:
        out["best_positions"] = keep[round(fit.log_scale, 6)]
    return out


def lbs_solver_settings(settings: GroundTruthSettings) -> dict:
    """The LBS solver settings of the ground-truth protocol (also used to simulate predictions)."""
    return {"cubature_points": settings.lbs_cubature_points, "mass_samples": settings.lbs_mass_samples,
            "max_dt": settings.lbs_max_dt}


def spring_solver_settings(settings: GroundTruthSettings) -> dict:
    """The spring-mass solver settings of the ground-truth protocol."""
    return {"anchors": settings.spring_anchors}


def ordered_scales(s0: float, s1: float, base0: np.ndarray, base1: np.ndarray) -> tuple[float, float, bool]:
    """Scales for the two ends such that s0·base0 <= s1·base1 everywhere.

    The fits are independent; where they would cross (the motion cannot tell the ends apart, e.g. both at
    the wave-speed cap) both ends take the geometric mean of the two fitted scales.  Returns
    (s0, s1, crossed).
    """
    b0 = np.asarray(base0, np.float64)
    b1 = np.asarray(base1, np.float64)
    if np.all(s0 * b0 <= s1 * b1 * (1 + 1e-9)):
        return s0, s1, False
    g = math.sqrt(s0 * s1)
    if np.all(b0 <= b1 * (1 + 1e-9)):
        return g, g, True
    raise UserError("the soft end's material is stiffer than the stiff end's somewhere: the annotation is inverted")


# =========================================================================== one object
@dataclass
class GroundTruth:
    """Ground truth of one object.

    solid: the simulated :class:`Solid`.  mpm: α -> Trajectory (tracked points).  mpm_info: α -> dict.
    lbs_params: (650,) skinning parameters; lbs_E_scale: (s0, s1); spring_stiffness: {0: (N_a,), 1: (N_a,)} N;
    spring_softness: η; anchors: (N_a, 3) rest positions; fits: timings and RMSEs of the fitters.
    """

    solid: Solid
    mpm: dict
    mpm_info: dict
    lbs_params: np.ndarray
    lbs_E_scale: tuple
    spring_stiffness: dict
    spring_softness: float
    anchors: np.ndarray
    fits: dict

    def lbs_part_E(self) -> np.ndarray:
        """(2, parts) Pa: the LBS E of each part at α = 0 and α = 1 (simulated E × fitted scale)."""
        return np.stack([self.solid.simulated_part_E(end) * s for end, s in zip((0.0, 1.0), self.lbs_E_scale)])

    def lbs_voxel_E(self, part_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K,) LBS E at α = 0 and α = 1 for voxels of the given part ids (Pa)."""
        e = self.lbs_part_E()
        return e[0][part_ids], e[1][part_ids]


def compute(obj, settings: GroundTruthSettings | None = None, progress: Optional[Progress] = None,
            timings: Optional[dict] = None) -> GroundTruth:
    """MPM at α = 0, 1 (and ``settings.extra_alphas``), then the LBS and spring-mass fits (module docstring).

    ``timings`` (optional dict) receives seconds per stage: ``mpm``, ``lbs_fit``, ``spring_fit``.
    """
    settings = settings or GroundTruthSettings()
    timings = timings if timings is not None else {}
    t = time.perf_counter()
    solid = build_solid(obj, settings)
    alphas = [0.0, 1.0] + [a for a in settings.extra_alphas if a not in (0.0, 1.0)]
    mpm_traj, mpm_info = {}, {}
    for a in alphas:
        if progress is not None:
            progress.set_status(f"MPM at α = {a:g}")
        mpm_traj[a], mpm_info[a] = simulate_mpm(solid, a, settings, progress=None)
        if progress is not None:
            progress.check()
    timings["mpm"] = time.perf_counter() - t

    t = time.perf_counter()
    if progress is not None:
        progress.set_status("LBS fit")
    lbs0 = fit_lbs(solid, 0.0, mpm_traj[0.0], settings, progress=progress)
    lbs1 = fit_lbs(solid, 1.0, mpm_traj[1.0], settings, skinning_params=lbs0["skinning_params"], progress=progress)
    timings["lbs_fit"] = time.perf_counter() - t

    t = time.perf_counter()
    if progress is not None:
        progress.set_status("spring-mass fit")
    sp0 = fit_spring(solid, 0.0, mpm_traj[0.0], settings, progress=progress)
    sp1 = fit_spring(solid, 1.0, mpm_traj[1.0], settings, progress=progress)
    timings["spring_fit"] = time.perf_counter() - t
    if sp0["anchor_count"] != sp1["anchor_count"] or not np.allclose(sp0["anchors"], sp1["anchors"]):
        raise RuntimeError("the spring-mass anchors differ between the two ends (they must depend on geometry only)")

    gt = GroundTruth(solid, mpm_traj, mpm_info, lbs0["skinning_params"], (1.0, 1.0), {}, sp0["softness"],
                     sp0["anchors"], {})
    e0, e1 = solid.simulated_part_E(0.0), solid.simulated_part_E(1.0)
    s0, s1, lbs_crossed = ordered_scales(lbs0["E_scale"], lbs1["E_scale"], e0, e1)
    gt.lbs_E_scale = (s0, s1)
    k0 = sp0["stiffness"] / sp0["fit"].scale
    k1 = sp1["stiffness"] / sp1["fit"].scale
    t0_, t1_, spring_crossed = ordered_scales(sp0["fit"].scale, sp1["fit"].scale, k0, k1)
    gt.spring_stiffness = {0.0: k0 * t0_, 1.0: k1 * t1_}
    gt.fits = {
        "lbs": {"E_scale_fitted": [lbs0["E_scale"], lbs1["E_scale"]], "E_scale": [s0, s1], "crossed": lbs_crossed,
                "rmse": [lbs0["fit"].rmse, lbs1["fit"].rmse], "seconds": [lbs0["seconds"], lbs1["seconds"]],
                "evaluations": [len(lbs0["fit"].evaluations), len(lbs1["fit"].evaluations)]},
        "spring_mass": {"scale_fitted": [sp0["fit"].scale, sp1["fit"].scale], "scale": [t0_, t1_],
                        "crossed": spring_crossed, "rmse": [sp0["fit"].rmse, sp1["fit"].rmse],
                        "seconds": [sp0["seconds"], sp1["seconds"]],
                        "evaluations": [len(sp0["fit"].evaluations), len(sp1["fit"].evaluations)],
                        "anchors": sp0["anchor_count"]},
    }
    return gt
