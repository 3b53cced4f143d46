"""The ground contact law every solver honours (one definition; kernels in :mod:`.contact_kernels`).

The ground is the plane z = h of the scenario.  Where the solid's surface lies a depth d > 0 below it,
the ground pushes the surface back along +z with the normal traction (force per unit area)::

    p = k_g d + c_g ḋ        (p >= 0: the ground never pulls)

and, with ``ground_friction`` μ, resists sliding with a tangential traction of at most μ p (Coulomb, sticking
below it).  The base model's ground is **rigid and frictionless** (k_g = ∞, c_g = 0, μ = 0): the solid cannot
pass through it and a contact takes no energy.  The ``contact_damping`` effect makes it a damped floor that
gives (finite k_g [Pa/m], c_g [Pa·s/m]).  Being per unit area, the law does not depend on how finely a solver
resolves the solid.

**Why the damper needs the floor to give.**  On a rigid floor the contact surface does not move normal to
the ground while it is pressed (ḋ = 0), so the contact does no work: for an elastic solid every joule of
the impact comes back, partly as rebound and partly as vibration.  Energy can leave an elastic solid at a
contact only through a floor that gives (k_g finite) and damps (c_g > 0), through friction, or in the
solid's own material (``material_damping``, ``plasticity``).  A solver that loses energy at a rigid
contact shows a discretisation artefact, not physics: docs/contact.md measures each solver's and bounds it.

**How the solvers realise the rigid limit.**  Each contact sample (an MPM particle's lower face, a
spring-mass anchor's cell, an LBS collision point) of mass m, contact area A and size ℓ (the spacing of the
solver's samples) feels the normal spring k = min(k_g A, k_r) and the damper c = min(c_g A, m / Δt), where
k_r = β² M A / ℓ (β = :data:`RIGID_CONTACT_BETA` of the solver, M = λ + 2μ the P-wave modulus of the touching material) is
a floor as stiff as a layer of the solid's own material ℓ/β² thick: its contact frequency β c_p / ℓ is one
the solver's resolution represents (a stiffer contact excites motion finer than the solver resolves, whose
energy the solver then loses: measured in docs/contact.md), and the explicit solvers cap it at ω Δt ≤ 1
(symplectic Euler, stable and lossless).  With ``material_damping`` η the layer also carries the
material's Kelvin–Voigt viscosity: the damper 2η k_r / M (the layer's relaxation time 2η/M times its
spring), scaled by k / k_r; without it a reduced model (LBS), whose handles cannot compress the solid
locally, would store an impact's energy in an undamped contact spring and bounce back higher than the
damped continuum.  As the resolution grows (ℓ → 0) the contact converges to the rigid floor; a sample hitting the floor at speed v sinks about v ℓ / (β c_p) into it (a millimetre or less at the
default resolutions and impact speeds below ~2 m/s), and tracked points and baked vertices are put back on the
plane (:func:`clamp_to_ground`).
"""

from __future__ import annotations

import numpy as np

RIGID_CONTACT_BETA = {"mpm": 2.0, "spring_mass": 2.0, "lbs": 2.0}
"""β of each solver's rigid floor, k_r = β² M A / ℓ (module docstring): in every solver the β above which the
canonical drop no longer depends on it (docs/contact.md).  The reduced models' samples lie 10–16 mm apart, so at
β = 0.55 their floor was as soft as a layer of the solid 35–52 mm thick under a 0.2 m cube and gave back the energy
it stored as extra rebound (spring-mass 0.1857, 0.1724, 0.1709, 0.1706 m at β = 0.55, 1.1, 2, 4; LBS 0.1870 m at
0.55, 0.1768 m at 2 and 4).  MPM (since 2026-11-28; 0.55 before): its particles' floor spring is capped at
ω Δt ≤ 1 (:data:`MAX_CONTACT_RATE`), which binds from β ≈ 2 on — rebound 0.1666 / 0.1578 / 0.1556 / 0.1556 m at
β = 0.55 / 1 / 2 / 4 (16 cells across, particle springs undamped), and the stick-slip landing of the diagnosis's ``friction_drop`` the same to
the last digit at 2 and 4.  At 0.55 MPM's floor was a layer 3.3 particle spacings thick of the solid: the canonical
drop rebounded +4.1 / +2.9 / +2.0 % of the independent referee at 16 / 24 / 32 cells, and the cube landing at
1 m/s sideways (μ 0.4, 12 cells) spun on its leading edge and tipped over (88° by 0.6 s) where the referee's rocks back;
at 2 it rocks back (4° at 0.6 s with the critically damped particle springs below), and the drop converges from
below: 0.1551 / 0.1570 / 0.1574 / 0.1583 / 0.1585 m at 16 / 24 / 32 / 48 / 64 cells (−3.1 … −0.9 %), contact 33–34 ms
(one H100, docs/fidelity.md)."""

