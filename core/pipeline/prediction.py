"""The model's material at α: where an object's prediction comes from, and the call a bake makes.

:class:`ModelPlan` (set by the Blender side before a bake: the feature grid, the α sweep, the checkpoint) per
object; :func:`load_sweep` keeps sweeps in memory; :func:`exact_prediction` gives the prediction at one α —
the sweep's own values when α is one of its α values, else a cached or freshly computed exact prediction (the
interpolated sweep is for the viewport only); :func:`model_material` is the "model" material source of
:mod:`unipixie.core.bake` (registered with :func:`~unipixie.core.bake.register_material_predictor`; it runs in
the bake's worker thread, without Blender).  May use the model (imported when called), the cache and the bake's
material conversion.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ...solvers.registry import SOLVER_NAMES
from ..errors import UserError


@dataclass
class ModelPlan:
    """Where an object's model material comes from (set by the Blender side before a bake; read in the
    bake's worker thread, so it holds plain values only).

    grid / sweep: the feature grid and α-sweep files.  checkpoint: the checkpoint directory.
    seed / steps: the sweep's inference settings.  device: torch device for exact predictions.
    """

    grid: str
    sweep: str
    checkpoint: str
    seed: int = 0
    steps: int = 15
    device: str = "cpu"


_PLANS: dict = {}
_SWEEPS: dict = {}
_LOCK = threading.Lock()


def set_plan(object_name: str, plan: Optional[ModelPlan]) -> None:
    """Make ``plan`` the model material of the object named ``object_name`` (``None`` forgets it)."""
    with _LOCK:
        if plan is None:
            _PLANS.pop(object_name, None)
        else:
            _PLANS[object_name] = plan


def get_plan(object_name: str) -> Optional[ModelPlan]:
    with _LOCK:
        return _PLANS.get(object_name)


def load_sweep(path):
    """An :class:`~unipixie.core.model.sweep.AlphaSweep` from disk, kept in memory (keyed by path and mtime)."""
    from ..model.sweep import AlphaSweep

    p = Path(path)
    try:
        stamp = p.stat().st_mtime_ns
    except OSError:
        raise UserError(f"the α sweep {p} is no longer in the cache; run Predict again") from None
    with _LOCK:
        hit = _SWEEPS.get(str(p))
        if hit is not None and hit[0] == stamp:
            return hit[1]
    sweep = AlphaSweep.load(p)
    with _LOCK:
        if len(_SWEEPS) > 16:
            _SWEEPS.clear()
        _SWEEPS[str(p)] = (stamp, sweep)
    return sweep


def sweep_heads(sweep) -> tuple:
    """The heads an α sweep holds."""
    heads = []
    if sweep.log10_E is not None:
        heads.append("mpm")
    if sweep.lbs_log10_E is not None:
        heads.append("lbs")
    if sweep.spring_log10_stiffness is not None:
        heads.append("spring_mass")
    return tuple(heads)


def prediction_from_sweep(sweep, alpha: float):
    """A one-α :class:`~unipixie.core.model.inference.Prediction` read from a sweep (exact at its own α
    values, interpolated between them)."""
    from ..model.inference import Prediction

    a = float(alpha)
    return Prediction(alphas=np.array([a]),
                      mpm=[sweep.field_at(a)] if sweep.log10_E is not None else None,
                      lbs=[sweep.lbs_at(a)] if sweep.lbs_log10_E is not None else None,
                      spring_mass=[sweep.spring_at(a)] if sweep.spring_log10_stiffness is not None else None,
                      meta=dict(sweep.meta))


def refined_path(plan: ModelPlan, alpha: float, heads) -> Path:
    """Where the exact prediction at ``alpha`` for ``plan`` is cached."""
    from ..paths import cache_dir, content_key

    key = content_key("refined", Path(plan.sweep).stem, round(float(alpha), 6), sorted(heads))
    return cache_dir("alpha_refined") / f"{key}.npz"


def exact_prediction(plan: ModelPlan, alpha: float, heads, progress=None, from_sweep: bool = True):
    """The model's exact prediction at ``alpha`` with at least ``heads``.

    Returns ``(Prediction, how, path)``: a one-α ``Prediction``; how it was obtained — ``"from the α
    sweep"`` (α is one of the sweep's values and the sweep has the heads), ``"refined"`` (a cached exact
    prediction) or ``"exact inference"`` (computed now and cached); and the file it came from.
    ``from_sweep=False`` skips the sweep (the panel's "refine" always keeps a file at its α).
    """
    from ..model.sweep import AlphaSweep
    from ..types import FeatureGrid

    alpha = float(alpha)
    if not 0.0 <= alpha <= 1.0:
        raise UserError(f"α must lie in [0, 1], got {alpha:g}")
    sweep = load_sweep(plan.sweep)
    heads = tuple(heads)
    have = sweep_heads(sweep)
    on_node = np.isclose(sweep.alphas, alpha, rtol=0.0, atol=1e-9)
    if from_sweep and on_node.any() and all(h in have for h in heads):
        node = float(sweep.alphas[int(np.argmax(on_node))])
        return prediction_from_sweep(sweep, node), "from the α sweep", Path(plan.sweep)
    want = tuple(h for h in SOLVER_NAMES if h in set(heads) | set(have))
    path = refined_path(plan, alpha, want)
    if path.is_file():
        try:
            return prediction_from_sweep(AlphaSweep.load(path), alpha), "refined", path
        except UserError:
            path.unlink(missing_ok=True)
    from ..model.inference import get_predictor

    predictor = get_predictor(plan.checkpoint, device=plan.device)
    grid = FeatureGrid.load(plan.grid)
    pred = predictor.predict(grid, [alpha], heads=want, seed=plan.seed, steps=plan.steps, progress=progress)
    one = AlphaSweep.from_prediction(pred, grid)
    one.meta.update({"checkpoint": str(plan.checkpoint), "seconds": pred.seconds})
    one.save(path)  # atomic (core/atomic_io.py), with a unique temporary name
    return pred, "exact inference", path


def model_material(obj, alpha: float, solver: str, solver_heads: bool = False):
    """The model's material for ``obj`` (a :class:`~unipixie.core.bake.BakeObject`) at ``alpha`` for ``solver``
    (registered as the bake's material predictor; no Blender access: runs in the bake's worker thread);
    ``solver_heads``: see :func:`~unipixie.core.bake.material_from_prediction`."""
    from ..bake import MODEL_HEADS, material_from_prediction

    plan = get_plan(obj.name)
    if plan is None:
        raise UserError(f"object '{obj.name}' has no predicted material yet: run Predict in the UniPixie panel "
                        "(after Render views and Features), or bake with a homogeneous material or a field file")
    pred, how, _ = exact_prediction(plan, alpha, MODEL_HEADS[solver])
    res = material_from_prediction(obj, pred, 0, solver, solver_heads=solver_heads)
    res.description = f"model at α {float(alpha):g} ({how}, {Path(plan.checkpoint).name}, seed {plan.seed})"
    return res
