"""Small-deformation statics and vibration modes of a clamped solid on quadratic (10-node) tetrahedra.

Part of the independent referee (:mod:`unipixie.training.independent_fem`); it shares no code with
:mod:`unipixie.solvers`.  Linear tetrahedra lock in bending (a bar needs many of them across its
thickness), so the clamped bars are measured here on quadratic tetrahedra: the linear elements of
:func:`~unipixie.training.independent_fem.box_tet_mesh` get a node on every edge, shape functions
N_i = L_i (2 L_i − 1) at the corners and N_ij = 4 L_i L_j on the edges (L the barycentric coordinates).

* Stiffness: isotropic linear elasticity (λ, μ from E, ν), integrated exactly by the 4-point rule of
  degree 2 (the strain of a quadratic element is linear).
* Mass: the consistent mass matrix ρ ∫ N_a N_b dV, integrated exactly (products of barycentric monomials:
  ∫ L₀^a L₁^b L₂^c L₃^d dV = 6 V a! b! c! d! / (a + b + c + d + 3)!).
* Static deflection under gravity: K u = M g on the free degrees of freedom (sparse LU).
* Modes: K φ = ω² M φ, the lowest few by shift-invert Lanczos (``scipy.sparse.linalg.eigsh``).

The geometry is linear (small deflection): right for a tip sag of a few percent of the length, where the
first nonlinear correction is of order (sag / length)².  SI units throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
import numpy as np

from . import TetMesh, _cof, _det
from .inputs import _check_material

EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))
"""The local edges of a tetrahedron, in the order of the quadratic element's nodes 4..9."""
_QA, _QB = 0.5854101966249685, 0.1381966011250105
QUADRATURE = np.array([[_QA, _QB, _QB, _QB], [_QB, _QA, _QB, _QB], [_QB, _QB, _QA, _QB], [_QB, _QB, _QB, _QA]])
"""(4, 4) barycentric points of the degree-2 rule (weights V/4 each)."""


@dataclass
class QuadraticMesh:
    """nodes: (n, 3) float64 m (corners first, then one node per edge); tets: (m, 10) int64."""

    nodes: np.ndarray
    tets: np.ndarray


def quadratic_mesh(mesh: TetMesh) -> QuadraticMesh:
    """The quadratic mesh of a linear one: one new node at the midpoint of every edge (shared between tets)."""
    T = np.asarray(mesh.tets, dtype=np.int64)
    pairs = np.stack([np.sort(T[:, list(e)], axis=1) for e in EDGES], axis=1)  # (m, 6, 2)
    unique, inverse = np.unique(pairs.reshape(-1, 2), axis=0, return_inverse=True)
    n = len(mesh.nodes)
    mid = 0.5 * (mesh.nodes[unique[:, 0]] + mesh.nodes[unique[:, 1]])
    tets = np.concatenate([T, n + inverse.reshape(-1, 6)], axis=1)
    return QuadraticMesh(np.concatenate([mesh.nodes, mid]), tets)


def _reference_mass() -> np.ndarray:
    """(10, 10) ∫ N_a N_b dV / V for the quadratic tetrahedron, exactly."""
    # each shape function as {exponents (4,): coefficient}
    funcs = []
    for i in range(4):
        e2 = [0] * 4
        e2[i] = 2
        e1 = [0] * 4
        e1[i] = 1
        funcs.append({tuple(e2): 2.0, tuple(e1): -1.0})
    for i, j in EDGES:
        e = [0] * 4
        e[i] += 1
        e[j] += 1
        funcs.append({tuple(e): 4.0})

    def integral(exp):  # ∫ Π L_k^e_k dV / V
        return 6.0 * math.prod(math.factorial(k) for k in exp) / math.factorial(sum(exp) + 3)

    M = np.zeros((10, 10))
    for a in range(10):
        for b in range(10):
            M[a, b] = sum(ca * cb * integral(tuple(x + y for x, y in zip(ea, eb)))
                          for ea, ca in funcs[a].items() for eb, cb in funcs[b].items())
    return M


REFERENCE_MASS = _reference_mass()


def _gradients(qmesh: QuadraticMesh) -> tuple[np.ndarray, np.ndarray]:
    """((m, 4 points, 10, 3) shape-function gradients 1/m at the quadrature points, (m,) volumes m³)."""
    X, T = qmesh.nodes, qmesh.tets
    Dm = np.stack([X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]], X[T[:, 3]] - X[T[:, 0]]], axis=2)
    vol = _det(Dm) / 6.0
    inv = _cof(Dm).transpose(0, 2, 1) / (6.0 * vol)[:, None, None]  # rows: ∇L1, ∇L2, ∇L3
    gL = np.concatenate([-inv.sum(1, keepdims=True), inv], axis=1)  # (m, 4, 3): ∇L0..∇L3
    grads = np.zeros((len(T), 4, 10, 3))
    for q, L in enumerate(QUADRATURE):
        for i in range(4):
            grads[:, q, i] = (4.0 * L[i] - 1.0) * gL[:, i]
        for k, (i, j) in enumerate(EDGES):
            grads[:, q, 4 + k] = 4.0 * (L[i] * gL[:, j] + L[j] * gL[:, i])
    return grads, vol


