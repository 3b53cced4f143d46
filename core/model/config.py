"""The model's configuration: every size and constant a checkpoint depends on.

A :class:`ModelConfig` is saved as ``config.json`` beside every checkpoint's
weights.  Loading compares it with what the caller has (the feature grid's
extractor and feature width, a resumed run's requested sizes) and raises a
:class:`~unipixie.core.errors.UserError` naming each mismatching field.

The defaults are the paper's sizes (appendix "Model Architecture and
Training Details"); :data:`PRESETS` holds smaller ones (``small`` for a model
shipped with the add-on, ``tiny`` for tests).  Shared contracts are imported,
never copied: the material classes from :mod:`unipixie.solvers.materials`, the
650 LBS parameters from :mod:`unipixie.solvers.skinning`, the number of
spring-mass anchors from :mod:`unipixie.solvers.spring_mass_settings` when importable.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

from ...solvers import materials
from ...solvers.registry import SOLVER_NAMES
from ...solvers.skinning import LBS_PARAM_COUNT
from ..errors import UserError, read_json
from .normalization import DEFAULT_NORMALISATION, normalisation_from_dict, normalisation_to_dict

CONFIG_FORMAT = "unipixie.model_config/1"

FALLBACK_SPRING_ANCHORS = 2048
"""N_a when :mod:`unipixie.solvers.spring_mass` cannot be imported (the paper's value)."""


def default_spring_anchors() -> int:
    """The spring-mass solver's default anchor count (``DEFAULT_ANCHORS``), or the paper's 2048."""
    try:
        from ...solvers.spring_mass_settings import DEFAULT_ANCHORS  # noqa: PLC0415
    except ImportError:
        return FALLBACK_SPRING_ANCHORS
    return int(DEFAULT_ANCHORS)


HEADS = SOLVER_NAMES
"""The decoder heads, in the order the model runs them: one per solver (:data:`unipixie.solvers.registry.SOLVERS`)."""


@dataclass
class ModelConfig:
    """Sizes of the grid encoder and the three decoder heads.

    feature_model / feature_dim: the feature extractor the model was trained on and its width D.
    grid_resolution: R, voxels per side of the input grid (64; multiple of 4 and of ``patch_size``).
    width / attention_heads / mlp_ratio: C, attention heads and the MLP expansion of all transformers.
    voxel_channels: per-voxel linear D -> this many channels before the dense conv stem (the only dense
        tensor is (B, voxel_channels + 1, R, R, R); see docs/model.md).
    stem_channels: channels after the first of the two stride-2 Conv3d 4x4x4 (the second outputs C).
    fourier_frequencies: frequencies of the 3D Fourier positional encoding.
    latent_tokens / encoder_blocks / encoder_self_layers: L latents; blocks of cross-attention to the
        (R/4)³ grid tokens, each followed by this many self-attention layers.
    patch_size: P, decoder tokens are occupied P³ patches of the grid (1 = one token per voxel).
    local_features: decoder tokens also see their voxels' projected input features (a skip from the
        encoder's per-voxel projection; not in the paper, see docs/model.md).
    local_context_layers / local_context_channels: with ``local_features``, a stack of this many
        residual 3x3x3 Conv3d layers at full resolution R³ (dilations 1, 2, 4, ...; receptive field
        1 + 2·(2^layers − 1) voxels) over the dense stem input adds ``local_context_channels`` per voxel
        to the decoders' local features: where inside the object a voxel lies and what surrounds it
        (0 layers = off, the behaviour of checkpoints made before it; not in the paper, see docs/model.md).
    time_frequencies / alpha_embedding_dim: Fourier features of t, sinusoidal embedding width of α.
    mpm_blocks / lbs_blocks / spring_blocks: FMT blocks per head.
    hypernet_layers / hypernet_width: the LBS HyperNetwork MLP.
    lbs_param_count: skinning parameters (650, from the LBS solver's contract).
    spring_anchors / spring_chunk: N_a stiffnesses (+1 softness) and values per vector token.
    class_names: material classes of the class logits, in id order (from the registry).
    normalisation: quantity -> :class:`~.normalization.ChannelNorm` as dicts.
    """

    feature_model: str = "ViT-B-16"
    feature_dim: int = 768
    grid_resolution: int = 64
    width: int = 512
    attention_heads: int = 8
    mlp_ratio: float = 4.0
    voxel_channels: int = 32
    stem_channels: int = 256
    fourier_frequencies: int = 16
    latent_tokens: int = 64
    encoder_blocks: int = 6
    encoder_self_layers: int = 2
    patch_size: int = 4
    local_features: bool = True
    local_context_layers: int = 0
    local_context_channels: int = 16
    time_frequencies: int = 6
    alpha_embedding_dim: int = 64
    mpm_blocks: int = 6
    lbs_blocks: int = 6
    spring_blocks: int = 4
    hypernet_layers: int = 4
    hypernet_width: int = 512
    lbs_param_count: int = LBS_PARAM_COUNT
    spring_anchors: int = field(default_factory=default_spring_anchors)
    spring_chunk: int = 64
    prediction: str = "data"
    min_remaining_time: float = 0.05
    class_names: tuple = field(default_factory=lambda: tuple(materials.names()))
    normalisation: dict = field(default_factory=lambda: normalisation_to_dict(DEFAULT_NORMALISATION))

    def __post_init__(self):
        self.class_names = tuple(self.class_names)
        self.validate()

    # ------------------------------------------------------------------ derived sizes
    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    @property
    def spring_dim(self) -> int:
        """Length of the spring-mass vector: N_a stiffnesses + 1 softness (2049 by default)."""
        return self.spring_anchors + 1

    @property
    def coarse_resolution(self) -> int:
        """Side of the conv stem's output grid (R / 4)."""
        return self.grid_resolution // 4

    @property
    def local_channels(self) -> int:
        """Per-voxel channels of the decoders' local features: c0 (+ the local context's channels)."""
        return self.voxel_channels + (self.local_context_channels if self.local_context_layers else 0)

    @property
    def patch_voxels(self) -> int:
        return self.patch_size ** 3

    def norms(self):
        """quantity -> ChannelNorm."""
        return normalisation_from_dict(self.normalisation)

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        def need(cond, msg):
            if not cond:
                raise UserError(f"model config: {msg}")

        for name in ("feature_dim", "grid_resolution", "width", "attention_heads", "voxel_channels", "stem_channels",
                     "fourier_frequencies", "latent_tokens", "encoder_blocks", "patch_size", "time_frequencies",
                     "alpha_embedding_dim", "mpm_blocks", "lbs_blocks", "spring_blocks", "hypernet_layers",
                     "hypernet_width", "lbs_param_count", "spring_anchors", "spring_chunk"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v > 0, f"{name} must be a positive integer, got {v!r}")
        need(self.encoder_self_layers >= 0, "encoder_self_layers must be >= 0")
        for name in ("local_context_layers", "local_context_channels"):
            v = getattr(self, name)
            need(isinstance(v, int) and not isinstance(v, bool) and v >= 0, f"{name} must be an integer >= 0, got {v!r}")
        need(self.local_context_layers == 0 or (self.local_features and self.local_context_channels > 0),
             "local_context_layers needs local_features = True and local_context_channels > 0")
        need(2 ** max(self.local_context_layers - 1, 0) < self.grid_resolution,
             f"local_context_layers {self.local_context_layers}: the largest dilation would exceed the grid")
        need(self.grid_resolution % 4 == 0, f"grid_resolution must be a multiple of 4 (two stride-2 convs), got {self.grid_resolution}")
        need(self.grid_resolution % self.patch_size == 0,
             f"grid_resolution {self.grid_resolution} must be a multiple of patch_size {self.patch_size}")
        need(self.width % self.attention_heads == 0, f"width {self.width} must be divisible by attention_heads {self.attention_heads}")
        need((self.width // self.attention_heads) % 2 == 0, "width / attention_heads must be even")
        need(self.alpha_embedding_dim % 2 == 0, "alpha_embedding_dim must be even")
        need(self.mlp_ratio > 0, "mlp_ratio must be positive")
        need(self.hypernet_layers >= 2, "hypernet_layers must be >= 2")
        need(len(self.class_names) >= 1, "class_names must not be empty")
        need(isinstance(self.feature_model, str), "feature_model must be a string")
        need(self.prediction in ("velocity", "data"), f"prediction must be 'velocity' or 'data', got {self.prediction!r}")
        need(0.0 < self.min_remaining_time < 1.0, "min_remaining_time must lie in (0, 1)")

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["class_names"] = list(self.class_names)
        return d

    @classmethod
    def from_dict(cls, d: dict, where: str = "model config") -> "ModelConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise UserError(f"{where}: unknown field(s) {', '.join(unknown)} (written by a newer UniPixie?)")
        return cls(**d)

    def replace(self, **changes) -> "ModelConfig":
        d = self.to_dict()
        known = {f.name for f in dataclasses.fields(self)}
        bad = sorted(set(changes) - known)
        if bad:
            raise UserError(f"unknown model config field(s): {', '.join(bad)}; known: {', '.join(sorted(known))}")
        d.update(changes)
        return ModelConfig(**d)

    def save(self, path) -> Path:
        from ..atomic_io import write_json

        path = Path(path)
        write_json(path, {"format": CONFIG_FORMAT, "config": self.to_dict()})
        return path

    @classmethod
    def load(cls, path) -> "ModelConfig":
        path = Path(path)
        if not path.is_file():
            raise UserError(f"{path}: model config not found (a checkpoint directory holds config.json and model.safetensors)")
        doc = read_json(path)
        if not isinstance(doc, dict) or doc.get("format") != CONFIG_FORMAT:
            raise UserError(f"{path}: 'format' is {doc.get('format') if isinstance(doc, dict) else None!r}, expected {CONFIG_FORMAT!r}")
        return cls.from_dict(doc.get("config", {}), where=str(path))

    def differences(self, other: "ModelConfig", ignore=()) -> list[str]:
        """Human-readable ``field: mine != other`` lines for every differing field (except ``ignore``)."""
        a, b = self.to_dict(), other.to_dict()
        return [f"{k}: {a[k]!r} != {b.get(k)!r}" for k in a if k not in ignore and a[k] != b.get(k)]


PRESETS: dict[str, dict] = {
    "paper": {},
    "small": dict(width=256, attention_heads=8, stem_channels=128, voxel_channels=16, latent_tokens=32,
                  encoder_blocks=3, encoder_self_layers=1, mpm_blocks=4, lbs_blocks=3, spring_blocks=2,
                  hypernet_width=256, mlp_ratio=3.0, spring_chunk=128, local_context_layers=5,
                  local_context_channels=24),
    "tiny": dict(width=64, attention_heads=4, stem_channels=32, voxel_channels=8, latent_tokens=8,
                 encoder_blocks=1, encoder_self_layers=1, mpm_blocks=2, lbs_blocks=2, spring_blocks=2,
                 hypernet_width=64, fourier_frequencies=4, time_frequencies=6, alpha_embedding_dim=16,
                 mlp_ratio=2.0, spring_chunk=8, patch_size=1),
}
"""Named size presets: ``paper`` (the defaults), ``small`` (ships with the add-on), ``tiny`` (tests)."""


def preset(name: str, **overrides) -> ModelConfig:
    """A config from a named preset plus field overrides (feature_model, feature_dim, grid_resolution, ...)."""
    if name not in PRESETS:
        raise UserError(f"unknown model preset {name!r}; choose one of: {', '.join(PRESETS)}")
    d = dict(PRESETS[name])
    d.update(overrides)
    return ModelConfig(**d)
