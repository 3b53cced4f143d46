"""Training loop of the UniPixie model (single process or torch.distributed data parallel).

Command line (same options both ways)::

    unipixie train --data DATA_DIR --out CKPT_DIR [--steps N] [--batch B] [--resume]
    torchrun --nproc_per_node=2 -m unipixie.training.train --data DATA_DIR --out CKPT_DIR ...
    torchrun --nproc_per_node=2 training/train.py ...       # from a bare checkout (no install)

``--batch`` is the global batch; each of the W processes takes B / W objects of it.  All randomness
of an object comes from (seed, step, its position in the global batch) (see
:mod:`unipixie.core.model.objective`), so W processes compute the same averaged gradient as one
process on the whole batch, and ``--resume`` continues exactly where the saved step left off.
Backends: NCCL on GPUs, gloo on the CPU.  Mixed precision: bf16 autocast on GPUs that support it.

This module imports only the standard library at module level; it needs torch, numpy and
safetensors to run (no warp, bpy or trimesh), so it runs on a bare GPU machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional

if __package__ in (None, ""):  # run as a file (torchrun training/train.py): import the checkout as `unipixie`
    import runpy

    runpy.run_path(str(Path(__file__).resolve().parents[1] / "standalone.py"))["import_checkout"]()
    __package__ = "unipixie.training"

from ..core.atomic_io import atomic_path, copy_file, write_json  # noqa: E402  (stdlib-only module)
from ..core.errors import CancelledError, UserError  # noqa: E402  (stdlib-only module)

PRECISIONS = ("auto", "fp32", "bf16")
CACHE_BYTES = 1 << 30
"""At most this many bytes of features are kept in memory per data-loading process (small datasets
are then read from disk once)."""
LOG_FILE = "train_log.jsonl"


@dataclass
class TrainSettings:
    """Everything that defines a training run (saved in the checkpoint's training_state.json).

    batch: global batch size (objects per step, split over the processes).
    warmup: linear warm-up steps; None = min(3000, steps // 10) (3000 is the paper's).
    preset / model: model size preset and per-field overrides (``{"width": 256}``).
    fit_normalisation: fit the spring stiffness / softness and LBS parameter normalisation to the data
        (the MPM channels always use the fixed constants of :mod:`unipixie.core.model.normalization`).
    stop_after: stop (and save) after this many steps of this invocation, e.g. to fit a job's time
        limit; continue later with ``resume`` (the schedule still runs to ``steps``).
    """

    data: str
    out: str
    steps: int = 1000
    batch: int = 1
    lr: float = 5e-5
    weight_decay: float = 0.01
    warmup: Optional[int] = None
    min_lr_ratio: float = 0.0
    grad_clip: float = 1.0
    precision: str = "auto"
    device: str = "auto"
    seed: int = 0
    save_every: int = 500
    log_every: int = 10
    workers: int = 0
    preset: str = "paper"
    model: dict = field(default_factory=dict)
    fit_normalisation: bool = True
    resume: bool = False
    allow_new_data: bool = False
    save_dtype: str = "float32"
    loss: dict = field(default_factory=dict)
    sampling: dict = field(default_factory=dict)
    dump_gradients: Optional[str] = None
    stats_out: Optional[str] = None
    cache_samples: int = 256
    stop_after: Optional[int] = None

    def warmup_steps(self) -> int:
        return int(self.warmup) if self.warmup is not None else min(3000, self.steps // 10)


def learning_rate(step: int, s: TrainSettings) -> float:
    """Linear warm-up to ``lr`` then cosine annealing to ``min_lr_ratio · lr`` at ``steps``."""
    w = s.warmup_steps()
    if w > 0 and step < w:
        return s.lr * (step + 1) / w
    span = max(1, s.steps - w)
    progress = min(1.0, (step - w) / span)
    return s.lr * (s.min_lr_ratio + (1.0 - s.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress)))


# ---------------------------------------------------------------------------- data
class Collate:
    """TrainingSamples -> :class:`~unipixie.core.model.objective.TrainBatch` (CPU, normalised targets)."""

    def __init__(self, cfg):
        self.cfg = cfg
        self.norms = cfg.norms()

    def check(self, sample, where: str) -> None:
        cfg = self.cfg
        g = sample.grid
        if g.feature_model != cfg.feature_model:
            raise UserError(f"{where}: features from {g.feature_model!r}, the model is for {cfg.feature_model!r}")
        if g.dim != cfg.feature_dim:
            raise UserError(f"{where}: {g.dim} feature channels, the model expects {cfg.feature_dim}")
        if g.geometry.resolution != cfg.grid_resolution:
            raise UserError(f"{where}: grid {g.geometry.resolution}³, the model expects {cfg.grid_resolution}³")
        if sample.spring is not None and sample.spring.stiffness_min.size > cfg.spring_anchors:
            raise UserError(f"{where}: {sample.spring.stiffness_min.size} spring anchors, the model expects at most "
                            f"{cfg.spring_anchors} (set --set spring_anchors=N for a new model)")

    def __call__(self, items):
        import numpy as np
        import torch

        from ..core.model.objective import TrainBatch

        n = self.norms
        V = self.cfg.spring_dim
        B = len(items)
        vox, feats, mlo, mhi, mcls, llo, lhi = [], [], [], [], [], [], []
        lparams = np.zeros((B, self.cfg.lbs_param_count), np.float32)
        slo, shi = np.zeros((B, V), np.float32), np.zeros((B, V), np.float32)
        smask = np.ones((B, V), np.float32)
        has = np.zeros((3, B), np.float32)
        seeds = []
        for b, (sample, seed, where) in enumerate(items):
            self.check(sample, where)
            idx = sample.grid.indices
            K = idx.shape[0]
            vox.append(np.concatenate([np.full((K, 1), b), idx], axis=1))
            feats.append(sample.grid.features.astype(np.float32))
            m = sample.mpm
            mlo.append(np.stack([n["E"].encode(m.E_min), n["density"].encode(m.density_min), n["nu"].encode(m.nu_min)], 1))
            mhi.append(np.stack([n["E"].encode(m.E_max), n["density"].encode(m.density_max), n["nu"].encode(m.nu_max)], 1))
            mcls.append(m.material.astype(np.int64))
            has[0, b] = 1.0
            if sample.lbs is not None:
                L = sample.lbs
                llo.append(np.stack([n["E"].encode(L.E_min), n["nu"].encode(L.nu_min)], 1))
                lhi.append(np.stack([n["E"].encode(L.E_max), n["nu"].encode(L.nu_max)], 1))
                lparams[b] = n["lbs_params"].encode(L.params)
                has[1, b] = 1.0
            else:
                llo.append(np.zeros((K, 2)))
                lhi.append(np.zeros((K, 2)))
            if sample.spring is not None:
                S = sample.spring
                na = S.stiffness_min.size  # fewer than N_a on a solid too small or thin for more: padded, masked
                slo[b, :na], shi[b, :na] = n["stiffness"].encode(S.stiffness_min), n["stiffness"].encode(S.stiffness_max)
                smask[b, na:-1] = 0.0
                slo[b, -1], shi[b, -1] = n["softness"].encode(S.softness_min), n["softness"].encode(S.softness_max)
                has[2, b] = 1.0
            seeds.append(seed)

        def t(x, dtype=torch.float32):
            return torch.from_numpy(np.ascontiguousarray(np.concatenate(x) if isinstance(x, list) else x)).to(dtype)

        return TrainBatch(t(vox, torch.int64), t(feats), B, self.cfg.grid_resolution, t(mlo), t(mhi),
                          t(mcls, torch.int64), t(llo), t(lhi), t(lparams), t(slo), t(shi),
                          t(has[0]), t(has[1]), t(has[2]), seeds, t(smask))


class StepSamples:
    """The objects this process trains on, in order: item j = (sample, seed, file) of global batch
    position ``rank * local + j % local`` at step ``start + j // local``.  Epoch e visits the files in
    a permutation seeded by (seed, e)."""

    def __init__(self, files, start_step: int, steps: int, batch: int, rank: int, world: int, seed: int,
                 cache_limit: int):
        self.files = [str(f) for f in files]
        self.start, self.steps, self.batch, self.rank, self.seed = start_step, steps, batch, rank, seed
        self.local = batch // world
        self.cache_limit = cache_limit
        self._cache: dict = {}
        self._cached_bytes = 0
        self._perms: dict = {}

    def __len__(self):
        return max(0, self.steps - self.start) * self.local

    def position(self, j: int):
        step = self.start + j // self.local
        pos = self.rank * self.local + j % self.local
        return step, pos

    def file_index(self, step: int, pos: int) -> int:
        import numpy as np

        i = step * self.batch + pos
        n = len(self.files)
        epoch = i // n
        if epoch not in self._perms:
            self._perms = {epoch: np.random.default_rng([self.seed, epoch]).permutation(n)}
        return int(self._perms[epoch][i % n])

    def __getitem__(self, j: int):
        from ..core.model.objective import sample_seed
        from .sample_format import TrainingSample

        step, pos = self.position(j)
        path = self.files[self.file_index(step, pos)]
        sample = self._cache.get(path)
        if sample is None:
            sample = TrainingSample.load(path)
            size = sample.grid.features.nbytes
            if len(self._cache) < self.cache_limit and self._cached_bytes + size <= CACHE_BYTES:
                self._cache[path] = sample
                self._cached_bytes += size
        return sample, sample_seed(self.seed, step, pos), path


# ---------------------------------------------------------------------------- set-up helpers
def _distributed():
    """(rank, world size, local rank) from torchrun's environment (1 process without it)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    return rank, world, local


def _device(s: TrainSettings, local_rank: int, world: int):
    import torch

    from ..core.model.inference import resolve_torch_device

    dev = resolve_torch_device(s.device)
    if dev.type == "cuda" and world > 1:
        dev = torch.device("cuda", local_rank)
        torch.cuda.set_device(dev)
    return dev


def _precision(s: TrainSettings, dev) -> str:
    import torch

    if s.precision not in PRECISIONS:
        raise UserError(f"--precision must be one of {', '.join(PRECISIONS)}, got {s.precision!r}")
    if s.precision == "auto":
        return "bf16" if dev.type == "cuda" and torch.cuda.is_bf16_supported() else "fp32"
    return s.precision


def build_config(s: TrainSettings, first_sample, files, anchor_counts: dict | None = None):
    """The model config for a new run: preset + overrides, input sizes from the data (``anchor_counts``:
    :func:`spring_anchor_counts` of ``files`` when already read)."""
    from ..core.model.config import preset
    from ..core.model.normalization import fitted_norm, normalisation_to_dict

    g = first_sample.grid
    base = dict(feature_model=g.feature_model, feature_dim=g.dim, grid_resolution=g.geometry.resolution)
    counts = spring_anchor_counts(files) if anchor_counts is None else anchor_counts
    if counts:  # the network's N_a: a solid too small or thin for it has fewer anchors (its targets are padded)
        base["spring_anchors"] = max(counts)
    base.update(s.model)
    cfg = preset(s.preset, **base)
    if s.fit_normalisation:
        import numpy as np

        k, eta, params = [], [], []
        for f in files[: min(len(files), 256)]:  # read only the target arrays (not the features)
            with np.load(f, allow_pickle=False) as z:
                if "spring_stiffness_min" in z.files:
                    k += [z["spring_stiffness_min"], z["spring_stiffness_max"]]
                    eta += [float(z["spring_softness_min"]), float(z["spring_softness_max"])]
                if "lbs_params" in z.files:
                    params.append(z["lbs_params"])
        norms = cfg.norms()
        if k:
            norms["stiffness"] = fitted_norm(norms["stiffness"], np.concatenate(k))
            norms["softness"] = fitted_norm(norms["softness"], np.asarray(eta))
        if params:
            norms["lbs_params"] = fitted_norm(norms["lbs_params"], np.concatenate(params))
        cfg = cfg.replace(normalisation=normalisation_to_dict(norms))
    return cfg


def spring_anchor_counts(files) -> dict:
    """{anchor count: [object ids]} of the samples' spring targets; reads only those arrays, not the features."""
    import numpy as np

    counts: dict = {}
    for f in files:
        with np.load(f, allow_pickle=False) as z:
            if "spring_stiffness_min" in z.files:
                counts.setdefault(int(z["spring_stiffness_min"].size), []).append(Path(f).stem)
    return counts


def check_spring_anchors(counts: dict, expected: int, data_dir=None) -> None:
    """Refuse a training set whose spring targets were made with other network settings than ``expected`` anchors,
    naming the counts found: one with more anchors than the model has, or any short of them while the dataset's
    card (``data_dir``/dataset.json) says its ground truth is mixed (a rebuild under way,
    :mod:`.ground_truth_rebuild`).  Otherwise a count below ``expected`` is a solid too small or thin for more
    anchors (:func:`unipixie.solvers.spring_mass_network.select_anchors`), trained on its own anchors.
    ``counts``: :func:`spring_anchor_counts` of the training files."""
    other = {n: ids for n, ids in counts.items() if n != expected}
    if not _ground_truth_mixed(data_dir):
        other = {n: ids for n, ids in other.items() if n > expected}
    if other:
        found = "; ".join(f"{len(ids)} with {n} (e.g. {ids[0]})" for n, ids in sorted(other.items()))
        raise UserError(f"the training samples' spring targets have different anchor counts: the model expects "
                        f"{expected} spring anchors, {found} — finish the dataset's ground-truth rebuild (unipixie "
                        "dataset ground-truth) or train on one kind")


def _ground_truth_mixed(data_dir) -> bool:
    """Whether the dataset card in ``data_dir`` lists more than one ground truth (False without a card)."""
    import json

    card = Path(data_dir) / "dataset.json" if data_dir is not None else None
    if card is None or not card.is_file():
        return False
    try:
        return len(json.loads(card.read_text()).get("ground_truth_settings") or []) > 1
    except (OSError, ValueError, AttributeError):
        raise UserError(f"{card} is not a readable dataset card; rebuild it with 'unipixie dataset card'") from None


def _save(out: Path, objective, optimizer, step: int, s: TrainSettings, fingerprint: str, stats: dict) -> None:
    import torch

    from ..core.model.checkpoint import save_model, save_training_state
    from ..core.model.objective import SamplingSettings

    dtype = {"float32": None, "bfloat16": torch.bfloat16, "float16": torch.float16}[s.save_dtype]
    # the flow-time distribution goes with the weights: the sampler steps through its quantiles
    sampling = asdict(SamplingSettings(**s.sampling))
    save_model(objective.model, out, dtype=dtype, info={"step": step, "data_fingerprint": fingerprint,
                                                          "preset": s.preset, "sampling": sampling})
    save_training_state(out, optimizer, step, asdict(s), fingerprint, extra=stats)
    recipe = Path(s.data) / "feature_recipe.json"   # how the training objects were rendered (training/pack.py)
    if recipe.is_file():
        copy_file(recipe, Path(out) / "feature_recipe.json")


# ---------------------------------------------------------------------------- the loop
def train(s: TrainSettings, progress=None) -> dict:
    """Run (or resume) training; returns statistics (losses per step, samples/s, final step)."""
    import torch
    import torch.distributed as dist

    from ..core.model.checkpoint import is_checkpoint, load_model, load_training_state, read_config
    from ..core.model.network import UniPixieModel
    from ..core.model.objective import LossWeights, SamplingSettings, TrainingObjective, make_draws
    from ..core.progress import Progress
    from .sample_format import TrainingSample, data_fingerprint, list_samples

    if s.steps < 1 or s.batch < 1:
        raise UserError("--steps and --batch must be positive")
    if s.save_dtype not in ("float32", "bfloat16", "float16"):
        raise UserError(f"--save-dtype must be float32, bfloat16 or float16, got {s.save_dtype!r}")
    rank, world, local_rank = _distributed()
    if s.batch % world:
        raise UserError(f"--batch {s.batch} must be a multiple of the number of processes ({world})")
    dev = _device(s, local_rank, world)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if dev.type == "cuda" else "gloo")
    precision = _precision(s, dev)
    out = Path(s.out)
    files = list_samples(s.data, "train")
    fingerprint = data_fingerprint(files)
    first = TrainingSample.load(files[0])
    anchor_counts = spring_anchor_counts(files)  # read once: the model's N_a and the check below

    start_step = 0
    if is_checkpoint(out) and not s.resume:
        raise UserError(f"{out} already holds a checkpoint; pass --resume to continue it or choose another --out")
    if s.resume:
        if not is_checkpoint(out):
            raise UserError(f"--resume: no checkpoint in {out} to continue")
        cfg = read_config(out)
        requested = build_config(replace(s, fit_normalisation=False), first, files, anchor_counts)
        diff = cfg.differences(requested, ignore=("normalisation",) if s.fit_normalisation else ())
        if diff:
            raise UserError(f"--resume: the checkpoint in {out} was made with another model config: "
                            + "; ".join(diff) + " (use the original --preset/--set options)")
        model, _ = load_model(out, device="cpu", expect=cfg)
    else:
        cfg = build_config(s, first, files, anchor_counts)
        torch.manual_seed(s.seed)
        model = UniPixieModel(cfg)
    Collate(cfg).check(first, str(files[0]))
    check_spring_anchors(anchor_counts, cfg.spring_anchors, s.data)
    model.to(dev).train()
    weights = LossWeights(**s.loss)
    sampling = SamplingSettings(**s.sampling)
    objective = TrainingObjective(model, weights)
    optimizer = torch.optim.AdamW(model.parameters(), lr=s.lr, weight_decay=s.weight_decay)
    if s.resume:
        doc = load_training_state(out, optimizer)
        start_step = int(doc["step"])
        if doc.get("data_fingerprint") != fingerprint and not s.allow_new_data:
            raise UserError(f"--resume: the data in {s.data} differs from the data the checkpoint was trained on "
                            f"(fingerprint {fingerprint} vs {doc.get('data_fingerprint')}); pass --allow-new-data to "
                            "continue on the new data")
    runner = objective
    if world > 1:
        from torch.nn.parallel import DistributedDataParallel

        runner = DistributedDataParallel(objective, device_ids=[dev.index] if dev.type == "cuda" else None)

    data = StepSamples(files, start_step, s.steps, s.batch, rank, world, s.seed, s.cache_samples)
    local = s.batch // world
    loader = torch.utils.data.DataLoader(data, batch_size=local, shuffle=False, num_workers=s.workers,
                                         collate_fn=Collate(cfg), pin_memory=dev.type == "cuda",
                                         persistent_workers=False)
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    own_progress = progress is None
    if progress is None:
        progress = Progress(total=max(1, s.steps - start_step), description="train", show_bar=rank == 0)
    losses, t_measure, n_measure = [], None, 0
    feature_noise = weights.consistency > 0
    autocast = (torch.autocast(device_type=dev.type, dtype=torch.bfloat16) if precision == "bf16"
                else torch.autocast(device_type=dev.type, enabled=False))
    log = open(out / LOG_FILE, "a") if rank == 0 else None
    step = start_step
    t0 = time.perf_counter()
    try:
        for step_offset, batch in enumerate(loader):
            step = start_step + step_offset
            batch = batch.to(dev)
            draws = make_draws(batch, cfg.spring_dim, feature_noise, sampling, dev)
            lr = learning_rate(step, s)
            for group in optimizer.param_groups:
                group["lr"] = lr
            with autocast:
                parts = runner(batch, draws)
            parts["total"].backward()
            if s.dump_gradients and step == start_step:
                _dump_gradients(model, s.dump_gradients, rank, parts)
            if s.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), s.grad_clip)
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
            total = parts["total"].detach()
            if world > 1:
                dist.all_reduce(total)
                total = total / world
            loss = float(total)
            if not math.isfinite(loss):
                raise UserError(f"training diverged at step {step} (loss {loss}); lower --lr or check the data")
            losses.append(loss)
            done = step + 1
            if step_offset == 1:
                if dev.type == "cuda":
                    torch.cuda.synchronize(dev)
                t_measure, n_measure = time.perf_counter(), 0
            elif t_measure is not None:
                n_measure += s.batch
            if log is not None and (done % s.log_every == 0 or done == s.steps):
                rec = {"step": done, "lr": lr, "loss": loss, **{k: float(v) for k, v in parts.items() if k != "total"}}
                log.write(json.dumps(rec) + "\n")
                log.flush()
            progress.step(1, f"loss {loss:.4g}")
            stopping = s.stop_after is not None and step_offset + 1 >= s.stop_after
            if done % s.save_every == 0 or done == s.steps or stopping:
                if rank == 0:
                    _save(out, objective, optimizer, done, s, fingerprint, {"last_loss": loss})
                if world > 1:
                    dist.barrier()
            if stopping:
                break
    except (CancelledError, KeyboardInterrupt):
        saved = start_step + len(losses)
        if world == 1 and saved > start_step:  # keep what was trained: resumable with --resume
            _save(out, objective, optimizer, saved, s, fingerprint, {"cancelled_at": saved})
        raise
    finally:
        if log is not None:
            log.close()
        if own_progress:
            progress.close()
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    elapsed = time.perf_counter() - t0
    rate = n_measure / (time.perf_counter() - t_measure) if t_measure is not None and n_measure else (
        len(losses) * s.batch / elapsed if elapsed > 0 else 0.0)
    stats = {"start_step": start_step, "final_step": start_step + len(losses), "losses": losses,
             "samples_per_s": rate, "seconds": elapsed, "world_size": world, "device": str(dev),
             "precision": precision, "parameters": sum(p.numel() for p in model.parameters())}
    if s.stats_out and rank == 0:
        write_json(s.stats_out, stats, indent=1)
    if world > 1:
        dist.barrier()
    return stats


