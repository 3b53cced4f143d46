"""The LBS skinning network shared by the LBS solver, the model's HyperNetwork and the dataset.

A skinning network maps a point of the *normalised* object (the unit cube
centred at the origin, see :func:`normalise_points`) to the weights of H
handles (default 10)::

    x (3) --fixed layer 1--> h1 (64) --fixed layer 2--> h (64) --last layer--> w (H)

Only the last layer is object-specific: ``H × 64`` weights + ``H`` biases =
**650 parameters** for H = 10 — exactly the vector the paper's HyperNetwork
predicts.  The two hidden layers are fixed for every object (seeded sine
features, SIREN-style, with frequencies that resolve part-sized detail in the
unit cube), so the 64 hidden features form a shared basis and one object's
skinning weights are a linear read-out of it.  A constant handle (weight 1
everywhere) is added by the solver; it carries the object's rigid/affine
motion.

Parameter vector layout (flat float32): ``[W (H×64) row-major, b (H)]``.
"""

from __future__ import annotations

import numpy as np

HIDDEN = 64
"""Width of the fixed hidden layers."""
DEFAULT_HANDLES = 10
"""Number of learned handles (the constant handle is extra)."""
_SEED = 20260413
_OMEGA_FIRST = 6.0
"""First-layer frequency scale (radians per unit of the normalised cube)."""


def param_count(handles: int = DEFAULT_HANDLES, hidden: int = HIDDEN) -> int:
    """Size of the object-specific parameter vector (650 for the defaults)."""
    return handles * hidden + handles


LBS_PARAM_COUNT = param_count()


def _fixed_layers(hidden: int = HIDDEN):
    rng = np.random.default_rng(_SEED)
    W1 = rng.uniform(-1.0, 1.0, (hidden, 3)) * _OMEGA_FIRST
    b1 = rng.uniform(-np.pi, np.pi, hidden)
    bound = np.sqrt(6.0 / hidden)
    W2 = rng.uniform(-bound, bound, (hidden, hidden))
    b2 = rng.uniform(-0.5, 0.5, hidden)
    return W1, b1, W2, b2


_LAYERS = {HIDDEN: _fixed_layers(HIDDEN)}


def normalise_points(points: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Map (N, 3) metres into the normalised cube: centre of ``bounds`` (2, 3) at 0, largest extent 1."""
    bounds = np.asarray(bounds, dtype=np.float64)
    centre = 0.5 * (bounds[0] + bounds[1])
    extent = float(np.max(bounds[1] - bounds[0]))
    if extent <= 0:
        raise ValueError("degenerate bounds")
    return (np.asarray(points, dtype=np.float64) - centre) / extent


def hidden_features(x_normalised: np.ndarray, hidden: int = HIDDEN) -> np.ndarray:
    """(N, 3) normalised points -> (N, hidden) fixed features (the shared basis)."""
    if hidden not in _LAYERS:
        _LAYERS[hidden] = _fixed_layers(hidden)
    W1, b1, W2, b2 = _LAYERS[hidden]
    x = np.asarray(x_normalised, dtype=np.float64)
    h1 = np.sin(x @ W1.T + b1)
    return np.sin(h1 @ W2.T + b2)


def hidden_features_jacobian(x_normalised: np.ndarray, hidden: int = HIDDEN) -> tuple[np.ndarray, np.ndarray]:
    """Features and their spatial derivatives: (N, hidden) and (N, hidden, 3) d(feature)/d(x_normalised).

    Used by the LBS solver for deformation gradients (∇w = W · d(features)/dx).
    """
    if hidden not in _LAYERS:
        _LAYERS[hidden] = _fixed_layers(hidden)
    W1, b1, W2, b2 = _LAYERS[hidden]
    x = np.asarray(x_normalised, dtype=np.float64)
    a1 = x @ W1.T + b1
    h1 = np.sin(a1)
    a2 = h1 @ W2.T + b2
    dh1 = np.cos(a1)[:, :, None] * W1[None, :, :]          # (N, hidden, 3)
    jac = np.cos(a2)[:, :, None] * np.einsum("ij,njk->nik", W2, dh1)
    return np.sin(a2), jac


def split_params(params: np.ndarray, handles: int = DEFAULT_HANDLES, hidden: int = HIDDEN):
    """Flat (650,) vector -> (W (H, hidden), b (H,))."""
    p = np.asarray(params, dtype=np.float64).reshape(-1)
    if p.size != param_count(handles, hidden):
        raise ValueError(f"expected {param_count(handles, hidden)} skinning parameters, got {p.size}")
    return p[: handles * hidden].reshape(handles, hidden), p[handles * hidden:]


def join_params(W: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(W, np.float64).reshape(-1), np.asarray(b, np.float64).reshape(-1)]).astype(np.float32)


def skinning_weights(x_normalised: np.ndarray, params: np.ndarray, handles: int = DEFAULT_HANDLES,
                     hidden: int = HIDDEN) -> np.ndarray:
    """(N, 3) normalised points and the flat parameter vector -> (N, H) handle weights (no constant handle)."""
    W, b = split_params(params, handles, hidden)
    return hidden_features(x_normalised, hidden) @ W.T + b
