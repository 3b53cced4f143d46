"""The fault matrix's inputs: the repository, small fixture texts, and the makers of the files a case gets
(``Case.files``: a maker is called with the path to write and the fixtures folder; see ``materialise``)."""

from __future__ import annotations

import json
import os
import shutil
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np


REPO = Path(__file__).resolve().parents[2]

OBJ_CUBE = "".join(f"v {x} {y} {z}\n" for x in (0, 1) for y in (0, 1) for z in (0, 1)) + \
    "f 1 2 4 3\nf 5 7 8 6\nf 1 5 6 2\nf 3 4 8 7\nf 1 3 7 5\nf 2 6 8 4\n"

SYNTH_SMALL = ["--solver", "spring_mass", "--duration", "0.2", "--fps", "20", "--points", "30", "--setting", "anchors=32"]


# --------------------------------------------------------------------------- file makers
def npz_mut(fixture: str, **changes):
    """A maker that writes the fixture archive with keys replaced (a value, or a function of the arrays), removed
    (None) or added."""
    def make(path: Path, fx: Path):
        with np.load(fx / fixture, allow_pickle=False) as d:
            arrays = {k: d[k] for k in d.files}
        for k, v in changes.items():
            if v is None:
                arrays.pop(k, None)
            elif callable(v):
                arrays[k] = v(arrays)
            else:
                arrays[k] = v
        with open(path, "wb") as f:
            np.savez(f, **arrays)
    return make


def scen_mut(fn, fixture="m.npz"):
    """A measurement whose scenario JSON is changed by ``fn(dict)``."""
    def change(a):
        s = json.loads(str(a["scenario"]))
        fn(s)
        return np.array(json.dumps(s))
    return npz_mut(fixture, scenario=change)


def pos_mut(fn, fixture="m.npz"):
    def change(a):
        p = a["positions"].copy()
        return fn(p, a)
    return npz_mut(fixture, positions=change)


def truncated(fixture: str, keep: float = 0.5):
    def make(path: Path, fx: Path):
        data = (fx / fixture).read_bytes()
        path.write_bytes(data[: int(len(data) * keep)])
    return make


def csv_mut(fn, fixture="m.csv"):
    """A CSV whose lines (header first) are changed by ``fn(list of str) -> list of str``."""
    def make(path: Path, fx: Path):
        lines = (fx / fixture).read_text().splitlines()
        path.write_text("\n".join(fn(lines)) + "\n")
    return make


def json_file(obj):
    return json.dumps(obj)


def zip_with(members: dict):
    def make(path: Path, fx: Path):
        with zipfile.ZipFile(path, "w") as z:
            for name, data in members.items():
                z.writestr(name, data)
    return make


def pickled_npz(path: Path, fx: Path):
    with open(path, "wb") as f:
        np.savez(f, positions=np.array([{"__reduce__": "os.system"}], dtype=object), times=np.zeros(2),
                 scenario=np.array("{}"))


def fifo(path: Path, fx: Path):
    os.mkfifo(path)


def bomb_npz(path: Path, fx: Path):
    """A 60 KB archive that unpacks to 400 MB of positions."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        with z.open("positions.npy", "w", force_zip64=True) as f:
            header = {"descr": "<f8", "fortran_order": False, "shape": (1000, 16667, 3)}
            np.lib.format.write_array_header_1_0(f, header)
            chunk = bytes(1 << 20)
            for _ in range(400):
                f.write(chunk)
        with np.load(fx / "m.npz") as d:
            for k in ("times", "scenario", "rest_positions", "faces"):
                buf = __import__("io").BytesIO()
                np.save(buf, d[k])
                z.writestr(f"{k}.npy", buf.getvalue())


def link(target: str, hard: bool = False):
    def make(path: Path, fx: Path):
        (os.link if hard else os.symlink)(path.parent / target if hard else target, path)
    return make


def folder(path: Path, fx: Path):
    path.mkdir(parents=True, exist_ok=True)


def checkpoint_dir(config=None, weights: Optional[bytes] = None, recipe=True):
    """A copy of the shipped model's folder with its config or weights replaced."""
    def make(path: Path, fx: Path):
        path.mkdir(parents=True, exist_ok=True)
        src = REPO / "models" / "default"
        for name in ("config.json", "feature_recipe.json", "model.safetensors"):
            if name == "feature_recipe.json" and not recipe:
                continue
            if (src / name).exists():
                shutil.copyfile(src / name, path / name)
        if config is not None:
            (path / "config.json").write_text(config if isinstance(config, str) else json.dumps(config))
        if weights is not None:
            (path / "model.safetensors").write_bytes(weights)
    return make


def shipped_config(**changes):
    c = json.loads((REPO / "models" / "default" / "config.json").read_text())
    c["config"].update(changes)
    return c


def materialise(d: Path, files: dict, fx: Path) -> None:
    for name, spec in files.items():
        p = d / name
        p.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(spec, str) and spec.startswith("@"):
            src = fx / spec[1:]
            if src.is_dir():
                shutil.copytree(src, p)
            else:
                shutil.copyfile(src, p)
        elif isinstance(spec, bytes):
            p.write_bytes(spec)
        elif isinstance(spec, str):
            p.write_text(spec)
        else:
            spec(p, fx)
