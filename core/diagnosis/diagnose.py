"""The diagnosis loop: compare with a measurement, find the missing physical effect, add it, repeat.

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
2. **Noise**: the measurement noise σ is estimated from the tracks themselves
   (:func:`.compare.estimate_noise`).
3. **Base fit**: the base material's Young's modulus is refitted (a grid of starts, then
   Levenberg–Marquardt).  Under gravity and inertia alone the motion depends on E/ρ only,
   so this is a fit of E/ρ, reported as a scale of the stated E.  It is applied through the
   effect mechanism (a stiffness factor over the whole solid), so every solver re-runs it
   without being prepared again.
4. **Candidates**: every effect of the registry (:mod:`unipixie.solvers.effects`) is fitted
   *together with* the base scale and the effects added so far (start grid + bounded LM,
   batched through ``Simulation.run_batch``).  ``stiffness_region`` searches regions (halves
   of the solid along each axis and k-means clusters of the rest positions): every region
   is probed, the few best (after compensating for a global E change) are fitted, and the
   region found is reported.
5. **Significance** (:mod:`.significance`): the gain must beat noise plus the extra
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

import contextvars
import dataclasses
import functools
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Optional, Sequence

import numpy as np

from ...solvers import effects as fx
from ..errors import SimulationDiverged, UserError
from ..progress import Progress, silent
from . import sanity
from . import significance as sig
from . import verdict as verdict_mod
from .batching import BatchGate
from .compare import Comparison, compare, estimate_noise, kmeans_regions, noise_rmse, region_box
from .contact_fit import fit_base_contact
from .fit import (BASE, BASE_SCALE_BOUNDS, FitResult, FreeParam, Parametrisation, base_param, e_prior_width,
                  free_params_for, grid_search, levenberg_marquardt, uncertainty)
from .resolution import DEFAULT_BUDGET_S, apply_floor, check_resolution, half_step_settings, plain_settings

REPORT_FORMAT = "unipixie.diagnosis/1"
DAMPING_LIKE = ("linear_drag", "quadratic_drag", "material_damping")
"""Effects re-checked at half the time step (numerical dissipation looks like them)."""
DEFAULT_MAX_ADDITIONS = 3
_SEPARATE_STARTS = ("material_damping",)
"""Effects whose start grid spans decades of the stable time step: each start runs in its own launch."""
DEFAULT_REGION_CLUSTERS = 6
REGION_FACTOR_BOUNDS = (0.1, 10.0)
"""Range of the stiffness factor of one region."""
UNBATCHED_SOLVERS = ("spring_mass",)
"""Solvers whose ``run_batch`` results depend on what else is in the batch: the spring-mass solver steps
every environment with the smallest stable substep among them, and its time-integration error (of
deformation and contact; free flight is exact with its leapfrog stepping) then changes with the company a
parameter set keeps, which breaks finite differences and comparisons.  Their environments run one per
launch (on the CPU this costs nothing: the batched spring-mass kernel scales linearly with the environments)."""
DEFAULT_SOLVER = {"cuda": "mpm", "cpu": "spring_mass"}
"""The diagnosis's solver when none is chosen, per device kind: the most faithful one the device affords within
the diagnosis's time limits (docs/fidelity.md, docs/diagnosis.md): on a GPU MPM (the drop's rebound +2 % against
the independent referee, spring-mass +16 %, LBS +17 %; a full MPM diagnosis 22.5 s on an H100), on the CPU
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
MAX_DAMPING_RATIO = 0.3
"""Largest Kelvin–Voigt viscosity tried, as a damping ratio of the solid's first axial mode (ω ≈ π c / L).
Explicit solvers need a time step ∝ 1/η, so the cost of a simulation grows with η; "moderate"
damping of compact solids lies well below this."""
"""Range of the E/ρ scale the base fit may use."""

Log = Callable[[str], None]


