"""Before a diagnosis fits anything: does the stated scenario fit the measurement at all?

A diagnosis compares a simulation of the *stated* scenario with the measured motion.  When the
scenario contradicts the measurement in a way no physical effect can repair — the solid starts
below the ground, the clamp holds every point, the coordinates are in the wrong unit, the times
are milliseconds — every effect fits badly and the ranking means nothing.  :func:`check` finds
these before any simulation and refuses them (a :class:`~unipixie.core.errors.UserError` naming
what is wrong and the remedy) or returns warnings for milder doubts.

Checks (σ is the noise estimated from the tracks, ``size`` the rest shape's largest extent):

* **size** — the solid must be 1 µm to 100 km across (the bake's range,
  :data:`unipixie.core.bake.SIZE_REFUSE_RANGE`); outside 1 mm to 1 km a warning.
* **ground** — no rest point more than ``max(5σ, 2 % of size)`` below the ground plane; no more than
  5 % of the observed samples more than ``max(5σ, 5 % of size)`` below it (the measurement passes
  through the stated ground).
* **clamp** — the pinned box must leave some points free; the points it holds must not move in
  the measurement by more than ``max(10σ, 5 % of size)`` (median; more than 8σ is a warning).
* **reach** — no observed point farther from its rest position than ten times what the scenario can
  explain (size + |v₀|·T + ½·2|g|·T² + |ω|·size·T): such values are unit mistakes or sentinels for
  "not observed" (use NaN).
* **time unit** — a median step of 0.5 s or more (at most 2 instants per second: no motion of a solid is
  resolved that coarsely) looks like milliseconds or frame numbers, not seconds; whole-number times in
  steps of 1 are named frame numbers.
* **gravity** — ``|g|`` above :data:`GRAVITY_REFUSE` (100 g) is a unit mistake (mm/s²) and refused; above
  :data:`GRAVITY_WARN` a warning (no planet's).
* **material** — a stated density above :data:`DENSITY_REFUSE` (denser than any solid) or E above
  :data:`E_REFUSE` (stiffer than diamond) is refused as a unit mistake; a density below :data:`DENSITY_WARN`
  (g/cm³ for kg/m³?) or E below :data:`E_WARN` (MPa for Pa?) is a warning.
* **gravity's sign** — with a ground, gravity must not point away from it (positive z) while the measured solid
  touches the ground (within the ground tolerance above): the solid would be pulled off the ground it is seen
  resting on or striking; a wind or drag would then be "found" to undo the wrong sign.
* **initial motion** — the stated initial velocity (and spin, at the solid's size) must not carry the solid
  farther than :data:`REACH_FACTOR` times the farthest any tracked point moves, even under a deceleration of
  :data:`STOPPING_DECELERATION` (friction, drag and impacts together): such a velocity is a unit mistake (mm/s).
* **cost** — :mod:`unipixie.core.cost`: the whole diagnosis (about :data:`DIAGNOSIS_SIMULATIONS`
  simulations) must stay below the long-job limit unless ``allow_long``.

Time-unit and cost refusals can be overridden with ``allow_long`` (``--allow-long``); the others
are contradictions and cannot.
"""

from __future__ import annotations

import math
from typing import Callable, Optional

import numpy as np

from ...solvers.materials import DENSITY_REFUSE, E_REFUSE
from ..errors import UserError

