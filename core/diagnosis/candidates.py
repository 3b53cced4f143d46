"""The candidate search: every effect of the registry fitted against a round's reference model.

:func:`plan_for` gives each effect its start grid, typical magnitudes and plausible bounds from the problem's
scales; :func:`fit_candidates` fits a round's candidates side by side, each from its start grid and then by
bounded Levenberg–Marquardt together with the base E/ρ scale and the effects added so far.
``stiffness_region`` screens the regions of the solid (halves along each axis, k-means clusters of the rest
positions) and fits the two most promising.  Also owns which effects do not apply to a measurement
(:func:`not_applicable_effects`) and whether an effect's "no effect" value lies on a bound or inside (the
significance test's degrees of freedom).  May use :mod:`.problem`, :mod:`.results`, :mod:`.fit`,
:mod:`.compare` and the effect registry.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from ...solvers import effects as fx
from ..errors import UserError
from ..progress import Progress
from .compare import kmeans_regions, region_box
from .contact_fit import ground_gap, touches_ground
from .fit import FitResult, Parametrisation, grid_search, levenberg_marquardt
from .problem import EVALUATIONS, Problem, Reference, Scales, param_for
from .results import CandidateResult

_SEPARATE_STARTS = ("material_damping",)
"""Effects whose start grid spans decades of the stable time step: each start runs in its own launch."""
DEFAULT_REGION_CLUSTERS = 6
REGION_FACTOR_BOUNDS = (0.1, 10.0)
"""Range of the stiffness factor of one region."""
MAX_DAMPING_RATIO = 0.3
"""Largest Kelvin–Voigt viscosity tried, as a damping ratio of the solid's first axial mode (ω ≈ π c / L).
Explicit solvers need a time step ∝ 1/η, so the cost of a simulation grows with η; "moderate"
damping of compact solids lies well below this."""


@dataclass
class Plan:
    """How to fit one effect here: start values, typical magnitudes and plausible bounds per parameter."""

    starts: list
    scales: dict
    bounds: dict = field(default_factory=dict)


def plan_for(name: str, sc: Scales, E_now: float) -> Plan:
    """Start grid, typical magnitudes and plausible bounds for the effect ``name`` in this problem.

    The ranges follow from the problem's scales: drag rates against the duration D and the
    typical speed v, a Kelvin–Voigt viscosity against E (η/E is a time: damping ratios from
    ~0.01 to ~1 for vibrations between ~1 and ~300 Hz), a yield stress against E (yield strain).
    """
    D = sc.duration
    ladder = [0.03, 0.1, 0.3, 1.0, 3.0]
    if name == "linear_drag":
        return Plan([{"c": x / D} for x in ladder], {"c": 1.0 / D})
    if name == "quadratic_drag":
        u = 1.0 / (sc.speed * D)
        return Plan([{"k": x * u} for x in ladder], {"k": u})
    if name == "material_damping":
        # critical damping of the fundamental mode: η ≈ 2E/ω₁ with ω₁ ≈ π c / L, c = sqrt(E/ρ)
        eta_crit = 2.0 * E_now * sc.extent / (math.pi * math.sqrt(E_now / sc.density))
        return Plan([{"eta": eta_crit * x} for x in (0.01, 0.05, 0.25)], {"eta": eta_crit * 0.1},
                     {"eta": (0.0, eta_crit * MAX_DAMPING_RATIO)})
    if name == "ground_friction":
        return Plan([{"mu": x} for x in (0.05, 0.15, 0.3, 0.6, 1.0)], {"mu": 0.3})
    if name == "plasticity":
        # the response to a yield stress is sharp (nothing above the largest stress, a lot just below it):
        # a fine ladder (ratio 1.35) from 1.5 × down to 1/20 of the largest elastic stress of the model
        top = E_now * max(sc.strain, 1e-4)
        ladder = top * 1.5 / 1.35 ** np.arange(11)
        return Plan([{"yield_stress": float(y)} for y in ladder], {"yield_stress": top * 0.3},
                     {"yield_stress": (top * 1e-3, top * 10.0)})
    if name == "wind":
        return Plan([{"acceleration": np.zeros(3)}], {"acceleration": max(0.1 * sc.gravity, 0.1)})
    if name == "stiffness_region":
        return Plan([{"factor": 1.0}], {"factor": 1.0}, {"factor": REGION_FACTOR_BOUNDS})
    # an effect added to the registry later: a few points across each scalar parameter's range
    cls = fx.get(name)
    starts: list[dict] = []
    for p in cls.fittable_params():
        if p.size != 1:
            continue
        lo = p.lower if math.isfinite(p.lower) else -10.0
        hi = p.upper if math.isfinite(p.upper) else 10.0
        if p.log_scale:
            lo_l = math.log(max(lo, hi * 1e-8, 1e-300))
            vals = list(np.exp(np.linspace(lo_l, math.log(hi), 7)[1:-1]))
        else:
            vals = list(np.linspace(lo, hi, 7)[1:-1])
        starts = [{p.name: v} for v in vals]
        break
    return Plan(starts or [{}], {})


def _null_kind(cls: type, p: fx.Param) -> str:
    """``"bounded"`` when the "no effect" value of ``p`` sits on (or beyond) a bound, else ``"interior"``."""
    ctx = fx.EffectContext(sample_positions=np.zeros((1, 3)), tracked_rest_positions=np.zeros((1, 3)))
    region = {"box": [[-1, -1, -1], [1, 1, 1]]}

    def base_at(value) -> bool:
        try:
            kwargs = {p.name: value}
            if cls is fx.StiffnessRegion:
                kwargs["region"] = region
            t = fx.combine([cls(**kwargs)], ctx)
            return t.is_base()
        except UserError:
            return False

    if p.size == 1:
        if math.isfinite(p.lower) and base_at(p.lower):
            return "bounded"
        if math.isfinite(p.upper) and base_at(p.upper):
            return "bounded"
        for neutral in (0.0, 1.0):
            if p.lower < neutral < p.upper and base_at(neutral):
                return "interior"
        return "bounded"  # the effect vanishes only in a limit beyond a bound (yield stress → ∞)
    return "interior" if base_at(np.zeros(p.size)) else "bounded"


def _count_kinds(effect: fx.Effect) -> tuple[int, int]:
    interior = bounded = 0
    for p in effect.fittable_params():
        if _null_kind(type(effect), p) == "bounded":
            bounded += p.size
        else:
            interior += p.size
    return interior, bounded


def not_applicable_effects(names: Sequence[str], measurement, sigma: float) -> dict:
    """{effect name: why it is not tried} for the effects of ``names`` that act only at the ground
    (``Effect.acts_at_ground``: friction, a yielding floor) when the scenario has no ground or the measured solid
    never comes within 2 % of its size plus 5 σ of it: they could change nothing, and each fit costs simulations."""
    out = {}
    at_ground = [n for n in names if fx.get(n).acts_at_ground]
    if not at_ground:
        return out
    if measurement.scenario.ground_height is None:
        why = "the scenario has no ground"
    elif touches_ground(measurement, sigma):
        return out
    else:
        why = f"the solid never comes within {1e3 * ground_gap(measurement):.0f} mm of the ground"
    return {n: why for n in at_ground}


def fit_candidates(P: Problem, ref: Reference, names: Sequence[str], sc: Scales, material, plans: dict, *,
                   region_clusters: int, lm_iterations: int, sigma: float, progress: Progress,
                   round_no: int) -> list[CandidateResult]:
    """Fit the effects ``names`` against ``ref`` (round ``round_no``), side by side when :attr:`Problem.parallel`;
    each result counts its simulations and seconds.  Returns the fitted candidates (a region search that found
    no region gives none), in the order of ``names``."""
    def fit_job(name: str) -> Callable[[], Optional[CandidateResult]]:
        def job() -> Optional[CandidateResult]:
            if not P.parallel:
                progress.set_status(f"round {round_no}: fitting {name}")
            counter = [0]  # simulations of this fit (its own side-by-side fits included)
            token = EVALUATIONS.set(counter)
            w0 = time.perf_counter()
            try:
                if name == "stiffness_region":
                    c = _fit_region(P, ref, sc, material, plans, region_clusters, lm_iterations, sigma, progress)
                else:
                    c = _fit_candidate(P, ref, name, sc, material, plans, lm_iterations, progress)
            finally:
                EVALUATIONS.reset(token)
            if c is not None:
                c.evaluations = counter[0]
                c.seconds = time.perf_counter() - w0
            return c
        return job

    if P.parallel:
        progress.set_status(f"round {round_no}: fitting {len(names)} candidate effects side by side")
    return [c for c in P.side_by_side([fit_job(n) for n in names]) if c is not None]


def _fit_candidate(P: Problem, ref: Reference, name: str, sc: Scales, material, plans: dict,
                   lm_iterations: int, progress: Progress) -> Optional[CandidateResult]:
    cls = fx.get(name)
    starts_vals = list(plans[name].starts)
    template_vals = {}
    fixed = list(ref.fixed)
    replaced = next((e for e in fixed if e.name == name), None)
    if replaced is not None:  # the user's effect of this name is refitted, not stacked
        fixed = [e for e in fixed if e is not replaced]
        starts_vals = [dict(replaced.values)] + starts_vals
    template = cls(**(dict(replaced.values) if replaced is not None else {**template_vals, **starts_vals[0]}))
    param = param_for(ref, [template], plans, fixed)
    ufn = P.residuals(param)
    base_u = param.internal()
    idx = [i for i, p in enumerate(param.params) if p.slot == len(param.effects) - 1]
    starts = []
    E_variants = [base_u[0]]
    if abs(base_u[0]) > math.log(1.2):  # the base fit may have absorbed the effect: also start from the stated E
        E_variants.append(0.0)
    for sv in starts_vals:
        e = cls(**{**template.values, **sv})
        p2 = param.with_internal(base_u)
        p2.effects[-1] = e
        for uE in E_variants:
            u = p2.internal()
            u[0] = uE
            starts.append(u)
    if name == "wind":
        starts.append(_wind_start(P, ref, param, base_u, idx))
    best, costs, res = grid_search(P.residuals(param, separate=name in _SEPARATE_STARTS), starts)
    u_start, r_start = starts[best], res[best]
    null = _null_start(param, ref, replaced is None)
    if null is not None and ref.sse <= costs[best]:
        u_start, r_start = null, P.with_priors(param, null, ref.residual)  # the reference itself (effect off)
    lo, hi = param.bounds()
    fit = levenberg_marquardt(ufn, u_start, lo, hi, param.steps(), r0=r_start, max_iter=lm_iterations,
                              progress=progress)
    if null is not None and P.sse(fit.residual) > ref.sse:  # never report worse than the reference itself
        fit = FitResult(null, ref.sse, P.with_priors(param, null, ref.residual), fit.jacobian, fit.evaluations,
                        fit.iterations, fit.converged, fit.trace)
    scale, effs = param.realise(fit.u)
    interior, bounded = _count_kinds(effs[-1])
    return CandidateResult(name=name, effect=effs[-1], effects=effs, E_scale=scale, sse=P.sse(fit.residual),
                           rmse=math.sqrt(P.sse(fit.residual) / P.n_obs), residual=fit.residual[:P.size], fit=fit,
                           parametrisation=param,
                           free_params=list(param.params), interior=interior, bounded=bounded, tests=1)


def _null_start(param: Parametrisation, ref: Reference, add_new: bool) -> Optional[np.ndarray]:
    """Internal vector of the reference model inside ``param`` (the new effect switched off), or
    ``None`` when the effect has no "off" value inside its bounds."""
    if not add_new:
        return None
    u = param.internal()
    new_slot = len(param.effects) - 1
    cls = type(param.effects[-1])
    lo, hi = param.bounds()
    for i, p in enumerate(param.params):
        if p.slot != new_slot:
            continue
        fp = next(q for q in cls.fittable_params() if q.name == p.name)
        kind = _null_kind(cls, fp)
        if kind == "bounded":
            # "off" at the bound where the effect vanishes: the lower one for drag, friction and damping;
            # else the upper one (a yield stress far above any stress in the problem)
            u[i] = lo[i] if _is_off(cls, fp, fp.lower) else hi[i]
        else:
            neutral = 0.0 if _is_off(cls, fp, 0.0) else 1.0
            u[i] = p.to_internal(neutral) if (not p.log or neutral > 0) else lo[i]
    return u


def _is_off(cls: type, p: fx.Param, value) -> bool:
    """Does parameter ``p`` at ``value`` leave the base model unchanged?"""
    ctx = fx.EffectContext(sample_positions=np.zeros((1, 3)), tracked_rest_positions=np.zeros((1, 3)))
    try:
        kwargs = {p.name: value if p.size == 1 else np.full(p.size, value)}
        if cls is fx.StiffnessRegion:
            kwargs["region"] = {"box": [[-1, -1, -1], [1, 1, 1]]}
        return fx.combine([cls(**kwargs)], ctx).is_base()
    except UserError:
        return False


def _wind_start(P: Problem, ref: Reference, param: Parametrisation, base_u: np.ndarray, idx: list) -> np.ndarray:
    """Start for the wind acceleration: least squares of the centre-of-mass drift on ½ t²."""
    r = ref.residual.reshape(-1, 3)  # simulated − measured at observed samples
    t = (P.m.times - P.m.times[0])
    tt = np.broadcast_to(t[:, None], P.obs.shape)[P.obs]
    w = 0.5 * tt * tt
    a = -(w @ r) / max(float(w @ w), 1e-300)
    u = base_u.copy()
    lo, hi = param.bounds()
    for j, i in enumerate(idx):
        u[i] = float(np.clip(param.params[i].to_internal(float(a[param.params[i].component])), lo[i], hi[i]))
    return u


def _region_candidates(rest: np.ndarray, clusters: int) -> list[tuple[str, dict, np.ndarray]]:
    """(label, region dict for the effect, member point indices) for halves and k-means clusters."""
    out = []
    lo, hi = rest.min(0), rest.max(0)
    pad = 0.01 * float(np.max(hi - lo)) + 1e-9
    for axis in range(3):
        if hi[axis] - lo[axis] <= 1e-9:
            continue
        mid = float(np.median(rest[:, axis]))
        for side in ("low", "high"):
            blo, bhi = lo - pad, hi + pad
            if side == "low":
                bhi = bhi.copy()
                bhi[axis] = mid
                members = np.nonzero(rest[:, axis] <= mid)[0]
            else:
                blo = blo.copy()
                blo[axis] = mid
                members = np.nonzero(rest[:, axis] >= mid)[0]
            if 0 < len(members) < len(rest):
                out.append((f"{'xyz'[axis]} {side} half", {"box": np.stack([blo, bhi])}, members))
    if clusters > 1 and len(rest) >= 2 * clusters:
        labels = kmeans_regions(rest, clusters)
        for k in range(labels.max() + 1):
            members = np.nonzero(labels == k)[0]
            if 0 < len(members) < len(rest):
                out.append((f"cluster {k}", {"points": members}, members))
    return out


def _fit_region(P: Problem, ref: Reference, sc: Scales, material, plans: dict, clusters: int,
                lm_iterations: int, sigma: float, progress: Progress) -> Optional[CandidateResult]:
    rest = np.asarray(P.m.rest, dtype=np.float64)
    regions = _region_candidates(rest, clusters)
    if not regions:
        return None
    # Screening (a score test, used only to shortlist): one probe per region gives the sensitivity of the
    # residual to log(factor) there; together with the sensitivity to a global E change, the best
    # linearised reduction of the squared error is predicted for every region.
    up, probe = 1.25, 2.5
    probe_lists = [P.model_effects(ref.scale * up, ref.effects, ref.fixed)]
    for _, region, _ in regions:
        probe_lists.append(P.model_effects(ref.scale, list(ref.effects) + [fx.make("stiffness_region", factor=probe,
                                                                                      region=region)], ref.fixed))
    pos = P.run(probe_lists)
    r0 = ref.residual
    jE = (P.residual_of(pos[0]) - r0) / math.log(up)
    scored = []
    for i, (label, region, members) in enumerate(regions):
        jR = (P.residual_of(pos[1 + i]) - r0) / math.log(probe)
        A = np.stack([jE, jR], axis=1)
        coef, *_ = np.linalg.lstsq(A, -r0, rcond=None)
        predicted = float(np.sum((r0 + A @ coef) ** 2))
        log_f = float(np.clip(coef[1], math.log(REGION_FACTOR_BOUNDS[0]), math.log(REGION_FACTOR_BOUNDS[1])))
        scored.append((predicted, i, math.exp(log_f) if abs(log_f) > 1e-3 else probe))
    scored.sort()

    def region_fit(i: int, f0: float) -> Callable[[], tuple]:
        def job() -> tuple:
            label, region, members = regions[i]
            template = fx.make("stiffness_region", factor=f0, region=region)
            param = param_for(ref, [template], plans)
            lo, hi = param.bounds()
            fit = levenberg_marquardt(P.residuals(param), param.internal(), lo, hi, param.steps(),
                                      max_iter=lm_iterations, progress=progress)
            return fit, param, label, region, members
        return job

    results = P.side_by_side([region_fit(i, f0) for _, i, f0 in scored[:2]])
    fit, param, label, region, members = min(results, key=lambda x: P.sse(x[0].residual))
    if P.sse(fit.residual) > ref.sse:  # never report worse than the reference itself: factor 1
        u = param.internal()
        u[0] = math.log(ref.scale)
        u[-1] = 0.0
        fit = FitResult(u, ref.sse, P.with_priors(param, u, ref.residual), fit.jacobian, fit.evaluations,
                        fit.iterations, fit.converged, fit.trace)
    scale, effs = param.realise(fit.u)
    eff = effs[-1]
    reg = {"name": label, "points": [int(i) for i in members], "box": region_box(rest, members),
           "regions_tried": len(regions)}
    interior, bounded = _count_kinds(eff)
    return CandidateResult(name="stiffness_region", effect=eff, effects=effs, E_scale=scale, sse=P.sse(fit.residual),
                           rmse=math.sqrt(P.sse(fit.residual) / P.n_obs), residual=fit.residual[:P.size], fit=fit,
                           parametrisation=param,
                           free_params=list(param.params), interior=interior, bounded=bounded, tests=len(regions),
                           region=reg)
