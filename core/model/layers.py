"""Building blocks of the encoder and the flow-matching decoders (torch).

* :func:`fourier_encode` — 3D Fourier positional encoding of points in the unit cube;
* :func:`time_fourier` / :func:`sinusoidal` — embeddings of the flow time t and of α;
* :class:`Attention` — multi-head (cross- or self-) attention with RMSNorm QK-normalisation;
* :class:`SwiGLU` — the gated feed-forward network;
* :class:`TransformerBlock` — pre-norm attention + MLP (encoder);
* :class:`FMTBlock` — cross-attention + SwiGLU with AdaLN(-Zero) modulation from the condition c.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


def fourier_frequencies(count: int, max_cycles: float) -> torch.Tensor:
    """(count,) angular frequencies 2π·f, f log-spaced from 1 to ``max_cycles`` cycles per unit length."""
    if count == 1:
        cycles = torch.ones(1)
    else:
        cycles = torch.logspace(0.0, math.log10(max(max_cycles, 1.0)), count)
    return 2.0 * math.pi * cycles


def fourier_encode(points: torch.Tensor, frequencies: torch.Tensor) -> torch.Tensor:
    """(..., 3) points in [0, 1]³ -> (..., 3 + 6F): the points and sin/cos of every frequency per axis."""
    angles = points[..., :, None] * frequencies.to(points)  # (..., 3, F)
    enc = torch.cat([angles.sin(), angles.cos()], dim=-1).flatten(-2)
    return torch.cat([points, enc], dim=-1)


def fourier_dim(count: int) -> int:
    return 3 + 6 * count


def time_fourier(t: torch.Tensor, count: int) -> torch.Tensor:
    """(B,) flow times in [0, 1] -> (B, 1 + 2·count): t and sin/cos(π·2^k·t), k = 0..count-1."""
    freqs = math.pi * (2.0 ** torch.arange(count, device=t.device, dtype=torch.float32))
    ang = t.float()[:, None] * freqs
    return torch.cat([t.float()[:, None], ang.sin(), ang.cos()], dim=-1)


def sinusoidal(x: torch.Tensor, dim: int, max_frequency: float = 16.0) -> torch.Tensor:
    """(B,) scalars in [0, 1] -> (B, dim + 1): x and cos/sin(ω·x) for dim/2 angular frequencies ω
    log-spaced from 1 to ``max_frequency`` rad per unit.  Low frequencies only: the embedding of α
    must vary smoothly so that fields interpolate between the α values seen in training."""
    half = dim // 2
    freqs = torch.exp(torch.linspace(0.0, math.log(max_frequency), half, device=x.device, dtype=torch.float32))
    ang = x.float()[:, None] * freqs
    return torch.cat([x.float()[:, None], ang.cos(), ang.sin()], dim=-1)


class RMSNorm(nn.Module):
    """Root-mean-square normalisation over the last dimension with a learned gain."""

    def __init__(self, dim: int, eps: float = 1e-6):
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(dim))

    def forward(self, x):
        dtype = x.dtype
        x = x.float()
        x = x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + self.eps)
        return (x * self.weight.float()).to(dtype)


class Attention(nn.Module):
    """Multi-head attention of queries (B, Nq, C) to a context (B, Nk, C) with RMSNorm on Q and K.

    ``kv(context)`` projects keys and values once; a decoder reuses them for every flow step.
    ``key_padding`` (B, Nk) bool marks valid context tokens (None = all valid).
    """

    def __init__(self, width: int, heads: int, qk_norm: bool = True):
        super().__init__()
        self.heads = heads
        self.head_dim = width // heads
        self.q = nn.Linear(width, width)
        self.k = nn.Linear(width, width)
        self.v = nn.Linear(width, width)
        self.out = nn.Linear(width, width)
        self.q_norm = RMSNorm(self.head_dim) if qk_norm else nn.Identity()
        self.k_norm = RMSNorm(self.head_dim) if qk_norm else nn.Identity()

    def _split(self, x):
        B, N, _ = x.shape
        return x.view(B, N, self.heads, self.head_dim).transpose(1, 2)

    def kv(self, context: torch.Tensor):
        """(B, Nk, C) -> keys and values, each (B, heads, Nk, head_dim), keys RMS-normalised."""
        return self.k_norm(self._split(self.k(context))), self._split(self.v(context))

    def forward(self, x, context=None, kv=None, key_padding=None):
        if kv is None:
            kv = self.kv(x if context is None else context)
        k, v = kv
        q = self.q_norm(self._split(self.q(x)))
        B = q.shape[0]
        if k.shape[0] != B:
            k, v = k.expand(B, -1, -1, -1), v.expand(B, -1, -1, -1)
        mask = None if key_padding is None else key_padding[:, None, None, :]
        y = F.scaled_dot_product_attention(q, k.to(q.dtype), v.to(q.dtype), attn_mask=mask)
        return self.out(y.transpose(1, 2).reshape(B, -1, self.heads * self.head_dim))


class SwiGLU(nn.Module):
    """Gated feed-forward network: W3 (SiLU(W1 x) * W2 x); hidden = 2/3 · ratio · C (rounded to 8)."""

    def __init__(self, width: int, ratio: float):
        super().__init__()
        hidden = max(8, int(round(2.0 / 3.0 * ratio * width / 8.0)) * 8)
        self.w12 = nn.Linear(width, 2 * hidden)
        self.w3 = nn.Linear(hidden, width)

    def forward(self, x):
        a, b = self.w12(x).chunk(2, dim=-1)
        return self.w3(F.silu(a) * b)


class TransformerBlock(nn.Module):
    """Pre-norm block: x += Attn(LN x, LN context); x += SwiGLU(LN x).  Self-attention when no context."""

    def __init__(self, width: int, heads: int, mlp_ratio: float, cross: bool):
        super().__init__()
        self.cross = cross
        self.norm_q = nn.LayerNorm(width)
        self.norm_kv = nn.LayerNorm(width) if cross else None
        self.attn = Attention(width, heads)
        self.norm_mlp = nn.LayerNorm(width)
        self.mlp = SwiGLU(width, mlp_ratio)

    def forward(self, x, context=None, key_padding=None):
        h = self.norm_q(x)
        ctx = self.norm_kv(context) if self.cross else h
        x = x + self.attn(h, ctx, key_padding=key_padding)
        return x + self.mlp(self.norm_mlp(x))


def modulate(x, shift, scale):
    """AdaLN: x * (1 + scale) + shift, with shift/scale (B, C) broadcast over tokens."""
    return x * (1.0 + scale[:, None, :]) + shift[:, None, :]


class FMTBlock(nn.Module):
    """Flow-matching transformer block: tokens cross-attend to the latents, then a SwiGLU MLP.

    Both sub-layers are AdaLN-modulated: shift, scale and gate per sub-layer are regressed from the
    condition c (B, C).  The regression layer is zero-initialised (AdaLN-Zero), so every block starts as
    the identity.
    """

    def __init__(self, width: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.norm_attn = nn.LayerNorm(width, elementwise_affine=False, eps=1e-6)
        self.norm_ctx = nn.LayerNorm(width)
        self.attn = Attention(width, heads)
        self.norm_mlp = nn.LayerNorm(width, elementwise_affine=False, eps=1e-6)
        self.mlp = SwiGLU(width, mlp_ratio)
        self.ada = nn.Linear(width, 6 * width)
        nn.init.zeros_(self.ada.weight)
        nn.init.zeros_(self.ada.bias)

    def kv(self, latents):
        """Keys/values of the (normalised) latents; independent of t and α, computed once per solve."""
        return self.attn.kv(self.norm_ctx(latents))

    def forward(self, x, kv, c_act):
        """x (B, N, C) tokens; kv from :meth:`kv`; c_act = SiLU(c) (B, C)."""
        shift1, scale1, gate1, shift2, scale2, gate2 = self.ada(c_act).chunk(6, dim=-1)
        x = x + gate1[:, None, :] * self.attn(modulate(self.norm_attn(x), shift1, scale1), kv=kv)
        x = x + gate2[:, None, :] * self.mlp(modulate(self.norm_mlp(x), shift2, scale2))
        return x


class FinalLayer(nn.Module):
    """AdaLN-modulated LayerNorm and a zero-initialised linear read-out."""

    def __init__(self, width: int, out_dim: int):
        super().__init__()
        self.norm = nn.LayerNorm(width, elementwise_affine=False, eps=1e-6)
        self.ada = nn.Linear(width, 2 * width)
        self.linear = nn.Linear(width, out_dim)
        for lin in (self.ada, self.linear):
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)

    def forward(self, x, c_act):
        shift, scale = self.ada(c_act).chunk(2, dim=-1)
        return self.linear(modulate(self.norm(x), shift, scale))


class Conditioning(nn.Module):
    """c = MLP(Fourier(t) ⊕ sinusoidal(α) ⊕ mean(z_latent)) -> (B, C)."""

    def __init__(self, width: int, time_frequencies: int, alpha_dim: int):
        super().__init__()
        self.time_frequencies = time_frequencies
        self.alpha_dim = alpha_dim
        in_dim = 1 + 2 * time_frequencies + 1 + alpha_dim + width
        self.mlp = nn.Sequential(nn.Linear(in_dim, width), nn.SiLU(), nn.Linear(width, width))

    def forward(self, t, alpha, latent_mean):
        """t (B,), alpha (B,), latent_mean (B, C) -> c (B, C)."""
        emb = torch.cat([time_fourier(t, self.time_frequencies), sinusoidal(alpha, self.alpha_dim),
                         latent_mean.float()], dim=-1)
        return self.mlp(emb)
