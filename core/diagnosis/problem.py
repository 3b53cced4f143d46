"""The fitting problem a diagnosis solves: the measurement, the prepared simulation and the residuals.

:class:`Problem` runs models (the base's fitted contact, the user's effects, an E/ρ scale and the effects
being fitted) in batches, joined across side-by-side fits by :mod:`.batching`, and turns trajectories into
residual vectors (the data part over the observed samples, then the priors' pseudo-residuals);
:class:`Reference` is the model a round compares against and :func:`param_for` its parametrisation with
extra effects; :class:`Scales` the problem's typical magnitudes.  May use the effect registry,
:mod:`.batching` and :mod:`.fit`; nothing of the diagnosis above it.
"""

from __future__ import annotations

import contextvars
import math
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from ...solvers import effects as fx
from ..errors import SimulationDiverged
from ..jobs import map_in_threads, usable_cores
from ..progress import Progress
from .batching import BatchGate
from .fit import BASE_SCALE_BOUNDS, FreeParam, Parametrisation, base_param, free_params_for

EVALUATIONS: contextvars.ContextVar = contextvars.ContextVar("unipixie_diagnosis_evaluations", default=None)
"""The simulation counter ([count]) of the fit running in this context (side-by-side fits inherit it)."""


CONCURRENT_RUNS_PER_CORE = 1.5
"""Runs in flight per CPU core where a solver's runs may go on at once (:attr:`.Simulation.concurrent_runs`): more
than one, because part of every run is Python between its kernel launches (set-up, each frame's output), holding
the interpreter lock.  Measured on the referee's clamped bar, eight damped runs on this 2-core CPU: 2.18× faster
with 2 threads than one after another, 2.25× with 3 (with a launch per substep instead of per frame: 1.42×, 1.67×)."""


def concurrent_run_threads() -> int:
    """Threads that run a diagnosis's simulations at once where the solver allows it: ⌈1.5 × the usable cores⌉."""
    return max(1, math.ceil(CONCURRENT_RUNS_PER_CORE * usable_cores()))


