"""Data-free fitting of an object's 650 skinning parameters (Simplicits-style).

The skinning network (:mod:`.skinning`) maps a point of the normalised object to H
handle weights through fixed hidden layers and one object-specific linear read-out
θ_h = (W_h, b_h) ∈ R^65 per handle.  A good basis lets the handles' affine transforms
deform the solid *cheaply* (low elastic energy for any transforms) while the handles
stay distinct.  Simplicits trains exactly that: the elastic energy of the solid under
random handle transforms plus an orthogonality loss on the weights.  This module does
it in two stages:

1. **Small-deformation limit, solved exactly.**  For a handle with weight w and a random
   affine transform Z (i.i.d. entries of unit variance), the displacement is
   u = w Z [x̂; 1] and the expected linear-elastic energy density is
   (2μ + λ/2) ‖G‖², with G = ∂(w [x̂; 1])/∂x̂, i.e.::

       E_Z[Ψ] = (2μ + λ/2) ((1 + |x̂|²) |∇w|² + 2 w x̂·∇w + 3 w²)

   Because w is linear in θ, the expected energy over the solid is a quadratic form
   θᵀQθ, and the orthogonality condition (Σ_p V_p w_h w_k / V = δ_hk, and every handle
   orthogonal to the constant handle the solver adds) is θᵀSθ = I, mᵀθ = 0.  Minimising
   the energy under these constraints is the generalised eigenproblem Q θ = s S θ on the
   complement of the constant: the H lowest modes are the handles (smooth, low-frequency
   weight functions — the linear-modes limit of Simplicits).
2. **Simplicits refinement** (``iterations`` > 0): Adam on the finite-deformation loss —
   stable neo-Hookean energy (E- and ν-weighted per point) under random handle
   transforms of size ``transform_scale`` (normalised units) plus
   ``orthogonality_weight`` × (‖W̃ᵀW̃ − I‖² + ‖mean weights‖²), starting from stage 1.

Everything runs in torch on the CPU in well under a few seconds for the default object
(2000 sample points, 10 handles).
"""

from __future__ import annotations

import numpy as np

from ..core.errors import UserError
from ..core.progress import Progress
from . import skinning

DEFAULT_FIT_POINTS = 2000
"""Sample points used by the fit (a deterministic subset of the solid's samples)."""
DEFAULT_FIT_ITERATIONS = 0
"""Refinement steps by default: none — stage 1 is the exact optimum of the expected energy; on a
clamped cantilever the stochastic refinement (100 steps) made the basis stiffer (sag 0.81 of
Euler–Bernoulli instead of 0.95), so it is opt-in."""
REFINE_POINTS = 1000
"""Points used by the stochastic refinement (the exact stage 1 uses up to ``max_points``)."""
DEFAULT_TRANSFORM_SCALE = 0.1
DEFAULT_ORTHOGONALITY_WEIGHT = 10.0


def basis(points_normalised: np.ndarray, hidden: int = skinning.HIDDEN) -> tuple[np.ndarray, np.ndarray]:
    """Read-out basis φ = [features, 1] (N, hidden + 1) and ∇φ (N, hidden + 1, 3) in normalised units."""
    feat, jac = skinning.hidden_features_jacobian(points_normalised, hidden)
    n = len(feat)
    phi = np.concatenate([feat, np.ones((n, 1))], axis=1)
    dphi = np.concatenate([jac, np.zeros((n, 1, 3))], axis=1)
    return phi, dphi


def _stiffness_weight(E: np.ndarray | None, nu: np.ndarray | None, n: int) -> np.ndarray:
    """Per-point 2μ + λ/2 relative to its mean (ones for a homogeneous solid)."""
    if E is None:
        return np.ones(n)
    E = np.asarray(E, np.float64).reshape(-1)
    nu_ = np.full(n, 0.3) if nu is None else np.asarray(nu, np.float64).reshape(-1)
    mu = E / (2 * (1 + nu_))
    lam = E * nu_ / ((1 + nu_) * (1 - 2 * nu_))
    c = 2 * mu + 0.5 * lam
    return c / c.mean()


