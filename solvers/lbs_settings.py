"""The LBS solver's set-up and stepping settings (:class:`LBSSettings`) and their defaults (SI units).

Light on purpose (numpy only): the solver registry (:mod:`.registry`), cost estimates and the command line
read them without loading the solver, torch or Warp.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import numpy as np

from ..core.errors import UserError
from . import skinning
from .lbs_fit import DEFAULT_FIT_ITERATIONS
from .settings import SolverSettings, setting

DEFAULT_CUBATURE_POINTS = 500
DEFAULT_MASS_SAMPLES = 4000
DEFAULT_COLLISION_POINTS = 256
DEFAULT_MAX_DT = 2.5e-3
"""Largest step (s); a frame interval is split into equal steps no longer than this.

The step also sets how stiff the ground can be (the contact spring is capped at ω Δt ≤
:data:`.contact.IMPLICIT_MAX_CONTACT_RATE`, :mod:`.lbs`), so the drop's rebound converges in the step, not in the
cubature: the fidelity study's soft cube (docs/fidelity.md) rebounds to 0.1768 / 0.1622 / 0.1604 / 0.1634 /
0.1633 m at 5 / 2.5 / 1 / 0.5 / 0.25 ms (referee 0.1600 m; the 500-point default), 0.7 % from the step-converged
value at 2.5 ms against +8 % at the former 5 ms, whose soft floor gave back +10.5 % of the referee's height.  The
clamped bars' sag and frequency are the same at 5 and 2.5 ms within 0.05 %; a frame costs up to twice the steps
(the drop scene's whole run 1.06× on the CPU: set-up dominates)."""
DEFAULT_NEWTON_ITERATIONS = 4
KEPT_HESSIAN_STEPS_CPU = 16
"""Steps an elastic Hessian is kept for on the CPU (``hessian_max_age`` 0), where its evaluation is most of a
step's cost (docs/lbs.md, "Keeping the Hessian across steps")."""
INTEGRATORS = ("newmark", "backward_euler")
"""Time integrators: Newmark's average acceleration (default: no numerical damping) and backward Euler (damps
every vibration the step does not resolve: for settling into a static state with large steps)."""

@dataclass
class LBSSettings(SolverSettings):
    """Set-up and stepping options of the LBS solver.

    handles: H learned handles (the constant handle is extra).
    cubature_points / mass_samples / collision_points: sample counts (module docstring).
    skinning_params: ``None`` (fit with :func:`.lbs_fit.fit_skinning`, cached on disk) or the
        (H·64 + H,) parameters — what the model's HyperNetwork predicts.
    fit_iterations: Simplicits refinement steps when fitting.
    max_dt: largest time step, s.
    newton_iterations: at most this many Newton iterations per step.
    newton_tolerance: stop when the next Newton update (mass-weighted RMS) would be below this × the body size.
    line_search_steps: step halvings before giving up on an iteration.
    reuse_hessian: factor the Hessian once per step and reuse it for the step's later Newton
        iterations (each still has a line search on the true energy).
    hessian_max_age: keep the elastic Hessian of an earlier step for at most this many steps (1 = evaluate it at
        every step; 0 = automatic: :data:`KEPT_HESSIAN_STEPS_CPU` on the CPU, 1 on a GPU).  A kept Hessian is
        evaluated afresh when the step length changes, when the body has turned by more than
        :data:`.lbs.HESSIAN_REUSE_MAX_TURN`, and after a step whose Newton iterations converged slowly; its steps
        converge to a tenth of ``newton_tolerance`` (docs/lbs.md, "Keeping the Hessian across steps").
    clamp_stiffness: dimensionless penalty factor of the clamp (module docstring).
    friction_velocity: m/s, slip speed below which ground friction sticks.
    cache_skinning: reuse fitted parameters from the cache directory.
    torch_threads: torch intra-op threads on the CPU while stepping — the host's Newton solve, and the
        elastic terms on a CPU device (0 = leave torch's setting).
    line_search_candidates: step lengths (1, 1/2, 1/4, ...) of the backtracking line search
        evaluated together in one launch; the accepted length is the same as one at a time (the first
        that satisfies the Armijo condition).  0 = automatic: 1 on the CPU (each costs a kernel's
        work), 4 on a GPU (they cost one launch and one synchronisation).
    profile_device: time the device phases of a GPU run with CUDA events (``meta["phase_seconds"]``;
        adds a few microseconds per evaluation).  On the CPU they are always timed.
    integrator: ``"newmark"`` (default; average acceleration, no numerical damping) or ``"backward_euler"``
        (quasi-static: settles into equilibrium with large steps, and damps vibrations and bounces it does not
        resolve - not for dynamics).
    """

    solver_words: ClassVar[str] = "LBS"

    handles: int = setting(skinning.DEFAULT_HANDLES, "count")
    cubature_points: int = setting(DEFAULT_CUBATURE_POINTS, "count")
    mass_samples: int = setting(DEFAULT_MASS_SAMPLES, "count")
    collision_points: int = setting(DEFAULT_COLLISION_POINTS, "count")
    skinning_params: Optional[np.ndarray] = None
    fit_iterations: int = setting(DEFAULT_FIT_ITERATIONS, "count0")
    max_dt: float = setting(DEFAULT_MAX_DT, "positive")
    newton_iterations: int = setting(DEFAULT_NEWTON_ITERATIONS, "count")
    newton_tolerance: float = setting(1e-6, "positive")
    line_search_steps: int = setting(10, "count")
    reuse_hessian: bool = setting(True, "flag")
    hessian_max_age: int = setting(0, "count0")
    clamp_stiffness: float = setting(1.0, "positive")
    friction_velocity: float = setting(1e-3, "positive")
    cache_skinning: bool = setting(True, "flag")
    torch_threads: int = setting(1, "count0")
    line_search_candidates: int = setting(0, "count0")
    profile_device: bool = setting(False, "flag")
    integrator: str = setting("newmark", "choice", choices=INTEGRATORS)

    def check(self):
        if self.skinning_params is not None:
            p = np.asarray(self.skinning_params, dtype=np.float64).reshape(-1)
            expected = skinning.param_count(self.handles)
            if p.size != expected:
                raise UserError(f"skinning parameters must have {expected} numbers for {self.handles} handles "
                                f"(H·64 + H), got {p.size}")
            if not np.all(np.isfinite(p)):
                raise UserError("skinning parameters contain NaN/inf")
            self.skinning_params = p
