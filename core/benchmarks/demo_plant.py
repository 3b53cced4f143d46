"""``unipixie bench demo_plant``: the demo's plant at one α, by MPM and spring-mass at several resolutions.

``unipixie demo`` reports how far its MPM and spring-mass plants at the same α move apart
(``solver_difference`` in its summary).  This benchmark asks which of the two is off, and by how much, by
refining each on the same object, material and scene:

- MPM at each level of ``--cells`` (cells across the plant, thin parts not refined further, as the demo bakes),
  and ``default``: the bake default (32 across and 4 across the thinnest parts, within the device's particle
  budget);
- spring-mass at each anchor count of ``--anchors`` (the bake default is 2048).

Every run's motion (the baked mesh's vertices, world metres) is compared with the finest MPM level's: the RMS of
the difference of the displacements over vertices and frames 2 … T (the demo's ``solver_difference``), as a
fraction of the plant's size (metric ``displacement_rms_over_size``); and the crown's sway — the top 10 % of the
vertices — is summarised by :func:`crown_sway`: its frequency (``crown_sway_hz``), its swing in the clip's last
quarter (``crown_last_swing_m``, peak to peak; an undamped material keeps its first quarter's) and the
horizontal displacement it sways about (``crown_lean_m``).

Input: the demo's ``.blend`` (read with Blender: the plant, its recorded prediction and bake settings), or a
scene file that ``--export`` wrote from it (the body, the resolved material of each solver, the scenario and the
frame times; a pickle, for a machine of the same package without Blender, e.g. a GPU server).  Only load scene
files you made: a pickle runs code when loaded.
"""

from __future__ import annotations

import math
import pickle
import time
from pathlib import Path

import numpy as np

from ..demo import FULL, PLANT, check_checkpoint, displacement_rms

HELP = ("the demo's plant at one α by MPM and spring-mass at several resolutions: which solver the demo's "
        "MPM-vs-spring-mass difference comes from")

SCENE_FORMAT = "unipixie.demo_plant_scene/1"
CROWN_FRACTION = 0.1
"""The crown: this fraction of the plant's vertices, the highest at rest."""


def add_arguments(p):
    p.add_argument("--blend", default="demo/unipixie_demo.blend",
                   help="the demo's .blend (default demo/unipixie_demo.blend, where 'unipixie demo' writes it)")
    p.add_argument("--object", default=None,
                   help="the baked plant to take the material and scene from (default: the demo's MPM plant at "
                        "the α of its spring-mass plant)")
    p.add_argument("--scene", default=None, metavar="FILE",
                   help="simulate a scene file written by --export instead of reading the .blend (no Blender needed)")
    p.add_argument("--export", default=None, metavar="FILE",
                   help="only write the scene file (needs Blender) and stop")
    p.add_argument("--cells", default="17,32,48,64,96,default",
                   help="MPM levels, cells across the plant, and 'default' for the bake default; the finest number "
                        "is the reference (default 17,32,48,64,96,default; 96 takes about a minute on one H200, "
                        "hours on a CPU)")
    p.add_argument("--anchors", default="2048,4096,8192,16384",
                   help="spring-mass anchor counts (default 2048,4096,8192,16384)")
    p.add_argument("--checkpoint", default=None, help="the model the demo used (default: the shipped model)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: cpu)")


