"""The evaluation's report files: ``report.json`` and its Markdown rendering ``report.md`` (:mod:`.evaluate`)."""

from __future__ import annotations

import json
from pathlib import Path


def write_report(out, report: dict) -> None:
    """Write ``out/report.json`` and ``out/report.md`` (atomically, each)."""
    from ..core.atomic_io import json_default, write_text

    out = Path(out)
    write_text(out / "report.json", json.dumps(report, indent=1, default=json_default))
    write_text(out / "report.md", report_markdown(report))


def _cell(stats: dict) -> str:
    """A breakdown bin as "MSE (share %)", pooled over voxels; "–" for an empty bin."""
    if not stats or stats.get("logE_mse_pooled") is None:
        return "–"
    share = stats.get("share_pooled")
    return f"{stats['logE_mse_pooled']:.3f}" + ("" if share is None else f" ({100 * share:.0f} %)")


def _bin_title(name: str) -> str:
    """A distance bin's name as a column title: "<=1" -> "≤ 1", "(1,3]" -> "(1, 3]", "single_part" -> "single-part"."""
    return name.replace("<=", "≤ ").replace(">", "> ").replace(",", ", ").replace("_", "-")


def breakdown_markdown(b: dict, shown: dict | None = None) -> list:
    """Lines of report.md for ``report["breakdown"]`` (:func:`.error_breakdown.error_breakdown`).

    shown: method -> how its name appears in the tables (default the name itself).
    """
    methods = b.get("methods") or {}
    if not methods:
        return []
    shown = shown or {}
    bins = list(b["distance_bins"])
    L = ["## Where the log E error lies", "",
         "Squared error of log10 E per voxel (averaged over α), pooled over each bin's voxels: MSE (the bin's share "
         "of the method's squared error). Distance: from the voxel to the nearest voxel of another part, in voxels. "
         "Part labels, surface and class serve this scoring only; per-object means and object-weighted shares are "
         "in report.json (`breakdown`).", "",
         "| method | all | surface | interior | " + " | ".join(_bin_title(x) for x in bins) + " |",
         "|---|" + "---|" * (3 + len(bins))]
    for name, m in methods.items():
        kind, dist = m.get("by_voxel_kind") or {}, m.get("by_boundary_distance") or {}
        L.append(f"| {shown.get(name, name)} | {_cell({**m['all'], 'share_pooled': None})} | "
                 f"{_cell(kind.get('surface'))} | {_cell(kind.get('interior'))} | "
                 + " | ".join(_cell(dist.get(x)) for x in bins) + " |")
    first = next(iter(methods.values()))
    kind, dist = first.get("by_voxel_kind") or {}, first.get("by_boundary_distance") or {}
    count = lambda d, k: str(d[k]["voxels"]) if k in d else "–"  # noqa: E731
    L.append(f"| voxels | {first['voxels']} | {count(kind, 'surface')} | {count(kind, 'interior')} | "
             + " | ".join(count(dist, x) for x in bins) + " |")
    classes = sorted({c for m in methods.values() for c in (m.get("by_class") or {})})
    if classes:
        L += ["", "By class (log E MSE pooled over the class's voxels; share of the method's squared error):", "",
              "| class | voxels | " + " | ".join(shown.get(n, n) for n in methods) + " |",
              "|---|---|" + "---|" * len(methods)]
        for c in classes:
            voxels = first.get("by_class", {}).get(c, {}).get("voxels", "–")
            L.append(f"| {c} | {voxels} | " + " | ".join(_cell((m.get("by_class") or {}).get(c)) for m in methods.values())
                     + " |")
    notes = sorted({f"{k}: {v}" for m in methods.values() for k, v in (m.get("not_available") or {}).items()})
    if notes:
        L += [""] + [f"- {x}" for x in notes]
    return L


def table2_by_class_markdown(by_class: list, shown: dict) -> list:
    """Lines of the per-class Table 2 (mean RMSE / size over the class's objects and α) and, per solver, how far
    the learned heads are from the test-time fits (the ratio of their mean RMSE over the same objects)."""
    columns = sorted({(x["solver"], x["method"]) for x in by_class})
    classes = sorted({x["semantic_class"] for x in by_class})
    cell = {(x["semantic_class"], x["solver"], x["method"]): x for x in by_class}
    L = ["### Table 2 by class (tracked-point RMSE / object size, mean over the class's objects and α)", "",
         "| class | objects | " + " | ".join(f"{s} {shown.get(m, m)}" for s, m in columns) + " |",
         "|---|---|" + "---|" * len(columns)]
    for c in classes:
        n = max(cell[(c, s, m)]["objects"] for s, m in columns if (c, s, m) in cell)
        L.append(f"| {c} | {n} | " + " | ".join(
            f"{cell[(c, s, m)]['relative_rmse']:.3f}" if (c, s, m) in cell else "–" for s, m in columns) + " |")
    for solver in sorted({s for s, _ in columns}):
        fit = [x for x in by_class if x["solver"] == solver and x["method"] == "test_time_fit"]
        head = [x for x in by_class if x["solver"] == solver and x["method"] == "unipixie"]
        both = sorted({x["semantic_class"] for x in fit} & {x["semantic_class"] for x in head})
        if both:
            f = sum(cell[(c, solver, "test_time_fit")]["relative_rmse"] * cell[(c, solver, "test_time_fit")]["objects"]
                    for c in both)
            h = sum(cell[(c, solver, "unipixie")]["relative_rmse"] * cell[(c, solver, "unipixie")]["objects"]
                    for c in both)
            L += ["", f"{solver}: the learned head's error is {h / f:.2f}× the test-time fit's (object-weighted)."]
    return L


