"""The paper's evaluation on our test split: property regression (Table 1), solver fidelity (Table 2), a figure.

``unipixie evaluate CHECKPOINT --data DATASET --split test --out DIR [--baseline DIR ...]`` writes::

    DIR/report.json        methods → metrics (the file shipped as models/default/evaluation.json)
    DIR/report.md          the same as Markdown tables
    DIR/logE_distributions.png
    DIR/predictions/<method>/<object>.npz   the raw predictions every number is computed from
    DIR/predictions/targets/<object>.npz    the annotated ranges of the occupied voxels, and facts used only for
                                            scoring (surface, distance to a part boundary, class: .error_breakdown)
    DIR/renders/...        (Table 2) the rendered frames compared by PSNR / SSIM

**Table 1** (property regression).  For every test object, method and α ∈ ``alphas`` (default 0, 0.5, 1)
the per-voxel predictions are compared with the targets at α — the annotated ranges interpolated as the
model's training does (log10-linear for E and ρ, linear for ν).  Per object: MSE of log10 E, of log10 ρ,
of ν over the occupied voxels, and the fraction of voxels whose material class is right; the table gives
the mean over objects and α (and ± the standard deviation over objects of the α-averaged value).  A
deterministic baseline predicts one field for every α, compared with all three targets, as the paper
does.  ``runtime_s``: wall time of one MPM-head prediction at α = 0.5 (median over objects).  Also the
fraction of occupied voxels whose α = 0 / α = 1 predictions lie inside the annotated range, widened by
a tolerance of 0, 10 % or 25 % of the range's width on each side (in log10 for E and ρ) — at α = 0 the
target *is* the range's lower end, so without a tolerance about half of any unbiased error falls out.

**Table 2** (solver fidelity; the first ``simulate_objects`` test objects, as the paper uses a 10-object
subset).  The object's ground-truth MPM motion at α (the dataset's; α = 0.5 is simulated for test
objects at build time) is compared with (a) MPM driven by each method's predicted material field, (b)
the LBS solver driven by UniPixie's LBS head (650 skinning parameters + E, ν field; density from the MPM
head), (c) the spring-mass solver driven by UniPixie's spring head (k, η), and (d) the specialist
test-time fitters of :mod:`.ground_truth` (fitted to the ground-truth motion itself, timed).  The
primary number is the RMSE of the tracked vertices over all frames (metres, and relative to the
object's size); PSNR / SSIM compare Blender renders (Workbench, ``render_views`` views) of
``render_frames`` frames of the deformed, textured object with the same frames of the ground truth.
Every simulation follows the ground-truth protocol (same particles, scenario, wave-speed cap).

**Where the error lies** (``report["breakdown"]``, :mod:`.error_breakdown`): per method, the log10 E squared error
by object class, surface vs. interior voxel and distance to the nearest voxel of another part.

**Figure**: histograms of log10 E over the occupied voxels of the test objects, target vs. UniPixie's
prediction, for the MPM and LBS heads, and of log10 k over the anchors for the spring-mass head, at each α.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.errors import SimulationDiverged, UserError
from ..core.progress import Progress, silent
from ..core import annotation as ann_mod
from ..core.model.config import HEADS
from ..core.model.inference import DEFAULT_TEMPERATURE, check_temperature
from .error_breakdown import error_breakdown, scoring_facts
from .evaluation_report import write_report
from .oracle import REFERENCES, OracleSettings, oracle_predictions

REPORT_FORMAT = "unipixie.evaluation/1"
TOLERANCES = (0.0, 0.1, 0.25)
TABLE1_KEYS = ("logE_mse", "logrho_mse", "nu_mse", "material_acc")


@dataclass
class EvalSettings:
    """alphas: α values of Table 1 (and of Table 2 where ground truth exists).  split: dataset split.
    device: torch device of the models; solver_device: Warp device of the simulations.  seed: noise seed.
    max_objects: 0 = every object of the split.  simulate_objects: Table 2 objects (0 = no Table 2).
    fitters: run the specialist test-time fitters in Table 2.  render_frames / render_views /
    render_resolution: the PSNR/SSIM renders (0 frames = no renders).  mean_prediction: also evaluate
    ``unipixie_mean``, the model's one-step prediction (steps = 1: the data-predicting network's output from
    pure noise, its estimate of the conditional mean — the MSE-optimal point estimate), besides ``unipixie``
    (the ODE sampler at the product's default temperature,
    :data:`~unipixie.core.model.inference.DEFAULT_TEMPERATURE`).  average_samples: for each K, also evaluate
    ``unipixie_avgK``, the average of K draws (seeds ``seed`` … ``seed + K − 1``, averaged in the network's
    normalised units: :meth:`~unipixie.core.model.inference.Predictor.predict`'s ``samples``), a Monte-Carlo
    estimate of the conditional mean.  temperatures: for each τ other than the default's, also evaluate
    ``unipixie_tτ``, one draw at that temperature (``unipixie_t1``: the paper's sampler, a draw from the model);
    ``unipixie_mean`` and ``unipixie_avgK`` are draws from the model (temperature 1).  oracle: on a procedural
    dataset, also score the reference predictors of :mod:`.oracle` (what the best possible model reaches on these
    labels), each from ``oracle_draws`` annotations drawn from the generator's priors."""

    alphas: tuple = (0.0, 0.5, 1.0)
    split: str = "test"
    device: str = "auto"
    solver_device: str = "cpu"
    seed: int = 0
    max_objects: int = 0
    simulate_objects: int = 10
    fitters: bool = True
    render_frames: int = 3
    render_views: int = 2
    render_resolution: int = 128
    mean_prediction: bool = True
    average_samples: tuple = ()
    temperatures: tuple = (1.0,)
    oracle: bool = True
    oracle_draws: int = 1000


# =========================================================================== metrics
def temperature_method(temperature: float) -> str:
    """The evaluated method's name for one draw at ``temperature`` (``unipixie_t1``, ``unipixie_t0.5``)."""
    return f"unipixie_t{float(temperature):g}"


def targets_at(targets: dict, alpha: float) -> dict:
    """Targets (K,) at ``alpha`` in metric channels: ``E``, ``density``, ``nu`` and ``material``."""
    out = {q: ann_mod.channel(ann_mod.interpolate(targets[f"{q}_min"], targets[f"{q}_max"], alpha, q), q)
           for q in ann_mod.QUANTITIES}
    out["material"] = targets["material"]
    return out


def object_metrics(pred: dict, targets: dict) -> dict:
    """Per-α Table 1 metrics of one object's saved predictions (``pred``: arrays (A, K); ``targets``: (K,))."""
    out = {}
    for i, a in enumerate(np.asarray(pred["alphas"], np.float64)):
        t = targets_at(targets, float(a))
        out[f"{a:g}"] = {
            "logE_mse": float(np.mean((pred["log10_E"][i] - t["E"]) ** 2)),
            "logrho_mse": float(np.mean((pred["log10_density"][i] - t["density"]) ** 2)),
            "nu_mse": float(np.mean((pred["nu"][i] - t["nu"]) ** 2)),
            "material_acc": float(np.mean(pred["material"][i] == t["material"])),
        }
    return out


def in_range_fractions(pred: dict, targets: dict, tolerances=TOLERANCES) -> dict:
    """{α: {quantity | "all": {tolerance: fraction of voxels inside the widened range}}} for α = 0 and 1."""
    out = {}
    names = {"E": "log10_E", "density": "log10_density", "nu": "nu"}
    for i, a in enumerate(np.asarray(pred["alphas"], np.float64)):
        if a not in (0.0, 1.0):
            continue
        res, all_in = {}, {}
        for q in ann_mod.QUANTITIES:
            lo, hi = ann_mod.channel(targets[f"{q}_min"], q), ann_mod.channel(targets[f"{q}_max"], q)
            w = hi - lo
            p = pred[names[q]][i]
            res[q] = {}
            for tol in tolerances:
                inside = (p >= lo - tol * w - 1e-9) & (p <= hi + tol * w + 1e-9)
                res[q][f"{tol:g}"] = float(inside.mean())
                all_in[f"{tol:g}"] = inside if f"{tol:g}" not in all_in else all_in[f"{tol:g}"] & inside
        res["all"] = {k: float(v.mean()) for k, v in all_in.items()}
        out[f"{a:g}"] = res
    return out


def logE_is_monotone(pred: dict, slack: float = 1e-6) -> bool:
    """Whether the object's mean log10 E over its occupied voxels does not decrease with α.

    ``pred``: ``alphas`` (A,) and ``log10_E`` (A, K) log10 Pa.  ``slack``: allowed decrease (log10 Pa, round-off).
    """
    order = np.argsort(np.asarray(pred["alphas"], np.float64))
    means = np.asarray(pred["log10_E"], np.float64)[order].mean(axis=1)
    return bool(np.all(np.diff(means) >= -slack))


def table1(pred_root) -> dict:
    """Table 1 from the raw predictions saved under ``pred_root`` (``predictions/``): method -> metrics."""
    root = Path(pred_root)
    tdir = root / "targets"
    if not tdir.is_dir():
        raise UserError(f"{root}: no targets/ folder; not an evaluation's predictions directory")
    methods = {}
    for mdir in sorted(p for p in root.iterdir() if p.is_dir() and p.name != "targets"):
        per_obj, runtimes, ranges, monotone = [], [], [], []
        for f in sorted(mdir.glob("*.npz")):
            with np.load(f, allow_pickle=False) as z:
                pred = {k: z[k] for k in z.files}
            with np.load(tdir / f.name, allow_pickle=False) as z:
                targets = {k: z[k] for k in z.files}
            per_obj.append(object_metrics(pred, targets))
            runtimes.append(float(pred["runtime_s"]))
            ranges.append(in_range_fractions(pred, targets))
            monotone.append(logE_is_monotone(pred))
        if not per_obj:
            continue
        alphas = list(per_obj[0])
        m = {"objects": len(per_obj), "alphas": [float(a) for a in alphas]}
        for key in TABLE1_KEYS:
            per_alpha = np.array([[o[a][key] for a in alphas] for o in per_obj])  # (objects, A)
            avg = per_alpha.mean(axis=1)
            m[key] = float(avg.mean())
            m[f"{key}_std"] = float(avg.std())
            m[f"{key}_per_alpha"] = {a: float(per_alpha[:, j].mean()) for j, a in enumerate(alphas)}
        m["runtime_s"] = float(np.median(runtimes))
        m["logE_monotone_fraction"] = float(np.mean(monotone))
        m["runtime_s_mean"] = float(np.mean(runtimes))
        if ranges and ranges[0]:
            m["in_range"] = {a: {q: {t: float(np.mean([r[a][q][t] for r in ranges])) for t in ranges[0][a][q]}
                                 for q in ranges[0][a]} for a in ranges[0]}
        methods[mdir.name] = m
    return methods


# =========================================================================== predictions
def _save_npz(path: Path, **arrays) -> None:
    from ..core.atomic_io import save_npz

    save_npz(path, **arrays)


def _unipixie_arrays(pred, alphas) -> dict:
    mpm = pred.mpm
    d = {"alphas": np.asarray(alphas, np.float64),
         "log10_E": np.stack([np.log10(f.E) for f in mpm]).astype(np.float32),
         "log10_density": np.stack([np.log10(f.density) for f in mpm]).astype(np.float32),
         "nu": np.stack([f.nu for f in mpm]).astype(np.float32),
         "material": np.stack([f.material for f in mpm]).astype(np.int16)}
    if pred.lbs is not None:
        d["lbs_log10_E"] = np.stack([np.log10(p.E) for p in pred.lbs]).astype(np.float32)
        d["lbs_nu"] = np.stack([p.nu for p in pred.lbs]).astype(np.float32)
        d["lbs_params"] = np.stack([p.params for p in pred.lbs]).astype(np.float32)
    if pred.spring_mass is not None:
        d["spring_log10_k"] = np.stack([np.log10(p.stiffness) for p in pred.spring_mass]).astype(np.float32)
        d["spring_softness"] = np.array([p.softness for p in pred.spring_mass], np.float32)
    return d


def _baseline_arrays(fields, alphas) -> dict:
    return {"alphas": np.asarray(alphas, np.float64),
            "log10_E": np.stack([np.log10(f["E"]) for f in fields]).astype(np.float32),
            "log10_density": np.stack([np.log10(f["density"]) for f in fields]).astype(np.float32),
            "nu": np.stack([f["nu"] for f in fields]).astype(np.float32),
            "material": np.stack([f["material"] for f in fields]).astype(np.int16)}


class Methods:
    """The evaluated methods: UniPixie (a checkpoint) and baselines (directories of training/baselines.py)."""

    def __init__(self, checkpoint, baselines, settings: EvalSettings):
        from ..core.model.inference import Predictor
        from .baselines import BaselinePredictor

        self.model = Predictor.load(checkpoint, device=settings.device) if checkpoint else None
        self.baselines = [BaselinePredictor(b, device=settings.device) for b in baselines]
        names = [b.name for b in self.baselines]
        if len(set(names)) != len(names):
            raise UserError(f"two baselines of the same kind given ({', '.join(names)})")
        self.settings = settings

    def names(self) -> list:
        mean = ["unipixie_mean"] if self.model and self.settings.mean_prediction else []
        averages = [f"unipixie_avg{k}" for k in self.settings.average_samples] if self.model else []
        return (["unipixie"] if self.model else []) + mean + averages + \
            [temperature_method(t) for t in self.other_temperatures()] + [b.name for b in self.baselines]

    def other_temperatures(self) -> list:
        """The temperatures evaluated besides the default's (``unipixie_tτ``), in the order given."""
        if self.model is None:
            return []
        out = []
        for t in self.settings.temperatures:
            t = check_temperature(t)
            if t != DEFAULT_TEMPERATURE and t not in out:
                out.append(t)
        return out

    def predict_all(self, grid, alphas, heads=HEADS) -> dict:
        """method -> (arrays for the predictions file, native prediction object), runtime included."""
        import torch

        out = {}
        s = self.settings
        if self.model is not None:
            def model_method(name, predict_heads, **sampler):
                """Predict at ``alphas``, then time one MPM-head prediction at α = 0.5 with the same sampler."""
                pred = self.model.predict(grid, alphas=alphas, heads=predict_heads, seed=s.seed, **sampler)
                t = time.perf_counter()
                self.model.predict(grid, alphas=(0.5,), heads=("mpm",), seed=s.seed, **sampler)
                arrays = _unipixie_arrays(pred, alphas)
                arrays["runtime_s"] = np.float64(time.perf_counter() - t)
                out[name] = (arrays, pred)

            model_method("unipixie", heads)
            if s.mean_prediction:
                model_method("unipixie_mean", ("mpm",), steps=1, temperature=1.0)
            for k in s.average_samples:
                model_method(f"unipixie_avg{k}", ("mpm",), samples=k, temperature=1.0)
            for temp in self.other_temperatures():
                model_method(temperature_method(temp), ("mpm",), temperature=temp)
        for b in self.baselines:
            fields = b.predict(grid, alphas, seed=s.seed)
            t = time.perf_counter()
            b.predict(grid, (0.5,), seed=s.seed)
            if b.device.type == "cuda":
                torch.cuda.synchronize(b.device)
            arrays = _baseline_arrays(fields, alphas)
            arrays["runtime_s"] = np.float64(time.perf_counter() - t)
            out[b.name] = (arrays, fields)
        return out


# =========================================================================== simulations for Table 2
def _world_material_at_points(field, normalisation, points):
    """A predicted MaterialField (normalised cube) looked up at world points (nearest occupied voxel)."""
    from ..solvers.material_sampling import sample_material

    return sample_material(normalisation.field_to_world(field), points)


def _voxel_centres_world(grid, normalisation) -> np.ndarray:
    return normalisation.to_world(grid.geometry.centres(grid.indices))


def _run_or_none(fn):
    try:
        return fn(), ""
    except (SimulationDiverged, UserError) as exc:
        return None, f"{type(exc).__name__}: {exc}"


def simulate_methods(obj, gt: dict, sample, preds: dict, alphas, gt_settings, settings: EvalSettings,
                     progress: Optional[Progress] = None) -> dict:
    """Trajectories (tracked points) of every solver/method at every α with ground truth.

    Returns {(solver, method, α): {"positions": (T, N, 3) or None, "seconds": s, "error": str}}.
    """
    from ..core.normalise import Normalisation
    from ..core.types import MaterialField
    from ..solvers import lbs, mpm, spring_mass
    from ..solvers.material_sampling import PointMaterial
    from . import ground_truth as G

    gt_settings.device = settings.solver_device
    solid = G.build_solid(obj, gt_settings)
    if solid.tracked.shape != gt["tracked_rest"].shape or not np.allclose(solid.tracked, gt["tracked_rest"], atol=1e-9):
        raise UserError(f"{obj.object_id}: the regenerated object differs from the one the ground truth was made "
                        "for (different code or settings)")
    norm = Normalisation.from_dict(sample.meta["normalisation"])
    gt_alphas = [float(a) for a in gt["mpm_alphas"]]
    body = solid.body()
    results = {}
    centres = _voxel_centres_world(sample.grid, norm)
    for i, a in enumerate(alphas):
        if float(a) not in gt_alphas:
            continue
        for method, (arrays, native) in preds.items():
            if method.startswith("unipixie"):  # the model's Prediction (every sampler of it)
                field = native.mpm[i]
            else:
                f = native[i]
                field = MaterialField(sample.grid.geometry, sample.grid.occupancy, f["E"], f["nu"], f["density"],
                                      f["material"], float(a))
            sm = _world_material_at_points(field, norm, solid.points)

            def run_mpm(sm=sm):
                mat, _ = solid.capped_material(sm.E, sm.nu, sm.density, sm.material)
                t = time.perf_counter()
                sim = mpm.prepare(body, mat, solid.scenario, solid.frame_times, device=settings.solver_device,
                                  settings={"dx": solid.dx, "particles_per_cell_axis": gt_settings.particles_per_cell_axis})
                return sim.run([]).positions, time.perf_counter() - t

            r, err = _run_or_none(run_mpm)
            results[("mpm", method, float(a))] = {"positions": None if r is None else r[0],
                                                  "seconds": None if r is None else r[1], "error": err}
            if method != "unipixie":
                continue
            if native.lbs is not None:
                lp = native.lbs[i]

                def run_lbs(lp=lp, sm=sm):
                    mat = PointMaterial(centres, lp.E, lp.nu, np.asarray(native.mpm[i].density, np.float64),
                                        np.asarray(native.mpm[i].material, np.int32))
                    st = dict(G.lbs_solver_settings(gt_settings), skinning_params=np.asarray(lp.params, np.float64))
                    t = time.perf_counter()
                    sim = lbs.prepare(body, mat, solid.scenario, solid.frame_times, device=settings.solver_device,
                                      settings=st)
                    return sim.run([]).positions, time.perf_counter() - t

                r, err = _run_or_none(run_lbs)
                results[("lbs", method, float(a))] = {"positions": None if r is None else r[0],
                                                      "seconds": None if r is None else r[1], "error": err}
            if native.spring_mass is not None:
                sp = native.spring_mass[i]

                def run_spring(sp=sp, sm=sm):
                    mat = PointMaterial(solid.points, sm.E, sm.nu, sm.density, sm.material)
                    t = time.perf_counter()
                    sim = spring_mass.prepare_with_parameters(body, sp.stiffness, sp.softness, mat, solid.scenario,
                                                              solid.frame_times, device=settings.solver_device,
                                                              settings=G.spring_solver_settings(gt_settings))
                    return sim.run([]).positions, time.perf_counter() - t

                r, err = _run_or_none(run_spring)
                results[("spring_mass", method, float(a))] = {"positions": None if r is None else r[0],
                                                              "seconds": None if r is None else r[1], "error": err}
        if settings.fitters:
            from ..core.types import Trajectory

            target = Trajectory(solid.frame_times, gt["mpm_positions"][gt_alphas.index(float(a))])
            for solver, fitter in (("lbs", G.fit_lbs), ("spring_mass", G.fit_spring)):
                r, err = _run_or_none(lambda fitter=fitter: fitter(solid, float(a), target, gt_settings,
                                                                   progress=progress, keep_best=True))
                results[(solver, "test_time_fit", float(a))] = {
                    "positions": None if r is None else r["best_positions"],
                    "seconds": None if r is None else r["seconds"], "error": err}
        if progress is not None:
            progress.check()
    return results


# =========================================================================== renders, PSNR / SSIM
def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two images with values in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def ssim(a: np.ndarray, b: np.ndarray, sigma: float = 1.5) -> float:
    """Mean SSIM (Wang et al. 2004) of two (H, W, 3) images in [0, 1]: Gaussian window σ = 1.5,
    C1 = (0.01)², C2 = (0.03)², computed per channel and averaged."""
    from scipy.ndimage import gaussian_filter

    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    vals = []
    for ch in range(a.shape[-1]):
        x, y = a[..., ch], b[..., ch]
        mx, my = gaussian_filter(x, sigma), gaussian_filter(y, sigma)
        sxx = gaussian_filter(x * x, sigma) - mx * mx
        syy = gaussian_filter(y * y, sigma) - my * my
        sxy = gaussian_filter(x * y, sigma) - mx * my
        m = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
        vals.append(float(m.mean()))
    return float(np.mean(vals))


def full_vertex_motion(rest_all: np.ndarray, tracked_index: np.ndarray, tracked_positions: np.ndarray,
                       k: int = 4) -> np.ndarray:
    """Positions of every vertex (V, 3) from the tracked vertices' positions (N, 3): tracked vertices exactly,
    the others by inverse-distance-squared weighting of the displacements of their k nearest tracked vertices
    (at rest).  The same operator is applied to the ground truth and to every method."""
    from scipy.spatial import cKDTree

    rest_t = rest_all[tracked_index]
    disp = np.asarray(tracked_positions, np.float64) - rest_t
    k = min(k, len(rest_t))
    d, j = cKDTree(rest_t).query(rest_all, k=k)
    d, j = np.asarray(d).reshape(len(rest_all), k), np.asarray(j).reshape(len(rest_all), k)
    w = 1.0 / np.maximum(d, 1e-12) ** 2
    out = rest_all + np.einsum("vk,vkc->vc", w / w.sum(1, keepdims=True), disp[j])
    out[tracked_index] = tracked_positions
    return out


def render_frames(obj, frames: dict, frame_box: np.ndarray, out_dir: Path, settings: EvalSettings) -> dict:
    """Render deformed copies of ``obj``: frames = {name: (V, 3) vertex positions}; returns name -> (views, H, W, 3).

    Each copy is exported as .glb with two frame markers at the corners of ``frame_box`` (so all copies share
    the renderer's normalisation and cameras), imported into Blender and rendered with Workbench.
    """
    import torch._dynamo  # noqa: F401  (imports triton; it must be loaded before Blender's first render)

    from ..core.blender_io import render
    from ..core.blender_io.scene_import import loaded_objects
    from ..core.jobs import run_job

    out_dir.mkdir(parents=True, exist_ok=True)
    rs = render.RenderSettings(view_count=settings.render_views, resolution=settings.render_resolution,
                               engine="workbench", device="cpu")
    images = {}
    for name, verts in frames.items():
        path = out_dir / f"{name}.glb"
        obj.with_vertices(verts).export_glb(path, frame_box=frame_box)
        with loaded_objects(path) as objects:
            views = run_job(render.render_job(objects, rs))
        images[name] = views.images
        path.unlink()
    return images


# =========================================================================== the figure
def distributions_figure(path: Path, dists: dict, alphas) -> Path:
    """dists[(row, α)] = (target values, predicted values); rows: 'MPM log10 E', 'LBS log10 E', 'spring log10 k'."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in ("MPM log10 E [Pa]", "LBS log10 E [Pa]", "spring-mass log10 k [N]") if any(k[0] == r for k in dists)]
    fig, axes = plt.subplots(len(rows), len(alphas), figsize=(3.4 * len(alphas), 2.6 * len(rows)), squeeze=False)
    for r, row in enumerate(rows):
        for c, a in enumerate(alphas):
            ax = axes[r, c]
            t, p = dists.get((row, float(a)), (np.zeros(0), np.zeros(0)))
            if len(t) or len(p):
                both = np.concatenate([t, p]) if len(t) and len(p) else (t if len(t) else p)
                bins = np.linspace(np.percentile(both, 0.5), np.percentile(both, 99.5) + 1e-6, 40)
                if len(t):
                    ax.hist(t, bins=bins, alpha=0.55, density=True, label="target", color="#444444")
                if len(p):
                    ax.hist(p, bins=bins, alpha=0.55, density=True, label="UniPixie", color="#d04a02")
            ax.set_title(f"{row.split(' log10')[0]}, α = {a:g}", fontsize=9)
            ax.set_xlabel(row.split(" ", 1)[1] if " " in row else row, fontsize=8)
            ax.tick_params(labelsize=7)
            if r == 0 and c == 0:
                ax.legend(fontsize=7)
    fig.tight_layout()
    from ..core.atomic_io import save_figure

    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return path


# =========================================================================== the whole evaluation
def evaluate(checkpoint, data, out, baselines=(), settings: EvalSettings | None = None,
             progress: Optional[Progress] = None, log=None) -> dict:
    """Run the evaluation (module docstring); returns the report (also written to ``out``)."""
    from .dataset import DatasetDir

    settings = settings or EvalSettings()
    progress = progress or silent()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ds = DatasetDir(data)
    ids = ds.ids(settings.split)
    if settings.max_objects:
        ids = ids[: settings.max_objects]
    if not ids:
        raise UserError(f"{data}: split {settings.split!r} has no objects")
    alphas = [float(a) for a in settings.alphas]
    methods = Methods(checkpoint, baselines, settings)
    if not methods.names():
        raise UserError("nothing to evaluate: give a checkpoint and/or --baseline directories")
    pred_root = out / "predictions"
    dists: dict = {}
    sim_ids = ids[: settings.simulate_objects] if settings.simulate_objects else []
    table2_rows: list = []
    renders: list = []
    failures: list = []
    oracle_skipped = None if settings.oracle else "not asked for (--no-oracle)"
    oracle_settings = OracleSettings(draws=settings.oracle_draws, seed=settings.seed) if settings.oracle else None
    _drop_references(pred_root)                # never score another run's reference predictions
    t_all = time.perf_counter()
    for n, oid in enumerate(ids):
        sample = ds.sample(oid)
        m = sample.mpm
        targets = {"E_min": m.E_min, "E_max": m.E_max, "nu_min": m.nu_min, "nu_max": m.nu_max,
                   "density_min": m.density_min, "density_max": m.density_max, "material": m.material}
        _save_npz(pred_root / "targets" / f"{oid}.npz", **targets, **scoring_facts(ds, oid, sample.grid))
        preds = methods.predict_all(sample.grid, alphas)
        for name, (arrays, _) in preds.items():
            _save_npz(pred_root / name / f"{oid}.npz", **arrays)
        if settings.oracle and oracle_skipped is None:
            oracle_skipped = _save_oracle(ds, oid, sample, alphas, oracle_settings, pred_root)
        if "unipixie" in preds:
            arr = preds["unipixie"][0]
            for i, a in enumerate(alphas):
                t = targets_at(targets, a)
                _add(dists, ("MPM log10 E [Pa]", a), t["E"], arr["log10_E"][i])
                if sample.lbs is not None and "lbs_log10_E" in arr:
                    tl = np.log10(ann_mod.interpolate(sample.lbs.E_min, sample.lbs.E_max, a, "E"))
                    _add(dists, ("LBS log10 E [Pa]", a), tl, arr["lbs_log10_E"][i])
                if sample.spring is not None and "spring_log10_k" in arr:
                    tk = np.log10(ann_mod.interpolate(sample.spring.stiffness_min, sample.spring.stiffness_max, a, "E"))
                    pk = arr["spring_log10_k"][i]
                    if tk.size <= pk.size:  # a solid with fewer anchors than N_a uses the first entries
                        _add(dists, ("spring-mass log10 k [N]", a), tk, pk[:tk.size])
        if oid in sim_ids:
            try:
                rows, rend = _table2_object(ds, oid, sample, preds, alphas, settings, out, progress)
                table2_rows += rows
                renders += rend
            except UserError as exc:
                failures.append({"object_id": oid, "error": str(exc)})
        if log is not None:
            log(f"[{n + 1}/{len(ids)}] {oid}")
        progress.step(1.0, oid)

    t1 = table1(pred_root)
    if oracle_skipped is not None:             # a reference that failed part-way is not reported at all
        _drop_references(pred_root)
        for name in REFERENCES:
            t1.pop(name, None)
    breakdown = error_breakdown(pred_root)     # after the drop: a failed reference is not broken down either
    summary = ("logE_mse", "logrho_mse", "nu_mse", "material_acc", "runtime_s")
    report = {"format": REPORT_FORMAT, "checkpoint": str(checkpoint) if checkpoint else None,
              "dataset": str(data), "split": settings.split, "objects": len(ids), "alphas": alphas,
              "settings": asdict(settings),
              "methods": {k: {kk: v[kk] for kk in summary} for k, v in t1.items() if k not in REFERENCES},
              "references": {k: {"description": REFERENCES[k], **{kk: v[kk] for kk in summary}}
                             for k, v in t1.items() if k in REFERENCES},
              "references_skipped": oracle_skipped,
              "table1": t1, "in_range": {k: v.get("in_range", {}) for k, v in t1.items()},
              "table2": _summarise_table2(table2_rows, renders), "table2_objects": sim_ids,
              "table2_rows": table2_rows, "table2_by_class": table2_by_class(table2_rows),
              "table2_failures": failures, "breakdown": breakdown, "seconds": time.perf_counter() - t_all}
    card = Path(data) / "dataset.json"
    if card.is_file():
        c = json.loads(card.read_text())
        report["feature_model"] = c.get("feature_model")
        report["dataset_objects"] = c.get("objects")
    if methods.model is not None:
        report["model_feature_model"] = methods.model.cfg.feature_model
        report["model_is_clip"] = not methods.model.cfg.feature_model.startswith("offline-")
    fig = distributions_figure(out / "logE_distributions.png", dists, alphas) if dists else None
    report["figure"] = fig.name if fig else None
    write_report(out, report)
    return report


def _drop_references(pred_root: Path) -> None:
    import shutil

    for name in REFERENCES:
        shutil.rmtree(pred_root / name, ignore_errors=True)


def _save_oracle(ds, oid, sample, alphas, settings: OracleSettings, pred_root: Path):
    """Write both references' predictions of one object; returns None, or why the references are skipped."""
    try:
        part_ids, _ = ds.part_labels(oid)
        preds = oracle_predictions(ds.annotation(oid), part_ids, sample.grid.indices, sample.grid.geometry.resolution,
                                   alphas, settings)
    except (UserError, OSError) as exc:
        return f"{oid}: {exc}"
    for name, arrays in preds.items():
        _save_npz(pred_root / name / f"{oid}.npz", **arrays)
    return None


def _add(dists, key, target, pred):
    t, p = dists.get(key, (np.zeros(0), np.zeros(0)))
    dists[key] = (np.concatenate([t, np.asarray(target, np.float64)]), np.concatenate([p, np.asarray(pred, np.float64)]))


def _table2_object(ds, oid, sample, preds, alphas, settings: EvalSettings, out: Path, progress):
    from . import ground_truth as G

    obj = ds.object(oid)
    gt = ds.ground_truth(oid, need_motion=True)
    split = ds.record(oid).get("split", settings.split)
    gt_settings = ds.ground_truth_settings(oid, split)
    sims = simulate_methods(obj, gt, sample, preds, alphas, gt_settings, settings, progress)
    size = float(gt["info"]["size"])
    gt_alphas = [float(a) for a in gt["mpm_alphas"]]
    semantic_class = ds.record(oid).get("semantic_class")
    rows = []
    for (solver, method, a), r in sims.items():
        target = gt["mpm_positions"][gt_alphas.index(a)]
        rmse = G.motion_rmse(r["positions"], target) if r["positions"] is not None else None
        rows.append({"object_id": oid, "semantic_class": semantic_class, "solver": solver, "method": method,
                     "alpha": a, "rmse_m": rmse,
                     "relative_rmse": None if rmse is None else rmse / size, "seconds": r["seconds"],
                     "error": r["error"]})
    rend = []
    if settings.render_frames > 0:
        T = gt["mpm_positions"].shape[1]
        frames = sorted({int(round(x)) for x in np.linspace(0, T - 1, settings.render_frames + 1)[1:]})
        rest_all = obj.vertices()
        idx = gt["tracked_index"].astype(np.int64)
        allpos = [gt["mpm_positions"].reshape(-1, 3)] + [r["positions"].reshape(-1, 3) for r in sims.values()
                                                         if r["positions"] is not None]
        pts = np.concatenate(allpos + [rest_all])
        lo, hi = pts.min(0), pts.max(0)
        pad = 0.05 * (hi - lo).max()
        box = np.stack([lo - pad, hi + pad])
        for a in alphas:
            if a not in gt_alphas:
                continue
            target = gt["mpm_positions"][gt_alphas.index(a)]
            for f in frames:
                named = {"ground_truth": full_vertex_motion(rest_all, idx, target[f])}
                for (solver, method, aa), r in sims.items():
                    if aa == a and r["positions"] is not None:
                        named[f"{solver}__{method}"] = full_vertex_motion(rest_all, idx, r["positions"][f])
                imgs = render_frames(obj, named, box, out / "renders" / oid / f"a{a:g}_f{f}", settings)
                ref = imgs["ground_truth"]
                for name, im in imgs.items():
                    if name == "ground_truth":
                        continue
                    solver, method = name.split("__")
                    rend.append({"object_id": oid, "solver": solver, "method": method, "alpha": a, "frame": f,
                                 "psnr": float(np.mean([psnr(im[v], ref[v]) for v in range(len(im))])),
                                 "ssim": float(np.mean([ssim(im[v], ref[v]) for v in range(len(im))]))})
                _save_sheet(out / "renders" / oid / f"a{a:g}_f{f}.png", imgs)
    return rows, rend


def _save_sheet(path: Path, imgs: dict) -> None:
    from PIL import Image

    tiles = [np.concatenate(list(v), axis=0) for v in imgs.values()]
    sheet = np.concatenate(tiles, axis=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.clip(sheet, 0, 1) * 255).astype(np.uint8)).save(path)


def table2_by_class(rows: list) -> list:
    """Table 2's motion error per semantic class: where a solver cannot follow the ground-truth MPM.

    ``rows``: the per-object rows of Table 2 (``object_id``, ``semantic_class``, ``solver``, ``method``,
    ``alpha``, ``relative_rmse``).  Returns one dict per (class, solver, method): ``objects``, and
    ``relative_rmse`` — the mean over its objects and α of the tracked-point RMSE divided by the object's size
    (dimensionless) — with the ``worst`` object's id and value.  Failed simulations are left out.
    """
    out = []
    keys = sorted({(r.get("semantic_class") or "?", r["solver"], r["method"]) for r in rows})
    for cls, solver, method in keys:
        rs = [r for r in rows if (r.get("semantic_class") or "?", r["solver"], r["method"]) == (cls, solver, method)
              and r["relative_rmse"] is not None]
        if not rs:
            continue
        per_object: dict = {}
        for r in rs:
            per_object.setdefault(r["object_id"], []).append(r["relative_rmse"])
        means = {oid: float(np.mean(v)) for oid, v in per_object.items()}
        worst = max(means, key=means.get)
        out.append({"semantic_class": cls, "solver": solver, "method": method, "objects": len(means),
                    "relative_rmse": float(np.mean(list(means.values()))), "worst_object": worst,
                    "worst_relative_rmse": means[worst]})
    return out


def _summarise_table2(rows: list, renders: list) -> list:
    out = []
    keys = sorted({(r["solver"], r["method"], r["alpha"]) for r in rows})
    for solver, method, a in keys:
        rs = [r for r in rows if (r["solver"], r["method"], r["alpha"]) == (solver, method, a)]
        ok = [r for r in rs if r["rmse_m"] is not None]
        rd = [r for r in renders if (r["solver"], r["method"], r["alpha"]) == (solver, method, a)]
        out.append({"solver": solver, "method": method, "alpha": a, "objects": len(rs), "failed": len(rs) - len(ok),
                    "rmse_m": float(np.mean([r["rmse_m"] for r in ok])) if ok else None,
                    "relative_rmse": float(np.mean([r["relative_rmse"] for r in ok])) if ok else None,
                    "seconds": float(np.median([r["seconds"] for r in ok])) if ok else None,
                    "psnr": float(np.mean([r["psnr"] for r in rd if np.isfinite(r["psnr"])])) if rd else None,
                    "ssim": float(np.mean([r["ssim"] for r in rd])) if rd else None,
                    "errors": sorted({r["error"] for r in rs if r["error"]})[:3]})
    return out
