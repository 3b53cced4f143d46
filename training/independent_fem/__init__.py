"""An independent simulator for validating the diagnosis: linear-tetrahedral FEM, RK4, penalty contact.

The diagnosis (:mod:`unipixie.core.diagnosis`) must find missing physics in measurements made by
*other* simulators, which it never sees.  This module is such a simulator, written from scratch for
validation only — the diagnosis never imports it, and it shares no code with
:mod:`unipixie.solvers` (no anchors, particles or grids; its own mesh, constitutive law, effects,
contact, integrator and file writer).  It implements the measurement spec
(``shared/specs/measurement-format.md``) from the outside: it reads a scenario dict and writes a
``unipixie.measurement/1`` archive.

Model
-----
* **Mesh.**  Linear tetrahedra.  Boxes get a structured mesh (each lattice cell cut into six
  tetrahedra around its main diagonal, conforming); other closed surfaces a Delaunay mesh of the
  surface vertices plus interior lattice points (``scipy.spatial.Delaunay``), keeping the
  tetrahedra whose centroid is inside the surface and whose volume is not degenerate.  The
  tracked points are the mesh's boundary nodes; the boundary triangles (outward) are the
  measurement's ``faces``.
* **Elasticity.**  Fixed-corotated hyperelasticity (the spec's base model) with E, ν honoured:
  ψ(F) = μ‖F − R‖² + ½λ(J − 1)², first Piola stress P = 2μ(F − R) + λ(J − 1) cof F, R the
  rotation of the polar decomposition (scaled Newton iteration; SVD for badly distorted
  elements).  Lumped masses m_a = Σ ρ V_e / 4 (exact total mass and centre of mass).
* **Time integration.**  Classical explicit Runge–Kutta of order 4 on (x, v), with a fixed step
  per frame interval at ``safety`` × the RK4 stability limit 2.5 / max(ω_max, γ_max), where
  ω_max² and γ_max are the largest eigenvalues of M⁻¹K and M⁻¹C at rest (power iteration on the
  force function).  The default ``safety`` = 0.25 keeps RK4's own dissipation of the slowest
  vibration below 0.5 % over a second (|R(iωΔt)|² = 1 − (ωΔt)⁶/72 + …).  Plastic flow and
  friction (and the hard contact's projection) are applied after each step (operator splitting).
* **Ground.**  Two laws, chosen by name (``FEMSettings.contact_law``), so that no single contact law
  is the truth.  ``"penalty"`` (the default): on every node a normal force
  m_a (k (h − z) − c v_z), never pulling, with k = ``contact_stiffness`` × ω_max² and c = 2ζ √k (ζ =
  ``contact_damping_ratio``, default 1) — at the default stiffness the contact is exactly as stiff
  as the stiffest element, so it barely shortens the step, and sinks ~0.1 mm under a block's weight;
  ζ = 0 keeps what the springs store.  ``"hard"``: an inelastic projection after each step — a node
  below the plane is put back on it and its downward velocity zeroed (never any penetration at the
  frames; the energy of the touching nodes' normal motion is lost).  With the ``contact_damping``
  effect (k Pa/m, c Pa·s/m) neither law applies: the floor gives and damps, each node feeling
  A_a (k (h − z) − c v_z), never pulling, with A_a its footprint (a third of the horizontal projection of
  each downward-facing boundary triangle it is a corner of).
* **Clamp.**  Nodes inside the scenario's ``pinned_box`` never move.

Effects (the spec's vocabulary and parameter meanings, implemented here independently)
---------------------------------------------------------------------------------------
``linear_drag`` c: −c m_a v_a on every node.  ``quadratic_drag`` k: −k m_a ‖v_a‖ v_a.
``wind`` a: extra acceleration on every node.  ``material_damping`` η: Kelvin–Voigt viscous
Cauchy stress σ_v = 2η D, D = sym(∇v) (first Piola 2η D cof F; zero for rigid motion).
``plasticity`` σ_y: multiplicative von Mises plasticity, F = F_e F_p; after each step the
Hencky strain of F_e is returned to the yield surface √(3/2)‖dev τ‖ ≤ σ_y with τ = 2μ ε + λ tr ε
(the uniaxial yield stress is σ_y); the plastic part is permanent.  ``ground_friction`` μ: after
each step the tangential velocity of every node in contact is reduced by μ × its normal impulse
per unit mass over the step (under the hard law: the normal velocity the projection removed), to zero at
most (Coulomb with sticking).  ``stiffness_region``
factor, box: E (hence μ and λ) of the elements whose centroid lies in the box multiplied by
the factor.

Everything is SI: metres, seconds, kilograms, pascals.  Z is up.

Checked against analytic answers in ``tests/test_independent_fem.py`` (free fall, a clamped
bar's axial period, linear-drag decay, Coulomb stopping distance, Kelvin–Voigt decay rate and
undamped rigid motion, the measurement file read back by :mod:`unipixie.core.measurement`).

Bad input (an unknown effect, shape or scenario, a missing or out-of-range parameter, a bad
material, non-increasing times) raises :class:`~unipixie.core.errors.UserError` naming it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from ...core.errors import SimulationDiverged, UserError
from .inputs import EFFECT_NAMES, EXTRA_EFFECT_NAMES, _check_material, _effect_params, _vector3

MEASUREMENT_FORMAT = "unipixie.measurement/1"
CONTACT_LAWS = ("penalty", "hard")
"""The ground's contact laws (:class:`FEMSettings`.contact_law); neither is the truth, so a referee reports both."""
RK4_STABILITY = 2.5
"""|λ Δt| below which classical RK4 is stable for eigenvalues λ in the closed left half-plane (≈ 2.78 on
the real axis, 2.83 on the imaginary axis)."""


