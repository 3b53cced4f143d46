"""``unipixie bench model``: inference time of all three heads at 64³ and training throughput.

Inference: the model at the requested preset (default: the paper's sizes) with random weights (the
timing does not depend on the weights), or a trained checkpoint (``--checkpoint DIR``: its own sizes, feature
width and spring anchors, e.g. the shipped ``models/default``), a procedural object with ~30k occupied voxels on a 64³ grid
and D = 768 random features; all three heads with 15 Heun steps, at 1 α and at 11 α's (one batched
pass each).  On CUDA also the peak GPU memory.  Training: samples/s of the full objective (all heads,
latent consistency term) on a synthetic 64³ dataset of that object, in one process and, on a machine
with several GPUs, with torchrun over ``--ddp-procs`` GPUs.
"""

from __future__ import annotations

import json
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

if __package__ in (None, ""):  # run as a file with only torch + numpy + safetensors (see standalone.py)
    import runpy

    runpy.run_path(str(Path(__file__).resolve().parents[2] / "standalone.py"))["import_checkout"]()
    __package__ = "unipixie.training.benchmarks"

TRAIN_SCRIPT = Path(__file__).resolve().parents[2] / "training" / "train.py"

HELP = "material model: inference time (all heads, 1 and 11 alphas, 64^3) and training samples/s"


def add_arguments(p):
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (default)")
    p.add_argument("--preset", default="paper", help="model size preset (default paper)")
    p.add_argument("--checkpoint", default=None, metavar="DIR",
                   help="time this trained model instead (its sizes, feature width and spring anchors; --preset and "
                        "--feature-dim are then ignored; inference cases only)")
    p.add_argument("--voxels", type=int, default=30000, help="occupied voxels of the test object (default 30000)")
    p.add_argument("--feature-dim", type=int, default=768, help="feature width D (default 768, CLIP ViT-B/16)")
    p.add_argument("--runs", type=int, default=None, help="timed runs per case (default 5 on GPU, 1 on CPU)")
    p.add_argument("--train-steps", type=int, default=None, help="training steps to time (default 20 GPU / 4 CPU)")
    p.add_argument("--train-batch", type=int, default=None, help="objects per GPU per step (default 2 GPU / 1 CPU)")
    p.add_argument("--ddp-procs", type=int, default=None, help="also time torchrun with this many GPUs (default: all, if > 1)")
    p.add_argument("--cases", default="mpm1,all1,all11,train",
                   help="comma-separated subset of: mpm1 (MPM head, 1 alpha), all1 (all heads, 1 alpha), "
                        "all11 (all heads, 11 alphas), train (training samples/s); default all")


def _device_name(dev) -> str:
    import torch

    from ...solvers.warp_runtime import cpu_description

    return torch.cuda.get_device_name(dev) if dev.type == "cuda" else cpu_description(platform.processor() or "CPU")


def _make_dataset(root: Path, resolution: int, voxels: int, feature_dim: int, anchors: int, count: int):
    from ..synthetic import make_sample, procedural_occupancy

    occ = procedural_occupancy(resolution, voxels)
    root.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        s = make_sample(i, resolution, feature_dim, anchors, feature_model="bench-random", parts=3, occupancy=occ)
        s.save(root / f"{s.object_id}.npz", compress=False)
    return occ


