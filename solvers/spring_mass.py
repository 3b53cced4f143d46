"""Spring-mass solver (Spring-Gaus parameterisation) in NVIDIA Warp.

The solid is a network of *anchors* (point masses) joined by springs:

* **Anchors.**  The solid is filled with sample points (:func:`~.sampling.fill_mesh`, or the
  body's own points), thinned by voxel down-sampling and then ordered by farthest-point
  sampling; the first ``anchors`` points (default :data:`DEFAULT_ANCHORS` = 2048) are the
  anchors.  The order is deterministic — the model's spring head predicts one stiffness per
  anchor in this order.  Each anchor owns the fill points nearest to it (its Voronoi cell):
  its volume ``V_i`` and mass ``m_i = Σ ρ ΔV`` come from them.
* **Springs.**  Each anchor is joined to its ``neighbours`` nearest anchors (default
  :data:`DEFAULT_NEIGHBOURS` = 32: in 3D this gives every anchor 30–45 springs, enough for
  the network to resist shear without bending or volume modes of zero energy, while a step
  stays one gather over a few dozen springs).  The directed k-NN lists are merged into one
  undirected spring per pair (Newton's third law; momentum is conserved); a spring's *rank*
  is its lower rank in the two lists (0 = nearest).
* **Stiffness.**  A per-anchor stiffness vector ``k`` ∈ R^{N_a} (newtons) and one global
  softness ``η`` (dimensionless, any real) give the spring constant of spring s = (i, j) of
  rest length L_s::

      κ_s = ½ (k_i + k_j) · w(rank_s; η) / L_s                      [N/m]
      w(r) = 1                                          for r < fixed_springs
      w(r) = clip(2 − b^((r − fixed)/(neighbours − fixed)), 0, 1),  b = exp(softplus(η))

  so the nearest ``fixed_springs`` (default 16) springs of every anchor keep full strength and
  farther ones are weakened by rank, more strongly the larger η (η → −∞: no weakening;
  η = 0: the farthest springs go from 1 down to ~0).  This is Spring-Gaus's form (stiffness
  over rest length, a rank-wise soft vector controlled by one scalar).  ``(k, η)`` is the
  2049-number vector (:data:`SPRING_PARAM_COUNT`) the model predicts.
* **Forces.**  Springs are linear in their length change; a dashpot along each spring damps
  the relative velocity along it (only with ``material_damping``).  Gravity and the
  ``wind`` acceleration act on every anchor; drags act on the absolute velocity.
* **Integration.**  Leapfrog: semi-implicit (symplectic) Euler with the velocities kept half a
  substep behind the positions (a half kick v −= Δt/2 a before the first substep, and
  v += (Δt − Δt')/2 a where the substep changes to Δt'), so positions are second-order accurate — a
  free fall is exact instead of drifting by g·t·Δt/2 (the velocities of ``particle_states`` are
  these half-step velocities); the substep is a fraction ``safety`` of
  the stability limit of the stiffest / most damped anchor (Gershgorin bound on M⁻¹K and
  M⁻¹C): ``ω² = max_i 2 Σ_s κ_s / m_i``, ``γ = max_i 2 Σ_s c_s / m_i``,
  ``dt ≤ safety · 4 / (γ + sqrt(γ² + 4 ω²))``.  Drags are applied implicitly.  Dashpots are
  explicit, so a strong ``material_damping`` (viscous time ρℓ²/η below the elastic substep,
  roughly η > ℓ sqrt(ρE)) makes the substep shorter in proportion — the cost of the exact
  Kelvin–Voigt rate; implicit one-sweep (Jacobi) alternatives were tried and dropped: they
  saturate and no longer damp in proportion to η (measured on the cantilever test).
* **Contact.**  The ground plane z = h is a hard, inelastic, frictionless (base model)
  constraint on anchors, applied at z = h + ``contact_offset`` (half the fill spacing: an anchor
  stands for a cell of material, the lowest anchors lie that far inside the surface): an anchor that would cross it lands on it and loses its normal
  velocity; ``ground_friction`` removes up to μ × that normal impulse from the tangential
  velocity (Coulomb, with sticking).  Anchors inside the scenario's ``pinned_box`` (the
  clamp) or of a ``held_fixed`` class (stationary) never move.
* **Output.**  Tracked points (mesh vertices, measurement points) are bound to their
  ``binding`` nearest anchors with inverse-distance-squared weights and follow the anchors
  *and* their rotations: x_p = Σ_b w_pb (x_b + R_b (X_p − X_b)), R_b the rotation of anchor
  b's spring star (polar decomposition of its least-squares deformation), so rigid motion
  of the whole solid is reproduced exactly.

**From (E, ν, ρ) to (m, k).**  A central-force network deformed affinely stores the energy
density ½ C:ε:ε with C_ijkl = (1/V) Σ_s κ_s L_s² n_i n_j n_k n_l; for isotropically
distributed springs this is an isotropic solid with λ = μ (ν = 1/4, Cauchy's relation) and
E = S / (6V), S = Σ_s κ_s L_s².  Attributing to each anchor its springs' share gives::

    k_i = c_E · 12 E_i V_i / Σ_{s∋i} w_s L_s          (with κ_s as above)

with E_i the volume mean of E over anchor i's cell.  Σ_{s∋i} w_s L_s assumes the anchor's springs spread evenly
over all directions; in a thin part (a bar or a leaf a few anchors thick) they lie along the part, and the
network is stiffer there (a 0.04 × 0.02 m bar 3 anchors thick stretched 10 % too little).  So the sum is
replaced by the one that fits the anchor's affine stiffness tensor (∝ k_i Σ w L d⊗d⊗d⊗d) to the isotropic
one in least squares, 5 ‖Σ_{s∋i} w L d⊗d⊗d⊗d‖² / Σ_{s∋i} w L (:meth:`AnchorNetwork.fabric_sums`; equal to
Σ w L for evenly spread springs; the bar then stretches within 1 %).  The calibration ``c_E``
(:data:`STIFFNESS_CALIBRATION`) corrects the affine estimate for the non-affine relaxation
of a disordered network and for the surface; it was measured on a clamped bar under
gravity (static elongation and axial period, both against the continuum) — see
``docs/spring_mass.md``.  The network's Poisson ratio is 1/4 whatever ν says (ν is not
used).  Masses: m_i = Σ ρ ΔV over the cell (mass is conserved exactly).

**Effects.**
``linear_drag`` / ``quadratic_drag`` / ``wind``: forces on every anchor as the registry says.
``material_damping`` (η_v Pa·s): dashpots on all springs, ``c_s = ½ (d_i + d_j) / L_s`` with
``d_i = c_E · 30 η_v V_i / Σ_{s∋i} L_s`` — the same affine argument with the network's
viscous "shear modulus" S_c / 15 set to η_v (its volumetric part equals the shear part, as
for the elastic network); dashpots leave rigid motion alone.
``plasticity`` (σ_y Pa): a spring whose strain exceeds ε_y = σ_y / Ē_s (Ē_s the mean of its
ends' E: the uniaxial yield strain) has its rest length moved so its strain stays at ±ε_y —
permanent deformation.  Classes with von Mises plasticity (metal, plasticine) use their
class yield stress the same way.
``ground_friction`` (μ): Coulomb friction at the ground (above).
``stiffness_region`` (factor): multiplies k_i (and E_i for the yield strain) of the anchors
in the region.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields
from typing import Optional

import numpy as np

from ..core.errors import SimulationDiverged, UserError
from ..core.progress import Progress, frame_done
from ..core.types import Trajectory
from . import materials as materials_mod
from .api import Simulation
from .body import Body
from .effects import PhysicsTerms
from .material_sampling import HomogeneousMaterial, MaterialSpec, sample_material
from .sampling import farthest_point_sampling, fill_mesh, thickness_at, voxel_downsample
from .scenario import Scenario
from .contact import RIGID_CONTACT_BETA

DEFAULT_ANCHORS = 2048
"""N_a: anchors of the network (the paper's spring head predicts N_a stiffnesses + 1 softness)."""
DEFAULT_NEIGHBOURS = 32
"""Springs from every anchor to its 32 nearest anchors (merged into undirected springs)."""
DEFAULT_FIXED_SPRINGS = 16
"""Springs of rank < 16 are never weakened by the softness."""
DEFAULT_SOFTNESS = 0.0
"""η used when the stiffness comes from a material field (Spring-Gaus's initial value)."""
DEFAULT_BINDING = 6
"""Anchors each tracked point / vertex is bound to."""
SPRING_PARAM_COUNT = DEFAULT_ANCHORS + 1
"""Length of the model's spring-mass vector (k ∈ R^{N_a}, η): 2049."""
NETWORK_POISSON_RATIO = 0.25
"""Poisson's ratio of an isotropic central-force network (Cauchy relation λ = μ)."""
P_WAVE_PER_E = (1 - NETWORK_POISSON_RATIO) / ((1 + NETWORK_POISSON_RATIO) * (1 - 2 * NETWORK_POISSON_RATIO))
"""M / E = (1 − ν) / ((1 + ν)(1 − 2ν)) of the network's material (ν = 1/4): its P-wave modulus per unit E."""
AFFINE_STIFFNESS_FACTOR = 12.0
"""k_i = c_E · 12 E_i V_i / Σ w_s L_s (affine network, see module docstring)."""
AFFINE_DASHPOT_FACTOR = 30.0
"""d_i = c_E · 30 η_v V_i / Σ L_s (affine network, viscous shear modulus S_c/15 = η_v)."""
STIFFNESS_CALIBRATION = 0.94
"""c_E: measured correction of the affine estimate (docs/spring_mass.md, tests/test_spring_mass.py)."""
ANCHORS_ACROSS_THIN = 3.0
"""Anchors wanted through the thickness of thin parts (adaptive anchor sampling, :func:`select_anchors`)."""
MAX_ANCHOR_REFINEMENT = 4.0
"""Thin parts get anchors at most this many times closer together than the uniform spacing."""
GPU_LANES_PER_ANCHOR = 32
"""Threads (one warp) that gather an anchor's ~40-60 half-edges on a GPU (settings.lanes_per_anchor)."""


# ------------------------------------------------------------------------------------- settings
@dataclass
class SpringMassSettings:
    """Set-up options of the spring-mass solver.

    anchors: N_a, number of anchors (fewer when the solid has fewer fill points).
    neighbours: springs per anchor before merging (k of the k-NN graph).
    fixed_springs: ranks below this keep full strength whatever the softness (at most ``neighbours``).
    softness: η, the global softness (dimensionless real).
    stiffness: ``None`` (derive k from the material's E) or (N_a,) newtons — explicit per-anchor
        stiffness, what the model's spring head predicts.
    binding: anchors per tracked point.
    fill_per_anchor: fill points per anchor used for masses and cell volumes.
    max_fill_points: cap on the number of fill points.
    safety: fraction of the stability limit used as the substep (0 < safety <= 1).
    substeps: ``None`` (from stability) or a fixed number of substeps per frame interval.
    max_substeps_per_frame: refuse (UserError) a run whose stability limit needs more substeps
        per frame interval than this (e.g. a huge ``material_damping`` η: dashpots are explicit).
    stiffness_calibration: c_E (see module docstring).
    lanes_per_anchor: threads that gather one anchor's spring forces (a tile reduction joins them; more than
        1 on the CPU needs ``warp.config.enable_cpu_blocks``).  ``None``: :data:`GPU_LANES_PER_ANCHOR` on a GPU,
        1 on the CPU.
    """

    anchors: int = DEFAULT_ANCHORS
    neighbours: int = DEFAULT_NEIGHBOURS
    fixed_springs: int = DEFAULT_FIXED_SPRINGS
    softness: float = DEFAULT_SOFTNESS
    stiffness: Optional[np.ndarray] = None
    binding: int = DEFAULT_BINDING
    fill_per_anchor: int = 12
    max_fill_points: int = 400_000
    safety: float = 0.7
    substeps: Optional[int] = None
    max_substeps_per_frame: int = 200_000
    stiffness_calibration: float = STIFFNESS_CALIBRATION
    lanes_per_anchor: Optional[int] = None

    def __post_init__(self):
        if self.lanes_per_anchor is not None:
            lanes = self.lanes_per_anchor
            if not isinstance(lanes, (int, np.integer)) or not 1 <= lanes <= 1024:
                raise UserError(f"spring-mass setting 'lanes_per_anchor' must be None or a whole number in 1..1024, "
                                f"got {lanes!r}")
            self.lanes_per_anchor = int(lanes)
        for name in ("anchors", "neighbours", "binding", "fill_per_anchor", "max_fill_points", "max_substeps_per_frame"):
            val = getattr(self, name)
            if not isinstance(val, (int, np.integer)) or val < 1:
                raise UserError(f"spring-mass setting '{name}' must be a positive whole number, got {val!r}")
            setattr(self, name, int(val))
        if not isinstance(self.fixed_springs, (int, np.integer)) or self.fixed_springs < 0:
            raise UserError(f"spring-mass setting 'fixed_springs' must be a whole number >= 0, got {self.fixed_springs!r}")
        self.fixed_springs = min(int(self.fixed_springs), self.neighbours)
        try:
            self.softness = float(self.softness)
        except (TypeError, ValueError):
            raise UserError(f"spring-mass setting 'softness' must be a number, got {self.softness!r}") from None
        if math.isnan(self.softness) or self.softness == math.inf:
            raise UserError(f"spring-mass setting 'softness' must be a real number (or -inf), got {self.softness}")
        if not (0.0 < float(self.safety) <= 1.0):
            raise UserError(f"spring-mass setting 'safety' must lie in (0, 1], got {self.safety!r}")
        if self.substeps is not None and (int(self.substeps) != self.substeps or self.substeps < 1):
            raise UserError(f"spring-mass setting 'substeps' must be None or a positive whole number, got {self.substeps!r}")
        if not (np.isfinite(self.stiffness_calibration) and self.stiffness_calibration > 0):
            raise UserError("spring-mass setting 'stiffness_calibration' must be positive")
        if self.stiffness is not None:
            k = np.asarray(self.stiffness, dtype=np.float64).reshape(-1)
            if k.size == 0 or not np.all(np.isfinite(k)) or np.any(k <= 0):
                raise UserError("explicit spring stiffness vector must be finite and positive (newtons, one per anchor)")
            self.stiffness = k

    @classmethod
    def coerce(cls, settings) -> "SpringMassSettings":
        if settings is None:
            return cls()
        if isinstance(settings, cls):
            return settings
        if isinstance(settings, dict):
            known = {f.name for f in fields(cls)}
            unknown = set(settings) - known
            if unknown:
                raise UserError(f"unknown spring-mass setting(s) {sorted(unknown)}; known: {sorted(known)}")
            return cls(**settings)
        raise UserError(f"spring-mass settings must be a SpringMassSettings or a dict, got {type(settings).__name__}")


# ------------------------------------------------------------------------------------- network
def softness_weights(ranks: np.ndarray, neighbours: int, fixed_springs: int, softness: float) -> np.ndarray:
    """Strength factor w ∈ [0, 1] of springs of the given neighbour ranks (0 = nearest).

    ranks: (S,) int; returns (S,) float64 (see the module docstring for the formula).
    """
    r = np.asarray(ranks, dtype=np.float64)
    span = max(neighbours - fixed_springs, 1)
    if softness == -math.inf:
        return np.ones_like(r)
    base_log = np.logaddexp(0.0, softness)  # softplus(η) = log b
    t = np.clip((r - fixed_springs) / span, 0.0, None)
    w = np.clip(2.0 - np.exp(base_log * t), 0.0, 1.0)
    return np.where(r < fixed_springs, 1.0, w)


@dataclass
class AnchorNetwork:
    """The anchors and springs of one solid (everything that does not depend on the effects).

    fill_points: (F, 3) m, samples of the solid; fill_volume: (F,) m³ each; fill_cell: (F,) anchor index.
    anchors: (N, 3) m rest positions in FPS order; volume: (N,) m³; mass: (N,) kg;
    E: (N,) Pa (cell mean); material: (N,) class ids; pinned: (N,) bool (clamp or stationary class).
    springs: (S, 2) anchor indices (i < j); rank: (S,) int; rest_length: (S,) m.
    """

    fill_points: np.ndarray
    fill_volume: np.ndarray
    fill_cell: np.ndarray
    anchors: np.ndarray
    volume: np.ndarray
    mass: np.ndarray
    E: np.ndarray
    material: np.ndarray
    pinned: np.ndarray
    springs: np.ndarray
    rank: np.ndarray
    rest_length: np.ndarray
    warnings: list

    @property
    def count(self) -> int:
        return int(len(self.anchors))

    def fabric_sums(self, weights: np.ndarray) -> np.ndarray:
        """Per anchor (Σ w L)² / ‖Σ w L d⊗d⊗d⊗d‖² · (1/5), (N,) m: the Σ w L that the least-squares fit of the
        network's affine stiffness tensor to an isotropic one divides by (module docstring).  Equal to Σ w L
        when an anchor's springs spread evenly over all directions; larger where they lie in a thin part's plane
        or along its axis (the network is stiffer along those directions than the trace says)."""
        n = self.count
        d = self.anchors[self.springs[:, 1]] - self.anchors[self.springs[:, 0]]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        wl = weights * self.rest_length
        quartic = np.einsum("si,sj,sk,sl->sijkl", d, d, d, d).reshape(len(d), 81) * wl[:, None]
        A = np.zeros((n, 81))
        np.add.at(A, self.springs[:, 0], quartic)
        np.add.at(A, self.springs[:, 1], quartic)
        swl = np.bincount(self.springs[:, 0], wl, n) + np.bincount(self.springs[:, 1], wl, n)
        return 5.0 * np.einsum("ij,ij->i", A, A) / np.maximum(swl, 1e-300)

    def spring_sums(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per anchor Σ_{s∋i} w_s L_s and Σ_{s∋i} L_s, (N,) m each."""
        n = self.count
        wl = weights * self.rest_length
        swl = np.bincount(self.springs[:, 0], wl, n) + np.bincount(self.springs[:, 1], wl, n)
        sl = (np.bincount(self.springs[:, 0], self.rest_length, n)
              + np.bincount(self.springs[:, 1], self.rest_length, n))
        return swl, sl


def _solid_volume(body: Body, fallback_pts: np.ndarray) -> float:
    if body.mesh is not None and getattr(body.mesh, "is_watertight", False) and body.mesh.volume > 0:
        return float(body.mesh.volume)
    if body.mesh is not None:
        try:
            return float(body.mesh.convex_hull.volume)
        except Exception:  # degenerate hull
            pass
    ext = np.ptp(fallback_pts, axis=0)
    return float(np.prod(np.maximum(ext, 1e-9)))


def fill_solid(body: Body, target_points: int, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample points of the solid and the volume each stands for.

    Returns (F, 3) m and (F,) m³ (summing to the mesh volume for a closed mesh, or to
    ``point_volume`` × count for a point body).
    """
    target_points = int(min(max(target_points, 64), max_points))
    if body.mesh is None:
        pts = np.asarray(body.points, dtype=np.float64)
        if body.point_volume is not None:
            vol = float(body.point_volume)
            if not (np.isfinite(vol) and vol > 0):
                raise UserError(f"the body's point_volume must be a positive volume in m³, got {body.point_volume!r}")
        elif len(pts) == 1:
            raise UserError("a body of a single point needs point_volume (m³)")
        else:
            from scipy.spatial import cKDTree

            d, _ = cKDTree(pts).query(pts, k=2)
            spacing = float(np.median(d[:, 1]))
            if spacing <= 0:
                raise UserError("the body's points coincide; give distinct points or a mesh")
            vol = spacing ** 3
        return pts, np.full(len(pts), vol)
    volume = _solid_volume(body, body.rest_points)
    spacing = (volume / target_points) ** (1.0 / 3.0)
    pts = fill_mesh(body.mesh, spacing)
    # a thin solid can come back nearly empty at the first spacing: refine until it has enough points
    for _ in range(3):
        if len(pts) >= 0.25 * target_points:
            break
        spacing *= 0.5
        pts = fill_mesh(body.mesh, spacing, max_points=max(8 * max_points, 20_000_000))
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(0).choice(len(pts), max_points, replace=False)]
    return pts, np.full(len(pts), volume / len(pts))


def select_anchors(points: np.ndarray, count: int, pinned: np.ndarray | None = None,
                   point_volume: float | None = None, thickness: np.ndarray | None = None,
                   across: float = ANCHORS_ACROSS_THIN) -> np.ndarray:
    """Indices into ``points`` of ``count`` anchors: voxel down-sampling, then farthest-point order.

    points: (F, 3) m fill points; pinned: (F,) bool, clamped points; point_volume: m³ each; thickness: (F,) m,
    the local thickness of the part each point belongs to (:func:`~.sampling.thickness_at`).
    With ``thickness``, the sampling is adaptive: where a part is thinner than ``across`` uniform anchor
    spacings, the wanted spacing shrinks in proportion (to at most :data:`MAX_ANCHOR_REFINEMENT` times finer), so
    a trunk, a leaf or a slender bar gets about ``across`` anchors through its thickness when the count allows
    (a bending part of one or two anchors' thickness bends far too easily or not at all).
    The clamped region gets anchors only where it meets free material (within three anchor spacings of it; the
    rest of a clamp holds nothing), in proportion to that volume (at least 4 when it has them).
    """
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    count = min(int(count), n)
    vol = float(point_volume) if point_volume else None

    def thin(idx: np.ndarray, k: int) -> np.ndarray:
        if k <= 0 or len(idx) == 0:
            return np.zeros(0, dtype=np.int64)
        sub = pts[idx]
        ext = np.ptp(sub, axis=0)
        occupied = len(idx) * vol if vol else max(float(np.prod(np.maximum(ext, 1e-12))), 1e-30)
        uniform = (occupied / k) ** (1.0 / 3.0)
        if len(idx) > 8 * k:
            voxel = 0.5 * uniform if thickness is not None else (occupied / (3.0 * k)) ** (1.0 / 3.0)
            cand = voxel_downsample(sub, voxel)
            while len(cand) < 2 * k:  # the volume over-estimates sparse clouds: shrink until enough
                voxel *= 0.7
                cand = voxel_downsample(sub, voxel)
            idx = idx[cand]
            sub = pts[idx]
        spacing = None
        if thickness is not None:
            spacing = np.clip(thickness[idx] / (across * uniform), 1.0 / MAX_ANCHOR_REFINEMENT, 1.0)
        return idx[farthest_point_sampling(sub, k, spacing=spacing)]

    if pinned is None or not np.any(pinned) or np.all(pinned):
        return thin(np.arange(n), count)
    free_idx = np.flatnonzero(~pinned)
    pin_idx = np.flatnonzero(pinned)
    from scipy.spatial import cKDTree

    uniform = (len(free_idx) * (vol or 1.0) / max(count, 1)) ** (1.0 / 3.0) if vol else None
    if uniform:
        near, _ = cKDTree(pts[free_idx]).query(pts[pin_idx], distance_upper_bound=3.0 * uniform)
        pin_idx = pin_idx[np.isfinite(near)] if np.isfinite(near).sum() >= 4 else pin_idx
    n_pin = int(round(count * len(pin_idx) / (len(pin_idx) + len(free_idx))))
    n_pin = min(max(n_pin, min(4, len(pin_idx))), len(pin_idx), count - 1)
    return np.concatenate([thin(pin_idx, n_pin), thin(free_idx, count - n_pin)])


def _springs_inside(anchors: np.ndarray, springs: np.ndarray, fill: np.ndarray, fill_spacing: float) -> np.ndarray:
    """(S,) bool: springs whose segment stays inside the solid - points at ¼, ½ and ¾ of it within one fill spacing
    of a fill point.  A spring through the air between two parts (two leaves, a trunk and the pot's rim) would
    join what the solid does not."""
    from scipy.spatial import cKDTree

    tree = cKDTree(fill)
    a, b = anchors[springs[:, 0]], anchors[springs[:, 1]]
    ok = np.ones(len(springs), dtype=bool)
    for t in (0.25, 0.5, 0.75):
        d, _ = tree.query(a + t * (b - a), distance_upper_bound=fill_spacing)
        ok &= np.isfinite(d)
    return ok


def build_network(body: Body, material: MaterialSpec, scenario: Scenario | None = None,
                  settings: SpringMassSettings | None = None) -> AnchorNetwork:
    """Anchors, masses, cell volumes and springs of ``body`` (see the module docstring)."""
    from scipy.spatial import cKDTree

    settings = SpringMassSettings.coerce(settings)
    warnings: list[str] = []
    fill, fvol = fill_solid(body, settings.anchors * settings.fill_per_anchor, settings.max_fill_points)
    mat = sample_material(material, fill)
    simulated = np.array([materials_mod.get(int(c)).simulated for c in range(materials_mod.NUM_CLASSES)])
    keep = simulated[mat.material]
    if not np.any(keep):
        raise UserError("the material field marks the whole solid as background (not simulated)")
    if not np.all(keep):
        warnings.append(f"{int((~keep).sum())} of {len(keep)} fill points are background material and carry no mass")
        fill, fvol = fill[keep], fvol[keep]
        mat = type(mat)(mat.E[keep], mat.nu[keep], mat.density[keep], mat.material[keep])
    held = np.array([materials_mod.get(int(c)).held_fixed for c in range(materials_mod.NUM_CLASSES)])
    pinned_fill = held[mat.material]
    if scenario is not None:
        pinned_fill = pinned_fill | scenario.pinned_mask(fill)
    if len(fill) < 2:
        raise UserError("the solid has fewer than 2 sample points; a spring-mass network needs at least 2 anchors")
    fill_spacing = float(np.mean(fvol)) ** (1.0 / 3.0)
    thickness = thickness_at(fill, fill_spacing) if body.mesh is not None else None
    a_idx = select_anchors(fill, settings.anchors, pinned_fill, point_volume=float(np.mean(fvol)), thickness=thickness)
    anchors = fill[a_idx]
    n = len(anchors)
    if n < settings.anchors:
        warnings.append(f"only {n} anchors could be placed (asked for {settings.anchors})")
    tree = cKDTree(anchors)
    _, cell = tree.query(fill)
    volume = np.bincount(cell, fvol, n)
    mass = np.bincount(cell, fvol * mat.density, n)
    E_cell = np.bincount(cell, fvol * mat.E, n) / np.maximum(volume, 1e-300)
    # an anchor whose cell is empty (cannot happen for anchors drawn from the fill points, kept safe)
    empty = volume <= 0
    if np.any(empty):
        mean_v = float(volume[~empty].mean())
        volume[empty] = mean_v
        mass[empty] = mean_v * float(np.mean(mat.density))
        E_cell[empty] = float(np.mean(mat.E))
    a_mat = mat.material[a_idx]
    pinned = pinned_fill[a_idx]
    # springs: directed k-NN merged into undirected pairs with the lower rank
    k = min(settings.neighbours, n - 1)
    _, nn = tree.query(anchors, k=k + 1)
    nn = np.asarray(nn).reshape(n, k + 1)
    src = np.repeat(np.arange(n), k)
    dst = nn[:, 1:].reshape(-1)
    rank = np.tile(np.arange(k), n)
    ok = dst != src  # duplicates of a point can return itself later in the list
    src, dst, rank = src[ok], dst[ok], rank[ok]
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    order = np.lexsort((rank, hi, lo))
    lo, hi, rank = lo[order], hi[order], rank[order]
    first = np.ones(len(lo), dtype=bool)
    first[1:] = (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
    springs = np.stack([lo[first], hi[first]], axis=1).astype(np.int64)
    rank = rank[first].astype(np.int64)
    if body.mesh is not None:  # no springs through the air between parts; every anchor keeps its nearest three
        inside = _springs_inside(anchors, springs, fill, fill_spacing) | (rank < 3)
        if not np.all(inside):
            warnings.append(f"{int((~inside).sum())} of {len(springs)} springs would cross empty space and were left out")
        springs, rank = springs[inside], rank[inside]
    rest = np.linalg.norm(anchors[springs[:, 1]] - anchors[springs[:, 0]], axis=1)
    if np.any(rest <= 0):
        raise UserError("two anchors coincide (duplicate points in the body); remove duplicate points")
    return AnchorNetwork(fill, fvol, cell, anchors, volume, mass, E_cell, a_mat, pinned, springs, rank, rest, warnings)


def anchor_positions(body: Body, anchors: int = DEFAULT_ANCHORS, scenario: Scenario | None = None) -> np.ndarray:
    """(N_a, 3) m rest positions of the anchors in the order the spring head's stiffnesses refer to.

    The anchors depend on the geometry (and the clamp), not on the material.
    """
    mat = HomogeneousMaterial(1e5, 0.3, 1000.0)
    return build_network(body, mat, scenario, SpringMassSettings(anchors=anchors)).anchors


def stiffness_from_youngs_modulus(network: AnchorNetwork, E: np.ndarray, settings: SpringMassSettings) -> np.ndarray:
    """Per-anchor stiffness k (N_a,) newtons that makes the network's modulus E (N_a,) Pa (module docstring)."""
    w = softness_weights(network.rank, settings.neighbours, settings.fixed_springs, settings.softness)
    swl = network.fabric_sums(w)
    if np.any(swl <= 0):
        raise UserError("the softness weakens every spring of some anchor to zero; lower the softness η")
    return settings.stiffness_calibration * AFFINE_STIFFNESS_FACTOR * np.asarray(E, np.float64) * network.volume / swl


def youngs_modulus_from_stiffness(network: AnchorNetwork, k: np.ndarray, settings: SpringMassSettings) -> np.ndarray:
    """Inverse of :func:`stiffness_from_youngs_modulus`: the modulus (N_a,) Pa a stiffness vector stands for."""
    w = softness_weights(network.rank, settings.neighbours, settings.fixed_springs, settings.softness)
    swl = network.fabric_sums(w)
    return np.asarray(k, np.float64) * swl / (settings.stiffness_calibration * AFFINE_STIFFNESS_FACTOR * network.volume)


# ------------------------------------------------------------------------------------- simulation
class SpringMassSimulation(Simulation):
    """A prepared spring-mass simulation (see the module docstring).

    Public attributes (numpy, SI): ``network`` (:class:`AnchorNetwork`), ``stiffness`` (N,) N,
    ``softness`` η, ``spring_weight`` (S,), ``spring_kappa`` (S,) N/m (base, no effects),
    ``dashpot_unit`` (N,) N·s per Pa·s of ``material_damping``, ``youngs_modulus`` (N,) Pa the
    stiffness stands for, ``inv_mass`` (N,) (0 = clamped), ``contact_offset`` m (anchors touch the
    ground this far above it).
    """

    solver = "spring_mass"

    def __init__(self, body: Body, material: MaterialSpec, scenario: Scenario, frame_times, device: str,
                 settings: SpringMassSettings, progress: Progress | None = None):
        from .warp_runtime import init_warp, resolve_device

        super().__init__(body, scenario, frame_times, resolve_device(device))
        self.settings = settings
        self.warnings: list[str] = list(body.warnings)
        net = build_network(body, material, scenario, settings)
        self.network = net
        self.warnings += net.warnings
        n = net.count
        self.sample_positions = net.anchors.copy()
        if progress is not None:
            progress.step(0.0, "spring network built")
        # stiffness: explicit (model) or from the material's E
        self.softness = settings.softness
        self.spring_weight = softness_weights(net.rank, settings.neighbours, settings.fixed_springs, settings.softness)
        if settings.stiffness is not None:
            if len(settings.stiffness) != n:
                raise UserError(f"the explicit stiffness vector has {len(settings.stiffness)} entries but the solid "
                                f"has {n} anchors (settings.anchors = {settings.anchors}); give one per anchor")
            self.stiffness = settings.stiffness.copy()
            self.youngs_modulus = youngs_modulus_from_stiffness(net, self.stiffness, settings)
        else:
            self.stiffness = stiffness_from_youngs_modulus(net, net.E, settings)
            self.youngs_modulus = net.E.copy()
        sl = net.fabric_sums(np.ones(len(net.springs)))
        self.dashpot_unit = settings.stiffness_calibration * AFFINE_DASHPOT_FACTOR * net.volume / np.maximum(sl, 1e-300)
        self.spring_kappa = self._kappa(self.stiffness)
        # class yield stress (von Mises classes): per anchor
        cls_yield = np.array([c.params.get("yield_stress", math.inf) if c.plasticity == "von_mises" else math.inf
                              for c in materials_mod.MATERIAL_CLASSES])
        self.class_yield = cls_yield[net.material]
        inelastic = {materials_mod.get(int(c)).name for c in np.unique(net.material)
                     if materials_mod.get(int(c)).plasticity in ("drucker_prager", "snow")
                     or materials_mod.get(int(c)).elasticity == "weakly_compressible"}
        if inelastic:
            self.warnings.append("the spring-mass solver models " + ", ".join(sorted(inelastic))
                                 + " material as an elastic spring network (no granular/fluid/snow law)")
        self.inv_mass = np.where(net.pinned, 0.0, 1.0 / net.mass)
        # contact: each anchor's cell (its fill points and nearest surface samples) touches the ground with its
        # lowest point, over the area V^(2/3) of a cube of its volume (solvers/contact.py)
        self.contact_size = net.volume ** (1.0 / 3.0)
        self.contact_area = self.contact_size ** 2
        self._cell_points = self._contact_cells(body)
        # half-edges in CSR order
        s_idx = np.arange(len(net.springs))
        src = np.concatenate([net.springs[:, 0], net.springs[:, 1]])
        dst = np.concatenate([net.springs[:, 1], net.springs[:, 0]])
        sid = np.concatenate([s_idx, s_idx])
        order = np.argsort(src, kind="stable")
        self._he_src, self._he_dst, self._he_spring = src[order], dst[order], sid[order]
        self._he_start = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=n))]).astype(np.int32)
        # rotation fit (Gram matrix inverse per anchor)
        d0 = net.anchors[self._he_dst] - net.anchors[self._he_src]
        gram = np.zeros((n, 3, 3))
        np.add.at(gram, self._he_src, d0[:, :, None] * d0[:, None, :])
        tr = np.trace(gram, axis1=1, axis2=2)
        gram += (1e-6 * tr + 1e-30)[:, None, None] * np.eye(3)
        self._gram_inv = np.linalg.inv(gram)
        # binding of tracked points
        from scipy.spatial import cKDTree

        kb = min(settings.binding, n)
        dist, idx = cKDTree(net.anchors).query(self.tracked_rest, k=kb)
        dist = np.asarray(dist).reshape(len(self.tracked_rest), kb)
        idx = np.asarray(idx).reshape(len(self.tracked_rest), kb)
        scale = float(np.median(net.rest_length)) if len(net.rest_length) else 1.0
        w = 1.0 / (dist + 1e-3 * scale) ** 2
        self.binding_index = idx.astype(np.int32)
        self.binding_weight = w / w.sum(1, keepdims=True)
        self._wp = init_warp()
        self._upload_static()

    # -------------------------------------------------------------------------------- helpers
    def _contact_cells(self, body: Body) -> tuple[np.ndarray, np.ndarray]:
        """Each anchor's contact cell as CSR: (N + 1,) int32 starts and (Q, 3) m offsets X_q − X_i of its points.

        The points are the anchor's fill points and the solid's surface samples (mesh vertices and area samples,
        or the body's own points) nearest to it, so the lowest one reaches the solid's surface.
        """
        from scipy.spatial import cKDTree

        net = self.network
        pts = [net.fill_points]
        if body.mesh is not None:
            import trimesh

            count = max(8 * net.count, 1000)
            surf, _ = trimesh.sample.sample_surface_even(body.mesh, count, seed=0)
            pts += [np.asarray(body.mesh.vertices, np.float64), np.asarray(surf, np.float64)]
        # a point body's points stand for cubes of material: its surface lies half their spacing further out
        self.contact_margin = 0.0 if body.mesh is not None else 0.5 * float(np.mean(net.fill_volume)) ** (1.0 / 3.0)
        allp = np.concatenate(pts)
        _, owner = cKDTree(net.anchors).query(allp)
        order = np.argsort(owner, kind="stable")
        start = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=net.count))]).astype(np.int32)
        return start, allp[order] - net.anchors[owner[order]]

    def _kappa(self, k_anchor: np.ndarray) -> np.ndarray:
        """(S,) N/m spring constants for per-anchor stiffness (N,) newtons."""
        s = self.network.springs
        return 0.5 * (k_anchor[s[:, 0]] + k_anchor[s[:, 1]]) * self.spring_weight / self.network.rest_length

    def _upload_static(self):
        wp = self._wp
        dev = self.device
        self._d_start = wp.array(self._he_start, dtype=wp.int32, device=dev)
        self._d_nbr = wp.array(self._he_dst.astype(np.int32), dtype=wp.int32, device=dev)
        self._d_inv_mass = wp.array(self.inv_mass.astype(np.float32), dtype=wp.float32, device=dev)
        self._d_rest_pos = wp.array(self.network.anchors.astype(np.float32), dtype=wp.vec3, device=dev)
        self._d_gram_inv = wp.array(self._gram_inv.astype(np.float32), dtype=wp.mat33, device=dev)
        self._d_track_rest = wp.array(self.tracked_rest.astype(np.float32), dtype=wp.vec3, device=dev)
        self._d_bind_idx = wp.array(self.binding_index, dtype=wp.int32, device=dev)
        self._d_bind_w = wp.array(self.binding_weight.astype(np.float32), dtype=wp.float32, device=dev)
        start, offsets = self._cell_points
        self._d_cell_start = wp.array(start, dtype=wp.int32, device=dev)
        self._d_cell_offsets = wp.array(offsets.astype(np.float32), dtype=wp.vec3, device=dev)
        self._d_contact_area = wp.array(self.contact_area.astype(np.float32), dtype=wp.float32, device=dev)

    def env_arrays(self, terms: PhysicsTerms) -> dict:
        """Per-environment numpy arrays for one set of physics terms (half-edge order)."""
        net = self.network
        scale = terms.E_multiplier(net.count)
        kappa_s = self._kappa(self.stiffness * scale)
        s = net.springs
        damp_s = terms.damping_eta * 0.5 * (self.dashpot_unit[s[:, 0]] + self.dashpot_unit[s[:, 1]]) / net.rest_length
        E_eff = self.youngs_modulus * scale
        E_s = 0.5 * (E_eff[s[:, 0]] + E_eff[s[:, 1]])
        ys = np.minimum(np.minimum(self.class_yield[s[:, 0]], self.class_yield[s[:, 1]]), terms.yield_stress)
        from .spring_mass_kernels import BIG

        ey = np.where(np.isfinite(ys), ys / E_s, BIG)
        he = self._he_spring
        return {"kappa": kappa_s[he], "dashpot": damp_s[he], "yield_strain": np.minimum(ey, BIG)[he], "kappa_s": kappa_s,
                "dashpot_s": damp_s}

    def stable_substep(self, kappa_s: np.ndarray, dashpot_s: np.ndarray) -> float:
        """Largest stable substep (s) for spring constants (S,) N/m and dashpots (S,) N·s/m, times ``safety``."""
        net = self.network
        n = net.count
        s = net.springs
        ksum = np.bincount(s[:, 0], kappa_s, n) + np.bincount(s[:, 1], kappa_s, n)
        csum = np.bincount(s[:, 0], dashpot_s, n) + np.bincount(s[:, 1], dashpot_s, n)
        free = self.inv_mass > 0
        if not np.any(free):
            return math.inf
        omega2 = float(np.max(2.0 * ksum[free] * self.inv_mass[free]))
        gamma = float(np.max(2.0 * csum[free] * self.inv_mass[free]))
        if omega2 <= 0 and gamma <= 0:
            return math.inf
        return self.settings.safety * 4.0 / (gamma + math.sqrt(gamma * gamma + 4.0 * omega2))

    def energy(self, positions: np.ndarray, velocities: np.ndarray, rest_lengths: np.ndarray | None = None,
               terms: PhysicsTerms | None = None) -> dict:
        """Kinetic, elastic and gravitational energy (J) of anchor positions/velocities (N, 3).

        rest_lengths: (S,) m (default: the initial ones).  Gravity potential is m g·x summed
        (relative to the origin), wind included when ``terms`` is given.
        """
        net = self.network
        x = np.asarray(positions, np.float64)
        v = np.asarray(velocities, np.float64)
        L = net.rest_length if rest_lengths is None else rest_lengths
        kappa = self.spring_kappa if terms is None else self.env_arrays(terms)["kappa_s"]
        l = np.linalg.norm(x[net.springs[:, 1]] - x[net.springs[:, 0]], axis=1)
        acc = self.scenario.gravity + (0 if terms is None else terms.extra_acceleration)
        kin = 0.5 * float(np.sum(net.mass * np.sum(v * v, axis=1)))
        ela = 0.5 * float(np.sum(kappa * (l - L) ** 2))
        pot = -float(np.sum(net.mass * (x @ acc)))
        return {"kinetic": kin, "elastic": ela, "potential": pot, "total": kin + ela + pot}

    # -------------------------------------------------------------------------------- running
    def _run_terms(self, terms_list: list[PhysicsTerms], *, progress: Progress | None,
                   particle_states: bool) -> list[Trajectory]:
        wp = self._wp
        from . import spring_mass_kernels as K

        dev = self.device
        net = self.network
        n_env = len(terms_list)
        if n_env == 0:
            return []
        n = net.count
        T = len(self.frame_times)
        P = len(self.tracked_rest)
        envs = [self.env_arrays(t) for t in terms_list]
        dt_max = min(self.stable_substep(e["kappa_s"], e["dashpot_s"]) for e in envs)
        stack = lambda key: np.stack([e[key] for e in envs]).astype(np.float32)  # noqa: E731
        d_kappa = wp.array(stack("kappa"), dtype=wp.float32, device=dev)
        d_dash = wp.array(stack("dashpot"), dtype=wp.float32, device=dev)
        d_yield = wp.array(stack("yield_strain"), dtype=wp.float32, device=dev)
        rest0 = net.rest_length[self._he_spring].astype(np.float32)
        d_rest = wp.array(np.tile(rest0, (n_env, 1)), dtype=wp.float32, device=dev)
        accel = np.stack([self.scenario.gravity + t.extra_acceleration for t in terms_list]).astype(np.float32)
        d_accel = wp.array(accel, dtype=wp.vec3, device=dev)
        d_lin = wp.array(np.array([t.linear_drag for t in terms_list], np.float32), dtype=wp.float32, device=dev)
        d_quad = wp.array(np.array([t.quadratic_drag for t in terms_list], np.float32), dtype=wp.float32, device=dev)
        ground_law = np.array([(min(t.ground_stiffness, 1e30), t.ground_damping, t.friction_mu) for t in terms_list])
        d_ground_law = wp.array(ground_law.astype(np.float32), dtype=wp.vec3, device=dev)
        # each anchor's rigid-floor spring k_r = β² M A / ℓ (solvers/contact.py), M of the network's material
        M = P_WAVE_PER_E * self.youngs_modulus[None] * np.stack([t.E_multiplier(n) for t in terms_list])
        rigid_k = RIGID_CONTACT_BETA ** 2 * M * (self.contact_area / self.contact_size)[None]
        eta = np.array([t.damping_eta for t in terms_list])[:, None]
        d_rigid_k = wp.array(rigid_k.astype(np.float32), dtype=wp.float32, device=dev)
        d_rigid_c = wp.array((2.0 * eta * rigid_k / M).astype(np.float32), dtype=wp.float32, device=dev)
        d_contact_low = wp.zeros((n_env, n), dtype=wp.float32, device=dev)
        x0 = np.tile(net.anchors.astype(np.float32), (n_env, 1, 1))
        v0 = np.tile(self.scenario.initial_velocities(net.anchors, net.mass).astype(np.float32), (n_env, 1, 1))
        v0[:, net.pinned] = 0.0
        bufs = [(wp.array(x0, dtype=wp.vec3, device=dev), wp.array(v0, dtype=wp.vec3, device=dev)),
                (wp.zeros((n_env, n), dtype=wp.vec3, device=dev), wp.zeros((n_env, n), dtype=wp.vec3, device=dev))]
        rot = wp.zeros((n_env, n), dtype=wp.mat33, device=dev)
        out_track = wp.zeros((n_env, T, P), dtype=wp.vec3, device=dev)
        if particle_states:
            out_x = wp.zeros((n_env, T, n), dtype=wp.vec3, device=dev)
            out_v = wp.zeros((n_env, T, n), dtype=wp.vec3, device=dev)
        has_ground = 0 if self.scenario.ground_height is None else 1
        ground = 0.0 if self.scenario.ground_height is None else float(self.scenario.ground_height)

        use_graph = wp.get_device(dev).is_cuda
        lanes = self.settings.lanes_per_anchor or (GPU_LANES_PER_ANCHOR if use_graph else 1)

        def launch_substep(a, b, dt, record_cmd=False):
            """Launch (or record) one substep from buffer a to buffer b."""
            inputs = [bufs[a][0], bufs[a][1], bufs[b][0], bufs[b][1], d_rest, d_kappa, d_dash, d_yield,
                      self._d_start, self._d_nbr, self._d_inv_mass, self._d_rest_pos, d_accel, d_lin, d_quad,
                      d_ground_law, d_contact_low, self._d_contact_area, d_rigid_k, d_rigid_c, ground, has_ground,
                      float(dt)]
            return wp.launch_tiled(K.spring_substep, dim=(n_env, n), inputs=inputs, device=dev, block_dim=lanes,
                                   record_cmd=record_cmd)

        cmds = []
        if not use_graph:
            cmds = [launch_substep(a, 1 - a, 1e-4, record_cmd=True) for a in (0, 1)]
        graphs: dict = {}

        def output(frame: int):
            x, v = bufs[0]
            wp.launch(K.anchor_rotations, dim=(n_env, n), inputs=[x, self._d_rest_pos, self._d_start, self._d_nbr,
                                                                   self._d_gram_inv, rot], device=dev)
            if has_ground:  # the cells' lowest points for the next frame's contacts (rotation lagged by a frame)
                wp.launch(K.contact_depths, dim=(n_env, n), inputs=[rot, self._d_cell_start, self._d_cell_offsets,
                                                                     self.contact_margin, d_contact_low], device=dev)
            if P:
                wp.launch(K.bind_points, dim=(n_env, P), inputs=[x, self._d_rest_pos, rot, self._d_track_rest,
                                                                  self._d_bind_idx, self._d_bind_w, ground, has_ground,
                                                                  out_track, frame],
                          device=dev)
            if particle_states:
                wp.launch(K.store_state, dim=(n_env, n), inputs=[x, v, out_x, out_v, frame], device=dev)

        def kick(tau: float) -> None:
            """Leapfrog bookkeeping: v += τ a(x, v) on the current state (buffer 0), positions unchanged.  The
            kicked velocities go to buffer 1 (free between frames) and are copied back: every anchor's dashpots
            read its neighbours' velocities from before the kick."""
            wp.launch(K.velocity_kick, dim=(n_env, n), device=dev,
                      inputs=[bufs[0][0], bufs[0][1], bufs[1][1], d_rest, d_kappa, d_dash, d_yield, self._d_start,
                              self._d_nbr, self._d_inv_mass, d_accel, d_lin, d_quad, float(tau)])
            wp.copy(bufs[0][1], bufs[1][1])

        total_substeps = 0
        t_start = time.perf_counter()
        output(0)
        dt_now = 0.0  # the substep the half-step velocities are staggered for
        for f in range(1, T):
            interval = self.frame_times[f] - self.frame_times[f - 1]
            if self.settings.substeps is not None:
                n_sub = int(self.settings.substeps)
            else:
                n_sub = max(1, math.ceil(interval / dt_max)) if math.isfinite(dt_max) else 1
            if n_sub > self.settings.max_substeps_per_frame:
                eta = max(t.damping_eta for t in terms_list)
                raise UserError(f"the spring-mass network needs {n_sub:,} substeps per frame (limit "
                                f"{self.settings.max_substeps_per_frame:,}): its stiffest spring"
                                + (f" or the material damping η = {eta:g} Pa·s (explicit dashpots)" if eta > 0 else "")
                                + " is too stiff for its lightest anchor; use fewer anchors, a lower η or E, "
                                  "or the LBS solver (implicit)")
            n_sub += n_sub % 2  # even: the state ends in buffer 0
            dt = interval / n_sub
            if dt != dt_now:  # velocities are kept half a substep behind the positions (leapfrog)
                kick(0.5 * (dt_now - dt))
                dt_now = dt
            if use_graph:
                key = (n_sub, float(dt))
                if key not in graphs:
                    with wp.ScopedCapture(device=dev) as cap:
                        for s in range(n_sub):
                            launch_substep(s % 2, 1 - s % 2, dt)
                    graphs[key] = cap.graph
                wp.capture_launch(graphs[key])
            else:
                for c in cmds:
                    c.set_param_by_name("dt", float(dt))
                for s in range(n_sub // 2):
                    for c in cmds:
                        c.launch()
            total_substeps += n_sub
            output(f)
            frame_done(progress, 1.0 / max(T - 1, 1), f"spring-mass frame {f}/{T - 1}")
        tracked = out_track.numpy()
        wp.synchronize_device(dev)
        wall = time.perf_counter() - t_start
        part_x = out_x.numpy() if particle_states else None
        part_v = out_v.numpy() if particle_states else None
        results = []
        for e in range(n_env):
            pos = tracked[e]
            bad = ~np.all(np.isfinite(pos.reshape(T, -1)), axis=1)
            if np.any(bad):
                f = int(np.argmax(bad))
                raise SimulationDiverged(f"the spring-mass simulation diverged at frame {f} (t = {self.frame_times[f]:.4g} s); "
                                         "lower settings.safety or set more substeps")
            meta = {"substep_s": float(dt_max) if math.isfinite(dt_max) else None, "substeps": total_substeps,
                    "anchors": n, "springs": int(len(net.springs)), "softness": self.softness,
                    "device": dev, "wall_s": wall, "warnings": list(self.warnings)}
            traj = Trajectory(self.frame_times, pos, solver=self.solver, meta=meta)
            if particle_states:
                traj.particle_positions = part_x[e]
                traj.particle_attributes = {"velocity": part_v[e], "mass": net.mass.astype(np.float32),
                                            "E": self.youngs_modulus.astype(np.float32),
                                            "stiffness": self.stiffness.astype(np.float32),
                                            "material": net.material.astype(np.int32)}
            results.append(traj)
        return results


def prepare(body: Body, material: MaterialSpec, scenario: Scenario, frame_times, device: str = "cpu",
            settings=None, progress: Progress | None = None) -> SpringMassSimulation:
    """Build the anchor network and upload it; returns a :class:`SpringMassSimulation`.

    settings: :class:`SpringMassSettings` or a dict of its fields (``stiffness`` + ``softness``
    run the model's explicit (k, η) parameters; the material then only gives masses).
    """
    if not isinstance(body, Body):
        raise UserError(f"expected a Body, got {type(body).__name__}")
    if not isinstance(scenario, Scenario):
        raise UserError(f"expected a Scenario, got {type(scenario).__name__}")
    settings = SpringMassSettings.coerce(settings)
    return SpringMassSimulation(body, material, scenario, frame_times, device, settings, progress)


def prepare_with_parameters(body: Body, stiffness: np.ndarray, softness: float, material: MaterialSpec,
                            scenario: Scenario, frame_times, device: str = "cpu", settings=None,
                            progress: Progress | None = None) -> SpringMassSimulation:
    """Run with the spring head's explicit parameters: ``stiffness`` (N_a,) newtons and softness η.

    ``material`` gives the density (masses) and class; its E is not used.
    """
    settings = SpringMassSettings.coerce(settings)
    k = np.asarray(stiffness, dtype=np.float64).reshape(-1)
    fields_ = {f.name: getattr(settings, f.name) for f in fields(SpringMassSettings)}
    fields_.update(stiffness=k, softness=softness, anchors=len(k))
    return prepare(body, material, scenario, frame_times, device=device, settings=SpringMassSettings(**fields_),
                   progress=progress)


def split_parameter_vector(vector: np.ndarray) -> tuple[np.ndarray, float]:
    """The model's (N_a + 1,) vector -> (stiffness (N_a,) newtons, softness η)."""
    v = np.asarray(vector, dtype=np.float64).reshape(-1)
    if v.size < 2:
        raise UserError(f"a spring-mass parameter vector needs N_a stiffnesses + 1 softness, got {v.size} numbers")
    return v[:-1], float(v[-1])
