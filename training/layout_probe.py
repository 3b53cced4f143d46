"""How much of an object's interior part layout a classifier can read from its shape: a probe, not a method.

    python -m unipixie.training.layout_probe --data DATASET --out DIR [--draws 1000] [--per-object 3000]

Why.  :mod:`.oracle`'s ``oracle_surface_parts`` gives every occupied voxel the part of its nearest outer-surface
voxel and scores far worse than ``oracle_appearance``, which knows every voxel's true part; the difference is the
interior layout (a ball's core, a can's contents, a pot's soil), which no render shows.  This probe asks how much of
that layout can be *read from the shape*, by fitting a classifier and scoring its parts exactly as the oracle scores
its own.

What the probe knows, per test object (what ``oracle_surface_parts`` knows, read through a classifier):

- the semantic class (which classifier to use) and the variant's part names (the parts it may predict);
- the occupancy grid, and the part of every outer-surface voxel (what the renders show);
- the visible parts' appearance codes, only through the oracle's per-part conditional means
  (:func:`part_moments`, the same Monte-Carlo draws as :func:`.oracle.oracle_predictions`; hidden parts' codes
  drawn anew each time).

What it never reads at test time: an interior voxel's own part, or any other interior label; the true interior
parts serve only as training targets (on the train split) and to score the predictions.

Descriptors per occupied voxel (:func:`shape_descriptors`, :func:`object_layout`), from the occupancy and the
outer-surface parts only:

- the part of the nearest outer-surface voxel (:func:`.oracle.nearest_surface_parts`; categorical);
- the depth inside the solid: the Euclidean distance transform of the occupancy (voxels; outside the grid counts as
  empty, so an outer-surface voxel has depth 1), and that depth over the object's largest depth (dimensionless);
- the position in the object's occupied bounding box, 0..1 per axis (x, y, z; z up);
- the bounding box's extents (voxels, per axis).

Outer-surface voxels keep their own (visible) part, as in ``oracle_surface_parts``.  For the interior voxels one
small torch MLP per semantic class (:class:`LayoutReader`; deterministic on one thread), fitted on the training
split's interior voxels (at most ``per_object`` per object, stratified by part so that rare interior parts are kept,
and weighted back to the true part frequencies: :func:`training_rows`), predicts the part among the object's own
part names.

Scoring is the oracle's: each voxel gets its predicted part's conditional mean (:func:`predictions_from_parts`),
written in the evaluation's format and scored by :func:`.evaluate.table1` (Table 1: per object the log10 E MSE over
the occupied voxels, averaged over α = 0, 0.5, 1, then the mean over objects) and by
:func:`.error_breakdown.error_breakdown` (per class, surface vs. interior voxels).  Methods written:

``oracle_appearance``
    the floor: every voxel's true part (recomputed here from the same moments);
``oracle_surface_parts``
    the nearest-surface rule (recomputed here);
``layout_probe``
    the classifier's most probable part, with the depth descriptors;
``layout_probe_no_depth``
    the same without the two depth columns (position, extents and nearest-surface part only);
``layout_probe_soft``
    with depth, each voxel the posterior-weighted mean of the parts' conditional means (the MSE-optimal reading of
    the same posterior; material: the most probable part's).

``layout_probe`` is a *learned reference, not a floor*: its MSE is what one particular classifier reaches from these
descriptors, so it shows that at least this much of the layout is readable from the shape; a better reader may go
lower (never below ``oracle_appearance``).

Units: log10 E in log10 Pa, log10 ρ in log10 kg/m³, ν dimensionless; depths and extents in voxels; positions and
relative depth dimensionless; interior part accuracies are fractions of interior voxels.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import UserError

CONTINUOUS = ("depth", "depth_rel", "pos_x", "pos_y", "pos_z", "extent_x", "extent_y", "extent_z")
"""Names of the continuous descriptor columns of :func:`shape_descriptors`, in order."""

DEPTH_COLUMNS = (0, 1)
"""The depth columns of :data:`CONTINUOUS` (left out by ``layout_probe_no_depth``)."""

PROBE, PROBE_NO_DEPTH, PROBE_SOFT = "layout_probe", "layout_probe_no_depth", "layout_probe_soft"
"""Names of the methods this probe writes (besides the two oracle references)."""

ALPHAS = (0.0, 0.5, 1.0)
"""The α values the predictions are written and scored at (Table 1's)."""

MLP = {"hidden": 64, "layers": 2, "epochs": 8, "batch": 2048, "lr": 3e-3}
"""The classifier's settings (recorded in ``layout_probe.json``)."""


# =========================================================================== descriptors
def shape_descriptors(indices: np.ndarray, resolution: int) -> np.ndarray:
    """(K, 8) float64 descriptors of the occupied voxels ``indices`` (K, 3) int of a ``resolution``³ grid.

    Columns (:data:`CONTINUOUS`): depth (Euclidean distance to the nearest empty voxel centre, voxels; outside the
    grid counts as empty, so an outer-surface voxel has 1), depth over the object's largest depth, position in the
    occupied bounding box (0..1 per axis; 0.5 on an axis one voxel thick), bounding-box extents (voxels).
    """
    from scipy import ndimage

    idx = np.asarray(indices, np.int64).reshape(-1, 3)
    out = np.zeros((len(idx), len(CONTINUOUS)), np.float64)
    if len(idx) == 0:
        return out
    occ = np.zeros((resolution + 2,) * 3, bool)               # one empty voxel of padding: the grid's edge is empty
    occ[idx[:, 0] + 1, idx[:, 1] + 1, idx[:, 2] + 1] = True
    depth = ndimage.distance_transform_edt(occ)[idx[:, 0] + 1, idx[:, 1] + 1, idx[:, 2] + 1]
    lo, hi = idx.min(axis=0), idx.max(axis=0)
    span = hi - lo
    out[:, 0] = depth
    out[:, 1] = depth / depth.max()
    out[:, 2:5] = np.where(span > 0, (idx - lo) / np.maximum(span, 1), 0.5)
    out[:, 5:8] = span + 1
    return out


@dataclass
class ObjectLayout:
    """One object's occupied voxels as the probe sees them.  K occupied voxels, P parts.

    part_names: (P,) str, the annotation's part order.  part_ids: (K,) int64 true part per voxel, an index into
    ``part_names`` (training targets and scoring only; the reader never reads it).  surface: (K,) bool, outer-surface
    voxel.  nearest: (K,) int64 part of the nearest outer-surface voxel (the voxel's own on the surface).
    descriptors: (K, 8) float64 :func:`shape_descriptors`.
    """

    object_id: str
    semantic_class: str
    part_names: list[str]
    part_ids: np.ndarray
    surface: np.ndarray
    nearest: np.ndarray
    descriptors: np.ndarray


def object_layout(object_id: str, semantic_class: str, part_names, part_ids: np.ndarray, indices: np.ndarray,
                  resolution: int) -> ObjectLayout:
    """The :class:`ObjectLayout` of one object.

    part_names: (P,) str; part_ids: (K,) int into ``part_names``; indices: (K, 3) int occupied voxels of a
    ``resolution``³ grid.  Raises :class:`UserError` if the labels do not fit the voxels or the names.
    """
    from .oracle import nearest_surface_parts, on_outer_surface

    part_ids = np.asarray(part_ids, np.int64)
    names = [str(n) for n in part_names]
    if len(part_ids) != len(indices):
        raise UserError(f"{object_id}: {len(part_ids)} part labels for {len(indices)} occupied voxels")
    if len(part_ids) and (part_ids.min() < 0 or part_ids.max() >= len(names)):
        raise UserError(f"{object_id}: part labels outside 0..{len(names) - 1} (parts {', '.join(names)})")
    return ObjectLayout(object_id, str(semantic_class), names, part_ids, on_outer_surface(indices, resolution),
                        nearest_surface_parts(part_ids, indices, resolution), shape_descriptors(indices, resolution))


def load_layout(ds, object_id: str) -> tuple:
    """(:class:`ObjectLayout`, sample, annotation) of one object of a :class:`.dataset.DatasetDir` ``ds``."""
    sample = ds.sample(object_id)
    part_ids, names = ds.part_labels(object_id)
    ann = ds.annotation(object_id)
    if list(names) != list(ann.part_names):
        raise UserError(f"{ds.root}: {object_id!r}'s part labels name parts {', '.join(names)}, its annotation "
                        f"{', '.join(ann.part_names)}")
    layout = object_layout(object_id, ann.semantic_class, names, part_ids, sample.grid.indices,
                           sample.grid.geometry.resolution)
    return layout, sample, ann


def training_rows(layout: ObjectLayout, per_object: int, rng: np.random.Generator) -> tuple:
    """(rows (n,) int64, weights (n,) float64) of one object's interior voxels to train on, n ≤ ``per_object``.

    Stratified: each interior part gets an equal share of ``per_object`` (what a small part leaves over goes to the
    others); a voxel's weight is its part's interior count over its sampled count, so the weighted rows have the
    object's true interior part frequencies.
    """
    interior = np.flatnonzero(~layout.surface)
    if len(interior) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    parts = layout.part_ids[interior]
    groups = sorted((interior[parts == p] for p in np.unique(parts)), key=len)
    budget, rows, weights = int(per_object), [], []
    for i, g in enumerate(groups):
        take = min(len(g), budget // (len(groups) - i))
        budget -= take
        pick = rng.choice(g, take, replace=False) if take < len(g) else g
        rows.append(pick)
        weights.append(np.full(len(pick), len(g) / max(len(pick), 1)))
    return np.concatenate(rows), np.concatenate(weights)


# =========================================================================== the classifier
class _MLP:
    """A small torch network (:data:`MLP`): standardised continuous columns + one-hot nearest part -> part logits.

    Inputs X: (n, C + 1) float64, C continuous columns, then the nearest part's code 0..n_nearest-1.  Outputs: one of
    ``n_parts`` classes.  Seeded by ``seed`` (deterministic on one thread).
    """

    def __init__(self, n_nearest: int, n_parts: int, seed: int, epochs: int = MLP["epochs"]):
        self.n_nearest, self.n_parts, self.seed, self.epochs = n_nearest, n_parts, seed, epochs

    def _inputs(self, X: np.ndarray):
        """(n, C + n_nearest) float32 tensor: standardised continuous columns, one-hot nearest part."""
        import torch

        cont = (X[:, :-1] - self.mean) / self.scale
        onehot = np.eye(self.n_nearest)[X[:, -1].astype(np.int64)]
        return torch.as_tensor(np.concatenate([cont, onehot], axis=1), dtype=torch.float32)

    def fit(self, X: np.ndarray, y: np.ndarray, w: np.ndarray) -> "_MLP":
        """X (n, C + 1) float64; y (n,) int class 0..n_parts-1; w (n,) float sample weights (weighted cross-entropy)."""
        import torch

        torch.manual_seed(self.seed)
        w = w / w.mean()
        self.mean = np.average(X[:, :-1], axis=0, weights=w)
        self.scale = np.sqrt(np.average((X[:, :-1] - self.mean) ** 2, axis=0, weights=w))
        self.scale = np.where(self.scale > 1e-9, self.scale, 1.0)
        Z = self._inputs(X)
        hidden = MLP["hidden"]
        self.net = torch.nn.Sequential(torch.nn.Linear(Z.shape[1], hidden), torch.nn.ReLU(),
                                       torch.nn.Linear(hidden, hidden), torch.nn.ReLU(),
                                       torch.nn.Linear(hidden, self.n_parts))
        opt = torch.optim.Adam(self.net.parameters(), lr=MLP["lr"])
        Y, W = torch.as_tensor(y, dtype=torch.int64), torch.as_tensor(w, dtype=torch.float32)
        g = torch.Generator().manual_seed(self.seed)
        batch = MLP["batch"]
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, self.epochs * max(1, -(-len(y) // batch)))
        for _ in range(self.epochs):
            order = torch.randperm(len(y), generator=g)
            for s in range(0, len(y), batch):
                b = order[s:s + batch]
                loss = (torch.nn.functional.cross_entropy(self.net(Z[b]), Y[b], reduction="none") * W[b]).mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
                sched.step()
        return self

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        """(n, n_parts) float64 class probabilities of the rows X (n, C + 1)."""
        import torch

        with torch.no_grad():
            return torch.softmax(self.net(self._inputs(X)), dim=1).double().numpy()


class LayoutReader:
    """Per semantic class, an MLP from shape descriptors to the part of an interior voxel.

    use_depth: whether the depth columns are used.  per_object: interior voxels sampled per training object
    (:func:`training_rows`).  seed: sampling and fitting seed.  epochs: passes of the MLP over its rows (batches of
    2048; a small training set needs more).  A class's vocabulary is the sorted union of its training objects' part
    names; a part name the class never had in training is one extra nearest-part code, never predicted.
    """

    def __init__(self, use_depth: bool = True, per_object: int = 3000, seed: int = 0, epochs: int = MLP["epochs"]):
        self.use_depth, self.per_object, self.seed, self.epochs = use_depth, int(per_object), seed, int(epochs)
        self.columns = [i for i in range(len(CONTINUOUS)) if use_depth or i not in DEPTH_COLUMNS]
        self.vocab: dict = {}        # class -> [part names]
        self.models: dict = {}       # class -> fitted _MLP, or an int (the only part seen in training)

    def _X(self, layout: ObjectLayout, rows: np.ndarray, vocab: list) -> np.ndarray:
        """(n, C + 1) float64 inputs of ``rows``: the used descriptor columns, then the nearest part's vocab code."""
        code = np.array([vocab.index(n) if n in vocab else len(vocab) for n in layout.part_names])
        return np.concatenate([layout.descriptors[rows][:, self.columns],
                               code[layout.nearest[rows]][:, None].astype(np.float64)], axis=1)

    def fit(self, layouts) -> "LayoutReader":
        """Fit on training :class:`ObjectLayout` s (their true interior parts are the targets)."""
        rng = np.random.default_rng(self.seed)
        by_class: dict = {}
        for lay in layouts:
            by_class.setdefault(lay.semantic_class, []).append(lay)
        for cls, lays in sorted(by_class.items()):
            vocab = sorted({n for lay in lays for n in lay.part_names})
            Xs, ys, ws = [], [], []
            for lay in lays:
                rows, w = training_rows(lay, self.per_object, rng)
                if len(rows):
                    Xs.append(self._X(lay, rows, vocab))
                    ys.append(np.array([vocab.index(lay.part_names[p]) for p in lay.part_ids[rows]]))
                    ws.append(w)
            self.vocab[cls] = vocab
            if not ys:
                continue
            X, y, w = np.concatenate(Xs), np.concatenate(ys), np.concatenate(ws)
            seen = np.unique(y)
            if len(seen) == 1:
                self.models[cls] = int(seen[0])
                continue
            self.models[cls] = _MLP(len(vocab) + 1, len(vocab), self.seed, epochs=self.epochs).fit(X, y, w)
        return self

    def predict_proba(self, layout: ObjectLayout) -> np.ndarray:
        """(K, P) float64 probability of each of the object's P parts per voxel (rows sum to 1).

        Outer-surface voxels: their own part with probability 1.  Interior voxels: the class's classifier,
        renormalised over the object's own part names; a class without a classifier (never seen in training, or no
        interior voxels there), or a voxel whose classifier puts no mass on the object's parts, falls back on the
        nearest-surface part.  Reads ``layout.part_ids`` nowhere.
        """
        K, P = len(layout.nearest), len(layout.part_names)
        prob = np.zeros((K, P))
        prob[np.arange(K), layout.nearest] = 1.0           # the nearest-surface rule (exact on the surface)
        rows = np.flatnonzero(~layout.surface)
        model = self.models.get(layout.semantic_class)
        if model is None or len(rows) == 0:
            return prob
        vocab = self.vocab[layout.semantic_class]
        cols = np.array([vocab.index(n) if n in vocab else -1 for n in layout.part_names])
        if isinstance(model, int):
            full = np.zeros((len(rows), len(vocab)))
            full[:, model] = 1.0
        else:
            full = model.predict_proba(self._X(layout, rows, vocab))
        mine = np.where(cols[None] >= 0, full[:, np.maximum(cols, 0)], 0.0)     # (n, P): the object's parts only
        total = mine.sum(axis=1, keepdims=True)
        ok = total[:, 0] > 1e-12
        sub = prob[rows]
        sub[ok] = mine[ok] / total[ok]
        prob[rows] = sub
        return prob


# =========================================================================== scoring as the oracle does
def part_moments(annotation, part_ids: np.ndarray, indices: np.ndarray, resolution: int, settings=None) -> dict:
    """The per-part conditional means :func:`.oracle.oracle_predictions` predicts from, with the same draws
    (:func:`.oracle.visible_part_moments`: the visible parts' codes known).

    part_ids: (K,) int part per occupied voxel; indices: (K, 3) int voxels; settings: :class:`.oracle.OracleSettings`
    (None: its defaults).  Returns quantity (``E``, ``density``, ``nu``) -> (lo, hi), each (P,) float64 in evaluation
    channels (log10 Pa, log10 kg/m³, ν), and ``material`` (P,) class ids; P = the annotation's parts.
    """
    from . import oracle as O

    return O.visible_part_moments(annotation, part_ids, indices, resolution, settings)


def predictions_from_parts(moments: dict, alphas, part: np.ndarray | None = None,
                           prob: np.ndarray | None = None) -> dict:
    """Predictions in the evaluation's saved format from per-part moments (:func:`part_moments`); give one of:

    part: (K,) int one part per voxel -> that part's conditional mean at each α (the oracle's rule); prob: (K, P)
    part probabilities -> their weighted mean of the parts' conditional means (material: the most probable part's).
    alphas: (A,).  Returns {"alphas" (A,), "log10_E" / "log10_density" / "nu" (A, K) float32 (log10 Pa,
    log10 kg/m³, ν), "material" (A, K) int16, "runtime_s" 0}.
    """
    from .oracle import _CHANNELS

    if (part is None) == (prob is None):
        raise ValueError("give exactly one of part and prob")
    a = np.asarray(alphas, np.float64)
    part = np.asarray(np.argmax(prob, axis=1) if part is None else part, np.int64)
    d = {"alphas": a, "material": np.tile(moments["material"][part], (len(a), 1)).astype(np.int16),
         "runtime_s": np.float64(0.0)}
    for q, key in _CHANNELS.items():
        lo, hi = moments[q]
        per_part = (1.0 - a)[:, None] * lo[None] + a[:, None] * hi[None]          # (A, P)
        d[key] = (per_part @ prob.T if prob is not None else per_part[:, part]).astype(np.float32)
    return d


def _interior_hits(pred_part: np.ndarray, layout: ObjectLayout) -> tuple:
    """(interior voxels whose predicted part is the true one, interior voxels) of one object."""
    inner = ~layout.surface
    return int((pred_part[inner] == layout.part_ids[inner]).sum()), int(inner.sum())


def _accuracies(rows: list) -> dict:
    """Interior part accuracies (fractions of interior voxels) from per-object (class, right, total) rows."""
    right, total = sum(r[1] for r in rows), sum(r[2] for r in rows)
    per_object = [r[1] / r[2] for r in rows if r[2]]
    by_class: dict = {}
    for cls, r, tot in rows:
        c = by_class.setdefault(cls, [0, 0])
        c[0] += r
        c[1] += tot
    return {"interior_part_accuracy_pooled": right / total if total else None,
            "interior_part_accuracy_object_mean": float(np.mean(per_object)) if per_object else None,
            "interior_part_accuracy_by_class": {c: (v[0] / v[1] if v[1] else None)
                                                for c, v in sorted(by_class.items())}}


def _summary(t1: dict, b: dict) -> dict:
    """One method's entry of ``layout_probe.json``: its Table 1 metrics ``t1`` and error breakdown ``b`` condensed.

    MSEs of log10 E in (log10 Pa)², of log10 ρ in (log10 kg/m³)², of ν dimensionless; material_acc a fraction.
    """
    kind = b["by_voxel_kind"]
    return {
        "logE_mse": t1["logE_mse"], "logE_mse_std": t1["logE_mse_std"], "logE_mse_per_alpha": t1["logE_mse_per_alpha"],
        "logrho_mse": t1["logrho_mse"], "nu_mse": t1["nu_mse"], "material_acc": t1["material_acc"],
        "logE_mse_surface": {k: kind["surface"][k] for k in ("logE_mse_object_mean", "logE_mse_pooled")},
        "logE_mse_interior": {k: kind["interior"][k] for k in ("logE_mse_object_mean", "logE_mse_pooled",
                                                              "share_object_weighted")},
        "logE_mse_by_class": {c: v["logE_mse_object_mean"] for c, v in sorted(b["by_class"].items())},
        "logE_mse_by_boundary_distance": {c: v["logE_mse_pooled"] for c, v in b["by_boundary_distance"].items()},
    }


# =========================================================================== the whole probe
def run_probe(data, out, draws: int = 1000, per_object: int = 3000, seed: int = 0, max_train: int = 0,
              max_test: int = 0, keep_predictions: bool = False, log=print) -> dict:
    """Fit on the train split, score the test split (module docstring); writes ``out``/layout_probe.json, returns it.

    data: a built dataset directory (:class:`.dataset.DatasetDir`).  draws: annotation draws per test object for the
    conditional means (≥ 10).  per_object: interior voxels sampled per training object.  max_train / max_test: only
    the first N objects of the split (0: all).  keep_predictions: keep ``out``/predictions/ (the evaluation's format)
    instead of a temporary folder.  log: progress lines (None: silent).  Raises :class:`UserError` on bad input, before
    any fitting.
    """
    from ..core.atomic_io import save_npz, write_json
    from .dataset import DatasetDir
    from .error_breakdown import error_breakdown, scoring_facts
    from .evaluate import table1
    from .oracle import ORACLE, ORACLE_SURFACE, OracleSettings

    t0 = time.perf_counter()
    settings = OracleSettings(draws=draws, seed=seed)       # refuses draws < 10
    if int(per_object) < 1:
        raise UserError(f"per_object must be at least 1, got {per_object}")
    if int(max_train) < 0 or int(max_test) < 0:
        raise UserError(f"max_train / max_test must be 0 (all) or positive, got {max_train} / {max_test}")
    ds = DatasetDir(data)
    train_ids, test_ids = ds.ids("train"), ds.ids("test")
    train_ids = train_ids[:max_train] if max_train else train_ids
    test_ids = test_ids[:max_test] if max_test else test_ids
    for split, ids in (("train", train_ids), ("test", test_ids)):
        if not ids:
            raise UserError(f"{ds.root}: the {split} split holds no objects; the probe needs both a train and a test "
                            "split")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    train = []
    for n, oid in enumerate(train_ids):
        train.append(load_layout(ds, oid)[0])
        if log and (n + 1) % 200 == 0:
            log(f"train descriptors {n + 1}/{len(train_ids)} ({time.perf_counter() - t0:.0f} s)")
    t_desc = time.perf_counter() - t0
    readers, fit_s = {}, {}
    for name, use_depth in ((PROBE, True), (PROBE_NO_DEPTH, False)):
        t = time.perf_counter()
        readers[name] = LayoutReader(use_depth, per_object, seed).fit(train)
        fit_s[name] = time.perf_counter() - t
        if log:
            log(f"fitted {name} in {fit_s[name]:.0f} s")
    del train
    if keep_predictions:
        pred_root = out / "predictions"
        shutil.rmtree(pred_root, ignore_errors=True)
    else:
        pred_root = Path(tempfile.mkdtemp(prefix="layout_probe_"))
    hits: dict = {}                        # method -> [(class, right, total) per test object]
    t_test = time.perf_counter()
    try:
        for n, oid in enumerate(test_ids):
            layout, sample, ann = load_layout(ds, oid)
            m = sample.mpm
            targets = {"E_min": m.E_min, "E_max": m.E_max, "nu_min": m.nu_min, "nu_max": m.nu_max,
                       "density_min": m.density_min, "density_max": m.density_max, "material": m.material}
            save_npz(pred_root / "targets" / f"{oid}.npz", **targets, **scoring_facts(ds, oid, sample.grid))
            moments = part_moments(ann, layout.part_ids, sample.grid.indices, sample.grid.geometry.resolution,
                                   settings)
            parts = {ORACLE: layout.part_ids, ORACLE_SURFACE: layout.nearest}
            for name, reader in readers.items():
                prob = reader.predict_proba(layout)
                parts[name] = prob.argmax(axis=1)
                if name == PROBE:
                    soft = predictions_from_parts(moments, ALPHAS, prob=prob)
                    save_npz(pred_root / PROBE_SOFT / f"{oid}.npz", **soft)
            for name, part in parts.items():
                save_npz(pred_root / name / f"{oid}.npz", **predictions_from_parts(moments, ALPHAS, part=part))
                if name != ORACLE:
                    hits.setdefault(name, []).append((layout.semantic_class, *_interior_hits(part, layout)))
            if log and (n + 1) % 20 == 0:
                log(f"test {n + 1}/{len(test_ids)} ({time.perf_counter() - t0:.0f} s)")
        t1 = table1(pred_root)
        breakdown = error_breakdown(pred_root)
    finally:
        if not keep_predictions:
            shutil.rmtree(pred_root, ignore_errors=True)
    methods = {name: {**_summary(t, breakdown["methods"][name]), **(_accuracies(hits[name]) if name in hits else {})}
               for name, t in t1.items()}
    result = {"format": "unipixie.layout_probe/1", "dataset": str(data), "classifier": {"kind": "torch_mlp", **MLP},
              "train_objects": len(train_ids), "test_objects": len(test_ids), "draws": int(draws),
              "per_object": int(per_object), "seed": int(seed), "alphas": list(ALPHAS),
              "descriptors": list(CONTINUOUS) + ["nearest_surface_part"], "methods": methods,
              "seconds": {"total": time.perf_counter() - t0, "train_descriptors": t_desc, "fit": fit_s,
                          "test_and_scoring": time.perf_counter() - t_test}}
    write_json(out / "layout_probe.json", result, indent=1)
    return result


def main(argv=None) -> int:
    import os

    p = argparse.ArgumentParser(prog="python -m unipixie.training.layout_probe",
                                description="how much of the interior part layout a small MLP reads from the shape "
                                            "(occupancy + visible surface parts), scored as the oracle is scored")
    p.add_argument("--data", required=True, help="built procedural dataset (split.json, samples/, objects/)")
    p.add_argument("--out", required=True, help="output directory (layout_probe.json)")
    p.add_argument("--draws", type=int, default=1000, help="annotation draws per test object for the moments (>= 10)")
    p.add_argument("--per-object", type=int, default=3000, help="interior voxels sampled per training object")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-train", type=int, default=0, help="only the first N training objects (0: all)")
    p.add_argument("--max-test", type=int, default=0, help="only the first N test objects (0: all)")
    p.add_argument("--keep-predictions", action="store_true", help="keep OUT/predictions/ (evaluation format)")
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    try:
        result = run_probe(args.data, args.out, args.draws, args.per_object, args.seed, args.max_train, args.max_test,
                           args.keep_predictions)
    except UserError as exc:
        print(f"layout_probe: error: {exc}", file=sys.stderr)
        return 2
    for name, m in result["methods"].items():
        acc = m.get("interior_part_accuracy_pooled")
        print(f"{name:28s} logE MSE {m['logE_mse']:.4f}  surface {m['logE_mse_surface']['logE_mse_object_mean']:.4f}"
              f"  interior {m['logE_mse_interior']['logE_mse_object_mean']:.4f}"
              + (f"  interior part acc {acc:.3f}" if acc is not None else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
