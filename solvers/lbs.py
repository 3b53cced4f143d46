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
``newton_iterations`` iterations per step (a step they do not converge is retried as two halves:
:data:`MAX_STEP_HALVINGS`), on the incremental potential::

    Φ(Z) = 1/(2β dt²) ‖Z − Ẑ‖²_M + Σ_c V_c Ψ(F_c(Z)) − f_ext·Z + ground contact + clamp penalty + effect terms,
    Ẑ = Z_n + dt Ż_n + (½ − β) dt² Z̈_n

whose minimiser Z_{n+1} gives Z̈_{n+1} = (Z_{n+1} − Ẑ)/(β dt²) and Ż_{n+1} = Ż_n + dt ((1 − γ) Z̈_n + γ Z̈_{n+1}).  Dissipative terms (drags, Kelvin–Voigt viscosity, the ground's damper) act on the
mean velocity of the step (Z − Z_n)/dt, which Newmark's rule makes the midpoint velocity.  (Until this
version the step was backward Euler, whose numerical damping took most of a bounce's energy: docs/lbs.md.)
Ψ is fixed-corotated (:mod:`.lbs_kernels`, with its analytic PSD-projected Hessian).

**Where the work runs.**  Only what scales with the cubature points runs on the Warp device
(:class:`.lbs_terms.ElasticTerms`): one kernel forms F_c = I + Z G_c and evaluates the energy, stress
and (at a step start) the 9×9 Hessian per point, and torch reduces them to handle space with
GEMMs (Σ_c Gᵀ H_c G, 26 M multiply-adds for 500 points: what BLAS / cuBLAS do best).  The
reduced problem — 132 unknowns — stays on the host in float64 numpy (:class:`.lbs_terms.HostTerms`,
:class:`.lbs_terms.CholeskyFactors`): inertia, drags, gravity, clamp, contact and friction, the 132×132 Cholesky
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
from dataclasses import fields

import numpy as np

from ..core.errors import SimulationDiverged, UserError
from ..core.progress import Progress, frame_done
from ..core.types import Trajectory
from . import materials as materials_mod
from . import skinning
from .api import Simulation
from .body import Body
from .effects import PhysicsTerms
from .lbs_fit import fit_skinning, torch_threads
from .lbs_settings import DEFAULT_CUBATURE_POINTS, DEFAULT_MASS_SAMPLES, KEPT_HESSIAN_STEPS_CPU, LBSSettings
from .lbs_terms import CholeskyFactors, ElasticTerms, HostTerms, PhaseClock, host_matmul
from .material_sampling import MaterialSpec, PointMaterial, sample_material
from .contact import IMPLICIT_MAX_CONTACT_RATE, RIGID_CONTACT_BETA
from .sampling import farthest_point_sampling
from .scenario import Scenario
from .spring_mass_network import fill_solid

NEWMARK_ALPHA = 0.02
"""Newmark's γ = ½ + α, β = (γ + ½)²/4.  α = 0 (the average-acceleration rule) conserves the energy of linear
elasticity exactly but let large steps of a bouncing, rotating body gain energy and blow up (a 0.1 m block,
10 handles, 10 ms steps); α = 0.02 damps the vibrations a step does not resolve (per step about α ω Δt of a
mode's amplitude) and kept 10 and 20 ms steps stable; measured cost: a dropped cube's rebound height 1.7 %
lower at the default 5 ms step, 0.3 % at 1 ms (docs/lbs.md)."""

MAX_STEP_HALVINGS = 6
"""A step whose Newton iterations end before converging (``newton_iterations`` used up) is not taken: it is
retried as two half steps, down to ``max_dt`` / 2⁶; the frame's later steps keep the shorter step.  Newmark's
rule is lossless only at the minimiser of Φ: the out-of-balance force of an unconverged step goes into the
carried acceleration Z̈ = (Z − Ẑ)/(β dt²) and feeds the next step, and a stiff rotating body then gains energy
step after step (the demo's duck, parts of 41 MPa at ρ ≈ 300 kg/m³, 5 ms steps: steps stopped 2–13 mm from
their solution in free flight, its kinetic energy went 0.1 → 0.6 J in five steps, then the body flew 10⁶ m
away).  A step still unconverged at the shortest length is taken and counted (``meta["unconverged_steps"]``);
``meta["step_halvings"]`` counts the retries."""
HESSIAN_REUSE_MAX_TURN = 0.01
"""rad: a kept Hessian is evaluated afresh once the body has turned this far since (a corotated Hessian turns with
the body; a stale one still converges, but its convergence test then accepts states further from the solution)."""
KEPT_HESSIAN_TOLERANCE = 0.1
"""With a kept Hessian a step's Newton iterations converge linearly, and its convergence test (the next step it
predicts) is looser than a fresh one's: they stop at this fraction of ``newton_tolerance`` instead (measured on the
clamped bar: 0.05 mm from the fresh Hessian's motion at 1, 0.007 mm at 0.1, for 4 % more Newton iterations)."""
REFRESH_AFTER_ITERATIONS = 2
"""Newton iterations a step may take with a kept Hessian (``hessian_max_age`` > 1) before the next step evaluates
it afresh."""


def _turn_angle(before: np.ndarray | None, after: np.ndarray | None) -> float:
    """Largest angle (rad) between two (E, 3, 3) stacks of rotations (:meth:`LBSSimulation._mean_rotation`);
    infinite where either is missing."""
    if before is None or after is None:
        return math.inf
    R = np.swapaxes(before, 1, 2) @ after
    cos = np.clip(0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0), -1.0, 1.0)
    return float(np.max(np.arccos(cos)))


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
        clock = PhaseClock()
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
        k_rigid = RIGID_CONTACT_BETA["lbs"] ** 2 * M_col * area / self.cubature_spacing
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
        hessian_max_age = st.hessian_max_age or (KEPT_HESSIAN_STEPS_CPU if on_cpu else 1)
        elastic = ElasticTerms(self, mu, lam, np.where(np.isfinite(ys), ys, 1e301) if plastic else None,
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
        halvings = 0
        unconverged = 0
        hconst_dt, Hconst = None, None
        K_kept, kept_age, kept_dt, refresh_next, kept_rotation = None, 0, None, False, None
        extent = self.extent
        tolerance = st.newton_tolerance * extent
        clock.add("set_up", time.perf_counter() - t_begin)
        t_start = time.perf_counter()
        for f in range(1, T):
            interval = self.frame_times[f] - self.frame_times[f - 1]
            n_sub = max(1, math.ceil(interval / st.max_dt - 1e-9))
            kp = st.clamp_stiffness * self.elastic_rate2
            t_left, dt_next = interval, interval / n_sub
            dt_floor = dt_next / 2 ** MAX_STEP_HALVINGS * (1 + 1e-9)
            while t_left > 1e-9 * interval:
                dt = min(dt_next, t_left)
                if dt != hconst_dt:  # the step length changes at a halving and a frame's last piece only
                    elastic.set_viscosity(eta / dt)
                    Hconst = M[None] * (w_inertia / dt ** 2 + lin_drag / dt)[:, None, None]     # (E, nA, nA)
                    if clamp:
                        Hconst = Hconst + kp * Mpin[None]
                    hconst_dt = dt
                t0 = time.perf_counter()
                Zn = Z
                Z_hat = Zn + dt * V + ((0.5 - nm_beta) * dt * dt) * Acc if newmark else Zn + dt * V
                # lagged quantities of the step
                Mq = None
                if any_quad:
                    Mq = np.zeros((E_env, nA, nA))
                    for e in np.flatnonzero(quad_drag > 0):
                        speed = np.linalg.norm(host_matmul(V[e], self._a_fill.T), axis=0)   # (P,) m/s
                        wq = torch.as_tensor(m_fill * quad_drag[e] * speed)
                        Mq[e] = (a_fill_t.T * wq).matmul(a_fill_t).numpy()
                N_lag = None
                if ground is not None:
                    N_lag = kc * np.maximum(ground - (z_col[None] + host_matmul(Zn[:, 2, :], a_col.T)), 0.0)  # (E, K) N
                terms = HostTerms(M=M, Mpin=Mpin if clamp else None, kp=kp, dt=dt, Z_hat=Z_hat, Z_start=Zn,
                                   lin_drag=lin_drag, f_ext=f_ext, Mq=Mq, Hconst=Hconst, ground=ground, kc=kc,
                                   cc=cc, a_col=a_col, z_col=z_col, N_lag=N_lag, inertia_weight=w_inertia,
                                   mu_fric=mu_fric if any_fric else None, eps=st.friction_velocity * dt)
                clock.add("host_terms", time.perf_counter() - t0)
                # step start: elastic energy, gradient and Hessian at the predictor (the Hessian of an earlier
                # step while it still converges the Newton iterations quickly: hessian_max_age)
                t0 = time.perf_counter()
                rotation = self._mean_rotation(Z_hat) if hessian_max_age > 1 else None
                if (K_kept is None or kept_age >= hessian_max_age or abs(dt - kept_dt) > 1e-6 * dt or refresh_next
                        or _turn_angle(kept_rotation, rotation) > HESSIAN_REUSE_MAX_TURN):
                    psi, g_el, K_el = elastic.evaluate(Z_hat, envs, hessian=True, Z_start=Zn)
                    K_kept, kept_age, kept_dt, refresh_next, kept_rotation = K_el, 0, dt, False, rotation
                    step_tolerance = tolerance
                    t1 = time.perf_counter()
                    clock.add("hessian_evaluation", t1 - t0)
                else:
                    psi, g_el = elastic.evaluate(Z_hat, envs, Z_start=Zn)
                    K_el = K_kept
                    step_tolerance = KEPT_HESSIAN_TOLERANCE * tolerance
                    t1 = time.perf_counter()
                    clock.add("trial_evaluation", t1 - t0)
                kept_age += 1
                step_iterations = 0
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
                        factor = CholeskyFactors(Hm)
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
                    step_iterations += 1
                    active[idx] = accepted & (rms > step_tolerance)
                    clock.add("newton_solve", time.perf_counter() - t2)
                    if not active.any():
                        break
                if step_iterations > REFRESH_AFTER_ITERATIONS or active.any():
                    refresh_next = True  # a kept Hessian that slows Newton down is replaced at the next step
                if active.any():
                    if dt > dt_floor:        # not converged: the step is retried as two halves
                        Z = Zn
                        dt_next = 0.5 * dt
                        halvings += 1
                        continue
                    unconverged += 1
                t_left -= dt
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
            meta = {"steps": steps, "newton_iterations": newton_total, "step_halvings": halvings,
                    "unconverged_steps": unconverged, "cubature_points": C, "handles": self.handles,
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

    def _mean_rotation(self, Z: np.ndarray) -> np.ndarray:
        """(E, 3, 3) rotation of each environment's constant handle (the body's mean linear map, polar part) for
        states Z (E, 3, nA)."""
        H = self.handles
        A = Z[:, :, 4 * H:4 * H + 3] / self.extent + np.eye(3)
        U, _, Vt = np.linalg.svd(A)
        return U @ Vt

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
    settings = LBSSettings.from_any(settings)
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
    settings = LBSSettings.from_any(settings)
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
