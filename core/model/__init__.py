"""The UniPixie model (grid encoder, flow-matching decoders) and its inference path.

Public API (imported lazily, so ``import unipixie.core.model`` does not import torch)::

    from unipixie.core.model import predict, Predictor, predict_sweep, AlphaSweep, ModelConfig

* :func:`predict` / :class:`Predictor` — materials for a FeatureGrid at several α in one pass
  (:mod:`.inference`);
* :func:`predict_sweep` / :class:`AlphaSweep` — the cached α slider (:mod:`.sweep`);
* :class:`ModelConfig`, :func:`preset` — sizes (:mod:`.config`);
* :func:`load_model`, :func:`save_model` — checkpoints (:mod:`.checkpoint`);
* :class:`UniPixieModel` — the network (:mod:`.network`).

See docs/model.md.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "ModelConfig": "config", "preset": "config", "PRESETS": "config", "HEADS": "config",
    "UniPixieModel": "network",
    "Predictor": "inference", "predict": "inference", "Prediction": "inference", "LBSPrediction": "inference",
    "SpringPrediction": "inference", "get_predictor": "inference", "DEFAULT_CHECKPOINT": "inference",
    "AlphaSweep": "sweep", "predict_sweep": "sweep",
    "load_model": "checkpoint", "save_model": "checkpoint", "is_checkpoint": "checkpoint",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    mod = _EXPORTS.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{mod}"), name)
