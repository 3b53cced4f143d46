"""Small-deformation statics and vibration modes of a prepared spring-mass network (:mod:`.spring_mass`).

Linearised about the rest configuration, the network's springs give the stiffness matrix
K = Σ_s κ_s (e_j − e_i)(e_j − e_i)ᵀ ⊗ n_s n_sᵀ (3N × 3N, N/m; n_s the spring's rest direction), the volumetric term
(energy ½ s_k (J_k − 1)² per anchor star, J_k − 1 ≈ tr ∇u_k = b_k·u) adds Σ_k s_k b_k b_kᵀ, and its anchors the
lumped mass matrix M = diag(m_i) ⊗ I₃.  With the pinned anchors held, :func:`static_response` solves K u = M a for a
uniform body acceleration a (gravity) and :func:`vibration_modes` the lowest modes of K φ = ω² M φ.  A tracked point
follows its anchors as in the solver (inverse-distance weights, each anchor's star rotation), linearised:
u_p = Σ_b w_pb (u_b + θ_b × (X_p − X_b)), θ_b the rotation vector of the skew part of the star's least-squares
displacement gradient (:func:`tracked_displacement`).

What it is for: the solver's small-deflection answers (a clamped bar's static sag and bending frequency) in seconds
instead of a time-stepped run — e.g. sweeping the anchor count (docs/spring_mass.md, "Fidelity at the bake
default").  Units: SI (m, kg, N/m, Hz).
"""

from __future__ import annotations

import math

import numpy as np

from ..core.errors import UserError


def volume_gradient_matrix(sim):
    """(N, 3N) scipy CSR, 1/m: row k is b_k, the linearised J_k − 1 = tr ∇u_k of anchor k's star (least-squares
    gradient, as the solver's spring_star_pass): g_h = G_k⁻¹ d0_h on neighbour j_h, −Σ_h g_h on k itself."""
    import scipy.sparse as sp

    n = sim.network.count
    src, dst = sim._he_src, sim._he_dst
    g, own = sim.star_volume_gradients()
    comp = np.arange(3)
    rows = np.concatenate([np.repeat(src, 3), np.repeat(np.arange(n), 3)])
    cols = np.concatenate([(3 * dst[:, None] + comp).ravel(), (3 * np.arange(n)[:, None] + comp).ravel()])
    return sp.csr_matrix((np.concatenate([g.ravel(), own.ravel()]), (rows, cols)), shape=(n, 3 * n))


def stiffness_matrix(sim, spring_constants=None, star_stiffness=None):
    """(3N, 3N) scipy CSR, N/m: the linearised stiffness of ``sim``'s springs (:class:`.spring_mass.SpringMassSimulation`)
    and volumetric term at rest.  Row 3i + c is anchor i's force component c.

    spring_constants: (S,) N/m (None: the base ``spring_kappa``, no effects); star_stiffness: (N,) J, the volumetric
    term's s_k (None: the base ``star_stiffness``).  With the dashpots' constants (N·s/m) and zero star
    stiffness the same assembly is the dashpots' damping matrix."""
    import scipy.sparse as sp

    net = sim.network
    n = net.count
    s = net.springs
    kappa = sim.spring_kappa if spring_constants is None else np.asarray(spring_constants, np.float64)
    d = net.anchors[s[:, 1]] - net.anchors[s[:, 0]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    block = kappa[:, None, None] * d[:, :, None] * d[:, None, :]  # (S, 3, 3)
    rows, cols, vals = [], [], []
    comp = np.arange(3)
    for a, b, sign in ((0, 0, 1.0), (1, 1, 1.0), (0, 1, -1.0), (1, 0, -1.0)):
        r = 3 * s[:, a, None, None] + comp[None, :, None]
        c = 3 * s[:, b, None, None] + comp[None, None, :]
        rows.append(np.broadcast_to(r, block.shape).ravel())
        cols.append(np.broadcast_to(c, block.shape).ravel())
        vals.append((sign * block).ravel())
    K = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n, 3 * n))
    vol = sim.star_stiffness if star_stiffness is None else np.asarray(star_stiffness, np.float64)
    if np.any(vol > 0):
        B = volume_gradient_matrix(sim)
        K = (K + B.T @ sp.diags(vol) @ B).tocsr()
    return K


def largest_rate_squared(sim, matrix) -> float:
    """1/s²: the largest eigenvalue of M⁻¹ ``matrix`` over the free (unpinned) anchors' coordinates — for the stiffness
    matrix (:func:`stiffness_matrix`) the square of the network's highest angular frequency ω_max at rest, for the
    dashpots' damping matrix its largest decay rate γ_max (1/s, not squared).  Lanczos (ARPACK) on the symmetric
    M^(−1/2) K M^(−1/2); 0 when every anchor is pinned or the matrix is zero.  Raises scipy's ArpackNoConvergence when
    the iteration does not converge."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    free = np.repeat(~sim.network.pinned, 3)
    if not free.any():
        return 0.0
    scale = sp.diags(1.0 / np.sqrt(np.repeat(sim.network.mass, 3)[free]))
    A = (scale @ matrix[free][:, free] @ scale).tocsr()
    if A.nnz == 0 or not np.any(A.data):
        return 0.0
    if A.shape[0] <= 3:
        return float(np.linalg.eigvalsh(A.toarray()).max())
    # the start vector is fixed (ARPACK's default is random): the same network gives the same substep every run
    start = np.cos(np.arange(A.shape[0]) * 0.7853981633974483 + 0.3) + 1.5
    return float(sla.eigsh(A, k=1, which="LA", tol=1e-6, v0=start, return_eigenvectors=False)[0])


def _free_dofs(sim) -> np.ndarray:
    free = np.repeat(~sim.network.pinned, 3)
    if not free.any():
        raise UserError("every anchor is pinned: there is nothing to deform")
    if free.all():
        raise UserError("the linear analysis needs a clamp (pinned anchors): an unsupported network has rigid-body "
                        "modes and no static answer")
    return free


def static_response(sim, acceleration) -> np.ndarray:
    """(N, 3) m: the anchors' small static displacement under the uniform body acceleration (3,) m/s² (e.g. the
    scenario's gravity), pinned anchors held at rest."""
    import scipy.sparse.linalg as sla

    a = np.asarray(acceleration, np.float64).reshape(3)
    free = _free_dofs(sim)
    K = stiffness_matrix(sim)[free][:, free].tocsc()
    f = (sim.network.mass[:, None] * a[None, :]).ravel()
    u = np.zeros(3 * sim.network.count)
    u[free] = sla.splu(K).solve(f[free])
    return u.reshape(-1, 3)


def vibration_modes(sim, count: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` lowest vibration modes with the pinned anchors held: frequencies (count,) Hz, ascending, and
    shapes (count, N, 3) (mass-normalised, pinned anchors 0)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    free = _free_dofs(sim)
    count = int(count)
    if not 1 <= count < int(free.sum()):
        raise UserError(f"ask for 1 to {int(free.sum()) - 1} modes, got {count}")
    K = stiffness_matrix(sim)[free][:, free].tocsc()
    M = sp.diags(np.repeat(sim.network.mass, 3)[free])
    lam, vec = sla.eigsh(K, k=count, M=M, sigma=0, which="LM")
    order = np.argsort(lam)
    shapes = np.zeros((count, 3 * sim.network.count))
    shapes[:, free] = vec[:, order].T
    return np.sqrt(np.maximum(lam[order], 0.0)) / (2 * math.pi), shapes.reshape(count, -1, 3)


def tracked_displacement(sim, displacement: np.ndarray) -> np.ndarray:
    """(P, 3) m: the tracked points' displacement for anchor displacements (N, 3) m, through the solver's binding
    linearised (module docstring)."""
    net = sim.network
    u = np.asarray(displacement, np.float64).reshape(net.count, 3)
    d0 = net.anchors[sim._he_dst] - net.anchors[sim._he_src]
    du = u[sim._he_dst] - u[sim._he_src]
    grad = np.zeros((net.count, 3, 3))
    np.add.at(grad, sim._he_src, du[:, :, None] * d0[:, None, :])
    grad = grad @ sim._gram_inv  # least-squares displacement gradient of each anchor's star
    skew = 0.5 * (grad - np.swapaxes(grad, 1, 2))
    theta = np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=1)
    idx, w = sim.binding_index, sim.binding_weight
    arm = sim.tracked_rest[:, None, :] - net.anchors[idx]
    return np.einsum("pb,pbc->pc", w, u[idx] + np.cross(theta[idx], arm))