RIGID_SAMPLE_DAMPING_RATIO = {"mpm": 1.0, "spring_mass": 1.0, "lbs": 0.0}
"""ζ of each contact sample's own spring on the rigid floor (the damper 2 ζ √(k m) on the sample's normal speed, at
most m/Δt: :func:`.contact_kernels.ground_contact_impulse`), per solver using that function (LBS has its own law).

Spring-mass: 1 (critically damped, as the independent referee's penalty contact).  Undamped, each of the lowest
anchors — a sixth of the mass at 192 anchors — bounced off the floor on its own spring while the solid above was
still coming down (4 ms after touchdown of the friction_drop scene their mean vertical speed was +0.77 m/s against
the centre's still −0.8 m/s; 11 sign changes of their vertical speed in the 60 ms impact, 2.5 with ζ = 1), so they were
off the floor, where friction cannot act, for much of the impact: the friction impulse of a sliding cube landing
flat (μ 0.4, 1 m/s, 0.05 m) was 13–16 % below the referee's, and the diagnosis fitted μ 0.62–2 for the truth 0.4
(issue 18, docs/diagnosis.md).  Damped, the canonical drop's rebound converges to the referee's (springs only:
0.1607 / 0.1627 m at 512 / 2048 anchors against 0.1598 m, undamped 0.1709 m at both; with the volumetric term
0.1562 / 0.1588 / 0.1593 m at 512 / 2048 / 8192 against the symmetric referee's 0.1600 m, docs/spring_mass.md);
at 192 anchors the bottom layer's normal energy is lost at the impact (0.1480 m, springs only).  MPM: 1 as well
(since 2026-11-28; 0 before, when its floor was β = 0.55).  On the stiffer floor (β = 2) undamped particle springs
let the lowest layer chatter on coarse grids: the canonical drop's lowest tracked point left the floor after 2 / 1 ms
at 8 / 10 cells across (the solid's contact lasts 33 ms); critically damped, 33 / 34 / 34 / 33 ms at 8 / 10 / 12 /
16 cells, rebound 0.1505 / 0.1511 / 0.1531 / 0.1551 m (0.1535 / 0.1516 / 0.1540 / 0.1556 undamped), and the
friction_drop landing keeps 0.204 m/s of its 1 m/s (referee 0.217) and rocks back."""

SAMPLE_CONTACT_IMPLICIT = {"mpm": 0, "spring_mass": 1}
"""Whether each contact sample takes the ground's normal spring and damper implicitly (1: at the end of the step,
:func:`.contact_kernels.ground_contact_impulse`), per solver using that function.

Spring-mass: 1.  Its substep comes from the network's highest frequency at rest (``step_bound`` "spectral",
:mod:`.spring_mass`), 2.2–2.4 times the per-anchor bound it had; at that step an anchor's floor spring k_r (β = 2)
has ω Δt 2.4–3.1 and its critical damper twice that, so explicitly they were capped at ω Δt = 1 and c = m/Δt — a
floor that changes with the step: the canonical drop rebounded 0.1551 / 0.1597 m at 512 / 2048 anchors at the
long step against 0.1562 / 0.1588 m at the short one.  Implicit, the floor keeps k_r at any step (0.1575 / 0.1605
against 0.1578 / 0.1606 m).  MPM: 0 (its figures were measured with the explicit law)."""

RIGID_GROUND_STIFFNESS = 1.0e30
"""Pa/m: a ground stiffness k_g at or above this is the rigid floor (the solvers' kernels carry k_g = ∞ as this)."""

MAX_CONTACT_RATE = 1.0
"""Largest ω Δt of a contact spring in the explicit solvers (symplectic Euler is stable below 2)."""

IMPLICIT_MAX_CONTACT_RATE = 2.0
"""Largest ω Δt of a contact spring in LBS's implicit Newmark step, whose energy a stiffer contact switched on
and off within a step does not conserve (a duck of 35 MPa parts dropped at 5 ms steps, ω Δt ~ 100, flew off;
capped at 2 or 4 it bounces below its drop height, and the drop scene's rebound is the same as uncapped)."""

PENETRATION_TOLERANCE = 1.0e-3
"""m: no tracked point or baked vertex may end up further below the ground plane than this (tested)."""


def clamp_to_ground(positions: np.ndarray, ground_height: float | None) -> np.ndarray:
    """Positions (..., 3) m with every z below the ground plane put on it (a copy; unchanged without ground)."""
    pos = np.array(positions, copy=True)
    if ground_height is not None:
        np.maximum(pos[..., 2], ground_height, out=pos[..., 2])
    return pos
