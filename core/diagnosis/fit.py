"""Bounded least-squares fitting of effect and base parameters with batched simulations.

The diagnosis fits a few parameters at a time — the base material's E/ρ scale and the
parameters of one or more effects — by minimising the squared distance between simulated
and measured tracked points.  Each simulation is expensive and every solver can run several
parameter sets in one batched launch (``Simulation.run_batch``), so the optimiser here is
written around batches:

* a **projected Levenberg–Marquardt** method (:func:`levenberg_marquardt`): the Jacobian by
  forward finite differences (all p perturbed parameter sets in one batch, stepping inward
  at a bound), then three trial steps for three damping values in a second batch; the best
  trial is kept.  Parameters held at a bound by the gradient are frozen for the step
  (active set).  Converges when the relative cost decrease falls below ``ftol``.
* **start grids** (:func:`grid_search`): every start in one batch; LM starts from the best.

Parameters are fitted in internal coordinates: ``log`` of the value for scale parameters
(registry ``log_scale``; a floor stands for "off" when the registry's lower bound is 0) and
``value / scale`` for linear ones, so one finite-difference step suits every parameter.

The mapping from internal vectors to effect lists is a :class:`Parametrisation`: a set of
:class:`FreeParam` s, each pointing into one effect (or the base E scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from ...solvers import effects as fx
from ..progress import Progress

BASE = "base"
"""Slot name of the base material's Young's-modulus scale (E/ρ, see :mod:`.diagnose`)."""


# --------------------------------------------------------------------------- parameters
@dataclass
class FreeParam:
    """One scalar coordinate of a fit.

    slot: ``BASE`` or the index of the effect in the parametrisation's effect list.
    name: parameter name (``"E_scale"`` for the base), component: index into a vector parameter.
    lower / upper: physical bounds.  log: fitted as log(value).  scale: unit of the internal
    coordinate for linear parameters.  floor: for log parameters whose lower bound is 0, the
    value that stands for "off".  step: finite-difference step in internal units.
    """

    slot: object
    name: str
    component: int = 0
    lower: float = -math.inf
    upper: float = math.inf
    log: bool = False
    scale: float = 1.0
    floor: float = 0.0
    step: float = 0.02
    prior_width: float = 0.0
    """> 0: a weak prior keeps the parameter near its reference value where the data do not
    constrain it: a pseudo-residual σ·(u − u_ref)/prior_width joins the fit (internal units)."""
    prior_center: float = 0.0

    @property
    def label(self) -> str:
        base = "E/ρ scale" if self.slot == BASE else self.name
        return base if self.component == 0 and self.name != "acceleration" else f"{base}[{'xyz'[self.component]}]"

    def to_internal(self, value: float) -> float:
        if self.log:
            return math.log(max(value, self.internal_lower_value()))
        return value / self.scale

    def to_value(self, u: float) -> float:
        if self.log:
            v = math.exp(u)
            return 0.0 if (self.lower <= 0 and v <= self.floor * (1 + 1e-9)) else v
        return u * self.scale

    def internal_lower_value(self) -> float:
        return max(self.lower, self.floor) if self.log else self.lower

    def internal_bounds(self) -> tuple[float, float]:
        if self.log:
            return math.log(self.internal_lower_value()), math.log(self.upper)
        return self.lower / self.scale, self.upper / self.scale


@dataclass
class Parametrisation:
    """Maps internal parameter vectors to (base E scale, effect list).

    effects: the effect templates (current values); params: the free coordinates.
    fixed: effects that are on but not fitted (the user's ``--effects-on``).
    base_scale: the E scale used when the base is not a free parameter.
    """

    effects: list
    params: list
    fixed: list = field(default_factory=list)
    base_scale: float = 1.0

    @property
    def size(self) -> int:
        return len(self.params)

    def internal(self) -> np.ndarray:
        """The current values in internal coordinates."""
        out = []
        for p in self.params:
            if p.slot == BASE:
                out.append(p.to_internal(self.base_scale))
            else:
                v = np.atleast_1d(np.asarray(self.effects[p.slot].values[p.name], dtype=np.float64))
                out.append(p.to_internal(float(v[p.component])))
        return np.asarray(out)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        b = [p.internal_bounds() for p in self.params]
        return np.array([x[0] for x in b]), np.array([x[1] for x in b])

    def steps(self) -> np.ndarray:
        return np.array([p.step for p in self.params])

    def realise(self, u: Sequence[float]) -> tuple[float, list]:
        """Internal vector -> (E scale, fitted effects list) — does not include ``fixed``."""
        u = np.asarray(u, dtype=np.float64)
        scale = self.base_scale
        values = [dict(e.values) for e in self.effects]
        for p, x in zip(self.params, u):
            v = p.to_value(float(x))
            v = min(max(v, p.lower), p.upper)
            if p.slot == BASE:
                scale = v
            else:
                cur = values[p.slot][p.name]
                if np.ndim(cur) == 0:
                    values[p.slot][p.name] = v
                else:
                    arr = np.array(cur, dtype=np.float64)
                    arr[p.component] = v
                    values[p.slot][p.name] = arr
        effs = [type(e)(**vals) for e, vals in zip(self.effects, values)]
        return scale, effs

    def with_internal(self, u: Sequence[float]) -> "Parametrisation":
        """A copy whose current values are ``u`` (used to chain fits)."""
        scale, effs = self.realise(u)
        return Parametrisation(effs, list(self.params), list(self.fixed), scale)


# --------------------------------------------------------------------------- results
@dataclass
class FitResult:
    """Outcome of a fit.

    u: internal optimum; cost: squared residual norm (m²) at it; residual: the residual vector;
    jacobian: (M, p) last finite-difference Jacobian (internal units) or ``None``;
    evaluations: simulations run; iterations: LM iterations; converged: cost change below tol.
    """

    u: np.ndarray
    cost: float
    residual: np.ndarray
    jacobian: Optional[np.ndarray] = None
    evaluations: int = 0
    iterations: int = 0
    converged: bool = False
    trace: list = field(default_factory=list)

    def covariance(self, sigma2: float) -> Optional[np.ndarray]:
        """(p, p) covariance of the internal parameters, σ² (JᵀJ)⁻¹ (pseudo-inverse), or ``None``."""
        if self.jacobian is None or self.jacobian.size == 0:
            return None
        H = self.jacobian.T @ self.jacobian
        return sigma2 * np.linalg.pinv(H, rcond=1e-10)


ResidualBatch = Callable[[list], list]
"""Takes a list of internal vectors, returns their residual vectors (one batched simulation)."""


def grid_search(residuals: ResidualBatch, starts: Sequence[np.ndarray]) -> tuple[int, list[float], list[np.ndarray]]:
    """Evaluate every start in one batch; returns (index of the best, costs, residuals)."""
    res = residuals([np.asarray(s, dtype=np.float64) for s in starts])
    costs = [float(r @ r) for r in res]
    return int(np.nanargmin(costs)), costs, res


def _difference_points(u: np.ndarray, lower: np.ndarray, upper: np.ndarray, steps) -> tuple[np.ndarray, list]:
    """Forward-difference steps h at ``u`` (stepping inward at an upper bound) and the points u + h_i e_i."""
    h = np.asarray(steps, dtype=np.float64).copy()
    span = upper - lower
    h = np.minimum(h, 0.5 * np.where(np.isfinite(span), span, np.inf))
    flip = u + h > upper
    h[flip] = -h[flip]
    pts = []
    for i in range(u.size):
        v = u.copy()
        v[i] += h[i]
        pts.append(v)
    return h, pts


def levenberg_marquardt(residuals: ResidualBatch, u0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                        steps: np.ndarray, *, r0: Optional[np.ndarray] = None, max_iter: int = 8,
                        ftol: float = 1e-3, progress: Optional[Progress] = None,
                        damping: float = 1e-2) -> FitResult:
    """Projected Levenberg–Marquardt with batched finite differences (see the module docstring).

    residuals: maps a list of internal vectors to their residual vectors (metres).
    u0: start; lower / upper: internal bounds; steps: finite-difference steps (internal units).
    r0: the residual at ``u0`` when already known.  ftol: stop when an accepted step lowers the
    cost by less than this fraction.  damping: the initial λ (relative to diag(JᵀJ)).
    """
    lower = np.asarray(lower, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float64)
    u = np.clip(np.asarray(u0, dtype=np.float64), lower, upper)
    p = u.size
    evals = 0
    if r0 is None:
        r = residuals([u])[0]
        evals += 1
    else:
        r = np.asarray(r0, dtype=np.float64)
    cost = float(r @ r)
    trace = [cost]
    if p == 0:
        return FitResult(u, cost, r, None, evals, 0, True, trace)
    lam = float(damping)
    J = None
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        # ---- Jacobian by forward differences, stepping inward at a bound
        h, pts = _difference_points(u, lower, upper, steps)
        rs = residuals(pts)
        evals += p
        J = np.stack([(rs[i] - r) / h[i] for i in range(p)], axis=1)
        g = J.T @ r
        H = J.T @ J
        # ---- active set: at a bound with the gradient pushing outward
        tol_b = 1e-9 * np.maximum(1.0, np.abs(u))
        at_lo = (u <= lower + tol_b) & (g > 0)
        at_hi = (u >= upper - tol_b) & (g < 0)
        free = ~(at_lo | at_hi)
        if not np.any(free) or not np.all(np.isfinite(H)):
            converged = True
            break
        Hf = H[np.ix_(free, free)]
        gf = g[free]
        diag = np.maximum(np.diag(Hf), 1e-12 * max(float(np.max(np.diag(Hf))), 1e-30))
        trials = []
        lams = [lam * 0.1, lam, lam * 10.0]
        for lm in lams:
            try:
                delta = np.linalg.solve(Hf + lm * np.diag(diag), -gf)
            except np.linalg.LinAlgError:
                delta = -gf / (diag * (1 + lm))
            v = u.copy()
            v[free] += delta
            trials.append(np.clip(v, lower, upper))
        rt = residuals(trials)
        evals += len(trials)
        costs = [float(x @ x) if np.all(np.isfinite(x)) else math.inf for x in rt]
        best = int(np.argmin(costs))
        if progress is not None:
            progress.check()
        if costs[best] < cost:
            rel = (cost - costs[best]) / max(cost, 1e-300)
            step_size = float(np.max(np.abs(trials[best] - u) / np.maximum(np.abs(steps), 1e-12)))
            u, r, cost = trials[best], rt[best], costs[best]
            lam = max(lams[best] * 0.3, 1e-7)
            trace.append(cost)
            if rel < ftol or step_size < 0.05:
                converged = True
                break
        else:
            lam *= 100.0
            trace.append(cost)
            if lam > 1e6:
                converged = True
                break
    return FitResult(u, cost, r, J, evals, it, converged, trace)


# --------------------------------------------------------------------------- helpers for effects
def free_params_for(effect: fx.Effect, slot: int, scales: dict | None = None,
                    names: Sequence[str] | None = None, bounds: dict | None = None) -> list[FreeParam]:
    """Free coordinates for the fittable parameters of ``effect`` (vectors expanded).

    scales: ``{param name: typical magnitude}`` — the internal unit of linear parameters and
    the floor (× 1e-4) of log parameters bounded at zero.
    bounds: ``{param name: (lower, upper)}`` — a plausible range for this problem, intersected
    with the registry's bounds (a fit never leaves the registry's range).
    """
    scales = scales or {}
    bounds = bounds or {}
    out = []
    for p in effect.fittable_params():
        if names is not None and p.name not in names:
            continue
        typical = float(scales.get(p.name, _default_typical(p)))
        lower, upper = p.lower, p.upper
        if p.name in bounds:
            lower = max(lower, float(bounds[p.name][0]))
            upper = min(upper, float(bounds[p.name][1]))
            if not lower < upper:
                lower, upper = p.lower, p.upper
        for c in range(p.size):
            if p.log_scale:
                floor = typical * 1e-4 if lower <= 0 else 0.0
                out.append(FreeParam(slot, p.name, c, lower, upper, log=True, floor=floor, step=0.05))
            else:
                out.append(FreeParam(slot, p.name, c, lower, upper, log=False, scale=typical, step=0.02))
    return out


def _default_typical(p: fx.Param) -> float:
    d = np.atleast_1d(np.asarray(p.default, dtype=np.float64)) if p.default is not None else np.zeros(1)
    mag = float(np.max(np.abs(d))) if d.size else 0.0
    if mag > 0:
        return mag
    if math.isfinite(p.upper) and p.upper > 0:
        return 0.1 * p.upper
    return 1.0


BASE_SCALE_BOUNDS = (0.1, 10.0)
"""Range of the E/ρ scale the base fit may use (a model "close to the truth" is within a factor of 10;
a stiffer model also needs proportionally more time steps)."""


def base_param(lower: float = 0.05, upper: float = 20.0, center: float = 1.0,
               prior_width: float = math.log(10.0)) -> FreeParam:
    """The base material's E/ρ scale as a free log parameter with a prior at ``center``.

    prior_width: internal (log) units per σ of pseudo-residual — see :func:`e_prior_width`."""
    return FreeParam(BASE, "E_scale", 0, lower, upper, log=True, step=0.03, prior_width=prior_width,
                     prior_center=math.log(center))


E_PRIOR_SHARE = 0.1
"""Changing E/ρ by a factor of 2 from its reference must buy this fraction of the noise floor's squared error."""


