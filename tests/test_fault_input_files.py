"""Fault injection, bad input files: corrupt and malicious archives, JSON, .blend, grids, pack indexes and OBJ
files, numbers written as text in JSON inputs.  Each is one clear error (UserError, one line), never a traceback
or a file read as something else."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from unipixie.core import atomic_io, cli
from unipixie.core.errors import EXIT_BAD_INPUT, UserError, read_json
from unipixie.core.measurement import Measurement, load, load_csv
from unipixie.solvers.scenario import Scenario

from fault_helpers import _falling_cube


# --------------------------------------------------------------------------- corrupt and malicious files
def test_corrupt_and_malicious_archives_are_refused(tmp_path):
    from unipixie.core.types import MaterialField

    cut = tmp_path / "cut.npz"
    good = tmp_path / "good.npz"
    _falling_cube().save(good)
    cut.write_bytes(good.read_bytes()[:200])
    with pytest.raises(UserError, match="not a readable"):
        load(cut)
    evil = tmp_path / "evil.npz"  # an object array would need pickle: never loaded
    np.savez(evil, positions=np.array([{"x": 1}], dtype=object), times=np.zeros(2), scenario=np.array("{}"))
    with pytest.raises(UserError):
        load(evil)
    noE = tmp_path / "noE.npz"
    np.savez(noE, format="unipixie.material_field/1", occupancy=np.packbits(np.ones(64, bool)),
             geometry=json.dumps({"resolution": 4, "origin": [0, 0, 0], "voxel_size": 0.25}), nu=np.full(64, 0.3), density=np.full(64, 1e3),
             material=np.zeros(64, np.int16), alpha=np.float64(0.5), meta="{}")
    with pytest.raises(UserError, match="'E'"):
        MaterialField.load(noE)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(os.urandom(300))
    with pytest.raises(UserError):
        MaterialField.load(junk)


def test_corrupt_json_files_are_one_line_errors(tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(UserError, match="not valid JSON"):
        read_json(deep)
    binary = tmp_path / "bin.json"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(UserError, match="not valid JSON"):
        read_json(binary)
    from unipixie.core.diagnosis.report import load_report

    arr = tmp_path / "diagnosis.json"
    arr.write_text("[1, 2]")
    with pytest.raises(UserError, match="JSON object"):
        load_report(arr)


def test_cut_off_blend_is_refused_by_its_check(tmp_path):
    p = tmp_path / "x.blend"
    p.write_bytes(atomic_io.ZSTD_MAGIC + b"\0" * 100)
    with pytest.raises(UserError, match="cut off"):
        atomic_io.check_blend(p)
    p.write_bytes(b"not a blend at all")
    with pytest.raises(UserError, match="not a .blend"):
        atomic_io.check_blend(p)


def test_a_deeply_nested_scenario_key_is_a_one_line_error(tmp_path, capsys):
    m = _falling_cube()
    m.save(tmp_path / "m.npz")
    with np.load(tmp_path / "m.npz") as d:
        arrays = {k: d[k] for k in d.files}
    arrays["scenario"] = np.array("[" * 100000 + "]" * 100000)
    np.savez(tmp_path / "deep.npz", **arrays)
    with pytest.raises(UserError, match="not valid JSON"):
        load(tmp_path / "deep.npz")
    with pytest.raises(UserError, match="not valid JSON"):
        Scenario.from_json("[" * 100000 + "]" * 100000)
    assert cli.main(["measure", "show", str(tmp_path / "deep.npz")]) == EXIT_BAD_INPUT
    assert "internal error" not in capsys.readouterr().err


def test_a_grid_whose_resolution_does_not_match_its_bits_is_one_line(tmp_path):
    from unipixie.core.types import FeatureGrid, GridGeometry, MaterialField

    R = 8
    occ = np.zeros((R, R, R), bool)
    occ[2:5, 2:5, 2:5] = True
    geo = GridGeometry(resolution=R, origin=[0, 0, 0], voxel_size=0.1)
    FeatureGrid(geo, occ, np.zeros((int(occ.sum()), 4), np.float16), "offline-random-vit-w32").save(tmp_path / "g.npz")
    MaterialField.homogeneous(geo, occ, 2e5, 0.3, 800.0).save(tmp_path / "f.npz")
    for name, cls in (("g.npz", FeatureGrid), ("f.npz", MaterialField)):
        with np.load(tmp_path / name) as d:
            arrays = {k: d[k] for k in d.files}
        arrays["geometry"] = np.array(json.dumps({"resolution": 100000, "origin": [0, 0, 0], "voxel_size": 0.1}))
        np.savez(tmp_path / f"bad_{name}", **arrays)
        with pytest.raises(UserError, match="resolution 100000"):
            cls.load(tmp_path / f"bad_{name}")  # was ValueError: cannot reshape


@pytest.mark.parametrize("index", ["{bad json", "[1, 2]"])
def test_a_corrupt_pack_index_is_one_line(index, tmp_path, capsys):
    from unipixie import cli as root_cli

    (tmp_path / "pk").mkdir()
    (tmp_path / "pk" / "index.json").write_text(index)
    assert root_cli.main(["dataset", "unpack", str(tmp_path / "pk"), str(tmp_path / "out")]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "index.json" in err and "internal error" not in err, err  # was JSONDecodeError / AttributeError


@pytest.mark.parametrize("change, needle", [
    (lambda t: t.replace("v 0 0 0", "v nan 0 0"), "three finite coordinates"),   # Blender read nan as 0
    (lambda t: t.replace("v 1 1 1", "v inf 1 1"), "three finite coordinates"),
    (lambda t: t + "f 1 2 99\n", "names vertex 99"),                            # Blender dropped the face
    (lambda t: t + "f 0 1 2\n", "does not exist"),
])
def test_an_obj_that_blender_would_quietly_change_is_refused(change, needle, tmp_path):
    from unipixie.core.blender_io.scene_import import check_obj_file

    cube = "".join(f"v {x} {y} {z}\n" for x in (0, 1) for y in (0, 1) for z in (0, 1)) + \
        "f 1 2 4 3\nf 5 7 8 6\nf 1/1 5/2 6/3 2/4\nf -1 -2 -3\n"
    (tmp_path / "ok.obj").write_text(cube)
    check_obj_file(tmp_path / "ok.obj")
    (tmp_path / "bad.obj").write_text(change(cube))
    with pytest.raises(UserError, match=needle):
        check_obj_file(tmp_path / "bad.obj")


# --------------------------------------------------------------------------- numbers as text
def test_scenario_numbers_as_text_are_refused_in_every_key():
    base = {"format": "unipixie.measurement/1"}
    for key, value in (("gravity", ["0", "0", "-9.81"]), ("ground", {"height": "0"}),
                       ("initial_velocity", [0, "1", 0]), ("pinned_box", [[0, 0, 0], ["1", 1, 1]])):
        with pytest.raises(UserError, match=key):
            Scenario.from_dict({**base, key: value})


def test_numbers_as_text_are_refused_in_every_json_input(tmp_path):
    from unipixie.core import bake

    m = _falling_cube()
    m.save_csv(tmp_path / "m.csv")
    side = json.loads((tmp_path / "m.json").read_text())
    side["csv_sidecar"]["rest_positions"][0][2] = "0.05"     # was read: numpy turned the list into text
    (tmp_path / "m.json").write_text(json.dumps(side))
    with pytest.raises(UserError, match="csv_sidecar.rest_positions' must hold numbers"):
        load_csv(tmp_path / "m.csv")
    with pytest.raises(UserError, match="'material' key 'E' must hold numbers"):  # was accepted as 2e5 Pa
        bake.material_source_from_dict({"E": "2e5"})
    with pytest.raises(UserError, match="'seed' must hold numbers"):
        bake.material_source_from_dict({"source": "model", "seed": "3"})
    jobs = {"format": bake.MANIFEST_FORMAT, "jobs": [{"scene": "s.blend", "object": "A", "out": "o.blend",
                                                      "alpha": "0.5"}]}
    (tmp_path / "jobs.json").write_text(json.dumps(jobs))
    with pytest.raises(UserError, match="'alpha' must hold numbers"):  # was accepted as α = 0.5
        bake.load_manifest(tmp_path / "jobs.json")
    with pytest.raises(UserError, match="scenario key 'material' entry 'E' must hold numbers"):
        Measurement(positions=m.positions, times=m.times, scenario={**m.scenario_dict(), "material": {
            "E": "2e5", "nu": 0.3, "density": 1000.0}}, rest_positions=m.rest)
