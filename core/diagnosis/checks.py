"""The tests a round's candidates must pass to count as significant.

:func:`judge` applies the likelihood-ratio test against the noise (a chi-bar-squared threshold, Bonferroni over
everything tried) and the share of the reference's above-noise error removed (:mod:`.significance`), and
states the fitted parameters' uncertainties; :func:`check_leading` refits the leading candidates on the early
frames (they must not predict the held-out later frames worse than the reference) and re-checks a damping-like
leader at half the solver's time step (numerical dissipation looks like damping), down the ranking until a leader
passes.  May use :mod:`.problem`, :mod:`.results`, :mod:`.fit`, :mod:`.significance`, :mod:`.resolution` and the
solver interface (to prepare the half-step simulation).
"""

from __future__ import annotations

import math
from typing import Callable, Optional, Sequence

import numpy as np

from ..progress import Progress
from . import significance as sig
from .fit import BASE, FitResult, Parametrisation, levenberg_marquardt, uncertainty
from .problem import Problem, Reference, param_for
from .resolution import half_step_settings
from .results import CandidateResult, format_params, json_float

DAMPING_LIKE = ("linear_drag", "quadratic_drag", "material_damping")
"""Effects re-checked at half the time step (numerical dissipation looks like them)."""


def judge(P: Problem, ref: Reference, cands: Sequence[CandidateResult], sse_baseline: float, sigma: float) -> None:
    """Set each candidate's gain against ``ref`` and the model as given (``sse_baseline``, m²), its likelihood
    ratio, threshold and share of the above-noise error, its verdict (``significant``, ``reasons``) and its
    parameters' uncertainties; with a predictive window, ``rmse`` is recomputed over all observed samples."""
    tests = sum(c.tests for c in cands)
    if P.window is not None and cands:  # the spec's rmse / explained are over all observed samples
        full = P.run([P.model_effects(c.E_scale, c.effects, c.parametrisation.fixed if c.parametrisation
                                      else ref.fixed) for c in cands], full=True)
        for c, pos in zip(cands, full):
            c.sse_all, c.rmse = P.rmse_all(pos)
    for c in cands:
        c.explained = 1.0 - (c.sse_all if c.sse_all is not None else c.sse) / max(sse_baseline, 1e-300)
        c.explained_beyond_base = 1.0 - c.sse / max(ref.sse, 1e-300)
        c.lr = sig.likelihood_ratio(ref.sse, c.sse, sigma)
        c.threshold = sig.lr_threshold(c.interior, c.bounded, sig.ALPHA, tests)
        c.share = sig.share_of_excess(ref.sse, c.sse, P.n_obs, sigma)
        c.reasons = []
        if c.lr < c.threshold:
            c.reasons.append(f"gain Λ = {c.lr:.3g} below the noise threshold {c.threshold:.3g}")
        if c.share < sig.MIN_SHARE:
            c.reasons.append(f"removes only {100 * max(c.share, 0):.0f} % of the above-noise error "
                             f"(needs {100 * sig.MIN_SHARE:.0f} %)")
        c.significant = not c.reasons
        s2 = max(sigma ** 2, c.sse / max(P.obs.sum() * 3 - len(c.free_params), 1))
        if c.fit is not None:
            unc = uncertainty(c.fit, c.free_params, s2)
            c.uncertainty = {p.label: json_float(u) for p, u in zip(c.free_params, unc) if p.slot != BASE}


