"""Flow-matching transformer (FMT) decoders and the LBS HyperNetwork.

Every FMT decoder predicts the flow velocity v(x_t, t, c) of its targets.  Its tokens are the noisy
targets (the queries); they cross-attend to the latent tokens z and pass a SwiGLU MLP, both
AdaLN-modulated by c = MLP(Fourier(t) ⊕ sinusoidal(α) ⊕ mean(z)).  Tokens never attend to each other,
so every token's output depends only on its own input, t, α and z.

* :class:`GridFMT` — tokens are occupied P³ patches of the voxel grid (DiT-style "patchify"):
  token input = Linear(noisy values of its P³ voxels ⊕ their occupancy) + Linear(Fourier(patch centre))
  [+ Linear(projected input features of its voxels, and their local context when
  ``local_context_layers``) when ``local_features``].  Output per voxel:
  the velocity of each channel, plus ``extra_outputs`` per-voxel logits (MPM material classes).
  Unoccupied slots are zeroed in the input and in the output.
* :class:`VectorFMT` — tokens are consecutive chunks of one global vector (spring-mass k ⊕ η), with a
  learned embedding per chunk.
* :class:`HyperNetwork` — a plain MLP from mean(z) to the 650 LBS skinning parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from .config import ModelConfig
from .layers import Conditioning, FinalLayer, FMTBlock, fourier_dim, fourier_encode, fourier_frequencies


@dataclass
class DecoderContext:
    """What a decoder needs besides x_t, t and α, computed once per object (not per flow step).

    kv: per block, the latents' keys and values; latent_mean: (B, C) mean of z;
    token_base: (B, T, C) the t-independent part of each token (positions, local features) or None;
    slot_mask: (B, T, P³) bool occupied slots, or None for vector decoders.
    """

    kv: list
    latent_mean: torch.Tensor
    token_base: Optional[torch.Tensor] = None
    slot_mask: Optional[torch.Tensor] = None


class _FMTBase(nn.Module):
    def __init__(self, cfg: ModelConfig, blocks: int, out_dim: int):
        super().__init__()
        C = cfg.width
        self.cond = Conditioning(C, cfg.time_frequencies, cfg.alpha_embedding_dim)
        self.blocks = nn.ModuleList(FMTBlock(C, cfg.attention_heads, cfg.mlp_ratio) for _ in range(blocks))
        self.final = FinalLayer(C, out_dim)
        self.prediction = cfg.prediction
        self.min_remaining = cfg.min_remaining_time

    def to_velocity(self, out, x, t):
        """The network's output -> flow velocity.  ``prediction == "data"``: the output is the clean
        target x̂₁ and v = (x̂₁ − x_t) / max(1 − t, min_remaining_time); ``"velocity"``: v itself."""
        if self.prediction == "velocity":
            return out
        shape = (-1,) + (1,) * (x.dim() - 1)
        remaining = (1.0 - t.to(out.dtype)).clamp(min=self.min_remaining).view(shape)
        return (out - x.to(out.dtype)) / remaining

    def _kv(self, z):
        return [blk.kv(z) for blk in self.blocks]

    def _run(self, h, t, alpha, ctx: DecoderContext):
        B = h.shape[0]
        mean = ctx.latent_mean
        if mean.shape[0] != B:
            mean = mean.expand(B, -1)
        c_act = F.silu(self.cond(t, alpha, mean)).to(h.dtype)
        for blk, kv in zip(self.blocks, ctx.kv):
            h = blk(h, kv, c_act)
        return self.final(h, c_act)


class GridFMT(_FMTBase):
    """Per-voxel fields on patch tokens.  ``channels`` flow channels, ``extra_outputs`` logits per voxel."""

    def __init__(self, cfg: ModelConfig, channels: int, blocks: int, extra_outputs: int = 0):
        S = cfg.patch_voxels
        super().__init__(cfg, blocks, S * (channels + extra_outputs))
        C = cfg.width
        self.channels, self.extra_outputs, self.slots = channels, extra_outputs, S
        self.in_proj = nn.Linear(S * (channels + 1), C)
        self.pos_proj = nn.Linear(fourier_dim(cfg.fourier_frequencies), C)
        patches_per_side = cfg.grid_resolution // cfg.patch_size  # frequencies up to the patch grid's Nyquist
        self.register_buffer("pos_freqs", fourier_frequencies(cfg.fourier_frequencies, patches_per_side / 2),
                             persistent=False)
        self.local_proj = nn.Linear(S * cfg.local_channels, C) if cfg.local_features else None

    def context(self, z, centres, slot_mask, local_tokens=None) -> DecoderContext:
        """z (B, L, C); centres (B, T, 3); slot_mask (B, T, P³);
        local_tokens (B, T, P³·cfg.local_channels) or None."""
        base = self.pos_proj(fourier_encode(centres, self.pos_freqs))
        if self.local_proj is not None:
            base = base + self.local_proj(local_tokens)
        return DecoderContext(self._kv(z), z.mean(dim=1), base, slot_mask)

    def forward(self, x, t, alpha, ctx: DecoderContext):
        """x (B, T, P³, channels) noisy targets; t, alpha (B,) -> (B, T, P³, channels + extra_outputs) float32.

        The context may hold one object (batch 1) for B α values of it.  Unoccupied slots of ``x`` are
        ignored and the output there is zero.
        """
        B, T, S, _ = x.shape
        mask = ctx.slot_mask.to(x.dtype)[..., None]
        if mask.shape[0] != B:
            mask = mask.expand(B, -1, -1, -1)
        inp = torch.cat([x * mask, mask], dim=-1).reshape(B, T, -1)
        h = self.in_proj(inp) + ctx.token_base
        out = self._run(h, t, alpha, ctx).reshape(B, T, S, -1).float()  # velocities in float32 (1/(1-t) gain)
        ch = self.channels
        v = self.to_velocity(out[..., :ch], x.float(), t)
        return torch.cat([v, out[..., ch:]], dim=-1) * mask.float()


class VectorFMT(_FMTBase):
    """One global vector of ``dim`` values, in chunks of ``chunk`` values per token."""

    def __init__(self, cfg: ModelConfig, dim: int, chunk: int, blocks: int):
        self.dim, self.chunk = int(dim), int(chunk)
        self.tokens = math.ceil(self.dim / self.chunk)
        super().__init__(cfg, blocks, self.chunk)
        self.in_proj = nn.Linear(self.chunk, cfg.width)
        self.pos = nn.Parameter(torch.randn(self.tokens, cfg.width) * 0.02)

    def context(self, z) -> DecoderContext:
        return DecoderContext(self._kv(z), z.mean(dim=1))

    def forward(self, x, t, alpha, ctx: DecoderContext):
        """x (B, dim) noisy vector; t, alpha (B,) -> velocity (B, dim)."""
        B = x.shape[0]
        pad = self.tokens * self.chunk - self.dim
        xp = F.pad(x, (0, pad)).reshape(B, self.tokens, self.chunk)
        h = self.in_proj(xp) + self.pos.to(xp.dtype)[None]
        out = self._run(h, t, alpha, ctx).float()
        return self.to_velocity(out.reshape(B, -1)[:, : self.dim], x.float(), t)


class HyperNetwork(nn.Module):
    """mean(z) (B, C) -> (B, lbs_param_count) normalised skinning parameters; ``layers`` linear layers."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        dims = [cfg.width] + [cfg.hypernet_width] * (cfg.hypernet_layers - 1) + [cfg.lbs_param_count]
        layers = []
        for i in range(len(dims) - 1):
            layers.append(nn.Linear(dims[i], dims[i + 1]))
            if i < len(dims) - 2:
                layers.append(nn.SiLU())
        self.mlp = nn.Sequential(nn.LayerNorm(cfg.width), *layers)

    def forward(self, latent_mean):
        return self.mlp(latent_mean)
