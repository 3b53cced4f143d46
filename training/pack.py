"""A compact pack of a built dataset for a GPU machine that has only Python + torch (+ numpy).

The GPU machine receives at most ~60 MB per transfer and has no bpy, warp or
trimesh, so the pack holds only what training needs, compactly, in part files of
at most ``part_bytes`` each::

    PACK/index.json        format, objects (id, split, part file, offset, length), sizes, quantisation
    PACK/part-000.bin ...  concatenated per-object records (each a compressed .npz blob)

Per object (K occupied voxels, U distinct feature rows, P parts, N_a anchors):

===================  ===============  ====================================================================
key                  dtype, shape     meaning
===================  ===============  ====================================================================
occupancy            uint8 packbits   the (R, R, R) occupancy, ``np.packbits(occ.ravel())``
feature_rows         uint8 (U, D)     the distinct feature rows, quantised per channel:
                                      ``round((f − offset) / scale · 255)``
feature_offset       float32 (D,)     per-object, per-channel offset (the channel minimum)
feature_scale        float32 (D,)     per-object, per-channel scale (max − min; 0 → 1)
feature_source       uint16/32 (K,)   for every occupied voxel (``np.argwhere`` order) its feature row
part_ids             uint8 (K,)       part of every occupied voxel (index into the part tables)
part_E_min ...       float32 (P,)     per-part ``E_min, E_max, nu_min, nu_max, density_min, density_max``
part_material        int16 (P,)       material-class id per part
lbs_params           float32 (650,)   (optional) skinning parameters
part_lbs_E_min/_max  float32 (P,)     (optional) the LBS E per part at α = 0 / 1
spring_stiffness     float32 (2, N_a) (optional) per-anchor stiffness at α = 0 and 1
spring_softness      float32 (2,)     (optional) softness η at α = 0 and 1
meta                 str (JSON)       object id, geometry, feature model, sample meta
===================  ===============  ====================================================================

Why this is exact: the feature lifting gives every interior (and unseen) voxel
the features of its nearest painted surface voxel, so a grid holds only about as
many *distinct* feature rows as it has surface voxels; the pack stores those
once and an index per voxel.  Ranges and targets are per part, so a part table
and one part id per voxel reproduce the per-voxel arrays bit for bit.  The only
loss is the 8-bit quantisation of the features: the absolute error of each
channel is at most ``feature_scale / 510`` (then rounded to float16, as the
training sample stores it).  :func:`read_pack` / :func:`unpack` rebuild
:class:`~.sample_format.TrainingSample` objects / files with numpy only.

Run on the GPU machine from a bare checkout (no install)::

    python training/pack.py unpack PACK OUT      # writes OUT/samples/*.npz and OUT/split.json
"""

from __future__ import annotations

import io
import json
import os
import sys
import tempfile
from pathlib import Path

if __package__ in (None, ""):  # run as a file: import the checkout as `unipixie`
    import runpy

    runpy.run_path(str(Path(__file__).resolve().parents[1] / "standalone.py"))["import_checkout"]()
    __package__ = "unipixie.training"

import numpy as np  # noqa: E402

from ..core.atomic_io import write_json  # noqa: E402
from ..core.errors import UserError, read_json  # noqa: E402

PACK_FORMAT = "unipixie.pack/1"
INDEX_FILE = "index.json"
QUANT_LEVELS = 255
DEFAULT_PART_BYTES = 50_000_000


# =========================================================================== encoding one object
def _per_part(values: np.ndarray, part_ids: np.ndarray, parts: int, name: str) -> np.ndarray:
    """The per-part value of a per-voxel array that is constant within parts (checked exactly)."""
    v = np.asarray(values)
    table = np.zeros(parts, dtype=v.dtype)
    table[part_ids] = v
    if not np.array_equal(table[part_ids], v):
        raise UserError(f"{name} is not constant within each part: this sample cannot be packed by part tables")
    return table


def quantise_features(features: np.ndarray):
    """(K, D) features -> (rows (U, D) uint8, offset (D,), scale (D,), source (K,)): distinct rows, quantised."""
    f = np.asarray(features, dtype=np.float16)
    rows, source = np.unique(f, axis=0, return_inverse=True)
    source = source.reshape(-1)
    r32 = rows.astype(np.float32)
    lo = r32.min(0) if len(r32) else np.zeros(f.shape[1], np.float32)
    hi = r32.max(0) if len(r32) else np.zeros(f.shape[1], np.float32)
    scale = np.where(hi > lo, hi - lo, 1.0).astype(np.float32)
    q = np.clip(np.rint((r32 - lo) / scale * QUANT_LEVELS), 0, QUANT_LEVELS).astype(np.uint8)
    return q, lo.astype(np.float32), scale, source


