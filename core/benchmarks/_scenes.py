"""The canonical scenes of the solvers' refinement study (``unipixie bench fidelity``, tests/test_fidelity.py).

Each scene is a physical set-up that every solver runs as it is - the same body, material, scenario and
tracked points - and a measurement of what came out, checked against a reference that is not a solver of
ours: a closed form where one exists, else the independent referee (``training/independent_fem``).

* ``cantilever_z`` / ``cantilever_y``: a bar of 2:1 rectangular section (0.5 × 0.04 × 0.02 m, clamped over
  its first 0.05 m) bending under gravity across its thin (z) or its wide (y) side: static tip deflection and
  first bending frequency against Euler–Bernoulli.  The frequency (and the mean the tip oscillates about, and
  how fast that mean drifts) come from the bar released undamped; the static deflection from a second run of
  the same bar settled at rest under a mass-proportional drag (:attr:`Scene.settle`), which changes the
  equilibrium not at all and leaves no discretisation drift of the oscillating run in the static figure.
* ``drop``: a soft 0.2 m cube dropped flat from 0.1 m onto the rigid, frictionless floor: peak height of the
  centre of mass after the first contact, and the contact's duration.
* ``slide``: the cube sliding at 1.5 m/s on the floor with Coulomb friction μ = 0.3: stopping distance
  v² / (2 μ g).
* ``drag_linear`` / ``drag_quadratic``: the cube in free flight without gravity at 2 m/s with linear drag
  c = 0.5 /s or quadratic drag k = 0.3 /m: distance flown in 1 s against the closed forms
  (v₀/c)(1 − e^(−c t)) and ln(1 + k v₀ t)/k.

Measurements are functions of the tracked points only (a lattice through the solid, its faces included), so
every solver is measured the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

G = 9.81
"""m/s², gravity of every scene."""

# -- the cantilever -------------------------------------------------------------------------------------
BAR_LENGTH, BAR_WIDTH, BAR_THICKNESS, BAR_CLAMP = 0.5, 0.04, 0.02, 0.05
"""m: the bar along x (clamped over its first BAR_CLAMP), its section BAR_WIDTH (y) × BAR_THICKNESS (z)."""
BAR_E, BAR_NU, BAR_DENSITY = 1.68e8, 0.3, 1000.0
"""Pa, -, kg/m³: stiff enough that the tip sags about 2 % of the free length across the thin side."""
# -- the cube scenes ------------------------------------------------------------------------------------
CUBE_SIZE = 0.2
CUBE_E, CUBE_NU, CUBE_DENSITY = 2.0e5, 0.3, 1000.0
DROP_HEIGHT = 0.1
"""m: the cube's lower face above the floor at release."""
SLIDE_SPEED, SLIDE_MU = 1.5, 0.3
DRAG_SPEED, DRAG_C, DRAG_K = 2.0, 0.5, 0.3
SETTLE_DRAG, SETTLE_TIME, SETTLE_WINDOW = 40.0, 0.6, 0.05
"""1/s, s, s: the settled cantilever run: linear drag c (damping ratio 0.49 / 0.24 for the first bending mode across
the thin / wide side: its amplitude falls by e^(−c t / 2), e^(−12) by the end), run length, and the final window
whose mean tip deflection is the static sag."""
CONTACT_TOLERANCE = 5e-4
"""m: a tracked point this close to the floor touches it (contact duration)."""


@dataclass
class Scene:
    """One canonical scene (see the module docstring).

    body / material / scenario / frame_times / effects: what every solver runs.
    size: m, the object's largest extent (agreement is measured as a fraction of it).
    measure: Trajectory -> {metric: value} (SI units).
    reference: {metric: (value, where it comes from)}.
    units: {metric: unit}.
    """

    name: str
    title: str
    body: object
    material: object
    scenario: object
    frame_times: np.ndarray
    effects: list
    size: float
    measure: Callable
    reference: dict
    units: dict
    notes: str = ""
    cross_solver: bool = True
    extra: dict = field(default_factory=dict)
    settle: "Scene | None" = None
    """A companion run of the same body for the static figures (same metrics dict, merged; its own effects and
    frames): the cantilevers' static sag, settled under drag."""


