"""Spring-mass solver (Spring-Gaus parameterisation) in NVIDIA Warp.

The solid is a network of *anchors* (point masses) joined by springs:

* **Anchors.**  The solid is filled with sample points (:func:`~.sampling.fill_mesh`, or the
  body's own points), thinned by voxel down-sampling and then ordered by farthest-point
  sampling; the first ``anchors`` points (default :data:`.spring_mass_settings.DEFAULT_ANCHORS` = 2048) are the
  anchors.  The order is deterministic — the model's spring head predicts one stiffness per
  anchor in this order.  (``layout="lattice"``: a lattice centred on the bounding box that keeps the body's mirror
  symmetries instead, :mod:`.spring_mass_lattice`.)  Each anchor owns the fill points nearest to it (its Voronoi cell):
  its volume ``V_i`` and mass ``m_i = Σ ρ ΔV`` come from them.
* **Springs.**  Each anchor is joined to its ``neighbours`` nearest anchors (default
  :data:`.spring_mass_settings.DEFAULT_NEIGHBOURS` = 32: in 3D this gives every anchor 30–45 springs, enough for
  the network to resist shear without bending or volume modes of zero energy, while a step
  stays one gather over a few dozen springs).  The directed k-NN lists are merged into one
  undirected spring per pair (Newton's third law; momentum is conserved); a spring's *rank*
  is its lower rank in the two lists (0 = nearest).
* **Stiffness.**  A per-anchor stiffness vector ``k`` ∈ R^{N_a} (newtons) and one global
  softness ``η`` (dimensionless, any real) give the spring constant of spring s = (i, j) of
  rest length L_s::

      κ_s = ½ (k_i + k_j) · w(rank_s; η) / L_s                      [N/m]
      (k_i for both ends when j is a held anchor and i a free one — the free material bonded to a rigid support;
       :meth:`.spring_mass_network.AnchorNetwork.material_ends`)
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
* **Volumetric term** (``volumetric``, on by default).  Each anchor's spring star has the least-squares
  deformation gradient F_i = (Σ_h d_h d0_hᵀ) G_i⁻¹ (G_i = Σ_h d0_h d0_hᵀ, scaled so det F_i = 1 at rest; the
  same star fit as the tracked points' rotations) and stores W_i = ½ V_i λ_extra,i (J_i − 1)², J_i = det F_i.
  With A_i = V_i λ_extra,i (J_i − 1) cof(F_i) G_i⁻¹ (a first pass per substep) the force on anchor i is
  Σ_h (A_i + A_j)(X_j − X_i) over its half-edges (the second, gathering pass: its own star's gradient and that
  of every star it belongs to — the half-edges are symmetric).  The forces of one star sum to zero and exert no
  torque (momentum and angular momentum are conserved); J is rotation invariant, so rigid rotations store no
  energy.  The form (J − 1)² rather than (ln J)²: the same at small strain, but finite for a star squashed
  flat or inverted in a hard impact (ln J has no value at J ≤ 0), which an explicit step must survive.
  Plasticity moves only the springs' rest lengths: the term keeps each star's rest volume (von Mises flow is
  isochoric).
* **Integration.**  Leapfrog: semi-implicit (symplectic) Euler with the velocities kept half a
  substep behind the positions (a half kick v −= Δt/2 a before the first substep, and
  v += (Δt − Δt')/2 a where the substep changes to Δt'), so positions are second-order accurate — a
  free fall is exact instead of drifting by g·t·Δt/2 (the velocities of ``particle_states`` are
  these half-step velocities); the substep is a fraction ``safety`` of
  the stability limit of the stiffest / most damped anchor (Gershgorin bound on M⁻¹K and
  M⁻¹C): ``ω² = max_i (2 Σ_s κ_s + r_i) / m_i``, ``γ = max_i 2 Σ_s c_s / m_i``, r_i the volumetric term's
  per-anchor bound (:meth:`SpringMassSimulation.volume_rows`),
  ``dt ≤ safety · 4 / (γ + sqrt(γ² + 4 ω²))``.  Drags are applied implicitly.  Dashpots are
  explicit, so a strong ``material_damping`` (viscous time ρℓ²/η below the elastic substep,
  roughly η > ℓ sqrt(ρE)) makes the substep shorter in proportion — the cost of the exact
  Kelvin–Voigt rate; implicit one-sweep (Jacobi) alternatives were tried and dropped: they
  saturate and no longer damp in proportion to η (measured on the cantilever test).
* **Contact.**  The ground plane z = h pushes each anchor's cell where its lowest point is below
  the plane (:func:`.contact_kernels.ground_contact_impulse`, the law of :mod:`.contact`): on the
  base model's rigid, frictionless floor a stiff spring per anchor, critically damped
  (:data:`.contact.RIGID_SAMPLE_DAMPING_RATIO`: an anchor that hits the floor stays on it instead
  of bouncing off on its own); ``ground_friction`` removes up to μ × the normal impulse from the
  anchor's tangential velocity (Coulomb, with sticking).  Anchors inside the scenario's
  ``pinned_box`` (the clamp) or of a ``held_fixed`` class (stationary) never move.
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

with E_i the volume mean of E over anchor i's cell (over its fill points of deforming classes where it has any: a
held class's E is no material's).  Σ_{s∋i} w_s L_s assumes the anchor's springs spread evenly
over all directions; in a thin part (a bar or a leaf a few anchors thick) they lie along the part, and the
network is stiffer there (a 0.04 × 0.02 m bar 3 anchors thick stretched 10 % too little).  So the sum is
replaced by the one that fits the anchor's affine stiffness tensor (∝ k_i Σ w L d⊗d⊗d⊗d) to the isotropic
one in least squares, 5 ‖Σ_{s∋i} w L d⊗d⊗d⊗d‖² / Σ_{s∋i} w L (:meth:`.spring_mass_network.AnchorNetwork.fabric_sums`; equal to
Σ w L for evenly spread springs; the bar then stretches within 1 %).  The calibration ``c_E``
(:data:`.spring_mass_settings.STIFFNESS_CALIBRATION`) corrects the affine estimate for the non-affine relaxation
of a disordered network and for the surface; it was measured on a clamped bar under
gravity (static elongation and axial period, both against the continuum) — see
``docs/spring_mass.md``.  Springs alone give ν = 1/4; for the material's ν (cell mean ν_i) the springs are scaled
by 1.25 / (1 + ν_i) (the material's shear modulus μ) and the volumetric term adds λ_extra = λ − μ
(:func:`.spring_mass_network.poisson_split`; ν below 1/4 runs as ν = 1/4, above
:data:`.spring_mass_network.MAX_NETWORK_POISSON_RATIO` = 0.45 as 0.45).  With the model's explicit k the same
holds with E_i = the modulus k stands for (:func:`.spring_mass_network.youngs_modulus_from_stiffness`) and ν_i
from the material field.  Masses: m_i = Σ ρ ΔV over the cell (mass is conserved exactly), then changed as little
as possible so that the network's centre of mass and inertia are the solid's
(:func:`.spring_mass_network.moment_matched_masses`).

**Effects.**
``linear_drag`` / ``quadratic_drag`` / ``wind``: forces on every anchor as the registry says.
``material_damping`` (η_v Pa·s): dashpots on all springs, ``c_s = ½ (d_i + d_j) / L_s`` with
``d_i = c_E · 30 η_v V_i / Σ_{s∋i} L_s`` — the same affine argument with the network's
viscous "shear modulus" S_c / 15 set to η_v (its volumetric part equals the shear part; the
volumetric term has no dashpot); dashpots leave rigid motion alone.
``plasticity`` (σ_y Pa): a spring whose strain exceeds ε_y = σ_y / Ē_s (Ē_s the mean of its
ends' E: the uniaxial yield strain) has its rest length moved so its strain stays at ±ε_y —
permanent deformation.  Classes with von Mises plasticity (metal, plasticine) use their
class yield stress the same way.
``ground_friction`` (μ): Coulomb friction at the ground (above).
``stiffness_region`` (factor): multiplies k_i (and E_i for the yield strain and λ_extra,i) of the
anchors in the region.
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
from .api import Simulation
from .body import Body
from .effects import PhysicsTerms
from .material_sampling import MaterialSpec
from .scenario import Scenario
from .contact import RIGID_CONTACT_BETA, RIGID_GROUND_STIFFNESS
from .spring_mass_lattice import lattice_surface_points
from .spring_mass_network import (MAX_NETWORK_POISSON_RATIO, MIN_STAR_ISOTROPY, NETWORK_POISSON_RATIO, build_network,
                                  p_wave_per_e, poisson_split, softness_weights, stiffness_from_youngs_modulus,
                                  youngs_modulus_from_stiffness)
from .spring_mass_settings import DEFAULT_ANCHORS, DEFAULT_SOFTNESS, SpringMassSettings  # noqa: F401 - DEFAULT_SOFTNESS: public

SPRING_PARAM_COUNT = DEFAULT_ANCHORS + 1
"""Length of the model's spring-mass vector (k ∈ R^{N_a}, η): 2049."""
AFFINE_DASHPOT_FACTOR = 30.0
"""d_i = c_E · 30 η_v V_i / Σ L_s (affine network, viscous shear modulus S_c/15 = η_v)."""
GPU_LANES_PER_ANCHOR = 32
"""Threads (one warp) that gather an anchor's ~40-60 half-edges on a GPU (settings.lanes_per_anchor)."""