# --------------------------------------------------------------------------- results
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
        d = {"effect": self.name, "params": self.params(), "rmse": _f(self.rmse), "explained": _f(self.explained),
             "significant": bool(self.significant),
             "explained_beyond_base": _f(self.explained_beyond_base), "E_scale": _f(self.E_scale),
             "likelihood_ratio": _f(self.lr), "threshold": _f(self.threshold), "share_of_excess": _f(self.share),
             "uncertainty": self.uncertainty, "reasons": list(self.reasons), "simulations": self.evaluations,
             "seconds": _f(self.seconds)}
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
                "E_scale": _f(self.E_scale), "rmse": _f(self.rmse),
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
        return {"effect": c[1].name, "rmse": _f(c[1].rmse), "gap_likelihood_ratio": _f(gap),
                "rmse_ratio": _f(c[1].rmse / max(c[0].rmse, 1e-300))}

    def to_json(self) -> dict:
        """The ``unipixie.diagnosis/1`` report: the spec's keys plus extras."""
        first = self.rounds[0] if self.rounds else None
        out = {
            "format": REPORT_FORMAT,
            "solver": self.solver,
            "baseline": self.baseline.to_dict(),
            "candidates": [{"effect": c.name, "params": c.params(), "rmse": _f(c.rmse), "explained": _f(c.explained),
                            "significant": bool(c.significant), **{k: v for k, v in c.to_dict().items()
                                                                    if k not in ("effect", "params", "rmse",
                                                                                 "explained", "significant")}}
                           for c in (first.candidates if first else [])],
            "identified": self.identified,
            "history": self.history,
            # extras
            "verdict": self.verdict or verdict_mod.for_diagnosis(self),
            "measurement": self.measurement_source,
            "noise_sigma": _f(self.noise_sigma),
            "noise_rmse": _f(self.noise_rmse),
            "runner_up": self.runner_up(),
            "base_material": self.base_material,
            "effects_on": [e.to_dict() for e in self.effects_on],
            "added": [e.to_dict() for e in self.added],
            "final": {"rmse": _f(self.final.rmse), "E_scale": _f(self.E_scale),
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
            "predictive_until": _f(self.horizon),
            "wall_s": _f(self.wall_s),
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
                         f"{'significant' if c.significant else '-'}  {_fmt_params(c.effect)}")
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


def _f(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _fmt_params(effect: Optional[fx.Effect]) -> str:
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


# --------------------------------------------------------------------------- the problem
_EVALUATIONS: contextvars.ContextVar = contextvars.ContextVar("unipixie_diagnosis_evaluations", default=None)
"""The simulation counter ([count]) of the fit running in this context (side-by-side fits inherit it)."""


class _Problem:
    """The measurement, the prepared simulation and the residual evaluation shared by all fits."""

    def __init__(self, measurement, sim, fixed: list, progress: Progress, max_batch: int, parallel: bool = True):
        self.m = measurement
        self.parallel = bool(parallel)
        self.gate = BatchGate(self._run_now)
        self.sim = sim
        self.fixed = list(fixed)
        self.base_effects: list = []  # part of every model run: the base's fitted ground contact (contact_fit.py)
        self.progress = progress
        self.max_batch = max(1, int(max_batch))
        self.measured = np.asarray(measurement.positions, dtype=np.float64)
        self.obs_all = measurement.observed
        self.window: Optional[np.ndarray] = None  # (T,) frames the fits use (None: all)
        self.obs = self.obs_all
        self.target = self.measured[self.obs]  # (K, 3)
        self.n_obs = int(self.obs.sum())
        pts = np.concatenate([np.asarray(sim.sample_positions, dtype=np.float64).reshape(-1, 3),
                              np.asarray(measurement.rest, dtype=np.float64)])
        lo, hi = pts.min(0), pts.max(0)
        pad = 1.0 + float(np.max(hi - lo))
        self.everything_box = np.stack([lo - pad, hi + pad])
        self.evaluations = 0
        self.sim_seconds = 0.0
        self.sigma = 0.0  # measurement noise (m), set once estimated; scales the priors
        self.size = 3 * self.n_obs  # length of the data part of a residual vector
        self.sample_frame = np.nonzero(self.obs)[0]  # frame of each observed sample (residual order)

    def with_priors(self, param: Parametrisation, u, data_residual: np.ndarray) -> np.ndarray:
        """A data residual followed by the pseudo-residuals of ``param``'s priors at ``u``."""
        extra = [self.sigma * (float(u[i]) - p.prior_center) / p.prior_width
                 for i, p in enumerate(param.params) if p.prior_width > 0]
        return np.concatenate([np.asarray(data_residual)[: self.size], np.asarray(extra, dtype=np.float64)])

    def deformation_part(self, residual: np.ndarray) -> np.ndarray:
        """The data residual with each frame's mean (over its observed points) removed (3·n_obs entries)."""
        r = np.asarray(residual)[: self.size].reshape(-1, 3)
        T = self.obs.shape[0]
        cnt = np.maximum(np.bincount(self.sample_frame, minlength=T), 1)
        mean = np.stack([np.bincount(self.sample_frame, r[:, k], minlength=T) for k in range(3)], axis=1) / cnt[:, None]
        return (r - mean[self.sample_frame]).reshape(-1)

    def sse(self, residual: np.ndarray) -> float:
        """Squared error (m²) of the data part of a residual vector (priors excluded)."""
        r = np.asarray(residual)[: self.size]
        return float(r @ r)

    # effects for one model ---------------------------------------------------------------
    def model_effects(self, scale: float, effects: Sequence[fx.Effect], fixed: Optional[list] = None) -> list:
        out = list(self.base_effects) + list(self.fixed if fixed is None else fixed) + list(effects)
        if abs(scale - 1.0) > 1e-12:
            out.append(fx.make("stiffness_region", factor=float(scale), region={"box": self.everything_box}))
        return out

    def run(self, effect_lists: list, sim=None) -> list:
        """Trajectories (T, N, 3) positions for several effect lists, batched; a diverged run gives NaN.

        From a fit running in :attr:`gate`'s jobs the request joins the other fits' in a shared batch."""
        sim = sim or self.sim
        counter = _EVALUATIONS.get()
        if counter is not None:
            counter[0] += len(effect_lists)
        if self.gate.in_job():
            return self.gate.request(effect_lists, sim)
        return self._run_now(effect_lists, sim)

    def side_by_side(self, jobs: Sequence[Callable[[], object]]) -> list:
        """Run ``jobs`` (fits) side by side with their simulations batched together (:mod:`.batching`), or one
        after another when :attr:`parallel` is off; returns their results in order."""
        if not self.parallel or len(jobs) < 2:
            return [job() for job in jobs]
        return self.gate.map(jobs)

    def _run_now(self, effect_lists: list, sim) -> list:
        out: list = []
        for i in range(0, len(effect_lists), self.max_batch):
            chunk = effect_lists[i:i + self.max_batch]
            t0 = time.perf_counter()
            try:
                trajs = sim.run_batch(chunk)
                out.extend(np.asarray(t.positions, dtype=np.float64) for t in trajs)
            except SimulationDiverged:
                for effs in chunk:  # find the offending environment(s); the others still count
                    try:
                        out.append(np.asarray(sim.run(effs).positions, dtype=np.float64))
                    except SimulationDiverged:
                        out.append(np.full(self.measured.shape, np.nan))
            self.sim_seconds += time.perf_counter() - t0
            self.evaluations += len(chunk)
            self.progress.step(len(chunk))
        return out

    def set_window(self, frames: np.ndarray) -> None:
        """Fit and test on the instants ``frames`` (T,) bool only (the predictive window)."""
        self.window = np.asarray(frames, dtype=bool)
        self.obs = self.obs_all & self.window[:, None]
        self.target = self.measured[self.obs]
        self.n_obs = int(self.obs.sum())
        self.size = 3 * self.n_obs
        self.sample_frame = np.nonzero(self.obs)[0]

    def rmse_all(self, positions: np.ndarray) -> tuple[float, float]:
        """(squared error m², RMSE m) over all observed samples, whatever the window."""
        d = positions[self.obs_all] - self.measured[self.obs_all]
        sse = float(np.sum(d * d)) if np.all(np.isfinite(d)) else math.inf
        return sse, math.sqrt(sse / max(int(self.obs_all.sum()), 1))

    def residual_of(self, positions: np.ndarray) -> np.ndarray:
        r = (positions[self.obs] - self.target).reshape(-1)
        if not np.all(np.isfinite(r)):
            return np.full(r.shape, 1e3)  # a diverged run: a huge, finite misfit
        return r

    def residuals(self, param: Parametrisation, sim=None, separate: bool = False) -> Callable[[list], list]:
        """Residual function for fits: the data residual (3·n_obs entries, metres) followed by one
        pseudo-residual per parameter with a prior (see :class:`~.fit.FreeParam`).

        ``separate`` runs each parameter set in its own launch (for sets whose stable time steps
        differ a lot, e.g. a start grid over decades of damping) — unless fits run side by side (on a GPU,
        where a batch costs what its slowest environment costs, not the sum)."""
        priors = [(i, p) for i, p in enumerate(param.params) if p.prior_width > 0]

        def with_priors(r, u):
            return self.with_priors(param, u, r)

        def fn(us: list) -> list:
            lists = []
            for u in us:
                scale, effs = param.realise(u)
                lists.append(self.model_effects(scale, effs, param.fixed))
            if separate and not self.parallel:
                pos = [self.run([one], sim)[0] for one in lists]
            else:
                pos = self.run(lists, sim)
            return [with_priors(self.residual_of(p), np.asarray(u)) for p, u in zip(pos, us)]

        return fn

    def positions_for(self, scale: float, effects: Sequence[fx.Effect], fixed: Optional[list] = None) -> np.ndarray:
        return self.run([self.model_effects(scale, effects, fixed)])[0]


# --------------------------------------------------------------------------- problem scales
@dataclass
class _Scales:
    """Duration (s), typical speed (m/s), mean E (Pa), |gravity| (m/s²), size (bounding-box diagonal, m),
    mean density (kg/m³), largest extent (m)."""

    duration: float
    speed: float
    E: float
    gravity: float
    size: float
    density: float
    extent: float
    strain: float = 0.01
    """Largest strain of the model as given (99th percentile over edges and instants), dimensionless."""


def _problem_scales(measurement, material) -> _Scales:
    pos = measurement.positions
    t = measurement.times
    com = np.nanmean(pos, axis=1)
    ok = np.all(np.isfinite(com), axis=1)
    speed = 0.0
    if ok.sum() >= 3:
        v = np.gradient(com[ok], t[ok], axis=0)
        speed = float(np.sqrt(np.mean(np.sum(v * v, axis=1))))
    v0 = float(np.linalg.norm(measurement.scenario.initial_velocity))
    g = float(np.linalg.norm(measurement.scenario.gravity))
    size = float(np.linalg.norm(np.ptp(measurement.rest, axis=0)))
    duration = max(float(t[-1] - t[0]), 1e-6)
    speed = max(speed, v0, 0.1 * math.sqrt(max(g, 1e-3) * max(size, 1e-3)), 1e-3)
    extent = float(np.max(np.ptp(measurement.rest, axis=0)))
    return _Scales(duration, speed, material.mean_E(), g, max(size, 1e-6), material.mean_density(), max(extent, 1e-6))


@dataclass
class _Plan:
    """How to fit one effect here: start values, typical magnitudes and plausible bounds per parameter."""

    starts: list
    scales: dict
    bounds: dict = field(default_factory=dict)


def _plan(name: str, sc: _Scales, E_now: float) -> _Plan:
    """Start grid, typical magnitudes and plausible bounds for the effect ``name`` in this problem.

    The ranges follow from the problem's scales: drag rates against the duration D and the
    typical speed v, a Kelvin–Voigt viscosity against E (η/E is a time: damping ratios from
    ~0.01 to ~1 for vibrations between ~1 and ~300 Hz), a yield stress against E (yield strain).
    """
    D = sc.duration
    ladder = [0.03, 0.1, 0.3, 1.0, 3.0]
    if name == "linear_drag":
        return _Plan([{"c": x / D} for x in ladder], {"c": 1.0 / D})
    if name == "quadratic_drag":
        u = 1.0 / (sc.speed * D)
        return _Plan([{"k": x * u} for x in ladder], {"k": u})
    if name == "material_damping":
        # critical damping of the fundamental mode: η ≈ 2E/ω₁ with ω₁ ≈ π c / L, c = sqrt(E/ρ)
        eta_crit = 2.0 * E_now * sc.extent / (math.pi * math.sqrt(E_now / sc.density))
        return _Plan([{"eta": eta_crit * x} for x in (0.01, 0.05, 0.25)], {"eta": eta_crit * 0.1},
                     {"eta": (0.0, eta_crit * MAX_DAMPING_RATIO)})
    if name == "ground_friction":
        return _Plan([{"mu": x} for x in (0.05, 0.15, 0.3, 0.6, 1.0)], {"mu": 0.3})
    if name == "plasticity":
        # the response to a yield stress is sharp (nothing above the largest stress, a lot just below it):
        # a fine ladder (ratio 1.35) from 1.5 × down to 1/20 of the largest elastic stress of the model
        top = E_now * max(sc.strain, 1e-4)
        ladder = top * 1.5 / 1.35 ** np.arange(11)
        return _Plan([{"yield_stress": float(y)} for y in ladder], {"yield_stress": top * 0.3},
                     {"yield_stress": (top * 1e-3, top * 10.0)})
    if name == "wind":
        return _Plan([{"acceleration": np.zeros(3)}], {"acceleration": max(0.1 * sc.gravity, 0.1)})
    if name == "stiffness_region":
        return _Plan([{"factor": 1.0}], {"factor": 1.0}, {"factor": REGION_FACTOR_BOUNDS})
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
    return _Plan(starts or [{}], {})


def _max_strain(rest: np.ndarray, positions: np.ndarray, body) -> float:
    """99th percentile over edges and instants of |l/l0 − 1| for the surface edges (or 6-nearest-neighbour
    edges) of the tracked points in simulated ``positions`` (T, N, 3)."""
    edges = None
    mesh = getattr(body, "mesh", None)
    if mesh is not None and len(mesh.vertices) == len(rest) and np.allclose(mesh.vertices, rest):
        edges = np.asarray(mesh.edges_unique, dtype=np.int64)
    if edges is None or len(edges) == 0:
        from scipy.spatial import cKDTree

        k = min(7, len(rest))
        _, nn = cKDTree(rest).query(rest, k=k)
        edges = np.stack([np.repeat(np.arange(len(rest)), k - 1), nn[:, 1:].reshape(-1)], axis=1)
    l0 = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=1)
    ok = l0 > 1e-12
    d = positions[:, edges[ok, 1]] - positions[:, edges[ok, 0]]
    strain = np.abs(np.linalg.norm(d, axis=-1) / l0[ok] - 1.0)
    strain = strain[np.isfinite(strain)]
    return float(np.percentile(strain, 99)) if strain.size else 0.01


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


# --------------------------------------------------------------------------- reference model
@dataclass
class _Reference:
    """The model a round compares against: base scale, effects added so far, their free parameters."""

    scale: float
    effects: list
    sse: float
    residual: np.ndarray
    fixed: list
    prior_width: float = math.log(10.0)


def _param_for(ref: _Reference, extra: Sequence[fx.Effect], plans: dict,
               fixed: Optional[list] = None) -> Parametrisation:
    effects = list(ref.effects) + list(extra)
    params: list[FreeParam] = [base_param(*BASE_SCALE_BOUNDS, center=ref.scale, prior_width=ref.prior_width)]
    for i, e in enumerate(effects):
        plan = plans.get(e.name)
        params += free_params_for(e, i, plan.scales if plan else {}, bounds=plan.bounds if plan else {})
    return Parametrisation(effects, params, list(ref.fixed if fixed is None else fixed), ref.scale)


# --------------------------------------------------------------------------- the diagnosis
def diagnose(measurement, solver: str = "spring_mass", *, out_dir=None, effects_on: Iterable = (),
             add: Sequence[str] = (), max_additions: int = DEFAULT_MAX_ADDITIONS, device: str = "cpu",
             settings=None, candidates: Optional[Sequence[str]] = None, region_clusters: int = DEFAULT_REGION_CLUSTERS,
             max_batch: Optional[int] = None, dt_check: bool = True, holdout: bool = True, lm_iterations: int = 6,
             predictive_window: bool = True, parallel: Optional[bool] = None, allow_long: bool = False,
             resolution_budget_s: float = DEFAULT_BUDGET_S, progress: Optional[Progress] = None,
             log: Optional[Log] = None) -> Diagnosis:
    """Diagnose ``measurement`` (:class:`~unipixie.core.measurement.Measurement`) with ``solver``.

    effects_on: effects already on in the current model (effect objects or ``"name:k=v"`` specs);
    kept fixed, except that a candidate of the same name refits them.
    add: effect names to add in this order whatever the ranking (the user's picks); after them
    the best significant effect is added each round.  max_additions: rounds that add an effect
    (0: rank only).  candidates: effect names to try (default: the whole registry).
    settings: solver settings (dict or the solver's settings object; default :data:`DEFAULT_SETTINGS`).
    max_batch: parameter sets per ``run_batch`` launch (default 32; 1 for :data:`UNBATCHED_SOLVERS`).
    parallel: fit the candidates (and the held-out refits) side by side, their simulations joined into shared
    batches (:mod:`.batching`).  ``None``: on a GPU with a solver that batches (a batch of a few environments
    costs about what one does there), off on the CPU (where a batch costs the sum of its environments).
    With ``max_batch`` 1 the results are identical either way; MPM batches agree with single runs to float
    round-off (its grid and sort schedule are shared by the batch), which can steer a fit slightly
    differently.  resolution_budget_s: seconds of simulation the rest of the diagnosis may spend with a finer
    model when the fitted base model is not resolved (:mod:`.resolution`; 0: never switch, enforce the floor).
    out_dir: write ``diagnosis.json``, the pictures and ``diagnosis.html`` there (checked for writing before
    any simulation).
    allow_long: accept measurements whose times look like milliseconds and diagnoses past the long-job
    limit (:mod:`.sanity` refuses them otherwise, as it refuses scenarios that contradict the measurement).
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
    max_additions = max(int(max_additions), len(picks))
    if measurement.frame_count < 4:
        raise UserError(f"{measurement.source or 'measurement'}: a diagnosis needs at least 4 instants, "
                        f"got {measurement.frame_count}")
    material = measurement.require_material()
    if out_dir is not None:
        from .report import check_out_dir

        check_out_dir(out_dir)
    sigma = estimate_noise(measurement.positions, measurement.rest)
    if settings is None:
        settings = dict(DEFAULT_SETTINGS.get(solver, {})) or None
    api.coerce_settings(solver, settings)  # a bad value is named here, before the cost estimate reads it
    say(f"measurement: {measurement.summary()}")
    sane_warnings = sanity.check(measurement, solver, settings, sigma=sigma, allow_long=allow_long, log=say)
    body = measurement.body()
    warnings = list(measurement.warnings) + sane_warnings + list(body.warnings)
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
    if parallel is None:
        parallel = solver not in UNBATCHED_SOLVERS and not str(getattr(sim, "device", device)).startswith("cpu")
    P = _Problem(measurement, sim, effects_on, progress, max_batch, parallel=parallel)
    P.sigma = sigma
    sc = _problem_scales(measurement, material)
    # progress total is a rough count of simulations
    progress.total = max(progress.total, 40.0 * (len(names) + 2) * (1 + min(max_additions, 2)))

    # ---- 1. baseline: the model as given ------------------------------------------------------
    base_pos = P.positions_for(1.0, [])
    sc.strain = _max_strain(np.asarray(measurement.rest), base_pos, body)
    baseline = compare(base_pos, measurement.positions, measurement.times, measurement.rest,
                       region_count=6)
    sse_baseline = P.rmse_all(base_pos)[0]
    say("1. the model as given: " + baseline.describe(noise_rmse(sigma)).replace("\n", "\n   "))

    # ---- 2. base fit: E/ρ, several starts -----------------------------------------------------
    progress.set_status("fitting the base material (E/ρ)")
    e_width = e_prior_width(P.n_obs)
    base_fit_param = Parametrisation([], [base_param(*BASE_SCALE_BOUNDS, prior_width=e_width)], list(effects_on), 1.0)
    bf, full_residual = _fit_base(P, base_fit_param, lm_iterations, progress)
    base_scale = float(math.exp(bf.u[0]))
    ref = _Reference(base_scale, [], P.sse(full_residual), full_residual[:P.size], list(effects_on), e_width)
    say(f"2. base fit (E/ρ; E and density cannot be separated from gravity and inertia): "
        f"E × {base_scale:.3g} → RMSE {1e3 * math.sqrt(ref.sse / P.n_obs):.2f} mm")
    horizon = None
    if predictive_window:
        progress.set_status("checking where the model is predictive")
        win = _predictive_window(P, ref, sigma, sc)
        if win is not None:
            P.set_window(win)
            horizon = float(measurement.times[np.nonzero(win)[0][-1]])
            e_width = e_prior_width(P.n_obs)
            base_fit_param = Parametrisation([], [base_param(*BASE_SCALE_BOUNDS, prior_width=e_width)],
                                             list(effects_on), 1.0)
            bf, full_residual = _fit_base(P, base_fit_param, lm_iterations, progress, start=bf.u)
            base_scale = float(math.exp(bf.u[0]))
            ref = _Reference(base_scale, [], P.sse(full_residual), full_residual[:P.size], list(effects_on), e_width)
            warnings.append(f"the model is predictive only up to t = {horizon:.3g} s (later its motion stops "
                            "depending smoothly on E: chaotic contact); effects are fitted and tested on that "
                            "window, errors are reported over all samples")
            say(f"   the model is predictive up to t = {horizon:.3g} s only (chaotic later): fitting and testing "
                "on that window")

    # ---- 2b. is the fitted base model resolved? (resolution.py) ---------------------------------------
    progress.set_status("re-running the fitted base model finer (resolution check)")
    resolution, finer_sim = check_resolution(
        P, P.model_effects(ref.scale, ref.effects, ref.fixed),
        lambda s: api.prepare(solver, body, material.to_spec(measurement.rest), measurement.scenario, frame_times,
                              device=device, settings=s, progress=None),
        sigma, int(progress.total) - P.evaluations, budget_s=resolution_budget_s, say=say)
    if finer_sim is not None:  # from here on the finer model, its E/ρ refitted
        P.sim, settings = finer_sim, finer_sim.settings
        bf, full_residual = _fit_base(P, base_fit_param, lm_iterations, progress, start=np.array([math.log(ref.scale)]))
        ref = _Reference(float(math.exp(bf.u[0])), [], P.sse(full_residual), full_residual[:P.size],
                         list(effects_on), e_width)

    # ---- 2c. ground contact, part of the base (contact_fit.py) --------------------------------------
    contact = fit_base_contact(P, measurement, material, ref.scale, e_width, ref.sse, names, lm_iterations, progress,
                               say)
    if contact.adopted:
        ref = _Reference(contact.E_scale, [], contact.sse, contact.residual, list(effects_on), e_width)

    # ---- 3.-6. rounds ---------------------------------------------------------------------------
    rounds: list[Round] = []
    history = [{"effects": [e.name for e in effects_on], "rmse": float(baseline.rmse), "E_scale": 1.0}]
    history_positions = [base_pos]
    added: list[fx.Effect] = []
    plans = {n: _plan(n, sc, material.mean_E()) for n in names}
    not_applicable = _not_applicable(names, measurement, sigma)
    round_no = 0

    @functools.cache
    def half_step_sim():
        """The simulation at half the time step, prepared when first needed."""
        return _half_step_sim(P, settings, measurement, material, body, frame_times, device)
    while True:
        round_no += 1
        say(f"{2 + round_no}. round {round_no}: fitting {len(names) - len(not_applicable)} candidate effects "
            f"against {'the refitted base' if not ref.effects else ' + '.join(e.name for e in ref.effects)} "
            f"(RMSE {1e3 * math.sqrt(ref.sse / P.n_obs):.2f} mm)")
        todo = [name for name in names if name not in not_applicable
                # already added: its parameters are refitted with every later candidate
                and (name not in [e.name for e in ref.effects] or name == "stiffness_region")]

        def fit_job(name: str, ref: _Reference = ref) -> Callable[[], Optional[CandidateResult]]:
            def job() -> Optional[CandidateResult]:
                if not P.parallel:
                    progress.set_status(f"round {round_no}: fitting {name}")
                counter = [0]  # simulations of this fit (its own side-by-side fits included)
                token = _EVALUATIONS.set(counter)
                w0 = time.perf_counter()
                try:
                    if name == "stiffness_region":
                        c = _fit_region(P, ref, sc, material, plans, region_clusters, lm_iterations, sigma, progress)
                    else:
                        c = _fit_candidate(P, ref, name, sc, material, plans, lm_iterations, progress)
                finally:
                    _EVALUATIONS.reset(token)
                if c is not None:
                    c.evaluations = counter[0]
                    c.seconds = time.perf_counter() - w0
                return c
            return job

        if P.parallel:
            progress.set_status(f"round {round_no}: fitting {len(todo)} candidate effects side by side")
        cands: list[CandidateResult] = [c for c in P.side_by_side([fit_job(n) for n in todo]) if c is not None]
        # significance ---------------------------------------------------------------------------
        tests = sum(c.tests for c in cands)
        if P.window is not None and cands:  # the spec's rmse / explained are over all observed samples
            full = P.run([P.model_effects(c.E_scale, c.effects, c.parametrisation.fixed if c.parametrisation
                                          else ref.fixed) for c in cands])
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
                c.uncertainty = {p.label: _f(u) for p, u in zip(c.free_params, unc) if p.slot != BASE}
        apply_floor(resolution, cands, ref.residual, P.n_obs)  # imitating the discretisation error: not significant
        cands.sort(key=lambda c: -c.score)
        # held-out window and time-step checks on the leading candidates -------------------------------
        leading = [c for c in cands if c.significant][:3]
        holdout_jobs, holdout_finish = (_holdout_jobs(P, ref, leading, sigma, progress) if holdout and leading
                                        else ([], None))
        # side by side, the half-step check of the leading candidate runs with the held-out refits (wasted only
        # when the held-out check rejects that candidate; it is then run again for the new leader below)
        dt_done: dict = {}
        ahead = leading[0] if P.parallel and leading and dt_check and leading[0].name in DAMPING_LIKE else None
        dt_jobs, dt_finish = [], None
        if ahead is not None:
            dt_jobs, dt_finish = _half_step_jobs(P, ref, ahead, sigma, half_step_sim(), lm_iterations, progress)
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
        top = next((c for c in cands if c.significant), None)
        if dt_check and top is not None and top.name in DAMPING_LIKE:
            if top.name not in dt_done:
                progress.set_status(f"round {round_no}: re-checking {top.name} at half the time step")
                jobs, finish = _half_step_jobs(P, ref, top, sigma, half_step_sim(), lm_iterations, progress)
                dt_done[top.name] = finish(P.side_by_side(jobs))
            top.dt_check = dt_done[top.name]
            if top.dt_check.get("ok") is False:
                top.significant = False
                top.reasons.append(top.dt_check["verdict"])
        cands.sort(key=lambda c: (not c.significant, -c.score))
        identified = next((c.name for c in cands if c.significant), None)
        rnd = Round(list(ref.effects), ref.scale, math.sqrt(ref.sse / P.n_obs), ref.sse, cands, identified,
                    not_applicable=dict(not_applicable))
        rounds.append(rnd)
        for c in cands:
            say(f"   {c.name:18s} RMSE {1e3 * c.rmse:8.2f} mm  explained {100 * c.explained:5.1f} %  "
                f"Λ {c.lr:10.4g} (needs {c.threshold:.3g})  share {100 * c.share:5.1f} %  "
                f"{'SIGNIFICANT' if c.significant else 'no'}  {_fmt_params(c.effect)}  "
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
        ref = _Reference(choice.E_scale, list(choice.effects), choice.sse, choice.residual,
                         [e for e in ref.fixed if e.name != choice.name or e.name == "stiffness_region"],
                         ref.prior_width)
        pos = P.positions_for(ref.scale, ref.effects, ref.fixed)
        history_positions.append(pos)
        history.append({"effects": [e.name for e in ref.fixed] + [e.name for e in ref.effects],
                        "rmse": P.rmse_all(pos)[1], "E_scale": float(ref.scale),
                        "params": [e.to_dict() for e in ref.effects]})
        say(f"   added {choice.name} ({_fmt_params(choice.effect)}), E × {ref.scale:.3g}: RMSE → "
            f"{1e3 * history[-1]['rmse']:.2f} mm")
        if len(added) >= max_additions:
            say(f"   stopping after {len(added)} addition(s) (max_additions)")
            break

    # ---- 7. base material on its own --------------------------------------------------------------
    progress.set_status("checking the base material")
    base_material = _base_material_check(P, ref, material, sigma, lm_iterations, progress, plans)
    if base_material.get("looks_wrong"):
        say(f"   base material looks wrong: E/ρ × {base_material['E_scale']:.3g} "
            f"(RMSE {1e3 * base_material['rmse_stated_E']:.2f} mm with the stated E, "
            f"{1e3 * base_material['rmse_fitted_E']:.2f} mm with the fitted one)")
    final_pos = history_positions[-1] if len(history_positions) > 1 else P.positions_for(ref.scale, ref.effects,
                                                                                          ref.fixed)
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
                       base_contact=contact.to_dict(P.n_obs), resolution=resolution.to_dict())
    result.verdict = verdict_mod.for_diagnosis(result)
    result.wall_s = time.perf_counter() - t_start
    say(f"verdict: {result.verdict['sentence']}")
    say(f"done in {result.wall_s:.1f} s ({P.evaluations} simulations, {P.sim_seconds:.1f} s simulating)")
    if out_dir is not None:
        from . import report

        paths = report.write_report(result, out_dir)
        say(f"report: {paths['html']}")
    return result


# --------------------------------------------------------------------------- candidates
def _fit_base(P: _Problem, param: Parametrisation, lm_iterations: int, progress: Progress,
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
    # alone on the device: each LM batch is small, so the next Jacobian is evaluated with the trials (lookahead)
    dfit = levenberg_marquardt(deformation, starts[best], lo, hi, param.steps(), r0=res[best],
                               max_iter=lm_iterations, progress=progress, lookahead=P.parallel)
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
                             max_iter=lm_iterations, progress=progress, lookahead=P.parallel)
    return bf, bf.residual


def _sse_and_residual(P: _Problem, positions: np.ndarray) -> tuple[float, np.ndarray]:
    r = P.residual_of(positions)
    return float(r @ r), r


CHAOS_PERTURBATION = 0.02
"""Relative change of E used to probe where the model stops being predictive."""
CHAOS_NONLINEARITY = 0.3
"""The response to E × (1 + 2ε) must stay within this fraction of twice the response to E × (1 + ε)."""


def _predictive_window(P: _Problem, ref: _Reference, sigma: float, sc: _Scales) -> Optional[np.ndarray]:
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


def _not_applicable(names: Sequence[str], measurement, sigma: float) -> dict:
    out = {}
    ground = measurement.scenario.ground_height
    if "ground_friction" in names:
        if ground is None:
            out["ground_friction"] = "the scenario has no ground"
        else:
            z = measurement.positions[..., 2]
            gap = np.nanmin(z) - ground if np.any(np.isfinite(z)) else math.inf
            size = float(np.linalg.norm(np.ptp(measurement.rest, axis=0)))
            if gap > 0.02 * size + 5 * sigma:
                out["ground_friction"] = f"the solid never comes within {1e3 * gap:.0f} mm of the ground"
    return out


def _fit_candidate(P: _Problem, ref: _Reference, name: str, sc: _Scales, material, plans: dict,
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
    param = _param_for(ref, [template], plans, fixed)
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


def _null_start(param: Parametrisation, ref: _Reference, add_new: bool) -> Optional[np.ndarray]:
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


def _wind_start(P: _Problem, ref: _Reference, param: Parametrisation, base_u: np.ndarray, idx: list) -> np.ndarray:
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


def _fit_region(P: _Problem, ref: _Reference, sc: _Scales, material, plans: dict, clusters: int,
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
            param = _param_for(ref, [template], plans)
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


# --------------------------------------------------------------------------- checks
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


def _holdout_jobs(P: _Problem, ref: _Reference, cands: Sequence[CandidateResult], sigma: float,
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

    return [refit(_param_for(ref, [], {}), None)] + [refit(c.parametrisation, c.fit.u) for c in cands], finish


def _half_step_sim(P: _Problem, settings, measurement, material, body, frame_times, device: str):
    """The diagnosis's simulation prepared again at half the time step, or ``None`` (no time-step setting)."""
    from ...solvers import api

    half = half_step_settings(P.sim, settings)
    if half is None:
        return None
    return api.prepare(P.sim.solver, body, material.to_spec(measurement.rest), measurement.scenario, frame_times,
                       device=device, settings=half, progress=None)


def _half_step_jobs(P: _Problem, ref: _Reference, c: CandidateResult, sigma: float, sim2, lm_iterations: int,
                    progress: Progress) -> tuple[list, Callable[[list], dict]]:
    """Re-check candidate ``c`` with the simulation ``sim2`` at half the time step: (jobs, finish) — the refits of
    the reference and of the candidate, and the function that turns their results into the check's verdict."""
    if sim2 is None:
        return [], lambda results: {"ok": None, "verdict": "the solver exposes no time-step setting; not re-checked"}

    def refit(param: Parametrisation, u0) -> Callable[[], FitResult]:
        def job() -> FitResult:
            lo, hi = param.bounds()
            return levenberg_marquardt(P.residuals(param, sim=sim2), param.internal() if u0 is None else u0, lo, hi,
                                       param.steps(), max_iter=max(3, lm_iterations // 2), progress=progress)
        return job

    def finish(fits: list) -> dict:
        sses = {"reference": P.sse(fits[0].residual), "candidate": P.sse(fits[1].residual)}
        lr = sig.likelihood_ratio(sses["reference"], sses["candidate"], sigma)
        share = sig.share_of_excess(sses["reference"], sses["candidate"], P.n_obs, sigma)
        ok = lr >= c.threshold and share >= sig.MIN_SHARE
        return {"params_half_step": c.parametrisation.realise(fits[1].u)[1][-1].params_dict(),
                "params": c.effect.params_dict(), "likelihood_ratio_half_step": lr, "share_half_step": share,
                "ok": bool(ok),
                "verdict": ("the effect is still needed at half the time step" if ok else
                            "at half the time step the improvement is no longer significant: numerical dissipation")}

    return [refit(_param_for(ref, [], {}), None), refit(c.parametrisation, c.fit.u)], finish


def _base_material_check(P: _Problem, ref: _Reference, material, sigma: float, lm_iterations: int,
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
            "likelihood_ratio": _f(lr), "threshold": _f(thr), "share_of_excess": _f(share),
            "likelihood_ratio_deformation": _f(lr_def), "share_of_excess_deformation": _f(share_def),
            "looks_wrong": looks_wrong, "note": note}


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
