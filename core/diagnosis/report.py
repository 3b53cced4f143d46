"""The diagnosis report: ``diagnosis.json`` (format ``unipixie.diagnosis/1``), pictures, one HTML page.

:func:`write_report` writes into a directory:

* ``diagnosis.json`` — the spec's keys (``shared/specs/measurement-format.md`` §3) plus extras;
* ``error_over_time.png`` — RMSE per instant of the model as given and after each added effect,
  with the noise band and ground-contact markers;
* ``error_on_shape.png`` — the rest shape coloured by per-point RMSE (before / after);
* ``worst_paths.png`` — measured vs simulated paths (x, y, z over time) of the worst points;
* ``ladder.png`` — the error after each added effect, falling towards the noise floor;
* ``candidates.png`` — the share of the error each candidate explains, significant ones marked;
* ``regions.png`` — error per region of the solid (before / after);
* ``diagnosis.html`` — one page with the ranking, the base-material check and all pictures.

Pictures are drawn with matplotlib's object API (no pyplot state, no GUI backend), so this
works headless and inside Blender.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

import numpy as np

from ...solvers.registry import SOLVER_NAMES
from ..atomic_io import OutputLock, check_writable, save_figure, strict_json_default, write_text
from ..errors import UserError

JSON_NAME = "diagnosis.json"
HTML_NAME = "diagnosis.html"
PICTURES = ("error_over_time.png", "error_on_shape.png", "worst_paths.png", "ladder.png", "candidates.png",
            "regions.png")
REQUIRED_KEYS = ("format", "solver", "baseline", "candidates", "identified", "history")


# --------------------------------------------------------------------------- validation
def validate_report(doc: dict) -> None:
    """Check a report against the spec's ``unipixie.diagnosis/1`` contract; raises UserError naming the key."""
    for k in REQUIRED_KEYS:
        if k not in doc:
            raise UserError(f"diagnosis report: key '{k}' is missing")
    if doc["format"] != "unipixie.diagnosis/1":
        raise UserError(f"diagnosis report: key 'format' is {doc['format']!r}")
    if doc["solver"] not in SOLVER_NAMES:
        raise UserError(f"diagnosis report: key 'solver' is {doc['solver']!r}")
    b = doc["baseline"]
    if not (isinstance(b, dict) and isinstance(b.get("rmse"), (int, float)) and isinstance(b.get("worst_points"), list)
            and isinstance(b.get("worst_times"), list)):
        raise UserError("diagnosis report: key 'baseline' must hold rmse, worst_points, worst_times")
    if not all(isinstance(i, int) for i in b["worst_points"]) or not all(isinstance(t, (int, float))
                                                                        for t in b["worst_times"]):
        raise UserError("diagnosis report: baseline worst_points must be integers and worst_times numbers")
    if not isinstance(doc["candidates"], list):
        raise UserError("diagnosis report: key 'candidates' must be a list")
    for c in doc["candidates"]:
        for k, typ in (("effect", str), ("params", dict), ("rmse", (int, float)), ("explained", (int, float)),
                       ("significant", bool)):
            if not isinstance(c.get(k), typ):
                raise UserError(f"diagnosis report: candidate {c.get('effect')!r} key '{k}' is missing or mistyped")
    sig_first = [c["significant"] for c in doc["candidates"]]
    if sig_first != sorted(sig_first, reverse=True):
        raise UserError("diagnosis report: candidates are not ranked best first (a significant one follows a "
                        "non-significant one)")
    ident = doc["identified"]
    if ident is not None:
        sig_names = [c["effect"] for c in doc["candidates"] if c["significant"]]
        if not sig_names or ident != sig_names[0]:
            raise UserError("diagnosis report: key 'identified' must be the best significant candidate or null")
    elif any(c["significant"] for c in doc["candidates"]):
        raise UserError("diagnosis report: 'identified' is null although a candidate is significant")
    v = doc.get("verdict")
    if v is not None:  # an extra key (reports made before it existed have none)
        from .verdict import CODES

        if not (isinstance(v, dict) and v.get("code") in CODES and isinstance(v.get("sentence"), str)
                and isinstance(v.get("explained"), bool)):
            raise UserError(f"diagnosis report: key 'verdict' must hold code (one of {', '.join(CODES)}), explained "
                            "and sentence")
        if (v["code"] in ("effect_found", "effect_found_partly")) != (ident is not None):
            raise UserError("diagnosis report: key 'verdict' disagrees with 'identified'")
    h = doc["history"]
    if not isinstance(h, list) or not h:
        raise UserError("diagnosis report: key 'history' must be a non-empty list")
    for e in h:
        if not (isinstance(e.get("effects"), list) and isinstance(e.get("rmse"), (int, float))):
            raise UserError("diagnosis report: every history entry needs 'effects' (list) and 'rmse' (number)")


