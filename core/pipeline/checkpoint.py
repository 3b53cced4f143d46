"""Which model the pipeline uses: the checkpoint directory, the feature model it was trained on, its content key.

:func:`resolve_checkpoint` turns an empty choice into the shipped default model and a missing or foreign one into
one clear message; :func:`model_feature_model` and :func:`checkpoint_identity` read a checkpoint's files (memoised
on their size and mtimes).  May use :mod:`unipixie.core.model.checkpoint` (imported when called) and
:mod:`unipixie.core.clip_features`.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

from ..errors import UserError

_CKPT_KEYS: dict = {}
_CKPT_LOCK = threading.Lock()


def default_checkpoint() -> Path:
    """Where the shipped model lives (``models/default/`` of the package)."""
    from ..model.inference import DEFAULT_CHECKPOINT

    return Path(DEFAULT_CHECKPOINT)


def resolve_checkpoint(checkpoint=None) -> Path:
    """The checkpoint directory to use: ``checkpoint`` (a directory, or its ``model.safetensors`` /
    ``config.json``) or, when empty, the shipped default model.  Raises :class:`UserError` saying what
    is missing and what to do."""
    from ..model.checkpoint import CONFIG_FILE, MODEL_FILE, is_checkpoint

    if not checkpoint:
        d = default_checkpoint()
        if not is_checkpoint(d):
            raise UserError(f"the default model is not installed: {d} has no {MODEL_FILE} + {CONFIG_FILE}. "
                            "Put the shipped model there, or choose a checkpoint directory made by 'unipixie train' "
                            "(add-on preferences > Model checkpoint, or --checkpoint DIR)")
        return d
    p = Path(str(checkpoint)).expanduser()
    if p.is_file() and p.name in (MODEL_FILE, CONFIG_FILE):
        p = p.parent
    if not p.exists():
        raise UserError(f"model checkpoint {p} does not exist; choose a checkpoint directory made by 'unipixie train'")
    if not is_checkpoint(p):
        raise UserError(f"{p} is not a UniPixie checkpoint (it needs {CONFIG_FILE} and {MODEL_FILE}); choose the "
                        "directory 'unipixie train --out DIR' wrote")
    return p


def checkpoint_feature_model(checkpoint_dir: Path) -> tuple[str, int]:
    """(feature model name, feature width D) a checkpoint was trained on, read from its config.json."""
    from ..model.checkpoint import CONFIG_FILE

    path = Path(checkpoint_dir) / CONFIG_FILE
    try:
        doc = json.loads(path.read_text())
        cfg = doc.get("config", doc)
        return str(cfg["feature_model"]), int(cfg["feature_dim"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{path}: not a readable model config ({exc})") from None


_FEATURE_MODELS: dict = {}


def model_feature_model(checkpoint_dir) -> str:
    """The feature model (extractor) a checkpoint expects: its ``feature_recipe.json``'s ``extractor`` when the
    recipe names one, else its config's ``feature_model`` (they must agree).  Memoised on the files' mtimes."""
    from ..model.checkpoint import CONFIG_FILE, RECIPE_FILE, read_feature_recipe

    d = Path(checkpoint_dir).resolve()
    stamp = tuple(f.stat().st_mtime_ns if f.is_file() else 0 for f in (d / CONFIG_FILE, d / RECIPE_FILE))
    with _CKPT_LOCK:
        hit = _FEATURE_MODELS.get(str(d))
        if hit is not None and hit[0] == stamp:
            return hit[1]
    trained_on, _ = checkpoint_feature_model(d)
    recipe = read_feature_recipe(d) or {}
    named = recipe.get("extractor")
    if named and named != trained_on:
        raise UserError(f"{d / RECIPE_FILE} names the extractor {named!r} but {d / CONFIG_FILE} says the model was "
                        f"trained on {trained_on!r} features; the checkpoint is inconsistent (retrain or fix the recipe)")
    name = named or trained_on
    with _CKPT_LOCK:
        _FEATURE_MODELS[str(d)] = (stamp, name)
    return name


def feature_model_name(clip_weights: str = "") -> str:
    """The feature model the pipeline extracts with: CLIP ViT-B-16 when CLIP weights are set, else the
    offline extractor (``offline-random-vit-w32``, an untrained ViT: not CLIP)."""
    from .. import clip_features as cf

    return cf.CLIP_MODEL if clip_weights else cf.OFFLINE_FEATURE_MODEL


def checkpoint_identity(checkpoint_dir: Path) -> str:
    """The content key of a checkpoint (hash of its weights and config), memoised on size and mtime."""
    from ..model.checkpoint import CONFIG_FILE, MODEL_FILE, checkpoint_key

    d = Path(checkpoint_dir).resolve()
    stamp = tuple((f.stat().st_size, f.stat().st_mtime_ns) for f in (d / MODEL_FILE, d / CONFIG_FILE))
    with _CKPT_LOCK:
        hit = _CKPT_KEYS.get(str(d))
        if hit is not None and hit[0] == stamp:
            return hit[1]
    key = checkpoint_key(d)
    with _CKPT_LOCK:
        _CKPT_KEYS[str(d)] = (stamp, key)
    return key
