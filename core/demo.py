"""``unipixie demo``: the whole pipeline on built-in objects, on the CPU, in one command.

What it does (every step prints where it is and shows progress; Ctrl-C stops it):

1. Builds two procedural objects of the dataset (:mod:`unipixie.core.procedural`): a **potted
   plant** and a **rubber duck**, as textured ``.glb`` files, and imports each into an empty Blender
   scene as one closed mesh (parts united), with a ground plane, a camera and labels.
2. Runs the object pipeline (:mod:`unipixie.core.blender_io.pipeline`) on each: renders views, extracts the
   features the model was trained on (for the shipped model the render-pass appearance features
   ``appearance-gbuffer-v1``: Cycles' base colour, roughness, metallic and normal passes, no network and no
   weights, not CLIP; a model trained on the offline ViT gets those), and predicts the material with the model
   (default: the shipped ``models/default``) at exactly the α values the demo bakes (plant: 0, 0.5, 1; duck: 0.5),
   one batched pass per object — not the panel's 11-value α sweep, which is most of the model's time on a CPU (the
   panel's *Predict* makes it later for the α slider). Copies of the objects share the prediction (their pipeline
   record is copied; the fingerprint ignores placement). Meanwhile a worker thread compiles the solvers' Warp
   kernels (a fresh machine's kernel cache is empty).
3. Bakes the plant with **MPM at α = 0, 0.5 and 1** and with the **spring-mass** solver at α = 0.5
   (four copies side by side; each pot is clamped and the rest pushed sideways), and the duck, dropped
   on the ground, with **LBS** at α = 0.5 — on the CPU as many bakes at once as there are cores (Warp runs
   each simulation's CPU kernels on one core).  The MPM grid of each bake is sized to a compute budget from
   the predicted stiffness (the time step shrinks with the wave speed), so the demo's run time stays
   bounded whatever the model predicts; a spring-mass bake whose predicted springs would need more than
   :data:`SPRING_SUBSTEP_LIMIT` substeps per frame stops with a message instead.
4. Saves ``<out>/unipixie_demo.blend`` (bakes as shape keys or Mesh Cache files next to it), renders a
   contact sheet of frames, a picture of the plant's material field per α, and ``summary.json`` with
   how far every baked object moved and how different the α = 0 and α = 1 bakes are.

``--quick`` is the same with fewer views, fewer frames and coarser solvers (CI).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..solvers import registry as solver_registry
from .errors import CancelledError, UserError
from .jobs import usable_cores
from .progress import Progress, silent


# --------------------------------------------------------------------------- what the demo does
@dataclass(frozen=True)
class DemoObject:
    """A built-in object: a procedural class, its index and seed in the procedural set, and a label."""

    semantic_class: str
    index: int
    seed: int
    label: str


PLANT = DemoObject("potted_plant", 0, 0, "Potted plant")
DUCK = DemoObject("rubber_duck", 0, 0, "Rubber duck")


@dataclass(frozen=True)
class DemoPlan:
    """How much work the demo does.

    views / resolution: rendered views per object and their size (px).  frames / fps: the baked clip.  mpm_budget: particle ×
    substep updates allowed per MPM bake (sets its grid, within ``mpm_cells`` cells across the object).
    lbs_settings / spring_settings: solver settings.  sheet_frames / sheet_size: the contact sheet.
    plant_alphas: the plant's MPM bakes; spring_alpha: the plant's spring-mass bake; lbs_alpha: the
    duck's LBS bake.  push_speed: m/s given to the plants (their pots are held); drop_height: m of the
    duck above the ground.
    """

    name: str
    views: int
    resolution: int
    frames: int
    fps: int
    mpm_budget: float
    mpm_cells: tuple
    lbs_settings: dict
    spring_settings: dict
    sheet_frames: int
    sheet_size: tuple
    plant_alphas: tuple = (0.0, 0.5, 1.0)
    spring_alpha: float = 0.5
    lbs_alpha: float = 0.5
    push_speed: float = 0.8
    drop_height: float = 0.25


SPRING_SUBSTEP_LIMIT = 20_000
"""The demo's spring-mass bakes stop (and are reported) when the predicted springs need more substeps per
frame than this (20 000 × 48 frames is minutes on 2 CPU cores), instead of running for an hour."""

FULL = DemoPlan("full", views=24, resolution=224, frames=48, fps=24, mpm_budget=1.2e8,
                mpm_cells=(10, 32), lbs_settings={},
                spring_settings={"max_substeps_per_frame": SPRING_SUBSTEP_LIMIT},
                sheet_frames=6, sheet_size=(720, 360))
QUICK = DemoPlan("quick", views=6, resolution=224, frames=12, fps=24, mpm_budget=1.2e7,
                 mpm_cells=(8, 14), lbs_settings={"cubature_points": 120, "mass_samples": 1000, "collision_points": 64},
                 spring_settings={"max_substeps_per_frame": SPRING_SUBSTEP_LIMIT}, sheet_frames=4,
                 sheet_size=(480, 240))
BAKE_ORDER = ("spring_mass", "mpm", "lbs")
"""The demo's bakes start in this order (they run side by side on the CPU cores).  Measured on 2 idle cores in the
full demo (2026-11-27, sixth session): spring-mass 40–54 s (the bake default of 2048 anchors), each MPM plant 33–48 s,
the LBS duck 12–17 s (the shared cores' speed varies by 10–30 % between runs) — two at a time, the bakes end after
83–101 s in any order that starts the spring-mass or an MPM plant first."""

BLEND_NAME = "unipixie_demo.blend"
SHEET_NAME = "contact_sheet.png"
SUMMARY_NAME = "summary.json"
CLAMP_GROUP = "UniPixie clamp (pot)"
MOVE_THRESHOLD = 1e-3
"""Metres: a baked object whose vertices never move further than this did not "move"."""


@dataclass
class BakeSummary:
    object: str
    solver: str
    alpha: float
    material: str
    mode: str
    simulate_seconds: float
    max_displacement: float
    settings: dict = field(default_factory=dict)
    solver_steps: dict = field(default_factory=dict)
    """What the solver reported about its stepping (``substeps``, ``substep_s``, ``step_bound``, ``anchors``, where
    it says), from the trajectory's meta."""


@dataclass
class DemoResult:
    """Where everything is and what happened."""

    out_dir: str
    blend: str
    contact_sheet: str
    field_pictures: list
    objects: list
    bakes: list
    failed: list
    alpha_difference: float
    solver_difference: float
    """RMS (m, over the plant's vertices and the clip) of the difference between the MPM and the spring-mass
    plants' displacements at the spring-mass bake's α: one material, one motion (docs/fidelity.md)."""
    solver_difference_over_size: float
    seconds: float
    stage_seconds: dict
    stage_cpu_seconds: dict
    """CPU seconds of the whole process (all threads) during each stage; ``cpu_seconds``: from the start to the end."""
    cpu_seconds: float
    checkpoint: str
    plan: str

    def to_dict(self) -> dict:
        return asdict(self)


# --------------------------------------------------------------------------- checks and sizes
def check_checkpoint(checkpoint=None) -> Path:
    """The model the demo uses, refused early when missing or trained on features that need downloaded weights
    (CLIP): the demo extracts the features the model names, and only weight-free extractors
    (:mod:`.extractors`: the offline ViT, the render-pass appearance) can run anywhere without a download."""
    from . import extractors
    from .pipeline import checkpoint_feature_model, resolve_checkpoint

    ckpt = resolve_checkpoint(checkpoint)
    trained_on, width = checkpoint_feature_model(ckpt)
    if extractors.needs_weights(trained_on):
        free = ", ".join(extractors.feature_model(n) for n in extractors.EXTRACTORS if n != "clip")
        raise UserError(f"the demo needs no downloaded weights, but the model in {ckpt} was trained on {trained_on!r} "
                        f"(D = {width}), which needs CLIP weights; use a checkpoint trained on weight-free features "
                        f"({free}; the shipped models/default is)")
    return ckpt


def max_wave_speed(field_world) -> float:
    """Largest elastic wave speed (m/s) of the simulated, not held material of a world-space MaterialField:
    sqrt(M / ρ) with M the P-wave modulus (bulk modulus for weakly compressible classes)."""
    from ..solvers import materials
    from ..solvers.materials import p_wave_factor

    mat = np.asarray(field_world.material, np.int64)
    moving = np.array([c.simulated and not c.held_fixed for c in materials.MATERIAL_CLASSES])[mat]
    if not moving.any():
        return 0.0
    E = np.asarray(field_world.E, np.float64)[moving]
    nu = np.asarray(field_world.nu, np.float64)[moving]
    rho = np.asarray(field_world.density, np.float64)[moving]
    return float(np.sqrt(np.max(E * p_wave_factor(nu, mat[moving]) / rho)))


def mpm_cells_for_budget(wave_speed: float, size: float, volume: float, frames: int, fps: float, budget: float,
                         cells: tuple) -> tuple[int, float]:
    """The finest MPM grid (cells across the object, within ``cells``) whose cost fits ``budget``.

    Cost = (frames − 1) × substeps per frame × particles, with substeps = ⌈Δt_frame · c / (cfl · dx)⌉ (the
    solver's CFL bound with its default ``cfl``) and particles = volume / dx³ × (particles per cell) — an
    estimate (the solver also counts particle speeds).  Returns (cells across, estimated cost).
    """
    from ..solvers.mpm_settings import MPMSettings

    s = MPMSettings()
    lo, hi = int(cells[0]), int(cells[1])
    cost = math.inf
    for n in range(hi, lo - 1, -1):
        dx = size / n
        substeps = max(1, math.ceil((1.0 / fps) * wave_speed / (s.cfl * dx)))
        particles = volume / dx ** 3 * s.particles_per_cell_axis ** 3
        cost = (frames - 1) * substeps * particles
        if cost <= budget:
            return n, cost
    return lo, cost


def untrained_checkpoint(directory, preset_name: str = "small", seed: int = 0, spread: float = 0.02,
                         favour_class: Optional[str] = "jelly", spring_anchors: Optional[int] = None) -> Path:
    """Save an **untrained** model of a preset's size, for the offline features, as a checkpoint.

    For timing the demo at the shipped model's size and for tests, before a trained model exists: its
    materials are meaningless.  At initialisation the AdaLN-zero layers are exactly zero (every output
    would be one constant); they are filled with N(0, spread²).  ``favour_class`` biases the MPM head's
    class logits so that the object is one simulated material (a random class per voxel would hold
    stationary voxels fixed all over it).
    """
    import torch

    from ..solvers import materials
    from . import clip_features as cf
    from .model import UniPixieModel, preset, save_model

    over = {"feature_model": cf.OFFLINE_FEATURE_MODEL, "feature_dim": int(cf.OFFLINE_VISION_CFG["width"])}
    if spring_anchors is not None:
        over["spring_anchors"] = int(spring_anchors)
    if preset_name == "tiny":
        over["patch_size"] = 4          # tests: per-voxel tokens at 64³ would be slow
    cfg = preset(preset_name, **over)
    torch.manual_seed(int(seed))
    model = UniPixieModel(cfg)
    g = torch.Generator().manual_seed(int(seed) + 1)
    with torch.no_grad():
        for _, p in model.named_parameters():
            if not p.detach().abs().max() > 0:
                p.copy_(torch.randn(p.shape, generator=g) * spread)
        if favour_class is not None:
            bias = model.mpm.final.linear.bias
            per_voxel = 3 + cfg.num_classes            # (log E, log ρ, ν) + class logits per voxel of a patch token
            if bias.numel() == cfg.patch_voxels * per_voxel:
                bias.view(cfg.patch_voxels, per_voxel)[:, 3 + materials.get(favour_class).id] += 4.0
    return save_model(model, Path(directory), info={"untrained": True, "preset": preset_name, "seed": int(seed)})


# --------------------------------------------------------------------------- the run
class _Stages:
    """Progress over the demo's stages (shares of the bar) and the printed timeline; each stage's wall seconds and
    the CPU seconds the whole process spent meanwhile (all its threads: the kernel warm-up, the bakes' workers)."""

    def __init__(self, progress: Progress, say: Callable[[str], None], weights: dict):
        self.progress, self.say, self.weights = progress, say, weights
        self.total = sum(weights.values())
        self.seconds: dict = {}
        self.cpu_seconds: dict = {}
        self.t0 = time.perf_counter()

    def sub(self, name: str, text: str) -> Progress:
        self.say(f"[{time.perf_counter() - self.t0:6.0f} s] {text}")
        self._name, self._start, self._cpu = name, time.perf_counter(), time.process_time()
        return self.progress.sub(self.weights[name] / self.total * self.progress.total, 1.0, name)

    def done(self):
        self.seconds[self._name] = round(self.seconds.get(self._name, 0.0) + time.perf_counter() - self._start, 2)
        self.cpu_seconds[self._name] = round(self.cpu_seconds.get(self._name, 0.0) + time.process_time() - self._cpu, 2)


def run_demo(out_dir="demo", quick: bool = False, checkpoint=None, device: str = "cpu",
             say: Callable[[str], None] = print, progress: Optional[Progress] = None) -> DemoResult:
    """Run the demo (see the module docstring) into ``out_dir``; returns a :class:`DemoResult`.  A cancelled
    demo (Ctrl-C, Esc) removes the files it had made in ``out_dir`` (files there before it started stay), so no
    half demo is left that looks like a whole one."""
    out = Path(out_dir).expanduser().resolve()
    existed = out.is_dir()
    before = set(out.rglob("*")) if existed else set()
    try:
        return _run_demo(out_dir, quick, checkpoint, device, say, progress)
    except (CancelledError, KeyboardInterrupt):
        made = sorted((p for p in out.rglob("*") if p not in before) if out.is_dir() else [], reverse=True)
        for p in made:  # deepest first: files, then the folders they were in
            try:
                p.unlink() if not p.is_dir() or p.is_symlink() else p.rmdir()
            except OSError:
                pass
        if out.is_dir() and not existed and not any(out.iterdir()):
            out.rmdir()
        raise


def _run_demo(out_dir, quick, checkpoint, device, say, progress) -> DemoResult:
    """The demo's work (see :func:`run_demo`).

    It starts a new, empty Blender scene in the current session (the command line's), so run it from the
    command line, not inside a Blender session with unsaved work.  A bake that fails (e.g. a prediction too
    stiff for the demo's substep limit) is reported and recorded in the summary (``failed``); the other
    bakes and the pictures are still made.
    """
    from . import extractors, procedural
    from .bake import MODEL_HEADS
    from .blender_io import demo_scene as ds
    from .blender_io import pipeline as pio
    from .blender_io.bake import registered_properties
    from .jobs import run_side_by_side
    from .pipeline import PipelineSettings, checkpoint_feature_model

    plan = QUICK if quick else FULL
    t_start, cpu_start = time.perf_counter(), time.process_time()
    progress = progress or silent()
    out = Path(out_dir).expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    ckpt = check_checkpoint(checkpoint)
    say(f"UniPixie demo ({plan.name}): a potted plant and a rubber duck, from pictures to physics, on {device}.")
    say(f"  model: {ckpt}; output: {out}")
    stages = _Stages(progress, say, {"objects": 2, "features": 8 if quick else 14, "predict": 10 if quick else 30,
                                     "bake": 20 if quick else 45, "pictures": 3})
    settings = PipelineSettings(view_count=plan.views, resolution=plan.resolution, checkpoint=str(ckpt),
                                device=device).with_model_recipe()
    warm_up = KernelWarmUp(device).start()

    with registered_properties():
        # 1. objects and scene --------------------------------------------------------------
        p = stages.sub("objects", "building the demo objects and the scene")
        ds.reset(plan.frames, plan.fps)
        objects_dir = out / "objects"
        objects_dir.mkdir(exist_ok=True)
        sources = {}
        for spec in (PLANT, DUCK):
            po = procedural.generate(spec.index, seed=spec.seed, semantic_class=spec.semantic_class)
            glb = po.export_glb(objects_dir / f"{spec.semantic_class}.glb")
            sources[spec.semantic_class] = ds.import_solid(glb, spec.label)
            p.step(0.25)
        plant, duck = sources["potted_plant"], sources["rubber_duck"]
        ds.part_vertex_group(plant, "pot", CLAMP_GROUP)
        ground = ds.add_ground()
        pw = float(np.ptp(np.asarray([v.co[0] for v in plant.data.vertices])))
        gap = max(0.35, 1.5 * pw)
        # the plant four times in a row: MPM at each α of the plan, then the spring-mass solver
        bakes_todo = [("mpm", float(a)) for a in plan.plant_alphas] + [("spring_mass", plan.spring_alpha)]
        plants = []
        for k, (solver, a) in enumerate(bakes_todo):
            x = (k - 1.5) * gap
            label = f"{solver_registry.SOLVERS[solver].label} α={a:g}"
            name = f"{PLANT.label} {label}"
            obj = plant if k == 0 else ds.duplicate(plant, name, x, 0.0)
            if k == 0:
                obj.name = obj.data.name = name
                ds.place_on_ground(obj, x, 0.0)
            _setup(obj, solver=solver, alpha=a, ground=ground, device=device, clamp_group=CLAMP_GROUP,
                   velocity=(plan.push_speed, 0.0, 0.0))
            ds.add_label(label, (x, -0.22, 0.01))
            plants.append(obj)
        x = 2.5 * gap
        duck.name = duck.data.name = f"{DUCK.label} {solver_registry.SOLVERS['lbs'].label} α={plan.lbs_alpha:g}"
        ds.place_on_ground(duck, x, -0.3, plan.drop_height)
        _setup(duck, solver="lbs", alpha=plan.lbs_alpha, ground=ground, device=device)
        ds.add_label(f"{solver_registry.SOLVERS['lbs'].label} α={plan.lbs_alpha:g}", (x, -0.42, 0.01))
        ds.add_camera(target=(0.45 * gap, 0.0, 0.36), distance=1.9 + 2.4 * gap)
        blend = out / BLEND_NAME
        bpy_save(blend)          # saved first: bakes write their point caches next to it
        p.step(0.5)
        stages.done()

        # 2. render views + features --------------------------------------------------------------
        trained_on, _ = checkpoint_feature_model(ckpt)
        p = stages.sub("features", f"rendering {settings.view_count} views per object ({settings.engine}, "
                                   f"{settings.resolution} px: the model's training recipe) and extracting the "
                                   f"features it was trained on: {extractors.label(trained_on)}")
        for src in (plants[0], duck):
            result = pio.run_to_end(pio.features_step(src, settings), p.sub(0.5, 1.0, src.name))
            say(f"         {src.name}: {int(result.grid.occupancy.sum())} voxels, D = {result.grid.dim} "
                f"({'from the cache' if result.cache_hit else f'{sum(result.timings.values()):.1f} s'})")
        stages.done()

        # 3. predict at the α values the demo bakes ------------------------------------------------------
        jobs = [(o, solver, a) for o, (solver, a) in zip(plants, bakes_todo)] + [(duck, "lbs", plan.lbs_alpha)]
        p = stages.sub("predict", "predicting the material at the α values the demo bakes (one batched pass per "
                                  "object)")
        for src in (plants[0], duck):
            mine = [(solver, a) for o, solver, a in jobs if o is src or (src is plants[0] and o in plants)]
            heads = tuple(h for h in solver_registry.SOLVER_NAMES if any(h in MODEL_HEADS[sv] for sv, _ in mine))
            s = PipelineSettings(**{**settings.to_dict(), "heads": heads, "alphas": tuple(a for _, a in mine)})
            t = time.perf_counter()
            pio.run_to_end(pio.predict_step(src, s), p.sub(0.5, 1.0, src.name))
            say(f"         {src.name}: α {', '.join(f'{a:g}' for a in s.alphas)}, heads {', '.join(heads)} in "
                f"{time.perf_counter() - t:.1f} s")
        for obj in plants[1:]:
            pio.copy_pipeline(plants[0], obj)      # copies share the prediction (placement-invariant fingerprint)
        stages.done()

        # 4. bakes ----------------------------------------------------------------------------------
        workers = bake_workers(device, len(jobs))
        p = stages.sub("bake", f"baking {len(jobs)} objects ({plan.frames} frames at {plan.fps} fps"
                               + (f", {workers} at a time" if workers > 1 else "") + ")")
        planned = []
        for obj, solver, alpha in jobs:
            planned.append((obj, solver, alpha, _solver_settings(obj, solver, alpha, plan, settings, say)))
        planned.sort(key=lambda job: BAKE_ORDER.index(job[1]))       # the longest first (BAKE_ORDER)
        bakes, failed = [], []

        def bake_done(index, rep):
            obj, solver, alpha, solver_settings = planned[index]
            if isinstance(rep, Exception):
                if not isinstance(rep, UserError):
                    raise rep
                failed.append({"object": obj.name, "solver": solver, "alpha": alpha, "error": str(rep)})
                say(f"         {obj.name}: {solver} bake FAILED: {rep}")
                return
            moved = _max_displacement(obj, plan.frames)
            meta = getattr(rep.trajectory, "meta", None) or {}
            steps = {k: meta[k] for k in ("substeps", "substep_s", "step_bound", "anchors")
                     if k in meta and (meta[k] is None or np.isscalar(meta[k]))}
            bakes.append(BakeSummary(obj.name, solver, alpha, rep.material, rep.mode, round(rep.simulate_seconds, 2),
                                     moved, {k: v for k, v in solver_settings.items() if np.isscalar(v)}, steps))
            say(f"         {obj.name}: {rep.mode.replace('_', ' ')}, simulated in {rep.simulate_seconds:.1f} s, "
                f"moved up to {100 * moved:.1f} cm")

        run_side_by_side(
            [(lambda o=obj, sv=solver, ss=sset: warm_up.ready(sv, pio.bake_step(o, settings, solver_settings=ss)),
              p.sub(1.0 / len(jobs), 1.0, obj.name)) for obj, solver, _, sset in planned], max_running=workers,
            on_done=bake_done)
        say(f"         {warm_up.report()}")
        bpy_save(blend)
        stages.done()

        # 5. pictures -------------------------------------------------------------------------------
        p = stages.sub("pictures", "rendering the contact sheet and the field pictures")
        frames = np.unique(np.linspace(1, plan.frames, plan.sheet_frames).round().astype(int)).tolist()
        paths = ds.render_frames(frames, out / "frames", size=plan.sheet_size)
        sheet = contact_sheet(paths, [f"frame {f} (t = {(f - 1) / plan.fps:.2f} s)" for f in frames], out / SHEET_NAME)
        p.step(0.5)
        sweep_path = pio.read_record(plants[0]).file("predict", "sweep")
        fields = field_pictures(sweep_path, plan.plant_alphas, out, title=PLANT.label)
        p.step(0.5)
        stages.done()
        mpm = [o for o, (solver, _) in zip(plants, bakes_todo) if solver == "mpm"]
        baked = {b.object for b in bakes}
        difference = (_alpha_difference(mpm[0], mpm[-1], plan.frames)
                      if mpm[0].name in baked and mpm[-1].name in baked else float("nan"))
        same_alpha = [o for o, job in zip(plants, bakes_todo) if job == ("mpm", float(plan.spring_alpha))]
        spring = [o for o, (solver, _) in zip(plants, bakes_todo) if solver == "spring_mass"]
        solver_rms = (_rms_difference(same_alpha[0], spring[0], plan.frames)
                      if same_alpha and spring and same_alpha[0].name in baked and spring[0].name in baked
                      else float("nan"))
        plant_size = float(max(plants[0].dimensions))

    result = DemoResult(out_dir=str(out), blend=str(blend), contact_sheet=str(sheet),
                        field_pictures=[str(f) for f in fields], objects=[str(p) for p in sorted(objects_dir.glob("*.glb"))],
                        bakes=[asdict(b) for b in bakes], failed=failed, alpha_difference=difference,
                        solver_difference=solver_rms, solver_difference_over_size=solver_rms / plant_size,
                        seconds=round(time.perf_counter() - t_start, 1), stage_seconds=stages.seconds,
                        stage_cpu_seconds=stages.cpu_seconds, cpu_seconds=round(time.process_time() - cpu_start, 1),
                        checkpoint=str(ckpt), plan=plan.name)
    from .atomic_io import write_json

    write_json(out / SUMMARY_NAME, result.to_dict())
    say(f"Done in {result.seconds:.0f} s ({result.cpu_seconds:.0f} s of CPU).  The α = {plan.plant_alphas[0]:g} and "
        f"α = {plan.plant_alphas[-1]:g} MPM "
        f"plants differ by up to {100 * difference:.1f} cm; at α = {plan.spring_alpha:g} the MPM and spring-mass "
        f"plants' motions differ by {1000 * solver_rms:.1f} mm RMS ({100 * solver_rms / plant_size:.1f} % of the "
        "plant's size).")
    for f in failed:
        say(f"  FAILED: {f['object']} ({f['solver']}): {f['error']}")
    say(f"  Blender file:    {blend}  (open it, press Space to play; the UniPixie panel shows every step done)")
    say(f"  contact sheet:   {sheet}")
    say(f"  field pictures:  {', '.join(str(f) for f in fields)}")
    say(f"  objects (.glb):  {objects_dir}")
    say(f"  summary:         {out / SUMMARY_NAME}")
    return result


def bake_workers(device: str, jobs: int) -> int:
    """How many demo bakes run at once: one per CPU core this process may use on the CPU (Warp runs each
    simulation's CPU kernels on one core), one at a time on a GPU."""
    if str(device).startswith("cuda"):
        return 1
    return max(1, min(int(jobs), usable_cores()))


class KernelWarmUp:
    """Compile the solvers' Warp kernels in a worker thread while the demo builds, renders and predicts (an empty
    kernel cache costs about 20 s of CPU compiling, forward kernels only, otherwise paid inside the first bake of each
    solver).  It runs a two-frame simulation of a small sphere with each solver through the public solver API, so
    exactly the kernels a bake launches get compiled; :meth:`ready` holds a bake back until its solver's kernels
    are done.  A failure here is ignored (the bake compiles then)."""

    SOLVERS = BAKE_ORDER
    """In the order of the demo's bakes."""
    SETTINGS = {"mpm": {"cells_across": 4}, "spring_mass": {"anchors": 64},
                "lbs": {"cubature_points": 60, "mass_samples": 500, "collision_points": 32}}
    """The smallest runs that launch the solvers' kernels: Warp compiles a kernel module whole whatever the
    resolution, and at the solvers' bake defaults the sphere was 15 s of MPM (120 000 particles), 4 s of spring-mass
    and 2.6 s of LBS CPU on the 2-core machine, spent before the bakes could start."""

    def __init__(self, device: str = "cpu"):
        import threading

        self.device = device
        self.seconds: dict = {}
        self.error = ""
        self._done = {s: threading.Event() for s in self.SOLVERS}
        self._worker = None

    def start(self) -> "KernelWarmUp":
        from .jobs import start_worker

        self._worker = start_worker(self._main, name="unipixie-warp-warm-up")
        return self

    def wait(self, timeout=None) -> bool:
        """Wait (at most ``timeout`` s) for the warm-up to end; True when it has."""
        from .jobs import wait_workers

        return self._worker is not None and wait_workers([self._worker], timeout)

    def _main(self):
        try:
            import trimesh

            from ..solvers import api
            from ..solvers.body import Body
            from ..solvers.material_sampling import HomogeneousMaterial
            from ..solvers.scenario import Scenario

            mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
            mesh.apply_translation([0.0, 0.0, 0.1])
            body = Body.from_mesh(mesh)
            for solver in self.SOLVERS:
                t0 = time.perf_counter()
                api.simulate(solver, body, HomogeneousMaterial(E=1e5, nu=0.3, density=1000.0, material="jelly"),
                             Scenario(ground_height=0.0), np.linspace(0.0, 1.0 / 24.0, 2), [], device=self.device,
                             settings=self.SETTINGS.get(solver))
                self.seconds[solver] = time.perf_counter() - t0
                self._done[solver].set()
        except Exception as exc:          # noqa: BLE001 - only a head start; the bakes compile what is missing
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            for event in self._done.values():
                event.set()

    def ready(self, solver: str, job):
        """``job`` (a bake's job generator) once ``solver``'s kernels are compiled; yields while waiting."""
        event = self._done.get(solver)
        while event is not None and not event.wait(0.05):
            yield 0.0, f"waiting for the {solver_registry.SOLVERS[solver].label} kernels to compile"
        return (yield from job)

    def report(self) -> str:
        done = ", ".join(f"{solver_registry.SOLVERS[k].label} {v:.0f} s" for k, v in self.seconds.items())
        return (f"Warp kernels compiled in the background ({done})" if done else "Warp kernels: no warm-up") + (
            f"; warm-up failed ({self.error}), the bakes compile" if self.error else "")


def bpy_save(path: Path) -> None:
    from .blender_io.demo_scene import save

    save(path)


def _setup(obj, solver: str, alpha: float, ground, device: str, clamp_group: str = "",
           velocity=(0.0, 0.0, 0.0)) -> None:
    s = obj.unipixie
    s.solver, s.alpha, s.bake_material_source = solver, float(alpha), "model"
    s.device = "cuda" if str(device).startswith("cuda") else "cpu"
    s.bake_ground = ground
    s.bake_clamp_group = clamp_group
    s.bake_initial_velocity = velocity


def _solver_settings(obj, solver: str, alpha: float, plan: DemoPlan, settings, say) -> dict:
    """Solver settings of one demo bake; MPM: the grid that fits the plan's compute budget (from the object's
    predicted material at α: its model plan under the pipeline ``settings``)."""
    if solver == "lbs":
        return dict(plan.lbs_settings)
    if solver == "spring_mass":
        return dict(plan.spring_settings)
    from .blender_io import demo_scene as ds
    from .bake import plan_material
    from .blender_io import pipeline as pio
    from .blender_io.bake import read_object

    bo = read_object(obj)
    field_world = plan_material(bo, alpha, "mpm", pio.plan_of(obj, settings)).spec
    c = max_wave_speed(field_world)
    cells, cost = mpm_cells_for_budget(c, bo.size, ds.mesh_volume(obj), plan.frames, plan.fps, plan.mpm_budget,
                                       plan.mpm_cells)
    say(f"         {obj.name}: wave speed up to {c:.0f} m/s → MPM grid of {cells} cells across "
        f"(~{cost:.2g} particle-substeps)")
    # cells_across given: the grid its budget affords (the solver's bake default would also refine the thinnest
    # parts to 4 cells across their thickness: leaves, some 10³ times the particles of this budget on a CPU)
    return {"cells_across": cells}


def _max_displacement(obj, frames: int) -> float:
    """Largest distance (m) any vertex of the baked object gets from its rest position over the clip."""
    motion = _baked_motion(obj, frames)
    return float(np.linalg.norm(motion[1:] - motion[0], axis=-1).max())


def displacement_rms(a: np.ndarray, b: np.ndarray) -> float:
    """RMS (m) of the difference between two motions' displacements from their first frame, over the vertices and
    frames 2 … T — the demo's ``solver_difference`` (also ``unipixie bench demo_plant``'s).  a, b: (T, N, 3)
    positions, metres."""
    d = _displacement_difference(a, b)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))