def _dump_gradients(model, path, rank: int, parts) -> None:
    """Write the (data-parallel averaged) gradients of the first step to ``path`` (rank 0)."""
    if rank != 0:
        return
    import torch
    from safetensors.torch import save_file

    grads = {name: (p.grad.detach().float().cpu().contiguous() if p.grad is not None else torch.zeros_like(p, device="cpu"))
             for name, p in model.named_parameters()}
    with atomic_path(path) as tmp:
        save_file(grads, str(tmp), metadata={"loss": repr(float(parts["total"].detach()))})


# ---------------------------------------------------------------------------- command line
def add_arguments(p: argparse.ArgumentParser) -> None:
    """The training options (shared by ``unipixie train`` and ``python -m unipixie.training.train``)."""
    p.add_argument("--data", required=True, metavar="DIR", help="dataset directory of training samples (*.npz)")
    p.add_argument("--out", required=True, metavar="DIR", help="checkpoint directory (written every --save-every steps)")
    p.add_argument("--steps", type=int, default=1000, help="total optimiser steps (default 1000)")
    p.add_argument("--batch", type=int, default=1, help="global batch size in objects, split over processes (default 1)")
    p.add_argument("--resume", action="store_true", help="continue the run saved in --out")
    p.add_argument("--preset", default="paper", help="model size preset: paper (default), small, tiny")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                   help="override a model config field, e.g. --set width=256 (repeatable)")
    p.add_argument("--lr", type=float, default=5e-5, help="peak learning rate (AdamW; default 5e-5)")
    p.add_argument("--weight-decay", type=float, default=0.01)
    p.add_argument("--warmup", type=int, default=None, help="warm-up steps (default min(3000, steps/10))")
    p.add_argument("--grad-clip", type=float, default=1.0)
    p.add_argument("--precision", choices=PRECISIONS, default="auto", help="auto = bf16 on GPUs that have it, else fp32")
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (each torchrun process uses its LOCAL_RANK GPU)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save-every", type=int, default=500)
    p.add_argument("--log-every", type=int, default=10)
    p.add_argument("--workers", type=int, default=0, help="data-loading worker processes per training process")
    p.add_argument("--fixed-normalisation", action="store_true",
                   help="use the default normalisation constants for spring stiffness/softness and LBS parameters "
                        "instead of fitting them to the data")
    p.add_argument("--allow-new-data", action="store_true", help="with --resume: accept a changed dataset")
    p.add_argument("--save-dtype", choices=("float32", "bfloat16", "float16"), default="float32",
                   help="dtype of the saved model weights (bfloat16 halves a model to ship)")
    p.add_argument("--stop-after", type=int, default=None, metavar="N",
                   help="stop and save after N steps of this invocation (continue later with --resume)")
    p.add_argument("--stats-out", metavar="JSON", help="write run statistics (losses, samples/s) to this file")
    p.add_argument("--dump-gradients", metavar="FILE",
                   help="write the first step's averaged gradients (safetensors) to check a distributed set-up")


