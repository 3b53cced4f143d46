"""Warp kernels of the LBS solver: per-cubature-point energy, stress and projected Hessian.

Imported only after :func:`~.warp_runtime.init_warp`.  Arrays are ``[row or env, point]``
in float64; the kernels take the solver's handle-space states Z (3 × nA per row) and form the
deformation gradient F_c = I + Z G_c themselves.  The elastic law is fixed-corotated on the elastic part F_e = F F_p⁻¹ of the
deformation gradient (F_p: the plastic rest-shape change, identity without plasticity)::

    Ψ(F_e) = μ Σ_i (σ_i − 1)² + λ/2 (J − 1)²,   σ: signed singular values, J = σ1 σ2 σ3

Its Hessian is assembled from the analytic eigensystem of isotropic energies (Smith,
de Goes & Kim 2019): three scaling modes U diag(e_k) Vᵀ from the 3×3 Hessian in σ,
three twist modes U (e_i e_jᵀ − e_j e_iᵀ) Vᵀ/√2 with eigenvalue
2μ (1 − 2/(σ_i + σ_j)) + λ (J − 1) σ_k, and three flip modes U (e_i e_jᵀ + e_j e_iᵀ) Vᵀ/√2
with eigenvalue 2μ − λ (J − 1) σ_k.  Negative eigenvalues are clamped to zero, so the
Hessian is positive semi-definite and Newton's direction is a descent direction.

The Kelvin–Voigt term of ``material_damping`` is the incremental potential
(η/dt) ‖sym((F − F_n) F_n⁻¹)‖² per unit volume (F_n: start of the step): its gradient is
the viscous stress 2η sym(∇v) pulled back, its Hessian the six symmetric modes
S_k F_n⁻ᵀ with eigenvalue 2η/dt.
"""

from __future__ import annotations

import warp as wp

from .constitutive import von_mises_hencky_f64

# forward kernels only: nothing differentiates through them (no wp.Tape); the adjoints cost most of the
# module's compile time on an empty kernel cache (LBS 20 s -> 8 s CPU, spring-mass 6.7 s -> 4.5 s)
wp.set_module_options({"enable_backward": False})

vec9d = wp.types.vector(length=9, dtype=wp.float64)
mat99d = wp.types.matrix(shape=(9, 9), dtype=wp.float64)


@wp.func
def flat9(M: wp.mat33d):
    return vec9d(M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1], M[2, 2])


@wp.func
def signed_svd(F: wp.mat33d):
    """Rotation-variant SVD F = U diag(σ) Vᵀ with det U = det V = +1 (σ_3 carries the sign of det F)."""
    U = wp.mat33d()
    S = wp.vec3d()
    V = wp.mat33d()
    wp.svd3(F, U, S, V)
    if wp.determinant(U) < wp.float64(0.0):
        U = wp.mat33d(U[0, 0], U[0, 1], -U[0, 2], U[1, 0], U[1, 1], -U[1, 2], U[2, 0], U[2, 1], -U[2, 2])
        S = wp.vec3d(S[0], S[1], -S[2])
    if wp.determinant(V) < wp.float64(0.0):
        V = wp.mat33d(V[0, 0], V[0, 1], -V[0, 2], V[1, 0], V[1, 1], -V[1, 2], V[2, 0], V[2, 1], -V[2, 2])
        S = wp.vec3d(S[0], S[1], -S[2])
    return U, S, V


@wp.func
def basis33(i: int, j: int):
    M = wp.mat33d()
    M[i, j] = wp.float64(1.0)
    return M


@wp.func
def handle_deformation(Z: wp.array3d(dtype=wp.float64), r: int, G: wp.array3d(dtype=wp.float64), c: int):
    """F = I + Σ_m Z[r, :, m] ⊗ G[c, m, :]: the deformation gradient at cubature point c for state row r."""
    F = wp.identity(n=3, dtype=wp.float64)
    for m in range(G.shape[1]):
        z = wp.vec3d(Z[r, 0, m], Z[r, 1, m], Z[r, 2, m])
        g = wp.vec3d(G[c, m, 0], G[c, m, 1], G[c, m, 2])
        F = F + wp.outer(z, g)
    return F