def assemble(qmesh: QuadraticMesh, material: dict):
    """(K N/m, M kg) sparse (3n, 3n) CSR stiffness and consistent mass; degree of freedom 3 a + i."""
    from scipy import sparse

    E, nu, rho = _check_material(material)
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    grads, vol = _gradients(qmesh)
    if np.any(~(vol > 0)):
        raise ValueError("inverted or degenerate element")
    w = vol / 4.0
    # K_ab,ij = Σ_q w (λ g_a,i g_b,j + μ g_a,j g_b,i + μ δ_ij g_a·g_b)
    Ke = lam * np.einsum("m,mqai,mqbj->maibj", w, grads, grads)
    Ke += mu * np.einsum("m,mqaj,mqbi->maibj", w, grads, grads)
    dot = np.einsum("m,mqak,mqbk->mab", w, grads, grads)
    Ke += mu * dot[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
    T = qmesh.tets
    dof = (3 * T[:, :, None] + np.arange(3)[None, None]).reshape(len(T), 30)
    rows = np.repeat(dof, 30, axis=1).ravel()
    cols = np.tile(dof, (1, 30)).ravel()
    n = 3 * len(qmesh.nodes)
    K = sparse.csr_matrix((Ke.reshape(len(T), 30 * 30).ravel(), (rows, cols)), shape=(n, n))
    Me = (rho * vol)[:, None, None, None, None] * REFERENCE_MASS[None, :, None, :, None] * np.eye(3)[None, None, :, None, :]
    M = sparse.csr_matrix((Me.reshape(len(T), 900).ravel(), (rows, cols)), shape=(n, n))
    return K, M


@dataclass
class ClampedResult:
    """nodes: (n, 3) m of the quadratic mesh; static: (n, 3) m displacement under gravity; frequencies: (k,)
    Hz, lowest first; modes: (k, n, 3) (mass-normalised); dofs: number of free degrees of freedom."""

    nodes: np.ndarray
    static: np.ndarray
    frequencies: np.ndarray
    modes: np.ndarray
    dofs: int


def clamped_response(mesh: TetMesh, material: dict, gravity, pinned: np.ndarray, modes: int = 6) -> ClampedResult:
    """Static deflection under ``gravity`` (3,) m/s² and the lowest ``modes`` vibration modes of the
    quadratic version of ``mesh`` with its corner nodes ``pinned`` (n_linear,) bool held (edge nodes between
    two held corners are held too)."""
    from scipy.sparse.linalg import eigsh, splu

    q = quadratic_mesh(mesh)
    n_lin = len(mesh.nodes)
    T = np.asarray(mesh.tets)
    pairs = np.stack([np.sort(T[:, list(e)], axis=1) for e in EDGES], axis=1).reshape(-1, 2)
    held = np.zeros(len(q.nodes), dtype=bool)
    held[:n_lin] = pinned
    edge_nodes = q.tets[:, 4:].reshape(-1)
    held[edge_nodes[pinned[pairs[:, 0]] & pinned[pairs[:, 1]]]] = True
    K, M = assemble(q, material)
    free = np.repeat(~held, 3)
    Kf = K[free][:, free].tocsc()
    Mf = M[free][:, free].tocsc()
    g = np.tile(np.asarray(gravity, dtype=np.float64), len(q.nodes))
    load = (M @ g)[free]
    lu = splu(Kf)
    u = np.zeros(3 * len(q.nodes))
    u[free] = lu.solve(load)
    from scipy.sparse.linalg import LinearOperator

    op = LinearOperator(Kf.shape, matvec=lu.solve, dtype=np.float64)
    vals, vecs = eigsh(Kf, k=modes, M=Mf, sigma=0.0, which="LM", OPinv=op)
    order = np.argsort(vals)
    vals, vecs = vals[order], vecs[:, order]
    full = np.zeros((modes, 3 * len(q.nodes)))
    full[:, free] = vecs.T
    return ClampedResult(q.nodes, u.reshape(-1, 3), np.sqrt(np.maximum(vals, 0.0)) / (2 * math.pi),
                         full.reshape(modes, -1, 3), int(free.sum()))


__all__ = ["QuadraticMesh", "quadratic_mesh", "assemble", "clamped_response", "ClampedResult", "EDGES"]
