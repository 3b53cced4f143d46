"""Bake jobs for the command line and farms: a :class:`BakeJob` is one object of one scene baked with one set of
options into one output file.  :func:`expand_jobs` makes the batch objects × frame ranges × α values (output
names from placeholders, :func:`expand_out`), :func:`check_job_outputs` refuses outputs that collide or
overwrite an input, :func:`group_jobs` and :func:`shard_groups` split a batch for ``--shard``.

Uses :mod:`.frames`, :mod:`.sources`, :mod:`.output` and :mod:`unipixie.core.atomic_io`; the manifest reader is
:mod:`.manifest`, running jobs in Blender is :mod:`unipixie.core.blender_io.bake_jobs`.
"""

from __future__ import annotations

import fnmatch
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

from ..errors import UserError
from .frames import FrameRange
from .output import ARMATURE_TOLERANCE
from .sources import MaterialSource


@dataclass
class BakeJob:
    """One object of one scene baked with one set of options, saved to ``out``.

    scene: the .blend to open; object: the object's name; out: the .blend to save (several jobs
    may share one ``out`` when they bake different objects of the same scene).
    options: everything else (:class:`BakeOptions` fields except ``frames``/``fps``, which come
    from ``frames`` here or the scene).
    frames: ``None`` = the scene's frame range.
    """

    scene: str
    object: str
    out: str
    solver: str = "mpm"
    alpha: Optional[float] = None
    frames: Optional[FrameRange] = None
    effects: list = field(default_factory=list)
    device: str = "cpu"
    material: Optional[MaterialSource] = None
    output: str = "auto"
    interpolation: str = "LINEAR"
    particles: bool = False
    armature_tolerance: float = ARMATURE_TOLERANCE
    solver_settings: Optional[dict] = None
    scenario: dict = field(default_factory=dict)

    def describe(self) -> str:
        fr = f" frames {self.frames}" if self.frames else ""
        a = f" α {self.alpha:g}" if self.alpha is not None else ""
        return f"{Path(self.scene).name}:{self.object} {self.solver}{a}{fr} → {self.out}"

    def to_dict(self) -> dict:
        d = {"scene": self.scene, "object": self.object, "out": self.out, "solver": self.solver,
             "alpha": self.alpha, "frames": str(self.frames) if self.frames else None,
             "effects": [e if isinstance(e, str) else e.to_dict() for e in self.effects], "device": self.device,
             "material": None if self.material is None else self.material.to_dict(), "output": self.output,
             "interpolation": self.interpolation, "particles": self.particles,
             "armature_tolerance": self.armature_tolerance, "settings": self.solver_settings,
             "scenario": self.scenario}
        return d


JOB_KEYS = {"scene", "object", "objects", "out", "solver", "alpha", "frames", "effects", "device", "material",
            "output", "interpolation", "particles", "armature_tolerance", "settings", "scenario"}
SCENARIO_OVERRIDE_KEYS = {"gravity", "ground", "initial_velocity", "initial_angular_velocity", "pinned_box", "clamp",
                          "clamp_group"}
"""A job's ``scenario`` may set: gravity [x,y,z] m/s²; ground: an object name, ``{"height": z}`` or ``null``
(no ground); clamp: an object name; clamp_group: a vertex group; pinned_box [[x0,y0,z0],[x1,y1,z1]] m;
initial_velocity / initial_angular_velocity [x,y,z].  Unset keys come from the scene and the object."""


def expand_out(pattern: str, *, scene: str, obj: str, solver: str, alpha: Optional[float],
               frames: Optional[FrameRange], index: int) -> str:
    """Fill ``{scene}``, ``{object}``, ``{solver}``, ``{alpha}``, ``{frames}``, ``{start}``, ``{end}``, ``{job}``."""
    values = {"scene": Path(scene).stem, "object": safe_name(obj), "solver": solver,
              "alpha": "" if alpha is None else f"{alpha:g}", "frames": str(frames) if frames else "scene",
              "start": str(frames.start) if frames else "", "end": str(frames.end) if frames else "",
              "job": f"{index:04d}"}
    try:
        return str(pattern).format(**values)
    except (KeyError, IndexError, ValueError) as exc:
        raise UserError(f"output name {pattern!r}: unknown placeholder {exc}; use {{{'}, {'.join(values)}}}") from None


def safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "object"