def run(args) -> list[dict]:
    import numpy as np
    import torch

    from ...core.benchmarks import median_time
    from ...core.model.config import HEADS, preset
    from ...core.model.inference import Predictor, resolve_torch_device
    from ...core.model.layout import VoxelBatch
    from ...core.model.network import UniPixieModel
    from ...core.types import FeatureGrid, GridGeometry
    from ..synthetic import procedural_occupancy

    cases = {c.strip() for c in args.cases.split(",") if c.strip()}
    unknown = cases - {"mpm1", "all1", "all11", "train"}
    if unknown:
        from ...core.errors import UserError

        raise UserError(f"unknown --cases {sorted(unknown)}; choose from mpm1, all1, all11, train")
    if args.checkpoint and "train" in cases:
        from ...core.errors import UserError

        raise UserError("--checkpoint times a trained model's inference; the training case times a preset: leave "
                        "'train' out of --cases (e.g. --cases mpm1,all1,all11)")
    dev = resolve_torch_device(args.device)
    gpu = dev.type == "cuda"
    runs = args.runs or (5 if gpu else 1)
    if args.checkpoint:
        predictor = Predictor.load(args.checkpoint, device=str(dev))
        cfg = predictor.cfg
        model = predictor.model
        what = f"checkpoint {Path(args.checkpoint).name} ({cfg.feature_model})"
    else:
        cfg = preset(args.preset, feature_model="bench-random", feature_dim=args.feature_dim, grid_resolution=64)
        torch.manual_seed(0)
        model = UniPixieModel(cfg)
        # random, non-zero weights everywhere (AdaLN-Zero layers start at zero; a trained model's are not)
        with torch.no_grad():
            for name, p in model.named_parameters():
                if p.dim() >= 2 and torch.count_nonzero(p) == 0:
                    p.normal_(0.0, 0.02)
        predictor = Predictor(model, dev)
        what = f"{args.preset} sizes"
    R = int(cfg.grid_resolution)
    occ = procedural_occupancy(R, args.voxels)
    K = int(occ.sum())
    rng = np.random.default_rng(0)
    grid = FeatureGrid(GridGeometry(R, [-0.5] * 3, 1.0 / R), occ,
                       rng.normal(size=(K, cfg.feature_dim)).astype(np.float16), feature_model=cfg.feature_model)
    name = _device_name(dev)
    tokens = int(predictor.model.layout(VoxelBatch.from_grids([occ], [np.zeros((K, 1), np.float32)])).token_valid.sum())
    params = predictor.model.parameter_count()["total"]
    base = (f"{what} ({params / 1e6:.0f}M params, {cfg.spring_anchors} spring anchors), {R}^3, {K} voxels, "
            f"{tokens} patch tokens, D={cfg.feature_dim}")
    print(f"model: {base}; device {name}; {runs} run(s) per case", flush=True)
    results = []

    def timed(alphas, heads, metric, label):
        if gpu:
            torch.cuda.synchronize(dev)
            torch.cuda.reset_peak_memory_stats(dev)
        # GPU: one untimed run per case (kernel selection, allocator); CPU: none (nothing to warm, and slow)
        med, times = median_time(lambda: predictor.predict(grid, alphas, heads=heads), runs=runs, warmup=1 if gpu else 0)
        entry = {"case": f"{label}, {base}", "device": name, "metric": metric, "value": med, "runs": runs,
                 "unit": "s", "times": times}
        results.append(entry)
        print(f"  {metric}: {med:.3f} s", flush=True)
        if gpu:
            peak = torch.cuda.max_memory_allocated(dev) / 2 ** 30
            results.append({"case": f"{label}, {base}", "device": name, "metric": f"peak_gpu_memory_gib_{metric}",
                            "value": peak, "runs": runs, "unit": "GiB"})

    heads = HEADS
    if not gpu:  # allocate once outside the timed runs
        predictor.predict(grid, [0.5], heads=("spring_mass",), steps=1)
    if "mpm1" in cases:
        timed([0.5], ("mpm",), "inference_s_mpm_1alpha", "MPM head, 1 alpha, 15 Heun steps")
    if "all1" in cases:
        timed([0.5], heads, "inference_s_all_heads_1alpha", "all heads, 1 alpha, 15 Heun steps")
    if "all11" in cases:
        timed(list(np.linspace(0, 1, 11)), heads, "inference_s_all_heads_11alpha", "all heads, 11 alphas, 15 Heun steps")
    del predictor, model
    if gpu:
        torch.cuda.empty_cache()
    if "train" not in cases:
        return results

    from ..train import TrainSettings, train

    steps = args.train_steps or (20 if gpu else 4)
    per_gpu = args.train_batch or (2 if gpu else 1)
    with tempfile.TemporaryDirectory(prefix="unipixie-bench-model-") as tmp:
        data = Path(tmp) / "data"
        _make_dataset(data, R, args.voxels, args.feature_dim, cfg.spring_anchors, count=max(4, 2 * per_gpu))
        s = TrainSettings(data=str(data), out=str(Path(tmp) / "run1"), steps=steps, batch=per_gpu,
                          preset=args.preset,
                          device=str(dev), save_every=10 ** 9, log_every=10 ** 9, warmup=1, lr=5e-5)
        stats = train(s)
        label = (f"training, all heads + consistency, batch {per_gpu}, {stats['precision']}, 1 process, "
                 f"{steps - 2} timed steps")
        results.append({"case": f"{label}, {base}", "device": name, "metric": "train_samples_per_s",
                        "value": stats["samples_per_s"], "runs": steps - 2})
        print(f"  train_samples_per_s (1 process): {stats['samples_per_s']:.3g}", flush=True)
        procs = args.ddp_procs if args.ddp_procs is not None else (torch.cuda.device_count() if gpu else 0)
        if procs and procs > 1:
            stats_file = Path(tmp) / "ddp_stats.json"
            cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={procs}",
                   str(TRAIN_SCRIPT), "--data", str(data), "--out", str(Path(tmp) / "run_ddp"),
                   "--steps", str(steps), "--batch", str(per_gpu * procs), "--preset", args.preset,
                   "--device", "cuda" if gpu else "cpu", "--save-every", str(10 ** 9), "--log-every", str(10 ** 9),
                   "--warmup", "1", "--stats-out", str(stats_file)]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0 or not stats_file.is_file():
                print(f"  torchrun with {procs} processes failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}", flush=True)
            else:
                ddp = json.loads(stats_file.read_text())
                results.append({"case": f"training, all heads + consistency, batch {per_gpu} per GPU, {ddp['precision']}, "
                                        f"torchrun {procs} processes, {steps - 2} timed steps, {base}",
                                "device": f"{procs} x {name}" if gpu else name, "metric": "train_samples_per_s",
                                "value": ddp["samples_per_s"], "runs": steps - 2,
                                "vs": {"what": "1 process, same run", "ratio": ddp["samples_per_s"] / stats["samples_per_s"]}})
                print(f"  train_samples_per_s ({procs} processes): {ddp['samples_per_s']:.3g}", flush=True)
    return results


def main(argv=None) -> int:
    """``python training/benchmarks/model.py [--device cuda] ...`` — the same as ``unipixie bench model``."""
    import argparse

    from ...core.benchmarks import print_table, record

    parser = argparse.ArgumentParser(prog="training/benchmarks/model.py", description=HELP)
    parser.add_argument("--no-record", action="store_true", help="print only; do not write benchmarks/model.json")
    parser.add_argument("--out", metavar="JSON", help="write to this file instead of benchmarks/model.json")
    add_arguments(parser)
    args = parser.parse_args(argv)
    results = run(args)
    print_table(results)
    if not args.no_record:
        print(f"recorded {len(results)} result(s) in {record('model', results, path=args.out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
