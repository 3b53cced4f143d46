"""The grid encoder: occupied-voxel features -> L latent tokens z (B, L, C).

1. Per-voxel projection (only the K occupied voxels): LayerNorm(D) -> Linear(D, c0).  This is the
   trick that keeps training memory small: the D-wide features (D = 768 for CLIP ViT-B/16) never
   become a dense R³ tensor; only c0 + 1 channels do (the projected features and the occupancy).
2. Scatter into a dense (B, c0 + 1, R, R, R) grid, zero outside the occupancy.
3. Conv stem: Conv3d(c0 + 1 -> stem, 4x4x4, stride 2) -> GELU -> Conv3d(stem -> C, 4x4x4, stride 2):
   R³ -> (R/4)³ grid tokens (64³ -> 16³ = 4096 tokens), plus a Fourier positional encoding of the cell
   centres projected to C.
4. Latent tokenizer: L learnable queries; ``encoder_blocks`` blocks, each a cross-attention from the
   latents to the grid tokens followed by ``encoder_self_layers`` self-attention layers; final LayerNorm.

The projected per-voxel features (N, c0) are returned too: decoders with ``local_features`` use them.
With ``local_context_layers`` > 0, a :class:`LocalContext` stack (residual dilated 3x3x3 convolutions at
full resolution over the dense stem input) adds ``local_context_channels`` per occupied voxel to them,
(N, c0 + c_ctx): the decoders' tokens then know where inside the object their voxels lie (depth under
the surface, the neighbouring parts), which a P³ patch of surface-filled features cannot tell.
"""

from __future__ import annotations

import torch
from torch import nn

from .config import ModelConfig
from .layers import TransformerBlock, fourier_dim, fourier_encode, fourier_frequencies
from .layout import VoxelBatch


class LocalContext(nn.Module):
    """Residual dilated 3x3x3 convolutions at full resolution: (B, c0 + 1, R, R, R) -> (B, c_ctx, R, R, R).

    Layer 0 maps the stem input to c_ctx channels (dilation 1); layer i > 0 adds
    Conv3d(GELU(h), dilation 2^i) to h.  Receptive field: 1 + 2·(2^layers − 1) voxels per side.
    """

    def __init__(self, in_channels: int, channels: int, layers: int):
        super().__init__()
        self.inp = nn.Conv3d(in_channels, channels, 3, padding=1)
        self.convs = nn.ModuleList(nn.Conv3d(channels, channels, 3, padding=2 ** i, dilation=2 ** i)
                                   for i in range(1, layers))
        self.act = nn.GELU()

    def forward(self, x):
        h = self.inp(x)
        for conv in self.convs:
            h = h + conv(self.act(h))
        return h


class GridEncoder(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        C = cfg.width
        self.input_norm = nn.LayerNorm(cfg.feature_dim)
        self.voxel_proj = nn.Linear(cfg.feature_dim, cfg.voxel_channels)
        self.conv1 = nn.Conv3d(cfg.voxel_channels + 1, cfg.stem_channels, 4, stride=2, padding=1)
        self.conv2 = nn.Conv3d(cfg.stem_channels, C, 4, stride=2, padding=1)
        self.act = nn.GELU()
        self.local_context = (LocalContext(cfg.voxel_channels + 1, cfg.local_context_channels, cfg.local_context_layers)
                              if cfg.local_context_layers else None)
        self.register_buffer("pos_freqs", fourier_frequencies(cfg.fourier_frequencies, cfg.coarse_resolution / 2),
                             persistent=False)
        self.pos_proj = nn.Linear(fourier_dim(cfg.fourier_frequencies), C)
        self.latents = nn.Parameter(torch.randn(cfg.latent_tokens, C) * 0.02)
        blocks = []
        for _ in range(cfg.encoder_blocks):
            blocks.append(TransformerBlock(C, cfg.attention_heads, cfg.mlp_ratio, cross=True))
            for _ in range(cfg.encoder_self_layers):
                blocks.append(TransformerBlock(C, cfg.attention_heads, cfg.mlp_ratio, cross=False))
        self.blocks = nn.ModuleList(blocks)
        self.out_norm = nn.LayerNorm(C)
        Rc = cfg.coarse_resolution
        g = torch.arange(Rc, dtype=torch.float32)
        cells = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), dim=-1).reshape(-1, 3)
        self.register_buffer("cell_centres", (cells + 0.5) / Rc, persistent=False)

    def project_voxels(self, features: torch.Tensor) -> torch.Tensor:
        """(N, D) features -> (N, c0) projected per-voxel features."""
        return self.voxel_proj(self.input_norm(features))

    def dense_stem_input(self, batch: VoxelBatch, projected: torch.Tensor) -> torch.Tensor:
        """(B, c0 + 1, R, R, R): projected features and occupancy, zero at unoccupied voxels."""
        R, B = batch.resolution, batch.batch_size
        vals = torch.cat([projected, torch.ones_like(projected[:, :1])], dim=-1)
        dense = vals.new_zeros(B, R, R, R, vals.shape[-1])
        v = batch.voxels
        dense[v[:, 0], v[:, 1], v[:, 2], v[:, 3]] = vals
        return dense.permute(0, 4, 1, 2, 3)  # channels-last-3d memory layout, logical (B, c, R, R, R)

    def forward(self, batch: VoxelBatch):
        """-> (z (B, L, C) latent tokens, per-voxel local features (N, cfg.local_channels)).

        The local features are the projected input features (N, c0), followed by the local context's
        channels when ``local_context_layers`` > 0.
        """
        projected = self.project_voxels(batch.features)
        dense = self.dense_stem_input(batch, projected)
        local = projected
        if self.local_context is not None:
            v = batch.voxels
            context = self.local_context(dense).permute(0, 2, 3, 4, 1)[v[:, 0], v[:, 1], v[:, 2], v[:, 3]]
            local = torch.cat([projected, context.to(projected.dtype)], dim=-1)
        x = self.conv2(self.act(self.conv1(dense)))  # (B, C, R/4, R/4, R/4)
        tokens = x.flatten(2).transpose(1, 2)  # (B, (R/4)³, C), cell order i, j, k (C order)
        pos = self.pos_proj(fourier_encode(self.cell_centres, self.pos_freqs))
        tokens = tokens + pos.to(tokens.dtype)[None]
        z = self.latents[None].expand(batch.batch_size, -1, -1).to(tokens.dtype)
        for blk in self.blocks:
            z = blk(z, tokens) if blk.cross else blk(z)
        return self.out_norm(z), local

    def encode_dense(self, features: torch.Tensor, occupancy: torch.Tensor):
        """Encode dense inputs: features (B, D, R, R, R), occupancy (B, R, R, R) bool.

        Values at unoccupied voxels are ignored (they are never read); returns the same as
        :meth:`forward` on the occupied voxels.
        """
        idx = torch.nonzero(occupancy, as_tuple=False)  # (N, 4) [b, i, j, k], C order per sample
        feats = features.permute(0, 2, 3, 4, 1)[idx[:, 0], idx[:, 1], idx[:, 2], idx[:, 3]]
        return self(VoxelBatch(idx, feats, occupancy.shape[0], occupancy.shape[1]))
