"""``unipixie demo --diagnose``: a guided diagnosis of a built-in measurement with a hidden effect.

The built-in measurement is simulated on the spot (deterministic: fixed seed): a 0.2 m jelly
cube thrown through the air, tracked at 100 Hz with 1 mm noise and 10 % occlusions, made by
the MPM solver with air drag that grows with the square of the speed switched on.  The
diagnosis (by default with the spring-mass solver — a *different* simulator, as with real
data) is not told which effect is hidden; the demo prints every step and reveals the truth at
the end.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

from ..progress import Progress

DEMO_EFFECT = "quadratic_drag:k=0.4"
"""The hidden effect of the built-in measurement."""
DEMO_MEASUREMENT = dict(solver="mpm", shape="cube", scenario="throw", noise=0.001, occlusion=0.1, duration=1.0,
                        fps=100.0, points=250, E=2.0e5, nu=0.3, density=1000.0, seed=7,
                        settings={"cells_across": 10})
"""How the built-in measurement is made (:func:`unipixie.core.diagnosis.synth.synthesize` arguments)."""


def demo_measurement(device: str = "cpu", progress: Optional[Progress] = None):
    """The built-in hidden-effect measurement (:class:`~unipixie.core.measurement.Measurement`)."""
    from . import synth

    return synth.synthesize([DEMO_EFFECT], device=device, progress=progress, **DEMO_MEASUREMENT)


def run_demo(out_dir, solver: str = "spring_mass", device: str = "cpu", settings=None,
             say: Callable[[str], None] = print, progress: Optional[Progress] = None):
    """Make the built-in measurement, diagnose it step by step, write the report; returns the Diagnosis."""
    from ...solvers import effects as fx
    from . import diagnose
    from .synth import truth_of

    out = Path(out_dir).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    say("UniPixie diagnosis demo: find the physics a model is missing.")
    say(f"Step 0 - the measurement: a {DEMO_MEASUREMENT['shape']} thrown through the air, tracked at "
        f"{DEMO_MEASUREMENT['fps']:.0f} Hz with {1e3 * DEMO_MEASUREMENT['noise']:.0f} mm noise and "
        f"{100 * DEMO_MEASUREMENT['occlusion']:.0f} % occlusions. It was simulated by the "
        f"{DEMO_MEASUREMENT['solver']} solver with one physical effect switched on that the model does not have "
        f"(revealed at the end); the diagnosis uses the {solver} solver.")
    m = demo_measurement(device=device)
    path = m.save(out / "demo_measurement.npz")
    say(f"        wrote {path} ({m.summary()})")
    say("Steps 1-6 - simulate the model as given, compare, estimate the noise, refit the base material, fit every "
        "effect of the registry, test significance, add the best one, repeat:")
    result = diagnose.diagnose(m, solver, out_dir=out, device=device, settings=settings, log=say,
                               progress=progress)
    truth = truth_of(m)
    hidden = [fx.from_dict(e) for e in truth["effects"]]
    say("Reveal - the hidden effect was " + ", ".join(repr(e) for e in hidden) + ".")
    if result.added:
        say("        the diagnosis added " + ", ".join(repr(e) for e in result.added)
            + f"; the error fell from {1e3 * result.baseline.rmse:.1f} mm to {1e3 * result.final.rmse:.2f} mm "
              f"(noise floor {1e3 * result.noise_rmse:.2f} mm).")
    else:
        say("        the diagnosis found nothing significant.")
    say(f"Report: {out / 'diagnosis.html'} (open it in a browser) and {out / 'diagnosis.json'}")
    return result