def _displacement_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T − 1, N, 3) m: the difference between two motions' displacements from their first frame, frames 2 … T.
    a, b: (T, N, 3) positions, metres."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 3 or len(a) < 2:
        raise ValueError(f"motions of shapes {a.shape} and {b.shape} cannot be compared")
    return (a[1:] - a[0]) - (b[1:] - b[0])


def _baked_motion(obj, frames: int) -> np.ndarray:
    """(frames, N, 3) m: a baked copy's evaluated vertex positions at frames 1..frames."""
    from .blender_io.bake import evaluated_positions

    return np.stack([evaluated_positions(obj, f) for f in range(1, int(frames) + 1)])


def _rms_difference(a, b, frames: int) -> float:
    """:func:`displacement_rms` of two baked copies over frames 1..frames (NaN with fewer than two frames)."""
    if int(frames) < 2:
        return float("nan")
    return displacement_rms(_baked_motion(a, frames), _baked_motion(b, frames))


def _alpha_difference(a, b, frames: int) -> float:
    """Largest difference (m) between two baked copies' displacements from rest over the clip."""
    d = _displacement_difference(_baked_motion(a, frames), _baked_motion(b, frames))
    return float(np.linalg.norm(d, axis=-1).max())


# --------------------------------------------------------------------------- pictures (no Blender)
def contact_sheet(images, captions, path, columns: Optional[int] = None) -> Path:
    """Tile PNG ``images`` into one sheet (``columns``: default about square) with a caption under each."""
    from PIL import Image, ImageDraw

    tiles = [Image.open(p).convert("RGB") for p in images]
    if not tiles:
        raise UserError("no frames to put on the contact sheet")
    w, h = tiles[0].size
    cols = min(columns or math.ceil(math.sqrt(len(tiles))), len(tiles))
    rows = math.ceil(len(tiles) / cols)
    pad = 22
    sheet = Image.new("RGB", (cols * w, rows * (h + pad)), "white")
    draw = ImageDraw.Draw(sheet)
    for i, (tile, cap) in enumerate(zip(tiles, captions)):
        x, y = (i % cols) * w, (i // cols) * (h + pad)
        sheet.paste(tile, (x, y))
        draw.text((x + 6, y + h + 5), cap, fill=(0, 0, 0))
    from .atomic_io import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        sheet.save(tmp, format=Image.registered_extensions().get(path.suffix.lower(), "PNG"))
    return path


def field_pictures(sweep_path, alphas, out_dir, title: str = "") -> list:
    """One PNG per α: two slices through the object's centre (front: x–z, side: y–z) coloured by log10 E
    with the viewport's colour map and one colour scale for all α (so the pictures compare)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    from .pipeline import FieldColourScale, format_pascal, load_sweep

    sweep = load_sweep(sweep_path)
    scale = FieldColourScale.of_sweep(sweep)
    cmap = ListedColormap(scale.lut_srgb).with_extremes(bad="white")
    occ = sweep.occupancy
    idx = np.argwhere(occ)
    centre = np.round(idx.mean(0)).astype(int)
    lo, hi = idx.min(0), idx.max(0) + 1
    paths = []
    for a in alphas:
        vol = np.full(occ.shape, np.nan)
        vol[occ] = sweep.values_at("log10_E", float(a))
        fig, axes = plt.subplots(1, 2, figsize=(8, 4.6), constrained_layout=True)
        front = vol[lo[0]:hi[0], centre[1], lo[2]:hi[2]].T            # (z, x)
        side = vol[centre[0], lo[1]:hi[1], lo[2]:hi[2]].T             # (z, y)
        im = None
        for ax, img, name in ((axes[0], front, "front (x–z) slice"), (axes[1], side, "side (y–z) slice")):
            im = ax.imshow(np.ma.masked_invalid(img), origin="lower", cmap=cmap, vmin=scale.log10_min,
                           vmax=scale.log10_max, interpolation="nearest")
            ax.set_title(name)
            ax.set_xticks([])
            ax.set_yticks([])
        bar = fig.colorbar(im, ax=axes, shrink=0.85, label="Young's modulus E")
        ticks = scale.ticks(5)
        bar.set_ticks([scale.log10_min + t * (scale.log10_max - scale.log10_min) for t, _, _ in ticks])
        bar.set_ticklabels([label for _, _, label in ticks])
        med = 10 ** float(np.median(vol[occ]))
        fig.suptitle(f"{title}: material field at α = {float(a):g} (median E {format_pascal(med)})")
        path = Path(out_dir) / f"field_alpha_{float(a):.2f}.png"
        from .atomic_io import save_figure

        save_figure(fig, path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths
