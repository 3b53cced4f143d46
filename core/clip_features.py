"""Dense image features from an OpenCLIP vision transformer (patch tokens).

Two extractors share one code path (``open_clip.create_model`` → ``model.visual``
with ``output_tokens = True``):

* **CLIP** — a pretrained OpenCLIP ViT (default ``ViT-B-16``, D = 768) whose
  weights come from a local file or directory: ``--clip-weights`` /
  the add-on preference / ``$UNIPIXIE_CLIP_WEIGHTS`` / ``<cache>/clip/ViT-B-16/``.
  Extraction downloads nothing; ``unipixie weights fetch`` (and the add-on's
  *Fetch CLIP weights*) put the weights :data:`OPENCLIP_PRETRAINED` names into
  that default folder (:mod:`unipixie.core.weights`).
* **offline** — a *seeded, untrained* small ViT (:data:`OFFLINE_VISION_CFG`,
  width 32 → D = 32) built through the same OpenCLIP factory.  Its name,
  :data:`OFFLINE_FEATURE_MODEL` (``"offline-random-vit-w32"``), says what it is
  and is recorded in every feature grid it makes; it is **not** CLIP.  It is
  deterministic given the seed, needs no download, and the shipped demo model
  is trained on its features.

Features are the transformer's patch tokens after the final LayerNorm (before
the image projection): for a 224² input and patch 16, a 14 × 14 grid of
D-vectors per image, where token (a, b) covers pixels ``[16a, 16a+16) ×
[16b, 16b+16)`` (rows, columns) of the resized image.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from .errors import UserError

CLIP_MODEL = "ViT-B-16"
"""The default OpenCLIP architecture (paper: D = 768)."""

OPENCLIP_PRETRAINED = {CLIP_MODEL: "laion2b_s34b_b88k"}
"""Which OpenCLIP pretrained weights (open_clip's tag) a CLIP feature model means: the architecture name is the
feature-model name recorded in feature grids and checkpoints; the tag picks the weights ``unipixie weights fetch``
downloads (ViT-B-16 trained on LAION-2B, the weights the paper's feature extractor uses)."""

CLIP_WEIGHTS_ENV = "UNIPIXIE_CLIP_WEIGHTS"
"""Environment variable naming the local CLIP weights (file or directory)."""

OFFLINE_SEED = 0
OFFLINE_VISION_CFG = {"image_size": 224, "patch_size": 16, "width": 32, "layers": 4, "head_width": 8, "mlp_ratio": 4.0}
"""The untrained offline ViT: patch 16 at 224² (14 × 14 tokens), width 32 (D = 32), 4 layers of 4 heads."""
_OFFLINE_TEXT_CFG = {"context_length": 8, "vocab_size": 64, "width": 8, "heads": 1, "layers": 1}
"""A minimal text tower (OpenCLIP's CLIP class needs one; it is never used)."""
OFFLINE_FEATURE_MODEL = f"offline-random-vit-w{OFFLINE_VISION_CFG['width']}"
"""Name of the offline extractor everywhere it is used (never presented as CLIP)."""

_CHECKPOINT_NAMES = ("open_clip_model.safetensors", "open_clip_pytorch_model.safetensors", "open_clip_pytorch_model.bin",
                     "open_clip_pytorch_model.pth", "model.safetensors", "pytorch_model.bin", "model.pth")
_CHECKPOINT_SUFFIXES = (".safetensors", ".bin", ".pt", ".pth")


def default_weights_dir(model: str = CLIP_MODEL) -> Path:
    """Where UniPixie looks for CLIP weights last: ``<cache root>/clip/<model>/`` (not created)."""
    from .paths import cache_root

    return cache_root() / "clip" / model


def _missing_weights_message(model: str, where: str) -> str:
    tag = OPENCLIP_PRETRAINED.get(model, "")
    put = (f"an OpenCLIP {model} checkpoint (for example 'open_clip_pytorch_model.bin' of {model} {tag}, or an "
           f"open_clip 'local-dir' folder with open_clip_config.json) in {default_weights_dir(model)}")
    fetch = (f"Fetch them with 'unipixie weights fetch' (online: OpenCLIP {model} {tag} from the Hugging Face Hub), "
             f"put {put}" if tag else f"Put {put}")
    return (f"CLIP weights for {model} not found{where}. {fetch}, or pass --clip-weights PATH, set "
            f"${CLIP_WEIGHTS_ENV}, or set 'CLIP weights' in the add-on preferences; or use the offline extractor "
            f"(--offline-features: an untrained {OFFLINE_FEATURE_MODEL}, not CLIP)")


def resolve_clip_weights(explicit: Optional[str | os.PathLike] = None, model: str = CLIP_MODEL) -> Path:
    """The CLIP weights to use: ``explicit`` (argument / preference), else ``$UNIPIXIE_CLIP_WEIGHTS``, else
    :func:`default_weights_dir`.  Returns an existing file or directory; raises :class:`UserError` naming
    where to put the weights when none is found."""
    if explicit:
        p = Path(explicit).expanduser()
        if not p.exists():
            raise UserError(_missing_weights_message(model, f" at {p} (given as the CLIP weights path)"))
        return p
    env = os.environ.get(CLIP_WEIGHTS_ENV)
    if env:
        p = Path(env).expanduser()
        if not p.exists():
            raise UserError(_missing_weights_message(model, f" at {p} (from ${CLIP_WEIGHTS_ENV})"))
        return p
    d = default_weights_dir(model)
    if d.is_dir() and any(not p.name.startswith(".") for p in d.iterdir()):   # .cache/: a download's bookkeeping
        return d
    raise UserError(_missing_weights_message(model, ""))


def _checkpoint_in_dir(d: Path) -> Optional[Path]:
    for name in _CHECKPOINT_NAMES:
        if (d / name).is_file():
            return d / name
    found = sorted(p for p in d.iterdir() if p.suffix in _CHECKPOINT_SUFFIXES and p.is_file())
    return found[0] if found else None


def weights_identity(path: Path) -> dict:
    """A cheap identity of a weights file or folder for cache keys: names, sizes and modification times (hidden
    entries such as the download bookkeeping in ``.cache/`` do not count)."""
    files = [path] if path.is_file() else sorted(
        p for p in path.rglob("*") if p.is_file() and not any(part.startswith(".") for part in p.relative_to(path).parts))
    return {"path": str(path.resolve()),
            "files": [(p.name, p.stat().st_size, int(p.stat().st_mtime)) for p in files]}


@dataclass
class FeatureExtractor:
    """An OpenCLIP vision transformer that turns images into a grid of patch features.

    name: the feature-model name recorded in feature grids (``"ViT-B-16"`` or ``OFFLINE_FEATURE_MODEL``).
    visual: the ``open_clip`` vision tower (``output_tokens = True``), in eval mode on ``device``.
    image_size: side of the (square) network input in pixels; patch_size: pixels per token side.
    dim: feature dimension D (the transformer width).
    identity: what determines the features (for cache keys): model name, config, weights identity / seed.
    """

    name: str
    visual: object
    image_size: int
    patch_size: int
    dim: int
    mean: tuple
    std: tuple
    device: str = "cpu"
    identity: dict = field(default_factory=dict)

    @property
    def is_clip(self) -> bool:
        """True only for a model with pretrained CLIP weights loaded from a file (not the offline or the
        timing-only random-weight extractors)."""
        return "weights" in self.identity

    @property
    def token_grid(self) -> int:
        """Tokens per image side (14 for 224 / 16)."""
        return self.image_size // self.patch_size

    def __call__(self, images: np.ndarray, batch_size: int = 8, progress=None) -> "np.ndarray":
        """Patch features of a batch of images.

        images: (V, H, W, 3) float32 in [0, 1] (display sRGB, as rendered), any H, W; they are resized
            (bilinear, antialiased) to ``image_size``².
        Returns a torch tensor (V, g, g, D) float32 on ``self.device`` with g = ``token_grid``; row 0
        is the top of the image.
        """
        import torch
        import torch.nn.functional as F

        imgs = np.asarray(images, dtype=np.float32)
        if imgs.ndim != 4 or imgs.shape[-1] != 3:
            raise UserError(f"feature extraction needs (V, H, W, 3) images, got shape {imgs.shape}")
        mean = torch.tensor(self.mean, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(self.std, device=self.device).view(1, 3, 1, 1)
        out = []
        with torch.inference_mode():
            for start in range(0, len(imgs), batch_size):
                x = torch.from_numpy(imgs[start:start + batch_size]).to(self.device).permute(0, 3, 1, 2)
                if x.shape[-2:] != (self.image_size, self.image_size):
                    x = F.interpolate(x, size=(self.image_size, self.image_size), mode="bilinear",
                                      align_corners=False, antialias=True)
                x = (x.clamp(0, 1) - mean) / std
                _, tokens = self.visual(x)
                g = self.token_grid
                out.append(tokens.float().reshape(tokens.shape[0], g, g, tokens.shape[-1]))
                if progress is not None:
                    progress.step(len(x), f"features {min(start + batch_size, len(imgs))}/{len(imgs)}")
        return torch.cat(out, dim=0)


class _quiet_open_clip:
    """Silence open_clip's "No pretrained weights loaded ... initialized randomly" warning where random
    weights are intended (the offline and the timing-only extractors)."""

    def __enter__(self):
        import logging

        self._filter = lambda record: "initialized randomly" not in record.getMessage()
        logging.getLogger().addFilter(self._filter)
        return self

    def __exit__(self, *exc):
        import logging

        logging.getLogger().removeFilter(self._filter)
        return False


def _device(device: str) -> str:
    import torch

    d = (device or "cpu").lower()
    if d == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if d.startswith("cuda") and not torch.cuda.is_available():
        raise UserError(f"device {device!r} requested but torch sees no CUDA GPU; use --device cpu")
    return d


def _from_model(name: str, model, device: str, identity: dict) -> FeatureExtractor:
    import open_clip

    visual = model.visual
    visual.output_tokens = True
    visual.eval().to(device)
    cfg = getattr(visual, "preprocess_cfg", {}) or {}
    mean = tuple(cfg.get("mean", open_clip.OPENAI_DATASET_MEAN))
    std = tuple(cfg.get("std", open_clip.OPENAI_DATASET_STD))
    size = visual.image_size
    size = int(size[0] if isinstance(size, (tuple, list)) else size)
    patch = visual.patch_size
    patch = int(patch[0] if isinstance(patch, (tuple, list)) else patch)
    return FeatureExtractor(name=name, visual=visual, image_size=size, patch_size=patch,
                            dim=int(visual.transformer.width), mean=mean, std=std, device=device, identity=identity)


def load_clip(weights: Optional[str | os.PathLike] = None, model: str = CLIP_MODEL, device: str = "cpu") -> FeatureExtractor:
    """A pretrained OpenCLIP ViT from local weights (see :func:`resolve_clip_weights`).

    ``weights`` may be a checkpoint file (``.bin`` / ``.pt`` / ``.pth`` / ``.safetensors``, loaded into
    the built-in ``model`` architecture) or a directory (an open_clip ``local-dir`` folder with
    ``open_clip_config.json``, or one holding a checkpoint file).
    """
    import open_clip

    path = resolve_clip_weights(weights, model)
    device = _device(device)
    kwargs = {}
    if path.is_dir():
        if (path / "open_clip_config.json").is_file():
            name_arg = "local-dir:" + str(path)
        else:
            ckpt = _checkpoint_in_dir(path)
            if ckpt is None:
                raise UserError(_missing_weights_message(model, f": {path} holds no checkpoint file "
                                                                f"({', '.join(_CHECKPOINT_SUFFIXES)})"))
            name_arg, kwargs = model, {"pretrained": str(ckpt)}
    else:
        if path.suffix not in _CHECKPOINT_SUFFIXES:
            raise UserError(f"{path}: not a checkpoint file (expected {', '.join(_CHECKPOINT_SUFFIXES)}) or a folder")
        name_arg, kwargs = model, {"pretrained": str(path)}
    try:
        clip = open_clip.create_model(name_arg, device="cpu", **kwargs)
    except Exception as exc:  # wrong architecture, truncated file, not a checkpoint ...
        raise UserError(f"could not load CLIP weights from {path} into {model}: {type(exc).__name__}: "
                        f"{str(exc).splitlines()[0][:300]}") from None
    identity = {"model": model, "weights": weights_identity(path)}
    return _from_model(model, clip, device, identity)


def offline_extractor(seed: int = OFFLINE_SEED, device: str = "cpu") -> FeatureExtractor:
    """The seeded, untrained offline ViT (``OFFLINE_FEATURE_MODEL``; not CLIP), deterministic given ``seed``.

    Built with ``open_clip.create_model`` from :data:`OFFLINE_VISION_CFG` (no weights are loaded);
    the weights are initialised on the CPU under ``torch.manual_seed(seed)`` inside a forked RNG
    state, so the caller's random state is untouched.
    """
    import open_clip
    import torch

    device = _device(device)
    with torch.random.fork_rng(devices=[]), _quiet_open_clip():
        torch.manual_seed(int(seed))
        model = open_clip.create_model(CLIP_MODEL, pretrained=None, device="cpu", embed_dim=OFFLINE_VISION_CFG["width"],
                                       vision_cfg=dict(OFFLINE_VISION_CFG), text_cfg=dict(_OFFLINE_TEXT_CFG))
    identity = offline_identity(seed)
    return _from_model(identity["model"], model, device, identity)


def offline_identity(seed: int = OFFLINE_SEED) -> dict:
    """What determines the offline extractor's features (its name, architecture and seed)."""
    name = OFFLINE_FEATURE_MODEL if int(seed) == OFFLINE_SEED else f"{OFFLINE_FEATURE_MODEL}-seed{int(seed)}"
    return {"model": name, "vision_cfg": dict(OFFLINE_VISION_CFG), "seed": int(seed)}


def random_clip_architecture(model: str = CLIP_MODEL, seed: int = 0, device: str = "cpu") -> FeatureExtractor:
    """The full ``model`` architecture (ViT-B-16: D = 768) with *random* weights, for timing only.

    Named ``"<model>-random-weights"``; its features mean nothing and must never be used for prediction.
    """
    import open_clip
    import torch

    device = _device(device)
    with torch.random.fork_rng(devices=[]), _quiet_open_clip():
        torch.manual_seed(int(seed))
        clip = open_clip.create_model(model, pretrained=None, device="cpu")
    return _from_model(f"{model}-random-weights", clip, device, {"model": model, "random_seed": int(seed)})


def clip_identity(clip_weights: Optional[str | os.PathLike] = None, model: str = CLIP_MODEL) -> dict:
    """What determines CLIP ``model``'s features: its architecture and the identity of the weights that
    :func:`resolve_clip_weights` finds (for cache keys; nothing is loaded)."""
    return {"model": model, "weights": weights_identity(resolve_clip_weights(clip_weights, model))}


_LOADED: dict = {}
"""Extractors loaded in this process, by (identity, device): the add-on and repeated API calls reuse them."""


def make_extractor(offline: bool = False, clip_weights: Optional[str | os.PathLike] = None, device: str = "cpu",
                   model: str = CLIP_MODEL) -> FeatureExtractor:
    """The extractor the options ask for: the offline one when ``offline``, else CLIP from local weights.
    Loaded once per process and kept (keyed by what determines its features and by device)."""
    import json

    identity = offline_identity() if offline else clip_identity(clip_weights, model)
    key = (json.dumps(identity, sort_keys=True), _device(device))
    if key not in _LOADED:
        _LOADED.clear()                      # keep at most one model in memory
        _LOADED[key] = offline_extractor(device=device) if offline else load_clip(clip_weights, model=model, device=device)
    return _LOADED[key]