def _clean(x):
    """Replace NaN/inf by None recursively (JSON has no NaN)."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


REPORT_BYTES = 4_000_000
"""About how much a report takes on disk (six pictures, the JSON and the page): checked before a diagnosis."""


def check_out_dir(out_dir) -> Path:
    """Check, before any simulation, that the report can be written into ``out_dir`` (a folder that exists
    or can be made, writable, with room); raises :class:`UserError` naming the cause."""
    return check_writable(out_dir, REPORT_BYTES, directory=True, what="report folder")


# --------------------------------------------------------------------------- pictures
def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> None:
    fig.tight_layout()
    save_figure(fig, path)


def _labels(d) -> list[str]:
    out = []
    for h in d.history:
        out.append(" + ".join(h["effects"]) if h["effects"] else "as given")
    return out


def ladder_steps(d) -> list[tuple[str, str, float, np.ndarray]]:
    """The models the pictures compare, in order: (short label, long label, RMSE m over all observed samples,
    (T, N, 3) positions m) — the model as given, then each effect added (``history``).  When none was added and the
    base was refitted (its E/ρ, or a ground contact adopted with it), the refitted base model comes last: what the
    diagnosis's verdict is about, and how far it still is from the measurement."""
    labels = _labels(d)
    steps = [(labels[0] if i == 0 else "+ " + labels[i].split(" + ")[-1], labels[i], float(h["rmse"]),
              d.history_positions[i]) for i, h in enumerate(d.history)]
    refitted = abs(d.E_scale - 1.0) > 1e-3 or bool(d.base_contact.get("adopted"))
    if len(d.history) == 1 and len(d.history_positions) > 1 and refitted:
        fitted = f"E/ρ × {d.E_scale:.3g}" + (", its floor" if d.base_contact.get("adopted") else "")
        steps.append((f"base refit\n({fitted})", f"base refit ({fitted})", float(d.final.rmse),
                      d.history_positions[-1]))
    return steps


def _floor_label(d, floor: float) -> str:
    """The floor line's legend: measured over the predictive window where there is one (the fits' samples), while
    the bars and curves are over every observed sample."""
    where = f" (up to t = {d.horizon:.2f} s)" if d.horizon is not None else ""
    return f"model's discretisation floor{where} {1e3 * floor:.2f} mm"


def _discretisation_floor(d) -> float | None:
    """The model's discretisation floor (m) where the diagnosis enforced it (resolution check), else ``None``."""
    floor = d.resolution.get("floor_rmse") if d.resolution.get("enforce_floor") else None
    return float(floor) if floor is not None and math.isfinite(floor) else None