def modal_skinning(x_hat: np.ndarray, volumes: np.ndarray, stiffness: np.ndarray, handles: int,
                   hidden: int = skinning.HIDDEN) -> np.ndarray:
    """Stage 1: (handles, hidden + 1) read-out rows minimising the expected energy (module docstring)."""
    from scipy.linalg import eigh, null_space

    phi, dphi = basis(x_hat, hidden)
    V = volumes / volumes.sum()
    c = V * stiffness
    jx = np.einsum("nkd,nd->nk", dphi, x_hat)                      # ∇φ · x̂  (N, K)
    r2 = 1.0 + np.sum(x_hat * x_hat, axis=1)
    Q = (np.einsum("n,nkd,nld->kl", c * r2, dphi, dphi)
         + np.einsum("n,nk,nl->kl", c, phi, jx) + np.einsum("n,nk,nl->kl", c, jx, phi)
         + 3.0 * np.einsum("n,nk,nl->kl", c, phi, phi))
    S = np.einsum("n,nk,nl->kl", V, phi, phi)
    m = V @ phi
    N = null_space(m[None, :])                                      # (K, K-1)
    Qr = N.T @ Q @ N
    Sr = N.T @ S @ N
    k = Qr.shape[0]
    Qr = 0.5 * (Qr + Qr.T) + 1e-6 * np.trace(Qr) / k * np.eye(k)
    Sr = 0.5 * (Sr + Sr.T) + 1e-10 * np.trace(Sr) / k * np.eye(k)
    if handles > k:
        raise UserError(f"{handles} handles need at most {k} basis functions; use fewer handles")
    vals, vecs = eigh(Qr, Sr, subset_by_index=[0, handles - 1])
    theta = (N @ vecs).T                                            # (H, K)
    norms = np.sqrt(np.einsum("hk,kl,hl->h", theta, S, theta))
    theta /= norms[:, None]
    # deterministic sign: positive weight at the point of largest |weight|
    w = phi @ theta.T
    sign = np.sign(w[np.argmax(np.abs(w), axis=0), np.arange(handles)])
    return theta * np.where(sign == 0, 1.0, sign)[:, None]


class torch_threads:
    """Run a block with ``n`` torch intra-op threads (restored afterwards).

    Small tensors gain nothing from threads, and on a shared, loaded machine torch's
    thread pool can make them many times slower.
    """

    def __init__(self, n: int = 1):
        self.n = int(n)

    def __enter__(self):
        import torch

        self._prev = torch.get_num_threads()
        if self.n > 0:
            torch.set_num_threads(self.n)
        return self

    def __exit__(self, *exc):
        import torch

        torch.set_num_threads(self._prev)
        return False


class _SimplicitsLoss:
    """Simplicits' loss terms for read-out rows θ (H, K): elastic energy under given handle transforms and
    the orthogonality residual (torch, float64)."""

    def __init__(self, x_hat: np.ndarray, volumes: np.ndarray, E_rel: np.ndarray, nu: np.ndarray, hidden: int):
        import torch

        self.torch = torch
        dt = self.dtype = torch.float64
        phi_np, dphi_np = basis(x_hat, hidden)
        self.phi = torch.tensor(phi_np, dtype=dt)
        self.dphi = torch.tensor(dphi_np, dtype=dt)
        self.xh = torch.tensor(np.concatenate([x_hat, np.ones((len(x_hat), 1))], axis=1), dtype=dt)  # (N, 4)
        self.Vn = torch.tensor(volumes / volumes.sum(), dtype=dt)
        self.mu = torch.tensor(E_rel / (2 * (1 + nu)), dtype=dt)
        self.lam = torch.tensor(E_rel * nu / ((1 + nu) * (1 - 2 * nu)), dtype=dt)
        self.eye4x3 = torch.zeros(4, 3, dtype=dt)
        self.eye4x3[:3, :3] = torch.eye(3, dtype=dt)

    def __call__(self, theta, Z):
        """theta (H, K) tensor, Z (S, H+1, 3, 4) transforms -> (mean elastic energy per unit volume, orthogonality)."""
        torch = self.torch
        dt = self.dtype
        H = theta.shape[0]
        n = len(self.phi)
        w = self.phi @ theta.T                                             # (N, H)
        gw = torch.einsum("nkd,hk->nhd", self.dphi, theta)                  # (N, H, 3)
        w_all = torch.cat([w, torch.ones(n, 1, dtype=dt)], dim=1)           # constant handle last
        gw_all = torch.cat([gw, torch.zeros(n, 1, 3, dtype=dt)], dim=1)
        # G_h = [x̂;1] ∇w_hᵀ + w_h [I;0]   (N, H+1, 4, 3)
        G = self.xh[:, None, :, None] * gw_all[:, :, None, :] + w_all[:, :, None, None] * self.eye4x3
        F = torch.eye(3, dtype=dt) + torch.einsum("shar,nhrb->snab", Z, G)
        J = torch.linalg.det(F)
        Ic = torch.sum(F * F, dim=(-1, -2))
        mu, lam = self.mu, self.lam
        a = 1.0 + mu / lam.clamp_min(1e-12)
        # stable neo-Hookean (Smith et al. 2018), zero at rest, defined for inverted F
        psi = 0.5 * mu * (Ic - 3.0) - mu * (J - 1.0) + 0.5 * lam * (J - a) ** 2 - 0.5 * lam * (a - 1.0) ** 2
        elastic = torch.mean(torch.sum(psi * self.Vn, dim=1))
        Wt = w * torch.sqrt(self.Vn)[:, None]
        orth = torch.sum((Wt.T @ Wt - torch.eye(H, dtype=dt)) ** 2) + torch.sum((self.Vn @ w) ** 2)
        return elastic, orth


