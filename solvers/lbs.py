"""Reduced-order LBS solver (Simplicits / Vid2Sim style): Warp per-point physics, torch reduction.

**Kinematics.**  A point X of the solid (metres) moves as::

    x(X) = X + Σ_{h=0..H} w_h(X) Z_h [X̂; 1]

with X̂ = (X − centre)/extent the point in the normalised cube of the body's rest bounding
box, w_0..w_{H−1} the skinning network's weights (:mod:`.skinning`; the object's 650
parameters — given by the model or fitted by :func:`.lbs_fit.fit_skinning`) and w_H = 1
the constant handle.  The state is the (H+1) affine handle transforms Z_h ∈ R^{3×4}
(132 numbers for H = 10); the deformation gradient is linear in them.

**Samples.**  The solid is filled with ``mass_samples`` points (masses, gravity, drags,
clamp), thinned by farthest-point sampling to ``cubature_points`` cubature points (default
500) carrying the elastic energy: each has the volume of the fill points nearest to it and
its cell's mean E, ν (and class).  ``collision_points`` surface samples (FPS of mesh
vertices and surface samples; for a point body, FPS of its points, which touch the ground half
a point spacing below their centres) touch the ground.

**Time step.**  Backward Euler, solved by Newton's method with a backtracking (Armijo)
line search, at most ``newton_iterations`` iterations per step, on the incremental
potential::

    Φ(Z) = 1/(2dt²) ‖Z − Z_n − dt Ż_n‖²_M + Σ_c V_c Ψ(F_c(Z)) − f_ext·Z
           + ground penalty + clamp penalty + effect terms

Ψ is fixed-corotated (:mod:`.lbs_kernels`, with its analytic PSD-projected Hessian).  The
per-cubature-point energy, stress and 9×9 Hessian come from one Warp kernel; the reduction
to the 132×132 system Σ_c Gᵀ H_c G is a dense contraction done by torch on the same
device (a batched GEMM: what BLAS / cuBLAS do best), as are the small Cholesky solve and
the 44-dimensional mass-matrix terms.  All environments of :meth:`run_batch` step together.

**Contact and clamp.**  The ground is a penalty ½ κ_c (h − z_p)₊² on the collision points
with κ_c = ``contact_stiffness`` × (mass per collision point)/dt² (at rest the penetration is
about g dt² × (collision points / points in contact) / contact_stiffness); the clamp
(``pinned_box``, stationary class) is a penalty ½ κ_p m_p |x_p − X_p|² on the fill points
inside it, an elastic foundation with κ_p = ``clamp_stiffness`` × max(E/ρ)/ℓ² (ℓ the
cubature spacing), i.e. as stiff as the stiffest elastic mode the cubature resolves.  A far
stiffer penalty *locks*: the handles' weights are smooth global functions, and forcing the
displacement to vanish pointwise on a whole region forbids most of them.  Measured tip sag /
Euler–Bernoulli of a clamped cantilever (0.5 × 0.05 × 0.05 m, 3 cm clamp, 500 cubature
points, 10 handles) for clamp_stiffness 0.3 / 1 / 3 / 10 / 100: 1.13 / 1.00 / 0.95 / 0.91 /
0.79; for a stubbier one (0.24 × 0.04 m, 4 cm clamp) 1 / 3: 0.98 / 0.89 (16 handles at 3:
0.96).  1 is the default.

**Effects** (what each means in this reduced model):

* ``linear_drag`` c: Rayleigh damping (c/2dt)‖Z − Z_n‖²_M, i.e. force −c m v on every bit of mass.
* ``quadratic_drag`` k: the same with the per-sample coefficient k |v_p| taken at the start of
  the step (lagged): force −k m |v| v.
* ``wind``: extra uniform acceleration in f_ext.
* ``material_damping`` η: Kelvin–Voigt incremental potential (η/dt) ‖sym((F − F_n) F_n⁻¹)‖²
  per volume at the cubature points (viscous stress 2η sym(∇v); rigid motion is free).
* ``ground_friction`` μ: lagged-normal-force Coulomb friction at the collision points in
  contact, μ N_p f0(|Δx_t|) with IPC's C¹ smoothing f0 below a slip of
  ``friction_velocity`` × dt (sticking below it).
* ``plasticity`` σ_y: von Mises return mapping on the Hencky strain of each cubature point
  after each step; the plastic part is stored as a per-point rest-shape change F_p, so the
  energy's minimum moves: permanent deformation, restricted to what the handles can show.
  Classes with von Mises plasticity (metal, plasticine) use their class yield stress.
* ``stiffness_region`` factor: multiplies μ and λ of the cubature points in the region.

**Output.**  Tracked points / vertices: x = X + Z a(X) with a(X) = w(X) ⊗ [X̂; 1],
precomputed once (any number of points: one GEMM per frame).  ``handle_transforms``
(T, H+1, 3, 4) are world-space: the first H are displacement transforms D_h and the last
(the constant handle) is the full affine A = [I | 0] + D_H, so that
x = A [X; 1] + Σ_{h<H} w_h(X) D_h [X; 1]; weights come from :func:`skinning.skinning_weights`
on :func:`skinning.normalise_points` (X, ``meta["skinning_bounds"]``) with
``meta["skinning_params"]``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields
from typing import Optional

import numpy as np

from ..core.errors import SimulationDiverged, UserError
from ..core.progress import Progress
from ..core.types import Trajectory
from . import materials as materials_mod
from . import skinning
from .api import Simulation
from .body import Body
from .effects import PhysicsTerms
from .lbs_fit import DEFAULT_FIT_ITERATIONS, fit_skinning, torch_threads
from .material_sampling import MaterialSpec, PointMaterial, sample_material
from .sampling import farthest_point_sampling
from .scenario import Scenario
from .spring_mass import fill_solid

DEFAULT_CUBATURE_POINTS = 500
DEFAULT_MASS_SAMPLES = 4000
DEFAULT_COLLISION_POINTS = 256
DEFAULT_MAX_DT = 5.0e-3
"""Largest step (s); a frame interval is split into equal steps no longer than this."""
DEFAULT_NEWTON_ITERATIONS = 4


@dataclass
class LBSSettings:
    """Set-up and stepping options of the LBS solver.

    handles: H learned handles (the constant handle is extra).
    cubature_points / mass_samples / collision_points: sample counts (module docstring).
    skinning_params: ``None`` (fit with :func:`.lbs_fit.fit_skinning`, cached on disk) or the
        (H·64 + H,) parameters — what the model's HyperNetwork predicts.
    fit_iterations: Simplicits refinement steps when fitting.
    max_dt: largest time step, s.
    newton_iterations: at most this many Newton iterations per step.
    newton_tolerance: stop when the next Newton update (mass-weighted RMS) would be below this × the body size.
    line_search_steps: step halvings before giving up on an iteration.
    reuse_hessian: factor the Hessian once per step and reuse it for the step's later Newton
        iterations (each still has a line search on the true energy).
    contact_stiffness / clamp_stiffness: dimensionless penalty factors (module docstring).
    friction_velocity: m/s, slip speed below which ground friction sticks.
    cache_skinning: reuse fitted parameters from the cache directory.
    torch_threads: torch intra-op threads on the CPU while stepping (0 = leave torch's setting).
    """

    handles: int = skinning.DEFAULT_HANDLES
    cubature_points: int = DEFAULT_CUBATURE_POINTS
    mass_samples: int = DEFAULT_MASS_SAMPLES
    collision_points: int = DEFAULT_COLLISION_POINTS
    skinning_params: Optional[np.ndarray] = None
    fit_iterations: int = DEFAULT_FIT_ITERATIONS
    max_dt: float = DEFAULT_MAX_DT
    newton_iterations: int = DEFAULT_NEWTON_ITERATIONS
    newton_tolerance: float = 1e-6
    line_search_steps: int = 10
    reuse_hessian: bool = True
    contact_stiffness: float = 30.0
    clamp_stiffness: float = 1.0
    friction_velocity: float = 1e-3
    cache_skinning: bool = True
    torch_threads: int = 1

    def __post_init__(self):
        for name in ("handles", "cubature_points", "mass_samples", "collision_points", "newton_iterations",
                     "line_search_steps"):
            val = getattr(self, name)
            if not isinstance(val, (int, np.integer)) or val < 1:
                raise UserError(f"LBS setting '{name}' must be a positive whole number, got {val!r}")
            setattr(self, name, int(val))
        if not isinstance(self.fit_iterations, (int, np.integer)) or self.fit_iterations < 0:
            raise UserError(f"LBS setting 'fit_iterations' must be a whole number >= 0, got {self.fit_iterations!r}")
        for name in ("max_dt", "newton_tolerance", "contact_stiffness", "clamp_stiffness", "friction_velocity"):
            val = getattr(self, name)
            try:
                ok = math.isfinite(float(val)) and float(val) > 0
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise UserError(f"LBS setting '{name}' must be a positive number, got {val!r}")
            setattr(self, name, float(val))
        if self.skinning_params is not None:
            p = np.asarray(self.skinning_params, dtype=np.float64).reshape(-1)
            expected = skinning.param_count(self.handles)
            if p.size != expected:
                raise UserError(f"skinning parameters must have {expected} numbers for {self.handles} handles "
                                f"(H·64 + H), got {p.size}")
            if not np.all(np.isfinite(p)):
                raise UserError("skinning parameters contain NaN/inf")
            self.skinning_params = p

    @classmethod
    def coerce(cls, settings) -> "LBSSettings":
        if settings is None:
            return cls()
        if isinstance(settings, cls):
            return settings
        if isinstance(settings, dict):
            known = {f.name for f in fields(cls)}
            unknown = set(settings) - known
            if unknown:
                raise UserError(f"unknown LBS setting(s) {sorted(unknown)}; known: {sorted(known)}")
            return cls(**settings)
        raise UserError(f"LBS settings must be an LBSSettings or a dict, got {type(settings).__name__}")


def _torch_device(device: str) -> str:
    return "cpu" if device == "cpu" else device


def lift_basis(weights: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """a(X) = w ⊗ [x̂; 1]: (N, H+1) weights and (N, 3) normalised points -> (N, 4(H+1))."""
    xh1 = np.concatenate([x_hat, np.ones((len(x_hat), 1))], axis=1)
    return (weights[:, :, None] * xh1[:, None, :]).reshape(len(x_hat), -1)


def fitted_skinning(points: np.ndarray, volumes: np.ndarray, E: np.ndarray, nu: np.ndarray, bounds: np.ndarray,
                    settings: LBSSettings, progress: Progress | None = None) -> np.ndarray:
    """Skinning parameters fitted for a solid, from the on-disk cache when available."""
    from ..core.paths import cache_dir, content_key

    key = content_key("lbs-skinning/1", np.asarray(points, np.float64), np.asarray(volumes, np.float64),
                      np.asarray(E, np.float64), np.asarray(nu, np.float64), np.asarray(bounds, np.float64),
                      settings.handles, settings.fit_iterations)
    path = cache_dir("lbs_skinning") / f"{key}.npy"
    if settings.cache_skinning and path.is_file():
        try:
            p = np.load(path)
            if p.shape == (skinning.param_count(settings.handles),):
                return p
        except (OSError, ValueError):
            pass
    params = fit_skinning(points, volumes, E, nu, bounds=bounds, handles=settings.handles,
                          iterations=settings.fit_iterations, progress=progress)
    if settings.cache_skinning:
        tmp = path.with_suffix(".tmp.npy")
        np.save(tmp, params)
        tmp.replace(path)
    return params


class LBSSimulation(Simulation):
    """A prepared LBS simulation (see the module docstring).

    Public attributes (numpy, SI): ``skinning_params`` (650,), ``bounds`` (2, 3) of the
    normalised cube, ``cubature_rest`` (C, 3), ``cubature_volume`` (C,), ``cubature_E`` /
    ``cubature_nu`` (C,), ``mass_rest`` (M, 3) and ``mass`` (M,) of the fill points,
    ``collision_rest`` (K, 3), ``handles`` H.
    """

    solver = "lbs"

    def __init__(self, body: Body, material: MaterialSpec, scenario: Scenario, frame_times, device: str,
                 settings: LBSSettings, progress: Progress | None = None):
        from .warp_runtime import init_warp, resolve_device

        super().__init__(body, scenario, frame_times, resolve_device(device))
        self.settings = settings
        self.warnings: list[str] = list(body.warnings)
        H = settings.handles
        self.handles = H
        # ---- samples and material
        fill, fvol = fill_solid(body, settings.mass_samples, max(settings.mass_samples, 10 * settings.cubature_points))
        mat = sample_material(material, fill)
        simulated = np.array([c.simulated for c in materials_mod.MATERIAL_CLASSES])
        keep = simulated[mat.material]
        if not np.any(keep):
            raise UserError("the material field marks the whole solid as background (not simulated)")
        if not np.all(keep):
            self.warnings.append(f"{int((~keep).sum())} of {len(keep)} fill points are background material")
            fill, fvol = fill[keep], fvol[keep]
            mat = type(mat)(mat.E[keep], mat.nu[keep], mat.density[keep], mat.material[keep])
        held = np.array([c.held_fixed for c in materials_mod.MATERIAL_CLASSES])
        pinned = held[mat.material] | scenario.pinned_mask(fill)
        self.mass_rest = fill
        self._fill_volume = fvol
        self.mass = fvol * mat.density
        self.total_mass = float(self.mass.sum())
        C = min(settings.cubature_points, len(fill))
        c_idx = farthest_point_sampling(fill, C)
        self.cubature_rest = fill[c_idx]
        from scipy.spatial import cKDTree

        _, cell = cKDTree(self.cubature_rest).query(fill)
        vol_c = np.bincount(cell, fvol, C)
        self.cubature_volume = vol_c
        self.cubature_E = np.bincount(cell, fvol * mat.E, C) / np.maximum(vol_c, 1e-300)
        self.cubature_nu = np.bincount(cell, fvol * mat.nu, C) / np.maximum(vol_c, 1e-300)
        self.cubature_density = np.bincount(cell, fvol * mat.density, C) / np.maximum(vol_c, 1e-300)
        if isinstance(material, PointMaterial):
            # explicit per-point values (e.g. the model's per-cubature-point E, ν) are used as given
            s = sample_material(material, self.cubature_rest)
            self.cubature_E, self.cubature_nu = s.E.copy(), s.nu.copy()
        self.cubature_material = mat.material[c_idx]
        self.sample_positions = self.cubature_rest.copy()
        cls_yield = np.array([c.params.get("yield_stress", math.inf) if c.plasticity == "von_mises" else math.inf
                              for c in materials_mod.MATERIAL_CLASSES])
        self.class_yield = cls_yield[self.cubature_material]
        odd = sorted({materials_mod.get(int(c)).name for c in np.unique(self.cubature_material)
                      if materials_mod.get(int(c)).plasticity in ("drucker_prager", "snow")
                      or materials_mod.get(int(c)).elasticity == "weakly_compressible"})
        if odd:
            self.warnings.append("the LBS solver models " + ", ".join(odd) + " material as fixed-corotated elastic")
        # ---- skinning basis
        self.bounds = np.stack([body.rest_points.min(0), body.rest_points.max(0)])
        self.centre = 0.5 * (self.bounds[0] + self.bounds[1])
        self.extent = float(np.max(self.bounds[1] - self.bounds[0]))
        if settings.skinning_params is not None:
            self.skinning_params = np.asarray(settings.skinning_params, np.float64)
            self.skinning_fitted = False
        else:
            if progress is not None:
                progress.step(0.0, "fitting skinning weights")
            E_fill, nu_fill = mat.E, mat.nu
            self.skinning_params = np.asarray(fitted_skinning(fill, fvol, E_fill, nu_fill, self.bounds, settings),
                                              np.float64)
            self.skinning_fitted = True
        self._setup_basis(pinned)
        self._wp = init_warp()

    # ------------------------------------------------------------------------------ basis
    def weights(self, points: np.ndarray) -> np.ndarray:
        """(N, H+1) handle weights at (N, 3) rest points (metres); the last is the constant handle."""
        xh = skinning.normalise_points(points, self.bounds)
        w = skinning.skinning_weights(xh, self.skinning_params, self.handles)
        return np.concatenate([w, np.ones((len(w), 1))], axis=1)

    def lifted(self, points: np.ndarray) -> np.ndarray:
        """(N, 4(H+1)) lifted basis a(X) (x = X + Z a(X))."""
        return lift_basis(self.weights(points), skinning.normalise_points(points, self.bounds))

    def _setup_basis(self, pinned_fill: np.ndarray):
        H = self.handles
        s = self.extent
        nA = 4 * (H + 1)
        self.n_basis = nA
        a_fill = self.lifted(self.mass_rest)
        M = np.einsum("p,pi,pj->ij", self.mass, a_fill, a_fill)
        M += 1e-10 * np.trace(M) / nA * np.eye(nA)
        self.mass_matrix = M
        self.mass_moment = self.mass @ a_fill                      # Σ m a  (nA,)
        self._a_fill = a_fill
        self.pinned_fill = pinned_fill
        self.pin_matrix = np.einsum("p,pi,pj->ij", self.mass * pinned_fill, a_fill, a_fill)
        # deformation-gradient operator at the cubature points: F = I + Z G_c, G_c (nA, 3)
        xh = skinning.normalise_points(self.cubature_rest, self.bounds)
        W, b = skinning.split_params(self.skinning_params, H)
        feat, jac = skinning.hidden_features_jacobian(xh)
        w = np.concatenate([feat @ W.T + b, np.ones((len(xh), 1))], axis=1)            # (C, H+1)
        gw = np.concatenate([np.einsum("hk,nkd->nhd", W, jac), np.zeros((len(xh), 1, 3))], axis=1)  # ∇_x̂ w
        xh1 = np.concatenate([xh, np.ones((len(xh), 1))], axis=1)
        eye43 = np.zeros((4, 3))
        eye43[:3, :3] = np.eye(3)
        G = (xh1[:, None, :, None] * gw[:, :, None, :] + w[:, :, None, None] * eye43) / s   # (C, H+1, 4, 3)
        self.cubature_G = G.reshape(len(xh), nA, 3)
        self._a_cub = lift_basis(w, xh)
        # collision points
        self.collision_rest = self._collision_samples()
        self._a_col = self.lifted(self.collision_rest)
        self._a_track = self.lifted(self.tracked_rest) if len(self.tracked_rest) else np.zeros((0, nA))
        spacing = (float(self.cubature_volume.sum()) / len(self.cubature_rest)) ** (1.0 / 3.0)
        self.cubature_spacing = spacing
        self.elastic_rate2 = float(np.max(self.cubature_E / self.cubature_density)) / spacing ** 2

    def _collision_samples(self) -> np.ndarray:
        """Surface samples of a mesh (offset 0), or the body's points, each standing for a cell of material
        whose lower face is half a point spacing below it (``contact_offset``)."""
        k = self.settings.collision_points
        body = self.body
        if body.mesh is not None:
            import trimesh

            surf, _ = trimesh.sample.sample_surface(body.mesh, max(4 * k, 1000), seed=0)
            cand = np.concatenate([np.asarray(body.mesh.vertices, np.float64), np.asarray(surf, np.float64)])
            self.contact_offset = 0.0
        else:
            cand = np.asarray(body.points, np.float64)
            self.contact_offset = 0.5 * float(np.mean(self._fill_volume)) ** (1.0 / 3.0)
        return cand[farthest_point_sampling(cand, k)]

    def positions(self, Z: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Deformed positions (N, 3) m of rest points (N, 3) for handle transforms Z (3, 4(H+1))."""
        return np.asarray(points, np.float64) + self.lifted(points) @ np.asarray(Z, np.float64).T

    def handle_transforms(self, Z: np.ndarray) -> np.ndarray:
        """World-space handle transforms (H+1, 3, 4) from the state Z (3, 4(H+1)) (module docstring)."""
        H = self.handles
        Zh = np.asarray(Z, np.float64).reshape(3, H + 1, 4).transpose(1, 0, 2)   # (H+1, 3, 4)
        lin = Zh[:, :, :3] / self.extent
        trans = Zh[:, :, 3] - lin @ self.centre
        D = np.concatenate([lin, trans[:, :, None]], axis=2)
        D[H, :, :3] += np.eye(3)
        return D

    # ------------------------------------------------------------------------------ running
    def _run_terms(self, terms_list: list[PhysicsTerms], *, progress: Progress | None,
                   particle_states: bool) -> list[Trajectory]:
        if not terms_list:
            return []
        with torch_threads(self.settings.torch_threads if self.device == "cpu" else 0):
            return self._run(terms_list, progress, particle_states)

    def _run(self, terms_list, progress, particle_states):
        import torch

        wp = self._wp
        from . import lbs_kernels as K

        st = self.settings
        dev = _torch_device(self.device)
        f64 = torch.float64
        E_env = len(terms_list)
        H1 = self.handles + 1
        nA = 4 * H1
        C = len(self.cubature_rest)
        T = len(self.frame_times)
        tt = lambda a: torch.as_tensor(np.asarray(a), dtype=f64, device=dev)  # noqa: E731
        M = tt(self.mass_matrix)
        Mpin = tt(self.pin_matrix)
        G = tt(self.cubature_G)                                             # (C, nA, 3)
        Gt = G.transpose(1, 2).contiguous()                                 # (C, 3, nA)
        GrT = G.permute(0, 2, 1).reshape(3 * C, nA).T.contiguous()          # (nA, [c b])
        vol = tt(self.cubature_volume)
        a_col = tt(self._a_col)                                             # (K, nA)
        z_col = tt(self.collision_rest[:, 2] - self.contact_offset)
        xy_col = tt(self.collision_rest[:, :2])
        a_fill = tt(self._a_fill)
        m_fill = tt(self.mass)
        # per-environment physics
        scale = np.stack([t.E_multiplier(C) for t in terms_list])          # (E, C)
        E_pts = self.cubature_E[None] * scale
        nu = self.cubature_nu[None]
        mu = tt(E_pts / (2 * (1 + nu)))
        lam = tt(E_pts * nu / ((1 + nu) * (1 - 2 * nu)))
        ys = np.stack([np.minimum(self.class_yield, t.yield_stress) for t in terms_list])
        plastic = bool(np.any(np.isfinite(ys)))
        ys_t = tt(np.where(np.isfinite(ys), ys, 1e301))
        accel = np.stack([self.scenario.gravity + t.extra_acceleration for t in terms_list])   # (E, 3)
        f_ext = tt(accel[:, :, None] * self.mass_moment[None, None, :])    # (E, 3, nA)
        lin_drag = tt([t.linear_drag for t in terms_list])
        quad_drag = tt([t.quadratic_drag for t in terms_list])
        eta = tt([t.damping_eta for t in terms_list])
        mu_fric = tt([t.friction_mu for t in terms_list])
        any_quad = bool(np.any([t.quadratic_drag > 0 for t in terms_list]))
        any_fric = bool(np.any([t.friction_mu > 0 for t in terms_list]))
        ground = self.scenario.ground_height
        # state
        Z = torch.zeros(E_env, 3, nA, dtype=f64, device=dev)
        V = torch.zeros(E_env, 3, nA, dtype=f64, device=dev)
        V[:, :, (H1 - 1) * 4:] = tt(self._initial_affine_velocity())
        Fp_inv = torch.eye(3, dtype=f64, device=dev).repeat(E_env, C, 1, 1).contiguous()
        # output buffers (host)
        n_track = len(self.tracked_rest)
        out_track = np.zeros((E_env, T, n_track, 3), np.float32)
        out_handles = np.zeros((E_env, T, H1, 3, 4), np.float32)
        out_cub = np.zeros((E_env, T, C, 3), np.float32) if particle_states else None
        a_track = torch.as_tensor(self._a_track, dtype=torch.float32, device=dev)
        x_track = torch.as_tensor(self.tracked_rest, dtype=torch.float32, device=dev)
        a_cub = torch.as_tensor(self._a_cub, dtype=torch.float32, device=dev)
        x_cub = torch.as_tensor(self.cubature_rest, dtype=torch.float32, device=dev)
        # warp buffers viewing torch memory
        psi_t = torch.zeros(E_env, C, dtype=f64, device=dev)
        P_t = torch.zeros(E_env, C, 3, 3, dtype=f64, device=dev)
        H_t = torch.zeros(E_env, 3, C, 27, dtype=f64, device=dev)
        w_psi = wp.from_torch(psi_t, dtype=wp.float64)
        w_P = wp.from_torch(P_t, dtype=wp.mat33d)
        w_H = wp.from_torch(H_t, dtype=wp.float64)
        w_mu = wp.from_torch(mu.contiguous(), dtype=wp.float64)
        w_lam = wp.from_torch(lam.contiguous(), dtype=wp.float64)
        w_vol = wp.from_torch(vol.contiguous(), dtype=wp.float64)
        w_Fp = wp.from_torch(Fp_inv, dtype=wp.mat33d)
        w_ys = wp.from_torch(ys_t.contiguous(), dtype=wp.float64)
        stream = wp.stream_from_torch(torch.cuda.current_stream(dev)) if dev != "cpu" else None
        eye3 = torch.eye(3, dtype=f64, device=dev)

        def deformation(Zc):
            return (eye3 + torch.einsum("eam,cmb->ecab", Zc, G)).contiguous()

        def elastic(Zc, F_prev, visc, need):
            F = deformation(Zc)
            wF = wp.from_torch(F, dtype=wp.mat33d)
            wFn = wp.from_torch(F_prev, dtype=wp.mat33d)
            w_visc = wp.from_torch(visc.contiguous(), dtype=wp.float64)
            wp.launch(K.elastic_terms, dim=(E_env, C), inputs=[wF, wFn, w_Fp, w_mu, w_lam, w_vol, w_visc, need,
                                                                 w_psi, w_P, w_H], device=self.device, stream=stream)
            return F

        def record(frame):
            Zf = Z.to(torch.float32)
            pos = x_track[None] + torch.einsum("eam,nm->ena", Zf, a_track)
            out_track[:, frame] = pos.cpu().numpy()
            Zh = Z.cpu().numpy()
            for e in range(E_env):
                out_handles[e, frame] = self.handle_transforms(Zh[e])
            if out_cub is not None:
                out_cub[:, frame] = (x_cub[None] + torch.einsum("eam,nm->ena", Zf, a_cub)).cpu().numpy()

        record(0)
        t_start = time.perf_counter()
        steps = 0
        newton_total = 0
        extent = self.extent
        for f in range(1, T):
            interval = self.frame_times[f] - self.frame_times[f - 1]
            n_sub = max(1, math.ceil(interval / st.max_dt - 1e-9))
            dt = interval / n_sub
            kc = st.contact_stiffness * self.total_mass / len(self.collision_rest) / dt ** 2
            kp = st.clamp_stiffness * self.elastic_rate2
            visc = eta / dt
            Hconst = (M / dt ** 2)[None] * (1.0 + dt * lin_drag)[:, None, None] + kp * Mpin[None]   # (E, nA, nA)
            for _ in range(n_sub):
                Zn = Z.clone()
                Z_hat = Zn + dt * V
                Fn = deformation(Zn)
                # lagged quantities of the step
                if any_quad:
                    vel = torch.einsum("eam,pm->epa", V, a_fill)
                    speed = torch.linalg.norm(vel, dim=2)                         # (E, P)
                    Mq = torch.einsum("p,ep,pi,pj->eij", m_fill, quad_drag[:, None] * speed, a_fill, a_fill)
                else:
                    Mq = None
                if ground is not None:
                    zc = z_col[None] + Zn[:, 2, :] @ a_col.T
                    N_lag = kc * torch.clamp(ground - zc, min=0.0)               # (E, K) N
                else:
                    N_lag = None

                def objective(Zc, need):
                    """Φ (E,) and, with need >= 1, its gradient (E, 3, nA); need == 2 also leaves the
                    cubature points' 9×9 Hessians in H_t for :func:`elastic_hessian`."""
                    elastic(Zc, Fn, visc, need)
                    D = Zc - Z_hat
                    phi = 0.5 / dt ** 2 * torch.einsum("eam,mn,ean->e", D, M, D) + psi_t.sum(1)
                    dZ = Zc - Zn
                    phi = phi + 0.5 * lin_drag / dt * torch.einsum("eam,mn,ean->e", dZ, M, dZ)
                    phi = phi - torch.einsum("eam,eam->e", f_ext, Zc)
                    phi = phi + 0.5 * kp * torch.einsum("eam,mn,ean->e", Zc, Mpin, Zc)
                    grad = None
                    if need >= 1:
                        grad = (D @ M) / dt ** 2 + lin_drag[:, None, None] / dt * (dZ @ M) - f_ext + kp * (Zc @ Mpin)
                        grad = grad + torch.einsum("ecab,cmb->eam", P_t, G)
                    if Mq is not None:
                        phi = phi + 0.5 / dt * torch.einsum("eam,emn,ean->e", dZ, Mq, dZ)
                        if need >= 1:
                            grad = grad + torch.einsum("eam,emn->ean", dZ, Mq) / dt
                    if ground is not None:
                        zc = z_col[None] + Zc[:, 2, :] @ a_col.T                 # (E, K)
                        pen = torch.clamp(ground - zc, min=0.0)
                        phi = phi + 0.5 * kc * torch.sum(pen * pen, dim=1)
                        if need >= 1:
                            grad[:, 2, :] -= kc * pen @ a_col
                        if any_fric:
                            ut, y, f0, f1_over_y = friction_terms(Zc)
                            coef = mu_fric[:, None] * N_lag
                            phi = phi + torch.sum(coef * f0, dim=1)
                            if need >= 1:
                                grad[:, :2, :] += torch.einsum("ek,eka,km->eam", coef * f1_over_y, ut, a_col)
                    return phi, grad

                def friction_terms(Zc):
                    eps = st.friction_velocity * dt
                    ut = torch.einsum("eam,km->eka", Zc[:, :2, :] - Zn[:, :2, :], a_col)     # (E, K, 2) slip
                    y = torch.linalg.norm(ut, dim=2)
                    f0 = torch.where(y >= eps, y, -y ** 3 / (3 * eps ** 2) + y ** 2 / eps + eps / 3)
                    f1_over_y = torch.where(y >= eps, 1.0 / torch.clamp(y, min=1e-300), 2.0 / eps - y / eps ** 2)
                    return ut, y, f0, f1_over_y

                def elastic_hessian():
                    """Σ_c G_cᵀ H_c G_c from the last need == 2 evaluation: two batched GEMMs, (E, 3, nA, 3, nA)."""
                    T1 = torch.matmul(H_t.view(E_env, 3, C, 9, 3), Gt)                 # (E, a, c, [b x], n)
                    return torch.matmul(GrT, T1.view(E_env, 3, 3 * C, 3 * nA)).view(E_env, 3, nA, 3, nA)

                def cheap_hessian(Zc):
                    """Inertia, drags, clamp, contact and friction blocks at Zc (cheap: 44×44 blocks)."""
                    hess = torch.zeros(E_env, 3, nA, 3, nA, dtype=f64, device=dev)
                    blk = Hconst if Mq is None else Hconst + Mq / dt
                    for a in range(3):
                        hess[:, a, :, a, :] += blk
                    if ground is not None:
                        zc = z_col[None] + Zc[:, 2, :] @ a_col.T
                        act = (zc < ground).to(f64)
                        hess[:, 2, :, 2, :] += kc * torch.einsum("ek,ki,kj->eij", act, a_col, a_col)
                        if any_fric:
                            _, _, _, f1_over_y = friction_terms(Zc)
                            Bf = torch.einsum("ek,ki,kj->eij", mu_fric[:, None] * N_lag * f1_over_y, a_col, a_col)
                            hess[:, 0, :, 0, :] += Bf
                            hess[:, 1, :, 1, :] += Bf
                    return hess

                active = torch.ones(E_env, dtype=torch.bool, device=dev)
                Z = Z_hat.clone()
                phi0, grad = objective(Z, 2)
                H_el = elastic_hessian()
                for it in range(st.newton_iterations):
                    if it > 0 and not st.reuse_hessian:
                        phi0, grad = objective(Z, 2)
                        H_el = elastic_hessian()
                    Hm = (H_el + cheap_hessian(Z)).reshape(E_env, 3 * nA, 3 * nA)
                    Hm = 0.5 * (Hm + Hm.transpose(1, 2))
                    L, info = torch.linalg.cholesky_ex(Hm)
                    if bool(torch.any(info != 0)):
                        shift = 1e-8 * torch.diagonal(Hm, dim1=1, dim2=2).abs().max(dim=1).values
                        L, info = torch.linalg.cholesky_ex(Hm + shift[:, None, None]
                                                           * torch.eye(3 * nA, dtype=f64, device=dev))
                    g = grad.reshape(E_env, 3 * nA, 1)
                    step = -torch.cholesky_solve(g, L).reshape(E_env, 3, nA)
                    step = torch.where(active[:, None, None], step, torch.zeros_like(step))
                    slope = torch.einsum("eam,eam->e", grad, step)
                    alpha = torch.ones(E_env, dtype=f64, device=dev)
                    accepted = ~active
                    phi_new, grad_new = phi0.clone(), grad.clone()
                    for _ls in range(st.line_search_steps):
                        trial = Z + alpha[:, None, None] * step
                        # the trial's gradient comes with its energy: an accepted trial starts the next iteration
                        phi_t, grad_t = objective(trial, 1)
                        ok = phi_t <= phi0 + 1e-4 * alpha * slope + 1e-12 * phi0.abs()
                        newly = ok & ~accepted
                        Z = torch.where(newly[:, None, None], trial, Z)
                        phi_new = torch.where(newly, phi_t, phi_new)
                        grad_new = torch.where(newly[:, None, None], grad_t, grad_new)
                        accepted = accepted | ok
                        if bool(torch.all(accepted)):
                            break
                        alpha = torch.where(accepted, alpha, 0.5 * alpha)
                    phi0, grad = phi_new, grad_new
                    # converged when the next Newton step (predicted with the current factor) is tiny
                    nxt = torch.cholesky_solve(grad.reshape(E_env, 3 * nA, 1), L).reshape(E_env, 3, nA)
                    rms = torch.sqrt(torch.clamp(torch.einsum("eam,mn,ean->e", nxt, M, nxt), min=0.0)
                                     / self.total_mass)
                    newton_total += 1
                    active = active & accepted & (rms > st.newton_tolerance * extent)
                    if not bool(torch.any(active)):
                        break
                if plastic:
                    F_now = deformation(Z)
                    wp.launch(K.return_map, dim=(E_env, C), inputs=[wp.from_torch(F_now, dtype=wp.mat33d), w_Fp, w_mu,
                                                                     w_ys], device=self.device, stream=stream)
                V = (Z - Zn) / dt
                steps += 1
                if not bool(torch.all(torch.isfinite(Z))):
                    raise SimulationDiverged(f"the LBS simulation diverged at frame {f} (t = {self.frame_times[f]:.4g} s); "
                                             "use a smaller settings.max_dt")
            record(f)
            if progress is not None:
                progress.step(1.0 / max(T - 1, 1), f"LBS frame {f}/{T - 1}")
        wall = time.perf_counter() - t_start
        results = []
        for e in range(E_env):
            meta = {"steps": steps, "newton_iterations": newton_total, "cubature_points": C, "handles": self.handles,
                    "device": self.device, "wall_s": wall, "skinning_bounds": self.bounds.tolist(),
                    "skinning_params": self.skinning_params.tolist(), "skinning_fitted": self.skinning_fitted,
                    "handle_form": "x = A[X;1] + sum_h w_h(X) D_h[X;1]; A = handle_transforms[:, -1]",
                    "warnings": list(self.warnings)}
            traj = Trajectory(self.frame_times, out_track[e], solver=self.solver, handle_transforms=out_handles[e],
                              meta=meta)
            if particle_states:
                traj.particle_positions = out_cub[e]
                traj.particle_attributes = {"E": (self.cubature_E * np.asarray(terms_list[e].E_multiplier(C))).astype(np.float32),
                                            "nu": self.cubature_nu.astype(np.float32),
                                            "volume": self.cubature_volume.astype(np.float32),
                                            "material": self.cubature_material.astype(np.int32)}
            results.append(traj)
        return results

    def _initial_affine_velocity(self) -> np.ndarray:
        """Constant-handle velocity (3, 4) giving the scenario's rigid initial velocity field."""
        sc = self.scenario
        com = (self.mass[:, None] * self.mass_rest).sum(0) / self.total_mass
        Wm = np.array([[0, -sc.initial_angular_velocity[2], sc.initial_angular_velocity[1]],
                       [sc.initial_angular_velocity[2], 0, -sc.initial_angular_velocity[0]],
                       [-sc.initial_angular_velocity[1], sc.initial_angular_velocity[0], 0]])
        lin = Wm * self.extent
        trans = Wm @ (self.centre - com) + sc.initial_velocity
        return np.concatenate([lin, trans[:, None]], axis=1)


def prepare(body: Body, material: MaterialSpec, scenario: Scenario, frame_times, device: str = "cpu",
            settings=None, progress: Progress | None = None) -> LBSSimulation:
    """Sample the solid, fit (or take) the skinning basis and build the reduced operators.

    settings: :class:`LBSSettings` or a dict of its fields (``skinning_params`` runs the
    model's predicted 650 parameters).
    """
    if not isinstance(body, Body):
        raise UserError(f"expected a Body, got {type(body).__name__}")
    if not isinstance(scenario, Scenario):
        raise UserError(f"expected a Scenario, got {type(scenario).__name__}")
    settings = LBSSettings.coerce(settings)
    return LBSSimulation(body, material, scenario, frame_times, device, settings, progress)


def cubature_positions(body: Body, count: int = DEFAULT_CUBATURE_POINTS,
                       mass_samples: int = DEFAULT_MASS_SAMPLES) -> np.ndarray:
    """(C, 3) m rest positions of the cubature points, in the order the solver uses them."""
    fill, _ = fill_solid(body, mass_samples, max(mass_samples, 10 * count))
    return fill[farthest_point_sampling(fill, min(count, len(fill)))]


def prepare_with_parameters(body: Body, skinning_params: np.ndarray, E: np.ndarray, nu: np.ndarray, density,
                            scenario: Scenario, frame_times, device: str = "cpu", settings=None,
                            progress: Progress | None = None) -> LBSSimulation:
    """Run with the model's LBS outputs: 650 skinning parameters and per-cubature-point E (Pa), ν.

    E, nu: (C,) at :func:`cubature_positions` (C = settings.cubature_points); density: kg/m³,
    a number or (C,).  Without a clamp on the fill points' material these values are looked
    up by nearest cubature point.
    """
    settings = LBSSettings.coerce(settings)
    pts = cubature_positions(body, settings.cubature_points, settings.mass_samples)
    E = np.asarray(E, np.float64).reshape(-1)
    nu = np.asarray(nu, np.float64).reshape(-1)
    if E.shape != (len(pts),) or nu.shape != (len(pts),):
        raise UserError(f"E and nu must have one value per cubature point ({len(pts)}), got {E.shape} and {nu.shape}")
    dens = np.broadcast_to(np.asarray(density, np.float64), (len(pts),)).copy()
    material = PointMaterial(pts, E, nu, dens)
    values = {f.name: getattr(settings, f.name) for f in fields(LBSSettings)}
    values["skinning_params"] = np.asarray(skinning_params, np.float64)
    return prepare(body, material, scenario, frame_times, device=device, settings=LBSSettings(**values),
                   progress=progress)