# ------------------------------------------------------------------------------------- simulation
class SpringMassSimulation(Simulation):
    """A prepared spring-mass simulation (see the module docstring).

    Public attributes (numpy, SI): ``network`` (:class:`.spring_mass_network.AnchorNetwork`), ``stiffness`` (N,) N,
    ``softness`` η, ``spring_weight`` (S,), ``spring_ends`` (S, 2) the anchors each spring's stiffness, dashpot and
    yield come from (:meth:`.spring_mass_network.AnchorNetwork.material_ends`), ``spring_kappa`` (S,) N/m (base, no effects),
    ``dashpot_unit`` (N,) N·s per Pa·s of ``material_damping`` and ``spring_dashpot_unit`` (S,) N·s/m per Pa·s (the
    dashpots at η = 1), ``youngs_modulus`` (N,) Pa the stiffness stands for, ``poisson_ratio`` (N,) the ν each
    anchor realises, ``spring_factor`` (N,) and ``volume_unit`` (N,) m³ (λ_extra V / E) of the volumetric term,
    ``star_stiffness`` (N,) J (its base star stiffnesses V λ_extra, no effects), ``inv_mass`` (N,) (0 = clamped),
    ``contact_offset`` m (anchors touch the ground this far above it).
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
            self.stiffness = explicit_stiffness_for(settings.stiffness, n, settings.anchors)
            if len(self.stiffness) < len(settings.stiffness):
                self.warnings.append(f"the solid takes {n} of the {settings.anchors} anchors asked (too small or thin "
                                     f"for more); the explicit stiffness's first {n} entries are used")
            self.youngs_modulus = youngs_modulus_from_stiffness(net, self.stiffness, settings)
        else:
            self.stiffness = stiffness_from_youngs_modulus(net, net.E, settings)
            self.youngs_modulus = net.E.copy()
        # Poisson's ratio: springs scaled to the material's shear modulus, the volumetric term adds λ − μ
        # (not for anchors whose star is too flat to measure its volume change)
        self.poisson_ratio = np.full(n, NETWORK_POISSON_RATIO)
        if settings.volumetric:
            self.poisson_ratio = np.clip(net.nu, NETWORK_POISSON_RATIO, MAX_NETWORK_POISSON_RATIO)
            if np.any(net.nu > MAX_NETWORK_POISSON_RATIO):
                self.warnings.append(f"Poisson's ratio up to {float(net.nu.max()):.3g} runs as {MAX_NETWORK_POISSON_RATIO} "
                                     "in the spring-mass network (its explicit substep would shrink as 1/sqrt(1 − 2ν))")
            flat = (net.star_isotropy() < MIN_STAR_ISOTROPY) & (self.poisson_ratio > NETWORK_POISSON_RATIO)
            if np.any(flat):
                self.poisson_ratio[flat] = NETWORK_POISSON_RATIO
                self.warnings.append(f"{int(flat.sum())} of {n} anchors have spring stars too flat to measure a volume "
                                     "change (a part one or two anchors thick): they run with springs only (Poisson "
                                     "ratio 1/4 there); more anchors resolve the part")
        self.spring_factor, lam_per_E = poisson_split(self.poisson_ratio)
        # a held anchor's star has no volumetric stiffness: its class never deforms and its E is no material's (as its
        # springs to free anchors, :meth:`.spring_mass_network.AnchorNetwork.material_ends`)
        self.volume_unit = np.where(net.held, 0.0, lam_per_E * net.volume)
        sl = net.fabric_sums(np.ones(len(net.springs)))
        self.dashpot_unit = settings.stiffness_calibration * AFFINE_DASHPOT_FACTOR * net.volume / np.maximum(sl, 1e-300)
        self.spring_ends = net.material_ends()
        ends = self.spring_ends
        self.spring_dashpot_unit = 0.5 * (self.dashpot_unit[ends[:, 0]] + self.dashpot_unit[ends[:, 1]]) / net.rest_length
        self.spring_kappa = self._kappa(self.stiffness)
        self.star_stiffness = self.volume_unit * self.youngs_modulus
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
        self._slots = self._spring_slots()
        x32 = net.anchors.astype(np.float32)
        self._he_rest_vec = x32[self._he_dst] - x32[self._he_src]  # float32 as the kernels' X_j − X_i
        # rotation fit (Gram matrix inverse per anchor)
        d0 = net.anchors[self._he_dst] - net.anchors[self._he_src]
        gram = np.zeros((n, 3, 3))
        np.add.at(gram, self._he_src, d0[:, :, None] * d0[:, None, :])
        tr = np.trace(gram, axis1=1, axis2=2)
        rest_F = gram.copy()
        gram += (1e-6 * tr + 1e-30)[:, None, None] * np.eye(3)
        self._gram_inv = np.linalg.inv(gram)
        # the regularisation leaves det F ≈ 1 − 1e-5 at rest: scaled so that it is 1 (no pre-stress in the volumetric
        # term; the star rotations are the polar parts, which a positive scale leaves alone)
        rest_J = np.linalg.det(rest_F @ self._gram_inv)
        self._gram_inv *= np.where(rest_J > 1e-12, np.abs(rest_J), 1.0)[:, None, None] ** (-1.0 / 3.0)
        self._vol_bound = self._volume_bound_weights()
        self._spectral_cache: dict[str, float | None] = {}
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

            if self.settings.layout == "lattice":  # mirror images of each other, as the lattice's cells are
                surf = lattice_surface_points(body.mesh, net.fill_points)
            else:
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

    def _spring_slots(self) -> dict:
        """Which end computes each spring's force in a substep (:func:`.spring_mass_kernels.spring_star_pass`).  An
        anchor that moves owns its springs to held anchors and to anchors of a higher index; the owned springs take
        the slots 0, 1, ... in CSR order, so each anchor's are a range; springs between two held anchors (a force
        nobody reads) come last.  Returns int32 arrays ``slot_start`` (N + 1,) the range of each anchor's slots,
        ``slot_nbr`` (S,) the other end, ``slot_he`` (S, 2) the half-edges (CSR) of the owning end and of the other,
        and ``slot_spring`` (S,) each slot's spring (:attr:`.spring_mass_network.AnchorNetwork.springs` row)."""
        src, dst, sid = self._he_src, self._he_dst, self._he_spring
        n = self.network.count
        free = self.inv_mass > 0
        owned = free[src] & (~free[dst] | (src < dst))
        held_pairs = np.setdiff1d(np.arange(len(self.network.springs)), sid[owned])
        slot_spring = np.concatenate([sid[owned], held_pairs])
        ends = np.argsort(sid, kind="stable").reshape(-1, 2)  # the two half-edges of each spring
        swap = owned[ends[:, 1]]
        ends[swap] = ends[swap, ::-1]  # the owner's first
        he_of = ends[slot_spring]
        slot_start = np.concatenate([[0], np.cumsum(np.bincount(src[owned], minlength=n))])
        return {"slot_start": slot_start.astype(np.int32), "slot_nbr": dst[he_of[:, 0]].astype(np.int32),
                "slot_he": he_of.astype(np.int32), "slot_spring": slot_spring}

    def _kappa(self, k_anchor: np.ndarray) -> np.ndarray:
        """(S,) N/m spring constants for per-anchor stiffness (N,) newtons (times each anchor's shear factor
        ``spring_factor``, :func:`.spring_mass_network.poisson_split`)."""
        s = self.spring_ends
        kf = k_anchor * self.spring_factor
        kappa = 0.5 * (kf[s[:, 0]] + kf[s[:, 1]]) * self.spring_weight / self.network.rest_length
        if self.settings.mixing in ("series", "harmonic"):
            # the spring's two halves in series: the harmonic over the arithmetic mean of its ends' moduli (the
            # stiffness per unit E is the anchors' geometry; exactly 1 where both ends have one modulus)
            e = k_anchor / np.maximum(self.stiffness / np.maximum(self.youngs_modulus, 1e-300), 1e-300)
            ei, ej = e[s[:, 0]], e[s[:, 1]]
            kappa = kappa * 4.0 * ei * ej / np.maximum((ei + ej) ** 2, 1e-300)
        return kappa

    def star_volume_gradients(self) -> tuple[np.ndarray, np.ndarray]:
        """The linearised volume change of every anchor star, J_k − 1 ≈ b_k·u: b_k's block g_h = G_k⁻¹ d0_h (H, 3) on
        half-edge h's neighbour j_h, and c_k = −Σ_h g_h (N, 3) on the anchor k itself; 1/m."""
        net = self.network
        d0 = net.anchors[self._he_dst] - net.anchors[self._he_src]
        g = np.einsum("hij,hj->hi", self._gram_inv[self._he_src], d0)
        c = np.zeros((net.count, 3))
        np.add.at(c, self._he_src, -g)
        return g, c

    def _volume_bound_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """Weights of the volumetric term's bound on ω² (:meth:`stable_substep`): (H,) per half-edge and (N,) per
        anchor, 1/m².  Linearised, star k's energy is ½ s_k (b_k·u)² (:meth:`star_volume_gradients`);
        Cauchy–Schwarz with weights ‖b_ka‖ gives uᵀK u ≤ Σ_a ‖u_a‖² Σ_{k∋a} s_k ‖b_ka‖ S_k, S_k = Σ_a ‖b_ka‖ — a
        per-anchor bound like the springs' Gershgorin one, so the two add."""
        n = self.network.count
        g, c = self.star_volume_gradients()
        gn = np.linalg.norm(g, axis=1)
        cn = np.linalg.norm(c, axis=1)
        S = np.bincount(self._he_src, gn, n) + cn
        return gn * S[self._he_src], cn * S

    def volume_rows(self, vol_stiffness: np.ndarray) -> np.ndarray:
        """(N,) N/m: the volumetric term's per-anchor bound Σ_{k∋a} s_k ‖b_ka‖ S_k on ω² m_a for star stiffnesses
        s (N,) J (:meth:`_volume_bound_weights`)."""
        he_w, own_w = self._vol_bound
        s = np.asarray(vol_stiffness, np.float64)
        return s * own_w + np.bincount(self._he_dst, s[self._he_src] * he_w, self.network.count)

    def _upload_static(self):
        wp = self._wp
        dev = self.device
        self._d_start = wp.array(self._he_start, dtype=wp.int32, device=dev)
        self._d_nbr = wp.array(self._he_dst.astype(np.int32), dtype=wp.int32, device=dev)
        slots = self._slots
        self._d_slot_he = wp.array(slots["slot_he"], dtype=wp.int32, device=dev)
        self._d_slot_start = wp.array(slots["slot_start"], dtype=wp.int32, device=dev)
        self._d_slot_nbr = wp.array(slots["slot_nbr"], dtype=wp.int32, device=dev)
        self._d_rest_vec = wp.array(self._he_rest_vec, dtype=wp.vec3, device=dev)
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
        """Per-environment numpy arrays for one set of physics terms: ``kappa`` (N/m), ``dashpot`` (N·s/m),
        ``yield_strain`` in the kernels' spring-slot order (:meth:`_spring_slots`), ``kappa_s``, ``dashpot_s`` per
        spring, ``vol_stiffness`` (N,) J per anchor star."""
        net = self.network
        scale = terms.E_multiplier(net.count)
        kappa_s = self._kappa(self.stiffness * scale)
        s = self.spring_ends
        damp_s = terms.damping_eta * self.spring_dashpot_unit
        E_eff = self.youngs_modulus * scale
        E_s = 0.5 * (E_eff[s[:, 0]] + E_eff[s[:, 1]])
        ys = np.minimum(np.minimum(self.class_yield[s[:, 0]], self.class_yield[s[:, 1]]), terms.yield_stress)
        from .spring_mass_kernels import BIG

        ey = np.where(np.isfinite(ys), ys / E_s, BIG)
        sl = self._slots["slot_spring"]
        return {"kappa": kappa_s[sl], "dashpot": damp_s[sl], "yield_strain": np.minimum(ey, BIG)[sl], "kappa_s": kappa_s,
                "dashpot_s": damp_s, "vol_stiffness": self.volume_unit * E_eff}

    def stable_substep(self, kappa_s: np.ndarray, dashpot_s: np.ndarray, vol_stiffness: np.ndarray | None = None,
                       bound: str | None = None) -> float:
        """Largest stable substep (s) for spring constants (S,) N/m, dashpots (S,) N·s/m and the volumetric term's
        star stiffnesses (N,) J (None: none), times ``safety``: dt = safety · 4 / (γ + sqrt(γ² + 4 ω²)).

        bound: how ω² and γ are bounded (None: ``settings.step_bound``) — ``"spectral"``, the largest eigenvalues of
        M⁻¹K and M⁻¹C of the network at rest (:meth:`spectral_rates`; for constants that are a non-uniform multiple of
        the base ones, the largest multiple times the base eigenvalue, which bounds it); ``"gershgorin"``, the
        per-anchor row sums (2–3 times shorter)."""
        if (bound or self.settings.step_bound) == "spectral":
            rates = self._spectral_bounds(kappa_s, dashpot_s, vol_stiffness)
            if rates is not None:
                omega2, gamma = rates
                if omega2 <= 0 and gamma <= 0:
                    return math.inf
                return self.settings.safety * 4.0 / (gamma + math.sqrt(gamma * gamma + 4.0 * omega2))
        return self._gershgorin_substep(kappa_s, dashpot_s, vol_stiffness)

    def spectral_rates(self, kind: str) -> float | None:
        """The network's largest rate at rest for its base constants (cached; None when ARPACK did not converge):
        ``"stiffness"`` ω²_max (1/s²) of the springs and the volumetric term, ``"springs"`` of the springs alone,
        ``"dashpots"`` γ_max (1/s) of the dashpots per Pa·s of ``material_damping``
        (:func:`.spring_mass_linear.largest_rate_squared`)."""
        if kind not in self._spectral_cache:
            from scipy.sparse.linalg import ArpackNoConvergence

            from . import spring_mass_linear as linear

            zero = np.zeros(self.network.count)
            constants = {"stiffness": (self.spring_kappa, None), "springs": (self.spring_kappa, zero),
                         "dashpots": (self.spring_dashpot_unit, zero)}[kind]
            try:
                self._spectral_cache[kind] = linear.largest_rate_squared(self, linear.stiffness_matrix(self, *constants))
            except ArpackNoConvergence:
                self._spectral_cache[kind] = None
                self.warnings.append("the spring-mass network's highest frequency could not be computed (ARPACK did "
                                     "not converge): the substep comes from the per-anchor (Gershgorin) bound")
        return self._spectral_cache[kind]

    def _spectral_bounds(self, kappa_s, dashpot_s, vol_stiffness) -> tuple[float, float] | None:
        """(ω² 1/s², γ 1/s) bounding the network's rates for these constants, or None (use the Gershgorin bound).
        Each spring's and star's constant is at most r times its base one (r the largest such multiple), so
        K ≤ r K_base in the Loewner order (every spring's and star's rest stiffness is positive semi-definite)
        and ω²_max ≤ r ω²_max,base — exact for a uniform multiple (an E scale, a stiffer fit); likewise γ."""

        def multiple(values, base):
            values = np.asarray(values, np.float64)
            pos = base > 0
            if np.any(values[~pos] > 0):
                return None  # a constant with no base one: no bound from it
            return float(np.max(values[pos] / base[pos], initial=0.0))

        if vol_stiffness is None or not np.any(np.asarray(vol_stiffness) > 0):
            kind, r = "springs", multiple(kappa_s, self.spring_kappa)
        else:
            kind = "stiffness"
            r_k, r_v = multiple(kappa_s, self.spring_kappa), multiple(vol_stiffness, self.star_stiffness)
            r = None if r_k is None or r_v is None else max(r_k, r_v)
        base = self.spectral_rates(kind) if r is not None and r > 0 else 0.0
        if base is None or r is None:
            return None
        gamma = 0.0
        if np.any(np.asarray(dashpot_s) > 0):
            r_c = multiple(dashpot_s, self.spring_dashpot_unit)
            g_base = self.spectral_rates("dashpots") if r_c is not None else None
            if g_base is None:
                return None
            gamma = r_c * g_base
        return r * base, gamma

    def _gershgorin_substep(self, kappa_s: np.ndarray, dashpot_s: np.ndarray, vol_stiffness: np.ndarray | None) -> float:
        """:meth:`stable_substep` from per-anchor row sums: ω² = max_i (2 Σ_s κ_s + r_i) / m_i, γ = max_i 2 Σ_s c_s / m_i."""
        net = self.network
        n = net.count
        s = net.springs
        ksum = np.bincount(s[:, 0], kappa_s, n) + np.bincount(s[:, 1], kappa_s, n)
        if vol_stiffness is not None:
            ksum = ksum + 0.5 * self.volume_rows(vol_stiffness)
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
        env = None if terms is None else self.env_arrays(terms)
        kappa = self.spring_kappa if env is None else env["kappa_s"]
        vol = self.star_stiffness if env is None else env["vol_stiffness"]
        l = np.linalg.norm(x[net.springs[:, 1]] - x[net.springs[:, 0]], axis=1)
        acc = self.scenario.gravity + (0 if terms is None else terms.extra_acceleration)
        kin = 0.5 * float(np.sum(net.mass * np.sum(v * v, axis=1)))
        ela = 0.5 * float(np.sum(kappa * (l - L) ** 2)) + 0.5 * float(np.sum(vol * (self.star_volume_ratio(x) - 1.0) ** 2))
        pot = -float(np.sum(net.mass * (x @ acc)))
        return {"kinetic": kin, "elastic": ela, "potential": pot, "total": kin + ela + pot}

    def star_volume_ratio(self, positions: np.ndarray) -> np.ndarray:
        """(N,) J_i = det F_i of every anchor's spring star (least-squares F, as :func:`.spring_mass_kernels.spring_star_pass`)
        at anchor positions (N, 3) m."""
        net = self.network
        x = np.asarray(positions, np.float64)
        d = x[self._he_dst] - x[self._he_src]
        d0 = net.anchors[self._he_dst] - net.anchors[self._he_src]
        B = np.zeros((net.count, 3, 3))
        np.add.at(B, self._he_src, d[:, :, None] * d0[:, None, :])
        return np.linalg.det(B @ self._gram_inv)

    # -------------------------------------------------------------------------------- running
    @property
    def concurrent_runs(self) -> bool:
        """True on the CPU with one lane per anchor (the default there): its kernels are the plain-launch ones
        (:func:`.spring_mass_kernels.spring_star_pass_serial`, no tile operations, whose CPU scratch memory Warp keeps
        once per process), a run's arrays are its own and the prepared network is only read."""
        return not self._wp.get_device(self.device).is_cuda and (self.settings.lanes_per_anchor or 1) == 1

    def _run_terms(self, terms_list: list[PhysicsTerms], *, progress: Progress | None,
                   particle_states: bool) -> list[Trajectory]:
        """Run the environments at the substep of ``settings.step_bound``; a run that diverges at the spectral bound
        (a deformation stiffer than the network at rest by more than the safety factor leaves room for) is run
        again, whole, at the per-anchor (Gershgorin) bound, and says so in its warnings."""
        try:
            return self._run_terms_at(terms_list, progress=progress, particle_states=particle_states,
                                      bound=self.settings.step_bound)
        except SimulationDiverged:
            if self.settings.step_bound != "spectral" or self.settings.substeps is not None:
                raise
        note = ("the spring-mass run diverged at the substep of the network's highest frequency at rest and was run "
                "again at the shorter per-anchor (Gershgorin) bound")
        return self._run_terms_at(terms_list, progress=progress, particle_states=particle_states, bound="gershgorin",
                                  notes=(note,))

    def _run_terms_at(self, terms_list: list[PhysicsTerms], *, progress: Progress | None, particle_states: bool,
                      bound: str, notes: tuple = ()) -> list[Trajectory]:
        """One run of the environments at the substep of ``bound``; ``notes`` join this run's warnings only."""
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
        dt_max = min(self.stable_substep(e["kappa_s"], e["dashpot_s"], e["vol_stiffness"], bound) for e in envs)
        stack = lambda key: np.stack([e[key] for e in envs]).astype(np.float32)  # noqa: E731
        d_kappa = wp.array(stack("kappa"), dtype=wp.float32, device=dev)
        d_dash = wp.array(stack("dashpot"), dtype=wp.float32, device=dev)
        d_yield = wp.array(stack("yield_strain"), dtype=wp.float32, device=dev)
        damped = int(any(np.any(e["dashpot"] > 0) for e in envs))
        plastic = int(any(np.any(e["yield_strain"] < K.BIG) for e in envs))
        has_volume = int(any(np.any(e["vol_stiffness"] > 0) for e in envs))
        d_vol = wp.array(stack("vol_stiffness"), dtype=wp.float32, device=dev)
        d_stress = wp.zeros((n_env, n), dtype=wp.mat33, device=dev)
        d_force = wp.zeros((n_env, len(self._he_src)), dtype=wp.vec3, device=dev)
        rest0 = net.rest_length[self._slots["slot_spring"]].astype(np.float32)
        d_rest = wp.array(np.tile(rest0, (n_env, 1)), dtype=wp.float32, device=dev)
        accel = np.stack([self.scenario.gravity + t.extra_acceleration for t in terms_list]).astype(np.float32)
        d_accel = wp.array(accel, dtype=wp.vec3, device=dev)
        d_lin = wp.array(np.array([t.linear_drag for t in terms_list], np.float32), dtype=wp.float32, device=dev)
        d_quad = wp.array(np.array([t.quadratic_drag for t in terms_list], np.float32), dtype=wp.float32, device=dev)
        ground_law = np.array([(min(t.ground_stiffness, RIGID_GROUND_STIFFNESS), t.ground_damping, t.friction_mu) for t in terms_list])
        d_ground_law = wp.array(ground_law.astype(np.float32), dtype=wp.vec3, device=dev)
        # each anchor's rigid-floor spring k_r = β² M A / ℓ (solvers/contact.py), M of the network's material
        M = p_wave_per_e(self.poisson_ratio)[None] * self.youngs_modulus[None] * np.stack([t.E_multiplier(n) for t in terms_list])
        rigid_k = RIGID_CONTACT_BETA["spring_mass"] ** 2 * M * (self.contact_area / self.contact_size)[None]
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

        serial = lanes == 1 and not use_graph  # CPU kernels without tile operations (concurrent_runs)

        # the first pass's arrays after the state it reads (the same order in every kernel that runs the pass)
        pass_arrays = [self._d_start, self._d_nbr, self._d_rest_vec, self._d_slot_start, self._d_slot_nbr,
                       self._d_slot_he, d_rest, d_kappa, d_dash, d_yield, self._d_gram_inv, d_vol, d_force, d_stress,
                       damped, plastic]

        def launch_pass(a, record_cmd=False):
            """Launch (or record) a substep's first pass (springs and stars) on buffer a's state."""
            inputs = [bufs[a][0], bufs[a][1], *pass_arrays]
            if serial:
                return wp.launch(K.spring_star_pass_serial, dim=(n_env, n), inputs=inputs, device=dev,
                                 record_cmd=record_cmd)
            return wp.launch_tiled(K.spring_star_pass, dim=(n_env, n), inputs=inputs, device=dev, block_dim=lanes,
                                   record_cmd=record_cmd)

        def launch_substep(a, b, dt, record_cmd=False):
            """Launch (or record) one substep from buffer a to buffer b (its two passes)."""
            inputs = [bufs[a][0], bufs[a][1], bufs[b][0], bufs[b][1], self._d_start, self._d_nbr, d_force,
                      self._d_rest_vec, self._d_inv_mass, self._d_rest_pos, d_accel, d_lin,
                      d_quad, d_ground_law, d_contact_low, self._d_contact_area, d_rigid_k, d_rigid_c, ground,
                      has_ground, d_stress, has_volume, float(dt)]
            return [launch_pass(a, record_cmd), wp.launch_tiled(K.spring_substep, dim=(n_env, n), inputs=inputs,
                                                                device=dev, block_dim=lanes, record_cmd=record_cmd)]

        cmds = []
        if serial:  # every substep pair of a frame in one launch, one thread per environment
            pairs_cmd = wp.launch(K.substep_pairs_serial, dim=(n_env,), device=dev, record_cmd=True, inputs=[
                bufs[0][0], bufs[0][1], bufs[1][0], bufs[1][1], *pass_arrays, self._d_inv_mass, self._d_rest_pos,
                d_accel, d_lin, d_quad, d_ground_law, d_contact_low, self._d_contact_area, d_rigid_k, d_rigid_c,
                ground, has_ground, has_volume, 1e-4, 0])
        elif not use_graph:
            recorded = [launch_substep(a, 1 - a, 1e-4, record_cmd=True) for a in (0, 1)]
            cmds = [c for r in recorded for c in r]
            dt_cmds = [r[-1] for r in recorded]  # the substep launches (the first pass has no dt)
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
            """Leapfrog bookkeeping: v += τ a(x, v) on the current state (buffer 0), positions unchanged (the forces
            come from the first pass before any velocity changes, so the kick is in place)."""
            launch_pass(0)
            wp.launch(K.velocity_kick, dim=(n_env, n), device=dev,
                      inputs=[bufs[0][1], bufs[0][1], self._d_start, self._d_nbr, d_force, self._d_rest_vec,
                              self._d_inv_mass, d_accel, d_lin, d_quad, d_stress, has_volume, float(tau)])

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
            elif serial:
                pairs_cmd.set_param_by_name("dt", float(dt))
                pairs_cmd.set_param_by_name("pairs", n_sub // 2)
                pairs_cmd.launch()
            else:
                for c in dt_cmds:
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
                                         "lower settings.safety, set more substeps or step_bound 'gershgorin'")
            meta = {"substep_s": float(dt_max) if math.isfinite(dt_max) else None, "substeps": total_substeps,
                    "step_bound": bound if self.settings.substeps is None else "fixed",
                    "anchors": n, "layout": self.settings.layout, "springs": int(len(net.springs)),
                    "softness": self.softness,
                    "device": dev, "wall_s": wall, "warnings": list(self.warnings) + list(notes)}
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
    settings = SpringMassSettings.from_any(settings)
    return SpringMassSimulation(body, material, scenario, frame_times, device, settings, progress)


