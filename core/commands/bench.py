"""``unipixie bench NAME``: run a benchmark, print a table and write benchmarks/NAME.json."""

from __future__ import annotations

import importlib

NAME = "bench"
HELP = "run a benchmark (mpm, lbs, spring, features, model, diagnose, bake, fidelity, objects, demo_plant) and record benchmarks/<name>.json"
EXAMPLES = """  unipixie bench mpm --device cpu
  unipixie bench mpm --device cuda --no-record
  unipixie bench model --device cuda"""


LAYERED = True  # add_arguments gets the command line's layers: each may have a `benchmarks` package


def _benchmarks(layers=None):
    """``{name: dotted module}`` of the benchmarks in the layers' ``benchmarks`` packages
    (:mod:`unipixie.core.benchmarks`; ``bench model`` is in :mod:`unipixie.training.benchmarks`)."""
    from ..cli import CORE_LAYERS, layer_modules

    return layer_modules(layers or CORE_LAYERS, "benchmarks")


def add_arguments(p, layers=None):
    benchmarks = _benchmarks(layers)
    p.set_defaults(bench_modules=benchmarks)
    sub = p.add_subparsers(dest="bench_name", metavar="NAME", required=True)
    for name, modname in sorted(benchmarks.items()):
        mod = importlib.import_module(modname)
        sp = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        sp.add_argument("--no-record", action="store_true", help="print only; do not write benchmarks/<name>.json")
        sp.add_argument("--out", metavar="JSON", help="write to this file instead of benchmarks/<name>.json")
        mod.add_arguments(sp)


def run(args) -> int:
    from .. import benchmarks

    mod = importlib.import_module((getattr(args, "bench_modules", None) or _benchmarks())[args.bench_name])
    results = mod.run(args)
    if not results:             # a benchmark that only prepared something (bench demo_plant --export)
        return 0
    benchmarks.print_table(results)
    if not args.no_record:
        path = benchmarks.record(args.bench_name, results, path=args.out)
        print(f"recorded {len(results)} result(s) in {path}")
    return 0
