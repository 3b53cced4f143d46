"""``unipixie evaluate CHECKPOINT --data DIR --split test --out DIR``: the paper's tables on a dataset split."""

from __future__ import annotations

NAME = "evaluate"
HELP = "evaluate a model (and baselines) on a dataset split: property errors, solver fidelity, a figure"
EXAMPLES = """  unipixie evaluate models/default --data data/pmv --split test --out eval/default
  unipixie evaluate runs/main --data data/pmv --out eval/main --baseline runs/unet_det --baseline runs/unet_ddpm
  unipixie evaluate runs/main --data data/pmv --out eval/quick --simulate-objects 0     # Table 1 only
  unipixie evaluate none --data data/pmv --out eval/unet --baseline runs/unet_det        # baselines only"""


def add_arguments(p):
    from ...core.commands import _common

    p.add_argument("checkpoint", metavar="CHECKPOINT",
                   help="UniPixie checkpoint directory (config.json + model.safetensors); 'none' for baselines only")
    p.add_argument("--data", required=True, metavar="DIR", help="dataset directory (split.json + samples/ + objects/)")
    p.add_argument("--split", default="test", help="split to evaluate (default test)")
    p.add_argument("--out", required=True, metavar="DIR", help="report directory (report.json, report.md, figure, "
                                                               "raw predictions)")
    p.add_argument("--baseline", action="append", default=[], metavar="DIR",
                   help="a baseline checkpoint (python training/baselines.py train ...); repeatable")
    p.add_argument("--alphas", default="0,0.5,1", help="α values (default 0,0.5,1)")
    p.add_argument("--device", type=_common.device, default="auto", help="torch device of the models (default auto)")
    p.add_argument("--solver-device", type=_common.device, default="cpu",
                   help="Warp device of the Table 2 simulations (default cpu)")
    p.add_argument("--seed", type=_common.seed, default=0, help="noise seed of the generative models (default 0)")
    p.add_argument("--max-objects", type=int, default=0, help="evaluate only the first N objects (default all)")
    p.add_argument("--simulate-objects", type=int, default=10,
                   help="objects of the solver-fidelity table (default 10, as the paper; 0 = no simulations)")
    p.add_argument("--no-fitters", action="store_true", help="skip the specialist test-time fitters in Table 2")
    p.add_argument("--render-frames", type=int, default=3, help="rendered frames per α for PSNR/SSIM (0 = none)")
    p.add_argument("--render-views", type=_common.positive_int, default=2, help="views per rendered frame (default 2)")
    p.add_argument("--no-mean-prediction", action="store_true",
                   help="do not also evaluate 'unipixie_mean' (the model's one-step conditional-mean prediction)")
    p.add_argument("--average-samples", default="", metavar="K[,K...]",
                   help="also evaluate 'unipixie_avgK': the average of K draws of the model (the Monte-Carlo "
                        "conditional mean), for each K given (e.g. 2,4,8; default none)")
    p.add_argument("--temperatures", default="1", metavar="T[,T...]",
                   help="also evaluate 'unipixie_tT': one draw at each sampler temperature T in [0, 1] other than the "
                        "default's (1: the paper's sampler, a draw from the model; default 1; '' for none)")
    p.add_argument("--render-resolution", type=_common.positive_int, default=128, help="render size (default 128)")
    p.add_argument("--no-oracle", action="store_true",
                   help="do not score the reference predictors (procedural datasets only: the best any model can "
                        "reach on the labels, from the generator's own priors; training/oracle.py)")
    p.add_argument("--oracle-draws", type=int, default=1000,
                   help="annotations drawn per object for the reference predictors (default 1000, at least 10)")


def _comma_list(text: str, option: str, parse, check, what: str) -> tuple:
    """The distinct values of a comma-separated option, in order, each parsed and checked (a UserError names the
    option)."""
    from ...core.errors import UserError

    try:
        values = tuple(dict.fromkeys(parse(x) for x in text.split(",") if x.strip()))
    except ValueError:
        raise UserError(f"{option} {text!r}: expected {what} separated by commas") from None
    return tuple(check(v) for v in values)


def run(args) -> int:
    from pathlib import Path

    from ...core.errors import UserError
    from ...core.progress import Progress

    try:
        alphas = tuple(float(a) for a in args.alphas.split(","))
    except ValueError:
        raise UserError(f"--alphas {args.alphas!r}: expected numbers separated by commas") from None
    if any(not 0.0 <= a <= 1.0 for a in alphas):
        raise UserError(f"--alphas {args.alphas!r}: values must lie in [0, 1]")
    from ...core.model.inference import check_samples, check_temperature

    average_samples = _comma_list(args.average_samples, "--average-samples", int, check_samples, "whole numbers")
    temperatures = _comma_list(args.temperatures, "--temperatures", float, check_temperature, "numbers in [0, 1]")
    checkpoint = None if args.checkpoint.lower() == "none" else args.checkpoint
    if checkpoint is not None and not Path(checkpoint).is_dir():
        raise UserError(f"checkpoint {checkpoint}: directory not found")
    if args.simulate_objects > 0 and args.render_frames > 0:
        import importlib.util

        import torch._dynamo  # noqa: F401  (triton must be imported before Blender's first render)

        if importlib.util.find_spec("bpy") is None:
            raise UserError("the PSNR/SSIM renders need Blender's 'bpy' module; install it or pass --render-frames 0")
    from ..evaluate import EvalSettings, evaluate

    settings = EvalSettings(alphas=alphas, split=args.split, device=args.device, solver_device=args.solver_device,
                            seed=args.seed, max_objects=args.max_objects, simulate_objects=args.simulate_objects,
                            fitters=not args.no_fitters, render_frames=args.render_frames,
                            render_views=args.render_views, render_resolution=args.render_resolution,
                            mean_prediction=not args.no_mean_prediction, average_samples=average_samples,
                            temperatures=temperatures, oracle=not args.no_oracle,
                            oracle_draws=args.oracle_draws)
    from ..dataset import DatasetDir

    n = len(DatasetDir(args.data).ids(args.split))
    n = min(n, args.max_objects) if args.max_objects else n
    with Progress(total=n, description="evaluate") as progress:
        report = evaluate(checkpoint, args.data, args.out, baselines=args.baseline, settings=settings,
                          progress=progress)
    for name, m in report["methods"].items():
        print(f"{name}: log E MSE {m['logE_mse']:.4f}, log rho MSE {m['logrho_mse']:.4f}, nu MSE {m['nu_mse']:.5f}, "
              f"material {100 * m['material_acc']:.1f} %, {m['runtime_s']:.3f} s")
    for name, b in report["breakdown"]["methods"].items():
        if name in report["methods"] and b["interior_share_pooled"] is not None:
            print(f"{name}: interior voxels carry {100 * b['interior_share_pooled']:.0f} % of the log E squared error "
                  f"(report.md: where the error lies)")
    for name, m in report["references"].items():
        print(f"reference {name}: log E MSE {m['logE_mse']:.4f}, log rho MSE {m['logrho_mse']:.4f}, "
              f"nu MSE {m['nu_mse']:.5f}")
    if report["references_skipped"] and settings.oracle:
        print(f"reference predictors skipped: {report['references_skipped']}")
    print(f"report: {args.out}/report.md and report.json")
    return 0
