"""Checkpoints: safetensors + JSON, loaded without executing pickles.

A checkpoint is a directory::

    config.json                  {"format": "unipixie.model_config/1", "config": ModelConfig}
    model.safetensors            the model's weights (metadata: format, config JSON, free-form info)
    training_state.safetensors   optimiser tensors (training checkpoints only)
    training_state.json          step, optimiser hyper-parameters, training settings, data fingerprint

Every file is written to a temporary name and moved into place, the JSON
last, so an interrupted save leaves the previous checkpoint readable.
Loading builds the model from ``config.json`` and checks that every weight
exists with the right shape; any difference is a :class:`UserError` naming
the weight (a checkpoint of another architecture) — nothing is loaded
partially.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Optional

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from ..errors import UserError, read_json
from .config import ModelConfig
from .network import UniPixieModel

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
RECIPE_FILE = "feature_recipe.json"
"""Optional: how the training objects' views were rendered (engine, view count, resolution, samples) —
the pipeline renders new objects the same way so the model sees features from its training distribution."""
RECIPE_KEYS = ("engine", "view_count", "resolution", "samples")
RECIPE_OPTIONAL_KEYS = ("extractor",)
"""``extractor``: the feature model the training features came from (e.g. ``"ViT-B-16"``); when absent, the
model config's ``feature_model`` (the two must agree)."""
TRAINING_TENSORS = "training_state.safetensors"
TRAINING_JSON = "training_state.json"
WEIGHTS_FORMAT = "unipixie.model_weights/1"
TRAINING_FORMAT = "unipixie.training_state/1"


def _write_json(path: Path, doc: dict) -> None:
    from ..atomic_io import write_json

    write_json(path, doc, default=str)


def is_checkpoint(directory) -> bool:
    d = Path(directory)
    return (d / CONFIG_FILE).is_file() and (d / MODEL_FILE).is_file()


