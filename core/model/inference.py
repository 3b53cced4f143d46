"""Inference: Heun's method on the learned flow, all α values of a request in one batched pass.

:meth:`Predictor.predict` encodes the feature grid once, draws **one** noise sample per head (from the
seed; the same for every α), and integrates dx/dt = v_θ(x, t, α) from t = 0 (noise) to t = 1 (fields)
with Heun's method (15 steps: 30 network evaluations, 29 for the default data-predicting network, whose
last step is an Euler step — see :func:`heun`) for all α values as one batch.  The step times follow the
distribution the network was trained on (:func:`flow_times`: quantiles of its logit-normal t), so the
network is never asked at times it has hardly seen.
Because the noise is shared, the fields vary smoothly with α; because it comes from a seeded CPU
generator, the result is deterministic for a seed (and the same noise on every device).  On CUDA the
network runs under bf16 autocast (the ODE state stays float32).

``samples`` > 1 averages that many draws (seeds ``seed`` … ``seed + samples − 1``) in the network's normalised
units — log10 E, log10 ρ, ν, the class logits, the spring stiffness' logarithm —: a Monte-Carlo estimate of the
conditional mean, the prediction with the least expected squared error.  One draw commits each voxel to one
reading of the object (near a part boundary, to one of the parts); the average hedges where the draws disagree,
at ``samples`` times the cost.

``temperature`` τ scales the starting noise of the per-voxel heads (MPM, LBS material): x(0) = τ·ε.  τ = 1 draws
from the learned distribution (the paper's sampler); τ = 0 starts every voxel at the noise distribution's mean and
integrates the same flow from there — one deterministic path, no seed, at one draw's cost.  The spring-mass head
(one vector of N_a + 1 values per object) always draws at τ = 1 (:data:`SPRING_TEMPERATURE`).
:data:`DEFAULT_TEMPERATURE` says which the product uses and why.

Returns a :class:`Prediction`: per α, a :class:`~unipixie.core.types.MaterialField` (MPM head), an
:class:`LBSPrediction` (650 skinning parameters + E, ν per occupied voxel) and a
:class:`SpringPrediction` (N_a stiffnesses + the softness η).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from statistics import NormalDist
from typing import Optional, Sequence

import numpy as np
import torch

from ...solvers import materials
from ...solvers.registry import ALIASES as SOLVER_ALIASES
from ..errors import UserError
from ..progress import Progress, silent
from ..types import FeatureGrid, MaterialField
from .checkpoint import checkpoint_key, is_checkpoint, load_model
from .config import HEADS, ModelConfig
from .layout import VoxelBatch
from .network import UniPixieModel
from .normalization import LBS_CHANNELS, MPM_CHANNELS
from .objective import SamplingSettings

DEFAULT_STEPS = 15
"""Heun steps (2 function evaluations each)."""
DEFAULT_SWEEP_COUNT = 11
"""α values of the cached slider sweep (0, 0.1, ..., 1)."""

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CHECKPOINT = REPO_ROOT / "models" / "default"
"""Where the shipped model lives (``models/default/`` of the package)."""

@dataclass
class LBSPrediction:
    """LBS head output for one α: params (650,) float32 skinning parameters (layout of
    :mod:`unipixie.solvers.skinning`), E (K,) float32 Pa and nu (K,) float32 per occupied voxel."""

    alpha: float
    params: np.ndarray
    E: np.ndarray
    nu: np.ndarray


@dataclass
class SpringPrediction:
    """Spring-mass head output for one α: stiffness (N_a,) float32 per anchor (the spring-mass solver's
    units, N/m) and softness η (dimensionless)."""

    alpha: float
    stiffness: np.ndarray
    softness: float


@dataclass
class Prediction:
    """Outputs per α (lists in the order of ``alphas``; None for heads not run)."""

    alphas: np.ndarray
    mpm: Optional[list] = None
    lbs: Optional[list] = None
    spring_mass: Optional[list] = None
    seconds: float = 0.0
    meta: dict = field(default_factory=dict)


def resolve_torch_device(device: str = "auto") -> torch.device:
    """``"auto"`` -> cuda when available else cpu; ``"cuda"`` without a GPU is a UserError."""
    d = (device or "auto").strip().lower()
    if d == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if d.startswith("cuda"):
        if not torch.cuda.is_available():
            raise UserError(f"device {device!r} requested but torch sees no CUDA GPU; use --device cpu")
        return torch.device(d)
    if d == "cpu":
        return torch.device("cpu")
    raise UserError(f"unknown device {device!r}; use cpu, cuda, cuda:N or auto")


DEFAULT_TEMPERATURE = 0.0
"""The sampler's default noise scale (τ, module docstring): the deterministic path.  Measured on the shipped model's
200 test objects (one H200; models/default/evaluation_temperature.md): log E MSE 0.271 with one draw at τ = 1, 0.218
at τ = ½, **0.204 at τ = 0** — nearly as good as averaging 8 draws (0.199) at one draw's cost, better at every
class and distance from a part boundary, E inside its range at α = 0 / 1 for 49.6 / 40.9 % of the voxels (one draw
45.9 / 39.9 %), the sweep monotone on every object; on the 201 validation objects 0.226 against 0.282.  An artist's
slider wants one answer per α, not a new draw per seed.
On Table 2's 20 test objects (models/default/evaluation_table2_temperature.md) the MPM field at τ = 0 follows the
ground-truth motion more closely (0.053 / 0.042 / 0.041 of the size against 0.054 / 0.046 / 0.044) and the LBS head
is 1.12× its test-time fit (1.16× at τ = 1)."""

SPRING_TEMPERATURE = 1.0
"""The spring-mass head's noise scale, whatever ``temperature`` says: its stiffnesses are one draw.  Measured on
Table 2's 20 test objects: started at τ = 0 its motions were 1.60× the test-time fit's error, against 1.38× as a
draw (issue 17 asks for 1.5×)."""

MAX_SAMPLES = 64
"""Most draws :meth:`Predictor.predict` averages (each costs a whole prediction)."""


def check_samples(samples) -> int:
    """``samples`` as a whole number of draws in [1, :data:`MAX_SAMPLES`]; anything else is a UserError."""
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or not 1 <= int(samples) <= MAX_SAMPLES:
        raise UserError(f"samples must be a whole number of draws from 1 to {MAX_SAMPLES}, got {samples!r}")
    return int(samples)


def check_temperature(temperature) -> float:
    """``temperature`` as a float in [0, 1]; anything else is a UserError."""
    try:
        t = float(temperature)
    except (TypeError, ValueError):
        t = math.nan
    if isinstance(temperature, bool) or not 0.0 <= t <= 1.0:
        raise UserError(f"temperature must be a number from 0 (the deterministic path) to 1 (a draw from the model), "
                        f"got {temperature!r}")
    return t


def canonical_heads(heads) -> tuple:
    if isinstance(heads, str):
        heads = [h for h in heads.replace(" ", "").split(",") if h]
    out = []
    for h in heads:
        k = SOLVER_ALIASES.get(str(h).strip().lower(), str(h).strip().lower())
        if k not in HEADS:
            raise UserError(f"unknown head {h!r}; choose from {', '.join(HEADS)}")
        if k not in out:
            out.append(k)
    if not out:
        raise UserError(f"no heads selected; choose from {', '.join(HEADS)}")
    return tuple(out)


def check_alphas(alphas) -> np.ndarray:
    a = np.asarray(alphas, dtype=np.float64).reshape(-1)
    if a.size == 0:
        raise UserError("no alpha values given")
    if not np.all(np.isfinite(a)) or np.any(a < 0) or np.any(a > 1):
        raise UserError(f"alpha values must lie in [0, 1], got {a.tolist()}")
    return a


def flow_times(steps: int, t_mean: float = SamplingSettings.t_mean,
               t_std: float = SamplingSettings.t_std) -> np.ndarray:
    """The step times (steps + 1,) from 0 to 1: t_i = sigmoid(t_mean + t_std · Φ⁻¹(i / steps)) inside.

    These are the quantiles of the logit-normal distribution the flow times were drawn from in training
    (:class:`~.objective.SamplingSettings`, JiT's N(−0.8, 0.8) by default), so each step spans the same
    share of the training distribution and the network is evaluated only where it was trained.  With
    the default distribution and 15 steps the last time before 1 is 0.60.  Measured on the shipped model
    (12 test objects, α = 0 and 1): evenly spaced steps, which put 5 of 15 times above 0.6 where training
    drew 1 t in 15 (and above 0.8 fewer than 1 in 300), left log10 E biased by −0.26 decade (MSE 0.42);
    these times by −0.05 (MSE 0.29).  ``steps = 1`` gives [0, 1].
    """
    steps = int(steps)
    if steps < 1:
        raise UserError(f"steps must be >= 1, got {steps}")
    mean, std = float(t_mean), float(t_std)
    if not (math.isfinite(mean) and math.isfinite(std) and std > 0):
        raise UserError(f"flow-time distribution needs a finite mean and a positive spread, got N({mean}, {std})")
    normal = NormalDist()
    inner = [1.0 / (1.0 + math.exp(-(mean + std * normal.inv_cdf(i / steps)))) for i in range(1, steps)]
    return np.array([0.0] + inner + [1.0], dtype=np.float64)


def heun(velocity, x0: torch.Tensor, times, last_euler: bool = False):
    """Integrate dx/dt = velocity(x, t) over ``times`` (increasing, from 0 to 1) with Heun's method
    (2 evaluations per step; see :func:`flow_times`).

    velocity(x, t: float) -> (v, aux); returns (x(1), aux of the last evaluation).
    last_euler: take the last step with Euler (one evaluation fewer), as EDM's Heun sampler does
    for its step to noise level 0: for a data-predicting network v = (x̂ − x)/(1 − t) lands exactly on
    x̂ there, while a corrector evaluated at t = 1 would be 0/0.
    """
    times = [float(t) for t in times]
    x = x0
    aux = None
    steps = len(times) - 1
    for i in range(steps):
        t0, t1 = times[i], times[i + 1]
        dt = t1 - t0
        v0, aux = velocity(x, t0)
        x_pred = x + dt * v0
        if last_euler and i == steps - 1:
            x = x_pred
            break
        v1, aux = velocity(x_pred, t1)
        x = x + 0.5 * dt * (v0 + v1)
    return x, aux


class Predictor:
    """A loaded model on a device.  ``Predictor.load(checkpoint_dir)`` or ``Predictor(model)``."""

    def __init__(self, model: UniPixieModel, device="cpu", precision: str = "auto", checkpoint: str = "",
                 key: str = "", sampling: Optional[dict] = None):
        self.device = torch.device(device) if not isinstance(device, torch.device) else device
        self.model = model.to(self.device).eval()
        self.cfg: ModelConfig = model.cfg
        self.checkpoint = str(checkpoint)
        self.key = key
        registry = tuple(materials.names())
        if registry[: len(self.cfg.class_names)] != tuple(self.cfg.class_names):
            raise UserError(f"checkpoint {checkpoint or ''} predicts material classes {list(self.cfg.class_names)}, which do "
                            f"not match the registry's {list(registry)} (ids must agree); retrain the model")
        if precision == "auto":
            precision = "bf16" if self.device.type == "cuda" else "fp32"
        if precision not in ("fp32", "bf16"):
            raise UserError(f"precision must be fp32, bf16 or auto, got {precision!r}")
        self.precision = precision
        # the logit-normal N(t_mean, t_std) the flow times were drawn from in training (from the
        # checkpoint's info; checkpoints that do not record it were trained with the default)
        sampling = dict(sampling or {})
        self.t_mean = float(sampling.get("t_mean", SamplingSettings.t_mean))
        self.t_std = float(sampling.get("t_std", SamplingSettings.t_std))

    def times(self, steps: int) -> np.ndarray:
        """The flow times the sampler steps through (:func:`flow_times`)."""
        return flow_times(steps, self.t_mean, self.t_std)

    @property
    def sampler_id(self) -> str:
        """What determines the sampler besides steps and seed (part of cache keys)."""
        return f"heun-logitnormal-quantiles(N({self.t_mean:g}, {self.t_std:g}))"

    @classmethod
    def load(cls, checkpoint=None, device: str = "auto", precision: str = "auto") -> "Predictor":
        path = Path(checkpoint) if checkpoint else DEFAULT_CHECKPOINT
        if not is_checkpoint(path):
            if checkpoint is None:
                raise UserError(f"no default model in {path}; pass a checkpoint directory "
                                "(one made by 'unipixie train --out DIR')")
            raise UserError(f"{path}: not a UniPixie checkpoint (needs config.json and model.safetensors)")
        dev = resolve_torch_device(device)
        model, info = load_model(path, device=dev)
        sampling = info.get("sampling") if isinstance(info.get("sampling"), dict) else None
        return cls(model, dev, precision, checkpoint=str(path), key=checkpoint_key(path), sampling=sampling)

    # ------------------------------------------------------------------ input checks
    def check_grid(self, grid: FeatureGrid) -> None:
        cfg = self.cfg
        where = f"checkpoint {self.checkpoint}" if self.checkpoint else "this model"
        if grid.feature_model != cfg.feature_model:
            raise UserError(f"the feature grid was made with feature model {grid.feature_model!r} but {where} expects "
                            f"{cfg.feature_model!r}; extract features with {cfg.feature_model!r} or use a model "
                            f"trained on {grid.feature_model!r}")
        if grid.dim != cfg.feature_dim:
            raise UserError(f"the feature grid has {grid.dim} feature channels but {where} expects {cfg.feature_dim}")
        if grid.geometry.resolution != cfg.grid_resolution:
            raise UserError(f"the feature grid is {grid.geometry.resolution}³ but {where} expects "
                            f"{cfg.grid_resolution}³ voxels")
        if grid.features.shape[0] == 0:
            raise UserError("the feature grid has no occupied voxels (is the object empty or outside the grid?)")
        if not np.all(np.isfinite(grid.features)):
            bad = int((~np.isfinite(grid.features)).any(axis=1).sum())
            raise UserError(f"the feature grid has NaN/inf features in {bad} voxel(s); re-extract the features")

    def _autocast(self):
        if self.precision == "bf16":
            return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16)
        return torch.autocast(device_type=self.device.type, enabled=False)

    def _noise(self, seed: int, head_index: int, shape) -> torch.Tensor:
        g = torch.Generator(device="cpu")
        g.manual_seed(int(seed) * 1000003 + head_index)
        return torch.randn(*shape, generator=g).to(self.device)

    # ------------------------------------------------------------------ prediction
    @torch.no_grad()
    def predict(self, grid: FeatureGrid, alphas: Sequence[float] = (0.5,), heads=HEADS, seed: int = 0,
                steps: int = DEFAULT_STEPS, progress: Optional[Progress] = None, samples: int = 1,
                temperature: float = DEFAULT_TEMPERATURE) -> Prediction:
        """Predict every requested head for every α in one batched pass (see module docstring); ``samples`` draws
        averaged in normalised units (1: one draw); ``temperature``: the per-voxel heads' starting noise scale (0: the
        deterministic path, where ``seed`` plays no part; 1: a draw from the model; the spring head always draws,
        :data:`SPRING_TEMPERATURE`)."""
        self.check_grid(grid)
        a_np = check_alphas(alphas)
        heads = canonical_heads(heads)
        if int(steps) < 1:
            raise UserError(f"steps must be >= 1, got {steps}")
        samples = check_samples(samples)
        temperature = check_temperature(temperature)
        if samples > 1 and temperature == 0.0:
            raise UserError(f"averaging {samples} draws needs temperature > 0: at temperature 0 every draw is the same "
                            "deterministic path (use samples 1, or temperature 1 to average draws from the model)")
        progress = progress or silent()
        flow_heads = [h for h in heads if h in HEADS]
        evaluations = 2 * steps - (1 if self.cfg.prediction == "data" else 0)
        sub = progress.sub(1.0, 1 + 0.5 * evaluations * len(flow_heads) * samples, "predict")
        t_start = time.perf_counter()
        m, cfg, dev = self.model, self.cfg, self.device
        A = a_np.size
        alpha = torch.tensor(a_np, dtype=torch.float32, device=dev)
        batch = VoxelBatch.from_grids([grid.occupancy], [grid.features.astype(np.float32)], device=dev)
        with self._autocast():
            enc = m.encode(batch)
        sub.step(1, "encoded")
        layout = enc.layout
        N = batch.voxels.shape[0]
        norms = cfg.norms()
        times = self.times(steps)
        result = Prediction(alphas=a_np.astype(np.float64), meta={"seed": int(seed), "steps": int(steps),
                                                                  "sampler": self.sampler_id,
                                                                  "heads": list(heads), "samples": samples,
                                                                  "temperature": temperature})

        def grid_head(head, channels, head_index):
            with self._autocast():
                ctx = m.grid_context(head, enc)

            def vel(x, t):
                tt = torch.full((A,), t, device=dev)
                with self._autocast():
                    out = head(x, tt, alpha, ctx).float()
                sub.step(0.5)
                return out[..., :channels], out[..., channels:]

            total_x, total_aux = 0.0, 0.0
            for draw in range(samples):
                noise = self._noise(seed + draw, head_index, (N, channels)) * temperature
                x0 = layout.to_tokens(noise).expand(A, -1, -1, -1)
                x1, aux = heun(vel, x0, times, last_euler=cfg.prediction == "data")
                total_x = total_x + layout.from_tokens_single(x1)
                total_aux = total_aux + layout.from_tokens_single(aux)
            return total_x / samples, total_aux / samples  # (A, N, ch), (A, N, extra)

        if "mpm" in heads:
            vals, logits = grid_head(m.mpm, len(MPM_CHANNELS), 0)
            vals, logits = vals.cpu().numpy(), logits.cpu().numpy()
            E = norms["E"].decode(vals[..., 0])
            rho = norms["density"].decode(vals[..., 1])
            nu = norms["nu"].decode(vals[..., 2])
            cls = logits.argmax(axis=-1).astype(np.int16)
            result.mpm = [MaterialField(grid.geometry, grid.occupancy, E[i], nu[i], rho[i], cls[i], float(a_np[i]),
                                        meta={"model": self.checkpoint, "seed": int(seed)}) for i in range(A)]
        if "lbs" in heads:
            vals, _ = grid_head(m.lbs_material, len(LBS_CHANNELS), 1)
            vals = vals.cpu().numpy()
            E = norms["E"].decode(vals[..., 0]).astype(np.float32)
            nu = norms["nu"].decode(vals[..., 1]).astype(np.float32)
            with self._autocast():
                params = m.hypernet(enc.z.mean(dim=1)).float()[0].cpu().numpy()
            params = norms["lbs_params"].decode(params).astype(np.float32)
            result.lbs = [LBSPrediction(float(a_np[i]), params.copy(), E[i], nu[i]) for i in range(A)]
        if "spring_mass" in heads:
            with self._autocast():
                ctx = m.spring.context(enc.z)

            def vel(x, t):
                tt = torch.full((A,), t, device=dev)
                with self._autocast():
                    out = m.spring(x, tt, alpha, ctx).float()
                sub.step(0.5)
                return out, None

            x1 = 0.0
            for draw in range(samples):
                x0 = (self._noise(seed + draw, 2, (1, cfg.spring_dim)) * SPRING_TEMPERATURE).expand(A, -1)
                x1 = x1 + heun(vel, x0, times, last_euler=cfg.prediction == "data")[0]
            x1 = (x1 / samples).cpu().numpy()
            k = norms["stiffness"].decode(x1[:, :-1]).astype(np.float32)
            eta = norms["softness"].decode(x1[:, -1])
            result.spring_mass = [SpringPrediction(float(a_np[i]), k[i], float(eta[i])) for i in range(A)]
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        result.seconds = time.perf_counter() - t_start
        return result


_CACHE: dict = {}


def get_predictor(checkpoint=None, device: str = "auto") -> Predictor:
    """A :class:`Predictor` for ``checkpoint`` (default: the shipped model), kept loaded per process."""
    path = Path(checkpoint).resolve() if checkpoint else DEFAULT_CHECKPOINT
    dev = str(resolve_torch_device(device))
    weights = path / "model.safetensors"
    stamp = (weights.stat().st_mtime_ns, weights.stat().st_size) if weights.is_file() else None
    entry = _CACHE.get((str(path), dev))
    if entry is None or entry[0] != stamp:
        entry = (stamp, Predictor.load(checkpoint, device=dev))
        _CACHE[(str(path), dev)] = entry
    return entry[1]


def predict(feature_grid: FeatureGrid, alphas: Sequence[float] = (0.5,), heads=HEADS, seed: int = 0,
            checkpoint=None, device: str = "auto", steps: int = DEFAULT_STEPS,
            progress: Optional[Progress] = None, samples: int = 1,
            temperature: float = DEFAULT_TEMPERATURE) -> Prediction:
    """Predict materials for ``feature_grid`` at every α (one batched pass, one shared noise sample).

    feature_grid: the model's input (:class:`~unipixie.core.types.FeatureGrid`); alphas: values in [0, 1];
    heads: any of :data:`HEADS`; seed: noise seed (same seed, same result; at temperature 0 only the spring head's);
    checkpoint: checkpoint directory (default: the shipped model in ``models/default``);
    samples: draws averaged (seeds ``seed`` … ``seed + samples − 1``; the module docstring says why);
    temperature: the per-voxel heads' starting noise scale, 0 (the deterministic path, the default) to 1 (a draw from
    the model); the spring head always draws (:data:`SPRING_TEMPERATURE`).
    """
    return get_predictor(checkpoint, device).predict(feature_grid, alphas, heads, seed, steps, progress,
                                                     samples=samples, temperature=temperature)
