"""Warp functions of the ground contact law (:mod:`.contact`), shared by the MPM and spring-mass kernels.

Imported only after :func:`~.warp_runtime.init_warp` (through the kernel modules that use it).
"""

from __future__ import annotations

import warp as wp

from .contact import MAX_CONTACT_RATE, RIGID_CONTACT_BETA

MAX_RATE = wp.constant(MAX_CONTACT_RATE)
BETA2 = wp.constant(RIGID_CONTACT_BETA * RIGID_CONTACT_BETA)


@wp.func
def rigid_contact_stiffness(p_wave_modulus: float, area: float, size: float):
    """k_r = β² M A / ℓ (N/m): the rigid floor's spring for a sample of contact area A (m²) and size ℓ (m) of a
    material with P-wave modulus M = λ + 2μ (Pa) (:mod:`.contact`)."""
    return BETA2 * p_wave_modulus * area / size


@wp.func
def ground_contact_impulse(z_low: float, v: wp.vec3, m: float, area: float, rigid_k: float, rigid_c: float,
                           dt: float, ground: float, stiffness: float, damping: float, mu: float):
    """Impulse (N·s, world frame) of the ground on one contact sample over a step of dt seconds.

    z_low: height (m) of the sample's lowest point at the start of the step; v: its velocity (m/s);
    m: its mass (kg); area: the contact area it stands for (m²); rigid_k: its rigid-floor spring
    (:func:`rigid_contact_stiffness`, N/m); rigid_c: the Kelvin–Voigt damper of that layer of the solid's own
    material (2η k_r / M, N·s/m; 0 without ``material_damping``); ground: the plane's height (m); stiffness k_g
    (Pa/m, >= 1e30 for the rigid floor), damping c_g (Pa·s/m), mu: Coulomb coefficient.

    Normal: the spring k = min(k_g A, k_r, m (MAX_RATE/dt)²) on the depth and the damper
    min(c_g A + rigid_c k / k_r, m/dt) on the normal speed (explicit: symplectic Euler for the spring; the damper can at most stop the sample); zero
    when the sum would pull.  Tangential: Coulomb, at most μ times the normal impulse and never more than
    stops the sample's sliding.
    """
    d = ground - z_low
    if d <= 0.0:
        return wp.vec3(0.0)
    rate = MAX_RATE / dt
    k = wp.min(wp.min(stiffness * area, rigid_k), m * rate * rate)
    c = wp.min(damping * area + rigid_c * k / rigid_k, m / dt)
    fn = k * d - c * v[2]
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
