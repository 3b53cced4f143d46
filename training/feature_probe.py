"""What the feature grids carry: a ridge probe from surface-voxel features to the procedural generator's part
appearance codes, and the sharpness of part boundaries.

    python -m unipixie.training.feature_probe --objects 12 --out probe.json      (needs bpy)

For each of ``--objects`` procedural objects (the training generator, :mod:`unipixie.core.procedural`) the object
is exported, imported and rendered *once* with Cycles and its passes (:mod:`unipixie.core.blender_io.render`);
the same views are lifted by the offline ViT (as the shipped model's features), the appearance extractor and the
concatenation.  A ridge regression (numpy; the penalty chosen by leave-one-object-out on the training objects)
is fitted from the surface voxels' features to their part's appearance code on the training objects and scored
on held-out objects (split by object).  The generator's codes are the probe's *target* only: the features are
made by :func:`unipixie.core.features.features_from_views` from the rendered views.

Also measured: the RMS error on surface voxels next to another part, and :func:`transition_width` of a box cut
in two materials at x = 0 (the test object of tests/test_appearance_features.py).
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

EXTRACTORS = ("offline", "appearance", "appearance+vit")
RIDGE_PENALTIES = (1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0)
"""Ridge penalties tried (on standardised features, per voxel count)."""


def transition_width(indices: np.ndarray, features: np.ndarray, occupancy: np.ndarray, axis: int = 0,
                     boundary: float | None = None, margin: int = 16) -> float:
    """Width in voxels over which the features change from one side of a plane boundary to the other.

    indices / features: (K, 3) occupied voxel indices and (K, D) features (a grid's ``indices`` / ``features``);
    occupancy: (R, R, R) bool.  The boundary is the plane between slices ``boundary - 1`` and ``boundary``
    along ``axis`` (default R / 2).  Each surface voxel gets ``t`` = its features' position between the mean
    features of the surface voxels farther than ``margin`` slices on either side (0 and 1); per slice the
    median ``t``; the width is the distance between the slices (linearly interpolated) where that profile
    crosses 0.1 and 0.9.  A perfect step between two neighbouring slices gives 0.8.
    """
    from ..core.lift import surface_mask

    R = occupancy.shape[0]
    b = int(R // 2 if boundary is None else boundary)
    surf = surface_mask(occupancy)[tuple(np.asarray(indices).T)]
    x = np.asarray(indices)[:, axis]
    f = np.asarray(features, dtype=np.float64)
    a_side, b_side = surf & (x < b - margin), surf & (x >= b + margin)
    if not a_side.any() or not b_side.any():
        raise ValueError("no surface voxels beyond the margin on one side of the boundary")
    ma, mb = f[a_side].mean(axis=0), f[b_side].mean(axis=0)
    d = mb - ma
    t = (f - ma) @ d / max(float(d @ d), 1e-12)
    slices = np.arange(b - margin, b + margin)
    prof = np.array([np.median(t[surf & (x == i)]) if np.any(surf & (x == i)) else np.nan for i in slices])
    ok = np.isfinite(prof)
    slices, prof = slices[ok], np.maximum.accumulate(prof[ok])        # monotone envelope from side A to side B

    def crossing(q):
        k = int(np.argmax(prof >= q))
        if k == 0:
            return float(slices[0])
        return float(slices[k - 1] + (q - prof[k - 1]) / max(prof[k] - prof[k - 1], 1e-12))

    return crossing(0.9) - crossing(0.1)


def ridge_fit(X: np.ndarray, y: np.ndarray, penalty: float):
    """Ridge regression with an intercept: returns (w (D,), b)."""
    mu, ym = X.mean(axis=0), y.mean()
    Xc = X - mu
    w = np.linalg.solve(Xc.T @ Xc + penalty * len(X) * np.eye(X.shape[1]), Xc.T @ (y - ym))
    return w, ym - mu @ w


def probe(objects: list, train: list, test: list) -> dict:
    """objects: [{"features": {extractor: (S, D)}, "code": (S,), "boundary": (S,) bool}] of surface voxels.
    Ridge probes per extractor (penalty by leave-one-object-out on ``train``), scored on ``test``."""
    out = {}
    for name in objects[0]["features"]:
        Xs = [o["features"][name].astype(np.float64) for o in objects]
        ys = [o["code"].astype(np.float64) for o in objects]
        best = None
        for lam in RIDGE_PENALTIES:
            errs = []
            for hold in train:
                rest = [i for i in train if i != hold]
                w, b = ridge_fit(np.concatenate([Xs[i] for i in rest]), np.concatenate([ys[i] for i in rest]), lam)
                errs.append(Xs[hold] @ w + b - ys[hold])
            rms = float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))
            if best is None or rms < best[0]:
                best = (rms, lam)
        w, b = ridge_fit(np.concatenate([Xs[i] for i in train]), np.concatenate([ys[i] for i in train]), best[1])
        err = np.concatenate([Xs[i] @ w + b - ys[i] for i in test])
        near = np.concatenate([objects[i]["boundary"] for i in test])
        out[name] = {"test_rms": float(np.sqrt(np.mean(err ** 2))),
                     "test_rms_next_to_another_part": float(np.sqrt(np.mean(err[near] ** 2))) if near.any() else None,
                     "test_rms_elsewhere": float(np.sqrt(np.mean(err[~near] ** 2))),
                     "penalty": best[1], "loo_train_rms": best[0], "dim": int(Xs[0].shape[1])}
    codes = np.concatenate([objects[i]["code"] for i in test])
    train_mean = float(np.concatenate([objects[i]["code"] for i in train]).mean())
    out["code_spread_test"] = float(codes.std())
    out["train_mean_predictor_test_rms"] = float(np.sqrt(np.mean((codes - train_mean) ** 2)))
    return out


def _object_features(index: int, seed: int, render_settings, extractors: dict, workdir: Path):
    """Surface-voxel features of procedural object ``index`` by every extractor from one rendering, and the
    probe's targets (appearance codes, next-to-another-part flags) from the generator."""
    from ..core import procedural
    from ..core.blender_io import render
    from ..core.blender_io.scene_import import loaded_objects
    from ..core.features import features_from_views
    from ..core.jobs import run_job
    from ..core.lift import surface_mask
    from .dataset import voxel_part_labels

    obj = procedural.generate(index, seed)
    glb = obj.export_glb(workdir / f"{obj.object_id}.glb")
    with loaded_objects(glb) as objs:
        views = run_job(render.render_job(objs, render_settings))
    # ---- features: from the views only ----
    _, occ, part_ids = voxel_part_labels(obj, 64)          # occupancy from the mesh; part ids are targets only
    feats = {name: features_from_views(views, occ, ext).features for name, ext in extractors.items()}
    # ---- targets ----
    surf = surface_mask(occ)
    idx = np.argwhere(occ)
    on_surface = surf[tuple(idx.T)]
    codes = np.array([p.appearance.code for p in obj.parts], dtype=np.float64)
    labels = np.full(occ.shape, -1, dtype=np.int64)
    labels[tuple(idx.T)] = part_ids
    near = np.zeros(len(idx), dtype=bool)
    for axis in range(3):
        for step in (-1, 1):
            other = np.roll(labels, step, axis=axis)[tuple(idx.T)]
            near |= (other >= 0) & (other != part_ids)
    return {"features": {k: v[on_surface].astype(np.float32) for k, v in feats.items()},
            "code": codes[part_ids[on_surface]], "boundary": near[on_surface], "object_id": obj.object_id,
            "parts": len(obj.parts)}


def split_box_widths(render_settings, extractors: dict) -> dict:
    """:func:`transition_width` of the two-material box (x < 0 red rough, x > 0 blue metallic) per extractor."""
    from ..core.blender_io import render
    from ..core.blender_io.render_passes import split_box
    from ..core.blender_io.scene_import import temporary_scene
    from ..core.features import features_from_views, occupancy_of
    from ..core.jobs import run_job
    from ..core.normalise import Normalisation

    with temporary_scene("UniPixie probe box") as scene:
        obj = split_box(scene)
        info = render.describe_subject([obj])
        views = run_job(render.render_job([obj], render_settings))
    occ = occupancy_of(Normalisation.from_matrix(views.normalisation).to_normalised(info.vertices), info.faces).occupancy
    out = {}
    for name, ext in extractors.items():
        g = features_from_views(views, occ, ext)
        out[name] = round(transition_width(g.indices, g.features.astype(np.float32), occ), 2)
    return out


def main(argv=None) -> int:
    import argparse

    from ..core import extractors as ex
    from ..core.blender_io.render import RenderSettings

    p = argparse.ArgumentParser(prog="python -m unipixie.training.feature_probe", description=__doc__.split("\n")[0])
    p.add_argument("--objects", type=int, default=12, help="procedural objects (default 12)")
    p.add_argument("--test", type=int, default=4, help="of which held out for the test (default 4)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--resolution", type=int, default=160)
    p.add_argument("--samples", type=int, default=2)
    p.add_argument("--out", help="write the results as JSON here")
    args = p.parse_args(argv)
    if args.objects < args.test + 2:
        print("feature_probe: error: need at least two training objects", file=sys.stderr)
        return 2
    rs = RenderSettings(view_count=args.views, resolution=args.resolution, samples=args.samples, engine="cycles",
                        device="cpu", passes=True)
    extractors = {name: ex.make(name) for name in EXTRACTORS}
    t0 = time.perf_counter()
    objects = []
    with tempfile.TemporaryDirectory(prefix="unipixie-probe-") as tmp:
        for i in range(args.objects):
            objects.append(_object_features(i, args.seed, rs, extractors, Path(tmp)))
            print(f"object {i + 1}/{args.objects}: {objects[-1]['object_id']} ({objects[-1]['parts']} parts, "
                  f"{len(objects[-1]['code'])} surface voxels), {time.perf_counter() - t0:.0f} s", flush=True)
    test = list(range(args.objects - args.test, args.objects))
    train = [i for i in range(args.objects) if i not in test]
    result = {"probe": probe(objects, train, test), "boundary_width_voxels": split_box_widths(rs, extractors),
              "objects": [o["object_id"] for o in objects], "train": train, "test": test,
              "settings": vars(args), "seconds": round(time.perf_counter() - t0, 1)}
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        from ..core.atomic_io import write_text

        write_text(Path(args.out), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
