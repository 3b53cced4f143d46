"""Where a method's log10 E error lies: by object class, surface vs. interior voxel, distance to a part boundary.

    python -m unipixie.training.error_breakdown EVAL_DIR [--data DATASET]   # recompute report["breakdown"]

When the evaluation (:mod:`.evaluate`) writes an object's targets it also stores, beside the annotated ranges, facts
about each occupied voxel that are used **only for scoring** (no model and no feature ever sees them):

- ``surface`` (K,) bool: the voxel has an empty 6-neighbour (or lies on the grid's edge);
- ``part_boundary_distance`` (K,) float32, voxels: Euclidean distance from the voxel's centre to the centre of the
  nearest occupied voxel of *another* part (1 = face-adjacent); +inf on an object of one part;
- ``semantic_class``: the object's class (a 0-d string array);
- ``scoring_note`` (only where some fact is missing): why, e.g. the dataset has no part labels.

:func:`error_breakdown` then splits, per method, the squared error of log10 E — per voxel averaged over the method's
α values, as Table 1 averages over α — into bins, and gives for every bin its voxel count, the MSE pooled over the
bin's voxels, the mean over objects of each object's MSE in the bin, and the bin's share of the method's squared
error, both pooled (voxels weigh alike) and object-weighted (each object's per-voxel mean, as Table 1 weighs them:
the share of the Table 1 number).  The groupings: the object's class; surface vs. interior voxels; the distance to a
part boundary in :data:`DISTANCE_BINS` and single-part objects.  Targets written before these facts existed (or
without part labels) still score; the affected grouping then says why it is missing or partial.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from ..core import annotation as ann_mod
from ..core.errors import UserError

BREAKDOWN_FORMAT = "unipixie.error_breakdown/1"

DISTANCE_BINS = (("<=1", -math.inf, 1.0), ("(1,3]", 1.0, 3.0), ("(3,7]", 3.0, 7.0), (">7", 7.0, math.inf))
"""(name, lower, upper] bins of the distance to the nearest voxel of another part, in voxels; ``<=1`` is the
face-adjacent layer (a diagonal neighbour is √2 or √3 away)."""

SINGLE_PART = "single_part"
"""The bin of voxels of objects with one part (no boundary: distance +inf)."""

GROUPS = {"by_class": "semantic_class", "by_voxel_kind": "surface", "by_boundary_distance": "part_boundary_distance"}
"""Grouping name -> the targets key it needs."""

NOTE_KEY = "scoring_note"


# =========================================================================== per-voxel facts (scoring only)
def part_boundary_distance(part_ids: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(K,) float32: distance in voxels from each occupied voxel to the nearest occupied voxel of another part.

    part_ids: (K,) int part of each occupied voxel; indices: (K, 3) int voxel indices (same order).  Centre-to-centre
    Euclidean distance (1 for a face neighbour); +inf for every voxel when the object has fewer than two parts.
    """
    from scipy import ndimage

    part_ids = np.asarray(part_ids, np.int64)
    idx = np.asarray(indices, np.int64).reshape(-1, 3)
    if len(part_ids) != len(idx):
        raise UserError(f"{len(part_ids)} part labels for {len(idx)} occupied voxels")
    out = np.full(len(idx), np.inf, np.float32)
    parts = np.unique(part_ids)
    if len(parts) < 2:
        return out
    lo = idx.min(axis=0)                    # the occupied box holds every voxel and every nearest other-part voxel
    local = idx - lo
    labels = np.full(tuple(local.max(axis=0) + 1), -1, np.int64)
    labels[tuple(local.T)] = part_ids
    for p in parts:
        others = (labels >= 0) & (labels != p)
        dist = ndimage.distance_transform_edt(~others)   # distance to the nearest False, i.e. another part's voxel
        mine = part_ids == p
        out[mine] = dist[tuple(local[mine].T)]
    return out


def scoring_facts(ds, object_id: str, grid) -> dict:
    """The per-voxel scoring facts of one object (module docstring) for its targets file.

    ds: a :class:`.dataset.DatasetDir`; grid: the object's :class:`~..core.types.FeatureGrid` (occupancy (R, R, R)).
    What cannot be read (no part labels, no annotation) is left out and ``scoring_note`` says why.
    """
    from .part_code_probe import surface_mask

    facts, notes = {"surface": surface_mask(grid.occupancy)}, []
    try:
        facts["semantic_class"] = np.array(str(ds.annotation(object_id).semantic_class))
    except (UserError, OSError) as exc:
        notes.append(f"no class ({exc})")
    try:
        part_ids, _ = ds.part_labels(object_id)
        facts["part_boundary_distance"] = part_boundary_distance(part_ids, grid.indices)
    except (UserError, OSError, KeyError, ValueError) as exc:     # missing, unreadable or of another layout
        notes.append(f"no part labels ({exc})")
    if notes:
        facts[NOTE_KEY] = np.array("; ".join(notes))
    return facts


