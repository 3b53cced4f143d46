"""The diagnosis checks its own resolution: is the fitted base model converged at the resolution it runs?

A diagnosis runs its solver coarser than a bake (hundreds of simulations).  A discretisation error larger than
the noise looks like a missing effect (issue 18: a spring-mass drop moved 73 mm at 192 anchors and 26 mm at
2048 from a converged FEM).  Before effects are judged the fitted base model is therefore re-run finer
(:func:`finer_settings`: about twice the spring-mass anchors, 1.5× the MPM cells across, twice the LBS cubature,
collision points and mass samples, and half the time step) and the two trajectories are compared:

* they differ by no more than the noise (RMSE of 3-D distances ≤ the noise level √3 σ, over the observed samples
  the fits use — those of the predictive window where there is one: past it the motion stops depending smoothly
  on the model, a 2 % change of E already moving it far, and the runs stop there): the resolution is
  sufficient, nothing changes;
* they differ by more, and a diagnosis with the finer model fits the time budget (the finer run's measured
  cost × the simulations the diagnosis still needs, :data:`DEFAULT_BUDGET_S`; the runs' cost one after another:
  where they share the CPU's cores, :attr:`.problem.Problem.threads`, the wall time is about half that on 2
  cores, and the budget is kept as it was measured against): the diagnosis uses the finer model from here on;
* they differ by more and the finer model is too costly: the coarse model's **discretisation floor** (the RMSE
  between the two resolutions) is recorded, and no effect is called significant whose improvement is below the
  part of that floor it could be imitating (:func:`apply_floor`): with δ the change refinement makes (finer −
  coarse positions at the observed samples) and v the change the effect makes to the model's trajectory, an
  effect gains (ΔSSE) at most (δ·v/|v|)² from merely standing in for the discretisation; it must gain more.
  The whole floor n·floor² would refuse every effect whose signature has nothing in common with the
  discretisation error (measured: a stiffer half of a clamped bar, 64 spring-mass anchors, floor 10.9 mm).

What refinement changes that a different E/ρ would change as well is not a floor: the diagnosis fits E/ρ at the
resolution it runs, so a discretisation error that only makes the solid stiffer or softer (shear locking, a
coarse network's bending stiffness) is taken up by the base fit and shows only as a biased E.  Before the two
trajectories are compared the finer model's E/ρ is therefore refitted to the coarse model's trajectory
(:func:`absorb_base_scale`: a batch of scales ×⅔ … ×1.5, then up to two parabola steps through the best three);
the floor is what remains, and the factor is reported (the coarse model's E/ρ times it is the finer model's).
Measured on the validation's clamped bar with a stiffer half (MPM, 12 → 18 cells across): 19.7 mm at the same E/ρ,
4.1 mm after the refit (the factor at the batch's edge, ×1.5: an upper bound).

The floor is an estimate from one refinement step (the finer model's own error is not known); it is reported
as such in ``diagnosis.json`` (``resolution``), the summary and the HTML page.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .compare import noise_rmse

DEFAULT_BUDGET_S = 60.0
"""Seconds of simulation the rest of a diagnosis may take with the finer model before the floor is used instead
(a full diagnosis should stay within about two minutes on a 2-core CPU: 60 s with the finer model plus the
coarse work already done)."""
REFINE = {"anchors": 2.0, "cells_across": 1.5, "cells_across_thinnest": 1.5, "cubature_points": 2.0,
          "collision_points": 2.0, "mass_samples": 2.0}
"""Factor applied to each resolution setting a solver exposes (integer settings rounded)."""


def half_step_settings(sim, settings):
    """Solver settings with half the time step, or ``None`` when the solver exposes no time-step knob.

    Looks for a settings field ``dt`` / ``substep_dt`` / ``time_step`` (halved), else the Courant-like
    factors ``cfl`` / ``viscous_cfl`` / ``safety`` / ``courant`` (all present halved), else ``substeps``
    (doubled).
    """
    s = getattr(sim, "settings", None)
    if s is None or not dataclasses.is_dataclass(s):
        return None
    names = {f.name for f in dataclasses.fields(s)}
    for key in ("dt", "substep_dt", "time_step", "max_dt"):
        if key in names and getattr(s, key) is not None:
            return dataclasses.replace(s, **{key: getattr(s, key) * 0.5})
    courant = {key: getattr(s, key) * 0.5 for key in ("cfl", "viscous_cfl", "safety", "courant")
               if key in names and getattr(s, key) is not None}
    if courant:  # every limit of the step at once (MPM: the wave-speed and the viscous limit)
        return dataclasses.replace(s, **courant)
    if "substeps" in names and getattr(s, "substeps") is not None:
        return dataclasses.replace(s, substeps=int(getattr(s, "substeps")) * 2)
    return None


def finer_settings(sim) -> Optional[object]:
    """The settings of the prepared simulation ``sim`` refined in space (:data:`REFINE`) and time (half step), or
    ``None`` when the solver exposes neither."""
    s = getattr(sim, "settings", None)
    if s is None or not dataclasses.is_dataclass(s):
        return None
    names = {f.name for f in dataclasses.fields(s)}
    changes = {}
    for key, factor in REFINE.items():
        if key in names and isinstance(getattr(s, key), (int, float)) and getattr(s, key):
            v = getattr(s, key) * factor
            changes[key] = int(round(v)) if isinstance(getattr(s, key), int) else v
    spatial = dataclasses.replace(s, **changes) if changes else s

    class _Shim:  # half_step_settings reads ``.settings`` only
        settings = spatial

    fine = half_step_settings(_Shim, spatial)
    if fine is None and not changes:
        return None
    return fine if fine is not None else spatial


@dataclass
class ResolutionCheck:
    """Outcome of the check.  floor: RMSE (m, 3-D distances over the observed samples the fits use: those of the
    predictive window where there is one) between the fitted base model at the diagnosis's resolution and the finer
    one; noise_level: √3 σ (m); used_finer: the diagnosis continues
    with the finer model; enforce_floor: effects must beat the floor; seconds / finer_seconds: one run at each
    resolution (s); settings / finer_settings: the two solvers' settings (dicts)."""

    checked: bool = False
    floor: float = 0.0
    noise_level: float = 0.0
    used_finer: bool = False
    enforce_floor: bool = False
    seconds: float = 0.0
    finer_seconds: float = 0.0
    predicted_seconds: float = 0.0
    budget_s: float = DEFAULT_BUDGET_S
    settings: Optional[dict] = None
    finer: Optional[dict] = None
    verdict: str = "not checked"
    floor_before_refit: float = 0.0
    """RMSE (m) between the two resolutions at the same E/ρ (before the finer model's E/ρ is refitted)."""
    finer_E_factor: float = 1.0
    """The finer model's E/ρ over the coarse one's that matches the coarse trajectory best (1: not refitted)."""

    difference: Optional[np.ndarray] = None
    """(3·n,) m: finer − coarse positions at the observed samples of the fits (residual order); not reported."""

    def floor_sse(self, n_obs: int) -> float:
        """Squared error (m²) the discretisation alone moves over ``n_obs`` observed samples (0 when not enforced)."""
        return n_obs * self.floor ** 2 if self.enforce_floor else 0.0

    def imitable_sse(self, change: np.ndarray) -> float:
        """Squared error (m²) an effect that changes the trajectory by ``change`` (3·n,) m could gain by standing
        in for the discretisation error alone: (δ·v/|v|)² (0 when the floor is not enforced)."""
        if not self.enforce_floor or self.difference is None:
            return 0.0
        v = np.asarray(change, dtype=np.float64).reshape(-1)
        if v.shape != self.difference.shape:
            return self.floor_sse(len(v) // 3)
        norm = float(np.linalg.norm(v))
        if norm <= 0.0:
            return 0.0
        return float(self.difference @ v / norm) ** 2

    def to_dict(self) -> dict:
        return {"checked": self.checked, "floor_rmse": _f(self.floor), "noise_level": _f(self.noise_level),
                "used_finer": self.used_finer, "enforce_floor": self.enforce_floor, "seconds_per_run": _f(self.seconds),
                "finer_seconds_per_run": _f(self.finer_seconds), "predicted_seconds_finer": _f(self.predicted_seconds),
                "budget_s": _f(self.budget_s), "settings": self.settings, "finer_settings": self.finer,
                "floor_rmse_same_E": _f(self.floor_before_refit), "finer_E_factor": _f(self.finer_E_factor),
                "verdict": self.verdict}


def _f(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def plain_settings(s) -> dict:
    """The scalar fields (numbers, strings, flags, None) of a solver's settings dataclass, by name."""
    out = {}
    for f in dataclasses.fields(s):
        v = getattr(s, f.name)
        if isinstance(v, (int, float, str, bool)) or v is None:
            out[f.name] = v
    return out


REFIT_FACTORS = (2.0 / 3.0, 0.82, 1.22, 1.5)
"""E/ρ factors (besides 1) at which the finer model is run to find the scale that matches the coarse trajectory."""
REFIT_PARABOLAS = 2
"""Parabola steps after the batch (each one finer run)."""
REFIT_BUDGET_S = 30.0
"""Seconds of finer simulation the E/ρ refit may take (:data:`REFIT_FACTORS` plus :data:`REFIT_PARABOLAS` runs);
above that the floor is measured at the same E/ρ (an upper bound)."""


def _sse(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    d = a[mask] - b[mask]
    return float(np.sum(d * d)) if np.all(np.isfinite(d)) else math.inf


def absorb_base_scale(P, effects_at, scale: float, coarse: np.ndarray, fine: np.ndarray, fine_sim,
                      mask: np.ndarray) -> tuple[float, np.ndarray]:
    """The factor f on the E/ρ scale at which the finer model's trajectory comes closest to the coarse one (squared
    distances over the samples ``mask`` (T, N) bool), and that trajectory.

    effects_at: E/ρ scale → the base model's effect list; scale: the coarse model's fitted scale; coarse, fine:
    (T, N, 3) m, both at ``scale``; fine_sim: the finer simulation.  One batch at :data:`REFIT_FACTORS`, then
    :data:`REFIT_PARABOLAS` times the vertex of the parabola (in log f) through the best factor so far and its
    neighbours; the best run is returned (f = 1 and ``fine`` when nothing is closer)."""
    factors = [1.0] + [float(f) for f in REFIT_FACTORS]
    runs = [fine] + list(P.run([effects_at(scale * f) for f in factors[1:]], sim=fine_sim))
    tried = {f: (_sse(r, coarse, mask), r) for f, r in zip(factors, runs)}
    for _ in range(REFIT_PARABOLAS):
        fs = sorted(tried)
        costs = [tried[f][0] for f in fs]
        k = int(np.argmin(costs))
        if not (0 < k < len(fs) - 1 and all(math.isfinite(c) for c in costs[k - 1:k + 2])):
            break
        x = np.log(fs[k - 1:k + 2])
        a, b, _ = np.polyfit(x, costs[k - 1:k + 2], 2)
        if a <= 0:
            break
        f_star = float(np.exp(np.clip(-b / (2 * a), x[0], x[2])))
        if any(abs(f_star / f - 1.0) < 1e-3 for f in fs):
            break
        run = P.run([effects_at(scale * f_star)], sim=fine_sim)[0]
        tried[f_star] = (_sse(run, coarse, mask), run)
    best = min(tried, key=lambda f: tried[f][0])
    return best, tried[best][1]


def check_resolution(P, effects_at, scale: float, prepare, sigma: float, remaining_runs: int,
                     budget_s: float = DEFAULT_BUDGET_S, say=None) -> tuple[ResolutionCheck, Optional[object]]:
    """Re-run the fitted base model finer and decide (module docstring).

    P: the diagnosis problem (its :class:`.problem.Problem`: ``sim``, ``run``, observed mask, measured positions);
    effects_at: E/ρ scale → the fitted base model's effect list (``P.model_effects(scale, ...)``); scale: the
    fitted E/ρ scale; prepare: settings → a prepared simulation of the same scene; sigma: noise σ (m);
    remaining_runs: simulations the diagnosis still expects.
    Returns (check, the finer simulation when the diagnosis should use it, else ``None``).
    """
    fine_settings = finer_settings(P.sim)
    if fine_settings is None:
        return ResolutionCheck(verdict="the solver exposes no resolution or time-step setting: not checked"), None
    t0 = time.perf_counter()
    coarse = P.run([effects_at(scale)])[0]
    t_coarse = time.perf_counter() - t0
    fine_sim = prepare(fine_settings)
    t0 = time.perf_counter()
    fine = P.run([effects_at(scale)], sim=fine_sim)[0]
    t_fine = time.perf_counter() - t0
    obs = P.obs  # the samples the fits and tests use: beyond a predictive window any change moves the motion far
    level = noise_rmse(sigma)
    same_E = math.sqrt(_sse(coarse, fine, obs) / max(int(obs.sum()), 1))
    factor = 1.0
    refit_seconds = t_fine * (len(REFIT_FACTORS) + REFIT_PARABOLAS)
    needs_refit = level < same_E < math.inf
    refit_skipped = needs_refit and refit_seconds > REFIT_BUDGET_S
    if needs_refit and not refit_skipped:
        factor, fine = absorb_base_scale(P, effects_at, scale, coarse, fine, fine_sim, P.obs)
    floor = math.sqrt(_sse(coarse, fine, obs) / max(int(obs.sum()), 1))
    diff = (fine[P.obs] - coarse[P.obs]).reshape(-1)
    check = ResolutionCheck(checked=True, floor=floor, noise_level=level, seconds=t_coarse, finer_seconds=t_fine,
                            predicted_seconds=t_fine * max(int(remaining_runs), 0), budget_s=float(budget_s),
                            settings=plain_settings(P.sim.settings), finer=plain_settings(fine_settings),
                            difference=diff if np.all(np.isfinite(diff)) else None,
                            floor_before_refit=same_E, finer_E_factor=factor)
    moved = (f"{1e3 * floor:.2f} mm" if factor == 1.0 else
             f"{1e3 * same_E:.2f} mm at the same E/ρ, {1e3 * floor:.2f} mm with its E/ρ × {factor:.3g} (what the base "
             "fit cannot take up)")
    if refit_skipped:  # the floor then includes what a refit E/ρ would take up: an upper bound, and machine-dependent
        moved += (f" at the same E/ρ (its refit for the finer model was skipped: about {refit_seconds:.0f} s of finer "
                  f"runs, {REFIT_BUDGET_S:.0f} s allowed; this floor is an upper bound)")
    use = None
    if floor <= level:
        check.verdict = (f"the fitted base model moves by {moved} when refined (finer solid and half the time "
                         f"step), within the noise level {1e3 * level:.2f} mm: its resolution is sufficient")
    elif check.predicted_seconds <= budget_s:
        check.used_finer = True
        use = fine_sim
        check.verdict = (f"refined, the fitted base model moves by {moved}, more than the noise level "
                         f"{1e3 * level:.2f} mm: the diagnosis uses the finer model (predicted "
                         f"{check.predicted_seconds:.0f} s of simulation, budget {_budget_words(budget_s)})")
    else:
        check.enforce_floor = True
        cost = ("" if budget_s == 0.0 else
                f", and the finer model would cost about {check.predicted_seconds:.0f} s "
                f"(budget {_budget_words(budget_s)})")
        check.verdict = (f"refined, the fitted base model moves by {moved}, more than the noise level "
                         f"{1e3 * level:.2f} mm{cost}: the model's discretisation floor is {1e3 * floor:.2f} mm and no "
                         "effect whose improvement is below the part of it the effect could imitate is called "
                         "significant" + (" (resolution budget 0 s: the coarse model on every machine)"
                                          if budget_s == 0.0 else ""))
    if say is not None:
        say("   resolution: " + check.verdict)
    return check, use


def _budget_words(budget_s: float) -> str:
    """The budget as the verdict states it: the choice it made depends on this machine's measured speed."""
    if math.isinf(budget_s):
        return "unlimited"
    return (f"{budget_s:.3g} s; the choice follows this machine's speed, and a budget of 0 s makes it the same "
            "on every machine")


def apply_floor(check: ResolutionCheck, candidates: list, residual_reference: np.ndarray, n_obs: int) -> None:
    """Refuse significance (in place: ``significant`` False, a reason appended) to candidates whose gain in squared
    error over the reference is no more than they could gain by imitating the discretisation error
    (:meth:`ResolutionCheck.imitable_sse`).  residual_reference: the reference's data residual (3·n_obs,) m; each
    candidate's ``residual`` and ``sse`` are its own."""
    if not check.enforce_floor:
        return
    r_ref = np.asarray(residual_reference, dtype=np.float64).reshape(-1)
    sse_reference = float(r_ref @ r_ref)
    for c in candidates:
        if c.residual is None:
            continue
        gain = sse_reference - c.sse
        need = check.imitable_sse(r_ref - np.asarray(c.residual, dtype=np.float64).reshape(-1))
        if gain <= need:
            c.reasons.append(f"its improvement ({1e3 * math.sqrt(max(gain, 0.0) / n_obs):.2f} mm RMS) is no more "
                             f"than it gains by imitating the discretisation error ({1e3 * math.sqrt(need / n_obs):.2f}"
                             f" mm RMS of the model's discretisation floor {1e3 * check.floor:.2f} mm)")
            c.significant = False
