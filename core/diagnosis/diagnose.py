"""The diagnosis loop: compare with a measurement, find the missing physical effect, add it, repeat.

This module is the orchestrator (:func:`diagnose`, the diagnosis's defaults); the steps live beside it:
:mod:`.problem` (the measurement, the simulation and the residuals), :mod:`.base_fit` (the base model's E/ρ,
its predictive window, the base material's check), :mod:`.candidates` (the effects fitted each round),
:mod:`.checks` (their significance, held-out and half-step checks), :mod:`.results` (what is reported),
:mod:`.outliers` (samples a tracker got wrong).

::

    from unipixie.core import measurement
    from unipixie.core.diagnosis import diagnose

    m = measurement.load("drop.npz")
    result = diagnose.diagnose(m, solver="spring_mass", out_dir="report")
    print(result.identified, result.history)

What it does (``shared/specs/measurement-format.md`` §3, ``shared/notes/diagnosis.md``):

1. **Simulate** the measurement's scenario with the model as given (its material, the chosen
   solver, the effects already on) and **compare** (:mod:`.compare`): RMSE over observed
   samples, per point / instant / region, worst points and instants.
2. **Tracking outliers and noise**: samples a tracker got wrong are found from the tracks alone and treated as not
   observed (:mod:`.outliers`; ``reject_outliers``); the measurement noise σ is estimated from the tracks
   themselves (:func:`.compare.estimate_noise`).
3. **Base fit** (:mod:`.base_fit`): the base material's Young's modulus is refitted (a grid of starts, then
   Levenberg–Marquardt).  Under gravity and inertia alone the motion depends on E/ρ only,
   so this is a fit of E/ρ, reported as a scale of the stated E.  It is applied through the
   effect mechanism (a stiffness factor over the whole solid), so every solver re-runs it
   without being prepared again.
4. **Candidates** (:mod:`.candidates`): every effect of the registry (:mod:`unipixie.solvers.effects`) is fitted
   *together with* the base scale and the effects added so far (start grid + bounded LM,
   batched through ``Simulation.run_batch``).  ``stiffness_region`` searches regions (halves
   of the solid along each axis and k-means clusters of the rest positions): every region
   is probed, the few best (after compensating for a global E change) are fitted, and the
   region found is reported.
5. **Significance** (:mod:`.checks`, :mod:`.significance`): the gain must beat noise plus the extra
   parameters (a chi-bar-squared threshold for parameters bounded at "no effect",
   Bonferroni over everything tried), it must remove a real share of the structured error
   the reference model leaves (a close-but-not-identical base model leaves one), and
   refitting on the early frames must not predict the held-out later frames worse.  A
   suspected damping is re-checked at half the solver's time step (numerical dissipation).
6. **Rank** by the penalised gain; the best significant effect (or the user's pick) is
   **added** with its fitted parameters, the model re-simulated, and the round repeats until
   nothing significant remains or ``max_additions`` is reached.  ``history`` records the
   error after each addition.
7. Finally the base material is checked on its own: with the effects found, is E/ρ
   significantly different from the stated one?  (reported separately from effects.)
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Callable, Iterable, Optional, Sequence

import numpy as np

from ...solvers import effects as fx
from ..errors import UserError
from ..progress import Progress, silent
from . import sanity
from . import verdict as verdict_mod
from .base_fit import base_material_check, find_predictive_window, fit_base
from .candidates import DEFAULT_REGION_CLUSTERS, Plan, fit_candidates, not_applicable_effects, plan_for
from .checks import check_leading, half_step_simulation, judge
from .compare import compare, estimate_noise, noise_rmse
from .contact_fit import fit_base_contact, floor_caveat
from .fit import BASE_SCALE_BOUNDS, Parametrisation, base_param, e_prior_width
from .outliers import find_tracking_outliers, without_samples
from .problem import Problem, Reference, max_strain, problem_scales
from .resolution import DEFAULT_BUDGET_S, apply_floor, check_resolution, plain_settings
from .results import Diagnosis, Round, format_params

DEFAULT_MAX_ADDITIONS = 3
UNBATCHED_SOLVERS = ("spring_mass",)
"""Solvers whose ``run_batch`` results depend on what else is in the batch: the spring-mass solver steps
every environment with the smallest stable substep among them, and its time-integration error (of
deformation and contact; free flight is exact with its leapfrog stepping) then changes with the company a
parameter set keeps, which breaks finite differences and comparisons.  Their environments run one per
launch (on the CPU this costs nothing: the batched spring-mass kernel scales linearly with the environments)."""
DEFAULT_SOLVER = {"cuda": "mpm", "cpu": "spring_mass"}
"""The diagnosis's solver when none is chosen, per device kind: the most faithful one the device affords within
the diagnosis's time limits (docs/fidelity.md, docs/diagnosis.md): on a GPU MPM (the drop's rebound +2 % against
the independent referee, spring-mass +16 %, LBS +17 %; a full MPM diagnosis of the referee's cases 6–27 s on an
H200, 30–34 s for the three hardest drops; both solvers pass 15 of its 20 cases), on the CPU
spring-mass (an MPM diagnosis there takes far past 2 minutes; spring-mass is the closer of the other two on the
cantilevers' sag, −6/−7 % against LBS's −18/−19 %)."""


def default_solver(device: str) -> str:
    """:data:`DEFAULT_SOLVER` for ``device`` (``"cpu"``, ``"cuda"``, ``"cuda:N"``)."""
    return DEFAULT_SOLVER["cuda" if str(device).startswith("cuda") else "cpu"]


DEFAULT_SETTINGS = {"spring_mass": {"anchors": 192}, "mpm": {"cells_across": 12, "viscous_cfl": 0.2}}
"""Solver settings of a diagnosis when none are given: coarser than the solvers' own defaults (2048
spring-mass anchors, 32 MPM cells across), because a diagnosis runs hundreds of simulations
(MPM: ~8·C³ particles × ~200·C substeps per simulated second for C cells across a 0.2 m jelly).
MPM's viscous time-step factor is 0.2 instead of the solver's 0.1: the material-damping candidates,
whose explicit step is ∝ 1/η, then take half the substeps.  Measured (8 cells across, η = 700 and
3000 Pa·s, a thrown 0.2 m cube): stable up to 0.3, 1–1.5 mm from the 0.1 result at 0.2, unstable from
0.45 — far below the coarse grid's own error; the half-step check halves it again."""

