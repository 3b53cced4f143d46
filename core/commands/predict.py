"""``unipixie predict``: material fields, LBS and spring-mass parameters for a feature grid."""

from __future__ import annotations

import argparse

from ...solvers.registry import SOLVER_NAMES
from ._common import device, existing_file, positive_int, unit_interval
from ._common import seed as seed_type

NAME = "predict"
HELP = "predict materials (MPM field, LBS parameters, spring-mass stiffness) for a feature grid at one or more alpha values"
EXAMPLES = """  unipixie predict grid.npz --checkpoint runs/base --alpha 0.5 --out pred/
  unipixie predict grid.npz --alphas 0,0.5,1 --heads mpm --out pred/
  unipixie predict grid.npz --sweep 11 --out pred/       # the cached slider sweep"""


def _alphas(text: str) -> list:
    try:
        return [unit_interval(x) for x in text.split(",") if x.strip()]
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"--alphas: {exc}") from None


def add_arguments(p):
    p.add_argument("grid", type=existing_file, metavar="GRID.npz", help="feature grid (unipixie.feature_grid/1)")
    p.add_argument("--checkpoint", metavar="DIR", help="checkpoint directory (default: the shipped model)")
    p.add_argument("--alpha", type=unit_interval, default=None, help="one alpha in [0, 1] (soft to stiff; default 0.5)")
    p.add_argument("--alphas", type=_alphas, default=None, metavar="A,B,...", help="several alphas, predicted in one pass")
    p.add_argument("--sweep", type=positive_int, default=None, metavar="K", help="predict K evenly spaced alphas and write the cached sweep")
    p.add_argument("--heads", default=",".join(SOLVER_NAMES),
                   help=f"comma-separated: {', '.join(SOLVER_NAMES)} (default all)")
    p.add_argument("--seed", type=seed_type, default=0, help="noise seed (same seed, same result)")
    p.add_argument("--steps", type=positive_int, default=None, help="Heun steps, 1 or more (default 15)")
    p.add_argument("--samples", type=positive_int, default=1, metavar="K",
                   help="average K draws (seeds SEED … SEED+K−1) in log units: the conditional mean, the least "
                        "squared error, at K times the cost (default 1: one draw)")
    p.add_argument("--temperature", type=float, default=None, metavar="T",
                   help="the MPM and LBS heads' starting-noise scale in [0, 1]: 0 the deterministic path (the "
                        "default; --seed then only sets the spring head's draw), 1 a draw from the model (the paper's "
                        "sampler; --samples K > 1 averages K such draws)")
    p.add_argument("--device", type=device, default="auto")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")


def run(args) -> int:
    from pathlib import Path

    from ..atomic_io import OutputLock, check_writable, refuse_overwriting_inputs, write_error
    from ..errors import UserError
    from ..model.inference import DEFAULT_STEPS, DEFAULT_TEMPERATURE, Predictor, canonical_heads, check_temperature
    from ..types import FeatureGrid

    chosen = [x is not None for x in (args.alpha, args.alphas, args.sweep)]
    if sum(chosen) > 1:
        raise UserError("give only one of --alpha, --alphas and --sweep")
    heads = canonical_heads(args.heads)
    steps = args.steps if args.steps is not None else DEFAULT_STEPS
    if args.temperature is None:  # averaging draws needs draws: K > 1 samples the model (temperature 1)
        args.temperature = 1.0 if args.samples > 1 else DEFAULT_TEMPERATURE
    args.temperature = check_temperature(args.temperature)
    out = Path(args.out).expanduser()
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {args.out} is an existing file; --out names a folder for the prediction files")
    check_writable(out, directory=True, what="output folder")
    alphas = args.alphas if args.alphas is not None else [0.5 if args.alpha is None else args.alpha]
    names = ["alpha_sweep.npz"] if args.sweep is not None else ["prediction.json"] + [
        f"{kind}_a{a:.3f}.npz" for a in alphas for kind in ("material_field", "lbs", "spring")]
    for name in names:  # an existing output that is (a link to) the grid would overwrite it
        refuse_overwriting_inputs(out / name, [args.grid], what="output file")
    grid = FeatureGrid.load(args.grid)
    predictor = Predictor.load(args.checkpoint, device=args.device)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise write_error(out, exc, "create the output folder") from None
    with OutputLock(out / "prediction.json", "output folder"):  # a second run into the same folder is refused
        return _predict(args, out, grid, predictor, heads, steps)