# =========================================================================== the breakdown
def voxel_logE_sq_error(pred: dict, targets: dict) -> np.ndarray:
    """(K,) float64: squared error of log10 E per voxel, averaged over the prediction's α values.

    pred: ``alphas`` (A,) and ``log10_E`` (A, K) log10 Pa; targets: ``E_min`` / ``E_max`` (K,) Pa, interpolated at
    each α as Table 1 does (log10-linear).
    """
    alphas = np.asarray(pred["alphas"], np.float64)
    logE = np.asarray(pred["log10_E"], np.float64)
    err = np.zeros(logE.shape[1], np.float64)
    for i, a in enumerate(alphas):
        t = ann_mod.channel(ann_mod.interpolate(targets["E_min"], targets["E_max"], float(a), "E"), "E")
        err += (logE[i] - np.asarray(t, np.float64)) ** 2
    return err / len(alphas)


def distance_bin_labels(distance: np.ndarray) -> np.ndarray:
    """(K,) str: the :data:`DISTANCE_BINS` name of each distance (voxels), :data:`SINGLE_PART` where +inf."""
    d = np.asarray(distance, np.float64)
    out = np.full(d.shape, SINGLE_PART, dtype=object)
    for name, lo, hi in DISTANCE_BINS:
        out[np.isfinite(d) & (d > lo) & (d <= hi)] = name
    return out


class _Group:
    """Sums of one grouping's bins over objects."""

    def __init__(self, bins=()):
        self.bins = {b: np.zeros(5) for b in bins}   # voxels, squared error, objects, Σ object MSE, Σ error / K
        self.total = np.zeros(2)                     # squared error, Σ error / K over the objects covered
        self.covered = 0
        self.missing: list = []

    def add(self, labels: np.ndarray, err: np.ndarray) -> None:
        K = len(err)
        for b in dict.fromkeys(labels.tolist()):     # first-seen order
            m = labels == b
            n, s = int(m.sum()), float(err[m].sum())
            self.bins.setdefault(b, np.zeros(5))
            self.bins[b] += (n, s, 1, s / n, s / K)
        self.total += (float(err.sum()), float(err.sum()) / K)
        self.covered += 1

    def result(self) -> dict:
        out = {}
        for b, (n, s, objs, obj_mse, weighted) in self.bins.items():
            out[b] = {"voxels": int(n), "objects": int(objs),
                      "logE_mse_pooled": s / n if n else None,
                      "logE_mse_object_mean": obj_mse / objs if objs else None,
                      "share_pooled": s / self.total[0] if self.total[0] > 0 else None,
                      "share_object_weighted": weighted / self.total[1] if self.total[1] > 0 else None}
        return out


def _load(path: Path) -> dict:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: not a readable .npz ({exc})") from None


def _labels(group: str, value: np.ndarray, K: int, where: Path) -> np.ndarray:
    if group == "by_class":
        name = str(value) or "(no class)"
        return np.full(K, name, dtype=object)
    value = np.asarray(value)
    if value.shape != (K,):
        raise UserError(f"{where}: {GROUPS[group]} has shape {value.shape}, expected ({K},): the file is damaged")
    if group == "by_voxel_kind":
        return np.where(value.astype(bool), "surface", "interior").astype(object)
    return distance_bin_labels(value)


def error_breakdown(pred_root) -> dict:
    """Where each method's log10 E error lies (module docstring), from an evaluation's ``predictions/`` folder.

    Returns {"format", "quantity", "distance_bins", "methods": {method: {"objects", "voxels", "all", "by_class",
    "by_voxel_kind", "interior_share_pooled", "interior_share_object_weighted", "by_boundary_distance",
    "not_available"}}}; every bin is {"voxels", "objects", "logE_mse_pooled", "logE_mse_object_mean",
    "share_pooled", "share_object_weighted"} (shares of the grouping's squared error over the objects it covers).
    """
    root = Path(pred_root)
    tdir = root / "targets"
    if not tdir.is_dir():
        raise UserError(f"{root}: no targets/ folder; not an evaluation's predictions directory")
    targets_cache: dict = {}
    methods = {}
    for mdir in sorted(p for p in root.iterdir() if p.is_dir() and p.name != "targets"):
        files = sorted(mdir.glob("*.npz"))
        if not files:
            continue
        everything = _Group()
        groups = {"by_class": _Group(), "by_voxel_kind": _Group(("surface", "interior")),
                  "by_boundary_distance": _Group([b[0] for b in DISTANCE_BINS] + [SINGLE_PART])}
        for f in files:
            if f.name not in targets_cache:
                if not (tdir / f.name).is_file():
                    raise UserError(f"{tdir / f.name}: missing (the predictions {f} have no targets)")
                targets_cache[f.name] = _load(tdir / f.name)
            targets = targets_cache[f.name]
            err = voxel_logE_sq_error(_load(f), targets)
            K = len(err)
            everything.add(np.full(K, "all", dtype=object), err)
            for name, g in groups.items():
                key = GROUPS[name]
                if key in targets:
                    g.add(_labels(name, targets[key], K, tdir / f.name), err)
                else:
                    why = str(targets[NOTE_KEY]) if NOTE_KEY in targets else \
                        "targets written before the breakdown existed (re-run the evaluation)"
                    g.missing.append(f"{f.stem}: {why}")
        n = everything.covered
        m = {"objects": n, "voxels": int(everything.bins["all"][0]), "all": everything.result()["all"]}
        not_available = {}
        for name, g in groups.items():
            m[name] = g.result() if g.covered else {}
            if g.missing:
                not_available[name] = (f"{'not available' if not g.covered else 'partial'}: {len(g.missing)} of {n} "
                                       f"objects without {GROUPS[name]!r} (first: {g.missing[0]})")
        kind = m["by_voxel_kind"]
        m["interior_share_pooled"] = kind["interior"]["share_pooled"] if kind else None
        m["interior_share_object_weighted"] = kind["interior"]["share_object_weighted"] if kind else None
        m["not_available"] = not_available
        methods[mdir.name] = m
    return {"format": BREAKDOWN_FORMAT,
            "quantity": "squared error of log10 E [Pa] per occupied voxel, averaged over the method's α values",
            "distance_bins": {name: [None if math.isinf(lo) else lo, None if math.isinf(hi) else hi]
                              for name, lo, hi in DISTANCE_BINS} | {SINGLE_PART: None},
            "methods": methods}