Log = Callable[[str], None]


def diagnosis_settings(solver: str, settings=None):
    """The solver settings a diagnosis of ``solver`` runs with: a settings object as it is; a dict (or ``None``) as
    the keys it changes from :data:`DEFAULT_SETTINGS` — ``{"layout": "lattice"}`` keeps the diagnosis's 192
    spring-mass anchors (not the bake's 2048), ``{"cells_across": 16}`` MPM's viscous factor 0.2.  Returns a dict,
    a settings object, or ``None`` (the solver's own defaults)."""
    from ...solvers import api

    if settings is not None and not isinstance(settings, dict):
        return settings
    return {**DEFAULT_SETTINGS.get(api.canonical_solver(solver), {}), **(settings or {})} or None


def diagnose(measurement, solver: str = "spring_mass", *, out_dir=None, effects_on: Iterable = (),
             add: Sequence[str] = (), max_additions: int = DEFAULT_MAX_ADDITIONS, device: str = "cpu",
             settings=None, candidates: Optional[Sequence[str]] = None, region_clusters: int = DEFAULT_REGION_CLUSTERS,
             max_batch: Optional[int] = None, dt_check: bool = True, holdout: bool = True, lm_iterations: int = 6,
             predictive_window: bool = True, parallel: Optional[bool] = None, allow_long: bool = False,
             resolution_budget_s: float = DEFAULT_BUDGET_S, reject_outliers: bool = True,
             progress: Optional[Progress] = None, log: Optional[Log] = None) -> Diagnosis:
    """Diagnose ``measurement`` (:class:`~unipixie.core.measurement.Measurement`) with ``solver``.

    effects_on: effects already on in the current model (effect objects or ``"name:k=v"`` specs);
    kept fixed, except that a candidate of the same name refits them.
    add: effect names to add in this order whatever the ranking (the user's picks); after them
    the best significant effect is added each round.  max_additions: rounds that add an effect
    (0: rank only).  candidates: effect names to try (default: the whole registry).
    settings: solver settings (the solver's settings object, used as it is, or a dict of the keys to change from
    :data:`DEFAULT_SETTINGS`: ``{"layout": "lattice"}`` keeps the diagnosis's 192 anchors, not the bake's 2048).
    max_batch: parameter sets per ``run_batch`` launch (default 32; 1 for :data:`UNBATCHED_SOLVERS`).
    parallel: fit the candidates (and the held-out refits) side by side, their simulations joined into shared
    batches (:mod:`.batching`).  ``None``: on a GPU with a solver that batches (a batch of a few environments
    costs about what one does there), and where the simulation's runs go on at once in threads
    (:attr:`.Simulation.concurrent_runs`: the spring-mass solver on the CPU, a batch's runs shared among the cores,
    :attr:`.problem.Problem.threads`); otherwise off (a batch costs the sum of its environments).
    With ``max_batch`` 1 the results are identical either way; MPM batches agree with single runs to float
    round-off (its grid and sort schedule are shared by the batch), which can steer a fit slightly
    differently.  resolution_budget_s: seconds of simulation the rest of the diagnosis may spend with a finer
    model when the fitted base model is not resolved (:mod:`.resolution`; 0: never switch, enforce the floor, the
    same verdict on every machine; ``inf``: always switch).
    out_dir: write ``diagnosis.json``, the pictures and ``diagnosis.html`` there (checked for writing before
    any simulation).
    allow_long: accept measurements whose times look like milliseconds and diagnoses past the long-job
    limit (:mod:`.sanity` refuses them otherwise, as it refuses scenarios that contradict the measurement).
    reject_outliers: samples a tracker got wrong (:mod:`.outliers`, from the tracks alone) are treated as not
    observed, and the report says how many and which (``tracking_outliers``); False keeps every sample.
    Returns a :class:`Diagnosis`.
    """
    from ...solvers import api

    t_start = time.perf_counter()
    say = log or (lambda s: None)
    progress = progress or silent()
    solver = api.canonical_solver(solver)
    effects_on = [fx.parse(e) if isinstance(e, str) else e for e in effects_on]
    for e in effects_on:
        if not isinstance(e, fx.Effect):
            raise UserError(f"effects_on: not an effect: {e!r}")
    if candidates is not None and not list(candidates):
        raise UserError("candidates: the list of effects to try is empty; name at least one effect (or give none "
                        "for the whole registry)")
    names = list(fx.EFFECTS) if candidates is None else [fx.get(n).name for n in candidates]
    picks = [fx.get(n).name for n in add]
    if max_additions < 0:
        raise UserError("max_additions must be 0 or more")
    try:
        budget_ok = float(resolution_budget_s) >= 0.0  # NaN fails too
    except (TypeError, ValueError):
        budget_ok = False
    if not budget_ok:
        raise UserError(f"resolution_budget_s must be 0 or more seconds (inf: no limit), got {resolution_budget_s!r}")
    resolution_budget_s = float(resolution_budget_s)
    max_additions = max(int(max_additions), len(picks))
    if measurement.frame_count < 4:
        raise UserError(f"{measurement.source or 'measurement'}: a diagnosis needs at least 4 instants, "
                        f"got {measurement.frame_count}")
    material = measurement.require_material()
    if out_dir is not None:
        from .report import check_out_dir

        check_out_dir(out_dir)
    outliers = None
    if reject_outliers:
        outliers = find_tracking_outliers(measurement.positions, measurement.rest)
        if outliers.count:
            observed_before = measurement.observed_count
            measurement = without_samples(measurement, outliers.mask)
    if outliers is not None and outliers.count == 0 and math.isfinite(outliers.noise_sigma):
        sigma = outliers.noise_sigma  # the same tracks: the search's own estimate
    else:
        sigma = estimate_noise(measurement.positions, measurement.rest)
    settings = diagnosis_settings(solver, settings)
    api.coerce_settings(solver, settings)  # a bad value is named here, before the cost estimate reads it
    say(f"measurement: {measurement.summary()}")
    sane_warnings = sanity.check(measurement, solver, settings, sigma=sigma, allow_long=allow_long, log=say)
    body = measurement.body()
    warnings = list(measurement.warnings) + sane_warnings + list(body.warnings)
    if outliers is not None and outliers.count:
        warnings.append(outliers.describe(observed_before))
        say(warnings[-1])
    say(f"noise estimated from the tracks: σ = {1e3 * sigma:.3g} mm per coordinate "
        f"(noise floor RMSE {1e3 * noise_rmse(sigma):.3g} mm)")
    frame_times = measurement.times - measurement.times[0]
    progress.set_status(f"preparing the {solver} simulation")
    sim = api.prepare(solver, body, material.to_spec(measurement.rest), measurement.scenario, frame_times,
                      device=device, settings=settings, progress=None)
    warnings += list(getattr(sim, "warnings", []) or [])
    for e in effects_on:
        fx.check_supported([e], solver)
    names = [n for n in names if solver in fx.get(n).solvers]
    if max_batch is None:
        max_batch = 1 if solver in UNBATCHED_SOLVERS else 32
    # a batched solver on a GPU: its runs share launches there
    device_batches = solver not in UNBATCHED_SOLVERS and not str(getattr(sim, "device", device)).startswith("cpu")
    if parallel is None:
        parallel = device_batches or bool(getattr(sim, "concurrent_runs", False))
    P = Problem(measurement, sim, effects_on, progress, max_batch, parallel=parallel, device_batches=device_batches)
    P.sigma = sigma
    sc = problem_scales(measurement, material)
    # progress total is a rough count of simulations
    progress.total = max(progress.total, 40.0 * (len(names) + 2) * (1 + min(max_additions, 2)))

    # ---- 1. baseline: the model as given ------------------------------------------------------
    base_pos = P.positions_for(1.0, [])
    sc.strain = max_strain(np.asarray(measurement.rest), base_pos, body)
    baseline = compare(base_pos, measurement.positions, measurement.times, measurement.rest,
                       region_count=6)
    sse_baseline = P.rmse_all(base_pos)[0]
    say("1. the model as given: " + baseline.describe(noise_rmse(sigma)).replace("\n", "\n   "))

    # ---- 2. base fit: E/ρ, several starts (base_fit.py) -----------------------------------------
    progress.set_status("fitting the base material (E/ρ)")
    e_width = e_prior_width(P.n_obs)
    base_fit_param = Parametrisation([], [base_param(*BASE_SCALE_BOUNDS, prior_width=e_width)], list(effects_on), 1.0)
    bf, full_residual = fit_base(P, base_fit_param, lm_iterations, progress)
    base_scale = float(math.exp(bf.u[0]))
    ref = Reference(base_scale, [], P.sse(full_residual), full_residual[:P.size], list(effects_on), e_width)
    say(f"2. base fit (E/ρ; E and density cannot be separated from gravity and inertia): "
        f"E × {base_scale:.3g} → RMSE {1e3 * math.sqrt(ref.sse / P.n_obs):.2f} mm")
    horizon = None
    if predictive_window:
        progress.set_status("checking where the model is predictive")
        win = find_predictive_window(P, ref, sigma, sc)
        if win is not None:
            P.set_window(win)
            horizon = float(measurement.times[np.nonzero(win)[0][-1]])
            e_width = e_prior_width(P.n_obs)
            base_fit_param = Parametrisation([], [base_param(*BASE_SCALE_BOUNDS, prior_width=e_width)],
                                             list(effects_on), 1.0)
            bf, full_residual = fit_base(P, base_fit_param, lm_iterations, progress, start=bf.u)
            base_scale = float(math.exp(bf.u[0]))
            ref = Reference(base_scale, [], P.sse(full_residual), full_residual[:P.size], list(effects_on), e_width)
            warnings.append(f"the model is predictive only up to t = {horizon:.3g} s (later its motion stops "
                            "depending smoothly on E: chaotic contact); effects are fitted and tested on that "
                            "window, errors are reported over all samples")
            say(f"   the model is predictive up to t = {horizon:.3g} s only (chaotic later): fitting and testing "
                "on that window")

    # ---- 2b. is the fitted base model resolved? (resolution.py) ---------------------------------------
    progress.set_status("re-running the fitted base model finer (resolution check)")
    resolution, finer_sim = check_resolution(
        P, lambda scale: P.model_effects(scale, ref.effects, ref.fixed), ref.scale,
        lambda s: api.prepare(solver, body, material.to_spec(measurement.rest), measurement.scenario, frame_times,
                              device=device, settings=s, progress=None),
        sigma, int(progress.total) - P.evaluations, budget_s=resolution_budget_s, say=say)
    if finer_sim is not None:  # from here on the finer model, its E/ρ refitted
        P.sim, settings = finer_sim, finer_sim.settings
        bf, full_residual = fit_base(P, base_fit_param, lm_iterations, progress,
                                     start=np.array([math.log(ref.scale * resolution.finer_E_factor)]))
        ref = Reference(float(math.exp(bf.u[0])), [], P.sse(full_residual), full_residual[:P.size],
                        list(effects_on), e_width)

    # ---- 2c. ground contact, part of the base (contact_fit.py) --------------------------------------
    contact = fit_base_contact(P, measurement, material, ref.scale, e_width, ref.sse, names, lm_iterations, progress,
                               say)
    if contact.adopted:  # the floor is one of the reference's effects: refitted with every candidate
        ref = Reference(contact.E_scale, [contact.effect], contact.sse, contact.residual, list(effects_on), e_width)

    # ---- 3.-6. rounds: candidates (candidates.py), their significance (checks.py) ---------------------
    rounds: list[Round] = []
    ref_base = ref
    history = [{"effects": [e.name for e in effects_on], "rmse": float(baseline.rmse), "E_scale": 1.0}]
    history_positions = [base_pos]
    added: list[fx.Effect] = []
    plans = {n: plan_for(n, sc, material.mean_E()) for n in names}
    if contact.adopted:
        plans[contact.effect.name] = Plan([], contact.scales, contact.bounds)
    not_applicable = not_applicable_effects(names, measurement, sigma)
    round_no = 0
    early_material, early_material_ref = None, None  # the base-material check run with round 1 (GPU), its reference

    @functools.cache
    def half_step_sim():
        """The simulation at half the time step, prepared when first needed."""
        return half_step_simulation(P, settings, measurement, material, body, frame_times, device)
    while True:
        round_no += 1
        say(f"{2 + round_no}. round {round_no}: fitting {len(names) - len(not_applicable)} candidate effects "
            f"against {'the refitted base' if not added else ' + '.join(e.name for e in added)}"
            f"{' (its ground contact refitted with each)' if contact.adopted else ''} "
            f"(RMSE {1e3 * math.sqrt(ref.sse / P.n_obs):.2f} mm)")
        todo = [name for name in names if name not in not_applicable
                # already added: its parameters are refitted with every later candidate
                and (name not in [e.name for e in ref.effects] or name == "stiffness_region")]

        def candidates_job():
            return fit_candidates(P, ref, todo, sc, material, plans, region_clusters=region_clusters,
                                  lm_iterations=lm_iterations, sigma=sigma, progress=progress, round_no=round_no)
        if round_no == 1 and P.device_batches:
            # on a GPU the base-material check of this reference goes with the candidates (its ~14 small launches
            # joined to theirs): used when no effect is added (or the addition is retracted), else run again below
            cands, early_material = P.side_by_side(
                [candidates_job, lambda: base_material_check(P, ref, material, sigma, lm_iterations, progress, plans)])
            early_material_ref = ref
        else:
            cands = candidates_job()
        judge(P, ref, cands, sse_baseline, sigma)
        apply_floor(resolution, cands, ref.residual, P.n_obs)  # imitating the discretisation error: not significant
        cands.sort(key=lambda c: -c.score)
        check_leading(P, ref, cands, sigma, holdout=holdout, dt_check=dt_check, half_step_sim=half_step_sim,
                      lm_iterations=lm_iterations, progress=progress, round_no=round_no)
        cands.sort(key=lambda c: (not c.significant, -c.score))
        identified = next((c.name for c in cands if c.significant), None)
        rnd = Round(list(ref.effects), ref.scale, math.sqrt(ref.sse / P.n_obs), ref.sse, cands, identified,
                    not_applicable=dict(not_applicable))
        rounds.append(rnd)
        for c in cands:
            say(f"   {c.name:18s} RMSE {1e3 * c.rmse:8.2f} mm  explained {100 * c.explained:5.1f} %  "
                f"Λ {c.lr:10.4g} (needs {c.threshold:.3g})  share {100 * c.share:5.1f} %  "
                f"{'SIGNIFICANT' if c.significant else 'no'}  {format_params(c.effect)}  "
                f"[{c.evaluations} sims, {c.seconds:.1f} s]")
        for n, why in not_applicable.items():
            say(f"   {n:18s} not tried: {why}")
        # choose ---------------------------------------------------------------------------------------
        if max_additions == 0:
            break
        choice = None
        if len(added) < len(picks):
            want = picks[len(added)]
            choice = next((c for c in cands if c.name == want), None)
            if choice is None:
                raise UserError(f"cannot add {want!r}: it was not fitted "
                                f"({not_applicable.get(want, 'not a candidate for this solver or already added')})")
            rnd.added_by = "user"
        elif identified is not None:
            choice = cands[0]
            rnd.added_by = "ranking"
        if choice is None:
            say("   nothing significant remains")
            break
        rnd.added = choice.effect
        added.append(choice.effect)
        ref = Reference(choice.E_scale, list(choice.effects), choice.sse, choice.residual,
                         [e for e in ref.fixed if e.name != choice.name or e.name == "stiffness_region"],
                        ref.prior_width)
        pos = P.positions_for(ref.scale, ref.effects, ref.fixed, full=True)
        history_positions.append(pos)
        history.append({"effects": [e.name for e in ref.fixed] + [e.name for e in ref.effects],
                        "rmse": P.rmse_all(pos)[1], "E_scale": float(ref.scale),
                        "params": [e.to_dict() for e in ref.effects]})
        say(f"   added {choice.name} ({format_params(choice.effect)}), E × {ref.scale:.3g}: RMSE → "
            f"{1e3 * history[-1]['rmse']:.2f} mm")
        if len(added) >= max_additions:
            say(f"   stopping after {len(added)} addition(s) (max_additions)")
            break

    # ---- 6b. an honest verdict: no least-bad effect named (verdict.py) ------------------------------------
    # judged on every observed sample, as the verdict is (beyond a predictive window too: a model that is right
    # does not leave the measurement far behind there either)
    if added and not picks and history[-1]["rmse"] > verdict_mod.FAR_ABOVE_NOISE * noise_rmse(sigma):
        why = verdict_mod.retract(rounds, history[-1]["rmse"], noise_rmse(sigma))
        say("   " + why)
        warnings.append(why)
        ref, added = ref_base, []
        del history[1:], history_positions[1:]

    caveat = floor_caveat(contact, [e.name for e in added])  # a lossy floor and a lossy material look alike
    if caveat is not None:
        say("   note: " + caveat)
        warnings.append(caveat)

    # ---- 7. base material on its own (base_fit.py) ------------------------------------------------
    progress.set_status("checking the base material")
    if early_material is not None and ref is early_material_ref:
        base_material = early_material
    else:
        base_material = base_material_check(P, ref, material, sigma, lm_iterations, progress, plans)
    if base_material.get("looks_wrong"):
        say(f"   base material looks wrong: E/ρ × {base_material['E_scale']:.3g} "
            f"(RMSE {1e3 * base_material['rmse_stated_E']:.2f} mm with the stated E, "
            f"{1e3 * base_material['rmse_fitted_E']:.2f} mm with the fitted one)")
    final_pos = history_positions[-1] if len(history_positions) > 1 else P.positions_for(ref.scale, ref.effects,
                                                                                          ref.fixed, full=True)
    if len(history_positions) == 1:
        history_positions.append(final_pos)
    final = compare(final_pos, measurement.positions, measurement.times, measurement.rest,
                    regions={r.name: r.indices for r in baseline.regions})
    identified = rounds[0].identified if rounds else None
    contact_at = _contact_times(final_pos, measurement.times, measurement.scenario.ground_height, sc.size)
    settings_used = _settings_dict(P.sim)
    result = Diagnosis(solver=solver, measurement_source=str(measurement.source), times=measurement.times,
                       rest_positions=np.asarray(measurement.rest), measured=measurement.positions,
                       noise_sigma=sigma, baseline=baseline, baseline_positions=base_pos, final=final,
                       final_positions=final_pos, rounds=rounds, history=history,
                       history_positions=history_positions, base_material=base_material, effects_on=effects_on,
                       added=added, E_scale=ref.scale, identified=identified, wall_s=0.0,
                       simulations=P.evaluations, ground_height=measurement.scenario.ground_height,
                       warnings=warnings, contact_times=contact_at, settings=settings_used, horizon=horizon,
                       base_contact=contact.to_dict(P.n_obs), resolution=resolution.to_dict(),
                       tracking_outliers=(outliers.to_dict(measurement.times) if outliers is not None
                                          else {"checked": False}))
    result.verdict = verdict_mod.for_diagnosis(result)
    result.wall_s = time.perf_counter() - t_start
    say(f"verdict: {result.verdict['sentence']}")
    say(f"done in {result.wall_s:.1f} s ({P.evaluations} simulations, {P.sim_seconds:.1f} s simulating)")
    if out_dir is not None:
        from . import report

        paths = report.write_report(result, out_dir)
        say(f"report: {paths['html']}")
    return result


def _contact_times(positions: np.ndarray, times: np.ndarray, ground: Optional[float], size: float) -> list:
    """Instants (s) at which the simulated solid first touches the ground after being clear of it."""
    if ground is None:
        return []
    zmin = np.nanmin(positions[..., 2], axis=1) - ground
    touching = zmin <= 0.01 * size
    out = []
    for i in range(len(times)):
        if touching[i] and (i == 0 or not touching[i - 1]):
            out.append(float(times[i]))
    return out


def _settings_dict(sim) -> dict:
    s = getattr(sim, "settings", None)
    return plain_settings(s) if s is not None and dataclasses.is_dataclass(s) else {}