@wp.kernel
def elastic_terms(Z: wp.array3d(dtype=wp.float64), env: wp.array(dtype=wp.int32),
                  Z_start: wp.array3d(dtype=wp.float64), G: wp.array3d(dtype=wp.float64),
                  plastic_inv: wp.array2d(dtype=wp.mat33d), mu: wp.array2d(dtype=wp.float64),
                  lam: wp.array2d(dtype=wp.float64), volume: wp.array(dtype=wp.float64),
                  visc: wp.array(dtype=wp.float64), need: int,
                  psi: wp.array2d(dtype=wp.float64), P: wp.array3d(dtype=wp.float64), H: wp.array4d(dtype=wp.float64)):
    """Energy (J), first Piola stress × volume (N·m) and PSD Hessian × volume of state row r at cubature point c.

    The deformation gradient is formed here from the handle-space state, F = I + Z_r G_c, so the
    solver uploads only the 3 × nA numbers of each candidate state.  Outputs are laid out for the
    reduction to handle space by GEMMs without any transposing copy:
    P[r, a, 3 c + b] = V ∂Ψ/∂F_ab (gradient: P (3R, 3C) @ G_r (3C, nA)) and
    H[r, a, c, 9 b + 3 x + y] = V ∂²Ψ/∂F_ab ∂F_xy.

    Z: (R, 3, nA) candidate states (handle space; m for the translation columns).  env: (R,) the
    environment of each row.  Z_start: (E, 3, nA) the states at the step start (for the viscous
    term's F_n).  G: (C, nA, 3) 1/m, the deformation-gradient operator.  plastic_inv: (E, C) F_p⁻¹.
    mu, lam: (E, C) Pa.  volume: (C,) m³.  visc: (E,) η/dt in Pa (0 = no damping).
    need: 0 energy only, 1 + stress, 2 + Hessian (then row r writes H[r], so R <= H.shape[0]).
    psi: (R, C) J.  P: (R, 3, 3C).  H: (>= R, 3, C, 27).
    """
    r, c = wp.tid()
    e = env[r]
    Fc = handle_deformation(Z, r, G, c)
    F_prev = wp.identity(n=3, dtype=wp.float64)
    if visc[e] > wp.float64(0.0):
        F_prev = handle_deformation(Z_start, e, G, c)
    Q = plastic_inv[e, c]
    Fe = Fc * Q
    U, S, V = signed_svd(Fe)
    s0 = S[0]
    s1 = S[1]
    s2 = S[2]
    m = mu[e, c]
    l = lam[e, c]
    vol = volume[c]
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    J = s0 * s1 * s2
    energy = m * ((s0 - one) * (s0 - one) + (s1 - one) * (s1 - one) + (s2 - one) * (s2 - one)) \
        + wp.float64(0.5) * l * (J - one) * (J - one)
    eta = visc[e]
    Fninv = wp.mat33d()
    X = wp.mat33d()
    if eta > wp.float64(0.0):
        Fninv = wp.inverse(F_prev)
        X = (Fc - F_prev) * Fninv
        X = wp.float64(0.5) * (X + wp.transpose(X))
        energy = energy + eta * wp.ddot(X, X)
    psi[r, c] = vol * energy
    if need < 1:
        return
    d0 = two * m * (s0 - one) + l * (J - one) * s1 * s2
    d1 = two * m * (s1 - one) + l * (J - one) * s0 * s2
    d2 = two * m * (s2 - one) + l * (J - one) * s0 * s1
    Pe = U * wp.mat33d(d0, wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), d1, wp.float64(0.0),
                       wp.float64(0.0), wp.float64(0.0), d2) * wp.transpose(V)
    Pf = Pe * wp.transpose(Q)
    if eta > wp.float64(0.0):
        Pf = Pf + two * eta * X * wp.transpose(Fninv)
    for a in range(3):
        for b in range(3):
            P[r, a, 3 * c + b] = vol * Pf[a, b]
    if need < 2:
        return
    Hm = mat99d()
    # scaling modes: eigen-decomposition of the 3x3 Hessian in σ
    A = wp.mat33d(two * m + l * s1 * s1 * s2 * s2, l * s2 * (two * J - one), l * s1 * (two * J - one),
                  l * s2 * (two * J - one), two * m + l * s0 * s0 * s2 * s2, l * s0 * (two * J - one),
                  l * s1 * (two * J - one), l * s0 * (two * J - one), two * m + l * s0 * s0 * s1 * s1)
    Qa = wp.mat33d()
    ev = wp.vec3d()
    wp.eig3(A, Qa, ev)
    Vt = wp.transpose(V)
    Qpt = wp.transpose(Q)
    for k in range(3):
        lk = wp.max(ev[k], wp.float64(0.0))
        if lk > wp.float64(0.0):
            Dk = wp.mat33d(Qa[0, k], wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), Qa[1, k], wp.float64(0.0),
                           wp.float64(0.0), wp.float64(0.0), Qa[2, k])
            q = flat9(U * Dk * Vt * Qpt)
            Hm = Hm + lk * wp.outer(q, q)
    inv_sqrt2 = wp.float64(0.7071067811865476)
    for pair in range(3):
        i = 0
        j = 1
        sk = s2
        si = s0
        sj = s1
        if pair == 1:
            i = 0
            j = 2
            sk = s1
            si = s0
            sj = s2
        elif pair == 2:
            i = 1
            j = 2
            sk = s0
            si = s1
            sj = s2
        twist = two * m + l * (J - one) * sk
        ssum = si + sj
        if wp.abs(ssum) > wp.float64(1.0e-12):
            twist = two * m * (one - two / ssum) + l * (J - one) * sk
        flip = two * m - l * (J - one) * sk
        Eij = basis33(i, j)
        Eji = basis33(j, i)
        if twist > wp.float64(0.0):
            q = flat9(inv_sqrt2 * (U * (Eij - Eji) * Vt) * Qpt)
            Hm = Hm + twist * wp.outer(q, q)
        if flip > wp.float64(0.0):
            q = flat9(inv_sqrt2 * (U * (Eij + Eji) * Vt) * Qpt)
            Hm = Hm + flip * wp.outer(q, q)
    if eta > wp.float64(0.0):
        Fnt = wp.transpose(Fninv)
        for a in range(3):
            q = flat9(basis33(a, a) * Fnt)
            Hm = Hm + two * eta * wp.outer(q, q)
        for pair in range(3):
            i = 0
            j = 1
            if pair == 1:
                j = 2
            elif pair == 2:
                i = 1
                j = 2
            q = flat9(inv_sqrt2 * (basis33(i, j) + basis33(j, i)) * Fnt)
            Hm = Hm + two * eta * wp.outer(q, q)
    for a in range(3):
        for b in range(3):
            for x in range(3):
                for y in range(3):
                    H[r, a, c, 9 * b + 3 * x + y] = vol * Hm[3 * a + b, 3 * x + y]