# --------------------------------------------------------------------------- metrics (no solver, no Blender)
def crown_sway(positions: np.ndarray, fps: float, crown: np.ndarray | None = None, windows: int = 4) -> dict:
    """The sway of the crown: its mean horizontal displacement, projected on its main direction of motion.

    positions: (T, N, 3) metres; fps: frames per second; crown: (N,) bool (default: the highest
    :data:`CROWN_FRACTION` of the vertices at frame 0).  Returns ``frequency_hz`` (a damped sine fitted after the
    first quarter, started from the zero crossings about the mean of the second half; NaN with fewer than three
    crossings), ``swings_m``
    (peak-to-peak in each of ``windows`` equal parts of the clip), ``lean_m`` (length of the horizontal
    displacement about which it sways: the fit's centre, or the mean over the second half without a fit).
    """
    p = np.asarray(positions, np.float64)
    if crown is None:
        z = p[0, :, 2]
        crown = z >= np.quantile(z, 1.0 - CROWN_FRACTION)
    d = (p[:, crown, :2] - p[0, crown, :2]).mean(axis=1)                    # (T, 2)
    half = len(d) // 2
    centre = d[half:].mean(axis=0)
    _, _, vt = np.linalg.svd(d - d.mean(axis=0), full_matrices=False)
    x = (d - centre) @ vt[0]
    sign = np.sign(x)
    cross = np.flatnonzero(sign[:-1] * sign[1:] < 0)
    times = [(i + x[i] / (x[i] - x[i + 1])) / fps for i in cross]
    freq = 1.0 / (2.0 * float(np.mean(np.diff(times)))) if len(times) >= 3 else math.nan
    if math.isfinite(freq):
        freq, offset = _fit_sway(x, fps, freq)
        centre = centre + offset * vt[0]
    parts = np.array_split(np.arange(len(x)), windows)
    return {"frequency_hz": freq, "swings_m": [float(np.ptp(x[i])) for i in parts],
            "lean_m": float(np.linalg.norm(centre))}


