"""Constitutive laws shared by the solvers' Warp kernels (imported only after :func:`~.warp_runtime.init_warp`).

The material classes' laws (:mod:`.materials`: elasticity and plasticity models) as Warp functions on a
deformation gradient: the fixed-corotated and StVK-Hencky Kirchhoff stresses, the weakly compressible fluid,
the return mappings (von Mises, Drucker–Prager, snow) and :func:`constitutive_update`, which applies one
class's law (:class:`ClassLaw`).  The MPM kernels (:mod:`.mpm_kernels`, :mod:`.mpm_kernels_cuda`) use them in
float32; the von Mises return mapping on the Hencky strain, :func:`von_mises_hencky` (float32) /
:func:`von_mises_hencky_f64`, is also the LBS solver's plasticity (:func:`.lbs_kernels.return_map`).

Units: stresses in Pa (Kirchhoff stress τ = J σ), Lamé parameters μ, λ in Pa, strains dimensionless.
"""

# No ``from __future__ import annotations``: :func:`_von_mises_hencky` gives Warp its argument types at run time.

import math

import warp as wp

from . import materials

wp.set_module_options({"enable_backward": False})

# Constitutive-law codes: positions in the material registry's tuples (one definition).
LAW_FIXED_COROTATED = wp.constant(materials.ELASTICITY_MODELS.index("fixed_corotated"))
LAW_STVK_HENCKY = wp.constant(materials.ELASTICITY_MODELS.index("stvk_hencky"))
LAW_WEAKLY_COMPRESSIBLE = wp.constant(materials.ELASTICITY_MODELS.index("weakly_compressible"))
PLASTIC_NONE = wp.constant(materials.PLASTICITY_MODELS.index("none"))
PLASTIC_VON_MISES = wp.constant(materials.PLASTICITY_MODELS.index("von_mises"))
PLASTIC_DRUCKER_PRAGER = wp.constant(materials.PLASTICITY_MODELS.index("drucker_prager"))
PLASTIC_SNOW = wp.constant(materials.PLASTICITY_MODELS.index("snow"))

MIN_SINGULAR_VALUE = wp.constant(1.0e-4)
"""Lower clamp of singular values before taking logarithms (Hencky strain of inverted cells)."""

MIN_FLUID_J = wp.constant(1.0e-2)
"""Lower clamp of the fluid's volume ratio J (keeps the pressure law finite under extreme compression)."""

ROTATION_ITERATIONS = 1
"""Warm-started rotation-extraction iterations per substep (fast path of the fixed-corotated law)."""


@wp.struct
class ClassLaw:
    """Constitutive and plastic model of one material class (built from the registry)."""

    elastic: int
    plastic: int
    held: int
    yield_stress: float  # Pa, inf when the class has no yield of its own
    softening: float  # yield multiplier exp(-softening * equivalent plastic strain)
    dp_alpha: float  # Drucker-Prager cone coefficient sqrt(2/3) * 2 sin(phi) / (3 - sin(phi))
    theta_c: float
    theta_s: float
    hardening: float
    max_hardening: float


def class_law_table(device):
    """One ClassLaw per registry class (ids are array indices), as a Warp array on ``device``."""
    laws = []
    for c in materials.MATERIAL_CLASSES:
        law = ClassLaw()
        law.elastic = materials.ELASTICITY_MODELS.index(c.elasticity)
        law.plastic = materials.PLASTICITY_MODELS.index(c.plasticity)
        law.held = int(c.held_fixed)
        p = dict(c.params)
        law.yield_stress = float(p.get("yield_stress", math.inf))
        law.softening = float(p.get("softening", 0.0))
        phi = math.radians(float(p.get("friction_angle_deg", 0.0)))
        law.dp_alpha = math.sqrt(2.0 / 3.0) * 2.0 * math.sin(phi) / (3.0 - math.sin(phi))
        law.theta_c = float(p.get("theta_c", 0.0))
        law.theta_s = float(p.get("theta_s", 0.0))
        law.hardening = float(p.get("hardening", 0.0))
        law.max_hardening = float(p.get("max_hardening", math.inf))
        laws.append(law)
    return wp.array(laws, dtype=ClassLaw, device=device)



# ------------------------------------------------------------------------------ return mappings