# =========================================================================== recompute an evaluation's breakdown
def add_missing_facts(pred_root, ds, progress=None) -> int:
    """Add the scoring facts to the targets files of ``pred_root`` that lack any of them; returns how many changed.

    ds: the evaluated :class:`.dataset.DatasetDir` (its ``sample``, ``annotation``, ``part_labels``); an object
    whose occupied voxels are not the targets' (another dataset) is a :class:`UserError`.  progress: a
    :class:`~..core.progress.Progress` (one step per targets file; cancellable) or None.
    """
    from ..core.atomic_io import save_npz

    tdir = Path(pred_root) / "targets"
    if not tdir.is_dir():
        raise UserError(f"{pred_root}: no targets/ folder; not an evaluation's predictions directory")
    changed = 0
    for f in sorted(tdir.glob("*.npz")):
        targets = _load(f)
        if all(k in targets for k in GROUPS.values()):
            if progress is not None:
                progress.step(1.0, f.stem)
            continue
        grid = ds.sample(f.stem).grid
        if int(grid.occupancy.sum()) != len(targets["E_min"]):
            raise UserError(f"{f}: {len(targets['E_min'])} voxels, but the dataset's {f.stem!r} has "
                            f"{int(grid.occupancy.sum())}: not the dataset this evaluation ran on")
        targets = {k: v for k, v in targets.items() if k not in (*GROUPS.values(), NOTE_KEY)}
        save_npz(f, **targets, **scoring_facts(ds, f.stem, grid))
        changed += 1
        if progress is not None:
            progress.step(1.0, f.stem)
    return changed


def recompute(evaluation_dir, data=None, progress=None) -> dict:
    """Recompute the breakdown of an evaluation's ``--out`` folder; rewrite its report.json / report.md (if any).

    data: the evaluated dataset's directory, to add the scoring facts to targets written without them (or None).
    """
    from ..core.errors import read_json
    from .evaluation_report import write_report

    out = Path(evaluation_dir)
    if not out.is_dir():
        raise UserError(f"{out}: evaluation directory not found")
    if data is not None:
        from .dataset import DatasetDir

        add_missing_facts(out / "predictions", DatasetDir(data), progress)
    breakdown = error_breakdown(out / "predictions")
    report_path = out / "report.json"
    if report_path.is_file():
        report = read_json(report_path)
        if not isinstance(report, dict) or "table1" not in report:
            raise UserError(f"{report_path}: not an evaluation report (no 'table1')")
        report["breakdown"] = breakdown
        write_report(out, report)
    else:
        from ..core.atomic_io import write_json

        write_json(out / "breakdown.json", breakdown, indent=1)
    return breakdown


def main(argv=None) -> int:
    from .evaluation_report import breakdown_markdown

    p = argparse.ArgumentParser(prog="python -m unipixie.training.error_breakdown",
                                description="where each method's log10 E error lies (by class, surface/interior, "
                                            "distance to a part boundary), recomputed from an evaluation's saved "
                                            "predictions; updates its report.json and report.md (or writes "
                                            "breakdown.json when there is no report)")
    p.add_argument("evaluation", metavar="EVAL_DIR", help="the --out directory of 'unipixie evaluate'")
    p.add_argument("--data", metavar="DIR", help="the evaluated dataset: adds the scoring facts (surface, distance to "
                                                 "a part boundary, class) to targets an older evaluation wrote without")
    args = p.parse_args(argv)
    from ..core.progress import Progress

    try:
        n = len(list((Path(args.evaluation) / "predictions" / "targets").glob("*.npz"))) if args.data else 0
        with Progress(total=max(n, 1), description="scoring facts", show_bar=bool(n)) as progress:
            breakdown = recompute(args.evaluation, args.data, progress)
    except UserError as exc:                                     # a cancellation included (CancelledError)
        print(f"error_breakdown: error: {exc}", file=sys.stderr)
        return exc.exit_code
    print("\n".join(breakdown_markdown(breakdown)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
