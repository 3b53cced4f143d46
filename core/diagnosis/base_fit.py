"""The base model: its E/ρ refitted alone, the window in which it is predictive, and the base material's check.

:func:`fit_base` fits the E/ρ scale (to the deformation first, then to the whole motion);
:func:`find_predictive_window` finds the horizon past which the motion stops depending smoothly on E (chaotic
contact); :func:`base_material_check` asks whether, with the effects found, E/ρ differs significantly from the
stated value (reported apart from the effects).  May use :mod:`.problem`, :mod:`.fit`, :mod:`.significance`,
:mod:`.compare` and :mod:`.results`.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ..progress import Progress
from . import significance as sig
from .compare import noise_rmse
from .fit import FitResult, Parametrisation, free_params_for, grid_search, levenberg_marquardt
from .problem import Problem, Reference, Scales
from .results import json_float


def fit_base(P: Problem, param: Parametrisation, lm_iterations: int, progress: Progress,
             start: Optional[np.ndarray] = None) -> tuple[FitResult, np.ndarray]:
    """Fit the E/ρ scale alone; returns the fit and the full residual at its optimum.

    Two stages.  E/ρ acts on the motion through deformation, so it is first fitted to the *deformation*
    (each frame's mean displacement removed) from 9 starts between ×¼ and ×4: that finds the material
    without chasing what else is wrong with the centre-of-mass motion (a missing effect, or an explicit
    solver's free-fall integration error, which changes with the stable time step and so with E).  The
    reference model the effects are then judged against must however be the best base model for the whole
    motion, or every candidate would get credit for merely repairing E: the scale is refitted on the full
    residual from the better of the stated value and the deformation optimum, within ×¼ … ×4."""
    store: dict = {}
    fn = P.residuals(param)

    def deformation(us):
        out = []
        for u, r in zip(us, fn(us)):
            store[np.asarray(u).tobytes()] = r
            out.append(np.concatenate([P.deformation_part(r), r[P.size:]]))
        return out

    starts = [np.array([0.0])] + [np.array([math.log(x)]) for x in np.exp(np.linspace(math.log(0.25),
                                                                                       math.log(4.0), 9))]
    if start is not None:
        starts.append(np.asarray(start, dtype=np.float64))
    best, costs, res = grid_search(deformation, starts)
    lo, hi = param.bounds()
    dfit = levenberg_marquardt(deformation, starts[best], lo, hi, param.steps(), r0=res[best],
                               max_iter=lm_iterations, progress=progress)
    cands = [np.array([0.0]), np.asarray(dfit.u)] + ([np.asarray(start, dtype=np.float64)] if start is not None else [])
    full = []
    for u in cands:
        r = store.get(np.asarray(u).tobytes())
        full.append(r if r is not None else fn([u])[0])
    k = int(np.argmin([float(r @ r) for r in full]))
    lo2 = np.maximum(lo, math.log(0.25))
    hi2 = np.minimum(hi, math.log(4.0))
    u0 = np.clip(cands[k], lo2, hi2)
    bf = levenberg_marquardt(fn, u0, lo2, hi2, param.steps(), r0=full[k] if np.allclose(u0, cands[k]) else None,
                             max_iter=lm_iterations, progress=progress)
    return bf, bf.residual


CHAOS_PERTURBATION = 0.02
"""Relative change of E used to probe where the model stops being predictive."""
CHAOS_NONLINEARITY = 0.3
"""The response to E × (1 + 2ε) must stay within this fraction of twice the response to E × (1 + ε)."""


def find_predictive_window(P: Problem, ref: Reference, sigma: float, sc: Scales) -> Optional[np.ndarray]:
    """(T,) bool frames up to the predictive horizon, or ``None`` when the model is predictive throughout.

    Long rollouts with tumbling contact are chaotic (shared/notes/diagnosis.md): there the motion stops
    depending smoothly on the model, fits become rugged and a good model can be far off.  The reference
    is re-run with E × (1 + ε) and E × (1 + 2ε), ε = 2 %: while the motion depends smoothly on the model,
    the second moves the points twice as far as the first (RMS over the points, per instant).  The
    horizon is the first instant at which that ratio is off by more than 30 % while the motion
    difference exceeds 3 noise levels — or the difference exceeds 10 % of the solid's size.  At least
    40 % of the duration is kept.
    """
    eps = CHAOS_PERTURBATION
    r0, a, b = P.run([P.model_effects(ref.scale, ref.effects, ref.fixed),
                      P.model_effects(ref.scale * (1 + eps), ref.effects, ref.fixed),
                      P.model_effects(ref.scale * (1 + 2 * eps), ref.effects, ref.fixed)])
    if not all(np.all(np.isfinite(x)) for x in (r0, a, b)):
        return None
    s1 = np.sqrt(np.mean(np.sum((a - r0) ** 2, axis=-1), axis=1))
    s2 = np.sqrt(np.mean(np.sum((b - r0) ** 2, axis=-1), axis=1))
    resolved = s2 > 3.0 * noise_rmse(sigma)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = s2 / np.maximum(s1, 1e-300)
    nonlinear = resolved & (np.abs(ratio - 2.0) > 2.0 * CHAOS_NONLINEARITY)
    over = nonlinear | (s2 > 0.1 * sc.size)
    if not np.any(over):
        return None
    T = len(s1)
    end = max(int(np.argmax(over)), int(math.ceil(0.4 * T)), 4)
    if end >= T:
        return None
    return np.arange(T) < end


def base_material_check(P: Problem, ref: Reference, material, sigma: float, lm_iterations: int,
                        progress: Progress, plans: dict) -> dict:
    """Is E/ρ (with the effects found) significantly different from the stated value?"""
    note = ("under gravity and inertia alone the motion depends on E/ρ only: E and density cannot both be "
            "fitted, so the scale applies to E at the stated density (equivalently to 1/ρ)")
    # the model with E fixed at the stated value, effects refitted
    effects = list(ref.effects)
    params = []
    for i, e in enumerate(effects):
        plan = plans.get(e.name)
        params += free_params_for(e, i, plan.scales if plan else {}, bounds=plan.bounds if plan else {})
    param = Parametrisation(effects, params, list(ref.fixed), 1.0)
    fn = P.residuals(param)
    if params:
        lo, hi = param.bounds()
        fit = levenberg_marquardt(fn, param.internal(), lo, hi, param.steps(), max_iter=lm_iterations,
                                  progress=progress)
        sse_stated = P.sse(fit.residual)
        r_stated = fit.residual
    else:
        r_stated = fn([np.zeros(0)])[0]
        sse_stated = P.sse(r_stated)
    lr = sig.likelihood_ratio(sse_stated, ref.sse, sigma)
    thr = sig.lr_threshold(1, 0, sig.ALPHA, 1)
    share = sig.share_of_excess(sse_stated, ref.sse, P.n_obs, sigma)
    # E/ρ acts on the motion through deformation; a change that only moves the centre of mass (e.g. by
    # changing the solver's stable time step and with it the time-integration error of free flight) is not
    # evidence about the material.  The same tests are therefore also required of the residual with each
    # frame's mean displacement removed.
    def_stated = P.sse(P.deformation_part(r_stated))
    def_fitted = P.sse(P.deformation_part(ref.residual))
    lr_def = sig.likelihood_ratio(def_stated, def_fitted, sigma)
    share_def = sig.share_of_excess(def_stated, def_fitted, P.n_obs, sigma)
    looks_wrong = bool(lr >= thr and share >= sig.MIN_SHARE and lr_def >= thr and share_def >= sig.MIN_SHARE
                       and abs(math.log(ref.scale)) > math.log(1.02))
    E_stated = material.mean_E()
    return {"E_scale": float(ref.scale), "E_stated": E_stated, "E_fitted": E_stated * ref.scale,
            "density_stated": material.mean_density(),
            "E_over_density_stated": E_stated / material.mean_density(),
            "E_over_density_fitted": E_stated * ref.scale / material.mean_density(),
            "rmse_stated_E": math.sqrt(sse_stated / P.n_obs), "rmse_fitted_E": math.sqrt(ref.sse / P.n_obs),
            "likelihood_ratio": json_float(lr), "threshold": json_float(thr), "share_of_excess": json_float(share),
            "likelihood_ratio_deformation": json_float(lr_def),
            "share_of_excess_deformation": json_float(share_def),
            "looks_wrong": looks_wrong, "note": note}
