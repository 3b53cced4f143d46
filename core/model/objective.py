"""The training objective: conditional flow matching on α-interpolated targets, plus the auxiliary losses.

For each object b of a batch, with α_b drawn in [0, 1] and flow times t drawn logit-normal:

* targets x₁ = (1 − α) y_min + α y_max, in normalised channels (log10 for E, ρ, k);
* x₀ ~ N(0, I); x_t = (1 − t) x₀ + t x₁; flow loss ‖v_θ(x_t, t, c) − (x₁ − x₀)‖², averaged over the
  object's occupied voxels and channels (unoccupied voxels are in no loss);
* MPM: flow loss + cross-entropy of the material-class logits;
* LBS (weight λ_LBS = 0.8): flow loss of the (E, ν) field + MSE of the HyperNetwork's 650 parameters;
* spring-mass: flow loss, stiffness entries weighted 0.5 and the softness entry 2.5;
* latent consistency (λ = 1e-4): ‖z(features) − z(features + 0.01·ε)‖².

Each object's losses are averaged over its own voxels first and the batch loss is the mean over
objects, so data-parallel training (each process a slice of the batch, gradients averaged) computes
exactly the gradient of one process on the whole batch.  All random numbers of object b at step s
come from a generator seeded by (seed, s, b's position in the global batch), so results do not
depend on the number of processes and a resumed run continues exactly.

Objects without labels for a head carry a zero ``has_*`` flag: that head's loss is multiplied by 0
(every parameter still takes part in the graph, which data-parallel training needs).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from .layout import VoxelBatch
from .network import UniPixieModel


@dataclass
class LossWeights:
    """Loss weights and regularisation settings (the paper's values as defaults)."""

    lbs: float = 0.8
    spring_stiffness: float = 0.5
    spring_softness: float = 2.5
    consistency: float = 1e-4
    consistency_noise: float = 0.01
    class_ce: float = 1.0
    hypernet: float = 1.0


@dataclass
class SamplingSettings:
    """How α and t are drawn: t = sigmoid(N(t_mean, t_std)) (logit-normal); α ~ U[0, 1], except that with
    probability ``alpha_endpoint_prob`` it is exactly 0 or 1 (half each).

    The paper names the logit-normal but not its parameters.  N(−0.8, 0.8) is the choice of JiT (Li & He,
    2025) for data-predicting flow models: with the velocity loss a data prediction's error counts
    1/(1 − t)² times, and shifting t towards the noise keeps those weights moderate (measured here: the
    synthetic overfit test converges ~3× lower with far less step-to-step noise than with N(0, 1))."""

    t_mean: float = -0.8
    t_std: float = 0.8
    alpha_endpoint_prob: float = 0.1


@dataclass
class TrainBatch:
    """Inputs and normalised targets of B objects (N occupied voxels in all, V = N_a + 1).

    voxels (N, 4) int64 [sample, i, j, k]; features (N, D) float32.
    mpm_lo / mpm_hi (N, 3): y_min / y_max channels (log10 E, log10 ρ, ν normalised); mpm_class (N,) int64
    (-1 = unlabelled); lbs_lo / lbs_hi (N, 2); lbs_params (B, 650); spring_lo / spring_hi (B, V);
    has_mpm / has_lbs / has_spring (B,) float32 in {0, 1}; seeds: (B,) per-object random seeds;
    spring_mask (B, V) float32 in {0, 1} or None (all entries): 0 on the stiffness entries past an object's own
    anchor count (a solid too small or thin for N_a anchors has fewer; its targets are padded).
    """

    voxels: torch.Tensor
    features: torch.Tensor
    batch_size: int
    resolution: int
    mpm_lo: torch.Tensor
    mpm_hi: torch.Tensor
    mpm_class: torch.Tensor
    lbs_lo: torch.Tensor
    lbs_hi: torch.Tensor
    lbs_params: torch.Tensor
    spring_lo: torch.Tensor
    spring_hi: torch.Tensor
    has_mpm: torch.Tensor
    has_lbs: torch.Tensor
    has_spring: torch.Tensor
    seeds: list = field(default_factory=list)
    spring_mask: Optional[torch.Tensor] = None

    def to(self, device) -> "TrainBatch":
        kw = {k: (v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v) for k, v in self.__dict__.items()}
        return TrainBatch(**kw)

    def pin_memory(self) -> "TrainBatch":
        """Page-locked copies (DataLoader(pin_memory=True) calls this) for asynchronous GPU transfer."""
        kw = {k: (v.pin_memory() if isinstance(v, torch.Tensor) else v) for k, v in self.__dict__.items()}
        return TrainBatch(**kw)

    @property
    def voxel_batch(self) -> VoxelBatch:
        return VoxelBatch(self.voxels, self.features, self.batch_size, self.resolution)

    def counts(self) -> list[int]:
        return torch.bincount(self.voxels[:, 0], minlength=self.batch_size).tolist()


@dataclass
class Draws:
    """The random numbers of one training step: alpha (B,), t_mpm / t_lbs / t_spring (B,),
    noise_mpm (N, 3), noise_lbs (N, 2), noise_spring (B, V), feature_noise (N, D) or None."""

    alpha: torch.Tensor
    t_mpm: torch.Tensor
    t_lbs: torch.Tensor
    t_spring: torch.Tensor
    noise_mpm: torch.Tensor
    noise_lbs: torch.Tensor
    noise_spring: torch.Tensor
    feature_noise: Optional[torch.Tensor]


def sample_seed(seed: int, step: int, position: int) -> int:
    """A 63-bit seed for object ``position`` of the global batch at ``step`` of a run seeded ``seed``."""
    h = hashlib.sha256(f"unipixie-train/{seed}/{step}/{position}".encode()).digest()
    return int.from_bytes(h[:8], "little") & ((1 << 63) - 1)


def make_draws(batch: TrainBatch, spring_dim: int, feature_noise: bool, sampling: SamplingSettings,
               device) -> Draws:
    """Draw every random number of a step, object by object from ``batch.seeds`` (see module docstring)."""
    counts = batch.counts()
    D = batch.features.shape[1]
    alpha, t3, n_mpm, n_lbs, n_spring, n_feat = [], [], [], [], [], []
    for b, K in enumerate(counts):
        g = torch.Generator(device=device)
        g.manual_seed(int(batch.seeds[b]))
        u = torch.rand(2, generator=g, device=device)
        a = torch.rand((), generator=g, device=device)
        alpha.append(torch.where(u[0] < sampling.alpha_endpoint_prob, (u[1] >= 0.5).to(a.dtype), a))
        t3.append(torch.sigmoid(torch.randn(3, generator=g, device=device) * sampling.t_std + sampling.t_mean))
        n_mpm.append(torch.randn(K, 3, generator=g, device=device))
        n_lbs.append(torch.randn(K, 2, generator=g, device=device))
        n_spring.append(torch.randn(spring_dim, generator=g, device=device))
        if feature_noise:
            n_feat.append(torch.randn(K, D, generator=g, device=device))
    t = torch.stack(t3)
    return Draws(torch.stack(alpha), t[:, 0], t[:, 1], t[:, 2], torch.cat(n_mpm), torch.cat(n_lbs),
                 torch.stack(n_spring), torch.cat(n_feat) if feature_noise else None)


def _segment_mean(values: torch.Tensor, segment: torch.Tensor, count: int) -> torch.Tensor:
    """Mean of (N,) ``values`` per segment id in [0, count) -> (count,) (0 for empty segments)."""
    total = values.new_zeros(count).index_add(0, segment, values)
    n = values.new_zeros(count).index_add(0, segment, torch.ones_like(values))
    return total / n.clamp(min=1.0)


class TrainingObjective(nn.Module):
    """Wraps a :class:`UniPixieModel`; ``forward(batch, draws)`` returns the dict of losses.

    ``losses["total"]`` is the scalar to minimise; the others are detached parts for logging.
    Wrap *this* module in DistributedDataParallel (both encoder passes happen in one forward).
    """

    def __init__(self, model: UniPixieModel, weights: LossWeights | None = None):
        super().__init__()
        self.model = model
        self.weights = weights or LossWeights()

    def forward(self, batch: TrainBatch, draws: Draws) -> dict:
        m, w, cfg = self.model, self.weights, self.model.cfg
        B = batch.batch_size
        vb = batch.voxel_batch
        sample = batch.voxels[:, 0]
        use_consistency = w.consistency > 0 and draws.feature_noise is not None
        if use_consistency:
            noisy = batch.features + w.consistency_noise * draws.feature_noise
            shifted = batch.voxels.clone()
            shifted[:, 0] += B
            both = VoxelBatch(torch.cat([batch.voxels, shifted]), torch.cat([batch.features, noisy]), 2 * B,
                              batch.resolution)
            z_all, proj_all = m.encoder(both)
            z, z_noisy = z_all[:B], z_all[B:]
            projected = proj_all[: batch.voxels.shape[0]]
            consistency = (z.float() - z_noisy.float()).pow(2).flatten(1).mean(1)
        else:
            z, projected = m.encoder(vb)
            consistency = torch.zeros(B, device=batch.features.device)
        enc = m.finish_encoding(z, projected, vb)
        layout = enc.layout
        a_vox = draws.alpha[sample][:, None]

        def grid_flow(head, lo, hi, noise, t):
            x1 = (1.0 - a_vox) * lo + a_vox * hi
            tv = t[sample][:, None]
            xt = (1.0 - tv) * noise + tv * x1
            ctx = m.grid_context(head, enc)
            out = head(layout.to_tokens(xt.to(z.dtype)), t, draws.alpha, ctx)
            vox = layout.from_tokens(out).float()
            ch = lo.shape[1]
            err = (vox[:, :ch] - (x1 - noise)).pow(2).mean(dim=1)
            return _segment_mean(err, sample, B), vox[:, ch:]

        mpm_flow, logits = grid_flow(m.mpm, batch.mpm_lo, batch.mpm_hi, draws.noise_mpm, draws.t_mpm)
        labelled = batch.mpm_class >= 0
        ce = F.cross_entropy(logits, batch.mpm_class.clamp(min=0), reduction="none") * labelled
        mpm_class = (ce.new_zeros(B).index_add(0, sample, ce)
                     / ce.new_zeros(B).index_add(0, sample, labelled.float()).clamp(min=1.0))
        lbs_flow, _ = grid_flow(m.lbs_material, batch.lbs_lo, batch.lbs_hi, draws.noise_lbs, draws.t_lbs)
        latent_mean = z.mean(dim=1)
        hyper = (m.hypernet(latent_mean).float() - batch.lbs_params).pow(2).mean(dim=1)

        a = draws.alpha[:, None]
        x1 = (1.0 - a) * batch.spring_lo + a * batch.spring_hi
        ts = draws.t_spring[:, None]
        xt = (1.0 - ts) * draws.noise_spring + ts * x1
        v = m.spring(xt.to(z.dtype), draws.t_spring, draws.alpha, m.spring.context(z)).float()
        serr = (v - (x1 - draws.noise_spring)).pow(2)
        if batch.spring_mask is None:
            spring_k = serr[:, :-1].mean(dim=1)
        else:  # the mean over each object's own anchors (padded entries carry no target)
            mask = batch.spring_mask[:, :-1]
            spring_k = (serr[:, :-1] * mask).sum(dim=1) / mask.sum(dim=1).clamp(min=1.0)
        spring_eta = serr[:, -1]

        per_sample = (batch.has_mpm * (mpm_flow + w.class_ce * mpm_class)
                      + w.lbs * batch.has_lbs * (lbs_flow + w.hypernet * hyper)
                      + batch.has_spring * (w.spring_stiffness * spring_k + w.spring_softness * spring_eta)
                      + w.consistency * consistency)
        parts = {"mpm_flow": mpm_flow * batch.has_mpm, "mpm_class": mpm_class * batch.has_mpm,
                 "lbs_flow": lbs_flow * batch.has_lbs, "lbs_hyper": hyper * batch.has_lbs,
                 "spring_stiffness": spring_k * batch.has_spring, "spring_softness": spring_eta * batch.has_spring,
                 "consistency": consistency}
        out = {k: v.detach().mean() for k, v in parts.items()}
        out["total"] = per_sample.mean()
        return out