def _von_mises_hencky(real, vec3):
    """:func:`von_mises_hencky` for the scalar type ``real`` and its 3-vector ``vec3`` (one definition, two
    precisions: float32 for MPM, float64 for LBS)."""

    def von_mises_hencky(eps: vec3, mu: real, yield_stress: real):
        """Von Mises return mapping on the Hencky strain ``eps`` = log of the principal stretches.

        The deviatoric Kirchhoff stress 2μ dev(ε) is capped at sqrt(2/3) σ_y (the uniaxial yield stress σ_y,
        Pa); returns (the strain projected onto the yield surface, the plastic multiplier Δγ = the length of
        the removed deviatoric strain); Δγ = 0 and ``eps`` unchanged inside the surface.
        """
        mean = (eps[0] + eps[1] + eps[2]) / real(3.0)
        dev = eps - vec3(mean)
        norm = wp.length(dev)
        excess = real(2.0) * mu * norm - wp.sqrt(real(2.0) / real(3.0)) * yield_stress
        if excess > real(0.0) and norm > real(1.0e-12):
            dgamma = excess / (real(2.0) * mu)
            return dev * (real(1.0) - dgamma / norm) + vec3(mean), dgamma
        return eps, real(0.0)

    von_mises_hencky.__name__ = von_mises_hencky.__qualname__ = (
        "von_mises_hencky" if real is wp.float32 else f"von_mises_hencky_{real.__name__}")
    return wp.func(von_mises_hencky)


von_mises_hencky = _von_mises_hencky(wp.float32, wp.vec3)
von_mises_hencky_f64 = _von_mises_hencky(wp.float64, wp.vec3d)


# ------------------------------------------------------------------------------ laws
@wp.func
def kirchhoff_fixed_corotated(F: wp.mat33, U: wp.mat33, sig: wp.vec3, V: wp.mat33, mu: float, lam: float):
    """Kirchhoff stress τ = 2μ (F − R) Fᵀ + λ J (J − 1) I of the fixed-corotated model, Pa."""
    J = sig[0] * sig[1] * sig[2]
    R = U @ wp.transpose(V)
    return 2.0 * mu * (F - R) @ wp.transpose(F) + wp.identity(n=3, dtype=float) * (lam * J * (J - 1.0))


@wp.func
def rotation_part(A: wp.mat33, q0: wp.quat):
    """Rotation R of the polar decomposition A = R S, as a unit quaternion, refined from the guess ``q0``.

    Newton iteration on the rotation: with A' = Rᵀ A = Q S and Q ≈ I + [θ]×, the skew part of A'
    gives axial(A' − A'ᵀ) = (tr(S) I − S) θ with S = sym(A'); solve for θ and set R ← R rot(θ),
    where rot(θ) is the rotation of the quaternion (θ/2, 1) normalised (no trigonometric functions;
    its angle agrees with |θ| to third order).  Converges quadratically, so warm-started with the
    previous substep's rotation ``ROTATION_ITERATIONS`` iterations reach float32 round-off.  When
    tr(S) I − S is near-singular (cells close to inversion) the step falls back to θ = axial / tr(S)
    (Müller et al. 2016's rotation-extraction step), which converges to the rotation maximising
    tr(Rᵀ A): the sign-corrected SVD's U Vᵀ the fixed-corotated model needs for inverted cells.
    """
    q = q0
    for _it in range(ROTATION_ITERATIONS):
        Ap = wp.transpose(wp.quat_to_matrix(q)) @ A
        b = wp.vec3(Ap[2, 1] - Ap[1, 2], Ap[0, 2] - Ap[2, 0], Ap[1, 0] - Ap[0, 1])
        S = 0.5 * (Ap + wp.transpose(Ap))
        tr = S[0, 0] + S[1, 1] + S[2, 2]
        M = wp.identity(n=3, dtype=float) * tr - S
        detM = wp.determinant(M)
        theta = b / (wp.abs(tr) + 1.0e-20)
        if wp.abs(detM) > 1.0e-3 * wp.abs(tr * tr * tr):
            theta = wp.inverse(M) @ b
        half = 0.5 * theta
        q = wp.normalize(wp.mul(q, wp.quat(half[0], half[1], half[2], 1.0)))
    return q


@wp.func
def hencky_strain(sig: wp.vec3):
    return wp.vec3(wp.log(wp.max(sig[0], MIN_SINGULAR_VALUE)), wp.log(wp.max(sig[1], MIN_SINGULAR_VALUE)),
                   wp.log(wp.max(sig[2], MIN_SINGULAR_VALUE)))


@wp.func
def kirchhoff_hencky(U: wp.mat33, sig: wp.vec3, mu: float, lam: float):
    """Kirchhoff stress τ = U (2μ ε + λ tr(ε) I) Uᵀ of StVK on the Hencky strain ε = log Σ, Pa."""
    eps = hencky_strain(sig)
    tr = eps[0] + eps[1] + eps[2]
    t = 2.0 * mu * eps + wp.vec3(lam * tr)
    return U @ wp.diag(t) @ wp.transpose(U)


@wp.func
def von_mises_return(sig: wp.vec3, mu: float, yield_stress: float):
    """Project singular values onto the von Mises yield surface of the Hencky model (:func:`von_mises_hencky`).

    Returns (new singular values, plastic multiplier Δγ) packed as vec4; Δγ = 0 inside the surface.
    """
    eps_new, dgamma = von_mises_hencky(hencky_strain(sig), mu, yield_stress)
    if dgamma > 0.0:
        return wp.vec4(wp.exp(eps_new[0]), wp.exp(eps_new[1]), wp.exp(eps_new[2]), dgamma)
    return wp.vec4(sig[0], sig[1], sig[2], 0.0)


