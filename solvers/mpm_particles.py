"""The MPM solver's particles at rest: filling a body, its material per particle and the initial state.

:func:`initial_particles` fills a mesh body with a particle lattice (or takes a particle body's points), picks the
grid pitch dx (:func:`automatic_dx`: the body's largest extent and its thinnest parts, within a particle
budget), samples the material at every particle, drops the background, checks what a simulation cannot start
from (particles below the ground, unknown classes, non-physical E, ν, ρ) and builds the initial velocities,
deformation gradients, rotations and plastic states.  :mod:`.mpm` uploads the result and steps it.  SI units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..core.errors import UserError
from ..core.progress import Progress
from . import materials
from .body import Body
from .material_sampling import MaterialSpec, SampledMaterial, sample_material
from .mpm_settings import AUTO_MAX_PARTICLES, DEFAULT_CELLS_ACROSS_THINNEST, MPMSettings
from .sampling import fill_mesh
from .scenario import Scenario

THIN_PART_WARNING_CELLS = 2.0
"""A grid given by ``cells_across`` alone that leaves the thinnest parts fewer cells thick than this is warned about
(docs/fidelity.md, the demo's plant: at 1.1 cells thick its crown lost 87 % of its swing in 2 s, at 2.0 about
half, at 3.1 none)."""


@dataclass
class InitialParticles:
    """The P particles of a body at rest and its N tracked points, as the MPM solver starts them (SI, float64
    unless noted).

    dx: grid cell size, m.  positions: (P, 3) m.  volumes: (P,) m³.  material: :class:`SampledMaterial` of the
    particles (background removed).  held: (P,) bool, held at rest (clamp box or a held-fixed class).
    tracked_held: (N,) bool.  masses: (P,) kg.  velocities: (P, 3) m/s.  tracked_velocities: (N, 3) m/s.
    affine_velocity: (P, 3, 3) float32 1/s, APIC C.  displacement_gradient: (P, 3, 3) float32, H = F − I
    (the particles store H: mpm_kernels.displacement_gradient_update).  rotation: (4,) float32
    quaternion (x, y, z, w) of F's rotation.  plastic: (P,) plastic state (snow: Jp = 1).  contact_radius: m, half
    the particle spacing; contact_area: m², the spacing² (a particle stands for a cube of material,
    :mod:`.contact`).  grid_anchor: (3,) m, a point of the global grid lattice.  min_density: kg/m³.
    elastic_only: every deforming particle is purely elastic fixed-corotated (the elastic-only P2G applies).
    thinnest_part: m, measured when dx was chosen automatically, else None.  warnings: what the user should know.
    """

    dx: float
    positions: np.ndarray
    volumes: np.ndarray
    material: SampledMaterial
    held: np.ndarray
    tracked_held: np.ndarray
    masses: np.ndarray
    velocities: np.ndarray
    tracked_velocities: np.ndarray
    affine_velocity: np.ndarray
    displacement_gradient: np.ndarray
    rotation: np.ndarray
    plastic: np.ndarray
    contact_radius: float
    contact_area: float
    grid_anchor: np.ndarray
    min_density: float
    elastic_only: bool
    thinnest_part: Optional[float]
    warnings: list


def _per_class(attribute) -> np.ndarray:
    """(NUM_CLASSES,) array of ``attribute(material_class)`` indexed by class id (index it with class ids)."""
    return np.array([attribute(c) for c in materials.MATERIAL_CLASSES])


def _skew(w: np.ndarray) -> np.ndarray:
    """(3,) angular velocity -> (3, 3) matrix with skew(w) @ r = w x r."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _point_volume(points: np.ndarray) -> float:
    """m³ per point of a particle set, from the median nearest-neighbour distance."""
    if len(points) < 2:
        raise UserError("a particle body with a single point needs point_volume")
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=2)
    spacing = float(np.median(d[:, 1]))
    if not spacing > 0:
        raise UserError("the body's points coincide (zero spacing); give point_volume or distinct points")
    return spacing ** 3


