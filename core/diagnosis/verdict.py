"""The diagnosis's verdict in words, decided from the best model's error against the noise floor.

The spec's ``identified`` says which effect is missing (or ``null`` when none is significant).
``null`` alone does not mean the model explains the measurement: it also happens when the model
misses it badly and no effect of the registry helps.  The verdict decides from numbers which of
these it is, so that a report never says "the model explains these measurements" while its best
model stays far above the noise:

* ``best_rmse`` — the smallest RMSE of any model the diagnosis fitted (the model as given, the
  refitted base, every candidate, every addition), metres over all observed samples;
* ``noise_rmse`` — the RMSE noise alone gives (√3 σ, σ estimated from the tracks);
* the model **explains** the measurement when ``best_rmse ≤ EXPLAINED_WITHIN × noise_rmse``.

Codes (``diagnosis.json`` key ``verdict``: ``{"code", "explained", "sentence", ...}``):

``explained``           nothing significant is missing and the model is within the noise.
``effect_found``        an effect was identified and with it the model is within the noise.
``effect_found_partly`` an effect was identified, but even with it the model stays far above the noise.
``not_explained``       nothing the registry holds helps significantly and the model stays far above the
                        noise: the base model itself (scenario, material, solver) differs.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

EXPLAINED_WITHIN = 2.0
"""The model explains a measurement when its best RMSE is at most this many times the noise floor
(the validation's pass criterion, docs/diagnosis.md)."""

FAR_ABOVE_NOISE = 10.0
"""An effect is not named when, with it and every later addition, the model's RMSE (over every observed sample, as
the verdict judges it) stays more than this many times the noise floor: it is then only the least bad of the
registry, and the verdict says that no effect explains the difference (issue 18).  An order of magnitude: a base
model close to the truth but not identical to it leaves a few noise floors (measured on the independent referee:
1–3× after the right effect, the spring-mass network's plastic bar 3×); a missing physical law that no effect
describes leaves tens (the spring-mass network's cube bouncing on a floor that keeps energy: 22× after a stiffer
region was fitted)."""

DIRECTION_SHARE = 0.6
"""The remaining error is said to lie along one axis when that axis holds at least this share of it."""

CODES = ("explained", "effect_found", "effect_found_partly", "not_explained")


def _mm(x: float) -> str:
    return f"{1e3 * x:.3g} mm"


def decide(best_rmse: float, noise_rmse: float, identified: Optional[str], *, added: Sequence[str] = (),
           where: str = "") -> dict:
    """The verdict as data: ``code`` (one of :data:`CODES`), ``explained`` (bool), ``sentence`` (one line),
    ``best_rmse`` / ``noise_rmse`` (m), ``ratio`` (best / noise) and ``explained_within``.

    identified: the effect the diagnosis names (or ``None``); added: the effects it added (names);
    where: where and when the remaining error is largest (a phrase, optional).
    """
    best = float(best_rmse)
    noise = float(noise_rmse)
    ratio = best / noise if noise > 0 else math.inf
    if not math.isfinite(best):
        ratio = math.inf
    within = ratio <= EXPLAINED_WITHIN
    floor = f"the noise floor of {_mm(noise)}"
    times = "∞" if not math.isfinite(ratio) else f"{ratio:.3g}"
    extra = f" — it differs most {where}" if where else ""
    more = [a for a in added if a != identified]
    with_ = " + ".join([identified] + more) if identified else ""
    if identified and within:
        code = "effect_found"
        sentence = (f"{identified} is missing from the model; with {with_} the model explains these measurements "
                    f"(best RMSE {_mm(best)}, within {EXPLAINED_WITHIN:g}× {floor})")
    elif identified:
        code = "effect_found_partly"
        sentence = (f"{identified} is missing from the model, but even with {with_} the model does not explain these "
                    f"measurements: its best RMSE is {_mm(best)}, {times}× {floor}{extra}; something no effect of "
                    "the registry describes differs as well (check the scenario, the material and the solver's "
                    "resolution)")
    elif within:
        code = "explained"
        sentence = (f"no effect is missing: the model explains these measurements (best RMSE {_mm(best)}, within "
                    f"{EXPLAINED_WITHIN:g}× {floor})")
    else:
        code = "not_explained"
        sentence = (f"the model does NOT explain these measurements: its best RMSE is {_mm(best)}, {times}× {floor}"
                    f"{extra}, and no effect of the registry removes the difference significantly; check the "
                    "scenario (ground, clamp, initial motion, units), the stated material and the solver's resolution")
    return {"code": code, "explained": bool(within), "sentence": sentence, "best_rmse": best if math.isfinite(best)
            else None, "noise_rmse": noise, "ratio": ratio if math.isfinite(ratio) else None,
            "explained_within": EXPLAINED_WITHIN}


def retract(rounds: Sequence, rmse: float, noise_rmse: float) -> str:
    """Withdraw the effects a diagnosis added by ranking because its model stays far above the noise (in place on
    ``rounds``: no round identifies or adds anything; every candidate that was significant is no longer, with the
    reason).  rmse: the final model's RMSE over every observed sample (m); noise_rmse: the noise floor (m).
    Returns the sentence for the log and the report's warnings."""
    times = rmse / noise_rmse if noise_rmse > 0 else math.inf
    named = [r.added.name for r in rounds if getattr(r, "added", None) is not None]
    reason = (f"with it and every later addition the model stays {times:.3g}× above the noise floor (more than "
              f"{FAR_ABOVE_NOISE:g}×): it is the least bad effect of the registry, not the missing one")
    for r in rounds:
        r.identified, r.added, r.added_by = None, None, ""
        for c in r.candidates:
            if c.significant:
                c.significant = False
                c.reasons.append(reason)
    return (f"not named: {' + '.join(named)} (the best the registry offers) leaves {_mm(rmse)}, {times:.3g}× "
            f"the noise floor of {_mm(noise_rmse)}: no effect of the registry explains the difference; the base "
            "model itself differs (see where and when below)")


def where_it_differs(comparison, contact_times: Sequence[float] = ()) -> str:
    """``"in region 2 (around [x, y, z] m), at t = 0.41-0.43 s (after ground contact)"`` from a
    :class:`~unipixie.core.diagnosis.compare.Comparison` of the best model (empty if it says nothing)."""
    parts = []
    regions = getattr(comparison, "regions", None) or []
    if regions:
        r = regions[0]
        parts.append(f"in {r.name} (around [{', '.join(f'{c:.3g}' for c in r.centroid)}] m)")
    wt = list(getattr(comparison, "worst_times", None) or [])[:3]
    if wt:
        lo, hi = min(wt), max(wt)
        when = f"at t = {lo:.3g} s" if hi - lo < 1e-12 else f"at t = {lo:.3g}–{hi:.3g} s"
        if contact_times and any(t >= min(contact_times) for t in wt):
            when += " (after ground contact)"
        parts.append(when)
    axes = getattr(comparison, "axis_rmse", None)
    if axes is not None and np.all(np.isfinite(axes)) and float(np.sum(np.square(axes))) > 0:
        share = np.square(axes) / float(np.sum(np.square(axes)))
        k = int(np.argmax(share))
        if share[k] >= DIRECTION_SHARE:
            parts.append(f"mostly along {'xyz'[k]}{' (vertical)' if k == 2 else ''} "
                         f"({100 * share[k]:.0f} % of the squared error)")
    return ", ".join(parts)


def for_diagnosis(d) -> dict:
    """The verdict of a :class:`~unipixie.core.diagnosis.results.Diagnosis` (its best model: the smallest
    RMSE among the model as given, every candidate of every round and every addition)."""
    rmses = [d.final.rmse, d.baseline.rmse] + [h.get("rmse", math.inf) for h in d.history]
    for rnd in d.rounds:
        rmses += [c.rmse for c in rnd.candidates]
    finite = [float(r) for r in rmses if r is not None and math.isfinite(float(r))]
    best = min(finite) if finite else math.inf
    added = [e.name for e in d.added]
    return decide(best, d.noise_rmse, d.identified, added=added,
                  where=where_it_differs(d.final, getattr(d, "contact_times", ())))