def expand_jobs(scene: str, objects: Sequence[str], out: str, *, solver: str = "mpm",
                alphas: Sequence[Optional[float]] = (None,), frame_ranges: Sequence[Optional[FrameRange]] = (None,),
                resolve: Optional[Callable[[str], Sequence[str]]] = None, **common) -> list[BakeJob]:
    """The batch objects × frame ranges × α values, in that order (a stable order: shards rely on it).

    resolve: ``resolve(scene) -> object names`` to expand wildcards (``Rock*``) now, so that each
    object gets its own job and output name; without it a pattern stays one job (expanded when the
    scene is opened) and may not be combined with ``{object}`` in the output name.
    """
    if not objects:
        raise UserError("no object to bake: give --object NAME (repeatable, wildcards allowed)")
    if resolve is not None:
        objects = select_objects(objects, list(resolve(str(scene))))
    elif "{object}" in str(out) and any(any(c in o for c in "*?[") for o in objects):
        raise UserError("a wildcard object name with {object} in the output name needs the scene's object list")
    jobs = []
    for obj in objects:
        for fr in frame_ranges:
            for a in alphas:
                jobs.append(BakeJob(scene=str(scene), object=obj, out=expand_out(out, scene=scene, obj=obj, solver=solver,
                                                                                alpha=a, frames=fr, index=len(jobs)),
                                    solver=solver, alpha=a, frames=fr, **common))
    check_job_outputs(jobs)
    return jobs


def check_job_outputs(jobs: Sequence[BakeJob]) -> None:
    """Two jobs writing the same object into the same output file would overwrite each other: refuse.
    An output that is its input scene or material file — also through a symbolic link or a hard link —
    is refused too."""
    from ..atomic_io import output_path, refuse_overwriting_inputs, same_file

    seen: dict = {}
    for j in jobs:
        key = (str(output_path(j.out)), j.object)
        if key in seen:
            raise UserError(f"jobs '{seen[key].describe()}' and '{j.describe()}' both write object '{j.object}' into "
                            f"{j.out}; put a placeholder such as {{alpha}}, {{frames}} or {{job}} in the output name")
        seen[key] = j
        if same_file(j.out, j.scene):
            how = " (through a link)" if os.path.abspath(j.out) != os.path.abspath(j.scene) else ""
            raise UserError(f"job '{j.describe()}' would overwrite its input scene {j.scene}{how}: the output {j.out} "
                            "is the same file; choose another --out")
        inputs = [getattr(j.material, a, None) for a in ("path", "features")] if j.material is not None else []
        refuse_overwriting_inputs(j.out, [i for i in inputs if i], what="output")


def group_jobs(jobs: Sequence[BakeJob]) -> list[list[BakeJob]]:
    """Jobs grouped by (scene, out) — one group = open the scene once, bake, save once — in first-seen order."""
    groups: dict = {}
    for j in jobs:
        key = (os.path.abspath(j.scene), os.path.abspath(j.out))
        groups.setdefault(key, []).append(j)
    outs: dict = {}
    for (scene, out), g in groups.items():
        if out in outs and outs[out] != scene:
            raise UserError(f"two different scenes ({outs[out]} and {scene}) would be saved into the same file {out}")
        outs[out] = scene
    return list(groups.values())


def shard_groups(groups: Sequence, shard: Optional[tuple[int, int]]) -> list:
    """The part of a batch that shard ``(i, n)`` runs: groups ``i, i+n, i+2n, …`` (round-robin, stable).

    Jobs are grouped by output file first (:func:`group_jobs`) so no two shards write the same file.
    """
    if shard is None:
        return list(groups)
    i, n = shard
    if n <= 0 or not 0 <= i < n:
        raise UserError(f"shard {i}/{n}: need 0 <= i < n")
    return list(groups)[i::n]


def select_objects(patterns: Sequence[str], available: Sequence[str]) -> list[str]:
    """Object names matching the given names or shell wildcards (``Rock*``), in the order given; each must match."""
    chosen: list[str] = []
    for pat in patterns:
        if any(c in pat for c in "*?["):
            hits = sorted(n for n in available if fnmatch.fnmatchcase(n, pat))
            if not hits:
                raise UserError(f"no object matches {pat!r}; objects in the scene: {', '.join(sorted(available)) or 'none'}")
        else:
            if pat not in available:
                raise UserError(f"no object named {pat!r} in the scene; objects: {', '.join(sorted(available)) or 'none'}")
            hits = [pat]
        chosen.extend(h for h in hits if h not in chosen)
    return chosen
