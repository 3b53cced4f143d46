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

**Time step.**  Newmark's rule with γ = ½ + :data:`NEWMARK_ALPHA` and β = (γ + ½)²/4 (nearly the
average-acceleration rule: unconditionally stable, and its numerical damping only a small fraction of a
vibration per step, so a bounce keeps its energy), solved by Newton's method with a backtracking (Armijo) line search, at most
``newton_iterations`` iterations per step, on the incremental potential::

    Φ(Z) = 1/(2β dt²) ‖Z − Ẑ‖²_M + Σ_c V_c Ψ(F_c(Z)) − f_ext·Z + ground contact + clamp penalty + effect terms,
    Ẑ = Z_n + dt Ż_n + (½ − β) dt² Z̈_n

whose minimiser Z_{n+1} gives Z̈_{n+1} = (Z_{n+1} − Ẑ)/(β dt²) and Ż_{n+1} = Ż_n + dt ((1 − γ) Z̈_n + γ Z̈_{n+1}).  Dissipative terms (drags, Kelvin–Voigt viscosity, the ground's damper) act on the
mean velocity of the step (Z − Z_n)/dt, which Newmark's rule makes the midpoint velocity.  (Until this
version the step was backward Euler, whose numerical damping took most of a bounce's energy: docs/lbs.md.)
Ψ is fixed-corotated (:mod:`.lbs_kernels`, with its analytic PSD-projected Hessian).

**Where the work runs.**  Only what scales with the cubature points runs on the Warp device
(:class:`_ElasticTerms`): one kernel forms F_c = I + Z G_c and evaluates the energy, stress
and (at a step start) the 9×9 Hessian per point, and torch reduces them to handle space with
GEMMs (Σ_c Gᵀ H_c G, 26 M multiply-adds for 500 points: what BLAS / cuBLAS do best).  The
reduced problem — 132 unknowns — stays on the host in float64 numpy (:class:`_HostTerms`,
:class:`_Factor`): inertia, drags, gravity, clamp, contact and friction, the 132×132 Cholesky
solve and the line search's logic.  Each evaluation is then one upload of the candidate states,
one kernel, a few GEMMs, one download and one synchronisation (3 per step at ~2 Newton
iterations); the line search evaluates ``line_search_candidates`` step lengths per launch (4 on
a GPU).  The state of every frame is kept (132 numbers) and the tracked points / vertices are
computed after the stepping, one GEMM per chunk of frames.  ``meta["phase_seconds"]`` and
``meta["evaluation_seconds"]`` tell where a run's time went.  All environments of
:meth:`run_batch` step together.

**Contact and clamp.**  The ground follows the contact law of :mod:`.contact` at ``collision_points``
surface samples, each standing for an equal share A of the surface: the potential ½ k (h − z_p)₊² with
k = min(k_g A, k_r, m (ω_max)²), k_r = β² M A / ℓ (ℓ the cubature spacing: the rigid floor is as stiff as the
finest deformation the cubature resolves; m the sample's share of the mass and ω_max = ``IMPLICIT_MAX_CONTACT_RATE`` /
``max_dt``: the step resolves the contact's oscillation) and, with ``contact_damping``, the damper c_g A on the mean normal velocity
of the step at the samples in contact; the clamp
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
precomputed once (any number of points: one GEMM per chunk of frames).  ``handle_transforms``
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
from ..core.progress import Progress, frame_done
from ..core.types import Trajectory
from . import materials as materials_mod
from . import skinning
from .api import Simulation
from .body import Body
from .effects import PhysicsTerms
from .lbs_fit import DEFAULT_FIT_ITERATIONS, fit_skinning, torch_threads
from .material_sampling import MaterialSpec, PointMaterial, sample_material
from .contact import IMPLICIT_MAX_CONTACT_RATE, RIGID_CONTACT_BETA
from .sampling import farthest_point_sampling
from .scenario import Scenario
from .spring_mass import fill_solid

DEFAULT_CUBATURE_POINTS = 500
DEFAULT_MASS_SAMPLES = 4000
DEFAULT_COLLISION_POINTS = 256
DEFAULT_MAX_DT = 5.0e-3
"""Largest step (s); a frame interval is split into equal steps no longer than this."""
DEFAULT_NEWTON_ITERATIONS = 4
INTEGRATORS = ("newmark", "backward_euler")
"""Time integrators: Newmark's average acceleration (default: no numerical damping) and backward Euler (damps
every vibration the step does not resolve: for settling into a static state with large steps)."""
NEWMARK_ALPHA = 0.02
"""Newmark's γ = ½ + α, β = (γ + ½)²/4.  α = 0 (the average-acceleration rule) conserves the energy of linear
elasticity exactly but let large steps of a bouncing, rotating body gain energy and blow up (a 0.1 m block,
10 handles, 10 ms steps); α = 0.02 damps the vibrations a step does not resolve (per step about α ω Δt of a
mode's amplitude) and kept 10 and 20 ms steps stable; measured cost: a dropped cube's rebound height 1.7 %
lower at the default 5 ms step, 0.3 % at 1 ms (docs/lbs.md)."""


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
    clamp_stiffness: dimensionless penalty factor of the clamp (module docstring).
    friction_velocity: m/s, slip speed below which ground friction sticks.
    cache_skinning: reuse fitted parameters from the cache directory.
    torch_threads: torch intra-op threads on the CPU while stepping — the host's Newton solve, and the
        elastic terms on a CPU device (0 = leave torch's setting).
    line_search_candidates: step lengths (1, 1/2, 1/4, ...) of the backtracking line search
        evaluated together in one launch; the accepted length is the same as one at a time (the first
        that satisfies the Armijo condition).  0 = automatic: 1 on the CPU (each costs a kernel's
        work), 4 on a GPU (they cost one launch and one synchronisation).
    profile_device: time the device phases of a GPU run with CUDA events (``meta["phase_seconds"]``;
        adds a few microseconds per evaluation).  On the CPU they are always timed.
    integrator: ``"newmark"`` (default; average acceleration, no numerical damping) or ``"backward_euler"``
        (quasi-static: settles into equilibrium with large steps, and damps vibrations and bounces it does not
        resolve - not for dynamics).
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
    clamp_stiffness: float = 1.0
    friction_velocity: float = 1e-3
    cache_skinning: bool = True
    torch_threads: int = 1
    line_search_candidates: int = 0
    profile_device: bool = False
    integrator: str = "newmark"

    def __post_init__(self):
        if self.integrator not in INTEGRATORS:
            raise UserError(f"LBS setting 'integrator' must be one of {INTEGRATORS}, got {self.integrator!r}")
        for name in ("handles", "cubature_points", "mass_samples", "collision_points", "newton_iterations",
                     "line_search_steps"):
            val = getattr(self, name)
            if not isinstance(val, (int, np.integer)) or val < 1:
                raise UserError(f"LBS setting '{name}' must be a positive whole number, got {val!r}")
            setattr(self, name, int(val))
        for name in ("fit_iterations", "line_search_candidates"):
            val = getattr(self, name)
            if not isinstance(val, (int, np.integer)) or val < 0:
                raise UserError(f"LBS setting '{name}' must be a whole number >= 0, got {val!r}")
            setattr(self, name, int(val))
        for name in ("max_dt", "newton_tolerance", "clamp_stiffness", "friction_velocity"):
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


def lift_basis(weights: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """a(X) = w ⊗ [x̂; 1]: (N, H+1) weights and (N, 3) normalised points -> (N, 4(H+1))."""
    xh1 = np.concatenate([x_hat, np.ones((len(x_hat), 1))], axis=1)
    return (weights[:, :, None] * xh1[:, None, :]).reshape(len(x_hat), -1)


def fitted_skinning(points: np.ndarray, volumes: np.ndarray, E: np.ndarray, nu: np.ndarray, bounds: np.ndarray,
                    settings: LBSSettings, progress: Progress | None = None) -> np.ndarray:
    """Skinning parameters fitted for a solid, from the on-disk cache when available."""
    from ..core.paths import cache_dir, content_key, save_cached_array

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
        try:
            save_cached_array(path, params)
        except UserError:  # a cache that cannot be written (full disk): the fit is still good for this run
            pass
    return params


class _PhaseClock:
    """Seconds spent per named phase, accumulated."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds


def _host_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b on the host: numpy for tiny products, else torch's CPU BLAS (one thread inside a run).

    numpy's OpenBLAS runs products above ~10⁴ multiply-adds (a 44 × 256 matrix-vector product
    already) on its own thread pool, which stalls for milliseconds on a loaded machine.
    """
    if a.size * b.shape[-1] <= 8192:
        return a @ b
    import torch

    return torch.matmul(torch.from_numpy(np.ascontiguousarray(a)), torch.from_numpy(np.ascontiguousarray(b))).numpy()


class _Factor:
    """Cholesky factors of R symmetric positive-definite systems A (R, N, N), on the host in float64.

    Only the lower triangle of A is read.  A system whose factorisation fails gets a diagonal shift of
    1e-8 × its largest diagonal entry.
    """

    def __init__(self, A: np.ndarray):
        import torch

        A = np.ascontiguousarray(A)
        L, info = torch.linalg.cholesky_ex(torch.from_numpy(A))
        bad = np.flatnonzero(info.numpy() != 0)
        if len(bad):
            shift = 1e-8 * np.abs(np.diagonal(A[bad], axis1=1, axis2=2)).max(axis=1)
            shifted = A[bad] + shift[:, None, None] * np.eye(A.shape[1])
            L[torch.from_numpy(bad)] = torch.linalg.cholesky_ex(torch.from_numpy(shifted))[0]
        self.L = L

    def subset(self, rows: np.ndarray) -> "_Factor":
        """The factors of the systems ``rows`` (indices)."""
        import torch

        part = object.__new__(_Factor)
        part.L = self.L[torch.from_numpy(np.asarray(rows, np.int64))]
        return part

    def solve(self, b: np.ndarray) -> np.ndarray:
        """A⁻¹ b for right-hand sides b (R, ...) with N numbers each."""
        import torch

        rhs = torch.from_numpy(np.ascontiguousarray(b).reshape(len(b), -1, 1))
        return torch.cholesky_solve(rhs, self.L).numpy().reshape(b.shape)


class _HostTerms:
    """The incremental potential's terms other than elasticity for one time step, on the host (numpy, float64).

    Inertia w/(2dt²) ‖Z − Ẑ‖²_M (w = 1/β for Newmark, 1 for backward Euler), Rayleigh drag ½ c/dt ‖Z − Z_n‖²_M, quadratic drag ½/dt ‖Z − Z_n‖²_Mq,
    −f_ext·Z, the clamp ½ κ_p ‖Z‖²_Mpin, the ground's spring ½ Σ k_k (h − z_k)₊² and damper
    ½ Σ c_k/dt (z_k − z_k,n)² at the samples in contact, and Coulomb friction Σ μ N_k f0(|Δx_t,k|) (module
    docstring); kc, cc: (E, K) per environment and collision sample.  They reach the handle space only through (nA, nA)
    matrices and the collision points' lifted basis (K, nA), so they cost microseconds and need no
    device round trip.

    Methods take state rows Z (R, 3, nA) and their environments env (R,) (indices into the (E, ...)
    per-environment arrays).
    """

    def __init__(self, *, M, Mpin, kp, dt, Z_hat, Z_start, lin_drag, f_ext, Mq, Hconst, ground, kc, cc, a_col, z_col,
                 N_lag, mu_fric, eps, inertia_weight):
        self.M, self.Mpin, self.kp, self.dt = M, Mpin, kp, dt
        self.inertia_weight = inertia_weight
        self.Z_hat, self.Z_start, self.lin_drag, self.f_ext, self.Mq = Z_hat, Z_start, lin_drag, f_ext, Mq
        self.Hconst, self.ground, self.kc, self.cc, self.a_col, self.z_col = Hconst, ground, kc, cc, a_col, z_col
        self.N_lag, self.mu_fric, self.eps = N_lag, mu_fric, eps
        self.a_col_T = np.ascontiguousarray(a_col.T)
        if ground is not None:
            self.z_start = z_col + _host_matmul(Z_start[:, 2, :], self.a_col_T)                  # (E, K) m

    def _friction(self, Z, env):
        """Tangential slips (R, 2, K) m since the step start, f0 (R, K) and f1(y)/y (R, K) (IPC's C¹ smoothing)."""
        eps = self.eps
        ut = _host_matmul(Z[:, :2, :] - self.Z_start[env][:, :2, :], self.a_col_T)
        y = np.sqrt(ut[:, 0] ** 2 + ut[:, 1] ** 2)
        slipping = y >= eps
        f0 = np.where(slipping, y, -y ** 3 / (3 * eps ** 2) + y ** 2 / eps + eps / 3)
        f1_over_y = np.where(slipping, 1.0 / np.maximum(y, 1e-300), 2.0 / eps - y / eps ** 2)
        return ut, f0, f1_over_y

    def energy_gradient(self, Z: np.ndarray, env: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Φ without elasticity (R,) J and its gradient (R, 3, nA)."""
        nA = Z.shape[2]
        dt = self.dt
        D = Z - self.Z_hat[env]
        dZ = Z - self.Z_start[env]
        DM = _host_matmul(D.reshape(-1, nA), self.M).reshape(D.shape)
        dZM = _host_matmul(dZ.reshape(-1, nA), self.M).reshape(D.shape)
        drag = self.lin_drag[env] / dt
        fe = self.f_ext[env]
        w = self.inertia_weight
        phi = (0.5 * w / dt ** 2 * np.einsum("ram,ram->r", DM, D) + 0.5 * drag * np.einsum("ram,ram->r", dZM, dZ)
               - np.einsum("ram,ram->r", fe, Z))
        grad = w / dt ** 2 * DM + drag[:, None, None] * dZM - fe
        if self.Mpin is not None:
            ZP = _host_matmul(Z.reshape(-1, nA), self.Mpin).reshape(Z.shape)
            phi += 0.5 * self.kp * np.einsum("ram,ram->r", ZP, Z)
            grad += self.kp * ZP
        if self.Mq is not None:
            dZMq = np.matmul(dZ, self.Mq[env])
            phi += 0.5 / dt * np.einsum("ram,ram->r", dZMq, dZ)
            grad += dZMq / dt
        if self.ground is not None:
            z = self.z_col + _host_matmul(Z[:, 2, :], self.a_col_T)                                    # (R, K) m
            pen = np.maximum(self.ground - z, 0.0)
            kc = self.kc[env]
            phi += 0.5 * np.einsum("rk,rk,rk->r", kc, pen, pen)
            fz = kc * pen                                                                          # (R, K) N up
            if self.cc is not None:  # the ground's damper on the step's mean normal velocity, where in contact
                dz = (z - self.z_start[env]) * (pen > 0)
                cd = self.cc[env] / dt
                phi += 0.5 * np.einsum("rk,rk,rk->r", cd, dz, dz)
                fz = fz - cd * dz
            grad[:, 2, :] -= _host_matmul(fz, self.a_col)
            if self.mu_fric is not None:
                ut, f0, f1_over_y = self._friction(Z, env)
                coef = self.mu_fric[env][:, None] * self.N_lag[env]                          # (R, K) N
                phi += np.einsum("rk,rk->r", coef, f0)
                grad[:, :2, :] += _host_matmul((coef * f1_over_y)[:, None, :] * ut, self.a_col)
        return phi, grad

    def add_hessian(self, hess: np.ndarray, Z: np.ndarray, env: np.ndarray) -> None:
        """Add the Hessian of the same terms at Z to ``hess`` (R, 3nA, 3nA) in place (contact: the active set
        at Z; friction: lagged normal force, IPC's f1/y weight)."""
        R, _, nA = Z.shape
        blocks = hess.reshape(R, 3, nA, 3, nA)
        blk = self.Hconst[env]
        if self.Mq is not None:
            blk = blk + self.Mq[env] / self.dt
        for a in range(3):
            blocks[:, a, :, a, :] += blk
        if self.ground is None:
            return
        act = self.z_col + _host_matmul(Z[:, 2, :], self.a_col_T) < self.ground          # (R, K)
        w_fric = None
        if self.mu_fric is not None:
            _, _, f1_over_y = self._friction(Z, env)
            w_fric = self.mu_fric[env][:, None] * self.N_lag[env] * f1_over_y              # (R, K)
        kz = self.kc[env] + (0.0 if self.cc is None else self.cc[env] / self.dt)                 # (R, K) N/m
        for r in range(R):
            touching = np.flatnonzero(act[r])
            if len(touching):
                a_t = self.a_col[touching]
                blocks[r, 2, :, 2, :] += _host_matmul(a_t.T * kz[r, touching], a_t)
            if w_fric is not None:
                loaded = np.flatnonzero(w_fric[r])
                if len(loaded):
                    a_s = self.a_col[loaded]
                    Bf = _host_matmul(a_s.T * w_fric[r, loaded], a_s)
                    blocks[r, 0, :, 0, :] += Bf
                    blocks[r, 1, :, 1, :] += Bf


class _ElasticTerms:
    """The elastic (cubature) part of the incremental potential, evaluated on the simulation's Warp device.

    Everything that scales with the cubature points stays on the device.  One evaluation of R
    candidate states uploads them (R × 3 × nA numbers) with their environment indices, runs one Warp
    kernel (:func:`.lbs_kernels.elastic_terms`: F = I + Z G_c, Ψ, stress and, at a step start, the
    projected 9×9 Hessian per cubature point), reduces to handle space with torch GEMMs
    (gradient Σ_c P_c G_cᵀ; Hessian Σ_c G_cᵀ H_c G_c) and downloads Σ_c V_c Ψ_c (R,), the gradient
    (R, 3, nA) and the Hessian (E, 3nA, 3nA): one synchronisation per evaluation, all buffers
    allocated once (pinned host staging on a GPU; on the CPU the host arrays are the device's).

    mu, lam: (E, C) Pa.  yield_stress: (E, C) Pa (1e301 = none) or None without plasticity.
    ``seconds`` accumulates per-phase times (CPU: wall; GPU: CUDA events when ``profile``, else only
    the host's wait); ``counts`` the evaluations.
    """

    def __init__(self, sim, mu: np.ndarray, lam: np.ndarray, yield_stress, max_rows: int, profile: bool,
                 staged: Optional[bool] = None):
        import torch

        from . import lbs_kernels as K

        wp = sim._wp
        self.torch = torch
        dev = sim.device  # Warp's device names (cpu, cuda:N) are torch's
        self.cuda = dev != "cpu"
        self.profile = bool(profile) and self.cuda
        # separate host staging buffers and copies (a GPU; on the CPU only to test that path)
        self.staged = self.cuda if staged is None else bool(staged)
        E_env, C = mu.shape
        nA = sim.n_basis
        self.E, self.C, self.nA, self.max_rows = E_env, C, nA, max_rows
        f64 = torch.float64

        def zeros(*shape, dtype=f64):
            return torch.zeros(*shape, dtype=dtype, device=dev)

        def dev_tensor(a):
            return torch.as_tensor(np.ascontiguousarray(a, np.float64), device=dev)

        G = dev_tensor(sim.cubature_G)                                      # (C, nA, 3) 1/m
        self.Gr = G.permute(0, 2, 1).reshape(3 * C, nA).contiguous()        # [(c, b), m]
        self.GrT = self.Gr.T.contiguous()                                   # [m, (c, b)]
        self.Gt = G.transpose(1, 2).contiguous()                            # (C, 3, nA)
        self.Z_rows = zeros(max_rows, 3, nA)
        self.env_rows = zeros(max_rows, dtype=torch.int32)
        self.Z_start = zeros(E_env, 3, nA)
        self.Z_plastic = zeros(E_env, 3, nA)
        self.visc = zeros(E_env)
        self.psi = zeros(max_rows, C)
        self.P = zeros(max_rows, 3, 3 * C)
        self.H = zeros(E_env, 3, C, 27)
        self.T1 = zeros(E_env, 3, C, 9, nA)
        self.result = zeros(max_rows * (3 * nA + 1))
        self.hessian = zeros(E_env, 3 * nA, 3 * nA)
        plastic_inv = torch.eye(3, dtype=f64, device=dev).repeat(E_env, C, 1, 1).contiguous()
        mu_t, lam_t, vol_t = dev_tensor(mu), dev_tensor(lam), dev_tensor(sim.cubature_volume)
        if self.staged:
            def host(t):
                return torch.empty(t.shape, dtype=t.dtype, pin_memory=self.cuda)

            self.h_Z_rows, self.h_env_rows = host(self.Z_rows), host(self.env_rows)
            self.h_Z_start, self.h_Z_plastic, self.h_visc = host(self.Z_start), host(self.Z_plastic), host(self.visc)
            self.h_result, self.h_hessian = host(self.result), host(self.hessian)
        else:
            self.h_Z_rows, self.h_env_rows = self.Z_rows, self.env_rows
            self.h_Z_start, self.h_Z_plastic, self.h_visc = self.Z_start, self.Z_plastic, self.visc
            self.h_result, self.h_hessian = self.result, self.hessian
        self.stream = None
        if self.cuda:
            self.torch_stream = torch.cuda.current_stream(dev)
            self.stream = wp.stream_from_torch(self.torch_stream)
        self.n_Z_rows, self.n_env_rows = self.h_Z_rows.numpy(), self.h_env_rows.numpy()
        self.n_Z_start, self.n_Z_plastic, self.n_visc = self.h_Z_start.numpy(), self.h_Z_plastic.numpy(), self.h_visc.numpy()
        self.n_result, self.n_hessian = self.h_result.numpy(), self.h_hessian.numpy()

        def warp(t, dtype=wp.float64):
            return wp.from_torch(t, dtype=dtype)

        self._keep = (mu_t, lam_t, vol_t, plastic_inv)
        self.launch = wp.launch(K.elastic_terms, dim=(max_rows, C),
                                inputs=[warp(self.Z_rows), warp(self.env_rows, wp.int32), warp(self.Z_start), warp(G),
                                        warp(plastic_inv, wp.mat33d), warp(mu_t), warp(lam_t), warp(vol_t),
                                        warp(self.visc), 0, warp(self.psi), warp(self.P), warp(self.H)],
                                device=sim.device, stream=self.stream, record_cmd=True)
        self.need_index = [a.label for a in K.elastic_terms.adj.args].index("need")
        self._launch_shape = (max_rows, 0)
        self.plastic_launch = None
        if yield_stress is not None:
            ys_t = dev_tensor(yield_stress)
            self._keep = self._keep + (ys_t,)
            self.plastic_launch = wp.launch(K.return_map, dim=(E_env, C),
                                            inputs=[warp(self.Z_plastic), warp(G), warp(plastic_inv, wp.mat33d),
                                                    warp(mu_t), warp(ys_t)],
                                            device=sim.device, stream=self.stream, record_cmd=True)
        self.symmetric_reduction = not self.cuda
        self.seconds: dict[str, float] = {}
        self.counts = {"hessian": 0, "trial": 0, "trial_rows": 0}
        self._events: list = []
        self._t = 0.0

    # -- timing ---------------------------------------------------------------------------------
    def _mark(self, name: str) -> None:
        """End of a phase: CUDA event on a profiled GPU run, wall clock on the CPU (where work is synchronous)."""
        if self.cuda:
            if self.profile:
                ev = self.torch.cuda.Event(enable_timing=True)
                ev.record(self.torch_stream)
                self._events.append((name, ev))
            return
        t = time.perf_counter()
        self.seconds[name] = self.seconds.get(name, 0.0) + (t - self._t)
        self._t = t

    def _start_phases(self) -> None:
        self._t = time.perf_counter()
        if self.profile:
            ev = self.torch.cuda.Event(enable_timing=True)
            ev.record(self.torch_stream)
            self._events = [("", ev)]

    def _collect_events(self) -> None:
        if not self._events:
            return
        prev = self._events[0][1]
        for name, ev in self._events[1:]:
            self.seconds[name] = self.seconds.get(name, 0.0) + 1e-3 * prev.elapsed_time(ev)
            prev = ev
        self._events = []

    def synchronize(self) -> None:
        if self.cuda:
            t = time.perf_counter()
            self.torch_stream.synchronize()
            self.seconds["wait"] = self.seconds.get("wait", 0.0) + time.perf_counter() - t
            self._collect_events()

    # -- work -----------------------------------------------------------------------------------
    def set_viscosity(self, visc: np.ndarray) -> None:
        """η/dt (E,) Pa of the Kelvin–Voigt term for the coming steps."""
        if np.array_equal(self.n_visc, visc):
            return
        self.synchronize()   # the staging buffer may still feed an earlier copy
        self.n_visc[:] = visc
        if self.staged:
            self.visc.copy_(self.h_visc, non_blocking=True)

    def evaluate(self, Z: np.ndarray, env: np.ndarray, hessian: bool = False, Z_start: Optional[np.ndarray] = None):
        """Elastic energy (R,) J, gradient (R, 3, nA) and, with ``hessian``, Hessian (R, 3nA, 3nA) of states Z.

        Z: (R, 3, nA) rows; env: (R,) their environments.  ``hessian`` needs env = 0..E−1 in order.
        Z_start: (E, 3, nA), the step start (viscous F_n); give it at the first evaluation of each step.
        """
        torch = self.torch
        R, C, nA = len(Z), self.C, self.nA
        if R > self.max_rows or (hessian and R != self.E):
            raise ValueError(f"{R} rows do not fit the LBS elastic buffers")
        self._start_phases()
        self.n_Z_rows[:R] = Z
        self.n_env_rows[:R] = env
        if Z_start is not None:
            self.n_Z_start[:] = Z_start
        if self.staged:
            self.Z_rows[:R].copy_(self.h_Z_rows[:R], non_blocking=True)
            self.env_rows[:R].copy_(self.h_env_rows[:R], non_blocking=True)
            if Z_start is not None:
                self.Z_start.copy_(self.h_Z_start, non_blocking=True)
        self._mark("upload")
        need = 2 if hessian else 1
        if (R, need) != self._launch_shape:
            self.launch.set_dim((R, C))
            self.launch.set_param_at_index(self.need_index, need)
            self._launch_shape = (R, need)
        self.launch.launch(self.stream)
        self._mark("kernel_hessian" if hessian else "kernel_trial")
        n_grad = 3 * R * nA
        torch.mm(self.P[:R].view(3 * R, 3 * C), self.Gr, out=self.result[:n_grad].view(3 * R, nA))
        torch.sum(self.psi[:R], dim=1, out=self.result[n_grad:n_grad + R])
        self._mark("reduction_gradient")
        if hessian:
            self._reduce_hessian()
            self._mark("reduction_hessian")
        if self.staged:
            self.h_result[:n_grad + R].copy_(self.result[:n_grad + R], non_blocking=True)
            if hessian:
                self.h_hessian.copy_(self.hessian, non_blocking=True)
            self._mark("download")
        self.synchronize()
        self.counts["hessian" if hessian else "trial"] += 1
        if not hessian:
            self.counts["trial_rows"] += R
        energy = self.n_result[n_grad:n_grad + R].copy()
        grad = self.n_result[:n_grad].reshape(R, 3, nA).copy()
        if not hessian:
            return energy, grad
        return energy, grad, self.n_hessian.copy()

    def _reduce_hessian(self) -> None:
        """hessian[e] = Σ_c G_cᵀ H_c G_c (3nA × 3nA), from the kernel's H: two GEMMs.

        T1[e, a, c, (b x), n] = Σ_y H[e, a, c, (b x y)] G[c, n, y]; then per block row a,
        K[(a m), (x n)] = Σ_(c b) G[c, m, b] T1[e, a, (c b), (x n)].  With ``symmetric_reduction`` (the
        CPU) only the blocks x >= a are multiplied (a third less work) and the others are filled from
        the symmetry; on a GPU one GEMM does all (fewer launches).
        """
        torch = self.torch
        E_env, C, nA = self.E, self.C, self.nA
        torch.matmul(self.H.view(E_env, 3, C, 9, 3), self.Gt, out=self.T1)
        T1 = self.T1.view(E_env, 3, 3 * C, 3 * nA)
        K4 = self.hessian.view(E_env, 3, nA, 3 * nA)
        if not self.symmetric_reduction:
            torch.matmul(self.GrT, T1, out=K4)
            return
        for a in range(3):
            K4[:, a, :, a * nA:] = torch.matmul(self.GrT, T1[:, a, :, a * nA:])
        for a in range(3):
            for x in range(a + 1, 3):
                K4[:, x, :, a * nA:(a + 1) * nA] = K4[:, a, :, x * nA:(x + 1) * nA].transpose(1, 2)

    def return_map(self, Z: np.ndarray) -> None:
        """Plastic return mapping at the accepted states Z (E, 3, nA) (updates F_p on the device)."""
        self.n_Z_plastic[:] = Z
        if self.staged:
            self.Z_plastic.copy_(self.h_Z_plastic, non_blocking=True)
        self.plastic_launch.launch(self.stream)


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
        self._device_copies: dict = {}

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
        # the contact law's samples (solvers/contact.py): an equal share of the surface each, and the P-wave
        # modulus of the material at the nearest cubature point
        from scipy.spatial import cKDTree

        K = len(self.collision_rest)
        if self.body.mesh is not None:
            self.collision_area = np.full(K, float(self.body.mesh.area) / K)
        else:
            self.collision_area = np.full(K, (2.0 * self.contact_offset) ** 2)
        _, self._collision_cubature = cKDTree(self.cubature_rest).query(self.collision_rest)
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
        """World-space handle transforms (..., H+1, 3, 4) from states Z (..., 3, 4(H+1)) (module docstring)."""
        H = self.handles
        Z = np.asarray(Z, np.float64)
        Zh = Z.reshape(Z.shape[:-2] + (3, H + 1, 4)).swapaxes(-3, -2)     # (..., H+1, 3, 4)
        lin = Zh[..., :3] / self.extent
        trans = Zh[..., 3] - lin @ self.centre
        D = np.concatenate([lin, trans[..., None]], axis=-1)
        D[..., H, :, :3] += np.eye(3)
        return D

    # ------------------------------------------------------------------------------ running
    def _run_terms(self, terms_list: list[PhysicsTerms], *, progress: Progress | None,
                   particle_states: bool) -> list[Trajectory]:
        if not terms_list:
            return []
        # the host's Newton solve uses torch on the CPU whatever the device: small tensors, one thread
        with torch_threads(self.settings.torch_threads):
            return self._run(terms_list, progress, particle_states)

    def _run(self, terms_list, progress, particle_states):
        import torch

        st = self.settings
        clock = _PhaseClock()
        t_begin = time.perf_counter()
        E_env = len(terms_list)
        H1 = self.handles + 1
        nA = 4 * H1
        C = len(self.cubature_rest)
        T = len(self.frame_times)
        envs = np.arange(E_env)
        M = self.mass_matrix
        Mpin = self.pin_matrix
        clamp = bool(np.any(self.pinned_fill))
        a_col = self._a_col                                                  # (K, nA)
        z_col = self.collision_rest[:, 2] - self.contact_offset
        # per-environment physics
        scale = np.stack([t.E_multiplier(C) for t in terms_list])          # (E, C)
        E_pts = self.cubature_E[None] * scale
        nu = self.cubature_nu[None]
        mu = E_pts / (2 * (1 + nu))
        lam = E_pts * nu / ((1 + nu) * (1 - 2 * nu))
        ys = np.stack([np.minimum(self.class_yield, t.yield_stress) for t in terms_list])
        plastic = bool(np.any(np.isfinite(ys)))
        accel = np.stack([self.scenario.gravity + t.extra_acceleration for t in terms_list])   # (E, 3)
        f_ext = accel[:, :, None] * self.mass_moment[None, None, :]        # (E, 3, nA)
        lin_drag = np.array([t.linear_drag for t in terms_list], np.float64)
        quad_drag = np.array([t.quadratic_drag for t in terms_list], np.float64)
        eta = np.array([t.damping_eta for t in terms_list], np.float64)
        mu_fric = np.array([t.friction_mu for t in terms_list], np.float64)
        # the ground's spring and damper per environment and collision sample (solvers/contact.py)
        area = self.collision_area[None]
        M_col = (lam + 2 * mu)[:, self._collision_cubature]                                  # (E, K) Pa
        k_ground = np.array([t.ground_stiffness for t in terms_list])[:, None]
        k_rigid = RIGID_CONTACT_BETA ** 2 * M_col * area / self.cubature_spacing
        # the implicit step follows a contact's oscillation only while ω Δt ≲ 2 (ω² = k / m, m a sample's share
        # of the mass): a stiffer spring switched on and off by the active set feeds energy into a Newmark step
        # (a stiff duck dropped at Δt = 5 ms flew off); the cap lets a sample sink about v Δt, put back on the
        # plane in the output
        k_step = self.total_mass / len(self.collision_rest) * (IMPLICIT_MAX_CONTACT_RATE / st.max_dt) ** 2
        kc = np.minimum(np.minimum(k_ground * area, k_rigid), k_step)
        c_ground = np.array([t.ground_damping for t in terms_list])[:, None]
        c_layer = 2.0 * eta[:, None] * kc / M_col       # the layer's Kelvin–Voigt damper 2η k_r/M × k/k_r
        cc = c_ground * area + c_layer if np.any(c_ground > 0) or np.any(eta > 0) else None
        any_quad = bool(np.any(quad_drag > 0))
        any_fric = bool(np.any(mu_fric > 0))
        ground = self.scenario.ground_height
        on_cpu = self.device == "cpu"
        candidates = st.line_search_candidates or (1 if on_cpu else 4)
        candidates = min(candidates, st.line_search_steps)
        elastic = _ElasticTerms(self, mu, lam, np.where(np.isfinite(ys), ys, 1e301) if plastic else None,
                                max_rows=max(E_env * candidates, E_env), profile=st.profile_device)
        if any_quad:
            a_fill_t = torch.as_tensor(self._a_fill)                        # host (P, nA)
            m_fill = self.mass
        # state (host, float64)
        Z = np.zeros((E_env, 3, nA))
        V = np.zeros((E_env, 3, nA))
        V[:, :, (H1 - 1) * 4:] = self._initial_affine_velocity()
        newmark = st.integrator == "newmark"
        nm_gamma = 0.5 + NEWMARK_ALPHA
        nm_beta = 0.25 * (nm_gamma + 0.5) ** 2
        w_inertia = 1.0 / nm_beta if newmark else 1.0
        # Newmark's acceleration at the start: gravity and wind alone (at rest no elastic, clamp or contact force)
        Acc = np.linalg.solve(M[None], f_ext.transpose(0, 2, 1)).transpose(0, 2, 1)          # (E, 3, nA)
        Z_frames = np.zeros((T, E_env, 3, nA))
        steps = 0
        newton_total = 0
        extent = self.extent
        tolerance = st.newton_tolerance * extent
        clock.add("set_up", time.perf_counter() - t_begin)
        t_start = time.perf_counter()
        for f in range(1, T):
            interval = self.frame_times[f] - self.frame_times[f - 1]
            n_sub = max(1, math.ceil(interval / st.max_dt - 1e-9))
            dt = interval / n_sub
            kp = st.clamp_stiffness * self.elastic_rate2
            elastic.set_viscosity(eta / dt)
            Hconst = M[None] * (w_inertia / dt ** 2 + lin_drag / dt)[:, None, None]     # (E, nA, nA)
            if clamp:
                Hconst = Hconst + kp * Mpin[None]
            for _ in range(n_sub):
                t0 = time.perf_counter()
                Zn = Z
                Z_hat = Zn + dt * V + ((0.5 - nm_beta) * dt * dt) * Acc if newmark else Zn + dt * V
                # lagged quantities of the step
                Mq = None
                if any_quad:
                    Mq = np.zeros((E_env, nA, nA))
                    for e in np.flatnonzero(quad_drag > 0):
                        speed = np.linalg.norm(_host_matmul(V[e], self._a_fill.T), axis=0)   # (P,) m/s
                        wq = torch.as_tensor(m_fill * quad_drag[e] * speed)
                        Mq[e] = (a_fill_t.T * wq).matmul(a_fill_t).numpy()
                N_lag = None
                if ground is not None:
                    N_lag = kc * np.maximum(ground - (z_col[None] + _host_matmul(Zn[:, 2, :], a_col.T)), 0.0)  # (E, K) N
                terms = _HostTerms(M=M, Mpin=Mpin if clamp else None, kp=kp, dt=dt, Z_hat=Z_hat, Z_start=Zn,
                                   lin_drag=lin_drag, f_ext=f_ext, Mq=Mq, Hconst=Hconst, ground=ground, kc=kc,
                                   cc=cc, a_col=a_col, z_col=z_col, N_lag=N_lag, inertia_weight=w_inertia,
                                   mu_fric=mu_fric if any_fric else None, eps=st.friction_velocity * dt)
                clock.add("host_terms", time.perf_counter() - t0)
                # step start: elastic energy, gradient and Hessian at the predictor
                t0 = time.perf_counter()
                psi, g_el, K_el = elastic.evaluate(Z_hat, envs, hessian=True, Z_start=Zn)
                t1 = time.perf_counter()
                clock.add("hessian_evaluation", t1 - t0)
                phi_h, grad_h = terms.energy_gradient(Z_hat, envs)
                phi = psi + phi_h
                grad = g_el + grad_h
                Z = Z_hat.copy()
                active = np.ones(E_env, bool)
                clock.add("host_terms", time.perf_counter() - t1)
                previous = None          # (env indices, system, factor, next step) of the last iteration
                for it in range(st.newton_iterations):
                    if it > 0 and not st.reuse_hessian:
                        previous = None
                        t0 = time.perf_counter()
                        psi, g_el, K_el = elastic.evaluate(Z, envs, hessian=True)
                        t1 = time.perf_counter()
                        clock.add("hessian_evaluation", t1 - t0)
                        phi_h, grad_h = terms.energy_gradient(Z, envs)
                        phi, grad = psi + phi_h, g_el + grad_h
                        clock.add("host_terms", time.perf_counter() - t1)
                    t0 = time.perf_counter()
                    idx = np.flatnonzero(active)
                    Hm = K_el[idx]
                    terms.add_hessian(Hm, Z[idx], idx)
                    if previous is not None and np.array_equal(previous[1][np.searchsorted(previous[0], idx)], Hm):
                        # same system as the last iteration's (no contact / friction change): its factor
                        # and its convergence check's solve are this iteration's step
                        pos = np.searchsorted(previous[0], idx)
                        factor = previous[2].subset(pos)
                        step = -previous[3][pos]
                    else:
                        factor = _Factor(Hm)
                        step = -factor.solve(grad[idx])                                # (n, 3, nA)
                    slope = np.einsum("eam,eam->e", grad[idx], step)
                    t1 = time.perf_counter()
                    clock.add("newton_solve", t1 - t0)
                    # backtracking line search, `candidates` step lengths per evaluation
                    Zi, phi_i, grad_i = Z[idx], phi[idx], grad[idx]
                    Z_new, phi_new, grad_new = Zi.copy(), phi_i.copy(), grad_i.copy()
                    accepted = np.zeros(len(idx), bool)
                    inner = 0.0
                    for j0 in range(0, st.line_search_steps, candidates):
                        pend = np.flatnonzero(~accepted)
                        alpha = 0.5 ** np.arange(j0, min(j0 + candidates, st.line_search_steps))
                        trial = Zi[pend][None] + alpha[:, None, None, None] * step[pend][None]  # (j, p, 3, nA)
                        rows = trial.reshape(-1, 3, nA)
                        row_env = np.tile(idx[pend], len(alpha))
                        ta = time.perf_counter()
                        psi_t, g_t = elastic.evaluate(rows, row_env)
                        tb = time.perf_counter()
                        clock.add("trial_evaluation", tb - ta)
                        phi_h, grad_h = terms.energy_gradient(rows, row_env)
                        tc = time.perf_counter()
                        clock.add("trial_host_terms", tc - tb)
                        inner += tc - ta
                        phi_t = (psi_t + phi_h).reshape(len(alpha), len(pend))
                        grad_t = (g_t + grad_h).reshape(len(alpha), len(pend), 3, nA)
                        ok = phi_t <= (phi_i[pend] + 1e-4 * alpha[:, None] * slope[pend]
                                       + 1e-12 * np.abs(phi_i[pend]))
                        hit = np.flatnonzero(ok.any(axis=0))
                        first = ok.argmax(axis=0)[hit]
                        Z_new[pend[hit]] = trial[first, hit]
                        phi_new[pend[hit]] = phi_t[first, hit]
                        grad_new[pend[hit]] = grad_t[first, hit]
                        accepted[pend[hit]] = True
                        if accepted.all():
                            break
                    Z[idx], phi[idx], grad[idx] = Z_new, phi_new, grad_new
                    t2 = time.perf_counter()
                    clock.add("line_search_bookkeeping", t2 - t1 - inner)
                    # converged when the next Newton step (predicted with the current factor) is tiny
                    nxt = factor.solve(grad_new)
                    previous = (idx, Hm, factor, nxt)
                    rms = np.sqrt(np.maximum(np.einsum("eam,mn,ean->e", nxt, M, nxt), 0.0) / self.total_mass)
                    newton_total += 1
                    active[idx] = accepted & (rms > tolerance)
                    clock.add("newton_solve", time.perf_counter() - t2)
                    if not active.any():
                        break
                if plastic:
                    t0 = time.perf_counter()
                    elastic.return_map(Z)
                    clock.add("plasticity", time.perf_counter() - t0)
                if newmark:
                    Acc_new = (Z - Z_hat) / (nm_beta * dt * dt)
                    V = V + dt * ((1.0 - nm_gamma) * Acc + nm_gamma * Acc_new)
                    Acc = Acc_new
                else:
                    V = (Z - Zn) / dt
                steps += 1
                if not np.all(np.isfinite(Z)):
                    raise SimulationDiverged(f"the LBS simulation diverged at frame {f} (t = {self.frame_times[f]:.4g} s); "
                                             "use a smaller settings.max_dt")
            Z_frames[f] = Z
            frame_done(progress, 1.0 / max(T - 1, 1), f"LBS frame {f}/{T - 1}")
        t_out = time.perf_counter()
        # outputs: every frame's points from its handle transforms, one GEMM per chunk of frames
        out_track = self._lifted_positions(Z_frames, "tracked")
        if ground is not None:  # the contact law lets samples sink a little: tracked points stay on the plane
            np.maximum(out_track[..., 2], ground, out=out_track[..., 2])
        out_handles = np.ascontiguousarray(self.handle_transforms(Z_frames).astype(np.float32).swapaxes(0, 1))
        out_cub = self._lifted_positions(Z_frames, "cubature") if particle_states else None
        elastic.synchronize()
        t_end = time.perf_counter()
        clock.add("vertex_output", t_end - t_out)
        wall = t_out - t_start
        phases = dict(clock.seconds)
        phases["other"] = max(0.0, (t_end - t_begin) - sum(phases.values()))
        phases["total"] = t_end - t_begin
        evaluation = dict(elastic.seconds)
        results = []
        for e in range(E_env):
            meta = {"steps": steps, "newton_iterations": newton_total, "cubature_points": C, "handles": self.handles,
                    "device": self.device, "wall_s": wall, "skinning_bounds": self.bounds.tolist(),
                    "skinning_params": self.skinning_params.tolist(), "skinning_fitted": self.skinning_fitted,
                    "handle_form": "x = A[X;1] + sum_h w_h(X) D_h[X;1]; A = handle_transforms[:, -1]",
                    "phase_seconds": dict(phases), "evaluation_seconds": dict(evaluation),
                    "evaluations": dict(elastic.counts), "line_search_candidates": candidates,
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

    def _lifted_positions(self, Z_frames: np.ndarray, points: str, chunk_bytes: int = 64 << 20) -> np.ndarray:
        """(E, T, N, 3) float32 m: x = X + Z_t a(X) of the ``"tracked"`` or ``"cubature"`` points for the states
        Z_frames (T, E, 3, nA).

        One GEMM a (N, nA) @ [Z_t0ᵀ ... Z_tkᵀ] (nA, 3k) per chunk of frames (at most ``chunk_bytes`` of
        output), in float32 on the simulation's device.
        """
        import torch

        lifted, rest = {"tracked": (self._a_track, self.tracked_rest), "cubature": (self._a_cub, self.cubature_rest)}[points]
        T, E_env, _, nA = Z_frames.shape
        N = len(rest)
        out = np.empty((E_env, T, N, 3), np.float32)
        if N == 0:
            return out
        dev = self.device
        key = (points, dev)
        if key not in self._device_copies:   # kept between runs: the 100k-vertex basis is 18 MB
            self._device_copies[key] = (torch.as_tensor(np.asarray(lifted, np.float32), device=dev),
                                        torch.as_tensor(np.asarray(rest, np.float32), device=dev))
        a, x = self._device_copies[key]                                                      # (N, nA), (N, 3)
        Zf = torch.as_tensor(np.ascontiguousarray(Z_frames.swapaxes(0, 1)), dtype=torch.float32, device=dev)
        chunk = max(1, chunk_bytes // (12 * N))
        for e in range(E_env):
            for t0 in range(0, T, chunk):
                t1 = min(T, t0 + chunk)
                Zc = Zf[e, t0:t1].reshape((t1 - t0) * 3, nA).T                                  # (nA, [t a])
                pos = torch.matmul(a, Zc).view(N, t1 - t0, 3).permute(1, 0, 2) + x              # (t, N, 3)
                torch.from_numpy(out[e, t0:t1]).copy_(pos)
        return out

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