def check_leading(P: Problem, ref: Reference, cands: Sequence[CandidateResult], sigma: float, *, holdout: bool,
                  dt_check: bool, half_step_sim: Callable[[], object], lm_iterations: int, progress: Progress,
                  round_no: int) -> None:
    """The held-out check of the (up to 3) leading significant candidates of ``cands`` (ranked best first), and
    the half-step check of the leader when it is damping-like (:data:`DAMPING_LIKE`; ``half_step_sim()`` gives the
    simulation at half the time step).  A candidate failing one is no longer significant, and the next significant
    candidate leads and must pass the same checks (the reference's half-step refit is shared)."""
    leading = [c for c in cands if c.significant][:3]
    holdout_jobs, holdout_finish = (_holdout_jobs(P, ref, leading, sigma, progress) if holdout and leading
                                    else ([], None))
    # side by side, the half-step check of the leading candidate runs with the held-out refits (wasted only
    # when the held-out check rejects that candidate; it is then run again for the new leader below)
    dt_done: dict = {}
    dt_reference: dict = {}  # the reference refitted at half the step, shared by every candidate re-checked
    ahead = leading[0] if P.parallel and leading and dt_check and leading[0].name in DAMPING_LIKE else None
    dt_jobs, dt_finish = [], None
    if ahead is not None:
        dt_jobs, dt_finish = _half_step_jobs(P, ref, ahead, sigma, half_step_sim(), lm_iterations, progress,
                                             reference_store=dt_reference)
    if holdout_jobs or dt_jobs:
        progress.set_status(f"round {round_no}: held-out check of {', '.join(c.name for c in leading)}"
                            + (f"; {ahead.name} at half the time step" if ahead is not None else ""))
        results = P.side_by_side(holdout_jobs + dt_jobs)
        if holdout_finish is not None:
            for c, check in zip(leading, holdout_finish(results[:len(holdout_jobs)])):
                c.holdout = check
                if c.holdout.get("ok") is False:
                    c.significant = False
                    c.reasons.append(c.holdout["verdict"])
        if ahead is not None:
            dt_done[ahead.name] = dt_finish(results[len(holdout_jobs):])
    elif holdout_finish is not None:  # too few samples for a held-out window
        for c, check in zip(leading, holdout_finish([])):
            c.holdout = check
    # a leader that fails a check gives way to the next significant candidate, which must pass the same checks:
    # numerical dissipation that imitates one damping-like effect imitates the others as well
    top = next((c for c in cands if c.significant), None)
    while top is not None:
        failed = None
        if holdout and top.holdout is None:
            jobs, finish = _holdout_jobs(P, ref, [top], sigma, progress)
            top.holdout = finish(P.side_by_side(jobs) if jobs else [])[0]
            if top.holdout.get("ok") is False:
                failed = top.holdout["verdict"]
        if failed is None and dt_check and top.name in DAMPING_LIKE:
            if top.name not in dt_done:
                progress.set_status(f"round {round_no}: re-checking {top.name} at half the time step")
                jobs, finish = _half_step_jobs(P, ref, top, sigma, half_step_sim(), lm_iterations, progress,
                                               reference_fit=dt_reference.get("fit"), reference_store=dt_reference)
                dt_done[top.name] = finish(P.side_by_side(jobs))
            top.dt_check = dt_done[top.name]
            if top.dt_check.get("ok") is False:
                failed = top.dt_check["verdict"]
        if failed is None:
            break
        top.significant = False
        top.reasons.append(failed)
        top = next((c for c in cands if c.significant), None)


def _window_residuals(fn: Callable[[list], list], keep: np.ndarray, store: dict) -> Callable[[list], list]:
    """Residuals restricted to the data entries ``keep`` (prior pseudo-residuals after them are kept);
    full residuals are remembered by parameter vector."""
    def w(us):
        full = fn(us)
        out = []
        for u, r in zip(us, full):
            store[np.asarray(u).tobytes()] = r
            mask = np.concatenate([keep, np.ones(len(r) - len(keep), dtype=bool)])
            out.append(r[mask])
        return out

    return w