def initial_particles(body: Body, scenario: Scenario, material: MaterialSpec, settings: MPMSettings, device: str,
                      tracked_rest: np.ndarray, progress: Optional[Progress] = None) -> InitialParticles:
    """The particles of ``body`` at rest (module docstring); tracked_rest: (N, 3) m, the tracked points."""
    warnings: list = []
    measured: dict = {"thinnest_part": None}
    s = settings
    if progress:
        progress.set_status("MPM: filling the body with particles")
    if body.points is not None:
        points = np.asarray(body.points, dtype=np.float64)
        volume = float(body.point_volume) if body.point_volume is not None else _point_volume(points)
        if not (math.isfinite(volume) and volume > 0):
            raise UserError(f"the body's point_volume must be a positive number of m³, got {body.point_volume!r}")
        dx = s.dx if s.dx is not None else s.particles_per_cell_axis * volume ** (1.0 / 3.0)
        volumes = np.full(len(points), volume)
    else:
        dx = s.dx if s.dx is not None else automatic_dx(body.mesh, s, device, warnings, measured)
        spacing = dx / s.particles_per_cell_axis
        estimate = float(np.prod(np.ceil(np.asarray(body.mesh.extents) / spacing)))
        if estimate > 4 * s.max_particles:
            raise UserError(f"filling the mesh at particle spacing {spacing:.3g} m needs about {estimate:,.0f} "
                            f"lattice points (settings max_particles = {s.max_particles:,}); use a larger dx or "
                            "fewer cells_across")
        points = fill_mesh(body.mesh, spacing, jitter=s.jitter, seed=s.seed)
        volume = spacing ** 3
        if body.mesh.is_watertight and body.mesh.volume > 0:
            # the lattice misses part of the cells cut by the surface: share the true volume (and mass)
            volume = float(body.mesh.volume) / len(points)
        volumes = np.full(len(points), volume)
    if len(points) > s.max_particles:
        raise UserError(f"the body needs {len(points):,} particles, more than settings max_particles = "
                        f"{s.max_particles:,}; use a larger dx")
    if progress:
        progress.set_status(f"MPM: material at {len(points):,} particles")
    sampled = sample_material(material, points, mode=s.material_sampling)
    for name in ("E", "density"):
        arr = getattr(sampled, name)
        if not np.all(np.isfinite(arr) & (arr > 0)):
            raise UserError(f"material {name} must be finite and positive at every particle")
    if not np.all((sampled.nu > -1.0) & (sampled.nu < 0.5)):
        raise UserError("material Poisson's ratio must lie in (-1, 0.5) at every particle")
    bad_ids = np.setdiff1d(np.unique(sampled.material), list(materials.BY_ID))
    if bad_ids.size:
        raise UserError(f"unknown material class id(s) {bad_ids.tolist()}; valid ids are "
                        f"0..{materials.NUM_CLASSES - 1}")
    simulated = _per_class(lambda c: c.simulated)[sampled.material]
    if not simulated.any():
        raise UserError("no simulated material: every particle is 'background'")
    points, volumes = points[simulated], volumes[simulated]
    sampled = SampledMaterial(sampled.E[simulated], sampled.nu[simulated], sampled.density[simulated],
                              sampled.material[simulated])
    sc = scenario
    if sc.ground_height is not None:
        below = int(np.sum(points[:, 2] < sc.ground_height - 1e-6))
        if below:
            raise UserError(f"{below} of {len(points)} particles start below the ground plane z = "
                            f"{sc.ground_height:g} m; move the object up or set the scenario's ground lower/null")
    rigid = _per_class(lambda c: c.held_fixed)[sampled.material]  # stationary: never deforms
    held = sc.pinned_mask(points) | rigid  # clamped material is held but may deform
    masses = sampled.density * volumes
    v0 = sc.initial_velocities(points, masses)
    v0[held] = 0.0
    com = (points * masses[:, None]).sum(0) / masses.sum()
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(points).query(tracked_rest)
    tracked_held = sc.pinned_mask(tracked_rest) | held[nearest]
    # rigid initial motion at the tracked points, about the particles' centre of mass
    tv0 = sc.initial_velocity[None, :] + np.cross(sc.initial_angular_velocity[None, :], tracked_rest - com)
    tv0[tracked_held] = 0.0

    dx = float(dx)
    # a particle stands for a cube of material: its lower face touches the ground (solvers/contact.py)
    spacing = float(np.mean(volumes)) ** (1.0 / 3.0)
    contact_radius = 0.5 * spacing
    contact_area = spacing * spacing
    C0 = _skew(sc.initial_angular_velocity)
    C0 = np.where(held[:, None, None], 0.0, C0[None]).astype(np.float32)
    F0 = np.eye(3) if s.initial_deformation is None else s.initial_deformation
    H0_particles = np.where(rigid[:, None, None], 0.0, (F0 - np.eye(3))[None]).astype(np.float32)
    U, _, Vt = np.linalg.svd(F0)
    R0 = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    from scipy.spatial.transform import Rotation

    rot0 = Rotation.from_matrix(R0).as_quat().astype(np.float32)  # (x, y, z, w) as Warp stores quats
    plastic0 = np.zeros(len(points))
    snow = _per_class(lambda c: c.plasticity == "snow")[sampled.material]
    plastic0[snow] = 1.0  # snow: plastic volume ratio Jp starts at 1
    anchor = np.array([0.0, 0.0, sc.ground_height if sc.ground_height is not None else 0.0])
    rho_min = float(sampled.density.min())
    # every deforming particle purely elastic fixed-corotated: the elastic-only P2G applies (see _choose_p2g)
    elastic_only = all(
        c.held_fixed or c.elasticity == "fixed_corotated" and c.plasticity == "none"
        and not math.isfinite(float(c.params.get("yield_stress", math.inf)))
        for c in (materials.BY_ID[int(i)] for i in np.unique(sampled.material)))

    return InitialParticles(dx=dx, positions=points, volumes=volumes, material=sampled, held=held,
                            tracked_held=tracked_held, masses=masses, velocities=v0, tracked_velocities=tv0,
                            affine_velocity=C0, displacement_gradient=H0_particles, rotation=rot0, plastic=plastic0,
                            contact_radius=contact_radius, contact_area=contact_area, grid_anchor=anchor,
                            min_density=rho_min, elastic_only=elastic_only, thinnest_part=measured["thinnest_part"],
                            warnings=warnings)


