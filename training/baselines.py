"""Baselines of the evaluation: a PIXIE-style deterministic 3D U-Net and the generative 3D U-Net ablation.

* ``unet_deterministic`` (PIXIE's architecture family, re-trained on our data as the paper does): the
  dense feature grid (features at occupied voxels, zero elsewhere, plus the occupancy as one more
  channel) → a 3D U-Net → per voxel the normalised (log10 E, log10 ρ, ν) and material-class logits.
  Trained with masked MSE + cross-entropy on the **α = 0.5 midpoint** targets (the paper: "parameters
  generated with α = 0.5 as the single ground-truth target").  It predicts one field for every α.
* ``unet_ddpm`` (the paper's "3D U-Net (Ablation)"): the same U-Net, conditioned on α (sinusoidal
  embedding) and on the diffusion step through adaptive group normalisation (AdaGN), takes the noisy
  continuous channels as extra input and predicts the noise (DDPM, 1000 steps, linear β from 1e-4 to
  0.02); the targets are the α-LERPed ranges with α ~ U(0, 1) per object; the class is a deterministic
  cross-entropy head of the same network.  Sampling: DDIM with 50 steps, η = 0, one shared noise
  sample for every α of a request.

Channels use the model's own normalisation (:mod:`unipixie.core.model.normalization`), so the numbers are
comparable with UniPixie's.  Only torch, numpy and safetensors are needed (no warp, bpy or trimesh): the
baselines train on the GPU machine from unpacked samples::

    python training/baselines.py train --data DATA --out runs/unet_det --kind deterministic --steps 20000
    python training/baselines.py train --data DATA --out runs/unet_ddpm --kind ddpm --steps 20000

A checkpoint is ``baseline.safetensors`` + ``baseline.json`` (kind, sizes, feature model, normalisation,
step, data fingerprint).
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Sequence

if __package__ in (None, ""):  # run as a file: import the checkout as `unipixie`
    import runpy

    runpy.run_path(str(Path(__file__).resolve().parents[1] / "standalone.py"))["import_checkout"]()
    __package__ = "unipixie.training"

import numpy as np  # noqa: E402

from ..core.atomic_io import atomic_path, write_json  # noqa: E402
from ..core.errors import UserError  # noqa: E402

BASELINE_FORMAT = "unipixie.baseline/1"
KINDS = ("deterministic", "ddpm")
METHOD_NAMES = {"deterministic": "unet_deterministic", "ddpm": "unet_ddpm"}
DDPM_STEPS = 1000
DDIM_STEPS = 50
X0_CLIP = 6.0
"""DDIM clips its x̂₀ estimate to ±6 normalised units (the targets span about ±3), as image DDIMs clip to [−1, 1]."""


@dataclass
class UNetConfig:
    """Sizes of the 3D U-Net.  base: channels at full resolution (doubling per level); levels: resolution
    halvings; cond_dim: width of the (t, α) embedding for the DDPM variant (0 = unconditioned)."""

    kind: str = "deterministic"
    feature_model: str = ""
    feature_dim: int = 32
    grid_resolution: int = 64
    base: int = 32
    levels: int = 3
    groups: int = 8
    cond_dim: int = 0
    num_classes: int = 8
    normalisation: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise UserError(f"baseline kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.grid_resolution % (2 ** self.levels):
            raise UserError(f"grid {self.grid_resolution}³ is not divisible by 2^{self.levels} (U-Net levels)")


def _torch():
    import torch

    return torch


def build_network(cfg: UNetConfig):
    """The U-Net module for ``cfg`` (torch)."""
    import torch
    from torch import nn

    def gn(ch):
        return nn.GroupNorm(min(cfg.groups, ch), ch)

    class Block(nn.Module):
        """Two 3×3×3 convolutions with GroupNorm and SiLU; AdaGN (scale, shift from the condition) if conditioned."""

        def __init__(self, cin, cout):
            super().__init__()
            self.c1 = nn.Conv3d(cin, cout, 3, padding=1)
            self.n1 = gn(cout)
            self.c2 = nn.Conv3d(cout, cout, 3, padding=1)
            self.n2 = gn(cout)
            self.skip = nn.Conv3d(cin, cout, 1) if cin != cout else nn.Identity()
            self.film = nn.Linear(cfg.cond_dim, 2 * cout) if cfg.cond_dim else None
            if self.film is not None:
                nn.init.zeros_(self.film.weight)
                nn.init.zeros_(self.film.bias)

        def forward(self, x, c=None):
            h = torch.nn.functional.silu(self.n1(self.c1(x)))
            h = self.n2(self.c2(h))
            if self.film is not None and c is not None:
                s, b = self.film(c).chunk(2, dim=-1)
                h = h * (1 + s[:, :, None, None, None]) + b[:, :, None, None, None]
            return torch.nn.functional.silu(h + self.skip(x))

    class UNet3D(nn.Module):
        def __init__(self):
            super().__init__()
            extra = 3 if cfg.kind == "ddpm" else 0
            cin = cfg.feature_dim + 1 + extra
            ch = [cfg.base * 2 ** i for i in range(cfg.levels + 1)]
            self.inp = Block(cin, ch[0])
            self.down = nn.ModuleList([nn.Conv3d(ch[i], ch[i + 1], 4, stride=2, padding=1) for i in range(cfg.levels)])
            self.enc = nn.ModuleList([Block(ch[i + 1], ch[i + 1]) for i in range(cfg.levels)])
            self.up = nn.ModuleList([nn.ConvTranspose3d(ch[i + 1], ch[i], 4, stride=2, padding=1)
                                     for i in reversed(range(cfg.levels))])
            self.dec = nn.ModuleList([Block(2 * ch[i], ch[i]) for i in reversed(range(cfg.levels))])
            self.out = nn.Conv3d(ch[0], 3 + cfg.num_classes, 1)
            if cfg.cond_dim:
                self.cond = nn.Sequential(nn.Linear(2 * cfg.cond_dim, cfg.cond_dim), nn.SiLU(),
                                          nn.Linear(cfg.cond_dim, cfg.cond_dim))

        def forward(self, x, t=None, alpha=None):
            c = None
            if cfg.cond_dim:
                c = self.cond(torch.cat([sinusoidal(t, cfg.cond_dim), sinusoidal(alpha * 1000.0, cfg.cond_dim)], -1))
            h = self.inp(x, c)
            skips = [h]
            for d, e in zip(self.down, self.enc):
                h = e(d(h), c)
                skips.append(h)
            skips.pop()
            for u, dblock in zip(self.up, self.dec):
                h = dblock(torch.cat([u(h), skips.pop()], dim=1), c)
            return self.out(h)

    return UNet3D()


def sinusoidal(x, dim: int):
    """(B,) values -> (B, dim) sinusoidal embedding (periods from 1 to 10⁴)."""
    torch = _torch()
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=x.device, dtype=torch.float32) / max(half, 1))
    arg = x.float()[:, None] * freqs[None]
    emb = torch.cat([torch.sin(arg), torch.cos(arg)], dim=-1)
    return emb if dim % 2 == 0 else torch.nn.functional.pad(emb, (0, 1))


# =========================================================================== data
def norms(cfg: UNetConfig):
    from ..core.model.normalization import DEFAULT_NORMALISATION, normalisation_from_dict

    return normalisation_from_dict(cfg.normalisation) if cfg.normalisation else dict(DEFAULT_NORMALISATION)


def dense_input(grid, device=None):
    """(D + 1, R, R, R) float32 tensor: features at occupied voxels (0 elsewhere) and the occupancy."""
    torch = _torch()
    R = grid.geometry.resolution
    x = torch.zeros(grid.dim + 1, R, R, R, dtype=torch.float32)
    idx = torch.from_numpy(grid.indices)
    x[:-1, idx[:, 0], idx[:, 1], idx[:, 2]] = torch.from_numpy(grid.features.astype(np.float32)).T
    x[-1, idx[:, 0], idx[:, 1], idx[:, 2]] = 1.0
    return x if device is None else x.to(device)


def target_channels(sample, cfg: UNetConfig, alpha: float) -> np.ndarray:
    """(K, 3) normalised (log10 E, log10 ρ, ν) at ``alpha`` (LERP of the ranges in the model's channel space)."""
    n = norms(cfg)
    m = sample.mpm
    lo = np.stack([n["E"].encode(m.E_min), n["density"].encode(m.density_min), n["nu"].encode(m.nu_min)], 1)
    hi = np.stack([n["E"].encode(m.E_max), n["density"].encode(m.density_max), n["nu"].encode(m.nu_max)], 1)
    return ((1.0 - alpha) * lo + alpha * hi).astype(np.float32)


def dense_sample(sample, cfg: UNetConfig, device) -> dict:
    """One training sample as dense tensors on ``device``, built once and reused every step it is drawn.

    x: (D + 1, R, R, R) float16 features and occupancy (the samples store float16 features, so nothing is
    lost); lo / hi: (3, R, R, R) float32 normalised targets at α = 0 and α = 1 (0 outside the object);
    cls: (R, R, R) int8 material class, −1 outside the object.
    """
    torch = _torch()
    R = cfg.grid_resolution
    idx = torch.from_numpy(sample.grid.indices.astype(np.int64))
    lo = torch.zeros(3, R, R, R)
    hi = torch.zeros(3, R, R, R)
    lo[:, idx[:, 0], idx[:, 1], idx[:, 2]] = torch.from_numpy(target_channels(sample, cfg, 0.0)).T
    hi[:, idx[:, 0], idx[:, 1], idx[:, 2]] = torch.from_numpy(target_channels(sample, cfg, 1.0)).T
    cls = torch.full((R, R, R), -1, dtype=torch.int8)
    cls[idx[:, 0], idx[:, 1], idx[:, 2]] = torch.from_numpy(sample.mpm.material.astype(np.int8))
    return {"x": dense_input(sample.grid).half().to(device), "lo": lo.to(device), "hi": hi.to(device),
            "cls": cls.to(device)}


def _batch(dense: list, alphas) -> tuple:
    """Stack dense samples (:func:`dense_sample`) into a batch at the given α, one per sample.

    Returns x (B, D + 1, R, R, R) float32, y (B, 3, R, R, R) float32 (the LERP of the normalised ranges,
    linear in the model's channels), cls (B, R, R, R) int64 and the occupancy mask (B, R, R, R) bool.
    """
    torch = _torch()
    x = torch.stack([d["x"] for d in dense]).float()
    a = torch.tensor(alphas, dtype=torch.float32, device=x.device)[:, None, None, None, None]
    y = (1.0 - a) * torch.stack([d["lo"] for d in dense]) + a * torch.stack([d["hi"] for d in dense])
    cls = torch.stack([d["cls"] for d in dense]).long()
    return x, y, cls, x[:, -1] > 0


def _ddpm_schedule(device):
    torch = _torch()
    betas = torch.linspace(1e-4, 0.02, DDPM_STEPS, dtype=torch.float64)
    abar = torch.cumprod(1.0 - betas, 0)
    return abar.float().to(device)


# =========================================================================== training
@dataclass
class BaselineTrainSettings:
    """How a baseline is trained.  cache_limit: training samples kept as dense tensors on the training
    device (:func:`dense_sample`; about 11 MB each at 64³ with D = 8, 24 MB with D = 32); samples beyond it
    are loaded and rebuilt each time they are drawn.  None (the default): on a GPU, cache while more than
    :data:`CACHE_FREE_FRACTION` of its memory stays free (1,600 objects of the appearance build take about
    18 GB); elsewhere :data:`CPU_CACHE_LIMIT` samples.  A cap of 1,024 on the GPU made the U-Net on 1,599
    training objects rebuild a third of its draws on the CPU: 19 samples/s on an H100, 4× below its rate on
    400 objects."""

    data: str
    out: str
    kind: str = "deterministic"
    steps: int = 2000
    batch: int = 2
    lr: float = 1e-3
    weight_decay: float = 1e-4
    base: int = 32
    levels: int = 3
    cond_dim: int = 64
    seed: int = 0
    device: str = "auto"
    log_every: int = 50
    save_every: int = 1000
    cache_limit: Optional[int] = None


CACHE_FREE_FRACTION = 0.25
"""With ``cache_limit`` None on a GPU: the dense-sample cache grows while more than this fraction of the device's
memory is free (the network's activations and the optimiser keep the rest)."""

CPU_CACHE_LIMIT = 1024
"""With ``cache_limit`` None on the CPU: samples cached in host memory (about 11–24 GB at 64³)."""


def cache_has_room(cached: int, limit: Optional[int], device) -> bool:
    """Whether one more dense sample may be cached: below ``limit`` when one is given, else by the device's free
    memory (CUDA: :data:`CACHE_FREE_FRACTION`) or :data:`CPU_CACHE_LIMIT`."""
    if limit is not None:
        return cached < int(limit)
    if getattr(device, "type", str(device)) == "cuda":
        free, total = _torch().cuda.mem_get_info(device)
        return free > CACHE_FREE_FRACTION * total
    return cached < CPU_CACHE_LIMIT


def _losses(net, cfg, x, y, cls, mask, abar, gen, alpha_t):
    torch = _torch()
    F = torch.nn.functional
    m = mask[:, None].float()
    if cfg.kind == "deterministic":
        out = net(x)
        pred = out[:, :3]
    else:
        B = x.shape[0]
        t = torch.randint(0, DDPM_STEPS, (B,), generator=gen).to(x.device)
        eps = torch.randn(y.shape, generator=gen).to(x.device) * m
        ab = abar[t][:, None, None, None, None]
        xt = ab.sqrt() * y + (1 - ab).sqrt() * eps
        out = net(torch.cat([x, xt * m], 1), t.float(), alpha_t)
        pred, y = out[:, :3], eps
    mse = ((pred - y) ** 2 * m).sum() / (3 * m.sum()).clamp_min(1)
    ce = F.cross_entropy(out[:, 3:], cls.clamp_min(0), reduction="none")
    ce = (ce * mask.float()).sum() / mask.float().sum().clamp_min(1)
    return mse, ce


def train(s: BaselineTrainSettings, log=print) -> dict:
    """Train a baseline on the training split of ``s.data`` (training samples); returns statistics."""
    torch = _torch()
    from ..core.model.inference import resolve_torch_device
    from ..solvers.materials import NUM_CLASSES
    from .sample_format import TrainingSample, data_fingerprint, list_samples

    if s.kind not in KINDS:
        raise UserError(f"--kind must be one of {', '.join(KINDS)}, got {s.kind!r}")
    files = list_samples(s.data, "train")
    first = TrainingSample.load(files[0])
    cfg = UNetConfig(kind=s.kind, feature_model=first.grid.feature_model, feature_dim=first.grid.dim,
                     grid_resolution=first.grid.geometry.resolution, base=s.base, levels=s.levels,
                     cond_dim=s.cond_dim if s.kind == "ddpm" else 0, num_classes=NUM_CLASSES)
    dev = resolve_torch_device(s.device)
    torch.manual_seed(s.seed)
    net = build_network(cfg).to(dev)
    opt = torch.optim.AdamW(net.parameters(), lr=s.lr, weight_decay=s.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: 0.5 * (1 + math.cos(math.pi * min(k / max(s.steps, 1), 1.0))))
    gen = torch.Generator().manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    abar = _ddpm_schedule(dev)
    cache: dict = {}
    losses = []
    t0 = time.perf_counter()
    for step in range(s.steps):
        pick = rng.choice(len(files), size=min(s.batch, len(files)), replace=len(files) < s.batch)
        samples = []
        for i in pick:
            smp = cache.get(int(i))
            if smp is None:
                loaded = TrainingSample.load(files[i])
                if loaded.grid.feature_model != cfg.feature_model or loaded.grid.dim != cfg.feature_dim:
                    raise UserError(f"{files[i]}: features {loaded.grid.feature_model!r} (D = {loaded.grid.dim}) "
                                    f"differ from the first sample's {cfg.feature_model!r} (D = {cfg.feature_dim})")
                smp = dense_sample(loaded, cfg, dev)
                if cache_has_room(len(cache), s.cache_limit, dev):
                    cache[int(i)] = smp
            samples.append(smp)
        alphas = [0.5] * len(samples) if s.kind == "deterministic" else list(rng.uniform(0, 1, len(samples)))
        x, y, cls, mask = _batch(samples, alphas)
        alpha_t = torch.tensor(alphas, dtype=torch.float32, device=dev)
        mse, ce = _losses(net, cfg, x, y, cls, mask, abar, gen, alpha_t)
        loss = mse + ce
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if log and (step % s.log_every == 0 or step == s.steps - 1):
            log(f"step {step + 1}/{s.steps}: loss {losses[-1]:.4g} (mse {float(mse.detach()):.4g}, ce {float(ce.detach()):.4g})")
        if (step + 1) % s.save_every == 0 or step == s.steps - 1:
            save(net, cfg, s.out, {"step": step + 1, "data_fingerprint": data_fingerprint(files), "settings": asdict(s)})
    return {"losses": losses, "seconds": time.perf_counter() - t0, "steps": s.steps, "device": str(dev),
            "samples_per_s": s.steps * min(s.batch, len(files)) / max(time.perf_counter() - t0, 1e-9)}


def save(net, cfg: UNetConfig, out, info: dict) -> Path:
    from safetensors.torch import save_file

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    with atomic_path(out / "baseline.safetensors") as tmp:
        save_file(state, str(tmp))
    doc = {"format": BASELINE_FORMAT, "config": asdict(cfg), "info": info}
    write_json(out / "baseline.json", doc, indent=1, default=str)
    return out


class BaselinePredictor:
    """A loaded baseline: ``predict(grid, alphas)`` -> list of per-α dicts of per-voxel E, nu, density, material."""

    def __init__(self, directory, device: str = "auto"):
        from safetensors.torch import load_file

        from ..core.model.inference import resolve_torch_device

        d = Path(directory)
        if not (d / "baseline.json").is_file() or not (d / "baseline.safetensors").is_file():
            raise UserError(f"{d}: not a baseline checkpoint (needs baseline.json and baseline.safetensors)")
        doc = json.loads((d / "baseline.json").read_text())
        if doc.get("format") != BASELINE_FORMAT:
            raise UserError(f"{d}/baseline.json: format {doc.get('format')!r}, expected {BASELINE_FORMAT!r}")
        self.cfg = UNetConfig(**doc["config"])
        self.info = doc.get("info", {})
        self.device = resolve_torch_device(device)
        self.net = build_network(self.cfg)
        try:
            self.net.load_state_dict(load_file(str(d / "baseline.safetensors")))
        except RuntimeError as exc:
            raise UserError(f"{d}: weights do not match baseline.json ({str(exc).splitlines()[0]})") from None
        self.net.to(self.device).eval()
        self.name = METHOD_NAMES[self.cfg.kind]
        self.directory = d

    def check_grid(self, grid) -> None:
        c = self.cfg
        if grid.feature_model != c.feature_model or grid.dim != c.feature_dim or grid.geometry.resolution != c.grid_resolution:
            raise UserError(f"baseline {self.directory} expects {c.feature_model!r} features (D = {c.feature_dim}) on "
                            f"{c.grid_resolution}³, the grid has {grid.feature_model!r} (D = {grid.dim}) on "
                            f"{grid.geometry.resolution}³")

    def predict(self, grid, alphas: Sequence[float] = (0.5,), seed: int = 0) -> list:
        torch = _torch()
        self.check_grid(grid)
        n = norms(self.cfg)
        idx = torch.from_numpy(grid.indices).to(self.device)
        x = dense_input(grid, self.device)[None]
        A = len(alphas)
        with torch.no_grad():
            if self.cfg.kind == "deterministic":
                out = self.net(x)[0]
                vals = out[:3, idx[:, 0], idx[:, 1], idx[:, 2]].T.cpu().numpy()
                logits = out[3:, idx[:, 0], idx[:, 1], idx[:, 2]].T.cpu().numpy()
                vals = np.repeat(vals[None], A, 0)
                logits = np.repeat(logits[None], A, 0)
            else:
                vals, logits = self._ddim(x, idx, np.asarray(alphas, np.float32), seed)
        out = []
        for i, a in enumerate(alphas):
            out.append({"alpha": float(a), "E": n["E"].decode(vals[i, :, 0]).astype(np.float32),
                        "density": n["density"].decode(vals[i, :, 1]).astype(np.float32),
                        "nu": n["nu"].decode(vals[i, :, 2]).astype(np.float32),
                        "material": logits[i].argmax(-1).astype(np.int16)})
        return out

    def _ddim(self, x, idx, alphas: np.ndarray, seed: int):
        """DDIM (η = 0, 50 steps) for every α at once from one shared noise sample."""
        torch = _torch()
        A = len(alphas)
        R = self.cfg.grid_resolution
        mask = x[:, -1:]
        g = torch.Generator().manual_seed(int(seed))
        xt = (torch.randn(1, 3, R, R, R, generator=g).to(self.device) * mask).expand(A, -1, -1, -1, -1).clone()
        xa = x.expand(A, -1, -1, -1, -1)
        al = torch.tensor(alphas, device=self.device)
        abar = _ddpm_schedule(self.device)
        ts = np.linspace(DDPM_STEPS - 1, 0, DDIM_STEPS).round().astype(np.int64)
        logits = None
        for i, t in enumerate(ts):
            tt = torch.full((A,), float(t), device=self.device)
            out = self.net(torch.cat([xa, xt * mask], 1), tt, al)
            eps = out[:, :3]
            logits = out[:, 3:]
            ab = abar[t]
            x0 = ((xt - (1 - ab).sqrt() * eps) / ab.sqrt()).clamp(-X0_CLIP, X0_CLIP)
            ab_prev = abar[ts[i + 1]] if i + 1 < len(ts) else torch.tensor(1.0, device=self.device)
            xt = (ab_prev.sqrt() * x0 + (1 - ab_prev).sqrt() * eps) * mask
        vals = xt[:, :, idx[:, 0], idx[:, 1], idx[:, 2]].permute(0, 2, 1).cpu().numpy()
        lg = logits[:, :, idx[:, 0], idx[:, 1], idx[:, 2]].permute(0, 2, 1).cpu().numpy()
        return vals, lg


# =========================================================================== command line
def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python training/baselines.py", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train a baseline on DATA's training split")
    t.add_argument("--data", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--kind", choices=KINDS, default="deterministic")
    t.add_argument("--steps", type=int, default=2000)
    t.add_argument("--batch", type=int, default=2)
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--base", type=int, default=32, help="channels at full resolution (default 32)")
    t.add_argument("--levels", type=int, default=3, help="resolution halvings (default 3)")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--device", default="auto")
    t.add_argument("--save-every", type=int, default=1000)
    t.add_argument("--cache-limit", type=int, default=None,
                   help="training samples kept as dense tensors on the device (default: as many as leave a quarter "
                        "of a GPU's memory free; 1024 on the CPU)")
    args = p.parse_args(argv)
    try:
        stats = train(BaselineTrainSettings(data=args.data, out=args.out, kind=args.kind, steps=args.steps,
                                            batch=args.batch, lr=args.lr, base=args.base, levels=args.levels,
                                            seed=args.seed, device=args.device, save_every=args.save_every,
                                            cache_limit=args.cache_limit))
    except UserError as exc:
        print(f"baselines: error: {exc}", file=sys.stderr)
        return exc.exit_code
    print(f"trained {stats['steps']} steps on {stats['device']} in {stats['seconds']:.0f} s "
          f"({stats['samples_per_s']:.3g} samples/s): loss {stats['losses'][0]:.4g} -> {stats['losses'][-1]:.4g}; "
          f"checkpoint in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