def lattice(lo, hi, counts) -> np.ndarray:
    """(n, 3) m: a regular lattice of counts[0] × counts[1] × counts[2] points from corner lo to corner hi."""
    axes = [np.linspace(a, b, c) for a, b, c in zip(lo, hi, counts)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def box_mesh(lo, hi, subdivisions: int = 2):
    """A closed box mesh from corner lo to corner hi (m), its faces subdivided (more surface samples)."""
    import trimesh

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    mesh = trimesh.creation.box(extents=hi - lo)
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    mesh.apply_translation((lo + hi) / 2)
    return mesh


# ------------------------------------------------------------------------------------- measurements
def fit_oscillation(times: np.ndarray, signal: np.ndarray, f_guess: float) -> tuple[float, float, float]:
    """Fit s(t) = a + b cos(ωt) + c sin(ωt) by least squares over a, b, c and ω.

    times: (T,) s; signal: (T,) m; f_guess: Hz, where the search for ω starts.  Returns (a m, f Hz, rms of the
    residual m).  ``a`` is the static value the signal oscillates about (the mean over whole periods).
    """
    from scipy.optimize import least_squares

    t = np.asarray(times, float)
    s = np.asarray(signal, float)

    def linear(omega):
        A = np.stack([np.ones_like(t), np.cos(omega * t), np.sin(omega * t)], axis=1)
        coef, *_ = np.linalg.lstsq(A, s, rcond=None)
        return coef, s - A @ coef

    best = None
    for factor in np.linspace(0.5, 1.6, 23):  # coarse scan, then refine the best
        omega = 2 * math.pi * f_guess * factor
        r = linear(omega)[1]
        cost = float(r @ r)
        if best is None or cost < best[0]:
            best = (cost, omega)
    sol = least_squares(lambda w: linear(w[0])[1], x0=[best[1]], x_scale=[best[1]])
    coef, res = linear(sol.x[0])
    return float(coef[0]), float(abs(sol.x[0]) / (2 * math.pi)), float(np.sqrt(np.mean(res ** 2)))


def mean_drift_per_period(times: np.ndarray, signal: np.ndarray, frequency: float) -> float:
    """How fast the mean an oscillation swings about moves: the least-squares slope of the signal's means over
    consecutive whole periods of the *measured* frequency (windows of another period would read the swing itself
    as a drift), per period; signal units per period.  NaN with fewer than two whole periods.

    times: (T,) s, evenly spaced; signal: (T,); frequency: Hz.
    """
    t = np.asarray(times, float)
    s = np.asarray(signal, float)
    period = 1.0 / float(frequency)
    whole = int(np.floor((t[-1] - t[0]) / period + 1e-9))
    if whole < 2:
        return math.nan
    means = [s[(t >= t[0] + k * period) & (t < t[0] + (k + 1) * period)].mean() for k in range(whole)]
    return float(np.polyfit(np.arange(whole), means, 1)[0])


def contact_interval(times: np.ndarray, lowest: np.ndarray, ground: float = 0.0,
                     tol: float = CONTACT_TOLERANCE) -> tuple[float, float]:
    """(first, last) instant (s) of the first contact: the lowest tracked point within ``tol`` of the floor.

    times: (T,) s; lowest: (T,) m, the lowest tracked point's height.  NaN, NaN when it never touches.
    """
    touching = np.asarray(lowest) <= ground + tol
    if not touching.any():
        return math.nan, math.nan
    i0 = int(np.argmax(touching))
    after = np.flatnonzero(~touching[i0:])
    i1 = i0 + int(after[0]) - 1 if len(after) else len(times) - 1
    return float(times[i0]), float(times[i1])


# ------------------------------------------------------------------------------------- the scenes
def _cantilever(direction: str) -> Scene:
    from ...solvers.body import Body
    from ...solvers.effects import make
    from ...solvers.material_sampling import HomogeneousMaterial
    from ...solvers.scenario import Scenario

    L, b, h, clamp = BAR_LENGTH, BAR_WIDTH, BAR_THICKNESS, BAR_CLAMP
    z0 = 0.5
    lo = np.array([-clamp, -b / 2, z0 - h / 2])
    hi = np.array([L - clamp, b / 2, z0 + h / 2])
    free = L - clamp
    tip = np.array([[free, 0.0, z0]])
    tracked = np.concatenate([tip, lattice([free / 8, -b / 2, z0 - h / 2], hi, (8, 3, 3))])
    mesh = box_mesh(lo, hi, subdivisions=1)
    body = Body.from_mesh(mesh, tracked_points=tracked)
    axis = 2 if direction == "z" else 1
    gravity = np.zeros(3)
    gravity[axis] = -G
    sc = Scenario(gravity=gravity, ground_height=None,
                  pinned_box=[[-clamp - 0.01, -b, z0 - h], [0.0, b, z0 + h]])
    # Euler–Bernoulli for the free length, bending across the side normal to gravity
    depth = h if axis == 2 else b          # the section's dimension along the deflection
    across = b if axis == 2 else h
    inertia = across * depth ** 3 / 12
    area = b * h
    EI = BAR_E * inertia
    sag = BAR_DENSITY * G * area * free ** 4 / (8 * EI)
    f1 = 1.875104 ** 2 / (2 * math.pi * free ** 2) * math.sqrt(EI / (BAR_DENSITY * area))
    frames = np.linspace(0.0, 2.2 / f1, 221)

    def tip_deflection(traj):
        """(T,) m: the tip's displacement along the bending axis (negative: down the load)."""
        return traj.positions[:, 0, axis].astype(np.float64) - tip[0, axis]

    def measure(traj):
        d = tip_deflection(traj)
        a, f, rms = fit_oscillation(traj.times, d, f1)
        return {"oscillation_mean": -a, "frequency": f, "fit_residual": rms,
                "mean_drift_per_period": -mean_drift_per_period(traj.times, d, f)}

    def measure_settled(traj):
        d = tip_deflection(traj)
        last = np.asarray(traj.times, float) > SETTLE_TIME - SETTLE_WINDOW
        return {"tip_sag": float(-d[last].mean()), "settle_residual": float(d[last].std())}

    slenderness = free / depth
    title = f"cantilever, 2:1 section, bending across its {'thin (z)' if axis == 2 else 'wide (y)'} side"
    material = HomogeneousMaterial(BAR_E, BAR_NU, BAR_DENSITY)
    sag_reference = (sag, "Euler–Bernoulli ρgAL⁴/(8EI), free length")
    settled = Scene(
        name=f"cantilever_{direction}", size=L, title=title + ", settled under drag", body=body, material=material,
        scenario=sc, frame_times=np.linspace(0.0, SETTLE_TIME, int(round(SETTLE_TIME / 0.01)) + 1),
        effects=[make("linear_drag", c=SETTLE_DRAG)], measure=measure_settled,
        reference={"tip_sag": sag_reference}, units={"tip_sag": "m", "settle_residual": "m"}, cross_solver=False)
    return Scene(
        name=f"cantilever_{direction}", size=L, title=title,
        body=body, material=material, scenario=sc, frame_times=frames,
        effects=[], measure=measure, settle=settled,
        reference={"oscillation_mean": (sag, "Euler–Bernoulli ρgAL⁴/(8EI) (what a linear bar swings about)"),
                   "frequency": (f1, "Euler–Bernoulli 1.875²/(2πL²)·√(EI/ρA), free length")},
        units={"oscillation_mean": "m", "frequency": "Hz", "fit_residual": "m", "mean_drift_per_period": "m"},
        notes=(f"free length {free} m, L/depth = {slenderness:.1f}: Euler–Bernoulli neglects shear, rotary inertia "
               f"and the clamp's own give (Timoshenko lowers the first frequency by roughly (depth/L)² ≈ "
               f"{100 * (depth / free) ** 2:.1f} %)"))


def _cube_body(lower_face: float, tracked_counts=(5, 5, 5)):
    from ...solvers.body import Body

    s = CUBE_SIZE
    lo = np.array([-s / 2, -s / 2, lower_face])
    hi = lo + s
    return Body.from_mesh(box_mesh(lo, hi), tracked_points=lattice(lo, hi, tracked_counts))


def _drop() -> Scene:
    from ...solvers.material_sampling import HomogeneousMaterial
    from ...solvers.scenario import Scenario

    body = _cube_body(DROP_HEIGHT)
    frames = np.linspace(0.0, 0.36, 361)
    rest_com = CUBE_SIZE / 2

    def measure(traj):
        z = traj.positions[:, :, 2].astype(np.float64)
        com = z.mean(1)
        t0, t1 = contact_interval(traj.times, z.min(1))
        after = traj.times > t1
        peak = float(com[after].max()) if np.isfinite(t1) and after.any() else math.nan
        return {"rebound_peak": peak, "rebound_ratio": (peak - rest_com) / DROP_HEIGHT,
                "contact_duration": t1 - t0, "first_contact": t0}

    return Scene(
        name="drop", size=CUBE_SIZE, title="soft cube dropped flat onto the rigid, frictionless floor",
        body=body, material=HomogeneousMaterial(CUBE_E, CUBE_NU, CUBE_DENSITY),
        scenario=Scenario(ground_height=0.0), frame_times=frames, effects=[], measure=measure,
        reference={"first_contact": (math.sqrt(2 * DROP_HEIGHT / G), "free fall √(2h/g)")},
        units={"rebound_peak": "m", "rebound_ratio": "-", "contact_duration": "s", "first_contact": "s"},
        notes="no closed form for the rebound: the reference is the independent referee, converged")


def _slide() -> Scene:
    from ...solvers import effects as fx
    from ...solvers.material_sampling import HomogeneousMaterial
    from ...solvers.scenario import Scenario

    body = _cube_body(0.0)
    stop_time = SLIDE_SPEED / (SLIDE_MU * G)
    frames = np.linspace(0.0, 1.3 * stop_time, 131)

    def measure(traj):
        x = traj.positions[:, :, 0].astype(np.float64).mean(1)
        return {"stopping_distance": float(x[-1] - x[0])}

    return Scene(
        name="slide", size=CUBE_SIZE, title="cube sliding on the floor with Coulomb friction μ = 0.3",
        body=body, material=HomogeneousMaterial(CUBE_E, CUBE_NU, CUBE_DENSITY),
        scenario=Scenario(ground_height=0.0, initial_velocity=[SLIDE_SPEED, 0.0, 0.0]), frame_times=frames,
        effects=[fx.make("ground_friction", mu=SLIDE_MU)], measure=measure,
        reference={"stopping_distance": (SLIDE_SPEED ** 2 / (2 * SLIDE_MU * G), "Coulomb v²/(2μg)")},
        units={"stopping_distance": "m"})


def _drag(kind: str) -> Scene:
    from ...solvers import effects as fx
    from ...solvers.material_sampling import HomogeneousMaterial
    from ...solvers.scenario import Scenario

    body = _cube_body(1.0, (3, 3, 3))
    T = 1.0
    frames = np.linspace(0.0, T, 51)
    v0 = DRAG_SPEED
    if kind == "linear":
        eff = fx.make("linear_drag", c=DRAG_C)
        closed = v0 / DRAG_C * (1 - math.exp(-DRAG_C * T))
        law = "(v₀/c)(1 − e^(−cT))"
    else:
        eff = fx.make("quadratic_drag", k=DRAG_K)
        closed = math.log(1 + DRAG_K * v0 * T) / DRAG_K
        law = "ln(1 + k v₀ T)/k"

    def measure(traj):
        x = traj.positions[:, :, 0].astype(np.float64).mean(1)
        return {"distance": float(x[-1] - x[0])}

    return Scene(
        name=f"drag_{kind}", size=CUBE_SIZE, title=f"free flight (no gravity) with {kind} drag",
        body=body, material=HomogeneousMaterial(CUBE_E, CUBE_NU, CUBE_DENSITY),
        scenario=Scenario(gravity=[0.0, 0.0, 0.0], ground_height=None, initial_velocity=[v0, 0.0, 0.0]),
        frame_times=frames, effects=[eff], measure=measure,
        reference={"distance": (closed, f"closed form {law}")}, units={"distance": "m"}, cross_solver=False)


SCENE_BUILDERS = {"cantilever_z": lambda: _cantilever("z"), "cantilever_y": lambda: _cantilever("y"),
                  "drop": _drop, "slide": _slide, "drag_linear": lambda: _drag("linear"),
                  "drag_quadratic": lambda: _drag("quadratic")}
"""Scene name -> builder (bodies are built on demand: they fill meshes)."""


def scene(name: str) -> Scene:
    from ...core.errors import UserError

    try:
        return SCENE_BUILDERS[name]()
    except KeyError:
        raise UserError(f"unknown scene {name!r}; the scenes are {', '.join(SCENE_BUILDERS)}") from None