def report_markdown(r: dict) -> str:
    fm = r.get("model_feature_model") or ", ".join(r.get("feature_model") or [])
    clip_note = "" if r.get("model_is_clip", False) else (" — features from the offline extractor (a seeded, "
                                                         "untrained ViT), **not CLIP**")
    L = [f"# Evaluation on the {r['split']} split", "",
         f"- dataset: `{r['dataset']}` ({r['objects']} objects evaluated); checkpoint: `{r['checkpoint']}`",
         f"- features: {fm}{clip_note}", f"- α values: {', '.join(f'{a:g}' for a in r['alphas'])}", "",
         "## Table 1: physical property regression (averaged over α; log = log10)", "",
         "| method | log E MSE | log ρ MSE | ν MSE | material acc. | runtime (s) |", "|---|---|---|---|---|---|"]
    refs = r.get("references") or {}
    shown = {name: (f"*{name}* (reference)" if name in refs else name) for name in r["table1"]}
    for name, m in r["table1"].items():
        L.append(f"| {shown[name]} | {m['logE_mse']:.4f} ± {m['logE_mse_std']:.3f} | {m['logrho_mse']:.4f} ± "
                 f"{m['logrho_mse_std']:.3f} | {m['nu_mse']:.5f} ± {m['nu_mse_std']:.4f} | "
                 f"{100 * m['material_acc']:.1f} % | {m['runtime_s']:.3f} |")
    if refs:
        L += ["", "References (not methods: computed from the generator's own priors with knowledge no image gives; "
                  "each says what it knows, and oracle_appearance bounds what any model can reach on these labels; "
                  "training/oracle.py):"] + [f"- *{k}*: {v['description']}" for k, v in refs.items()]
    elif r.get("references_skipped"):
        L += ["", f"Reference predictors not computed: {r['references_skipped']}"]
    L += ["", "Mean log E over the object non-decreasing in α: " + ", ".join(
        f"{name} {100 * m['logE_monotone_fraction']:.0f} % of objects" for name, m in r["table1"].items()
        if "logE_monotone_fraction" in m), ""]
    L += ["", "Per α (log E MSE):", "", "| method | " + " | ".join(f"α = {a:g}" for a in r["alphas"]) + " |",
          "|---|" + "---|" * len(r["alphas"])]
    for name, m in r["table1"].items():
        L.append(f"| {shown[name]} | " + " | ".join(f"{v:.4f}" for v in m["logE_mse_per_alpha"].values()) + " |")
    if r.get("breakdown"):
        L += [""] + breakdown_markdown(r["breakdown"], shown)
    L += ["", "## Predictions inside the annotated ranges (fraction of occupied voxels)", "",
          "| method | α | quantity | tol 0 | tol 10 % | tol 25 % |", "|---|---|---|---|---|---|"]
    for name, rng in r["in_range"].items():
        for a, qs in rng.items():
            for q, v in qs.items():
                L.append(f"| {shown[name]} | {a} | {q} | " + " | ".join(f"{100 * v[t]:.1f} %" for t in ("0", "0.1", "0.25")) + " |")
    if r["table2"]:
        L += ["", f"## Table 2: solver fidelity against the ground-truth MPM motion ({len(r['table2_objects'])} objects)", "",
              "| solver | method | α | RMSE (mm) | RMSE / size | PSNR (dB) | SSIM | time (s) | failed |",
              "|---|---|---|---|---|---|---|---|---|"]
        f = lambda x, fmt: "–" if x is None else format(x, fmt)  # noqa: E731
        for row in r["table2"]:
            L.append(f"| {row['solver']} | {row['method']} | {row['alpha']:g} | {f(None if row['rmse_m'] is None else 1000 * row['rmse_m'], '.2f')} | "
                     f"{f(row['relative_rmse'], '.3f')} | {f(row['psnr'], '.2f')} | {f(row['ssim'], '.3f')} | "
                     f"{f(row['seconds'], '.2f')} | {row['failed']} |")
    if r.get("table2_by_class"):
        L += [""] + table2_by_class_markdown(r["table2_by_class"], shown)
    if r.get("table2_failures"):
        L += ["", "Table 2 objects skipped: " + "; ".join(f"{x['object_id']}: {x['error']}" for x in r["table2_failures"])]
    if r.get("figure"):
        L += ["", f"![log E distributions]({r['figure']})"]
    L.append("")
    return "\n".join(L)