# --------------------------------------------------------------------------------- meshes
@dataclass
class TetMesh:
    """A tetrahedral mesh.

    nodes: (n, 3) float64 rest positions, metres.  tets: (m, 4) int64, positively oriented.
    faces: (f, 3) int64 boundary triangles (outward), indices into ``nodes``.
    """

    nodes: np.ndarray
    tets: np.ndarray
    faces: np.ndarray

    @property
    def surface_nodes(self) -> np.ndarray:
        """(s,) int64 sorted indices of the boundary nodes (the tracked points)."""
        return np.unique(self.faces)

    def volumes(self) -> np.ndarray:
        """(m,) float64 signed volumes, m³ (positive for a valid mesh)."""
        x = self.nodes
        a, b, c, d = (x[self.tets[:, i]] for i in range(4))
        return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0


def _orient(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    x = nodes
    a, b, c, d = (x[tets[:, i]] for i in range(4))
    vol = np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a))
    tets = tets.copy()
    neg = vol < 0
    tets[neg, 2], tets[neg, 3] = tets[neg, 3].copy(), tets[neg, 2].copy()
    return tets


def boundary_faces(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(f, 3) outward boundary triangles of a positively oriented tetrahedral mesh (faces of one tet only)."""
    # the face opposite vertex i, ordered so that its normal points away from vertex i
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    out = faces[counts[inverse] == 1]
    # check the orientation against the opposite vertex (the local table is for positive tets)
    opp = tets[:, [0, 1, 2, 3]].reshape(-1)[counts[inverse] == 1]
    a, b, c = nodes[out[:, 0]], nodes[out[:, 1]], nodes[out[:, 2]]
    normal = np.cross(b - a, c - a)
    inward = np.einsum("ij,ij->i", normal, nodes[opp] - a) > 0
    out[inward] = out[inward][:, [0, 2, 1]]
    return out


def box_tet_mesh(extents: Sequence[float], centre: Sequence[float] = (0.0, 0.0, 0.0), spacing: float = 0.04,
                 mirrored: bool = True) -> TetMesh:
    """A structured tetrahedral mesh of an axis-aligned box (metres): a lattice of about ``spacing`` (m, one
    number or one per axis) cut into six tetrahedra per cell (Kuhn triangulation around one of the cell's
    diagonals).  Finer meshes of the same box: a smaller ``spacing``.

    mirrored: each cell's diagonal points away from the box's mid-planes (the split of a cell in the upper half
    of an axis is the mirror image of its partner's in the lower half), so the mesh has the box's three mirror
    symmetries wherever the cell count along an axis is even (an odd count leaves the middle layer unmirrored).
    With one diagonal direction everywhere (``False``) the mesh is not symmetric: its stiffness differs between
    a direction and its mirror image, and a cube dropped flat onto the ground starts to spin at its first
    impact, which the continuum cannot do."""
    ext = np.asarray(extents, dtype=np.float64)
    cells = np.maximum(np.round(ext / spacing).astype(int), 1)
    axes = [np.linspace(-e / 2, e / 2, c + 1) for e, c in zip(ext, cells)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    nodes = np.stack([X, Y, Z], axis=-1).reshape(-1, 3) + np.asarray(centre, dtype=np.float64)
    nx, ny, nz = cells + 1

    def idx(i, j, k):
        return (i * ny + j) * nz + k

    I, J, K = np.meshgrid(np.arange(cells[0]), np.arange(cells[1]), np.arange(cells[2]), indexing="ij")
    I, J, K = I.ravel(), J.ravel(), K.ravel()
    if mirrored:  # 1 where the cell lies in the upper half along the axis: its corners are taken mirrored
        flips = [(L >= (n + 1) // 2).astype(np.int64) for L, n in zip((I, J, K), cells)]
    else:
        flips = [np.zeros_like(I)] * 3
    corner = {(a, b, c): idx(I + (a ^ flips[0]), J + (b ^ flips[1]), K + (c ^ flips[2]))
              for a in (0, 1) for b in (0, 1) for c in (0, 1)}
    tets = []
    # the six monotone paths from corner (0,0,0) to (1,1,1) (in each cell's own, possibly mirrored, frame)
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        p = [0, 0, 0]
        verts = [corner[tuple(p)]]
        for axis in perm:
            p[axis] = 1
            verts.append(corner[tuple(p)])
        tets.append(np.stack(verts, axis=1))
    tets = _orient(nodes, np.concatenate(tets).astype(np.int64))
    return TetMesh(nodes, tets, boundary_faces(nodes, tets))


def surface_tet_mesh(surface, spacing: float) -> TetMesh:
    """A tetrahedral mesh of the inside of a closed ``trimesh.Trimesh``: Delaunay of its vertices and
    interior lattice points (at least ``0.4 × spacing`` inside), tetrahedra with the centroid inside and a
    volume above 1e-3 of a regular one kept.  Nodes that no kept tetrahedron uses are dropped."""
    from scipy.spatial import Delaunay

    lo, hi = surface.bounds
    axes = [np.arange(lo[i] + spacing / 2, hi[i], spacing) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    if len(grid):
        from trimesh.proximity import signed_distance

        depth = signed_distance(surface, grid)  # positive inside
        grid = grid[depth > 0.4 * spacing]
    pts = np.concatenate([np.asarray(surface.vertices, dtype=np.float64), grid])
    tets = Delaunay(pts).simplices.astype(np.int64)
    tets = _orient(pts, tets)
    cent = pts[tets].mean(1)
    inside = surface.contains(cent)
    vol = TetMesh(pts, tets, np.zeros((0, 3), np.int64)).volumes()
    keep = inside & (vol > 1e-3 * spacing ** 3 / (6 * math.sqrt(2)))
    tets = tets[keep]
    used = np.unique(tets)
    remap = -np.ones(len(pts), dtype=np.int64)
    remap[used] = np.arange(len(used))
    nodes = pts[used]
    tets = remap[tets]
    return TetMesh(nodes, tets, boundary_faces(nodes, tets))


# --------------------------------------------------------------------------------- small tensor helpers
def _cof(A: np.ndarray) -> np.ndarray:
    """(m, 3, 3) -> cofactor matrices det(A) A⁻ᵀ (columns a1×a2, a2×a0, a0×a1)."""
    a0, a1, a2 = A[:, :, 0], A[:, :, 1], A[:, :, 2]
    return np.stack([np.cross(a1, a2), np.cross(a2, a0), np.cross(a0, a1)], axis=2)


def _det(A: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", A[:, :, 0], np.cross(A[:, :, 1], A[:, :, 2]))


def polar_rotation(F: np.ndarray, iterations: int = 20, tol: float = 1e-12) -> np.ndarray:
    """(m, 3, 3) rotations R of the polar decompositions F = R S (scaled Newton iteration
    R ← ½(γR + R⁻ᵀ/γ); the SVD with reflection fix for elements with det F ≤ 0.05)."""
    R = F.copy()
    det = _det(F)
    bad = det <= 0.05
    for _ in range(iterations):
        C = _cof(R)
        d = _det(R)
        d = np.where(np.abs(d) < 1e-30, 1e-30, d)
        inv_t = C / d[:, None, None]
        g = np.sqrt(np.sqrt(np.einsum("mij,mij->m", inv_t, inv_t) / np.maximum(np.einsum("mij,mij->m", R, R), 1e-300)))
        new = 0.5 * (g[:, None, None] * R + inv_t / g[:, None, None])
        change = float(np.max(np.abs(new - R)[~bad])) if np.any(~bad) else 0.0
        R = new
        if change < tol:
            break
    if np.any(bad):
        U, _, Vt = np.linalg.svd(F[bad])
        s = np.sign(np.linalg.det(U @ Vt))
        U[:, :, 2] *= s[:, None]
        R[bad] = U @ Vt
    return R


# --------------------------------------------------------------------------------- the model
@dataclass
class FEMSettings:
    """Numerical settings.

    safety: fraction of the RK4 stability limit used as the step (accuracy of the slow modes).
    contact_law: the ground's law, one of :data:`CONTACT_LAWS`: ``"penalty"`` (a spring per node,
    m_a (k d − c v_z), never pulling) or ``"hard"`` (inelastic projection after each step: a node below
    the ground is put back on it and its downward velocity is zeroed).
    contact_damping_ratio: ζ of the penalty contact (1 = critically damped node contact, 0 = an
    undamped spring that returns what it stores).
    contact_stiffness: the penalty spring k per unit node mass as a multiple of ω_max² (the stiffest
    element's own rate); above 1 the contact, not the elements, sets the step.
    max_steps_per_frame: refuse a run that would need more steps per frame interval.
    """

    safety: float = 0.25
    contact_law: str = "penalty"
    contact_damping_ratio: float = 1.0
    contact_stiffness: float = 1.0
    max_steps_per_frame: int = 200_000

    def __post_init__(self):
        if self.contact_law not in CONTACT_LAWS:
            raise UserError(f"unknown contact law {self.contact_law!r}; the laws are {', '.join(CONTACT_LAWS)}")
        if not (0.0 < self.safety <= 1.0):
            raise UserError(f"safety must lie in (0, 1], got {self.safety}")
        if not (self.contact_damping_ratio >= 0.0 and self.contact_stiffness > 0.0):
            raise UserError("contact_damping_ratio must be 0 or more and contact_stiffness positive, got "
                            f"{self.contact_damping_ratio}, {self.contact_stiffness}")


class FEMModel:
    """A prepared FEM simulation of one solid in one scenario (see the module docstring).

    mesh: :class:`TetMesh`; material: {"E": Pa, "nu": -, "density": kg/m³}; scenario: the spec's
    scenario dict (gravity, ground, initial_velocity, initial_angular_velocity, pinned_box);
    effects: see :func:`_effect_params`.
    """

    def __init__(self, mesh: TetMesh, material: dict, scenario: dict, effects=(), settings: Optional[FEMSettings] = None):
        from scipy import sparse

        self.mesh = mesh
        self.settings = settings or FEMSettings()
        self.effects = _effect_params(effects)
        X = np.asarray(mesh.nodes, dtype=np.float64)
        T = np.asarray(mesh.tets, dtype=np.int64)
        self.X, self.T = X, T
        n, m = len(X), len(T)
        Dm = np.stack([X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]], X[T[:, 3]] - X[T[:, 0]]], axis=2)
        self.V0 = _det(Dm) / 6.0
        if m == 0 or np.any(~(self.V0 > 0)):
            raise UserError("the tetrahedral mesh is empty or has inverted or degenerate elements")
        self.Bm = _cof(Dm).transpose(0, 2, 1) / (6.0 * self.V0)[:, None, None]  # Dm⁻¹
        E, nu, rho = _check_material(material)
        E_el = np.full(m, E)
        region = self.effects.get("stiffness_region")
        if region is not None:
            if "region" not in region:
                raise UserError("effect 'stiffness_region': FEMModel needs 'region' {'box': ...} in metres "
                                "('rel_box' is turned into one by Case.effect_dicts)")
            box = np.asarray(region["region"]["box"], dtype=np.float64).reshape(2, 3)
            cent = X[T].mean(1)
            inside = np.all((cent >= box[0]) & (cent <= box[1]), axis=1)
            E_el[inside] *= float(region["factor"])
        self.mu = E_el / (2 * (1 + nu))
        self.lam = E_el * nu / ((1 + nu) * (1 - 2 * nu))
        self.mass = np.bincount(T.reshape(-1), np.repeat(rho * self.V0 / 4.0, 4), n)
        # node-from-element scatter: f = G @ H where H stacks the 4 per-element node forces
        rows = T.T.reshape(-1)  # order: all corner-0 entries, then corner-1, ...
        cols = np.arange(4 * m)
        self.G = sparse.csr_matrix((np.ones(4 * m), (rows, cols)), shape=(n, 4 * m))
        # scenario
        self.gravity = _vector3(scenario.get("gravity", [0.0, 0.0, -9.81]), "gravity")
        ground = scenario.get("ground", {"height": 0.0})
        if ground is not None and not (isinstance(ground, dict) and "height" in ground
                                       and math.isfinite(float(ground["height"]))):
            raise UserError(f"scenario key 'ground' must be null or {{'height': metres}}, got {ground!r}")
        self.ground = None if ground is None else float(ground["height"])
        pinned = np.zeros(n, dtype=bool)
        box = scenario.get("pinned_box")
        if box is not None:
            try:
                box = np.asarray(box, dtype=np.float64).reshape(2, 3)
            except (TypeError, ValueError):
                raise UserError(f"scenario key 'pinned_box' must be [[xmin,ymin,zmin],[xmax,ymax,zmax]], got {box!r}") from None
            pinned = np.all((X >= box[0]) & (X <= box[1]), axis=1)
        self.pinned = pinned
        self.free = (~pinned).astype(np.float64)[:, None]
        com = (self.mass[:, None] * X).sum(0) / self.mass.sum()
        v0 = _vector3(scenario.get("initial_velocity", [0, 0, 0]), "initial_velocity")
        w0 = _vector3(scenario.get("initial_angular_velocity", [0, 0, 0]), "initial_angular_velocity")
        self.v0 = (v0[None] + np.cross(w0[None], X - com)) * self.free
        # effects
        eff = self.effects
        self.c_lin = float(eff.get("linear_drag", {}).get("c", 0.0))
        self.k_quad = float(eff.get("quadratic_drag", {}).get("k", 0.0))
        self.eta = float(eff.get("material_damping", {}).get("eta", 0.0))
        self.mu_f = float(eff.get("ground_friction", {}).get("mu", 0.0))
        self.yield_stress = float(eff.get("plasticity", {}).get("yield_stress", math.inf))
        self.accel = self.gravity + np.asarray(eff.get("wind", {}).get("acceleration", [0.0, 0.0, 0.0]), dtype=np.float64)
        self.Fp_inv = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
        self.plastic = math.isfinite(self.yield_stress)
        # stability: largest eigenvalues of M⁻¹K and M⁻¹C at rest
        self.omega_max = self._largest_rate(elastic=True)
        self.gamma_max = self._largest_rate(elastic=False) if self.eta > 0 else 0.0
        floor = eff.get("contact_damping")
        self.floor = None if floor is None or self.ground is None else (float(floor["k"]), float(floor["c"]))
        self.floor_area = self._footprint() if self.floor is not None else None
        self.hard_contact = self.settings.contact_law == "hard" and self.floor is None
        self.k_contact = self.settings.contact_stiffness * self.omega_max ** 2
        self.c_contact = 2.0 * self.settings.contact_damping_ratio * math.sqrt(self.k_contact)
        # a node on the ground feels the stiffest element and the contact spring (ω² each) and the contact damper
        penalty = self.ground is not None and not self.hard_contact
        if self.floor is not None:  # the floor's spring and damper per unit node mass
            k_floor = float(np.max(self.floor[0] * self.floor_area / self.mass))
            rate = math.sqrt(self.omega_max ** 2 + k_floor) + self.gamma_max + float(
                np.max(self.floor[1] * self.floor_area / self.mass))
        else:
            rate = (math.sqrt(self.omega_max ** 2 + self.k_contact) if penalty else self.omega_max) + self.gamma_max
        rate = max(rate, 1e-9)
        self.dt_max = self.settings.safety * RK4_STABILITY / rate

    # ---------------------------------------------------------------- forces
    def internal_forces(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(n, 3) N: elastic (+ viscous) nodal forces at positions x (n, 3) m and velocities v (n, 3) m/s."""
        T = self.T
        x0 = x[T[:, 0]]
        Ds = np.stack([x[T[:, 1]] - x0, x[T[:, 2]] - x0, x[T[:, 3]] - x0], axis=2)
        F = Ds @ self.Bm
        Fe = F @ self.Fp_inv if self.plastic else F
        R = polar_rotation(Fe)
        J = _det(Fe)
        P = 2.0 * self.mu[:, None, None] * (Fe - R) + (self.lam * (J - 1.0))[:, None, None] * _cof(Fe)
        if self.plastic:
            P = P @ self.Fp_inv.transpose(0, 2, 1)
        if self.eta > 0:
            v0 = v[T[:, 0]]
            Dv = np.stack([v[T[:, 1]] - v0, v[T[:, 2]] - v0, v[T[:, 3]] - v0], axis=2)
            Fdot = Dv @ self.Bm
            cofF = _cof(F)
            detF = _det(F)
            L = Fdot @ (cofF.transpose(0, 2, 1) / detF[:, None, None])  # ∇v = Ḟ F⁻¹
            D = 0.5 * (L + L.transpose(0, 2, 1))
            P = P + 2.0 * self.eta * D @ cofF  # J σ F⁻ᵀ with σ = 2η D
        H = -self.V0[:, None, None] * (P @ self.Bm.transpose(0, 2, 1))  # columns: forces on corners 1, 2, 3
        f123 = H.transpose(0, 2, 1)  # (m, 3 corners, 3)
        f0 = -f123.sum(1)
        stacked = np.concatenate([f0[None], f123.transpose(1, 0, 2)], axis=0).reshape(-1, 3)
        return self.G @ stacked

    def _footprint(self) -> np.ndarray:
        """(n,) m²: the area of the ground each node stands for — every downward-facing boundary triangle's area
        projected on the horizontal plane, a third to each of its corners (at rest; a node inside has none)."""
        faces = boundary_faces(self.X, self.T)
        a, b, c = (self.X[faces[:, i]] for i in range(3))
        down = np.maximum(-0.5 * np.cross(b - a, c - a)[:, 2], 0.0)  # outward normals: n_z < 0 faces the ground
        return np.bincount(faces.reshape(-1), np.repeat(down / 3.0, 3), len(self.X))

    def contact_forces(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(n, 3) N: the ground's normal force, never pulling.  With ``contact_damping`` the floor's traction
        k d − c v_z times each node's footprint (:meth:`_footprint`); else the penalty law's force (zero under
        the hard law)."""
        f = np.zeros_like(x)
        if self.ground is None or self.hard_contact:
            return f
        depth = self.ground - x[:, 2]
        on = depth > 0
        if np.any(on):
            if self.floor is not None:
                fn = self.floor_area[on] * (self.floor[0] * depth[on] - self.floor[1] * v[on, 2])
            else:
                fn = self.mass[on] * (self.k_contact * depth[on] - self.c_contact * v[on, 2])
            f[on, 2] = np.maximum(fn, 0.0)
        return f

    def acceleration(self, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(a (n, 3) m/s², contact force (n, 3) N) at state (x, v)."""
        fc = self.contact_forces(x, v)
        a = (self.internal_forces(x, v) + fc) / self.mass[:, None] + self.accel[None]
        if self.c_lin > 0:
            a -= self.c_lin * v
        if self.k_quad > 0:
            a -= self.k_quad * np.linalg.norm(v, axis=1, keepdims=True) * v
        return a * self.free, fc

    def _largest_rate(self, elastic: bool, iterations: int = 40) -> float:
        """sqrt(largest eigenvalue of M⁻¹K) (elastic) or the largest eigenvalue of M⁻¹C (viscous), at rest."""
        rng = np.random.default_rng(0)
        n = len(self.X)
        u = rng.normal(size=(n, 3)) * self.free
        eps = 1e-6 * float(np.max(np.ptp(self.X, axis=0)))
        lam = 0.0
        zero = np.zeros((n, 3))
        f_rest = self.internal_forces(self.X, zero)
        saved = self.eta
        if elastic:
            self.eta = 0.0
        for _ in range(iterations):
            nrm = float(np.sqrt(np.sum(self.mass[:, None] * u * u)))
            if nrm == 0:
                break
            u = u / nrm
            if elastic:
                Ku = -(self.internal_forces(self.X + eps * u, zero) - f_rest) / eps
            else:
                Ku = -(self.internal_forces(self.X, eps * u) - f_rest) / eps
            w = Ku / self.mass[:, None] * self.free
            lam = float(np.sum(self.mass[:, None] * u * w))
            u = w
        self.eta = saved
        lam = abs(lam) * 1.05  # power iteration approaches from below
        return math.sqrt(lam) if elastic else lam

    # ---------------------------------------------------------------- stepping
    def _plastic_return(self, x: np.ndarray) -> None:
        """Return F_e = F F_p⁻¹ to the von Mises surface √(3/2)‖dev τ‖ ≤ σ_y (Hencky strain) where it is outside."""
        T = self.T
        x0 = x[T[:, 0]]
        F = np.stack([x[T[:, 1]] - x0, x[T[:, 2]] - x0, x[T[:, 3]] - x0], axis=2) @ self.Bm
        Fe = F @ self.Fp_inv
        # cheap screen on the symmetric stretch: elements far inside the surface are skipped
        R = polar_rotation(Fe)
        S = R.transpose(0, 2, 1) @ Fe
        e = 0.5 * (S + S.transpose(0, 2, 1)) - np.eye(3)[None]
        dev = e - (np.trace(e, axis1=1, axis2=2) / 3.0)[:, None, None] * np.eye(3)[None]
        q_est = math.sqrt(1.5) * 2.0 * self.mu * np.sqrt(np.einsum("mij,mij->m", dev, dev))
        cand = np.nonzero(q_est > 0.8 * self.yield_stress)[0]
        if len(cand) == 0:
            return
        U, sig, Vt = np.linalg.svd(Fe[cand])
        eps = np.log(np.maximum(sig, 1e-6))
        mean = eps.mean(1, keepdims=True)
        edev = eps - mean
        q = math.sqrt(1.5) * 2.0 * self.mu[cand] * np.linalg.norm(edev, axis=1)
        over = q > self.yield_stress
        if not np.any(over):
            return
        idx = cand[over]
        scale = self.yield_stress / q[over]
        eps_new = mean[over] + edev[over] * scale[:, None]
        Fe_new = (U[over] * np.exp(eps_new)[:, None, :]) @ Vt[over]
        Finv = _cof(F[idx]).transpose(0, 2, 1) / _det(F[idx])[:, None, None]
        self.Fp_inv[idx] = Finv @ Fe_new

    def _friction(self, v: np.ndarray, normal_impulse: np.ndarray) -> np.ndarray:
        """Coulomb: tangential velocity reduced by μ × normal impulse per unit mass (sticking at zero)."""
        jn = normal_impulse / self.mass
        on = jn > 0
        if not np.any(on):
            return v
        vt = v[on, :2]
        speed = np.linalg.norm(vt, axis=1)
        factor = np.where(speed > 0, np.maximum(0.0, 1.0 - self.mu_f * jn[on] / np.maximum(speed, 1e-300)), 0.0)
        v = v.copy()
        v[on, :2] = vt * factor[:, None]
        return v

    def step(self, x: np.ndarray, v: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """One RK4 step of (x, v) by dt seconds, then plastic return and friction."""
        a1, c1 = self.acceleration(x, v)
        x2, v2 = x + 0.5 * dt * v, v + 0.5 * dt * a1
        a2, c2 = self.acceleration(x2, v2)
        x3, v3 = x + 0.5 * dt * v2, v + 0.5 * dt * a2
        a3, c3 = self.acceleration(x3, v3)
        x4, v4 = x + dt * v3, v + dt * a3
        a4, c4 = self.acceleration(x4, v4)
        xn = x + dt / 6.0 * (v + 2 * v2 + 2 * v3 + v4)
        vn = v + dt / 6.0 * (a1 + 2 * a2 + 2 * a3 + a4)
        if self.ground is not None and self.hard_contact:
            below = xn[:, 2] < self.ground
            if np.any(below):
                xn = xn.copy()
                vn = vn.copy()
                xn[below, 2] = self.ground
                dv = np.maximum(-vn[below, 2], 0.0)  # the downward normal velocity the ground takes away
                vn[below, 2] += dv
                if self.mu_f > 0:
                    impulse = np.zeros(len(xn))
                    impulse[below] = self.mass[below] * dv
                    vn = self._friction(vn, impulse)
        elif self.mu_f > 0 and self.ground is not None:
            impulse = dt / 6.0 * (c1[:, 2] + 2 * c2[:, 2] + 2 * c3[:, 2] + c4[:, 2])
            vn = self._friction(vn, impulse)
        if self.plastic:
            self._plastic_return(xn)
        return xn, vn * self.free

    def run(self, times: Sequence[float], nodes: Optional[np.ndarray] = None, progress=None) -> np.ndarray:
        """(T, k, 3) positions of ``nodes`` (default: all) at ``times`` (s, from the initial state at times[0])."""
        times = np.asarray(times, dtype=np.float64)
        if times.ndim != 1 or len(times) < 1 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
            raise UserError("times must be a non-empty 1-D array of finite, strictly increasing seconds")
        x, v = self.X.copy(), self.v0.copy()
        self.Fp_inv = np.broadcast_to(np.eye(3), (len(self.T), 3, 3)).copy()
        sel = np.arange(len(x)) if nodes is None else np.asarray(nodes)
        out = np.zeros((len(times), len(sel), 3))
        out[0] = x[sel]
        self.steps_taken = 0
        for f in range(1, len(times)):
            interval = times[f] - times[f - 1]
            n = max(1, math.ceil(interval / self.dt_max - 1e-9))
            if n > self.settings.max_steps_per_frame:
                raise UserError(f"{n} FEM steps per frame interval needed (limit "
                                f"{self.settings.max_steps_per_frame}): use a coarser mesh, a softer material or "
                                "more frames")
            dt = interval / n
            for _ in range(n):
                x, v = self.step(x, v, dt)
            self.steps_taken += n
            if not np.all(np.isfinite(x)):
                raise SimulationDiverged(f"the FEM simulation diverged at t = {times[f]:.4g} s (frame {f}); "
                                         "lower FEMSettings.safety")
            out[f] = x[sel]
            if progress is not None:
                progress(f, len(times) - 1)
        self.final_state = (x, v)
        return out

    # ---------------------------------------------------------------- diagnostics
    def energy(self, x: np.ndarray, v: np.ndarray) -> dict:
        """Kinetic, elastic and gravitational energy (J) of a state (elastic with F_p = I)."""
        T = self.T
        x0 = x[T[:, 0]]
        F = np.stack([x[T[:, 1]] - x0, x[T[:, 2]] - x0, x[T[:, 3]] - x0], axis=2) @ self.Bm
        R = polar_rotation(F)
        J = _det(F)
        psi = self.mu * np.einsum("mij,mij->m", F - R, F - R) + 0.5 * self.lam * (J - 1.0) ** 2
        kin = 0.5 * float(np.sum(self.mass[:, None] * v * v))
        ela = float(np.sum(self.V0 * psi))
        pot = -float(np.sum(self.mass * (x @ self.accel)))
        return {"kinetic": kin, "elastic": ela, "potential": pot, "total": kin + ela + pot}


# --------------------------------------------------------------------------------- measurements
def occlusions(frames: int, points: int, fraction: float, rng: np.random.Generator, run_frames: float = 6.0,
               lost_points: float = 0.02) -> np.ndarray:
    """(T, N) bool, True where a sample is hidden: a few points lost for the whole record (``lost_points``
    of them) and runs of consecutive frames (exponential lengths, mean ``run_frames``) elsewhere, until
    about ``fraction`` of all samples are hidden.  The first instant is always fully observed."""
    hidden = np.zeros((frames, points), dtype=bool)
    lost = rng.choice(points, size=int(round(lost_points * points)), replace=False)
    hidden[1:, lost] = True
    target = fraction * frames * points
    while hidden.sum() < target:
        p = int(rng.integers(points))
        length = max(1, int(rng.exponential(run_frames)))
        start = int(rng.integers(1, max(frames - 1, 2)))
        hidden[start:start + length, p] = True
    hidden[0] = False
    return hidden


def measurement_arrays(positions: np.ndarray, times: np.ndarray, rest: np.ndarray, faces: np.ndarray,
                       scenario: dict, material: dict, noise: float, occlusion: float, seed: int,
                       truth: Optional[dict] = None) -> dict:
    """The arrays of a ``unipixie.measurement/1`` archive (``numpy.savez``): clean ``positions`` (T, N, 3) m
    get white noise σ = ``noise`` m per coordinate and ``occlusion`` of the samples hidden (NaN).  The
    scenario states ``material`` (what the model believes).  ``truth`` is stored as JSON under
    ``independent_truth`` (never read by the diagnosis)."""
    if not (math.isfinite(noise) and noise >= 0):
        raise UserError(f"noise must be a standard deviation of 0 m or more, got {noise}")
    if not (0.0 <= occlusion <= 0.9):
        raise UserError(f"occlusion must be a fraction of the samples in [0, 0.9], got {occlusion}")
    rng = np.random.default_rng(seed)
    pos = np.asarray(positions, dtype=np.float64) + rng.normal(scale=noise, size=np.shape(positions))
    if occlusion > 0:
        pos[occlusions(pos.shape[0], pos.shape[1], occlusion, rng)] = np.nan
    sc = {"format": MEASUREMENT_FORMAT, **{k: v for k, v in scenario.items() if k != "format"}}
    sc["material"] = {k: float(material[k]) for k in ("E", "nu", "density")}
    arrays = {"positions": pos, "times": np.asarray(times, dtype=np.float64),
              "rest_positions": np.asarray(rest, dtype=np.float64), "faces": np.asarray(faces, dtype=np.int64),
              "scenario": np.array(json.dumps(sc))}
    if truth is not None:
        arrays["independent_truth"] = np.array(json.dumps(truth))
    return arrays


@dataclass
class Case:
    """A validation measurement: shape, scenario, hidden effects and how it is observed.

    shape: ``"cube"`` (0.2 m), ``"bar"`` (0.4 × 0.08 × 0.08 m), ``"plate"`` (0.3 × 0.3 × 0.05 m) or
    ``"sphere"`` (radius 0.1 m).  scenario: ``"drop"`` (from ``height`` above the ground with
    ``velocity`` and ``spin``), ``"throw"`` (no ground), ``"slide"`` (on the ground at ``velocity``),
    ``"clamped"`` (low-x 15 % held, no ground, struck with ``velocity``).
    spacing: the mesh's cell size (m); the default 0.025 m puts 8 cells across the cube (an even count, so the
    mirrored mesh keeps the cube's symmetries: :func:`box_tet_mesh`).
    effects: spec effect strings / dicts.  stated_E_scale: the file states E / this (the model believes a
    material that is off by this factor).  contact_law / contact_damping_ratio: the ground's law and the penalty
    law's ζ (:class:`FEMSettings`; the defaults are its defaults).
    """

    name: str
    shape: str = "cube"
    scenario: str = "throw"
    effects: list = field(default_factory=list)
    E: float = 2.0e5
    nu: float = 0.3
    density: float = 1000.0
    stated_E_scale: float = 1.0
    duration: float = 0.8
    fps: float = 50.0
    noise: float = 0.001
    occlusion: float = 0.1
    spacing: float = 0.025
    velocity: Optional[Sequence[float]] = None
    spin: Optional[Sequence[float]] = None
    height: float = 0.1
    seed: int = 0
    contact_law: str = "penalty"
    contact_damping_ratio: float = 1.0

    def fem_settings(self) -> FEMSettings:
        """The referee's settings for this case (its contact law; the rest at their defaults)."""
        return FEMSettings(contact_law=self.contact_law, contact_damping_ratio=self.contact_damping_ratio)

    def mesh(self) -> TetMesh:
        ext = {"cube": (0.2, 0.2, 0.2), "bar": (0.4, 0.08, 0.08), "plate": (0.3, 0.3, 0.05)}
        if self.shape in ext:
            return box_tet_mesh(ext[self.shape], spacing=self.spacing)
        if self.shape == "sphere":
            import trimesh

            return surface_tet_mesh(trimesh.creation.icosphere(subdivisions=2, radius=0.1), self.spacing)
        raise UserError(f"unknown shape {self.shape!r}; the shapes are cube, bar, plate, sphere")

    def placed(self) -> tuple[TetMesh, dict]:
        """The mesh moved into place and the scenario dict."""
        mesh = self.mesh()
        X = mesh.nodes
        lo, hi = X.min(0), X.max(0)
        ext = hi - lo
        spin = [0.0, 0.0, 0.0] if self.spin is None else list(map(float, self.spin))
        if self.scenario == "drop":
            shift = -(lo + hi) / 2 + np.array([0.0, 0.0, ext[2] / 2 + self.height])
            sc = {"ground": {"height": 0.0}, "initial_velocity": list(self.velocity or (0.5, 0.0, 0.0))}
        elif self.scenario == "throw":
            shift = -(lo + hi) / 2 + np.array([0.0, 0.0, 1.0])
            sc = {"ground": None, "initial_velocity": list(self.velocity or (1.5, 0.0, 2.5))}
        elif self.scenario == "slide":
            shift = -(lo + hi) / 2 + np.array([0.0, 0.0, ext[2] / 2])
            sc = {"ground": {"height": 0.0}, "initial_velocity": list(self.velocity or (1.5, 0.0, 0.0))}
        elif self.scenario == "clamped":
            shift = -lo + np.array([0.0, -ext[1] / 2, 0.5 - ext[2] / 2])
            sc = {"ground": None, "initial_velocity": list(self.velocity or (0.0, 0.0, 0.0))}
        else:
            raise UserError(f"unknown scenario {self.scenario!r}; the scenarios are drop, throw, slide, clamped")
        nodes = X + shift
        if self.scenario == "clamped":
            lo2, hi2 = nodes.min(0), nodes.max(0)
            sc["pinned_box"] = [(lo2 - 0.01).tolist(), [lo2[0] + 0.15 * ext[0] + 1e-9, hi2[1] + 0.01, hi2[2] + 0.01]]
        sc.update({"format": MEASUREMENT_FORMAT, "gravity": [0.0, 0.0, -9.81], "initial_angular_velocity": spin,
                   "notes": f"independent FEM validation case {self.name}"})
        return TetMesh(nodes, mesh.tets, mesh.faces), sc

    def effect_dicts(self, mesh_nodes: np.ndarray) -> list:
        """The hidden effects as spec dicts; a ``stiffness_region`` box given relative to the solid
        (``rel_box`` in [0, 1]³ of its bounds) is turned into metres."""
        out = []
        lo, hi = mesh_nodes.min(0), mesh_nodes.max(0)
        for e in _effect_params(self.effects).items():
            name, params = e
            params = dict(params)
            if name == "stiffness_region" and "rel_box" in params:
                rb = np.asarray(params.pop("rel_box"), float).reshape(2, 3)
                pad = 1e-6
                params["region"] = {"box": (lo + rb * (hi - lo) + np.array([[-pad], [pad]])).tolist()}
            out.append({"effect": name, "params": params})
        return out


def make_case(case: Case, settings: Optional[FEMSettings] = None) -> dict:
    """Simulate ``case`` and return its measurement arrays (see :func:`measurement_arrays`), the truth
    under ``independent_truth`` (effects, true E, the simulator, its step and wall time)."""
    import time

    if not (case.duration > 0 and case.fps > 0 and case.duration * case.fps >= 1):
        raise UserError(f"case {case.name!r}: duration ({case.duration} s) and fps ({case.fps}) must give at least one "
                        "frame interval")
    if not (case.spacing > 0 and case.stated_E_scale > 0):
        raise UserError(f"case {case.name!r}: spacing and stated_E_scale must be positive")
    mesh, sc = case.placed()
    effects = case.effect_dicts(mesh.nodes)
    truth_material = {"E": case.E, "nu": case.nu, "density": case.density}
    model = FEMModel(mesh, truth_material, sc, effects, settings or case.fem_settings())
    times = np.arange(int(round(case.duration * case.fps)) + 1) / case.fps
    surf = mesh.surface_nodes
    remap = -np.ones(len(mesh.nodes), dtype=np.int64)
    remap[surf] = np.arange(len(surf))
    t0 = time.perf_counter()
    clean = model.run(times, surf)
    wall = time.perf_counter() - t0
    stated = dict(truth_material, E=case.E / case.stated_E_scale)
    law = model.settings.contact_law
    truth = {"simulator": f"unipixie.training.independent_fem (linear tets, fixed-corotated, RK4, {law} ground)",
             "case": case.name, "contact_law": law,
             "contact_damping_ratio": float(model.settings.contact_damping_ratio), "effects": effects, "true_E": case.E, "stated_E": stated["E"],
             "true_E_over_stated": case.stated_E_scale, "noise_sigma": case.noise, "occlusion": case.occlusion,
             "nodes": int(len(mesh.nodes)), "tets": int(len(mesh.tets)), "dt": float(model.dt_max),
             "steps": int(model.steps_taken), "wall_s": wall}
    return measurement_arrays(clean, times, mesh.nodes[surf], remap[mesh.faces], sc, stated, case.noise,
                              case.occlusion, case.seed, truth)
