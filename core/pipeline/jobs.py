"""The model's two jobs: Predict (the α sweep) and Refine (the exact prediction at one α).

Each runs in a worker thread (:func:`unipixie.core.jobs.worker_job`) as a job generator of
``(fraction, status)`` that returns its result; closing the generator (Esc) cancels it.  May use
:mod:`.settings`, :mod:`.checkpoint`, the model's plan (:mod:`unipixie.core.model.plan`; the model itself is
imported when run) and the cache.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator

from ..model.plan import ModelPlan, exact_prediction, load_sweep, sweep_heads
from ..types import check_alpha
from .checkpoint import resolve_checkpoint
from .settings import PipelineSettings


def _background(work: Callable, description: str) -> Iterator[tuple[float, str]]:
    """Run ``work(progress)`` in a worker thread, yielding ``(fraction, status)``; closing cancels it."""
    from ..jobs import worker_job

    return (yield from worker_job(work, description=description))


def predict_job(grid_path, settings: PipelineSettings) -> Iterator[tuple[float, str]]:
    """Predict the α sweep for a feature grid (:func:`unipixie.core.model.predict_sweep`, cached on disk).

    A job generator; returns ``(AlphaSweep, sweep_path, inputs)`` where ``inputs`` is what the record
    keeps to tell when the sweep becomes stale.  The model is loaded (once per process) and run in a
    worker thread; closing the generator cancels it.
    """
    from ..types import FeatureGrid

    grid_path = Path(grid_path)
    inputs = settings.predict_inputs(grid_path)           # a missing checkpoint fails here, before any work
    ckpt = resolve_checkpoint(settings.checkpoint)
    alphas = settings.resolved_alphas()
    yield 0.0, "loading the model"

    def work(progress):
        from ..model.inference import get_predictor
        from ..model.sweep import predict_sweep, sweep_cache_key
        from ..paths import cache_dir, content_key

        predictor = get_predictor(ckpt, device=settings.device)
        grid = FeatureGrid.load(grid_path)
        key = sweep_cache_key(predictor, grid, alphas, settings.seed, settings.resolved_steps(), settings.heads)
        path = cache_dir("alpha_sweeps") / f"{key}.npz"
        cached = bool(predictor.key) and path.is_file()
        progress.set_status(f"predicting {len(alphas)} α value(s)")
        sweep = predict_sweep(predictor, grid, alphas=alphas, seed=settings.seed, heads=settings.heads,
                              steps=settings.resolved_steps(), progress=progress)
        if not path.is_file():       # a predictor without a content key: keep the sweep under ours
            path = cache_dir("alpha_sweeps") / f"pipeline-{content_key('sweep', inputs, list(settings.heads))}.npz"
            sweep.save(path)  # atomic (core/atomic_io.py), with a unique temporary name
        return sweep, path, cached

    sweep, path, cached = yield from _background(work, "predict")
    what = (f"α sweep of {len(sweep.alphas)} values" if settings.alphas is None
            else f"α {', '.join(f'{a:g}' for a in sweep.alphas)}")
    yield 1.0, f"{what} ({', '.join(sweep_heads(sweep))})" + (" from the cache" if cached else "")
    return sweep, path, inputs


def refine_job(plan: ModelPlan, alpha: float, heads=()) -> Iterator[tuple[float, str]]:
    """The panel's "Refine at this α": exact inference at ``alpha`` with the sweep's heads (plus ``heads``),
    cached, as a job generator run in a worker thread; returns ``(Prediction, how, path)``.  ``alpha`` is checked
    here (:func:`~unipixie.core.types.check_alpha`): the Refine's entry point."""
    alpha = check_alpha(alpha)
    yield 0.0, "loading the model"
    heads = tuple(set(heads) | set(sweep_heads(load_sweep(plan.sweep))))
    result = yield from _background(lambda progress: exact_prediction(plan, alpha, heads, progress, from_sweep=False),
                                    "refine")
    return result
