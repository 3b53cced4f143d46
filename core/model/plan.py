"""An object's model prediction at any α: the plan (where its sweep and feature grid are) and the exact prediction.

:class:`ModelPlan` is plain data — the object's feature grid, its α sweep, the checkpoint, the sweep's seed and
steps, the torch device — built from the object's pipeline record by whoever starts a bake and carried by the
bake's model material source (:class:`~unipixie.core.bake.ModelSource`, field ``plan``), so a bake's worker thread
needs neither Blender nor any process-wide state.  :func:`load_sweep` keeps sweeps in memory;
:func:`exact_prediction` gives the prediction at one α — the sweep's own values when α is one of its α values,
else a cached or freshly computed exact prediction (the interpolated sweep is for the viewport only).
α is trusted here (a float in [0, 1], checked at the entry points by :func:`unipixie.core.types.check_alpha`).
May use the model's inference and sweep, the cache paths and the solvers' registry.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...solvers.registry import SOLVER_NAMES
from ..errors import UserError


@dataclass(frozen=True)
class ModelPlan:
    """Where an object's model material comes from (built from its pipeline record before a bake, read in the
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


_SWEEPS: dict = {}
_LOCK = threading.Lock()


def load_sweep(path):
    """An :class:`~unipixie.core.model.sweep.AlphaSweep` from disk, kept in memory (keyed by path and mtime)."""
    from .sweep import AlphaSweep

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
    from .inference import Prediction

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
    from ..types import FeatureGrid
    from .sweep import AlphaSweep

    alpha = float(alpha)
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
    from .inference import get_predictor

    predictor = get_predictor(plan.checkpoint, device=plan.device)
    grid = FeatureGrid.load(plan.grid)
    pred = predictor.predict(grid, [alpha], heads=want, seed=plan.seed, steps=plan.steps, progress=progress,
                             temperature=sweep.temperature)  # the sweep's own sampler
    one = AlphaSweep.from_prediction(pred, grid)
    one.meta.update({"checkpoint": str(plan.checkpoint), "seconds": pred.seconds})
    one.save(path)  # atomic (core/atomic_io.py), with a unique temporary name
    return pred, "exact inference", path