def dequantise_features(rows: np.ndarray, offset: np.ndarray, scale: np.ndarray, source: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quantise_features`: (K, D) float16."""
    r = rows.astype(np.float32) / QUANT_LEVELS * scale[None] + offset[None]
    return r[np.asarray(source, np.int64)].astype(np.float16)


def encode_object(sample, part_ids: np.ndarray) -> bytes:
    """One :class:`~.sample_format.TrainingSample` and its part id per occupied voxel -> a compressed record."""
    g = sample.grid
    part_ids = np.asarray(part_ids, np.int64).reshape(-1)
    K = g.features.shape[0]
    if part_ids.shape != (K,):
        raise UserError(f"{sample.object_id}: {part_ids.size} part ids for {K} occupied voxels")
    P = int(part_ids.max()) + 1
    if P > 255:
        raise UserError(f"{sample.object_id}: {P} parts; the pack stores part ids as uint8 (at most 255)")
    rows, offset, scale, source = quantise_features(g.features)
    d = {"occupancy": np.packbits(g.occupancy.ravel()), "feature_rows": rows, "feature_offset": offset,
         "feature_scale": scale,
         "feature_source": source.astype(np.uint16 if len(rows) <= 65535 else np.uint32),
         "part_ids": part_ids.astype(np.uint8)}
    m = sample.mpm
    for name in ("E_min", "E_max", "nu_min", "nu_max", "density_min", "density_max"):
        d[f"part_{name}"] = _per_part(getattr(m, name), part_ids, P, f"mpm_{name}").astype(np.float32)
    d["part_material"] = _per_part(m.material, part_ids, P, "mpm_material").astype(np.int16)
    if sample.lbs is not None:
        L = sample.lbs
        d["lbs_params"] = np.asarray(L.params, np.float32)
        d["part_lbs_E_min"] = _per_part(L.E_min, part_ids, P, "lbs_E_min").astype(np.float32)
        d["part_lbs_E_max"] = _per_part(L.E_max, part_ids, P, "lbs_E_max").astype(np.float32)
        d["part_lbs_nu_min"] = _per_part(L.nu_min, part_ids, P, "lbs_nu_min").astype(np.float32)
        d["part_lbs_nu_max"] = _per_part(L.nu_max, part_ids, P, "lbs_nu_max").astype(np.float32)
    if sample.spring is not None:
        S = sample.spring
        d["spring_stiffness"] = np.stack([S.stiffness_min, S.stiffness_max]).astype(np.float32)
        d["spring_softness"] = np.array([S.softness_min, S.softness_max], np.float32)
    d["meta"] = json.dumps({"object_id": sample.object_id, "geometry": g.geometry.to_dict(),
                            "feature_model": g.feature_model, "sample_meta": sample.meta}, default=str)
    buf = io.BytesIO()
    np.savez_compressed(buf, **d)
    return buf.getvalue()


def decode_object(blob: bytes):
    """A compressed record -> (:class:`~.sample_format.TrainingSample`, part ids (K,) int64)."""
    from ..core.types import FeatureGrid, GridGeometry
    from .sample_format import LBSTargets, MPMRanges, SpringTargets, TrainingSample

    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except Exception as exc:  # truncated transfer, wrong offsets
        raise UserError(f"a pack record is not readable ({exc}); the part file may be truncated") from None
    meta = json.loads(str(d["meta"]))
    geo = GridGeometry(**meta["geometry"])
    R = geo.resolution
    occ = np.unpackbits(d["occupancy"])[: R ** 3].astype(bool).reshape(R, R, R)
    feats = dequantise_features(d["feature_rows"], d["feature_offset"], d["feature_scale"], d["feature_source"])
    grid = FeatureGrid(geo, occ, feats, feature_model=meta["feature_model"])
    pid = d["part_ids"].astype(np.int64)
    mpm = MPMRanges(*(d[f"part_{n}"][pid] for n in ("E_min", "E_max", "nu_min", "nu_max", "density_min",
                                                   "density_max")), d["part_material"][pid])
    lbs = spring = None
    if "lbs_params" in d:
        lbs = LBSTargets(d["lbs_params"], d["part_lbs_E_min"][pid], d["part_lbs_E_max"][pid],
                         d["part_lbs_nu_min"][pid], d["part_lbs_nu_max"][pid])
    if "spring_stiffness" in d:
        s = d["spring_stiffness"]
        spring = SpringTargets(s[0], s[1], float(d["spring_softness"][0]), float(d["spring_softness"][1]))
    return TrainingSample(meta["object_id"], grid, mpm, lbs, spring, meta.get("sample_meta", {})), pid


# =========================================================================== packs
def write_pack(dataset_dir, out_dir, part_bytes: int = DEFAULT_PART_BYTES, splits=("train", "val", "test"),
               progress=None) -> dict:
    """Pack the finished objects of a built dataset (see module docstring); returns the index."""
    from .dataset import DatasetDir

    ds = DatasetDir(dataset_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if any(out.glob("part-*.bin")) or (out / INDEX_FILE).exists():
        raise UserError(f"{out} already holds a pack; write into an empty directory (nothing is overwritten)")
    part_bytes = int(part_bytes)
    if part_bytes < 1_000_000:
        raise UserError(f"part size must be at least 1 MB, got {part_bytes} bytes")
    objects, parts = [], []
    fh, cur, cur_size = None, -1, 0
    largest = 0
    anchor_counts: set = set()  # spring-mass N_a (a solid too small or thin for more has fewer)
    tmp_parts: dict = {}  # part name -> its unique temporary file (renamed once every part is whole)
    try:
        for split in splits:
            for oid in ds.ids(split):
                sample = ds.sample(oid)
                if sample.spring is not None:
                    anchor_counts.add(int(sample.spring.stiffness_min.size))
                part_ids, _ = ds.part_labels(oid)
                blob = encode_object(sample, part_ids)
                largest = max(largest, len(blob))
                if fh is None or (cur_size + len(blob) > part_bytes and cur_size > 0):
                    if fh is not None:
                        fh.close()
                    cur += 1
                    name = f"part-{cur:03d}.bin"
                    parts.append({"file": name, "bytes": 0})
                    tmp_parts[name] = Path(tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=out)[1])
                    fh = open(tmp_parts[name], "wb")
                    cur_size = 0
                fh.write(blob)
                objects.append({"object_id": oid, "split": split, "part": parts[-1]["file"], "offset": cur_size,
                                "length": len(blob), "voxels": int(sample.voxel_count)})
                cur_size += len(blob)
                parts[-1]["bytes"] = cur_size
                if progress is not None:
                    progress.step(1.0, oid)
        if fh is not None:
            fh.close()
            fh = None
        for p in parts:
            size = tmp_parts[p["file"]].stat().st_size
            if size != p["bytes"]:
                raise UserError(f"cannot write {out / p['file']}: {size} bytes written, {p['bytes']} expected (is the "
                                "disk full?)")
            os.replace(tmp_parts.pop(p["file"]), out / p["file"])
    except OSError as exc:
        from ..core.atomic_io import write_error

        raise write_error(out, exc) from None
    finally:
        if fh is not None:
            fh.close()
        for tmp in tmp_parts.values():  # a failure or Ctrl-C: no temporary part left behind
            tmp.unlink(missing_ok=True)
    first = ds.sample(objects[0]["object_id"]) if objects else None
    index = {"format": PACK_FORMAT, "objects": objects, "parts": parts, "bytes": int(sum(p["bytes"] for p in parts)),
             "count": len(objects), "largest_record_bytes": largest, "part_limit_bytes": part_bytes,
             "splits": {s: sum(o["split"] == s for o in objects) for s in splits},
             "feature_model": first.grid.feature_model if first else "", "feature_dim": first.grid.dim if first else 0,
             "resolution": first.grid.geometry.resolution if first else 0,
             "spring_anchors": max(anchor_counts, default=0),
             "quantisation": "features: per-object per-channel 8-bit, |error| <= feature_scale/510; everything else exact"}
    card = Path(dataset_dir) / "dataset.json"
    if card.is_file():
        index["dataset_card"] = json.loads(card.read_text())
    write_json(out / INDEX_FILE, index, indent=1)
    index["objects"] = len(objects)
    return index


def read_index(pack_dir) -> dict:
    p = Path(pack_dir) / INDEX_FILE
    if not p.is_file():
        raise UserError(f"{pack_dir}: no {INDEX_FILE}; not a pack directory (or the transfer is incomplete)")
    idx = read_json(p)
    if not isinstance(idx, dict):
        raise UserError(f"{p}: expected a JSON object (the pack's index), got {type(idx).__name__}")
    if idx.get("format") != PACK_FORMAT:
        raise UserError(f"{p}: format {idx.get('format')!r}, expected {PACK_FORMAT!r}")
    for part in idx["parts"]:
        f = Path(pack_dir) / part["file"]
        if not f.is_file():
            raise UserError(f"{pack_dir}: part file {part['file']} is missing (transfer it too)")
        if f.stat().st_size != part["bytes"]:
            raise UserError(f"{f}: {f.stat().st_size} bytes, the index says {part['bytes']} (truncated transfer?)")
    return idx


def read_pack(pack_dir, split: str | None = None):
    """Yield (split, TrainingSample, part ids) for every object of the pack (or of one split)."""
    pack_dir = Path(pack_dir)
    idx = read_index(pack_dir)
    handles: dict = {}
    try:
        for o in idx["objects"]:
            if split is not None and o["split"] != split:
                continue
            fh = handles.get(o["part"])
            if fh is None:
                fh = handles[o["part"]] = open(pack_dir / o["part"], "rb")
            fh.seek(o["offset"])
            sample, pid = decode_object(fh.read(o["length"]))
            if sample.object_id != o["object_id"]:
                raise UserError(f"{pack_dir}: record at {o['part']}+{o['offset']} is {sample.object_id!r}, "
                                f"the index says {o['object_id']!r}")
            yield o["split"], sample, pid
    finally:
        for fh in handles.values():
            fh.close()


def unpack(pack_dir, out_dir) -> int:
    """Write every object of a pack as ``OUT/samples/<id>.npz`` (training-sample format) plus ``OUT/split.json``
    — the directory ``unipixie train --data OUT`` (or ``python training/train.py``) reads.  Returns the count."""
    out = Path(out_dir)
    (out / "samples").mkdir(parents=True, exist_ok=True)
    split: dict = {}
    n = 0
    for s, sample, _ in read_pack(pack_dir):
        sample.save(out / "samples" / f"{sample.object_id}.npz")
        split.setdefault(s, []).append(sample.object_id)
        n += 1
    write_json(out / "split.json", split, indent=1)
    index = read_index(pack_dir)
    recipe = _recipe_of(index)
    if recipe is not None:
        write_json(out / "feature_recipe.json", recipe, indent=1)
    if index.get("dataset_card"):  # training reads it (a ground truth still being rebuilt is refused)
        write_json(out / "dataset.json", index["dataset_card"], indent=1)
    return n


def _recipe_of(index: dict):
    """How the packed objects were rendered (from the dataset card's build settings), or None.  Written beside the
    samples so that training copies it into the checkpoint (``feature_recipe.json``)."""
    settings = (index.get("dataset_card") or {}).get("settings") or {}
    try:
        recipe = {"engine": str(settings["engine"]).lower(), "view_count": int(settings["views"]),
                  "resolution": int(settings["render_resolution"]), "samples": int(settings.get("samples", 8))}
    except (KeyError, TypeError, ValueError):
        return None
    if settings.get("extractor"):
        from ..core.extractors import feature_model

        recipe["extractor"] = feature_model(settings["extractor"])
    return recipe


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python training/pack.py", description="unpack (or inspect) a UniPixie pack "
                                "with numpy only")
    sub = p.add_subparsers(dest="cmd", required=True)
    u = sub.add_parser("unpack", help="write OUT/samples/*.npz and OUT/split.json")
    u.add_argument("pack")
    u.add_argument("out")
    i = sub.add_parser("info", help="print the pack's index summary")
    i.add_argument("pack")
    args = p.parse_args(argv)
    try:
        if args.cmd == "unpack":
            n = unpack(args.pack, args.out)
            print(f"wrote {n} training samples and split.json to {args.out}")
        else:
            idx = read_index(args.pack)
            print(json.dumps({k: v for k, v in idx.items() if k not in ("objects", "dataset_card")}, indent=1))
    except UserError as exc:
        print(f"pack: error: {exc}", file=sys.stderr)
        return exc.exit_code
    return 0


if __name__ == "__main__":
    sys.exit(main())