def _parse_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def settings_from_args(args) -> TrainSettings:
    overrides = {}
    for item in args.overrides:
        if "=" not in item:
            raise UserError(f"--set expects FIELD=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        overrides[k.strip()] = _parse_value(v.strip())
    return TrainSettings(data=args.data, out=args.out, steps=args.steps, batch=args.batch, lr=args.lr,
                         weight_decay=args.weight_decay, warmup=args.warmup, grad_clip=args.grad_clip,
                         precision=args.precision, device=args.device, seed=args.seed, save_every=args.save_every,
                         log_every=args.log_every, workers=args.workers, preset=args.preset, model=overrides,
                         fit_normalisation=not args.fixed_normalisation, resume=args.resume,
                         allow_new_data=args.allow_new_data, save_dtype=args.save_dtype,
                         dump_gradients=args.dump_gradients, stats_out=args.stats_out, stop_after=args.stop_after)


def report(stats: dict, out: str) -> str:
    losses = stats["losses"]
    first = f"{losses[0]:.4g}" if losses else "-"
    last = f"{losses[-1]:.4g}" if losses else "-"
    return (f"trained steps {stats['start_step']}..{stats['final_step']} on {stats['device']} ({stats['precision']}, "
            f"{stats['world_size']} process(es)): loss {first} -> {last}, {stats['samples_per_s']:.3g} samples/s; "
            f"checkpoint in {out}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m unipixie.training.train", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        s = settings_from_args(args)
        stats = train(s)
    except UserError as exc:
        print(f"train: error: {exc}", file=sys.stderr)
        return exc.exit_code
    finally:
        try:
            import torch.distributed as dist

            if dist.is_available() and dist.is_initialized():
                dist.destroy_process_group()
        except ImportError:
            pass
    if _distributed()[0] == 0:
        print(report(stats, s.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