def plot_error_over_time(d, path: Path) -> None:
    from .compare import point_distances, _nan_rms

    fig = _figure(8, 4)
    ax = fig.add_subplot(111)
    t = d.times
    steps = ladder_steps(d)
    colours = ["#c0392b", "#2980b9", "#27ae60", "#8e44ad", "#d35400"]
    for i, (_, label, rmse, pos) in enumerate(steps):
        per_time = _nan_rms(point_distances(pos, d.measured), axis=1)
        ax.plot(t, 1e3 * per_time, color=colours[i % len(colours)], lw=1.8 if i in (0, len(steps) - 1) else 1.0,
                label=f"{label} ({1e3 * rmse:.2f} mm)")
    nr = 1e3 * d.noise_rmse
    ax.axhspan(0, nr, color="0.85", label=f"noise floor ±{nr:.2f} mm")
    ax.axhline(2 * nr, color="0.5", ls=":", lw=1, label="2 × noise")
    floor = _discretisation_floor(d)
    if floor is not None:
        ax.axhline(1e3 * floor, color="#e67e22", ls="-.", lw=1, label=_floor_label(d, floor))
    for i, tc in enumerate(d.contact_times):
        ax.axvline(tc, color="0.3", ls="--", lw=0.8, label="ground contact" if i == 0 else None)
    if d.horizon is not None:  # fits and tests used the instants before it (chaotic contact later)
        ax.axvspan(d.horizon, t[-1], color="#f5cba7", alpha=0.35, lw=0, label="after the predictive window")
    wt = d.baseline.worst_times[:3]
    if wt:
        idx = [int(np.argmin(np.abs(t - w))) for w in wt]
        ax.plot(t[idx], 1e3 * d.baseline.per_time[idx], "kv", ms=6, label="worst instants")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("RMSE per instant [mm]")
    ax.set_title("Error over time")
    top = 1e3 * float(np.nanmax(d.baseline.per_time)) if np.isfinite(d.baseline.per_time).any() else nr
    if top > 30 * nr:  # the fall spans decades: a log axis shows the final error next to the noise
        ax.set_yscale("log")
        ax.set_ylim(bottom=0.2 * nr)
    else:
        ax.set_ylim(bottom=0)
    ax.legend(fontsize=7, loc="upper left")
    _save(fig, path)


def plot_error_on_shape(d, path: Path) -> None:
    fig = _figure(10, 4.6)
    rest = d.rest_positions
    vals = [d.baseline.per_point, d.final.per_point]
    finite = np.concatenate([v[np.isfinite(v)] for v in vals]) if any(np.isfinite(v).any() for v in vals) else [1.0]
    vmax = 1e3 * float(np.max(finite)) if len(finite) else 1.0
    titles = ["model as given", "after adding " + (" + ".join(e.name for e in d.added) if d.added else "nothing")]
    sc = None
    for k, (v, title) in enumerate(zip(vals, titles)):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ok = np.isfinite(v)
        if np.any(~ok):
            ax.scatter(*rest[~ok].T, c="0.7", s=8)
        sc = ax.scatter(*rest[ok].T, c=1e3 * v[ok], cmap="viridis", vmin=0, vmax=vmax, s=14)
        for w in d.baseline.worst_points[:3] if k == 0 else d.final.worst_points[:3]:
            ax.text(*rest[w], f"#{w}", fontsize=7)
        ax.set_title(f"{title}\nRMSE {1e3 * (d.baseline.rmse if k == 0 else d.final.rmse):.2f} mm", fontsize=9)
        ax.set_xlabel("x [m]", fontsize=7)
        ax.set_ylabel("y [m]", fontsize=7)
        ax.set_zlabel("z [m]", fontsize=7)
        ax.tick_params(labelsize=6)
        span = np.ptp(rest, axis=0)
        ax.set_box_aspect(np.maximum(span, 0.05 * span.max()))
    if sc is not None:
        cb = fig.colorbar(sc, ax=fig.axes, shrink=0.7)
        cb.set_label("per-point RMSE [mm]")
    fig.suptitle("Rest shape coloured by per-point error (grey: never observed)", fontsize=10)
    save_figure(fig, path)


