"""Rebuilding a built dataset's ground truth with other settings, in place or on another machine.

A dataset built with ``--tiny-ground-truth`` (6 cells, 32 anchors: minutes for thousands of objects) can be
given the full ground truth later without rendering again: the objects are procedural, so each one is
generated again from ``(seed, index)`` (checked against its record), simulated and fitted with the new
:class:`~.ground_truth.GroundTruthSettings`, and its ``ground_truth.npz``, its training sample's LBS and
spring-mass targets and its ``record.json`` are replaced.  Features and MPM ranges are not touched.

Two ways to run it:

* **In place** (:func:`rebuild`): on the machine holding the dataset, a shard at a time; objects whose record
  already carries the target settings are skipped (resumable), every file is written atomically.
* **Portable** (:func:`compute_portable` then :func:`apply_portable`): on a machine holding only
  ``build.json`` (a farm or the GPU machine's CPU cores), each object's ground truth is written to
  ``OUT/<object_id>.npz``; back on the dataset's machine those files are applied.  Without
  ``keep_trajectories`` a portable file holds the fitted targets and their record but not the MPM motions
  (about 20 kB instead of 0.3–0.7 MB an object); the applied ``ground_truth.npz`` then says so
  (``trajectories_kept`` False) and the evaluation, which needs the motions, refuses it with a clear error.

When every finished object carries the target settings, ``build.json`` is updated to them (later shards and
resumes of ``dataset build`` then use them); until then the card lists the mixture
(``ground_truth_settings``), and training refuses a training split whose spring-anchor counts differ while it does
(a solid too small for the anchors asked has fewer whatever the settings: :func:`.train.check_spring_anchors`).
"""

from __future__ import annotations

import json
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterable, Optional

import numpy as np

from ..core.atomic_io import json_default, save_npz, write_text
from ..core.errors import CancelledError, UserError, read_json
from ..core.progress import Progress
from . import dataset as ds
from .ground_truth import GroundTruthSettings

GT_STAGES = ("mpm", "lbs_fit", "spring_fit")
"""Record timings (seconds) that a ground-truth rebuild replaces."""


def settings_key(gt: GroundTruthSettings | dict) -> dict:
    """What identifies a ground truth's settings (the device it ran on does not)."""
    d = dict(gt.to_dict() if isinstance(gt, GroundTruthSettings) else gt)
    d.pop("device", None)
    d["extra_alphas"] = sorted(float(a) for a in d.get("extra_alphas", ()))
    return d


def object_settings(build: ds.BuildSettings, target: GroundTruthSettings, split: str) -> GroundTruthSettings:
    """The target settings as an object of ``split`` is simulated with (test objects add the build's α)."""
    gt = GroundTruthSettings.from_dict(target.to_dict())
    if split == "test":
        gt.extra_alphas = tuple(sorted(set(gt.extra_alphas) | set(build.test_alphas)))
    return gt


def _regenerate(build: ds.BuildSettings, index: int, expected_id: Optional[str] = None):
    from ..core import procedural

    obj = procedural.generate(int(index), build.seed, classes=build.classes)
    if expected_id is not None and obj.object_id != expected_id:
        raise UserError(f"object {index} regenerates as {obj.object_id!r}, its record says {expected_id!r}: the "
                        "build's seed or classes no longer match this version of the generator")
    return obj


def compute_object(build: ds.BuildSettings, index: int, target: GroundTruthSettings,
                   expected_id: Optional[str] = None, progress: Optional[Progress] = None):
    """Generate object ``index`` again and compute its ground truth; returns (GroundTruth, the settings it was
    computed with (:func:`object_settings`), timings s)."""
    from . import ground_truth

    obj = _regenerate(build, index, expected_id)
    settings = object_settings(build, target, ds.split_of(index, build.split))
    timings: dict = {}
    gt = ground_truth.compute(obj, settings, progress=progress, timings=timings)
    return gt, settings, timings


def record_update(gt, settings: GroundTruthSettings, timings: dict) -> dict:
    """The record fields a ground truth sets (``mpm``, ``fits``, ``spring_anchors``, ``ground_truth``, timings)."""
    return {"mpm": {str(a): gt.mpm_info[a] for a in sorted(gt.mpm_info)}, "fits": gt.fits,
            "spring_anchors": int(len(gt.anchors)), "ground_truth": settings_key(settings),
            "ground_truth_device": settings.device, "gt_timings": {k: float(timings.get(k, 0.0)) for k in GT_STAGES}}


def _apply_record(root: Path, rec: dict, update: dict) -> dict:
    rec = {**rec, **{k: v for k, v in update.items() if k != "gt_timings"}}
    rec["timings"] = {**rec.get("timings", {}), **update["gt_timings"]}
    rec["total_seconds"] = float(sum(rec["timings"].values()))
    rec["sample_bytes"] = (root / "samples" / f"{rec['object_id']}.npz").stat().st_size
    write_text(root / "objects" / rec["object_id"] / "record.json", json.dumps(rec, indent=1, default=json_default))
    return rec