def save_model(model: UniPixieModel, directory, dtype: Optional[torch.dtype] = None, info: Optional[dict] = None) -> Path:
    """Write ``config.json`` and ``model.safetensors`` into ``directory`` (created).

    dtype: store the weights in this dtype (e.g. ``torch.bfloat16`` halves a shipped model); default as is.
    info: free-form JSON-able facts stored in the weights' metadata (training steps, data fingerprint, ...).
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    tensors = {}
    for k, v in model.state_dict().items():
        v = v.detach()
        if dtype is not None and v.is_floating_point():
            v = v.to(dtype)
        tensors[k] = v.contiguous().cpu()
    meta = {"format": WEIGHTS_FORMAT, "config": json.dumps(model.cfg.to_dict()), "info": json.dumps(info or {}, default=str)}
    from ..atomic_io import atomic_path

    with atomic_path(d / MODEL_FILE) as tmp:
        save_file(tensors, str(tmp), metadata=meta)
    model.cfg.save(d / CONFIG_FILE)
    return d


def write_feature_recipe(directory, recipe: dict) -> Path:
    """Write ``feature_recipe.json`` (keys :data:`RECIPE_KEYS`) into a checkpoint or data directory."""
    missing = [k for k in RECIPE_KEYS if k not in recipe]
    if missing:
        raise ValueError(f"feature recipe lacks {missing}")
    path = Path(directory) / RECIPE_FILE
    _write_json(path, {k: recipe[k] for k in RECIPE_KEYS + RECIPE_OPTIONAL_KEYS if k in recipe})
    return path


def read_feature_recipe(directory) -> Optional[dict]:
    """The checkpoint's feature recipe, or None when it has none (then the pipeline's own defaults apply)."""
    path = Path(directory) / RECIPE_FILE
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
        recipe = {"engine": str(doc["engine"]).lower(), "view_count": int(doc["view_count"]),
                  "resolution": int(doc["resolution"]), "samples": int(doc["samples"])}
        if doc.get("extractor"):
            recipe["extractor"] = str(doc["extractor"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{path}: not a readable feature recipe ({exc})") from None
    if recipe["engine"] not in ("cycles", "workbench") or min(recipe["view_count"], recipe["resolution"],
                                                               recipe["samples"]) < 1:
        raise UserError(f"{path}: engine must be cycles or workbench and the counts positive, got {recipe}")
    return recipe


def read_config(directory) -> ModelConfig:
    d = Path(directory)
    if not d.is_dir():
        raise UserError(f"checkpoint {d}: directory not found")
    return ModelConfig.load(d / CONFIG_FILE)


def _read_tensors(path: Path) -> tuple[dict, dict]:
    if not path.is_file():
        raise UserError(f"{path}: file not found (is this a UniPixie checkpoint directory?)")
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # truncated / not a safetensors file
        raise UserError(f"{path}: not a readable safetensors file ({exc})") from None
    return tensors, meta


def load_model(directory, device="cpu", expect: Optional[ModelConfig] = None) -> tuple[UniPixieModel, dict]:
    """Load a checkpoint directory -> (model in eval mode on ``device``, info dict from its metadata).

    expect: if given, the checkpoint's config must equal it (a resumed run); differences are listed.
    """
    d = Path(directory)
    cfg = read_config(d)
    if expect is not None:
        diff = cfg.differences(expect)
        if diff:
            raise UserError(f"checkpoint {d} was made with another model config: " + "; ".join(diff)
                            + " (use the same settings, or train into a new --out directory)")
    tensors, meta = _read_tensors(d / MODEL_FILE)
    if meta.get("format") != WEIGHTS_FORMAT:
        raise UserError(f"{d / MODEL_FILE}: metadata 'format' is {meta.get('format')!r}, expected {WEIGHTS_FORMAT!r}")
    if "config" in meta:
        try:
            embedded = ModelConfig.from_dict(json.loads(meta["config"]), where=str(d / MODEL_FILE))
        except UserError:
            raise
        diff = embedded.differences(cfg)
        if diff:
            raise UserError(f"checkpoint {d}: config.json does not describe model.safetensors ("
                            + "; ".join(diff[:5]) + "); the two files come from different models")
    model = UniPixieModel(cfg)
    own = model.state_dict()
    missing = sorted(set(own) - set(tensors))
    unexpected = sorted(set(tensors) - set(own))
    wrong = [f"{k}: {tuple(tensors[k].shape)} in the file, {tuple(own[k].shape)} in the model"
             for k in own if k in tensors and tuple(tensors[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or wrong:
        parts = []
        if missing:
            parts.append(f"missing weights {missing[:3]}{' ...' if len(missing) > 3 else ''}")
        if unexpected:
            parts.append(f"unexpected weights {unexpected[:3]}{' ...' if len(unexpected) > 3 else ''}")
        if wrong:
            parts.append("shape mismatch " + "; ".join(wrong[:3]))
        raise UserError(f"checkpoint {d}: weights do not match its config ({', '.join(parts)})")
    model.load_state_dict({k: v.to(own[k].dtype) for k, v in tensors.items()})
    model.to(device).eval()
    try:
        info = json.loads(meta.get("info", "{}"))
    except json.JSONDecodeError:
        info = {}
    return model, info


def checkpoint_key(directory) -> str:
    """A content hash of the checkpoint's weights and config (keys cached predictions)."""
    d = Path(directory)
    h = hashlib.sha256()
    h.update((d / CONFIG_FILE).read_bytes())
    with open(d / MODEL_FILE, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()[:32]


# ---------------------------------------------------------------------------- training state
def save_training_state(directory, optimizer: torch.optim.Optimizer, step: int, settings: dict,
                        data_fingerprint: str, extra: Optional[dict] = None) -> None:
    """Optimiser tensors as safetensors, everything else as JSON (written last)."""
    d = Path(directory)
    sd = optimizer.state_dict()
    tensors, scalars = {}, {}
    for idx, st in sd["state"].items():
        for name, val in st.items():
            if isinstance(val, torch.Tensor):
                tensors[f"state.{idx}.{name}"] = val.detach().contiguous().cpu()
            else:
                scalars[f"{idx}.{name}"] = val
    from ..atomic_io import atomic_path

    with atomic_path(d / TRAINING_TENSORS) as tmp:
        save_file(tensors, str(tmp), metadata={"format": TRAINING_FORMAT})
    groups = [{k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()} for g in sd["param_groups"]]
    _write_json(d / TRAINING_JSON, {"format": TRAINING_FORMAT, "step": int(step), "settings": settings,
                                    "data_fingerprint": data_fingerprint, "param_groups": groups,
                                    "scalar_state": scalars, "extra": extra or {}})


def load_training_state(directory, optimizer: torch.optim.Optimizer) -> dict:
    """Restore the optimiser from a checkpoint; returns the JSON document (step, settings, fingerprint)."""
    d = Path(directory)
    p = d / TRAINING_JSON
    if not p.is_file():
        raise UserError(f"{d}: no {TRAINING_JSON}; this checkpoint cannot be resumed (it holds only a model)")
    doc = read_json(p)
    if doc.get("format") != TRAINING_FORMAT:
        raise UserError(f"{p}: 'format' is {doc.get('format')!r}, expected {TRAINING_FORMAT!r}")
    tensors, _ = _read_tensors(d / TRAINING_TENSORS)
    state: dict = {}
    for key, val in tensors.items():
        _, idx, name = key.split(".", 2)
        state.setdefault(int(idx), {})[name] = val
    for key, val in doc.get("scalar_state", {}).items():
        idx, name = key.split(".", 1)
        state.setdefault(int(idx), {})[name] = val
    groups = []
    for g in doc["param_groups"]:
        g = dict(g)
        if "betas" in g:
            g["betas"] = tuple(g["betas"])
        groups.append(g)
    try:
        optimizer.load_state_dict({"state": state, "param_groups": groups})
    except (ValueError, KeyError) as exc:
        raise UserError(f"{d}: optimiser state does not fit this model ({exc})") from None
    return doc