def plot_worst_paths(d, path: Path, count: int = 3) -> None:
    pts = d.baseline.worst_points[:count]
    if not pts:
        pts = [0]
    fig = _figure(10, 2.6 * len(pts))
    t = d.times
    for r, p in enumerate(pts):
        for c in range(3):
            ax = fig.add_subplot(len(pts), 3, 3 * r + c + 1)
            ax.plot(t, d.measured[:, p, c], ".", ms=3, color="k", label="measured")
            ax.plot(t, d.baseline_positions[:, p, c], "--", color="#c0392b", lw=1.2, label="model as given")
            ax.plot(t, d.final_positions[:, p, c], "-", color="#2980b9", lw=1.2,
                    label="after " + (" + ".join(e.name for e in d.added) if d.added else "base refit"))
            ax.set_title(f"point #{p}: {'xyz'[c]}", fontsize=9)
            ax.tick_params(labelsize=7)
            if r == len(pts) - 1:
                ax.set_xlabel("time [s]", fontsize=8)
            if c == 0:
                ax.set_ylabel("position [m]", fontsize=8)
            if r == 0 and c == 0:
                ax.legend(fontsize=6)
    fig.suptitle("Measured vs simulated paths of the worst points", fontsize=10)
    _save(fig, path)


def plot_ladder(d, path: Path) -> None:
    fig = _figure(6, 3.6)
    ax = fig.add_subplot(111)
    steps = ladder_steps(d)
    vals = [1e3 * rmse for _, _, rmse, _ in steps]
    ax.bar(range(len(vals)), vals, color=["#c0392b"] + ["#2980b9"] * (len(vals) - 1))
    for i, v in enumerate(vals):
        ax.text(i, v, f"{v:.2f}", ha="center", va="bottom", fontsize=8)
    nr = 1e3 * d.noise_rmse
    ax.axhline(nr, color="0.3", ls="--", lw=1, label=f"noise floor {nr:.2f} mm")
    ax.axhline(2 * nr, color="0.5", ls=":", lw=1, label="2 × noise")
    floor = _discretisation_floor(d)
    if floor is not None:
        ax.axhline(1e3 * floor, color="#e67e22", ls="-.", lw=1, label=_floor_label(d, floor))
    ax.set_xticks(range(len(vals)))
    ax.set_xticklabels([short for short, _, _, _ in steps], fontsize=8, rotation=15)
    ax.set_ylabel("RMSE [mm]")
    ax.set_title("Error after each added effect")
    ax.legend(fontsize=7)
    _save(fig, path)


def plot_candidates(d, path: Path) -> None:
    cands = d.candidates
    fig = _figure(7, 0.45 * max(len(cands), 2) + 1.2)
    ax = fig.add_subplot(111)
    if cands:
        names = [c.name for c in cands][::-1]
        vals = [100 * max(c.explained_beyond_base, 0.0) for c in cands][::-1]
        cols = ["#27ae60" if c.significant else "0.6" for c in cands][::-1]
        ax.barh(range(len(names)), vals, color=cols)
        ax.set_yticks(range(len(names)))
        ax.set_yticklabels(names, fontsize=8)
        for i, v in enumerate(vals):
            ax.text(v, i, f" {v:.1f} %", va="center", fontsize=7)
        ax.set_xlim(0, 110)
    ax.set_xlabel("share of the (base-refitted) squared error explained [%]")
    ax.set_title("Candidates, best first (green: significant)")
    _save(fig, path)


def plot_regions(d, path: Path) -> None:
    regions = d.baseline.regions
    fig = _figure(7, 3.4)
    ax = fig.add_subplot(111)
    final = {r.name: r.rmse for r in d.final.regions}
    names = [r.name for r in regions]
    x = np.arange(len(names))
    ax.bar(x - 0.2, [1e3 * r.rmse for r in regions], 0.4, color="#c0392b", label="model as given")
    ax.bar(x + 0.2, [1e3 * final.get(n, math.nan) for n in names], 0.4, color="#2980b9", label="final model")
    ax.axhline(1e3 * d.noise_rmse, color="0.3", ls="--", lw=1, label="noise floor")
    ax.set_xticks(x)
    ax.set_xticklabels([f"{n}\n({len(r.indices)} pts)" for n, r in zip(names, regions)], fontsize=7)
    ax.set_ylabel("RMSE [mm]")
    ax.set_title("Error per region of the solid (k-means clusters of the rest shape)")
    ax.legend(fontsize=7)
    _save(fig, path)


# --------------------------------------------------------------------------- HTML
def _fmt(x, unit: str = "", scale: float = 1.0, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x * scale:.{digits}g}{(' ' + unit) if unit else ''}"