def _replace_targets(root: Path, object_id: str, targets) -> None:
    """Rewrite ``samples/<id>.npz`` with the LBS and spring-mass targets of ``targets`` (grid, ranges kept)."""
    from .sample_format import TrainingSample

    sample_path = root / "samples" / f"{object_id}.npz"
    sample = TrainingSample.load(sample_path)
    labels = root / "objects" / object_id / "labels.npz"
    if not labels.is_file():
        raise UserError(f"{root}: part labels of {object_id!r} missing ({labels})")
    with np.load(labels, allow_pickle=False) as z:
        part_ids = z["part_ids"].astype(np.int64)
    if part_ids.size != sample.voxel_count:
        raise UserError(f"{labels}: {part_ids.size} labelled voxels, the sample has {sample.voxel_count}")
    sample.lbs, sample.spring = ds.solver_targets(targets, part_ids, sample.mpm)
    sample.validate(str(sample_path))
    sample.save(sample_path)


def _finished(root: Path) -> list[dict]:
    out = []
    for d in sorted((root / "objects").iterdir()) if (root / "objects").is_dir() else []:
        rec = ds.read_record(root, d.name) if d.is_dir() else None
        if rec is not None and rec.get("status") == "done":
            out.append(rec)
    return out


def _selected(records: Iterable[dict], shard: tuple[int, int], splits) -> list[dict]:
    i, n = shard
    return [r for r in records if int(r["index"]) % n == i and (splits is None or r.get("split") in splits)]


def _at_target(rec: dict, build: ds.BuildSettings, target: GroundTruthSettings) -> bool:
    want = settings_key(object_settings(build, target, rec.get("split", "train")))
    return rec.get("ground_truth") == want


def _promote_if_uniform(root: Path) -> bool:
    """Write the finished objects' ground-truth settings into build.json once they all share them (a test
    object's extra α aside; :func:`~.dataset.ground_truth_mixture`); returns whether it did."""
    records = _finished(root)
    mixture = ds.ground_truth_mixture(records)
    if len(mixture) != 1 or mixture[0]["settings"] is None:
        return False
    path = root / "build.json"
    d = read_json(path)
    alphas = next((r["ground_truth"]["extra_alphas"] for r in records if r.get("split") != "test"), [])
    device = d.get("ground_truth", {}).get("device", "cpu")
    d["ground_truth"] = GroundTruthSettings.from_dict({**mixture[0]["settings"], "extra_alphas": alphas,
                                                      "device": device}).to_dict()
    write_text(path, json.dumps(d, indent=1))
    return True


def _build_settings(root: Path) -> ds.BuildSettings:
    p = root / "build.json"
    if not p.is_file():
        raise UserError(f"{root}: no build.json — a ground-truth rebuild needs the build's settings (seed, classes, "
                        "split) to generate its objects again")
    return ds.BuildSettings.from_dict(read_json(p))


@contextmanager
def _progress_for(given: Optional[Progress], total: int, description: str):
    """``given``, or a new :class:`Progress` of ``total`` steps (one an object), closed at the end."""
    if given is not None:
        yield given
        return
    with Progress(total=total, description=description) as own:
        yield own


def _attempt(object_id: str, work: Callable[[], float], summary: dict, done_key: str, failure_note: str = "") -> str:
    """Run ``work`` (returns seconds) for one object; record it under ``summary[done_key]`` or, when it raises
    (a cancellation excepted), under ``summary["failed"]`` — the run goes on.  Returns the message."""
    try:
        seconds = work()
    except CancelledError:
        raise
    except Exception as exc:  # noqa: BLE001 - per object, the run goes on
        summary["failed"][object_id] = f"{type(exc).__name__}: {exc}"
        return f"{object_id} FAILED{failure_note}: {summary['failed'][object_id]}"
    summary[done_key].append(object_id)
    return f"{object_id} {done_key} in {seconds:.1f} s"


def _report(message: str, progress: Progress, log: Optional[Callable[[str], None]]) -> None:
    if log is not None:
        log(message)
    progress.step(1.0, message)


