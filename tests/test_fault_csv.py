"""Fault injection, measurement CSV files: columns read by name in any order, a byte-order mark, a missing header
or scenario said, fractional ids and long rows refused, and npz -> CSV -> npz a lossless round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest

from unipixie.core import cli
from unipixie.core.errors import UserError
from unipixie.core.measurement import MeasuredMaterial, load, load_csv

from fault_helpers import _falling_cube


# --------------------------------------------------------------------------- CSV by column name
def test_csv_columns_are_read_by_name_in_any_order(tmp_path):
    m = _falling_cube()
    m.save_csv(tmp_path / "m.csv")
    rows = (tmp_path / "m.csv").read_text().splitlines()
    swapped = ["T,ID,Z,Y,X"] + [",".join([r.split(",")[i] for i in (0, 1, 4, 3, 2)]) for r in rows[1:]]
    (tmp_path / "s.csv").write_text("\n".join(swapped) + "\n")
    back = load_csv(tmp_path / "s.csv", scenario=tmp_path / "m.json")
    np.testing.assert_array_equal(back.positions, m.positions)
    (tmp_path / "bad.csv").write_text("t,id,x,y\n0,0,1,2\n")
    with pytest.raises(UserError, match="lacks column"):
        load_csv(tmp_path / "bad.csv")


def test_a_fractional_point_id_is_refused(tmp_path):
    (tmp_path / "ids.csv").write_text("t,id,x,y,z\n0,1,0,0,0\n0,1.5,0,0,1\n0.1,1,0,0,0\n")
    with pytest.raises(UserError, match="'1.5' is not a whole number"):
        load_csv(tmp_path / "ids.csv")


def test_a_csv_with_a_byte_order_mark_reads_as_without(tmp_path):
    m = _falling_cube()
    m.save_csv(tmp_path / "m.csv")
    text = (tmp_path / "m.csv").read_text(encoding="utf-8")
    (tmp_path / "bom.csv").write_text("\ufeff" + text, encoding="utf-8")
    (tmp_path / "bom.json").write_text((tmp_path / "m.json").read_text())
    back = load_csv(tmp_path / "bom.csv")
    np.testing.assert_array_equal(back.positions, m.positions)


def test_a_csv_row_longer_than_its_header_is_refused(tmp_path):
    m = _falling_cube()
    m.save_csv(tmp_path / "m.csv")
    rows = (tmp_path / "m.csv").read_text().splitlines()
    (tmp_path / "long.csv").write_text("\n".join(rows + ["0," * 2000]) + "\n")  # was read as t=0, id=0, x=y=z=0
    (tmp_path / "long.json").write_text((tmp_path / "m.json").read_text())
    with pytest.raises(UserError, match=f"line {len(rows) + 1}: 2001 cells where the header names 5"):
        load_csv(tmp_path / "long.csv")
    (tmp_path / "trail.csv").write_text("\n".join([rows[0]] + [r + "," for r in rows[1:]]) + "\n")
    (tmp_path / "trail.json").write_text((tmp_path / "m.json").read_text())
    np.testing.assert_array_equal(load_csv(tmp_path / "trail.csv").positions, m.positions)  # empty trailing cells


def test_a_csv_without_scenario_says_the_default_it_assumes(tmp_path, capsys):
    m = _falling_cube()
    m.save_csv(tmp_path / "m.csv")
    (tmp_path / "m.json").unlink()
    assert any("default is assumed" in w for w in load_csv(tmp_path / "m.csv").warnings)
    assert cli.main(["measure", "convert", str(tmp_path / "m.csv"), str(tmp_path / "m.npz")]) == 0
    assert "warning: no scenario for this CSV" in capsys.readouterr().out


def test_a_csv_without_header_says_how_its_columns_are_read(tmp_path):
    (tmp_path / "n.csv").write_text("0,0,0,0,1\n0.1,0,0,0,0.95\n")
    assert any("no header" in w for w in load_csv(tmp_path / "n.csv").warnings)
    (tmp_path / "h.csv").write_text("t,id,x,y,z\n0,0,0,0,1\n0.1,0,0,0,0.95\n")
    assert not any("no header" in w for w in load_csv(tmp_path / "h.csv").warnings)


# --------------------------------------------------------------------------- lossless round trip
def test_csv_round_trip_keeps_faces_rest_and_unobserved_points(tmp_path):
    m = _falling_cube()
    m.positions[:, 5] = np.nan  # a point never observed
    m.extra_arrays["synth_truth"] = np.array("{}")
    path, dropped = m.save_csv(tmp_path / "m.csv")
    assert dropped == ["synth_truth"]
    back = load(path)
    assert back.point_count == m.point_count
    np.testing.assert_array_equal(back.positions, m.positions)
    np.testing.assert_array_equal(back.rest, m.rest)
    np.testing.assert_array_equal(back.faces, m.faces)
    np.testing.assert_array_equal(back.times, m.times)


def test_measure_convert_round_trip_npz_csv_npz_is_lossless(tmp_path, capsys):
    m = _falling_cube()
    m.positions[:, 5] = np.nan                       # a point never observed
    m.positions[3:6, 2] = np.nan                     # occlusions
    m.rest_positions = m.rest + 1e-3                 # a rest shape that is not positions[0]
    m.material = MeasuredMaterial(np.linspace(1e5, 3e5, 8), 0.3, np.full(8, 900.0))  # per point
    m.extra_arrays["synth_truth"] = np.array("{}")
    m.save(tmp_path / "a.npz")
    assert cli.main(["measure", "convert", str(tmp_path / "a.npz"), str(tmp_path / "a.csv")]) == 0
    out = capsys.readouterr().out
    assert "12 faces" in out and "rest positions" in out and "per-point material" in out
    assert "drop the archive key(s) synth_truth" in out           # what the CSV cannot hold is said
    assert cli.main(["measure", "convert", str(tmp_path / "a.csv"), str(tmp_path / "b.npz")]) == 0
    with np.load(tmp_path / "a.npz") as a, np.load(tmp_path / "b.npz") as b:
        assert sorted(b.files) == sorted(k for k in a.files if k != "synth_truth")
        for k in b.files:
            if a[k].dtype.kind == "f":
                np.testing.assert_array_equal(a[k], b[k], err_msg=k)  # NaN where NaN, every bit of the rest
            elif k == "scenario":
                assert json.loads(str(a[k])) == json.loads(str(b[k]))
            else:
                np.testing.assert_array_equal(a[k], b[k], err_msg=k)