def _params_html(c) -> str:
    out = []
    for k, v in c.params().items():
        unc = c.uncertainty.get(k) if isinstance(c.uncertainty, dict) else None
        if isinstance(v, dict):
            if "points" in v:
                region = c.region or {}
                out.append(f"region: {html.escape(str(region.get('name', '')))} ({len(v['points'])} points, box "
                           f"{html.escape(str(np.round(np.asarray(region.get('box', [])), 3).tolist()))})")
            else:
                out.append(f"region: box {html.escape(str(np.round(np.asarray(v.get('box')), 3).tolist()))}")
        elif isinstance(v, list):
            uncs = [c.uncertainty.get(f"{k}[{a}]") for a in "xyz"]
            out.append(f"{k} = [" + ", ".join(f"{x:.3g}" + (f" ± {u:.2g}" if u else "") for x, u in zip(v, uncs)) + "]")
        else:
            out.append(f"{k} = {v:.4g}" + (f" ± {unc:.2g}" if unc else ""))
    return "<br>".join(out)


def render_html(d, doc: dict) -> str:
    e = html.escape
    ident = d.identified
    rows = []
    for i, c in enumerate(d.candidates):
        hold = c.holdout or {}
        hold_txt = ("–" if not hold else ("ok" if hold.get("ok") else ("failed" if hold.get("ok") is False else
                                                                        e(hold.get("verdict", "")))))
        rows.append(
            f"<tr class='{'sig' if c.significant else ''}'><td>{i + 1}</td><td><b>{e(c.name)}</b></td>"
            f"<td>{_params_html(c)}</td><td>{_fmt(c.rmse, 'mm', 1e3)}</td><td>{_fmt(100 * c.explained, '%')}</td>"
            f"<td>{_fmt(100 * c.explained_beyond_base, '%')}</td><td>{_fmt(c.lr)} / {_fmt(c.threshold)}</td>"
            f"<td>{_fmt(100 * c.share, '%')}</td><td>{hold_txt}</td><td>{_fmt(c.E_scale)}</td>"
            f"<td>{'<b>yes</b>' if c.significant else 'no'}</td><td class='small'>{e('; '.join(c.reasons))}</td></tr>")
    hist = "".join(f"<tr><td>{i}</td><td>{e(' + '.join(h['effects']) or 'as given')}</td>"
                   f"<td>{_fmt(h['rmse'], 'mm', 1e3)}</td><td>{_fmt(h.get('E_scale'))}</td></tr>"
                   for i, h in enumerate(d.history))
    bm = d.base_material
    ru = d.runner_up()
    na = doc.get("not_applicable") or {}
    rounds = []
    for k, r in enumerate(d.rounds):
        items = ", ".join(f"{e(c.name)} {_fmt(c.rmse, 'mm', 1e3)}{' ✔' if c.significant else ''}" for c in r.candidates)
        rounds.append(f"<li>round {k + 1} (reference: {e(' + '.join(x.name for x in r.effects) or 'refitted base')}, "
                      f"{_fmt(r.rmse, 'mm', 1e3)}): {items}; identified: <b>{e(str(r.identified))}</b>"
                      + (f"; added <b>{e(r.added.name)}</b> ({e(r.added_by)})" if r.added is not None else "") + "</li>")
    pics = "".join(f"<figure><img src='{p}' alt='{p}'><figcaption>{e(cap)}</figcaption></figure>" for p, cap in (
        ("error_over_time.png", "RMSE per instant for the model as given and after each added effect; grey band: "
                                "noise floor; dashed lines: ground contact; triangles: worst instants."),
        ("error_on_shape.png", "Rest shape coloured by per-point RMSE, before and after (worst points labelled)."),
        ("worst_paths.png", "Measured (dots) vs simulated paths of the worst points."),
        ("ladder.png", "Error after each added effect, falling towards the noise floor."),
        ("candidates.png", "Share of the base-refitted squared error each candidate explains."),
        ("regions.png", "Error per region of the solid."),
    ))
    v = doc.get("verdict") or {}
    verdict = (f"The missing effect is <b>{e(ident)}</b>." if ident else "No effect of the registry is significant "
               "(identified: null).") + (f" <b>{e(v['sentence'][0].upper() + v['sentence'][1:])}.</b>"
                                         if v.get("sentence") else "")
    ru_txt = (f"Runner-up: <b>{e(ru['effect'])}</b> at {_fmt(ru['rmse'], 'mm', 1e3)} "
              f"(likelihood-ratio gap {_fmt(ru['gap_likelihood_ratio'])}, RMSE ratio {_fmt(ru['rmse_ratio'])}). "
              "A good fit is not proof of the mechanism: when the true term is missing from the library, "
              "others stand in for it." if ru else "")
    bm_txt = (f"E/ρ fitted × {_fmt(bm.get('E_scale'))} of the stated value "
              f"(E {_fmt(bm.get('E_stated'), 'Pa')} → {_fmt(bm.get('E_fitted'), 'Pa')} at the stated density "
              f"{_fmt(bm.get('density_stated'), 'kg/m³')}); RMSE {_fmt(bm.get('rmse_stated_E'), 'mm', 1e3)} with the "
              f"stated E, {_fmt(bm.get('rmse_fitted_E'), 'mm', 1e3)} with the fitted one. "
              + ("<b>The base material looks wrong.</b> " if bm.get("looks_wrong") else
                 "The stated base material is consistent with the data. ") + e(bm.get("note", "")))
    bm_txt += _base_extras_html(d)
    na_txt = "".join(f"<li>{e(k)}: {e(v)}</li>" for k, v in na.items())
    warn = "".join(f"<li>{e(w)}</li>" for w in d.warnings)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>UniPixie diagnosis</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 2em; max-width: 1200px; color: #222; }}