@wp.kernel
def return_map(Z: wp.array3d(dtype=wp.float64), G: wp.array3d(dtype=wp.float64),
               plastic_inv: wp.array2d(dtype=wp.mat33d), mu: wp.array2d(dtype=wp.float64),
               yield_stress: wp.array2d(dtype=wp.float64)):
    """Von Mises return mapping on the Hencky strain of F_e = F F_p⁻¹; updates F_p⁻¹ in place.

    The deviatoric Kirchhoff stress 2μ dev(log Σ) is capped at sqrt(2/3) σ_y (the uniaxial
    yield stress σ_y); the part of the strain past it becomes permanent (F_p⁻¹ ← F⁻¹ F_e,new).

    Z: (E, 3, nA) the accepted states; G: (C, nA, 3); plastic_inv, mu, yield_stress: (E, C).
    """
    e, c = wp.tid()
    ys = yield_stress[e, c]
    if not (ys < wp.float64(1.0e300)):
        return
    Fc = handle_deformation(Z, e, G, c)
    Fe = Fc * plastic_inv[e, c]
    U, S, V = signed_svd(Fe)
    s0 = S[0]
    s1 = S[1]
    s2 = S[2]
    tiny = wp.float64(1.0e-6)
    if s0 < tiny or s1 < tiny or s2 < tiny:
        return  # inverted or collapsed: leave to the elastic law
    eps, dgamma = von_mises_hencky_f64(wp.vec3d(wp.log(s0), wp.log(s1), wp.log(s2)), mu[e, c], ys)
    if not (dgamma > wp.float64(0.0)):
        return
    Snew = wp.mat33d(wp.exp(eps[0]), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.exp(eps[1]),
                     wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.exp(eps[2]))
    Fe_new = U * Snew * wp.transpose(V)
    plastic_inv[e, c] = wp.inverse(Fc) * Fe_new