class Problem:
    """The measurement, the prepared simulation and the residual evaluation shared by all fits."""

    def __init__(self, measurement, sim, fixed: list, progress: Progress, max_batch: int, parallel: bool = True,
                 device_batches: bool = False):
        self.m = measurement
        self.parallel = bool(parallel)
        # the runs of a launch share a GPU (a batched solver there): a few more parameter sets in a launch cost little,
        # so a check whose result may go unused is worth running early, its runs joined to other fits' launches
        self.device_batches = bool(device_batches) and self.parallel
        self.gate = BatchGate(self._run_now)
        self.sim = sim
        self.fixed = list(fixed)
        self.progress = progress
        self.max_batch = max(1, int(max_batch))
        self.threads = concurrent_run_threads()
        self.measured = np.asarray(measurement.positions, dtype=np.float64)
        self.obs_all = measurement.observed
        self.window: Optional[np.ndarray] = None  # (T,) frames the fits use (None: all)
        self.window_frames = len(self.measured)  # runs stop after this many instants (the window's last + 1)
        self._views: dict = {}  # simulation → its view up to window_frames (Simulation.up_to)
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
        out = list(self.fixed if fixed is None else fixed) + list(effects)
        if abs(scale - 1.0) > 1e-12:
            out.append(fx.make("stiffness_region", factor=float(scale), region={"box": self.everything_box}))
        return out

    def run(self, effect_lists: list, sim=None, full: bool = False) -> list:
        """Trajectories (T, N, 3) positions for several effect lists, batched; a diverged run gives NaN.

        With a predictive window (:meth:`set_window`) a run stops at the window's last instant unless ``full``: the
        fits see nothing later, and a run costs only the substeps up to there; the instants after it are NaN.  What
        is reported over every observed sample (``rmse_all``) asks for ``full`` runs.
        From a fit running in :attr:`gate`'s jobs the request joins the other fits' in a shared batch."""
        sim = self._simulation_for(sim or self.sim, full)
        counter = EVALUATIONS.get()
        if counter is not None:
            counter[0] += len(effect_lists)
        if self.gate.in_job():
            runs = self.gate.request(effect_lists, sim)
        else:
            runs = self._run_now(effect_lists, sim)
        return [self._full_length(positions) for positions in runs]

    def _simulation_for(self, sim, full: bool):
        """``sim`` itself, or (a window set and not ``full``) its view that stops at the window's end
        (:meth:`.Simulation.up_to`), one per simulation so that a batch's runs share it."""
        if full or self.window_frames >= len(sim.frame_times):
            return sim
        if sim not in self._views:
            self._views[sim] = sim.up_to(self.window_frames)
        return self._views[sim]

    def _full_length(self, positions: np.ndarray) -> np.ndarray:
        """(T, N, 3) m: a run that stopped early padded with NaN after its last instant."""
        if len(positions) == len(self.measured):
            return positions
        out = np.full(self.measured.shape, np.nan)
        out[:len(positions)] = positions
        return out

    def side_by_side(self, jobs: Sequence[Callable[[], object]]) -> list:
        """Run ``jobs`` (fits) side by side with their simulations batched together (:mod:`.batching`), or one
        after another when :attr:`parallel` is off; returns their results in order."""
        if not self.parallel or len(jobs) < 2:
            return [job() for job in jobs]
        return self.gate.map(jobs)

    def _run_now(self, effect_lists: list, sim) -> list:
        """Run ``effect_lists`` in launches of at most :attr:`max_batch` environments; where the prepared simulation
        allows it (:attr:`.Simulation.concurrent_runs`: the spring-mass solver on the CPU) the launches go on at once
        in :attr:`threads` threads, each run the same as alone.  ``sim_seconds`` counts the wall time."""
        chunks = [effect_lists[i:i + self.max_batch] for i in range(0, len(effect_lists), self.max_batch)]

        def run_chunk(chunk: list) -> list:
            try:
                return [np.asarray(t.positions, dtype=np.float64) for t in sim.run_batch(chunk)]
            except SimulationDiverged:
                out = []
                for effs in chunk:  # find the offending environment(s); the others still count
                    try:
                        out.append(np.asarray(sim.run(effs).positions, dtype=np.float64))
                    except SimulationDiverged:
                        out.append(np.full(self.measured.shape, np.nan))
                return out

        t0 = time.perf_counter()
        if len(chunks) > 1 and self.threads > 1 and getattr(sim, "concurrent_runs", False):
            results = map_in_threads(run_chunk, chunks, self.threads)
            self.progress.step(len(effect_lists))
        else:
            results = []
            for chunk in chunks:
                results.append(run_chunk(chunk))
                self.progress.step(len(chunk))
        self.sim_seconds += time.perf_counter() - t0
        self.evaluations += len(effect_lists)
        return [positions for result in results for positions in result]

    def set_window(self, frames: np.ndarray) -> None:
        """Fit and test on the instants ``frames`` (T,) bool only (the predictive window); runs then stop after
        its last instant (:meth:`run`)."""
        self.window = np.asarray(frames, dtype=bool)
        self.window_frames = int(np.nonzero(self.window)[0][-1]) + 1 if self.window.any() else len(self.measured)
        self._views = {}
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

    def positions_for(self, scale: float, effects: Sequence[fx.Effect], fixed: Optional[list] = None,
                      full: bool = False) -> np.ndarray:
        """(T, N, 3) m: one run of the base model at E/ρ × ``scale`` with ``effects`` (``full``: :meth:`run`)."""
        return self.run([self.model_effects(scale, effects, fixed)], full=full)[0]


@dataclass
class Scales:
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


def problem_scales(measurement, material) -> Scales:
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
    return Scales(duration, speed, material.mean_E(), g, max(size, 1e-6), material.mean_density(), max(extent, 1e-6))


def max_strain(rest: np.ndarray, positions: np.ndarray, body) -> float:
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


@dataclass
class Reference:
    """The model a round compares against: base scale, effects added so far, their free parameters."""

    scale: float
    effects: list
    sse: float
    residual: np.ndarray
    fixed: list
    prior_width: float = math.log(10.0)


def param_for(ref: Reference, extra: Sequence[fx.Effect], plans: dict,
              fixed: Optional[list] = None) -> Parametrisation:
    effects = list(ref.effects) + list(extra)
    params: list[FreeParam] = [base_param(*BASE_SCALE_BOUNDS, center=ref.scale, prior_width=ref.prior_width)]
    for i, e in enumerate(effects):
        plan = plans.get(e.name)
        params += free_params_for(e, i, plan.scales if plan else {}, bounds=plan.bounds if plan else {})
    return Parametrisation(effects, params, list(ref.fixed if fixed is None else fixed), ref.scale)