def prepare_with_parameters(body: Body, stiffness: np.ndarray, softness: float, material: MaterialSpec,
                            scenario: Scenario, frame_times, device: str = "cpu", settings=None,
                            progress: Progress | None = None) -> SpringMassSimulation:
    """Run with the spring head's explicit parameters: ``stiffness`` (N_a,) newtons and softness η.

    ``material`` gives the density (masses) and class; its E is not used.
    """
    settings = SpringMassSettings.from_any(settings)
    k = np.asarray(stiffness, dtype=np.float64).reshape(-1)
    fields_ = {f.name: getattr(settings, f.name) for f in fields(SpringMassSettings)}
    fields_.update(stiffness=k, softness=softness, anchors=len(k))
    return prepare(body, material, scenario, frame_times, device=device, settings=SpringMassSettings(**fields_),
                   progress=progress)


def explicit_stiffness_for(stiffness: np.ndarray, anchor_count: int, anchors_asked: int) -> np.ndarray:
    """The explicit per-anchor stiffness (N,) newtons for a network of ``anchor_count`` anchors, from ``stiffness``
    (one entry per anchor asked, FPS order).  A solid too small or thin for the ``anchors_asked`` anchors takes fewer
    (:func:`.spring_mass_network.select_anchors`): it uses the first ``anchor_count`` entries, the ones the spring
    head was trained on for such a solid (its ground truth has that many, :mod:`unipixie.training.train` masks the
    rest).  Any other length is a UserError."""
    k = np.asarray(stiffness, dtype=np.float64).reshape(-1)
    if len(k) == anchor_count:
        return k.copy()
    if len(k) == int(anchors_asked) > anchor_count:
        return k[:anchor_count].copy()
    raise UserError(f"the explicit stiffness vector has {len(k)} entries but the solid has {anchor_count} anchors "
                    f"(settings.anchors = {anchors_asked}); give one per anchor")


def split_parameter_vector(vector: np.ndarray) -> tuple[np.ndarray, float]:
    """The model's (N_a + 1,) vector -> (stiffness (N_a,) newtons, softness η)."""
    v = np.asarray(vector, dtype=np.float64).reshape(-1)
    if v.size < 2:
        raise UserError(f"a spring-mass parameter vector needs N_a stiffnesses + 1 softness, got {v.size} numbers")
    return v[:-1], float(v[-1])