def e_prior_width(observed_samples: int) -> float:
    """Prior width (log units, per noise σ of pseudo-residual) on the E/ρ scale.

    The motion depends on E/ρ through deformation; where it hardly does (rigid flight), an explicit
    solver's time step still changes with E, and with it its time-integration error (millimetres in free
    fall), which a free E would chase.  The prior makes a factor-2 change cost
    ``E_PRIOR_SHARE`` × the noise floor's squared error (3 σ² per observed sample): nothing against a
    material that is really off (that moves the error by many noise floors), enough to keep E put otherwise.
    """
    return math.log(2.0) / math.sqrt(E_PRIOR_SHARE * 3.0 * max(int(observed_samples), 1))


def uncertainty(fit: FitResult, params: Sequence[FreeParam], sigma2: float) -> list[Optional[float]]:
    """One-sigma uncertainty of each parameter in its physical unit (linearised; ``None`` if unknown)."""
    cov = fit.covariance(sigma2)
    if cov is None:
        return [None] * len(params)
    out: list[Optional[float]] = []
    for i, p in enumerate(params):
        s = float(math.sqrt(max(cov[i, i], 0.0)))
        if not math.isfinite(s):
            out.append(None)
            continue
        if p.log:
            out.append(abs(p.to_value(float(fit.u[i]))) * s)
        else:
            out.append(s * p.scale)
    return out
