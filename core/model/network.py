"""The full UniPixie model: grid encoder + MPM, LBS and spring-mass decoders.

Shapes (B objects, N occupied voxels in all, T patch tokens per object, S = P³ slots per token):

* ``encode(batch)`` -> :class:`Encoded`: z (B, L, C), local voxel features (N, c), the patch layout.
* ``mpm``: :class:`~.fmt.GridFMT`, 3 flow channels (log10 E, log10 ρ, ν normalised) + class logits
  (``cfg.num_classes``, the registry's classes) per voxel.
* ``lbs_material``: GridFMT, 2 flow channels (log10 E, ν normalised) per voxel.
* ``hypernet``: mean(z) -> the 650 skinning parameters (normalised).
* ``spring``: :class:`~.fmt.VectorFMT` over N_a log10 stiffnesses + 1 softness (normalised).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import nn

from .config import ModelConfig
from .encoder import GridEncoder
from .fmt import GridFMT, HyperNetwork, VectorFMT
from .layout import PatchLayout, VoxelBatch
from .normalization import LBS_CHANNELS, MPM_CHANNELS


@dataclass
class Encoded:
    """An encoded batch: latents z (B, L, C), per-voxel local features (N, c) (c = cfg.local_channels: the
    projected features, then the local context if any), patch layout and the per-token local features
    (B, T, S·c) (None without ``local_features``)."""

    z: torch.Tensor
    projected: torch.Tensor
    layout: PatchLayout
    local_tokens: Optional[torch.Tensor]


class UniPixieModel(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = GridEncoder(cfg)
        self.mpm = GridFMT(cfg, len(MPM_CHANNELS), cfg.mpm_blocks, extra_outputs=cfg.num_classes)
        self.lbs_material = GridFMT(cfg, len(LBS_CHANNELS), cfg.lbs_blocks)
        self.hypernet = HyperNetwork(cfg)
        self.spring = VectorFMT(cfg, cfg.spring_dim, cfg.spring_chunk, cfg.spring_blocks)

    def layout(self, batch: VoxelBatch) -> PatchLayout:
        return PatchLayout(batch.voxels, batch.batch_size, batch.resolution, self.cfg.patch_size)

    def finish_encoding(self, z, projected, batch: VoxelBatch) -> Encoded:
        layout = self.layout(batch)
        local = None
        if self.cfg.local_features:
            local = layout.to_tokens(projected.to(z.dtype)).flatten(2)
        return Encoded(z, projected, layout, local)

    def encode(self, batch: VoxelBatch) -> Encoded:
        z, projected = self.encoder(batch)
        return self.finish_encoding(z, projected, batch)

    def grid_context(self, head: GridFMT, enc: Encoded):
        return head.context(enc.z, enc.layout.centres.to(enc.z.dtype), enc.layout.slot_mask, enc.local_tokens)

    def parameter_count(self) -> dict:
        parts = {name: sum(p.numel() for p in mod.parameters())
                 for name, mod in (("encoder", self.encoder), ("mpm", self.mpm), ("lbs_material", self.lbs_material),
                                   ("hypernet", self.hypernet), ("spring", self.spring))}
        parts["total"] = sum(parts.values())
        return parts
