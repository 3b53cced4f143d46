"""Benchmarks (``unipixie bench <name>``) and the one writer of ``benchmarks/<name>.json``.

Each benchmark is a module ``core/benchmarks/<name>.py`` with ``HELP`` (one
line), ``add_arguments(parser)`` and ``run(args) -> list[dict]`` returning
result entries as ``shared/specs/benchmarks.md`` defines them::

    {"case": "1M particles, jelly, drop", "device": "NVIDIA H100 80GB HBM3",
     "metric": "particle_substeps_per_s", "value": 6.1e8, "runs": 5,
     "vs": {"what": "reference APIC kernel, same run", "ratio": 2.4}}

:func:`record` merges them into the JSON file: an entry replaces an earlier
one only when case, device and metric are the same; everything else is kept.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import statistics
import subprocess
import time
from pathlib import Path
from typing import Callable, Iterable

REPO_ROOT = Path(__file__).resolve().parents[2]


def results_dir() -> Path:
    """``benchmarks/`` of the source checkout (``UNIPIXIE_BENCH_DIR`` overrides)."""
    d = Path(os.environ.get("UNIPIXIE_BENCH_DIR") or (REPO_ROOT / "benchmarks"))
    d.mkdir(parents=True, exist_ok=True)
    return d


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True,
                              text=True, timeout=10).stdout.strip() or "unknown"
    except Exception:
        return "unknown"


def record(name: str, results: Iterable[dict], path: Path | None = None) -> Path:
    """Merge ``results`` into ``benchmarks/<name>.json`` (see module docstring); returns the path."""
    path = Path(path) if path else results_dir() / f"{name}.json"
    old = {"benchmark": name, "results": []}
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except json.JSONDecodeError:
            pass
    entries = list(old.get("results", []))
    for r in results:
        missing = {"case", "device", "metric", "value", "runs"} - set(r)
        if missing:
            raise ValueError(f"benchmark entry lacks {sorted(missing)}: {r}")
        entries = [e for e in entries if (e.get("case"), e.get("device"), e.get("metric"))
                   != (r["case"], r["device"], r["metric"])]
        entries.append(dict(r))
    doc = {"benchmark": name, "commit": git_commit(), "date": _dt.date.today().isoformat(), "results": entries}
    path.write_text(json.dumps(doc, indent=2) + "\n")
    return path


def median_time(fn: Callable[[], object], runs: int = 5, warmup: int = 1) -> tuple[float, list[float]]:
    """Median wall time in seconds of ``fn()`` over ``runs`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def print_table(results: list[dict]) -> None:
    if not results:
        print("(no results)")
        return
    rows = [(r["case"], r["device"], r["metric"], f"{r['value']:.4g}", str(r["runs"]),
             (f"x{r['vs']['ratio']:.2f} vs {r['vs']['what']}" if r.get("vs") else "")) for r in results]
    headers = ("case", "device", "metric", "value", "runs", "comparison")
    widths = [max(len(h), *(len(row[i]) for row in rows)) for i, h in enumerate(headers)]
    print("  ".join(h.ljust(w) for h, w in zip(headers, widths)))
    for row in rows:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths)))
