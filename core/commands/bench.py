"""``unipixie bench NAME``: run a benchmark, print a table and write benchmarks/NAME.json."""

from __future__ import annotations

import importlib
import pkgutil

NAME = "bench"
HELP = "run a benchmark (mpm, lbs, spring, features, model, diagnose, bake) and record benchmarks/<name>.json"
EXAMPLES = """  unipixie bench mpm --device cpu
  unipixie bench mpm --device cuda --no-record
  unipixie bench model --device cuda"""


def _benchmarks():
    from .. import benchmarks

    return {i.name: f"{benchmarks.__name__}.{i.name}" for i in pkgutil.iter_modules(benchmarks.__path__)
            if not i.name.startswith("_")}


def add_arguments(p):
    sub = p.add_subparsers(dest="bench_name", metavar="NAME", required=True)
    for name, modname in sorted(_benchmarks().items()):
        mod = importlib.import_module(modname)
        sp = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        sp.add_argument("--no-record", action="store_true", help="print only; do not write benchmarks/<name>.json")
        sp.add_argument("--out", metavar="JSON", help="write to this file instead of benchmarks/<name>.json")
        mod.add_arguments(sp)


def run(args) -> int:
    from .. import benchmarks

    mod = importlib.import_module(_benchmarks()[args.bench_name])
    results = mod.run(args)
    benchmarks.print_table(results)
    if not args.no_record:
        path = benchmarks.record(args.bench_name, results, path=args.out)
        print(f"recorded {len(results)} result(s) in {path}")
    return 0