# =========================================================================== in place
def rebuild(root, target: GroundTruthSettings, shard: tuple[int, int] = (0, 1), splits=None,
            progress: Optional[Progress] = None, log: Optional[Callable[[str], None]] = None) -> dict:
    """Give this shard's finished objects of ``root`` the ground truth of ``target`` (module docstring).

    Returns ``rebuilt``, ``skipped`` (already at the target), ``failed`` (id → error), ``seconds`` and
    ``promoted`` (build.json now names the target).  A failed object keeps its previous ground truth.
    """
    root = Path(root)
    build = _build_settings(root)
    todo = _selected(_finished(root), shard, splits)
    if not todo:
        raise UserError(f"{root}: no finished objects in shard {shard[0]}/{shard[1]}"
                        + (f" of the splits {', '.join(splits)}" if splits else ""))
    with _progress_for(progress, len(todo), f"ground truth {shard[0]}/{shard[1]}") as progress:
        summary = {"rebuilt": [], "skipped": [], "failed": {}, "seconds": 0.0}
        t0 = time.perf_counter()
        for rec in todo:
            oid = rec["object_id"]
            if _at_target(rec, build, target):
                summary["skipped"].append(oid)
                progress.step(1.0, f"{oid} already at the target")
                continue

            def work(rec=rec, oid=oid):
                gt, settings, timings = compute_object(build, rec["index"], target, oid, progress)
                gt_path = root / "objects" / oid / "ground_truth.npz"
                ds.save_ground_truth(gt_path, gt)
                _replace_targets(root, oid, ds.load_training_targets(gt_path))
                _apply_record(root, rec, record_update(gt, settings, timings))
                return sum(timings.values())

            _report(_attempt(oid, work, summary, "rebuilt", " (keeps its previous ground truth)"), progress, log)
    summary["seconds"] = time.perf_counter() - t0
    summary["promoted"] = _promote_if_uniform(root)
    ds.write_card(root)
    return summary


# =========================================================================== portable
def compute_portable(build_json, out, count: int, target: GroundTruthSettings, shard: tuple[int, int] = (0, 1),
                     splits=None, keep_trajectories: bool = False, progress: Optional[Progress] = None,
                     log: Optional[Callable[[str], None]] = None) -> dict:
    """Compute the ground truth of objects ``0..count-1`` of this shard from ``build_json`` alone into
    ``out/<object_id>.npz`` (:func:`~.dataset.save_ground_truth` plus ``record`` and ``index``); files already
    there are skipped.  Returns ``written``, ``skipped``, ``failed`` (id → error), ``seconds``."""
    from ..core import procedural

    build_json = Path(build_json)
    if not build_json.is_file():
        raise UserError(f"{build_json}: not found — a portable ground truth generates the objects from the build's "
                        "settings (copy the dataset's build.json)")
    build = ds.BuildSettings.from_dict(read_json(build_json))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    indices = ds.shard_indices(count, shard, splits, build.split)
    with _progress_for(progress, len(indices), f"ground truth {shard[0]}/{shard[1]}") as progress:
        summary = {"written": [], "skipped": [], "failed": {}, "seconds": 0.0}
        t0 = time.perf_counter()
        for index in indices:
            oid = procedural.object_id(index, procedural.class_of_index(index, build.classes))
            path = out / f"{oid}.npz"
            if path.is_file():
                summary["skipped"].append(oid)
                progress.step(1.0, f"{oid} already computed")
                continue

            def work(index=index, oid=oid, path=path):
                gt, settings, timings = compute_object(build, index, target, oid, progress)
                update = record_update(gt, settings, timings)
                ds.save_ground_truth(path, gt, keep_trajectories=keep_trajectories,
                                     extra={"index": np.int64(index), "record": json.dumps(update, default=json_default)})
                return sum(timings.values())

            _report(_attempt(oid, work, summary, "written"), progress, log)
    summary["seconds"] = time.perf_counter() - t0
    return summary


def apply_portable(root, source, progress: Optional[Progress] = None) -> dict:
    """Apply the portable files in ``source`` (``<object_id>.npz``) to ``root``'s finished objects.

    Each file must belong to a finished object of ``root`` (same id and index); the object's
    ``ground_truth.npz`` becomes the file (without its ``record`` / ``index`` keys), its sample's targets and
    its record are replaced; build.json takes the settings once every object shares them.  Returns ``applied``,
    ``unknown`` (files of no finished object), ``promoted``.
    """
    root, source = Path(root), Path(source)
    _build_settings(root)  # a build's directory (its build.json takes the new settings)
    files = sorted(source.glob("*.npz"))
    if not files:
        raise UserError(f"{source}: no ground-truth files (<object_id>.npz) to apply")
    records = {r["object_id"]: r for r in _finished(root)}
    with _progress_for(progress, len(files), "applying ground truth") as progress:
        summary = {"applied": [], "unknown": [], "promoted": False}
        for f in files:
            oid = f.stem
            rec = records.get(oid)
            if rec is None:
                summary["unknown"].append(oid)
                progress.step(1.0, f"{oid}: no finished object of that id in {root}")
                continue
            with np.load(f, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
            index = int(arrays.pop("index"))
            if index != int(rec["index"]):
                raise UserError(f"{f}: made for object index {index}, {oid} is index {rec['index']} in {root}")
            update = json.loads(str(arrays.pop("record")))
            gt_path = root / "objects" / oid / "ground_truth.npz"
            save_npz(gt_path, **arrays)
            _replace_targets(root, oid, ds.load_training_targets(gt_path))
            _apply_record(root, rec, update)
            summary["applied"].append(oid)
            progress.step(1.0, f"{oid} applied")
    summary["promoted"] = _promote_if_uniform(root)
    ds.write_card(root)
    return summary
