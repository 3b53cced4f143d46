"""What each solver gets wrong at its bake defaults: the measured floors the panel and the docs state.

The numbers are the bake-default rows (``"default": true``) of ``benchmarks/fidelity.json`` — the
refinement study of docs/fidelity.md, each measured against a reference that is not the solver
(Euler–Bernoulli for the clamped bars, the independent FEM referee for the drop, the closed forms
for the slide and the drag).  Only departures above :data:`STATED_ABOVE` are listed; the rest of the
study agrees within it.  ``tests/test_solver_fidelity.py`` re-reads the benchmark file and fails when
this table and the measurements part, so a re-measured study must update it.

    floor_lines("lbs")   # ['LBS at its bake defaults, against the continuum:', 'static bending sag -19 %', ...]
"""

from __future__ import annotations

from dataclasses import dataclass

from ..solvers.registry import SOLVERS

STATED_ABOVE = 0.05
"""Relative departures from the reference larger than this (5 %, the solver issue's bar) are stated."""


@dataclass(frozen=True)
class MeasuredDeparture:
    """One figure's signed relative error at the bake default: (solver − reference) / reference."""

    metric: str
    """Metric name in ``benchmarks/fidelity.json`` (``tip_sag``, ``frequency``, ``rebound_peak``, ``contact_duration``)."""
    scenes: tuple
    """Scenes of the study it was measured on (the worst of them is :attr:`error`)."""
    error: float
    """Signed relative error of the worst scene (dimensionless; 0.17 = 17 % too much)."""


METRIC_WORDS = {
    "tip_sag": "static bending sag",
    "frequency": "bending frequency",
    "rebound_peak": "drop rebound height",
    "contact_duration": "ground contact time",
}
"""How the panel names each metric."""

SHORT_WORDS = {"tip_sag": "sag", "frequency": "frequency", "rebound_peak": "rebound", "contact_duration": "contact"}
"""The same, in the one line of a refinement's figures."""

CANTILEVERS = ("cantilever_y", "cantilever_z")

MEASURED_FLOORS: dict = {
    "mpm": (),
    "spring_mass": (
        MeasuredDeparture("contact_duration", ("drop",), 0.121),
        MeasuredDeparture("tip_sag", CANTILEVERS, -0.061),
    ),
    "lbs": (
        MeasuredDeparture("tip_sag", CANTILEVERS, -0.188),
        MeasuredDeparture("contact_duration", ("drop",), 0.0909),
        MeasuredDeparture("frequency", CANTILEVERS, 0.100),
    ),
}
"""solver → its departures above :data:`STATED_ABOVE` at the bake defaults, largest first.

MPM states none: its static sag is +2.0 % (cantilever_z, settled under drag), its frequencies within 0.8 %."""


@dataclass(frozen=True)
class MeasuredRefinement:
    """How far the solver's own resolution takes its stated departures: the rows of ``benchmarks/fidelity.json``
    measured at the ladder level ``resolution``, one :class:`MeasuredDeparture` per stated metric (its worst scene)."""

    resolution: str
    """The ladder label of those rows (``resolution`` in the benchmark file)."""
    words: str
    """How the panel names the settings."""
    departures: tuple
    """:class:`MeasuredDeparture` at that resolution, one per metric of the solver's :data:`MEASURED_FLOORS`."""


REFINED: dict = {
    "lbs": MeasuredRefinement(
        "40 handles, 16,000 samples, 3000 cubature points",
        "40 handles and 16,000 mass samples (no LBS head)",
        (MeasuredDeparture("tip_sag", CANTILEVERS, -0.032),
         MeasuredDeparture("contact_duration", ("drop",), 0.0),
         MeasuredDeparture("frequency", CANTILEVERS, 0.015))),
}
"""solver → where refining its own resolution takes the departures above (docs/fidelity.md, "LBS's bars: the handles
are the resolution"): LBS's 10 handles are what its head predicts, so the refinement is for bakes without it."""

DRIFTS: dict = {}
"""solver → how far the mean an undamped oscillation swings about moves per period, as a fraction of the static sag
(its ``error``), at the bake default, where it is above 1 % (``mean_drift_per_period`` rows of
``benchmarks/fidelity.json`` with ``relative_to_static_reference``).  None is, since MPM's F is updated with the grid
velocity's gradient (2026-11-28): its bar across its thin side sinks 0.03 mm (0.3 % of its 9.0 mm sag) a period
while it swings; with APIC's affine matrix, the default before, 0.22 mm (2.4 %) — docs/fidelity.md, "MPM's creep"."""


def floor_lines(solver: str) -> list:
    """Short lines for the panel: a heading and one line per departure, largest first, then where refining the
    solver's resolution takes them (:data:`REFINED`); [] for a solver without departures above :data:`STATED_ABOVE`
    (or an unknown name)."""
    departures = MEASURED_FLOORS.get(solver, ())
    drift = DRIFTS.get(solver)
    if not departures and not drift:
        return []
    lines = [f"{SOLVERS[solver].label} at its bake defaults, against the continuum:"]
    for d in sorted(departures, key=lambda d: -abs(d.error)):
        lines.append(f"{METRIC_WORDS.get(d.metric, d.metric)} {100.0 * d.error:+.0f} %")
    if drift:
        lines.append(f"a swinging bar sinks {100.0 * drift.error:.0f} % of its sag per swing")
    refined = REFINED.get(solver)
    if refined is not None and departures:
        lines.append(f"refined, {refined.words}:")
        lines.append(", ".join(f"{SHORT_WORDS.get(d.metric, d.metric)} {100.0 * d.error:+.0f} %"
                               for d in sorted(refined.departures, key=lambda d: -abs(d.error))))
    return lines