def _refine(theta0: np.ndarray, x_hat: np.ndarray, volumes: np.ndarray, E_rel: np.ndarray, nu: np.ndarray,
            iterations: int, transform_scale: float, orthogonality_weight: float, seed: int,
            progress: Progress | None) -> tuple[np.ndarray, list]:
    """Stage 2: Simplicits loss minimised with Adam from ``theta0`` (torch, CPU); 8 random transforms a step."""
    import torch

    loss_fn = _SimplicitsLoss(x_hat, volumes, E_rel, nu, theta0.shape[1] - 1)
    theta = torch.tensor(theta0, dtype=torch.float64, requires_grad=True)
    H = theta0.shape[0]
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam([theta], lr=2e-3)
    history = []
    elastic_scale = None
    for it in range(iterations):
        Z = torch.randn(8, H + 1, 3, 4, generator=gen, dtype=torch.float64) * transform_scale
        elastic, orth = loss_fn(theta, Z)
        if elastic_scale is None:  # the loss is relative to the starting energy (scale-free weighting)
            elastic_scale = float(elastic.detach())
        loss = elastic / elastic_scale + orthogonality_weight * orth
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append((float(elastic.detach()) / elastic_scale, float(orth.detach())))
        if progress is not None and it % 10 == 0:
            progress.set_status(f"skinning fit {it + 1}/{iterations}")
    return theta.detach().numpy(), history


def simplicits_loss(params: np.ndarray, points: np.ndarray, volumes: np.ndarray | None = None,
                    youngs_modulus: np.ndarray | None = None, poisson_ratio: np.ndarray | None = None,
                    bounds: np.ndarray | None = None, handles: int = skinning.DEFAULT_HANDLES, samples: int = 64,
                    transform_scale: float = DEFAULT_TRANSFORM_SCALE, seed: int = 0) -> tuple[float, float]:
    """Simplicits' loss terms of given skinning parameters on a fixed, seeded set of random transforms.

    Returns (mean elastic energy density / transform_scale² — E relative to its mean, orthogonality
    residual); lower is better for both.  Used to compare bases (e.g. before/after refinement).
    """
    import torch

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(pts)
    vol = np.ones(n) if volumes is None else np.asarray(volumes, np.float64).reshape(-1)
    E_rel = np.ones(n) if youngs_modulus is None else np.asarray(youngs_modulus, np.float64) / np.mean(youngs_modulus)
    nu = np.full(n, 0.3) if poisson_ratio is None else np.asarray(poisson_ratio, np.float64).reshape(-1)
    if bounds is None:
        bounds = np.stack([pts.min(0), pts.max(0)])
    W, b = skinning.split_params(params, handles)
    theta = torch.tensor(np.concatenate([W, b[:, None]], axis=1), dtype=torch.float64)
    loss_fn = _SimplicitsLoss(skinning.normalise_points(pts, bounds), vol, E_rel, nu, W.shape[1])
    gen = torch.Generator().manual_seed(seed)
    Z = torch.randn(samples, handles + 1, 3, 4, generator=gen, dtype=torch.float64) * transform_scale
    with torch_threads(1), torch.no_grad():
        elastic, orth = loss_fn(theta, Z)
    return float(elastic) / transform_scale ** 2, float(orth)