GROUND_TOLERANCE = (5.0, 0.02)
"""A rest point may lie below the ground by ``max(5σ, 2 % of the size)`` (noise, a resting contact)."""
PENETRATION_TOLERANCE = (5.0, 0.05)
"""An observed sample counts as through the ground below ``max(5σ, 5 % of the size)``."""
PENETRATION_SHARE = 0.05
"""Refuse when more than this share of the observed samples is through the ground."""
CLAMP_MOTION_REFUSE = (10.0, 0.05)
"""Refuse when the clamped points move (median) by more than ``max(10σ, 5 % of the size)``."""
CLAMP_MOTION_WARN = 8.0
"""Warn when the clamped points move (median of their largest displacement) by more than 8σ (noise alone
reaches ~4-5σ over a few hundred instants)."""
REACH_FACTOR = 10.0
"""An observed point may be at most this many times farther from its rest than the scenario explains."""
MILLISECONDS_STEP = 0.5
"""A median time step this long (s) or longer looks like milliseconds or frame numbers (whatever the duration:
five frame numbers 0..4 are as wrong as five hundred)."""
GRAVITY_REFUSE = 1000.0
"""m/s²: a stated gravity stronger than this (about 100 g) is refused as a unit mistake (9810 mm/s² for 9.81 m/s²)."""
GRAVITY_WARN = 30.0
"""m/s²: a stated gravity stronger than this (about 3 g, more than any planet's surface but Jupiter's 25) is a warning."""
DENSITY_WARN = 10.0
"""kg/m³: a stated density below this (lighter than any solid but aerogels) is a warning: g/cm³ for kg/m³?"""
E_WARN = 10.0
"""Pa: a stated Young's modulus below this (softer than the softest gels) is a warning: MPa or kPa for Pa?"""
STOPPING_DECELERATION = 1000.0
"""m/s²: the strongest deceleration the initial-motion check grants the scene (about 100 g: friction, drag and
impacts together; a 20 m/s throw into the ground may stop in 0.2 m, a 3e8 m/s one cannot stop in a lab)."""
DIAGNOSIS_SIMULATIONS = 300
"""About how many simulations a diagnosis runs (measured: ~275 for the MPM benchmark diagnosis)."""


def _where(measurement) -> str:
    return f"{measurement.source}: " if measurement.source else ""


