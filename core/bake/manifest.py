"""Job manifests (format ``unipixie.bake-manifest/1``; schema in ``docs/baking.md``): :func:`load_manifest` reads
one into :class:`~.jobs.BakeJob` s, with errors that name the job and the key.

Uses :mod:`.frames`, :mod:`.sources`, :mod:`.output` and :mod:`.jobs`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Optional, Sequence

from ..errors import UserError, read_json
from ..types import check_alpha
from .frames import parse_frame_list, parse_frames
from .jobs import JOB_KEYS, SCENARIO_OVERRIDE_KEYS, BakeJob, check_job_outputs, expand_jobs
from .output import ARMATURE_TOLERANCE
from .sources import MATERIAL_RULE, material_source_from_dict


MANIFEST_FORMAT = "unipixie.bake-manifest/1"


def load_manifest(path, resolve: Optional[Callable[[str], Sequence[str]]] = None) -> list[BakeJob]:
    """Read a job manifest (format ``unipixie.bake-manifest/1``; schema in ``docs/baking.md``).

    Relative paths (scene, out, material files) are relative to the manifest's folder.  A job may
    name several objects (``"objects": [...]``, wildcards resolved when the scene is opened) and
    may give ``"alpha"`` or ``"frames"`` as lists (a batch).  Errors name the job and key.
    ``resolve``: see :func:`expand_jobs`.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: manifest not found")
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise UserError(f"{path}: a manifest is a JSON object with 'format' and 'jobs'")
    if doc.get("format") != MANIFEST_FORMAT:
        raise UserError(f"{path}: key 'format' is {doc.get('format')!r}, expected {MANIFEST_FORMAT!r}")
    defaults = doc.get("defaults", {}) or {}
    jobs_in = doc.get("jobs")
    if not isinstance(jobs_in, list) or not jobs_in:
        raise UserError(f"{path}: key 'jobs' must be a non-empty list")
    if not isinstance(defaults, dict):
        raise UserError(f"{path}: key 'defaults' must be an object")
    base = path.parent
    jobs: list[BakeJob] = []
    for k, raw in enumerate(jobs_in):
        if not isinstance(raw, dict):
            raise UserError(f"{path}: jobs[{k}] must be an object")
        d = {**defaults, **raw}
        where = f"{path}: jobs[{k}]"
        unknown = set(d) - JOB_KEYS
        if unknown:
            raise UserError(f"{where}: unknown key(s) {sorted(unknown)}; known keys: {', '.join(sorted(JOB_KEYS))}")
        for key in ("scene", "out"):
            if not d.get(key):
                raise UserError(f"{where}: key '{key}' is missing")
        objects = d.get("objects", d.get("object"))
        if isinstance(objects, str):
            objects = [objects]
        if not objects or not all(isinstance(o, str) for o in objects):
            raise UserError(f"{where}: key 'object' (a name) or 'objects' (a list of names) is missing")
        scene = str(_rel(base, d["scene"]))
        alphas = d.get("alpha")
        alphas = alphas if isinstance(alphas, list) else [alphas]
        frames = d.get("frames")
        if isinstance(frames, list):
            frame_ranges = [parse_frames(f) for f in frames]
        elif frames is None:
            frame_ranges = [None]
        else:
            frame_ranges = parse_frame_list(str(frames))
        material = d.get("material")
        if isinstance(material, dict):
            material = {**material, **{k: str(_rel(base, material[k])) for k in ("file", "features", "checkpoint")
                                       if material.get(k)}}
        elif isinstance(material, str) and material != "model":
            material = str(_rel(base, material))
        scen = d.get("scenario") or {}
        if not isinstance(scen, dict) or set(scen) - SCENARIO_OVERRIDE_KEYS:
            raise UserError(f"{where}: 'scenario' may set only {', '.join(sorted(SCENARIO_OVERRIDE_KEYS))}")
        from ...solvers.scenario import require_json_numbers

        try:
            require_json_numbers([a for a in alphas if a is not None], f"{where}: 'alpha'")
            if "armature_tolerance" in d:
                require_json_numbers(d["armature_tolerance"], f"{where}: 'armature_tolerance'")
        except UserError as exc:
            raise UserError(str(exc)) from None
        try:
            alphas = [None if a is None else check_alpha(a) for a in alphas]
        except UserError:
            raise UserError(f"{where}: 'alpha' must be a number in [0, 1] or a list of them") from None
        source = material_source_from_dict(material) if "material" in d else None
        if any(a is not None for a in alphas) and source is not None and source.kind != "model":
            raise UserError(f"{where}: 'alpha' with a {source.kind} 'material': {MATERIAL_RULE}")
        common = dict(effects=list(d.get("effects", []) or []), device=str(d.get("device", "cpu")),
                      material=source,
                      output=str(d.get("output", "auto")), interpolation=str(d.get("interpolation", "LINEAR")),
                      particles=bool(d.get("particles", False)),
                      armature_tolerance=float(d.get("armature_tolerance", ARMATURE_TOLERANCE)),
                      solver_settings=d.get("settings"), scenario=scen)
        try:
            new = expand_jobs(scene, objects, str(_rel(base, d["out"])), solver=str(d.get("solver", "mpm")),
                              alphas=alphas, frame_ranges=frame_ranges, resolve=resolve, **common)
        except UserError as exc:
            raise UserError(f"{where}: {exc}") from None
        jobs.extend(new)
    check_job_outputs(jobs)
    return jobs


def _rel(base: Path, p) -> Path:
    p = Path(os.path.expanduser(str(p)))
    return p if p.is_absolute() else (base / p)