def expected_energy(theta: np.ndarray, x_hat: np.ndarray, volumes: np.ndarray, stiffness: np.ndarray) -> np.ndarray:
    """(H,) expected small-deformation energy of each handle (stage 1's objective; lower = smoother)."""
    phi, dphi = basis(x_hat, theta.shape[1] - 1)
    V = volumes / volumes.sum()
    w = phi @ theta.T
    gw = np.einsum("nkd,hk->nhd", dphi, theta)
    g2 = ((1 + np.sum(x_hat ** 2, 1))[:, None] * np.sum(gw ** 2, 2) + 2 * w * np.einsum("nhd,nd->nh", gw, x_hat)
          + 3 * w ** 2)
    return (V * stiffness) @ g2


def fit_skinning(points: np.ndarray, volumes: np.ndarray | None = None, youngs_modulus: np.ndarray | None = None,
                 poisson_ratio: np.ndarray | None = None, bounds: np.ndarray | None = None,
                 handles: int = skinning.DEFAULT_HANDLES, iterations: int = DEFAULT_FIT_ITERATIONS,
                 transform_scale: float = DEFAULT_TRANSFORM_SCALE,
                 orthogonality_weight: float = DEFAULT_ORTHOGONALITY_WEIGHT, max_points: int = DEFAULT_FIT_POINTS,
                 seed: int = 0, progress: Progress | None = None, return_history: bool = False):
    """Fit the object-specific skinning parameters of a solid without any data.

    Parameters
    ----------
    points: (N, 3) metres, samples filling the solid.
    volumes: (N,) m³ each (default equal).
    youngs_modulus / poisson_ratio: (N,) Pa / - per sample (default homogeneous): stiff parts
        get nearly rigid weights.
    bounds: (2, 3) metres, the box that defines the normalised cube (default the points' box;
        the solver passes the body's bounds).
    handles: H learned handles (10 → 650 parameters).
    iterations: Adam steps of the Simplicits refinement (0 = stage 1 only).
    Returns
    -------
    (H·64 + H,) float32 parameters in :mod:`.skinning` layout (and the loss history
    [(elastic, orthogonality), ...] when ``return_history``).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 4 or not np.all(np.isfinite(pts)):
        raise UserError("the skinning fit needs at least 4 finite sample points of the solid")
    if handles < 1:
        raise UserError(f"the skinning fit needs at least one handle, got {handles}")
    n = len(pts)
    vol = np.ones(n) if volumes is None else np.asarray(volumes, np.float64).reshape(-1)
    if vol.shape != (n,) or np.any(vol <= 0):
        raise UserError("skinning fit: volumes must be one positive number per point")
    E = None if youngs_modulus is None else np.asarray(youngs_modulus, np.float64).reshape(-1)
    nu = None if poisson_ratio is None else np.asarray(poisson_ratio, np.float64).reshape(-1)
    for name, arr in (("youngs_modulus", E), ("poisson_ratio", nu)):
        if arr is not None and arr.shape != (n,):
            raise UserError(f"skinning fit: {name} must have one value per point ({n}), got {arr.shape}")
    if bounds is None:
        bounds = np.stack([pts.min(0), pts.max(0)])
    if n > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))
        pts, vol = pts[keep], vol[keep] * (vol.sum() / vol[keep].sum())
        E = None if E is None else E[keep]
        nu = None if nu is None else nu[keep]
    x_hat = skinning.normalise_points(pts, bounds)
    stiff = _stiffness_weight(E, nu, len(pts))
    theta = modal_skinning(x_hat, vol, stiff, handles)
    history: list = []
    if iterations > 0:
        E_rel = np.ones(len(pts)) if E is None else E / E.mean()
        nu_arr = np.full(len(pts), 0.3) if nu is None else nu
        sub = np.sort(np.random.default_rng(seed + 1).choice(len(pts), min(len(pts), REFINE_POINTS), replace=False))
        with torch_threads(1):
            theta, history = _refine(theta, x_hat[sub], vol[sub], E_rel[sub], nu_arr[sub], int(iterations),
                                     float(transform_scale), float(orthogonality_weight), seed, progress)
    params = skinning.join_params(theta[:, :-1], theta[:, -1])
    return (params, history) if return_history else params