def automatic_dx(mesh, settings: MPMSettings, device: str, warnings: list, measured: dict) -> float:
    """dx (m) for a mesh body when the settings give none (see :class:`~.mpm_settings.MPMSettings`); appends to
    ``warnings`` when the particle budget keeps the thinnest parts under-resolved, and sets
    ``measured["thinnest_part"]`` (m, :func:`~.sampling.thinnest_part`)."""
    from .sampling import thinnest_part

    s = settings
    extent = float(np.max(np.asarray(mesh.extents, dtype=np.float64)))
    thin = thinnest_part(mesh)
    dx = coarse = extent / s.cells_across
    measured["thinnest_part"] = thin
    if not s.cells_across_thinnest and thin / coarse < THIN_PART_WARNING_CELLS:
        warnings.append(f"MPM: the thinnest parts ({thin * 1000:.3g} mm) are only {thin / coarse:.1f} cells thick "
                        f"at {s.cells_across} cells across: they bend too easily and lose their swing to numerical "
                        "damping (the demo's plant, 1.1 cells thick at 17 cells across: its crown's swing fell from "
                        "16 to 2 cm in 2 s; docs/fidelity.md) - leave cells_across unset (the bake default refines "
                        f"thin parts to {DEFAULT_CELLS_ACROSS_THINNEST} cells) or raise it")
    if not s.cells_across_thinnest or thin / s.cells_across_thinnest >= coarse:
        return coarse
    dx = thin / s.cells_across_thinnest
    budget = s.auto_max_particles or AUTO_MAX_PARTICLES["cuda" if str(device).startswith("cuda") else "cpu"]
    volume = float(mesh.volume) if mesh.is_watertight and mesh.volume > 0 else float(np.prod(mesh.extents))
    budget_dx = s.particles_per_cell_axis * (volume / budget) ** (1.0 / 3.0)
    if dx < budget_dx:  # the budget limits only the refinement for thin parts, never the extent's grid
        dx = min(budget_dx, coarse)
        warnings.append(f"MPM: the thinnest parts ({thin * 1000:.3g} mm) get only {thin / dx:.1f} cells "
                             f"across within the particle budget (settings auto_max_particles = "
                             f"{budget:,}); their bending is resolved coarsely - give dx or a "
                             "larger budget (a GPU affords millions of particles)")
    measured["thinnest_part"] = thin
    return dx