@wp.func
def drucker_prager_return(sig: wp.vec3, mu: float, lam: float, alpha: float):
    """Cohesionless Drucker–Prager return mapping on the Hencky strain (Klár et al. 2016).

    Returns (new singular values, 1 if the state was projected else 0) as vec4.
    """
    eps = hencky_strain(sig)
    tr = eps[0] + eps[1] + eps[2]
    if tr >= 0.0:  # extension: a cohesionless material carries no tension, back to the cone's tip
        return wp.vec4(1.0, 1.0, 1.0, 1.0)
    dev = eps - wp.vec3(tr / 3.0)
    norm = wp.length(dev)
    dgamma = norm + (3.0 * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
    if dgamma <= 0.0 or norm <= 1.0e-12:
        return wp.vec4(sig[0], sig[1], sig[2], 0.0)
    eps_new = eps - dev * (dgamma / norm)
    return wp.vec4(wp.exp(eps_new[0]), wp.exp(eps_new[1]), wp.exp(eps_new[2]), 1.0)



@wp.func
def elastic_fixed_corotated(Fn: wp.mat33, q0: wp.quat, mu: float, lam: float):
    """Purely elastic fixed-corotated law without an SVD: (Kirchhoff stress Pa, rotation quaternion, J)."""
    q = rotation_part(Fn, q0)
    R = wp.quat_to_matrix(q)
    J = wp.determinant(Fn)
    tau = 2.0 * mu * (Fn - R) @ wp.transpose(Fn) + wp.identity(n=3, dtype=float) * (lam * J * (J - 1.0))
    return tau, q, J


@wp.func
def constitutive_update(law: ClassLaw, Fn: wp.mat33, q0: wp.quat, state: float, mu: float, lam: float,
                        effect_yield: float):
    """The class's law on the trial deformation gradient ``Fn``.

    Returns (Kirchhoff stress τ Pa, elastic F after the return mapping, rotation quaternion of the
    fast path, plastic state, J).  ``effect_yield`` is the plasticity effect's von Mises yield stress.
    """
    ys = wp.min(law.yield_stress, effect_yield) * wp.exp(-law.softening * state)
    if law.elastic == LAW_FIXED_COROTATED and law.plastic == PLASTIC_NONE and ys >= 1.0e30:
        tau, q, J = elastic_fixed_corotated(Fn, q0, mu, lam)
        return tau, Fn, q, state, J
    if law.elastic == LAW_WEAKLY_COMPRESSIBLE:
        # no tension (p >= 0: a free-surface fluid pulls nothing) and no memory of shear or expansion
        Jf = wp.clamp(wp.determinant(Fn), MIN_FLUID_J, 1.0)
        bulk = lam + 2.0 / 3.0 * mu
        tau_f = wp.identity(n=3, dtype=float) * (bulk * Jf * (Jf - 1.0))
        return tau_f, wp.identity(n=3, dtype=float) * wp.pow(Jf, 1.0 / 3.0), q0, state, Jf
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(Fn, U, sig, V)
    projected = bool(False)
    new_state = state
    mu_e = mu
    lam_e = lam
    if law.plastic == PLASTIC_SNOW:
        clamped = wp.vec3(wp.clamp(sig[0], 1.0 - law.theta_c, 1.0 + law.theta_s),
                          wp.clamp(sig[1], 1.0 - law.theta_c, 1.0 + law.theta_s),
                          wp.clamp(sig[2], 1.0 - law.theta_c, 1.0 + law.theta_s))
        new_state = state * (sig[0] * sig[1] * sig[2]) / (clamped[0] * clamped[1] * clamped[2])
        sig = clamped
        projected = True
        harden = wp.min(wp.exp(law.hardening * (1.0 - new_state)), law.max_hardening)
        mu_e = mu * harden
        lam_e = lam * harden
    elif law.plastic == PLASTIC_DRUCKER_PRAGER:
        r = drucker_prager_return(sig, mu, lam, law.dp_alpha)
        if r[3] > 0.0:
            sig = wp.vec3(r[0], r[1], r[2])
            projected = True
    elif ys < 1.0e30:  # von Mises: the class's own yield (metal, plasticine) or the effect on an elastic class
        r = von_mises_return(sig, mu, ys)
        if r[3] > 0.0:
            sig = wp.vec3(r[0], r[1], r[2])
            new_state = state + wp.sqrt(2.0 / 3.0) * r[3]
            projected = True
    Fe = Fn
    if projected:
        Fe = U @ wp.diag(sig) @ wp.transpose(V)
    J = sig[0] * sig[1] * sig[2]
    tau = wp.mat33(0.0)
    if law.elastic == LAW_FIXED_COROTATED:
        tau = kirchhoff_fixed_corotated(Fe, U, sig, V, mu_e, lam_e)
    else:
        tau = kirchhoff_hencky(U, sig, mu_e, lam_e)
    return tau, Fe, q0, new_state, J