def _fit_sway(x: np.ndarray, fps: float, guess: float) -> tuple[float, float]:
    """Frequency (Hz) and centre ``c`` (m) of the least-squares fit c + A·exp(−λt)·sin(2πft + φ) to ``x`` (T,)
    after its first quarter (the push), started at ``guess``: zero crossings about a mean over few periods are
    biased by that mean.  ``(guess, 0)`` when the fit fails."""
    import warnings

    from scipy.optimize import OptimizeWarning, curve_fit

    t = np.arange(len(x)) / fps
    keep = slice(len(x) // 4, None)

    def model(t, c, a, lam, f, phi):
        return c + a * np.exp(-lam * t) * np.sin(2.0 * math.pi * f * t + phi)

    best, cost = (guess, 0.0), math.inf
    for phi0 in np.linspace(0.0, 2.0 * math.pi, 8, endpoint=False):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", OptimizeWarning)     # the covariance is not used
                p, _ = curve_fit(model, t[keep], x[keep], p0=(0.0, float(np.ptp(x[keep])) / 2, 0.0, guess, phi0),
                                 maxfev=4000)
        except (RuntimeError, ValueError):
            continue
        r = float(np.sum((model(t[keep], *p) - x[keep]) ** 2))
        if r < cost and 0.5 * guess < p[3] < 2.0 * guess:
            best, cost = (float(p[3]), float(p[0])), r
    return best


# --------------------------------------------------------------------------- the scene
def export_scene(blend, object_name=None, checkpoint=None) -> dict:
    """The plant's scene from the demo's .blend (needs Blender; the session's file is replaced by it):
    :func:`~unipixie.core.blender_io.demo_scene.read_bake_scene` of the demo's MPM plant at the α of its
    spring-mass plant (or ``object_name``) with the demo's pipeline settings, plus ``"format"``."""
    from ..pipeline import PipelineSettings
    from ...solvers import registry
    from ..blender_io import demo_scene

    name = object_name or f"{PLANT.label} {registry.SOLVERS['mpm'].label} α={FULL.spring_alpha:g}"
    settings = PipelineSettings(view_count=FULL.views, resolution=FULL.resolution,
                                checkpoint=str(check_checkpoint(checkpoint)), device="cpu").with_model_recipe()
    return {"format": SCENE_FORMAT, **demo_scene.read_bake_scene(blend, name, settings, ("mpm", "spring_mass"))}


def save_scene(scene: dict, path) -> Path:
    from ..atomic_io import write_bytes

    return write_bytes(Path(path), pickle.dumps(scene, protocol=pickle.HIGHEST_PROTOCOL))


def load_scene(path) -> dict:
    from ..errors import UserError

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such scene file (write one with --export)")
    try:
        scene = pickle.loads(path.read_bytes())
    except Exception as exc:
        raise UserError(f"{path}: not a scene file written by --export ({type(exc).__name__})") from None
    if not isinstance(scene, dict) or scene.get("format") != SCENE_FORMAT:
        raise UserError(f"{path}: not a scene file written by --export (format {SCENE_FORMAT})")
    return scene


# --------------------------------------------------------------------------- the runs
def simulate(scene: dict, solver: str, level: str, device: str) -> np.ndarray:
    """(T, N, 3) vertex positions (m) of one run: MPM at ``level`` cells across (or ``"default"``), spring-mass at
    ``level`` anchors."""
    from ...solvers import api

    part = scene[solver]
    if solver == "mpm":
        extra = {} if level == "default" else {"cells_across": int(level)}
    else:
        extra = {"anchors": int(level)}
    sim = api.prepare(solver, part["body"], part["spec"], scene["scenario"], scene["times"], device=device,
                      settings={**part["settings"], **extra})
    return np.asarray(sim.run(scene["effects"]).positions, np.float64)


def _levels(text: str, allow_default: bool) -> list:
    from ..errors import UserError

    out = []
    for item in (s.strip() for s in str(text).split(",") if s.strip()):
        if allow_default and item == "default":
            out.append(item)
            continue
        if not item.isdigit() or int(item) < 2:
            raise UserError(f"{item!r} is not a resolution (a whole number of at least 2"
                            + (", or 'default')" if allow_default else ")"))
        out.append(item)
    return out


def run(args) -> list:
    from ..errors import UserError
    from ...solvers.warp_runtime import device_description, resolve_device

    cells = _levels(args.cells, True)
    anchors = _levels(args.anchors, False)
    numbered = [c for c in cells if c != "default"]
    if not numbered:
        raise UserError("--cells needs at least one number of cells: the finest is the reference")
    if args.scene:
        scene = load_scene(args.scene)
    else:
        scene = export_scene(args.blend, args.object, args.checkpoint)
        if args.export:
            path = save_scene(scene, args.export)
            print(f"wrote the scene of {scene['object']!r} (α {scene['alpha']:g}) to {path}")
            return []
    device = resolve_device(args.device)
    described = device_description(device)
    reference = max(numbered, key=int)
    runs = [("mpm", reference)] + [("mpm", c) for c in cells if c != reference] + [("spring_mass", a) for a in anchors]
    motions, seconds = {}, {}
    for solver, level in runs:
        t = time.perf_counter()
        motions[(solver, level)] = simulate(scene, solver, level, device)
        seconds[(solver, level)] = time.perf_counter() - t
        print(f"  {solver} {level}: {seconds[(solver, level)]:.1f} s", flush=True)
    size, fps = scene["size_m"], scene["fps"]
    ref = motions[("mpm", reference)]
    crown = ref[0, :, 2] >= np.quantile(ref[0, :, 2], 1.0 - CROWN_FRACTION)
    results = []
    for (solver, level), pos in motions.items():
        what = f"{'MPM' if solver == 'mpm' else 'spring-mass'} " + (
            "bake default" if level == "default" else f"{level} {'cells across' if solver == 'mpm' else 'anchors'}")
        case = f"demo plant α {scene['alpha']:g}, {what}"
        sway = crown_sway(pos, fps, crown)
        common = {"case": case, "device": described, "runs": 1, "seconds": round(seconds[(solver, level)], 2)}
        if (solver, level) != ("mpm", reference):
            results.append({**common, "metric": "displacement_rms_over_size",
                            "value": displacement_rms(pos, ref) / size,
                            "reference": f"MPM {reference} cells across, same run"})
        results += [{**common, "metric": "crown_sway_hz", "value": sway["frequency_hz"]},
                    {**common, "metric": "crown_last_swing_m", "value": sway["swings_m"][-1],
                     "first_swing_m": sway["swings_m"][0]},
                    {**common, "metric": "crown_lean_m", "value": sway["lean_m"]}]
    return results
