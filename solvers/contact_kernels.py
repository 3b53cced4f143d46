"""Warp functions of the ground contact law (:mod:`.contact`), shared by the MPM and spring-mass kernels.

Imported only after :func:`~.warp_runtime.init_warp` (through the kernel modules that use it).
"""

from __future__ import annotations

import warp as wp

from .contact import MAX_CONTACT_RATE, RIGID_GROUND_STIFFNESS

MAX_RATE = wp.constant(MAX_CONTACT_RATE)
RIGID_K = wp.constant(RIGID_GROUND_STIFFNESS)


@wp.func
def rigid_floor(has_ground: int, ground_law: wp.vec3):
    """Whether the plane is there and rigid (``ground_law`` = (k_g Pa/m, c_g Pa·s/m, μ), :mod:`.contact`).

    Only a rigid floor may put a sample back on the plane: a floor that gives (``contact_damping``) stores the
    impact's energy in its spring while the solid sinks into it, and putting the solid back on the plane would
    take that energy away (MPM's soft-floor drop lost its whole rebound so, before 2026-11-25)."""
    return has_ground != 0 and ground_law[0] >= RIGID_K


@wp.func
def rigid_contact_stiffness(beta2: float, p_wave_modulus: float, area: float, size: float):
    """k_r = β² M A / ℓ (N/m): the rigid floor's spring for a sample of contact area A (m²) and size ℓ (m) of a
    material with P-wave modulus M = λ + 2μ (Pa), β² = ``beta2`` (the solver's :data:`.contact.RIGID_CONTACT_BETA`
    squared)."""
    return beta2 * p_wave_modulus * area / size


@wp.func
def ground_contact_impulse(z_low: float, v: wp.vec3, m: float, area: float, size: float, rigid_k: float,
                           rigid_c: float, sample_zeta: float, dt: float, ground: float, stiffness: float,
                           damping: float, mu: float, implicit: int):
    """Impulse (N·s, world frame) of the ground on one contact sample over a step of dt seconds.

    z_low: height (m) of the sample's lowest point at the start of the step; v: its velocity (m/s);
    m: its mass (kg); area: the contact area it stands for (m²); size: its thickness ℓ along the normal (m);
    rigid_k: its rigid-floor spring
    (:func:`rigid_contact_stiffness`, N/m); rigid_c: the Kelvin–Voigt damper of that layer of the solid's own
    material (2η k_r / M, N·s/m; 0 without ``material_damping``); ground: the plane's height (m); stiffness k_g
    (Pa/m, >= RIGID_GROUND_STIFFNESS for the rigid floor), damping c_g (Pa·s/m), mu: Coulomb coefficient.

    Normal: the spring k = min(k_g A, k_r, m (MAX_RATE/dt)²) on the depth and the damper
    min(c_g A + rigid_c k / k_r, m/dt) on the normal speed (explicit: symplectic Euler for the spring; the damper
    can at most stop the sample); zero when the sum would pull.  A sample stands for a layer ℓ thick of the
    solid: when a floor that gives lets the solid sink deeper than that, the samples stacked above the lowest
    one are below the plane too, so each takes only the part of the depth that lies within its own layer,
    min(d, ℓ), and only the sample whose layer straddles the plane (d ≤ ℓ) carries the damper: a column of
    samples then feels k A d and c A ḋ once, as the solid's surface does, not once per submerged layer (the
    independent referee's soft-floor drop, docs/contact.md).  Contacts shallower than ℓ are unaffected.  Tangential: Coulomb, at most μ times the normal impulse and never more than
    stops the sample's sliding.

    implicit (:data:`.contact.SAMPLE_CONTACT_IMPLICIT`): 0 as above; 1 the spring and damper act on the sample's
    depth and normal speed at the end of the step (backward Euler, solved in closed form: the sample's own normal
    motion is one degree of freedom), so neither needs the caps m (MAX_RATE/Δt)² and m/Δt — stable at any Δt, and
    the floor stays as stiff as k_r when the solver's substep is long.
    """
    d = ground - z_low
    if d <= 0.0:
        return wp.vec3(0.0)
    rate = MAX_RATE / dt
    k = wp.min(stiffness * area, rigid_k)
    if implicit == 0:
        k = wp.min(k, m * rate * rate)
    c = float(0.0)
    if d <= size:
        c = damping * area + rigid_c * k / rigid_k
        if stiffness >= RIGID_K:
            c = c + 2.0 * sample_zeta * wp.sqrt(k * m)
        if implicit == 0:
            c = wp.min(c, m / dt)
    fn = float(0.0)
    if implicit != 0 and d <= size:
        # v' = v + Δt fn'/m with fn' = k (d − Δt v') − c v'
        v_end = (v[2] + dt * k * d / m) / (1.0 + dt * (c + dt * k) / m)
        fn = m * (v_end - v[2]) / dt
    else:
        fn = k * wp.min(d, size) - c * v[2]
    if fn <= 0.0:
        return wp.vec3(0.0)
    jn = fn * dt
    j = wp.vec3(0.0, 0.0, jn)
    if mu > 0.0:
        vt = wp.vec3(v[0], v[1], 0.0)
        st = wp.length(vt)
        if st > 0.0:
            jt = wp.min(mu * jn, m * st)
            j = j - vt * (jt / st)
    return j
