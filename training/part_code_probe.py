"""What a built dataset's feature grids carry about each part: a probe that *knows the parts* and reads their codes.

    python -m unipixie.training.part_code_probe DATASET --out probe.json

The procedural generator places each part's stiffness range by the part's *appearance code* u ∈ [0, 1], the same
number that set its colour, texture contrast and roughness (:mod:`unipixie.core.procedural.appearance`).  The
reference ``oracle_appearance`` of :mod:`.oracle` knows every voxel's part, the object's class and the visible
parts' codes, and bounds what any model can reach.  This probe asks the question between that bound and a trained
model: **if a model knew which voxels form which part, how well could it read the code from the features?**

For every part of every object it averages the part's *surface* voxels' features (a surface voxel has an
unoccupied 6-neighbour; interior voxels only copy their nearest surface voxel's features); per (class, part) it
fits a ridge map from that mean to the code on the training split (the codes are the target only) and predicts
the codes of the test split's parts.  The *part reader* reference is then :func:`.oracle.oracle_predictions` with
the predicted codes of the visible parts in place of the true ones, so its log10 E MSE is in the evaluation's
units (Table 1, averaged over α) and directly comparable with the oracle's and a model's.  The *part knower*
reference is the same with each visible part's code read as its (class, part) group's mean training code: it
knows the parts and reads nothing from their appearance.

What the probe is not: a method.  It uses the dataset's part labels, classes and codes, which no feature and no
model may read; it measures the features, not a model.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MIN_TRAINING_PARTS = 6
"""A (class, part) group needs at least this many training parts for its map; with fewer, its test parts are read
as the group's mean training code (or 0.5 when the group never occurs in training)."""

RIDGE_PENALTY = 1e-2
"""Ridge penalty per training part on the map's weights (not its offset), the features standardised per group:
mild, so that a group's map is determined where its features vary and stays finite where they do not."""


@dataclass
class PartRow:
    """One part of one object: who it is, its true code and the mean (D,) of its surface voxels' features."""

    object_id: str
    semantic_class: str
    part: str
    code: float
    mean_features: np.ndarray
    surface_voxels: int


def surface_mask(occupancy: np.ndarray) -> np.ndarray:
    """(K,) bool over the occupied voxels in ``np.argwhere`` order: True where a 6-neighbour is empty or outside.

    occupancy: (R, R, R) bool.
    """
    from scipy import ndimage

    occ = np.asarray(occupancy, bool)
    interior = ndimage.binary_erosion(occ, border_value=0)
    return ~interior[occ]


def part_rows(dataset, object_ids, codes_of=None, progress=None) -> list[PartRow]:
    """The :class:`PartRow` of every part with at least one surface voxel, over ``object_ids``.

    dataset: a :class:`.dataset.DatasetDir`; codes_of: annotation -> {part: code} (default
    :func:`.oracle.generator_codes`, which regenerates the procedural object).
    """
    from .oracle import generator_codes

    codes_of = codes_of or (lambda ann: generator_codes(ann)[2])
    rows = []
    for oid in object_ids:
        sample = dataset.sample(oid)
        part_ids, names = dataset.part_labels(oid)
        ann = dataset.annotation(oid)
        codes = codes_of(ann)
        surf = surface_mask(sample.grid.occupancy)
        feats = np.asarray(sample.grid.features, np.float64)
        for k, name in enumerate(names):
            m = (part_ids == k) & surf
            if m.any():
                rows.append(PartRow(oid, ann.semantic_class, name, float(codes[name]), feats[m].mean(axis=0),
                                    int(m.sum())))
        if progress is not None:
            progress.update(1)
    return rows


@dataclass
class CodeMap:
    """A (class, part) group's ridge map: code = clip(((f − mean) / scale) · weights + offset, 0, 1).

    mean / scale / weights: (D,) the group's training feature mean and standard deviation (1 where constant) and
    the weights on the standardised features; offset: the group's mean training code.
    """

    mean: np.ndarray
    scale: np.ndarray
    weights: np.ndarray
    offset: float

    def read(self, features: np.ndarray) -> float:
        return float(np.clip((features - self.mean) / self.scale @ self.weights + self.offset, 0.0, 1.0))


def fit_code_maps(rows: list[PartRow], penalty: float = RIDGE_PENALTY, min_parts: int = MIN_TRAINING_PARTS) -> dict:
    """(class, part) -> :class:`CodeMap` fitted on ``rows`` (ridge on standardised mean features), or a float (the
    group's mean code) where the group has fewer than ``min_parts`` rows."""
    groups = defaultdict(list)
    for r in rows:
        groups[(r.semantic_class, r.part)].append(r)
    maps = {}
    for key, g in groups.items():
        y = np.array([r.code for r in g])
        if len(g) < min_parts:
            maps[key] = float(y.mean())
            continue
        X = np.array([r.mean_features for r in g])
        mean, scale = X.mean(axis=0), X.std(axis=0)
        scale = np.where(scale > 1e-9, scale, 1.0)
        Z = (X - mean) / scale
        weights = np.linalg.solve(Z.T @ Z + penalty * len(g) * np.eye(Z.shape[1]), Z.T @ (y - y.mean()))
        maps[key] = CodeMap(mean, scale, weights, float(y.mean()))
    return maps