def _predict(args, out, grid, predictor, heads, steps) -> int:
    import numpy as np

    from ..atomic_io import save_npz, write_json
    from ..model.sweep import predict_sweep
    from ..progress import Progress

    with Progress(total=1.0, description="predict") as progress:
        if args.sweep is not None:
            sweep = predict_sweep(predictor, grid, count=args.sweep, seed=args.seed, heads=heads, steps=steps,
                                  progress=progress, samples=args.samples, temperature=args.temperature)
            path = sweep.save(out / "alpha_sweep.npz")
            print(f"wrote the {len(sweep.alphas)}-value alpha sweep to {path}")
            return 0
        alphas = args.alphas if args.alphas is not None else [0.5 if args.alpha is None else args.alpha]  # as checked
        pred = predictor.predict(grid, alphas, heads=heads, seed=args.seed, steps=steps, progress=progress,
                                 samples=args.samples, temperature=args.temperature)
    summary = {"checkpoint": predictor.checkpoint, "grid": str(args.grid), "seed": args.seed, "steps": steps,
               "samples": args.samples, "temperature": args.temperature,
               "seconds": pred.seconds, "device": str(predictor.device), "alphas": []}
    for i, a in enumerate(pred.alphas):
        tag = f"a{a:.3f}"
        entry = {"alpha": float(a)}
        if pred.mpm is not None:
            m = pred.mpm[i]
            m.save(out / f"material_field_{tag}.npz")
            logE = np.log10(m.E)
            entry["mpm"] = {"file": f"material_field_{tag}.npz", "mean_log10_E": float(logE.mean()),
                            "median_E_Pa": float(np.median(m.E)), "mean_density": float(m.density.mean()),
                            "mean_nu": float(m.nu.mean()),
                            "classes": {int(c): int(n) for c, n in zip(*np.unique(m.material, return_counts=True))}}
        if pred.lbs is not None:
            b = pred.lbs[i]
            save_npz(out / f"lbs_{tag}.npz", format="unipixie.lbs_prediction/1", alpha=a, params=b.params,
                                E=b.E, nu=b.nu, occupancy=np.packbits(grid.occupancy.ravel()))
            entry["lbs"] = {"file": f"lbs_{tag}.npz", "median_E_Pa": float(np.median(b.E))}
        if pred.spring_mass is not None:
            s = pred.spring_mass[i]
            save_npz(out / f"spring_{tag}.npz", format="unipixie.spring_prediction/1", alpha=a,
                                stiffness=s.stiffness, softness=np.float64(s.softness))
            entry["spring_mass"] = {"file": f"spring_{tag}.npz", "median_stiffness": float(np.median(s.stiffness)),
                                    "softness": s.softness}
        summary["alphas"].append(entry)
    write_json(out / "prediction.json", summary)
    for e in summary["alphas"]:
        line = f"alpha {e['alpha']:.3f}:"
        if "mpm" in e:
            line += f" median E {e['mpm']['median_E_Pa']:.3g} Pa, mean density {e['mpm']['mean_density']:.4g} kg/m^3"
        if "spring_mass" in e:
            line += f", softness {e['spring_mass']['softness']:.3g}"
        print(line)
    print(f"predicted {len(pred.alphas)} alpha value(s) in {pred.seconds:.2f} s on {predictor.device}; files in {out}")
    return 0