def _holdout_jobs(P: Problem, ref: Reference, cands: Sequence[CandidateResult], sigma: float,
                  progress: Progress) -> tuple[list, Callable[[list], list]]:
    """Held-out checks of ``cands``: refit each and the reference on the early frames and compare their errors
    on the later frames.  Returns (jobs, finish): the refits, and the function that turns their results into
    one check (dict) per candidate."""
    t = P.m.times - P.m.times[0]
    t_end = t[P.window][-1] if P.window is not None else t[-1]
    split = sig.HOLDOUT_FRACTION * t_end
    train_frames = t <= split
    frame_of_sample = np.broadcast_to(np.arange(len(t))[:, None], P.obs.shape)[P.obs]
    train = np.repeat(train_frames[frame_of_sample], 3)
    test = ~train
    n_test = int(test.sum() // 3)
    if n_test < 10 or int(train.sum() // 3) < 10:
        return [], lambda results: [{"ok": None, "verdict": "too few samples for a held-out window",
                                     "split_time": float(split)} for _ in cands]

    def refit(param: Parametrisation, u0) -> Callable[[], float]:
        def job() -> float:
            store: dict = {}
            fn = _window_residuals(P.residuals(param), train, store)
            lo, hi = param.bounds()
            fit = levenberg_marquardt(fn, param.internal() if u0 is None else u0, lo, hi, param.steps(), max_iter=3,
                                      progress=progress)
            full = store.get(np.asarray(fit.u).tobytes())
            if full is None:
                full = P.residuals(param)([fit.u])[0]
            return float(np.sum(full[: P.size][test] ** 2))
        return job

    def finish(results: list) -> list:
        sse_reference, *sse_candidates = results
        # worse on the held-out frames by more than the noise can explain → the fit does not generalise
        margin = 3.0 * math.sqrt(2.0 * 3 * n_test) * sigma * sigma
        out = []
        for sse_candidate in sse_candidates:
            ok = sse_candidate <= sse_reference + margin
            out.append({"split_time": float(split + P.m.times[0]), "sse_reference": sse_reference,
                        "sse_candidate": sse_candidate, "rmse_reference": math.sqrt(sse_reference / n_test),
                        "rmse_candidate": math.sqrt(sse_candidate / n_test), "ok": bool(ok),
                        "verdict": ("predicts the held-out frames at least as well" if ok else
                                    "fitted on the early frames it predicts the held-out later frames worse than "
                                    "the base model")})
        return out

    return [refit(param_for(ref, [], {}), None)] + [refit(c.parametrisation, c.fit.u) for c in cands], finish


def half_step_simulation(P: Problem, settings, measurement, material, body, frame_times, device: str):
    """The diagnosis's simulation prepared again at half the time step, or ``None`` (no time-step setting)."""
    from ...solvers import api

    half = half_step_settings(P.sim, settings)
    if half is None:
        return None
    return api.prepare(P.sim.solver, body, material.to_spec(measurement.rest), measurement.scenario, frame_times,
                       device=device, settings=half, progress=None)


def _half_step_jobs(P: Problem, ref: Reference, c: CandidateResult, sigma: float, sim2, lm_iterations: int,
                    progress: Progress, reference_fit: Optional[FitResult] = None,
                    reference_store: Optional[dict] = None) -> tuple[list, Callable[[list], dict]]:
    """Re-check candidate ``c`` with the simulation ``sim2`` at half the time step: (jobs, finish) — the refits of
    the reference (unless ``reference_fit`` gives it already) and of the candidate, and the function that turns
    their results into the check's verdict (it puts the reference's refit in ``reference_store["fit"]``)."""
    if sim2 is None:
        return [], lambda results: {"ok": None, "verdict": "the solver exposes no time-step setting; not re-checked"}

    def refit(param: Parametrisation, u0) -> Callable[[], FitResult]:
        def job() -> FitResult:
            lo, hi = param.bounds()
            return levenberg_marquardt(P.residuals(param, sim=sim2), param.internal() if u0 is None else u0, lo, hi,
                                       param.steps(), max_iter=max(3, lm_iterations // 2), progress=progress)
        return job

    def finish(fits: list) -> dict:
        if reference_fit is not None:
            fits = [reference_fit] + list(fits)
        if reference_store is not None:
            reference_store["fit"] = fits[0]
        sses = {"reference": P.sse(fits[0].residual), "candidate": P.sse(fits[1].residual)}
        lr = sig.likelihood_ratio(sses["reference"], sses["candidate"], sigma)
        share = sig.share_of_excess(sses["reference"], sses["candidate"], P.n_obs, sigma)
        ok = lr >= c.threshold and share >= sig.MIN_SHARE
        half = c.parametrisation.realise(fits[1].u)[1][-1]
        return {"params_half_step": half.params_dict(),
                "params": c.effect.params_dict(), "likelihood_ratio_half_step": lr, "share_half_step": share,
                "ok": bool(ok),
                "verdict": ("the effect is still needed at half the time step" if ok else
                            f"at half the time step the improvement is no longer significant (it removes "
                            f"{100 * max(share, 0.0):.0f} % of the above-noise error, {format_params(c.effect)} → "
                            f"{format_params(half)}): numerical dissipation — the model's own dissipation changes "
                            f"with the step by as much as the effect")}

    jobs = [refit(c.parametrisation, c.fit.u)]
    if reference_fit is None:
        jobs.insert(0, refit(param_for(ref, [], {}), None))
    return jobs, finish