def read_codes(maps: dict, rows: list[PartRow]) -> np.ndarray:
    """(len(rows),) codes in [0, 1] the maps read from the rows' mean features (0.5 for an unknown group)."""
    out = []
    for r in rows:
        m = maps.get((r.semantic_class, r.part), 0.5)
        out.append(m.read(r.mean_features) if isinstance(m, CodeMap) else float(np.clip(m, 0.0, 1.0)))
    return np.asarray(out)


def reference_errors(dataset, object_ids, readings: dict, alphas=(0.0, 0.5, 1.0), draws: int = 200,
                     seed: int = 0, progress=None) -> dict:
    """Per-object log10 E MSE (averaged over ``alphas`` and the object's voxels, as Table 1) of the oracle with the
    true codes and of one reference per reading in ``readings`` ({name: {object id: {part: code}}}; parts missing
    there keep their true code, hidden parts are drawn as the oracle draws them, with the same draws for every
    reference of an object).  Returns {"oracle": (O,), name: (O,) ...}."""
    from . import oracle as oracle_mod

    alphas = np.asarray(alphas, np.float64)
    out = {"oracle": [], **{name: [] for name in readings}}
    for oid in object_ids:
        sample = dataset.sample(oid)
        part_ids, _ = dataset.part_labels(oid)
        ann = dataset.annotation(oid)
        label = ((1.0 - alphas)[:, None] * np.log10(sample.mpm.E_min)[None]
                 + alphas[:, None] * np.log10(sample.mpm.E_max)[None])
        settings = oracle_mod.OracleSettings(draws=int(draws), seed=int(seed))
        for name, codes in [("oracle", None)] + [(n, r.get(oid, {})) for n, r in readings.items()]:
            pred = oracle_mod.oracle_predictions(ann, part_ids, sample.grid.indices, sample.grid.geometry.resolution,
                                                 alphas, settings, codes=codes)[oracle_mod.ORACLE]["log10_E"]
            out[name].append(float(np.mean((pred - label) ** 2)))
        if progress is not None:
            progress.update(1)
    return {k: np.asarray(v) for k, v in out.items()}


def run_probe(root, train_split: str = "train", test_split: str = "test", draws: int = 200,
              max_test: int | None = None) -> dict:
    """The whole probe on a built dataset; returns the JSON-ready result (see the module docstring)."""
    from tqdm import tqdm

    from .dataset import DatasetDir

    ds = DatasetDir(root)
    train_ids, test_ids = ds.ids(train_split), ds.ids(test_split)
    if max_test:
        test_ids = test_ids[:max_test]
    with tqdm(total=len(train_ids) + 2 * len(test_ids), desc="part code probe", unit="object") as bar:
        train_rows = part_rows(ds, train_ids, progress=bar)
        test_rows = part_rows(ds, test_ids, progress=bar)
        maps = fit_code_maps(train_rows)
        read = read_codes(maps, test_rows)
        # no group reaches min_parts: every part is read as its (class, part) group's mean training code
        group_mean = read_codes(fit_code_maps(train_rows, min_parts=len(train_rows) + 1), test_rows)
        readings = {"part_reader": defaultdict(dict), "part_knower": defaultdict(dict)}
        for r, u, g in zip(test_rows, read, group_mean):
            readings["part_reader"][r.object_id][r.part] = float(u)
            readings["part_knower"][r.object_id][r.part] = float(g)
        errors = reference_errors(ds, test_ids, readings, draws=draws, progress=bar)
    truth = np.array([r.code for r in test_rows])
    return {
        "dataset": str(root), "train_objects": len(train_ids), "test_objects": len(test_ids),
        "train_parts": len(train_rows), "test_parts": len(test_rows),
        "groups_with_a_map": int(sum(isinstance(m, CodeMap) for m in maps.values())),
        "code_rms_part_reader": float(np.sqrt(np.mean((read - truth) ** 2))),
        "code_rms_group_mean": float(np.sqrt(np.mean((group_mean - truth) ** 2))),
        "code_spread": float(np.std(truth)),
        "logE_mse_oracle": float(errors["oracle"].mean()),
        "logE_mse_part_reader": float(errors["part_reader"].mean()),
        "logE_mse_part_knower": float(errors["part_knower"].mean()),
        "draws": int(draws), "penalty": RIDGE_PENALTY, "min_training_parts": MIN_TRAINING_PARTS,
    }


def main(argv=None) -> int:
    from ..core.errors import UserError

    p = argparse.ArgumentParser(prog="python -m unipixie.training.part_code_probe",
                                description="how well a reader that knows the parts reads their appearance codes "
                                            "from a built dataset's features, and the log E MSE that reaches")
    p.add_argument("dataset", help="built dataset directory (split.json, samples/, objects/)")
    p.add_argument("--train-split", default="train")
    p.add_argument("--test-split", default="test")
    p.add_argument("--draws", type=int, default=200, help="annotation draws per object for the references")
    p.add_argument("--max-test", type=int, default=None, help="only the first N test objects")
    p.add_argument("--out", help="write the result as JSON here")
    args = p.parse_args(argv)
    try:
        result = run_probe(args.dataset, args.train_split, args.test_split, args.draws, args.max_test)
    except UserError as exc:
        print(f"part_code_probe: error: {exc}", file=sys.stderr)
        return 2
    if args.out:
        from ..core.atomic_io import write_json

        write_json(Path(args.out), result, indent=1)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