table {{ border-collapse: collapse; font-size: 0.85em; }} td, th {{ border: 1px solid #ccc; padding: 4px 6px; }}
tr.sig {{ background: #eafaf1; }} .small {{ font-size: 0.8em; color: #555; }}
figure {{ display: inline-block; margin: 0.5em; vertical-align: top; max-width: 48%; }}
img {{ max-width: 100%; border: 1px solid #ddd; }} figcaption {{ font-size: 0.8em; color: #555; }}
.verdict {{ font-size: 1.2em; }}
</style></head><body>
<h1>Diagnosis: where the model fails and which effect is missing</h1>
<p>Measurement <code>{e(d.measurement_source)}</code>; solver <b>{e(d.solver)}</b>;
{d.baseline.observed} observed samples; noise estimated from the tracks σ = {_fmt(d.noise_sigma, 'mm', 1e3)} per
coordinate (noise floor RMSE {_fmt(d.noise_rmse, 'mm', 1e3)}); {d.simulations} simulations in {_fmt(d.wall_s, 's')}.</p>
<p class="verdict">{verdict} Error: {_fmt(d.baseline.rmse, 'mm', 1e3)} as given → {_fmt(d.final.rmse, 'mm', 1e3)}
after {e(' + '.join(x.name for x in d.added) or 'the base refit')}.</p>
<p>{ru_txt}</p>
<h2>Where it fails (model as given)</h2>
<p>Worst points: {', '.join(f'#{p} ({_fmt(v, "mm", 1e3)})' for p, v in zip(d.baseline.worst_points, d.baseline.worst_point_errors))}.
Worst instants: {', '.join(f'{t:.3f} s ({_fmt(v, "mm", 1e3)})' for t, v in zip(d.baseline.worst_times, d.baseline.worst_time_errors))}.
Worst region: {e(d.baseline.regions[0].name) if d.baseline.regions else '–'}.</p>
<h2>Candidates (round 1, best first)</h2>
<table><tr><th>#</th><th>effect</th><th>fitted parameters (± 1σ)</th><th>RMSE</th><th>explained</th>
<th>beyond base refit</th><th>Λ = ΔSSE/σ² / threshold</th><th>share of above-noise error</th><th>held-out</th>
<th>E/ρ scale</th><th>significant</th><th>why not</th></tr>
{''.join(rows)}</table>
<p class="small">{e(doc['significance']['rule'])}. The held-out test refits on the first
{100 * doc['significance']['holdout_fraction']:.0f} % of the duration and scores the rest.</p>
{('<p>Not tried:</p><ul>' + na_txt + '</ul>') if na_txt else ''}
<h2>Error after each added effect</h2>
<table><tr><th>step</th><th>effects</th><th>RMSE</th><th>E/ρ scale</th></tr>{hist}</table>
<ul>{''.join(rounds)}</ul>
<h2>Base material</h2><p>{bm_txt}</p>
{('<h2>Warnings</h2><ul>' + warn + '</ul>') if warn else ''}
<h2>Pictures</h2>
{pics}
<p class="small">Machine-readable: <a href="{JSON_NAME}">{JSON_NAME}</a> (format unipixie.diagnosis/1).</p>
</body></html>
"""


# --------------------------------------------------------------------------- writer
def write_report(d, out_dir) -> dict:
    """Write ``diagnosis.json``, the pictures and ``diagnosis.html`` into ``out_dir``; returns their paths.

    Every file is written atomically (:mod:`unipixie.core.atomic_io`); the JSON last but one and the
    page last, so a report whose ``diagnosis.html`` exists is complete.  A second run writing the same
    folder at the same time is refused (:class:`~unipixie.core.atomic_io.OutputLock`)."""
    out = Path(out_dir).expanduser()
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a directory; give --out a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        from ..atomic_io import write_error

        raise write_error(out, exc, "create the report folder") from None
    with OutputLock(out / JSON_NAME, "report"):
        return _write_report(d, out)


def _write_report(d, out: Path) -> dict:
    doc = _clean(d.to_json())
    validate_report(doc)
    paths = {}
    for name, fn in (("error_over_time.png", plot_error_over_time), ("error_on_shape.png", plot_error_on_shape),
                     ("worst_paths.png", plot_worst_paths), ("ladder.png", plot_ladder),
                     ("candidates.png", plot_candidates), ("regions.png", plot_regions)):
        p = out / name
        fn(d, p)
        paths[name] = p
    doc["pictures"] = list(PICTURES)
    doc["html"] = HTML_NAME
    jp = out / JSON_NAME
    write_text(jp, json.dumps(doc, indent=2, default=strict_json_default, allow_nan=False) + "\n")
    hp = out / HTML_NAME
    write_text(hp, render_html(d, doc))
    paths["json"] = jp
    paths["html"] = hp
    return paths


def load_report(path) -> dict:
    """Read and validate a ``diagnosis.json``."""
    p = Path(path)
    if p.is_dir():
        p = p / JSON_NAME
    try:
        doc = json.loads(p.read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError) as exc:
        raise UserError(f"{p}: cannot read the diagnosis report ({exc})") from None
    if not isinstance(doc, dict):
        raise UserError(f"{p}: a diagnosis report is a JSON object")
    validate_report(doc)
    return doc


def _base_extras_html(d) -> str:
    """The base model's fitted ground contact and discretisation check (contact_fit.py, resolution.py), as HTML
    sentences for the base-material paragraph."""
    from html import escape as e

    out = ""
    bc = getattr(d, "base_contact", None) or {}
    if bc.get("touches_ground"):
        p = bc["params"]
        out += (f" <br>Ground contact fitted with E/ρ (part of the base, not a candidate effect): "
                f"c = {_fmt(p.get('c'), 'Pa·s/m')}, k = {_fmt(p.get('k'), 'Pa/m')}, E/ρ × {_fmt(bc.get('E_scale'))}; "
                f"RMSE {_fmt(bc.get('rmse'), 'mm', 1e3)} against {_fmt(bc.get('rmse_rigid_floor'), 'mm', 1e3)} with "
                f"the rigid, lossless floor. {e(bc.get('reason', ''))}")
    res = getattr(d, "resolution", None) or {}
    if res.get("checked"):
        out += f" <br>Resolution check: {e(res.get('verdict', ''))}"
    return out