def check(measurement, solver: str, settings=None, *, sigma: Optional[float] = None, allow_long: bool = False,
          log: Optional[Callable[[str], None]] = None, estimate_cost: bool = True) -> list[str]:
    """Refuse (``UserError``) a measurement whose stated scenario cannot describe it; return warnings.

    measurement: :class:`~unipixie.core.measurement.Measurement` (with a material); solver: the
    diagnosing solver; settings: its settings (for the cost estimate); sigma: the noise σ (m) if
    already estimated; allow_long: accept millisecond-looking times and long runs; estimate_cost: also
    estimate (and limit) the diagnosis's cost (``measure show`` checks the rest only).
    """
    from ..bake import SIZE_REFUSE_RANGE, SIZE_WARN_RANGE
    from .compare import estimate_noise

    say = log or (lambda s: None)
    src = _where(measurement)
    warnings: list[str] = []
    rest = np.asarray(measurement.rest, dtype=np.float64)
    pos = np.asarray(measurement.positions, dtype=np.float64)
    obs = measurement.observed
    times = np.asarray(measurement.times, dtype=np.float64)
    sc = measurement.scenario
    extent = rest.max(0) - rest.min(0)
    size = float(np.max(extent))
    if sigma is None:
        try:
            sigma = estimate_noise(pos)
        except UserError:
            sigma = 0.0
    sigma = float(sigma) if math.isfinite(sigma) else 0.0

    # ---- size: a unit mistake shows here first --------------------------------------------------
    lo, hi = SIZE_REFUSE_RANGE
    if not (lo <= size <= hi):
        raise UserError(f"{src}the solid is {size:.3g} m across (rest positions), outside what UniPixie simulates "
                        f"({lo:g} m to {hi:g} m): positions must be in metres — convert millimetres (× 0.001) or "
                        "check for sentinel values standing for 'not observed' (use NaN or an empty CSV cell)")
    wlo, whi = SIZE_WARN_RANGE
    if not (wlo <= size <= whi):
        warnings.append(f"the solid is {size:.3g} m across: positions are read as metres")

    # ---- gravity: metres per second squared ----------------------------------------------------------
    g = float(np.linalg.norm(sc.gravity))
    if g > GRAVITY_REFUSE:
        raise UserError(f"{src}scenario key 'gravity' is {g:.4g} m/s² ({g / 9.81:.3g} g): it must be in m/s² — "
                        "9810 would be Earth's gravity in mm/s², give [0, 0, -9.81]")
    if g > GRAVITY_WARN:
        warnings.append(f"gravity is {g:.4g} m/s² ({g / 9.81:.3g} g), stronger than any planet's surface: is scenario "
                        "key 'gravity' in m/s²?")

    # ---- material: pascals and kilograms per cubic metre -------------------------------------------
    material = measurement.material
    if material is not None:
        rho = np.asarray(material.density, dtype=np.float64)
        E = np.asarray(material.E, dtype=np.float64)
        if float(rho.max()) > DENSITY_REFUSE:
            raise UserError(f"{src}the stated density is {float(rho.max()):.3g} kg/m³, denser than any solid (osmium: "
                            "22 590 kg/m³): the scenario's material must be in kg/m³ (water 1000)")
        if float(E.max()) > E_REFUSE:
            raise UserError(f"{src}the stated Young's modulus is {float(E.max()):.3g} Pa, stiffer than any solid "
                            "(diamond: 1.2e12 Pa): the scenario's material must be in pascals (steel 2e11)")
        if float(rho.min()) < DENSITY_WARN:
            warnings.append(f"the stated density is {float(rho.min()):.3g} kg/m³, lighter than any solid but "
                            "aerogels: is it in kg/m³ (1000 for water, not 1 g/cm³)?")
        if float(E.min()) < E_WARN:
            warnings.append(f"the stated Young's modulus is {float(E.min()):.3g} Pa, softer than the softest gels: "
                            "is it in pascals (not kPa or MPa)?")

    # ---- reach: no point can be farther from rest than the scenario allows -----------------------
    duration = float(times[-1] - times[0]) if len(times) > 1 else 0.0
    v0 = float(np.linalg.norm(sc.initial_velocity))
    w0 = float(np.linalg.norm(sc.initial_angular_velocity))
    reach = REACH_FACTOR * (size + v0 * duration + g * duration ** 2 + w0 * size * duration)
    disp = np.linalg.norm(pos - rest[None], axis=-1)
    disp = np.where(obs, disp, 0.0)
    if disp.size and float(disp.max()) > reach:
        t_i, p_i = np.unravel_index(int(np.argmax(disp)), disp.shape)
        far = int(np.sum(disp > reach))
        raise UserError(f"{src}point {p_i} at t = {times[t_i]:.6g} s is {disp[t_i, p_i]:.3g} m from its rest position "
                        f"({far} sample(s) beyond {reach:.3g} m, ten times what the scenario's size, initial motion and "
                        "gravity can explain over the measurement): a unit mistake or a sentinel value for 'not "
                        "observed' — mark unobserved samples with NaN (an empty CSV cell)")

    # ---- initial motion: a stated velocity the measured solid never shows ------------------------------
    moved = float(disp.max()) if disp.size else 0.0
    speed = v0 + w0 * 0.5 * size
    if speed > 0.0 and duration > 0.0:
        a = STOPPING_DECELERATION
        stop_time = speed / a
        travel = speed ** 2 / (2 * a) if stop_time <= duration else speed * duration - 0.5 * a * duration ** 2
        if travel > REACH_FACTOR * (moved + size):
            raise UserError(f"{src}the stated initial motion ({v0:.3g} m/s, spin {w0:.3g} rad/s) would carry the solid "
                            f"at least {travel:.3g} m even under a deceleration of {a:g} m/s², but no tracked point "
                            f"moves more than {moved:.3g} m: scenario keys 'initial_velocity' (m/s) and "
                            "'initial_angular_velocity' (rad/s) must be in SI units (mm/s ÷ 1000, degrees/s × π/180)")

    # ---- time unit ------------------------------------------------------------------------------
    if len(times) > 1:
        step = float(np.median(np.diff(times)))
        if step >= MILLISECONDS_STEP:
            frames = bool(np.all(times == np.round(times)) and np.allclose(np.diff(times), 1.0))
            what = "frame numbers" if frames else "milliseconds or frame numbers"
            msg = (f"{src}the times run over {duration:.6g} s in steps of {step:.3g} s ({1 / step:.3g} instants per "
                   f"second): they look like {what}, not seconds — divide milliseconds by 1000 (frame numbers by "
                   "the frame rate)")
            if not allow_long:
                raise UserError(msg + "; if they really are seconds, pass --allow-long")
            warnings.append(msg.removeprefix(src))

    # ---- ground ----------------------------------------------------------------------------------
    if sc.ground_height is not None:
        h = float(sc.ground_height)
        tol = max(GROUND_TOLERANCE[0] * sigma, GROUND_TOLERANCE[1] * size)
        below = rest[:, 2] < h - tol
        if np.all(rest[:, 2] < h - tol):
            raise UserError(f"{src}the whole solid starts below the ground: the ground is at z = {h:g} m, the solid's "
                            f"highest rest point at z = {rest[:, 2].max():.4g} m. Heights are metres with z up; fix "
                            "scenario key 'ground' ({\"height\": z}) or set it to null (no ground)")
        if np.any(below):
            raise UserError(f"{src}{int(below.sum())} of {len(rest)} rest points lie more than {tol:.3g} m below the "
                            f"ground (z = {h:g} m; lowest at z = {rest[:, 2].min():.4g} m): the solid cannot start "
                            "inside the ground. Fix scenario key 'ground' ({\"height\": z}, metres, z up) or set it "
                            "to null")
        ptol = max(PENETRATION_TOLERANCE[0] * sigma, PENETRATION_TOLERANCE[1] * size)
        z = np.where(obs, pos[..., 2], np.inf)
        through = z < h - ptol
        n_obs = max(int(obs.sum()), 1)
        if through.sum() > PENETRATION_SHARE * n_obs:
            raise UserError(f"{src}{100 * through.sum() / n_obs:.0f} % of the observed samples are more than "
                            f"{ptol:.3g} m below the stated ground (z = {h:g} m): the measured solid passes through "
                            "it, so the ground is not where the scenario says. Fix scenario key 'ground' or set it "
                            "to null")

        # gravity's sign: pulled off the ground the solid is seen touching
        gvec = np.asarray(sc.gravity, dtype=np.float64)
        touching = bool(np.any(z < h + tol))
        if g > 0 and float(gvec[2]) > 0.0 and touching:
            raise UserError(f"{src}scenario key 'gravity' {list(map(float, gvec))} points up, away from the ground "
                            f"(z = {h:g} m), yet the measured solid touches the ground: gravity pulls towards the "
                            "ground below the solid (z is up), e.g. [0, 0, -9.81]; or set 'ground' to null")

    # ---- clamp -----------------------------------------------------------------------------------
    if sc.pinned_box is not None:
        pinned = sc.pinned_mask(rest)
        if np.all(pinned):
            raise UserError(f"{src}the clamp (scenario key 'pinned_box') holds all {len(rest)} tracked points, so the "
                            "model cannot move at all while the measurement does; make the box cover only the "
                            "clamped part (metres, [[xmin,ymin,zmin],[xmax,ymax,zmax]]) or remove it")
        if np.any(pinned):
            d = np.where(obs[:, pinned], disp[:, pinned], np.nan)
            with np.errstate(all="ignore"):
                moved = float(np.nanmedian(np.nanmax(d, axis=0))) if np.isfinite(d).any() else 0.0
            limit = max(CLAMP_MOTION_REFUSE[0] * sigma, CLAMP_MOTION_REFUSE[1] * size)
            if moved > limit:
                raise UserError(f"{src}the {int(pinned.sum())} points inside the clamp (scenario key 'pinned_box') "
                                f"move by {moved:.3g} m in the measurement (median of their largest displacement), "
                                "but clamped material cannot move: the box is in the wrong place or too large")
            if sigma > 0 and moved > CLAMP_MOTION_WARN * sigma:
                warnings.append(f"the points inside the clamp move by {1e3 * moved:.3g} mm in the measurement "
                                f"(median), {moved / sigma:.3g}× the noise σ: is the clamp box right?")

    # ---- cost ------------------------------------------------------------------------------------
    if estimate_cost and material is not None and len(times) > 1:
        from ..cost import estimate

        est = estimate(f"this {solver} diagnosis", solver, size=size, times=times - times[0],
                       material_spec=material, points=measurement.point_count, settings=settings,
                       simulations=DIAGNOSIS_SIMULATIONS)
        say(f"estimated cost: {est.describe()}")
        est.check(allow_long, remedy="use fewer instants or a shorter measurement (measurement.subset), or a "
                                     "coarser solver setting")
    return warnings
