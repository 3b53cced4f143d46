"""The diagnosis's results: one candidate effect fitted (:class:`CandidateResult`), one round of the loop
(:class:`Round`) and the whole diagnosis (:class:`Diagnosis`; :meth:`Diagnosis.to_json` is the
``unipixie.diagnosis/1`` report, :meth:`Diagnosis.summary` its text form).

Owns the report's format and how results print; plain data, no simulation.  May use the effect registry,
:mod:`.compare` (the comparison type), :mod:`.fit` (the fit types), :mod:`.significance` (the thresholds the
report states) and :mod:`.verdict`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ...solvers import effects as fx
from . import significance as sig
from . import verdict as verdict_mod
from .compare import Comparison, noise_rmse
from .fit import FitResult, Parametrisation

REPORT_FORMAT = "unipixie.diagnosis/1"


@dataclass
class CandidateResult:
    """One effect fitted against the reference model of a round.

    effect: the fitted effect; effects: all fitted effects of this model (added so far + this);
    E_scale: the base E/ρ scale fitted with it; sse: m² over observed samples; rmse: m.
    explained: share of the round's baseline (model as given) squared error removed;
    explained_beyond_base: share of the reference (refitted base) squared error removed;
    lr: Λ = ΔSSE/σ² against the reference; threshold: the Λ needed; share: share of the
    reference's above-noise error removed; holdout: dict or None; significant: the verdict.
    """

    name: str
    effect: Optional[fx.Effect]
    effects: list
    E_scale: float
    sse: float
    rmse: float
    residual: Optional[np.ndarray] = None
    explained: float = 0.0
    explained_beyond_base: float = 0.0
    lr: float = 0.0
    threshold: float = math.inf
    share: float = 0.0
    holdout: Optional[dict] = None
    dt_check: Optional[dict] = None
    significant: bool = False
    reasons: list = field(default_factory=list)
    uncertainty: dict = field(default_factory=dict)
    free_params: list = field(default_factory=list)
    fit: Optional[FitResult] = None
    parametrisation: Optional[Parametrisation] = None
    interior: int = 0
    bounded: int = 0
    tests: int = 1
    region: Optional[dict] = None
    evaluations: int = 0
    seconds: float = 0.0
    sse_all: Optional[float] = None

    @property
    def score(self) -> float:
        """Penalised gain used for ranking: Λ − threshold (larger is better)."""
        return self.lr - (self.threshold if math.isfinite(self.threshold) else 0.0)

    def params(self) -> dict:
        return self.effect.params_dict() if self.effect is not None else {}

    def to_dict(self) -> dict:
        d = {"effect": self.name, "params": self.params(), "rmse": json_float(self.rmse),
             "explained": json_float(self.explained), "significant": bool(self.significant),
             "explained_beyond_base": json_float(self.explained_beyond_base), "E_scale": json_float(self.E_scale),
             "likelihood_ratio": json_float(self.lr), "threshold": json_float(self.threshold),
             "share_of_excess": json_float(self.share),
             "uncertainty": self.uncertainty, "reasons": list(self.reasons), "simulations": self.evaluations,
             "seconds": json_float(self.seconds)}
        if self.holdout is not None:
            d["holdout"] = self.holdout
        if self.dt_check is not None:
            d["dt_check"] = self.dt_check
        if self.region is not None:
            d["region"] = self.region
        return d


@dataclass
class Round:
    """One round of the loop: the reference model, every candidate (best first), the choice."""

    effects: list
    E_scale: float
    rmse: float
    sse: float
    candidates: list
    identified: Optional[str]
    added: Optional[fx.Effect] = None
    added_by: str = ""
    not_applicable: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"effects": [e.name for e in self.effects], "effect_params": [e.to_dict() for e in self.effects],
                "E_scale": json_float(self.E_scale), "rmse": json_float(self.rmse),
                "candidates": [c.to_dict() for c in self.candidates], "identified": self.identified,
                "added": None if self.added is None else self.added.to_dict(), "added_by": self.added_by,
                "not_applicable": dict(self.not_applicable)}


@dataclass
class Diagnosis:
    """Everything the diagnosis found (see :meth:`to_json` for the report)."""

    solver: str
    measurement_source: str
    times: np.ndarray
    rest_positions: np.ndarray
    measured: np.ndarray
    noise_sigma: float
    baseline: Comparison
    baseline_positions: np.ndarray
    final: Comparison
    final_positions: np.ndarray
    rounds: list
    history: list
    history_positions: list
    base_material: dict
    effects_on: list
    added: list
    E_scale: float
    identified: Optional[str]
    wall_s: float
    simulations: int
    ground_height: Optional[float] = None
    warnings: list = field(default_factory=list)
    contact_times: list = field(default_factory=list)
    settings: dict = field(default_factory=dict)
    horizon: Optional[float] = None
    verdict: dict = field(default_factory=dict)
    """:func:`.verdict.for_diagnosis`: code, explained, sentence (set when the diagnosis ends)."""
    base_contact: dict = field(default_factory=dict)
    """The ground contact fitted as part of the base (:meth:`.contact_fit.ContactFit.to_dict`)."""
    resolution: dict = field(default_factory=dict)
    """The base model's resolution check (:meth:`.resolution.ResolutionCheck.to_dict`)."""
    tracking_outliers: dict = field(default_factory=dict)
    """Samples set aside as tracking errors (:meth:`.outliers.TrackingOutliers.to_dict`; ``{"checked": False}``
    when the search was switched off)."""

    @property
    def candidates(self) -> list:
        return self.rounds[0].candidates if self.rounds else []

    @property
    def noise_rmse(self) -> float:
        return noise_rmse(self.noise_sigma)

    def runner_up(self) -> Optional[dict]:
        c = self.candidates
        if len(c) < 2:
            return None
        gap = (c[1].sse - c[0].sse) / max(self.noise_sigma ** 2, 1e-300)
        return {"effect": c[1].name, "rmse": json_float(c[1].rmse), "gap_likelihood_ratio": json_float(gap),
                "rmse_ratio": json_float(c[1].rmse / max(c[0].rmse, 1e-300))}

    def to_json(self) -> dict:
        """The ``unipixie.diagnosis/1`` report: the spec's keys plus extras."""
        first = self.rounds[0] if self.rounds else None
        out = {
            "format": REPORT_FORMAT,
            "solver": self.solver,
            "baseline": self.baseline.to_dict(),
            "candidates": [{"effect": c.name, "params": c.params(), "rmse": json_float(c.rmse),
                            "explained": json_float(c.explained), "significant": bool(c.significant),
                            **{k: v for k, v in c.to_dict().items()
                               if k not in ("effect", "params", "rmse", "explained", "significant")}}
                           for c in (first.candidates if first else [])],
            "identified": self.identified,
            "history": self.history,
            # extras
            "verdict": self.verdict or verdict_mod.for_diagnosis(self),
            "measurement": self.measurement_source,
            "noise_sigma": json_float(self.noise_sigma),
            "noise_rmse": json_float(self.noise_rmse),
            "runner_up": self.runner_up(),
            "base_material": self.base_material,
            "effects_on": [e.to_dict() for e in self.effects_on],
            "added": [e.to_dict() for e in self.added],
            "final": {"rmse": json_float(self.final.rmse), "E_scale": json_float(self.E_scale),
                      "worst_points": self.final.worst_points, "worst_times": self.final.worst_times},
            "rounds": [r.to_dict() for r in self.rounds],
            "not_applicable": first.not_applicable if first else {},
            "significance": {"alpha": sig.ALPHA, "min_share_of_excess": sig.MIN_SHARE,
                             "holdout_fraction": sig.HOLDOUT_FRACTION,
                             "rule": "significant = likelihood ratio ΔSSE/σ² above the chi-bar-squared threshold "
                                     "(bounded parameters, Bonferroni over all candidates and regions) AND share of "
                                     "the reference model's above-noise squared error removed ≥ min_share AND the "
                                     "fit on the early frames does not predict the held-out later frames worse"},
            "contact_times": self.contact_times,
            "base_contact": self.base_contact,
            "resolution": self.resolution,
            "tracking_outliers": self.tracking_outliers,
            "predictive_until": json_float(self.horizon),
            "wall_s": json_float(self.wall_s),
            "simulations": int(self.simulations),
            "warnings": list(self.warnings),
            "settings": self.settings,
        }
        return out

    def summary(self) -> str:
        lines = [f"baseline RMSE {1e3 * self.baseline.rmse:.2f} mm, noise ≈ {1e3 * self.noise_rmse:.2f} mm "
                 f"(σ = {1e3 * self.noise_sigma:.2f} mm per coordinate)"]
        for c in self.candidates:
            lines.append(f"  {c.name:18s} rmse {1e3 * c.rmse:8.2f} mm  explained {100 * c.explained:5.1f} %  "
                         f"{'significant' if c.significant else '-'}  {format_params(c.effect)}")
        lines.append(f"identified: {self.identified or 'none'}")
        lines.append(f"verdict: {(self.verdict or verdict_mod.for_diagnosis(self))['sentence']}")
        lines.append("history: " + " → ".join(f"{'+'.join(h['effects']) or 'base'} {1e3 * h['rmse']:.2f} mm"
                                               for h in self.history))
        bc = self.base_contact
        if bc.get("touches_ground"):
            p = bc["params"]
            lines.append(f"base contact (fitted with E/ρ): c = {p['c']:.3g} Pa·s/m, k = {p['k']:.3g} Pa/m, "
                         + ("part of the base" if bc["adopted"] else "not needed (rigid, lossless floor kept)"))
        if self.resolution.get("checked"):
            lines.append("resolution: " + self.resolution["verdict"])
        bm = self.base_material
        if bm.get("looks_wrong"):
            lines.append(f"base material looks wrong: E/ρ × {bm['E_scale']:.3g} fits better ({bm['note']})")
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def json_float(x):
    """``x`` as a float for the JSON report, ``None`` for ``None``, NaN or ±inf."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def format_params(effect: Optional[fx.Effect]) -> str:
    """An effect's parameters in one short line (``c=0.2``; a region by its size), for the log and summaries."""
    if effect is None:
        return ""
    parts = []
    for k, v in effect.params_dict().items():
        if isinstance(v, list):
            parts.append(f"{k}=[{', '.join(f'{x:.3g}' for x in v)}]")
        elif isinstance(v, dict):
            if "points" in v:
                parts.append(f"region={len(v['points'])} points")
            else:
                parts.append(f"region=box")
        else:
            parts.append(f"{k}={v:.4g}")
    return ", ".join(parts)
