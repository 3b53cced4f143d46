"""The interface every solver implements, and the dispatcher over them.

Solvers are pure functions of (body, material, scenario, effects, frame
times, device) → :class:`~unipixie.core.types.Trajectory`.  Set-up (particle
filling, neighbour search, kernel compilation, material lookup) is separated
from stepping so that a caller can re-run cheaply with other effect
parameters — the diagnosis fits effects this way::

    sim = prepare("mpm", body, material, scenario, frame_times, device="cpu")
    base = sim.run([])
    dragged = sim.run([effects.make("linear_drag", c=0.8)])
    many = sim.run_batch([[], [drag], [wind]])   # one launch per step where the solver allows

Each solver module (:data:`.registry.SOLVERS`) defines a subclass of
:class:`Simulation` and a ``prepare(body, material, scenario, frame_times,
device="cpu", settings=None, progress=None)`` function.
"""

from __future__ import annotations

import copy
import importlib
from typing import Iterable, Sequence

import numpy as np

from ..core.errors import UserError
from ..core.progress import Progress
from ..core.types import Trajectory
from . import effects as effects_mod
from .body import Body
from .effects import Effect, EffectContext, PhysicsTerms
from .material_sampling import MaterialSpec
from .registry import SOLVERS, canonical_solver
from .scenario import Scenario

def check_frame_times(frame_times) -> np.ndarray:
    """(T,) float64 seconds, strictly increasing, starting at the initial state (T >= 1)."""
    t = np.asarray(frame_times, dtype=np.float64).reshape(-1)
    if t.size == 0:
        raise UserError("no frame times given (the frame range is empty)")
    if not np.all(np.isfinite(t)):
        raise UserError("frame times contain NaN/inf")
    if t.size > 1 and not np.all(np.diff(t) > 0):
        raise UserError("frame times must be strictly increasing")
    return t


class Simulation:
    """A prepared simulation; subclasses implement :meth:`_run_terms`.

    Attributes
    ----------
    solver: solver name.
    frame_times: (T,) seconds.
    sample_positions: (S, 3) rest positions of the material samples (for effect regions).
    tracked_rest: (N, 3) rest positions of the tracked points.
    device: Warp device name.
    """

    solver: str = ""

    def __init__(self, body: Body, scenario: Scenario, frame_times, device: str):
        self.body = body
        self.scenario = scenario
        self.frame_times = check_frame_times(frame_times)
        self.device = device
        self.sample_positions: np.ndarray = np.zeros((0, 3))
        self.tracked_rest: np.ndarray = np.asarray(body.tracked_points, dtype=np.float64)

    # -- effects -> terms -------------------------------------------------------------
    def effect_context(self) -> EffectContext:
        return EffectContext(sample_positions=self.sample_positions, tracked_rest_positions=self.tracked_rest)

    def terms_for(self, effect_list: Iterable[Effect]) -> PhysicsTerms:
        effect_list = list(effect_list)
        effects_mod.check_supported(effect_list, self.solver)
        return effects_mod.combine(effect_list, self.effect_context())

    # -- running ------------------------------------------------------------------------
    def run(self, effect_list: Iterable[Effect] = (), *, progress: Progress | None = None,
            particle_states: bool = False) -> Trajectory:
        """Simulate with the given effects; ``particle_states`` adds per-frame sample positions."""
        return self._run_terms([self.terms_for(effect_list)], progress=progress, particle_states=particle_states)[0]

    def run_batch(self, effect_lists: Sequence[Iterable[Effect]], *, progress: Progress | None = None) -> list[Trajectory]:
        """Simulate several environments (one effect list each); solvers that can batch do it in one launch."""
        terms = [self.terms_for(e) for e in effect_lists]
        return self._run_terms(terms, progress=progress, particle_states=False)

    def up_to(self, frames: int) -> "Simulation":
        """This prepared simulation reporting only its first ``frames`` instants (``frame_times[:frames]``).

        It shares everything prepared — body, particles or network, compiled kernels, cached device buffers and
        captured graphs — so its run is the first ``frames`` instants of this one's run and costs only their
        substeps (the diagnosis runs its fits only as far as its predictive window).  The two share those buffers:
        run them together only as runs of one simulation may be (at once only where :attr:`concurrent_runs`).
        frames: 1 … T."""
        frames = int(frames)
        if not 1 <= frames <= len(self.frame_times):
            raise ValueError(f"frames must be 1 … {len(self.frame_times)}, got {frames}")
        if frames == len(self.frame_times):
            return self
        view = copy.copy(self)
        view.frame_times = self.frame_times[:frames]
        return view

    @property
    def concurrent_runs(self) -> bool:
        """May separate runs of this prepared simulation go on at once, each in its own thread?  True where a run's
        launches are independent of any other's and leave the interpreter lock while they compute (the spring-mass
        solver's CPU kernels), so runs on several CPU cores take less time together; False by default."""
        return False

    def _run_terms(self, terms: list[PhysicsTerms], *, progress: Progress | None,
                   particle_states: bool) -> list[Trajectory]:  # pragma: no cover - abstract
        raise NotImplementedError


def solver_module(name: str):
    """The module of the named solver (:data:`.registry.SOLVERS`; an alias allowed)."""
    return importlib.import_module(f"{__package__}.{canonical_solver(name)}")


def coerce_settings(solver: str, settings):
    """The named solver's settings object from ``settings`` (``None``, a dict of its fields or the object),
    checked: an unknown key or a bad value (``anchors="abc"``) is a :class:`UserError` naming it — before any
    long work reads a value from the dict."""
    return SOLVERS[canonical_solver(solver)].settings.from_any(settings)


def prepare(solver: str, body: Body, material: MaterialSpec, scenario: Scenario, frame_times, device: str = "cpu",
            settings=None, progress: Progress | None = None) -> Simulation:
    """Prepare a simulation with the named solver (one of :data:`.registry.SOLVER_NAMES`)."""
    return solver_module(solver).prepare(body, material, scenario, frame_times, device=device, settings=settings,
                                         progress=progress)


def simulate(solver: str, body: Body, material: MaterialSpec, scenario: Scenario, frame_times,
             effect_list: Iterable[Effect] = (), device: str = "cpu", settings=None,
             progress: Progress | None = None, particle_states: bool = False) -> Trajectory:
    """Prepare and run in one call."""
    sim = prepare(solver, body, material, scenario, frame_times, device=device, settings=settings, progress=progress)
    return sim.run(effect_list, progress=progress, particle_states=particle_states)
