"""The fault matrix's cases: what a case is (``Case``: a command line, its files, the exit statuses it may end
with, its outputs, a check) and the matrix itself (``build_cases``), every command against bad inputs and faults."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from matrix_checks import csv_same_as_npz, output_exists, verdict_not_explained
from matrix_inputs import (OBJ_CUBE, REPO, SYNTH_SMALL, bomb_npz, checkpoint_dir, csv_mut, fifo, folder, json_file,
                           link, npz_mut, pickled_npz, pos_mut, scen_mut, shipped_config, truncated, zip_with)


BAD, OK, CANCEL, OKBAD = (2,), (0,), (130,), (0, 2)

EXIT_TABLE = {0: "done", 1: "internal error", 2: "bad input", 3: "simulation failed", 130: "cancelled"}


@dataclass
class Case:
    """One invocation: ``argv`` after ``unipixie`` ({d} is the case folder), ``files`` to make first."""

    id: str
    kind: str
    argv: list
    expect: tuple = BAD
    files: dict = field(default_factory=dict)
    outputs: list = field(default_factory=list)   # final output names (relative to {d}); folders allowed
    overwritten: list = field(default_factory=list)  # inputs that an exit 0 may legitimately replace
    check: Optional[Callable] = None              # (folder, result) -> None or what is false
    timeout: float = 90.0
    interrupt: bool = False                       # send SIGINT while it works (twice with interrupt_twice)
    interrupt_after: float = 2.5                  # seconds after the start (imports done, work begun)
    interrupt_twice: bool = False
    fs: Optional[str] = None                      # "full" or "ro": mnt/ is a small tmpfs
    concurrent: int = 1
    env: dict = field(default_factory=dict)
    note: str = ""


# --------------------------------------------------------------------------- the cases
def with_opt(base: list, opt: str, value=None) -> list:
    """``base`` with option ``opt`` set to ``value`` (replaced if present; a flag when value is None)."""
    out = list(base)
    if opt in out:
        i = out.index(opt)
        if value is None:
            return out
        out[i + 1] = value
        return out
    return out + ([opt] if value is None else [opt, value])


def without(base: list, opt: str, has_value=True) -> list:
    out = list(base)
    if opt in out:
        i = out.index(opt)
        del out[i: i + (2 if has_value else 1)]
    return out


def slug(s: str) -> str:
    keep = "".join(c if c.isalnum() or c in "-_=." else "_" for c in s)
    return keep.strip("_")[:40] or "empty"


def build_cases() -> list[Case]:
    cases: list[Case] = []

    def add(id, kind, argv, **kw):
        cases.append(Case(id=id, kind=kind, argv=argv, **kw))

    def bad_values(prefix, kind, base, opt, values, files, outputs, **kw):
        for v in values:
            add(f"{prefix}.{opt.lstrip('-')}={slug(v)}", kind, with_opt(base, opt, v), files=files,
                outputs=outputs, **kw)

    # ---------------------------------------------------------------- measure synth
    SYN = ["measure", "synth", "--out", "{d}/o.npz", *SYNTH_SMALL]
    so = ["o.npz"]
    add("synth.control", "control", SYN, expect=OK, outputs=so, check=output_exists("o.npz"))
    for opt, vals in {"--points": ["0", "-5", "abc", "1.5"], "--duration": ["0", "-1", "nan", "inf"],
                      "--fps": ["0", "-20", "nan", "inf"], "--noise": ["-0.001", "nan", "inf"],
                      "--occlusion": ["1.5", "-0.1", "1", "nan"], "--E": ["0", "-1", "nan", "inf", "1e400"],
                      "--nu": ["0.5", "0.6", "-1.1", "nan"], "--density": ["0", "-1", "nan"],
                      "--true-E-scale": ["0", "-1", "nan"], "--spin": ["nan", "inf"],
                      "--velocity": ["1,2", "a,b,c", "nan,0,0", "1,2,3,4"], "--height": ["nan", "inf", "-1"],
                      "--seed": ["-1", "1.5", "abc"], "--device": ["tpu", "cuda:99"],
                      "--setting": ["anchors=0", "anchors=-3", "anchors=abc", "nope=1", "anchors", "anchors=1e9"],
                      "--effect": ["nope", "wind:acceleration=0,0", "linear_drag:c=-1", "linear_drag:c=nan",
                                   "linear_drag:q=1", "linear_drag:c=abc", "stiffness_region:factor=3,box=1,1,1,0,0,0",
                                   "stiffness_region:factor=0,box=0,0,0,1,1,1", "linear_drag:c=0.5:extra"]}.items():
        bad_values("synth", "impossible_value" if opt not in ("--points", "--seed") else "wrong_type", SYN, opt,
                   vals, {}, so)
    add("synth.duration_absurd", "absurd_frames", with_opt(with_opt(SYN, "--duration", "1e6"), "--fps", "1000"),
        outputs=so, timeout=60)
    add("synth.fps_absurd", "absurd_frames", with_opt(SYN, "--fps", "1e7"), outputs=so, timeout=60)
    add("synth.exists_no_force", "existing_output", SYN, files={"o.npz": "@m.npz"}, outputs=so)
    add("synth.out_is_dir", "bad_output", SYN, files={"o.npz": folder}, outputs=[])
    add("synth.out_parent_is_file", "bad_output", with_opt(SYN, "--out", "{d}/f/o.npz"), files={"f": "x"}, outputs=[])
    add("synth.out_unknown_ext", "bad_output", with_opt(SYN, "--out", "{d}/o.txt"), outputs=["o.txt"])
    add("synth.out_symlink_dangling_force", "symlinked_output", with_opt(SYN, "--force"),
        files={"o.npz": link("nowhere/x.npz")}, expect=OKBAD, outputs=so)
    add("synth.out_symlink_to_fixture_force", "symlinked_output", with_opt(SYN, "--force"),
        files={"keep.npz": "@m.npz", "o.npz": link("keep.npz")}, expect=OKBAD, outputs=so, overwritten=["keep.npz"],
        note="writing through a link the user made is allowed; the target must stay readable")
    add("synth.full_disk", "full_disk", with_opt(SYN, "--out", "{d}/mnt/o.npz"), fs="full", outputs=["mnt/o.npz"])
    add("synth.full_disk_keeps_old", "full_disk", with_opt(with_opt(SYN, "--out", "{d}/mnt/o.npz"), "--force"),
        fs="full", files={"mnt/o.npz": "@m.npz"}, outputs=["mnt/o.npz"])
    add("synth.read_only", "read_only", with_opt(SYN, "--out", "{d}/mnt/o.npz"), fs="ro", outputs=["mnt/o.npz"])
    add("synth.read_only_csv", "read_only", with_opt(SYN, "--out", "{d}/mnt/o.csv"), fs="ro",
        outputs=["mnt/o.csv", "mnt/o.json"])
    add("synth.ctrl_c", "ctrl_c", ["measure", "synth", "--out", "{d}/o.npz", "--solver", "mpm", "--duration", "6",
                                   "--setting", "cells_across=12"], expect=CANCEL, interrupt=True, outputs=so)
    add("synth.ctrl_c_twice", "ctrl_c", ["measure", "synth", "--out", "{d}/o.npz", "--solver", "mpm", "--duration",
                                         "6", "--setting", "cells_across=12"], expect=CANCEL, interrupt=True,
        interrupt_twice=True, outputs=so)
    add("synth.concurrent_same_out", "concurrent", with_opt(SYN, "--force"), concurrent=2, expect=OKBAD, outputs=so)

    # ---------------------------------------------------------------- measure show / convert: corrupt files
    corrupt_npz = {
        "empty": b"", "random": os.urandom(2048), "truncated": truncated("m.npz"), "png_renamed": b"\x89PNG\r\n\x1a\n" + b"\0" * 64,
        "pickle": pickled_npz, "zip_of_junk": zip_with({"positions.npy": b"junk", "times.npy": b"junk"}),
        "no_positions": npz_mut("m.npz", positions=None), "no_times": npz_mut("m.npz", times=None),
        "no_scenario": npz_mut("m.npz", scenario=None),
        "positions_2d": npz_mut("m.npz", positions=lambda a: a["positions"][:, :, 0]),
        "positions_4_coords": npz_mut("m.npz", positions=lambda a: np.concatenate([a["positions"], a["positions"][..., :1]], -1)),
        "positions_text": npz_mut("m.npz", positions=lambda a: a["positions"].astype(str)),
        "positions_complex": npz_mut("m.npz", positions=lambda a: a["positions"].astype(complex)),
        "times_short": npz_mut("m.npz", times=lambda a: a["times"][:-1]),
        "times_nan": npz_mut("m.npz", times=lambda a: np.where(np.arange(len(a["times"])) == 2, np.nan, a["times"])),
        "times_decreasing": npz_mut("m.npz", times=lambda a: a["times"][::-1].copy()),
        "times_repeated": npz_mut("m.npz", times=lambda a: np.zeros_like(a["times"])),
        "times_inf": npz_mut("m.npz", times=lambda a: np.where(np.arange(len(a["times"])) == 4, np.inf, a["times"])),
        "positions_inf": pos_mut(lambda p, a: np.where(np.isfinite(p), p, 0) * np.where(np.arange(p.shape[0])[:, None, None] == 1, np.inf, 1)),
        "all_nan": pos_mut(lambda p, a: p * np.nan),
        "one_instant": npz_mut("m.npz", positions=lambda a: a["positions"][:1], times=lambda a: a["times"][:1]),
        "zero_points": npz_mut("m.npz", positions=lambda a: a["positions"][:, :0], rest_positions=lambda a: a["rest_positions"][:0],
                               faces=lambda a: a["faces"][:0]),
        "rest_mismatch": npz_mut("m.npz", rest_positions=lambda a: a["rest_positions"][:-2]),
        "faces_out_of_range": npz_mut("m.npz", faces=lambda a: a["faces"] + 1000),
        "faces_negative": npz_mut("m.npz", faces=lambda a: a["faces"] - 100),
        "faces_float": npz_mut("m.npz", faces=lambda a: a["faces"] + 0.5),
        "scenario_not_json": npz_mut("m.npz", scenario=np.array("{gravity: ")),
        "scenario_array": npz_mut("m.npz", scenario=np.array("[1, 2]")),
        "scenario_bytes": npz_mut("m.npz", scenario=np.frombuffer(b"\xff\xfe\x00garbage", np.uint8)),
        "gravity_strings": scen_mut(lambda s: s.update(gravity=["0", "0", "-9.81"])),
        "gravity_two": scen_mut(lambda s: s.update(gravity=[0, -9.81])),
        "gravity_nan": scen_mut(lambda s: s.update(gravity=[0, 0, float("nan")])),
        "ground_string": scen_mut(lambda s: s.update(ground={"height": "0"})),
        "velocity_string": scen_mut(lambda s: s.update(initial_velocity=[0, "1", 0])),
        "pinned_box_string": scen_mut(lambda s: s.update(pinned_box=[[0, 0, 0], ["1", 1, 1]])),
        "material_E_string": scen_mut(lambda s: s.update(material={"E": "2e5", "nu": 0.3, "density": 1000})),
        "material_E_negative": scen_mut(lambda s: s.update(material={"E": -2e5, "nu": 0.3, "density": 1000})),
        "material_nu_half": scen_mut(lambda s: s.update(material={"E": 2e5, "nu": 0.5, "density": 1000})),
        "material_density_zero": scen_mut(lambda s: s.update(material={"E": 2e5, "nu": 0.3, "density": 0})),
        "format_unknown": scen_mut(lambda s: s.update(format="unipixie.measurement/99")),
        "deep_json": npz_mut("m.npz", scenario=np.array("[" * 100000 + "]" * 100000)),
        "bomb": bomb_npz,
        "fifo": fifo,
        "directory": folder,
    }
    for name, maker in corrupt_npz.items():
        kind = {"pickle": "malicious_file", "bomb": "malicious_file", "fifo": "malicious_file",
                "deep_json": "malicious_file"}.get(name, "wrong_type" if "string" in name or "text" in name
                                                   or "float" in name or "complex" in name else "corrupt_file")
        timeout = 60
        expect = BAD
        if name == "bomb":
            expect = OKBAD  # a 400 MB measurement may be read or refused, never a crash or a hang
        add(f"show.{name}", kind, ["measure", "show", "{d}/x.npz"], files={"x.npz": maker}, timeout=timeout,
            expect=expect)
    for name in ("truncated", "pickle", "positions_2d", "times_decreasing", "faces_out_of_range", "scenario_not_json",
                 "gravity_strings", "material_E_negative", "fifo", "all_nan"):
        add(f"convert.{name}", corrupt_npz_kind(name), ["measure", "convert", "{d}/x.npz", "{d}/x.csv"],
            files={"x.npz": corrupt_npz[name]}, outputs=["x.csv", "x.json"], timeout=60)
    add("show.missing", "missing_file", ["measure", "show", "{d}/nope.npz"])
    add("show.dev_zero", "malicious_file", ["measure", "show", "{d}/z.npz"], files={"z.npz": link("/dev/zero")}, timeout=60)
    add("show.control", "control", ["measure", "show", "{d}/m.npz"], files={"m.npz": "@m.npz"}, expect=OK)

    # CSV
    csvf = {"m.json": "@m.json"}
    def csv_case(name, fn, kind="corrupt_file", expect=BAD, cmd="show", check=None, extra_files=None):
        files = {"x.csv": csv_mut(fn), "x.json": "@m.json", **(extra_files or {})}
        if cmd == "show":
            add(f"csv.{name}", kind, ["measure", "show", "{d}/x.csv"], files=files, expect=expect, check=check)
        else:
            add(f"csv.{name}", kind, ["measure", "convert", "{d}/x.csv", "{d}/out.npz"], files=files,
                expect=expect, outputs=["out.npz"], check=check)

    def reorder(lines):
        idx = (2, 4, 0, 3, 1)  # x, z, t, y, id
        return [",".join(l.split(",")[i] for i in idx) for l in lines]
    csv_case("columns_reordered", reorder, kind="reinterpretation", expect=OK, cmd="convert", check=csv_same_as_npz,
             extra_files={"m.npz": "@m.npz"})
    csv_case("columns_uppercase_reordered", lambda L: ["T,ID,Z,Y,X"] + [",".join(r.split(",")[i] for i in (0, 1, 4, 3, 2)) for r in L[1:]],
             kind="reinterpretation", expect=OK, cmd="convert", check=csv_same_as_npz, extra_files={"m.npz": "@m.npz"})
    csv_case("id_fractional", lambda L: L[:2] + [L[2].replace(",2,", ",1.5,", 1)] + L[3:], kind="reinterpretation")
    csv_case("missing_column", lambda L: [",".join(l.split(",")[:4]) for l in L])
    csv_case("x_not_number", lambda L: L[:3] + [",".join(L[3].split(",")[:2] + ["abc"] + L[3].split(",")[3:])] + L[4:],
             kind="wrong_type")
    csv_case("t_not_number", lambda L: L[:3] + ["soon," + ",".join(L[3].split(",")[1:])] + L[4:], kind="wrong_type")
    csv_case("empty", lambda L: [])
    csv_case("header_only", lambda L: L[:1])
    csv_case("semicolons", lambda L: [l.replace(",", ";") for l in L])
    csv_case("bom", lambda L: ["\ufeff" + L[0]] + L[1:], kind="reinterpretation", expect=OK)
    csv_case("duplicate_rows_disagree", lambda L: L + [",".join(L[1].split(",")[:2] + ["5", "5", "5"])],
             kind="contradictory_measurement")
    csv_case("x_inf", lambda L: L[:3] + [",".join(L[3].split(",")[:2] + ["inf"] + L[3].split(",")[3:])] + L[4:],
             kind="impossible_value")
    csv_case("t_milliseconds_show", lambda L: L[:1] + [",".join([str(float(l.split(",")[0]) * 1000)] + l.split(",")[1:]) for l in L[1:]],
             kind="milliseconds", expect=OKBAD)
    csv_case("sidecar_numbers_as_strings", lambda L: L, kind="wrong_type",
             extra_files={"x.json": lambda p, fx: p.write_text((fx / "m.json").read_text().replace("-9.81", '"-9.81"'))})
    csv_case("sidecar_not_json", lambda L: L, extra_files={"x.json": "{not json"})
    csv_case("sidecar_array", lambda L: L, extra_files={"x.json": "[1, 2, 3]"})
    csv_case("sidecar_ids_mismatch", lambda L: L, kind="contradictory_measurement",
             extra_files={"x.json": lambda p, fx: p.write_text(json.dumps({**json.loads((fx / "m.json").read_text()),
                 "csv_sidecar": {**json.loads((fx / "m.json").read_text())["csv_sidecar"], "point_ids": ["0", "1"]}}))})
    csv_case("binary", lambda L: L, extra_files={"x.csv": os.urandom(4096)})
    csv_case("huge_line", lambda L: L + ["0," * 200000], expect=BAD)
    add("convert.csv_missing_sidecar_given", "missing_file", ["measure", "convert", "{d}/m.csv", "{d}/out.npz",
                                                              "--scenario", "{d}/nope.json"],
        files={"m.csv": "@m.csv"}, outputs=["out.npz"])
    add("convert.exists_no_force", "existing_output", ["measure", "convert", "{d}/m.npz", "{d}/out.csv"],
        files={"m.npz": "@m.npz", "out.csv": "@m.csv"}, outputs=["out.csv"])
    add("convert.onto_itself", "symlinked_output", ["measure", "convert", "{d}/m.npz", "{d}/m.npz", "--force"],
        files={"m.npz": "@m.npz"})
    add("convert.onto_input_via_symlink", "symlinked_output", ["measure", "convert", "{d}/m.npz", "{d}/l.npz", "--force"],
        files={"m.npz": "@m.npz", "l.npz": link("m.npz")})
    add("convert.onto_input_via_hardlink", "symlinked_output", ["measure", "convert", "{d}/m.npz", "{d}/h.npz", "--force"],
        files={"m.npz": "@m.npz", "h.npz": link("m.npz", hard=True)})
    add("convert.csv_sidecar_onto_input", "symlinked_output", ["measure", "convert", "{d}/m.npz", "{d}/s.csv", "--force"],
        files={"m.npz": "@m.npz", "s.json": link("m.npz", hard=True)}, outputs=["s.csv"],
        note="the CSV's side-car s.json is a hard link of the input")
    add("convert.unknown_ext", "bad_output", ["measure", "convert", "{d}/m.npz", "{d}/out.xyz"], files={"m.npz": "@m.npz"},
        outputs=["out.xyz"])
    add("convert.full_disk", "full_disk", ["measure", "convert", "{d}/m.npz", "{d}/mnt/o.csv"], files={"m.npz": "@m.npz"},
        fs="full", outputs=["mnt/o.csv", "mnt/o.json"])
    add("convert.read_only", "read_only", ["measure", "convert", "{d}/m.npz", "{d}/mnt/o.npz"], files={"m.npz": "@m.npz"},
        fs="ro", outputs=["mnt/o.npz"])
    add("convert.concurrent", "concurrent", ["measure", "convert", "{d}/m.npz", "{d}/o.csv", "--force"],
        files={"m.npz": "@m.npz"}, concurrent=2, expect=OKBAD, outputs=["o.csv", "o.json"])
    for opt, v in (("--E", "-1"), ("--nu", "0.7"), ("--density", "nan")):
        add(f"show.override{opt}={v}", "impossible_value", ["measure", "show", "{d}/m.npz", opt, v], files={"m.npz": "@m.npz"})

    # ---------------------------------------------------------------- diagnose
    DIA = ["diagnose", "{d}/m.npz", "--solver", "spring_mass", "--out", "{d}/rep", "--max-additions", "0",
           "--candidates", "linear_drag", "--setting", "anchors=32", "--quiet"]
    df = {"m.npz": "@m.npz"}
    do = ["rep"]
    add("diagnose.control", "control", DIA, files=df, expect=OK, outputs=do, check=output_exists("rep/diagnosis.json"))
    add("diagnose.far_above_noise", "false_verdict", ["diagnose", "{d}/w.npz", *DIA[2:]], files={"w.npz": "@wind.npz"}, expect=OK, outputs=do,
        check=verdict_not_explained, note="a strong hidden wind, only linear drag offered: must not 'explain'")
    add("diagnose.gravity_flipped", "false_verdict", DIA, files={"m.npz": scen_mut(lambda s: s.update(gravity=[0, 0, 9.81]))},
        expect=OKBAD, outputs=do, check=verdict_not_explained)
    add("diagnose.teleport", "false_verdict", DIA,
        files={"m.npz": pos_mut(lambda p, a: p + np.where(np.arange(p.shape[0])[:, None, None] >= 3, [0.3, 0, 0], 0))},
        expect=OKBAD, outputs=do, check=verdict_not_explained)
    add("diagnose.axes_swapped", "false_verdict", DIA,
        files={"m.npz": pos_mut(lambda p, a: p[..., [2, 1, 0]])}, expect=OKBAD, outputs=do, check=verdict_not_explained)
    for name in ("truncated", "random", "pickle", "times_decreasing", "times_repeated", "all_nan", "one_instant",
                 "zero_points", "faces_out_of_range", "gravity_strings", "material_E_negative", "material_nu_half",
                 "material_density_zero", "positions_inf", "fifo", "directory"):
        add(f"diagnose.{name}", corrupt_npz_kind(name), DIA, files={"m.npz": corrupt_npz[name]}, outputs=do, timeout=60)
    contradictory = {
        "ground_above": scen_mut(lambda s: s.update(ground={"height": 10.0})),
        "all_pinned": scen_mut(lambda s: s.update(pinned_box=[[-9, -9, -9], [9, 9, 9]])),
        "times_1e9_scale": npz_mut("m.npz", positions=lambda a: a["positions"] * 1e9, rest_positions=lambda a: a["rest_positions"] * 1e9),
        "sentinels": pos_mut(lambda p, a: np.where(np.arange(p.shape[1])[None, :, None] < 3, -999999999.0, p)),
        "milliseconds": npz_mut("m.npz", times=lambda a: a["times"] * 1000),
        "frame_numbers_as_times": npz_mut("m.npz", times=lambda a: np.arange(len(a["times"]), dtype=float)),
        "below_ground": pos_mut(lambda p, a: p - 5.0),
    }
    for name, maker in contradictory.items():
        add(f"diagnose.{name}", "milliseconds" if name in ("milliseconds", "frame_numbers_as_times") else
            "contradictory_measurement", DIA, files={"m.npz": maker}, outputs=do, timeout=60)
    add("diagnose.csv_milliseconds", "milliseconds", ["diagnose", "{d}/x.csv", *DIA[2:]],
        files={"x.csv": csv_mut(lambda L: L[:1] + [",".join([str(float(l.split(",")[0]) * 1000)] + l.split(",")[1:]) for l in L[1:]]),
               "x.json": "@m.json"}, outputs=do)
    add("diagnose.csv_no_sidecar", "missing_file", ["diagnose", "{d}/x.csv", *DIA[2:]], files={"x.csv": "@m.csv"},
        outputs=do, expect=OKBAD, note="without a side-car: the default scenario, stated, or a refusal")
    add("diagnose.scenario_corrupt", "corrupt_file", ["diagnose", "{d}/x.csv", *DIA[2:], "--scenario", "{d}/s.json"],
        files={"x.csv": "@m.csv", "s.json": "{\"gravity\": [0, 0,"}, outputs=do)
    add("diagnose.scenario_strings", "wrong_type", ["diagnose", "{d}/x.csv", *DIA[2:], "--scenario", "{d}/s.json"],
        files={"x.csv": "@m.csv", "s.json": json_file({"format": "unipixie.measurement/1", "gravity": ["0", "0", "-9.81"]})},
        outputs=do)
    for opt, vals in {"--max-additions": ["-1", "abc"], "--candidates": ["nope", "", "linear_drag,nope"],
                      "--setting": ["anchors=0", "foo=1", "anchors=abc", "anchors"], "--E": ["0", "-1", "nan"],
                      "--nu": ["0.5", "nan"], "--density": ["0", "inf"], "--device": ["tpu", "cuda:7"],
                      "--add": ["nope", "linear_drag:c=-1"], "--solver": ["fem"]}.items():
        bad_values("diagnose", "impossible_value", DIA, opt, vals, df, do)
    bad_values("diagnose", "impossible_value", DIA, "--effects-on", ["nope", "linear_drag:c=-1", "linear_drag:c=nan"], df, do)
    add("diagnose.out_is_file", "bad_output", with_opt(DIA, "--out", "{d}/m.npz"), files=df)
    add("diagnose.out_is_input_folder_link", "symlinked_output", with_opt(DIA, "--out", "{d}/lnk"),
        files={**df, "lnk": link(".")}, expect=OKBAD, outputs=["lnk/diagnosis.json"],
        note="a report folder that is the input's folder: the input must survive")
    add("diagnose.full_disk", "full_disk", with_opt(DIA, "--out", "{d}/mnt/rep"), files=df, fs="full", outputs=["mnt/rep"])
    add("diagnose.read_only", "read_only", with_opt(DIA, "--out", "{d}/mnt/rep"), files=df, fs="ro", outputs=["mnt/rep"])
    add("diagnose.read_only_old_report", "read_only", with_opt(DIA, "--out", "{d}/mnt/rep"),
        files={**df, "mnt/rep/diagnosis.json": "{\"old\": true}"}, fs="ro", outputs=["mnt/rep"])
    add("diagnose.ctrl_c", "ctrl_c", ["diagnose", "{d}/m.npz", "--solver", "spring_mass", "--out", "{d}/rep",
                                      "--setting", "anchors=64"], files={"m.npz": "@wind.npz"}, expect=CANCEL,
        interrupt=True, outputs=do)
    add("diagnose.concurrent_same_out", "concurrent", DIA, files=df, concurrent=2, expect=OKBAD, outputs=do)
    add("diagnose.cache_dir_is_file", "bad_output", ["--cache-dir", "{d}/c", *DIA], files={**df, "c": "x"},
        expect=OKBAD, outputs=do, note="a cache that cannot be made: refused, or done without it")

    # ---------------------------------------------------------------- predict
    PRE = ["predict", "{d}/grid.npz", "--alpha", "0.5", "--steps", "1", "--out", "{d}/pred"]
    pf = {"grid.npz": "@grid.npz"}
    po = ["pred"]
    add("predict.control", "control", PRE, files=pf, expect=OK, outputs=po, check=output_exists("pred/prediction.json"))
    for opt, vals in {"--steps": ["0", "-1", "abc"], "--alpha": ["1.5", "-0.1", "nan", "inf"],
                      "--alphas": ["0,2", "", "a", "0,,1", "nan"], "--sweep": ["0", "1", "-1", "100000"],
                      "--heads": ["nope", "", "mpm,nope"], "--seed": ["-1", "1.5"], "--device": ["tpu", "cuda:3"]}.items():
        bad_values("predict", "impossible_value", PRE, opt, vals, pf, po, timeout=60)
    for name, maker in {"empty": b"", "random": os.urandom(1000), "truncated": truncated("grid.npz"),
                        "measurement_not_grid": "@m.npz", "pickle": pickled_npz, "fifo": fifo, "directory": folder,
                        "field_not_grid": "@field.npz",
                        "wrong_dim": npz_mut("grid.npz", features=lambda a: a["features"][:, :8]),
                        "rows_mismatch": npz_mut("grid.npz", features=lambda a: a["features"][:-5]),
                        "features_nan": npz_mut("grid.npz", features=lambda a: a["features"] * np.float16("nan")),
                        "geometry_not_json": npz_mut("grid.npz", geometry=np.array("{res")),
                        "resolution_negative": npz_mut("grid.npz", geometry=np.array(json.dumps({"resolution": -4, "origin": [0, 0, 0], "voxel_size": 0.1}))),
                        "resolution_huge": npz_mut("grid.npz", geometry=np.array(json.dumps({"resolution": 100000, "origin": [0, 0, 0], "voxel_size": 0.1}))),
                        "empty_occupancy": npz_mut("grid.npz", occupancy=lambda a: np.zeros_like(a["occupancy"]),
                                                   features=lambda a: a["features"][:0]),
                        "other_extractor": npz_mut("grid.npz", feature_model=np.array("ViT-B-16")),
                        }.items():
        add(f"predict.grid_{name}", corrupt_npz_kind(name), PRE, files={"grid.npz": maker}, outputs=po, timeout=60)
    for name, maker in {"missing": None, "empty_dir": folder,
                        "config_not_json": checkpoint_dir(config="{bad"),
                        "config_array": checkpoint_dir(config="[1]"),
                        "config_strings": checkpoint_dir(config=shipped_config(width="256")),
                        "config_negative_width": checkpoint_dir(config=shipped_config(width=-1)),
                        "weights_truncated": checkpoint_dir(weights=(REPO / "models/default/model.safetensors").read_bytes()[:4096]
                                                            if (REPO / "models/default/model.safetensors").exists() else b"x"),
                        "weights_random": checkpoint_dir(weights=os.urandom(4096)),
                        "weights_header_huge": checkpoint_dir(weights=(2 ** 62).to_bytes(8, "little") + b"{}"),
                        "config_other_size": checkpoint_dir(config=shipped_config(width=128)),
                        "file_not_dir": b"x"}.items():
        files = dict(pf)
        if maker is not None:
            files["ck"] = maker
        add(f"predict.checkpoint_{name}", "corrupt_file" if name != "config_strings" else "wrong_type",
            with_opt(PRE, "--checkpoint", "{d}/ck"), files=files, outputs=po, timeout=60)
    add("predict.out_is_grid", "bad_output", with_opt(PRE, "--out", "{d}/grid.npz"), files=pf)
    add("predict.out_symlink_to_input_dir", "symlinked_output", with_opt(PRE, "--out", "{d}/lnk"),
        files={"in/grid.npz": "@grid.npz", "lnk": link("in")}, expect=OKBAD, outputs=["lnk/prediction.json"])
    add("predict.out_file_is_grid_link", "symlinked_output", with_opt(PRE, "--out", "{d}/pred"),
        files={**pf, "pred/material_field_a0.500.npz": link("../grid.npz")}, expect=BAD, outputs=[],
        note="an output file inside --out is a link to the input grid")
    add("predict.full_disk", "full_disk", with_opt(PRE, "--out", "{d}/mnt/pred"), files=pf, fs="full", outputs=["mnt/pred"])
    add("predict.read_only", "read_only", with_opt(PRE, "--out", "{d}/mnt/pred"), files=pf, fs="ro", outputs=["mnt/pred"])
    add("predict.ctrl_c", "ctrl_c", ["predict", "{d}/grid.npz", "--sweep", "11", "--steps", "30", "--out", "{d}/pred"],
        files=pf, expect=CANCEL, interrupt=True, outputs=po)
    add("predict.concurrent", "concurrent", PRE, files=pf, concurrent=2, expect=OKBAD, outputs=po)

    # ---------------------------------------------------------------- bake
    BAK = ["bake", "{d}/scene.blend", "--object", "Block", "--solver", "spring_mass", "--E", "2e5", "--nu", "0.3",
           "--density", "800", "--frames", "1-5", "--out", "{d}/out.blend"]
    bf = {"scene.blend": "@scene.blend"}
    bo = ["out.blend"]
    add("bake.control", "control", BAK, files=bf, expect=OK, outputs=bo, check=output_exists("out.blend"), timeout=120)
    add("bake.alpha_and_E", "reinterpretation", with_opt(BAK, "--alpha", "0.5"), files=bf, outputs=bo)
    add("bake.material_file_and_E", "reinterpretation", with_opt(BAK, "--material-file", "{d}/field.npz"),
        files={**bf, "field.npz": "@field.npz"}, outputs=bo)
    for opt, vals in {"--alpha": ["1.5", "-0.1", "nan", "0,2"], "--frames": ["10-1", "a-b", "5", "1-5,", "-5-3", "1-10000000"],
                      "--solver": ["nope", "fem"], "--object": ["Nope", ""], "--E": ["0", "-1", "nan", "inf"],
                      "--nu": ["0.5", "nan", "-2"], "--density": ["0", "-800", "nan"], "--material-class": ["nope"],
                      "--gravity": ["0,0", "nan,0,0", "a,b,c"], "--initial-velocity": ["a", "inf,0,0"],
                      "--initial-angular-velocity": ["1,2"], "--ground": ["Nope"], "--ground-height": ["nan", "inf"],
                      "--clamp": ["Nope"], "--clamp-group": ["Nope"],
                      "--settings": ["not json", "[1]", '{"anchors": "8"}', '{"nope": 1}', '{"anchors": 0}',
                                     '{"anchors": -1}', '{"anchors": 1e12}'],
                      "--device": ["tpu", "cuda:5"], "--shard": ["3/2", "0/0", "-1/2", "a/b"],
                      "--output": ["nope"], "--interpolation": ["CUBIC"], "--seed": ["abc"]}.items():
        bad_values("bake", "impossible_value", BAK, opt, vals, bf, bo, timeout=90)
    add("bake.effects_unknown", "impossible_value", BAK + ["--effects", "nope"], files=bf, outputs=bo)
    add("bake.effects_negative", "impossible_value", BAK + ["--effects", "linear_drag:c=-1"], files=bf, outputs=bo)
    add("bake.effects_nan", "impossible_value", BAK + ["--effects", "wind:acceleration=nan,0,0"], files=bf, outputs=bo)
    for name, maker in {"empty": b"", "random": os.urandom(5000), "truncated": truncated("scene.blend"),
                        "npz_renamed": "@m.npz", "fifo": fifo, "directory": folder,
                        "header_only": b"BLENDER-v500REND" + b"\0" * 100}.items():
        add(f"bake.scene_{name}", corrupt_npz_kind(name), BAK, files={"scene.blend": maker}, outputs=bo, timeout=90)
    add("bake.scene_missing", "missing_file", BAK, outputs=bo)
    add("bake.out_is_scene", "symlinked_output", with_opt(BAK, "--out", "{d}/scene.blend"), files=bf)
    add("bake.out_symlink_to_scene", "symlinked_output", BAK, files={**bf, "out.blend": link("scene.blend")})
    add("bake.out_hardlink_to_scene", "symlinked_output", BAK, files={**bf, "out.blend": link("scene.blend", hard=True)})
    add("bake.out_is_dir", "bad_output", BAK, files={**bf, "out.blend": folder}, outputs=[])
    add("bake.out_parent_is_file", "bad_output", with_opt(BAK, "--out", "{d}/f/out.blend"), files={**bf, "f": "x"})
    add("bake.out_template_unknown", "impossible_value", with_opt(BAK, "--out", "{d}/out_{nope}.blend"), files=bf)
    add("bake.out_template_collision", "impossible_value", with_opt(with_opt(BAK, "--object", "Block"), "--frames", "1-3,4-5"),
        files=bf, outputs=bo, note="two frame ranges into one fixed --out name")
    add("bake.out_existing", "existing_output", BAK, files={**bf, "out.blend": "@scene.blend"}, expect=OKBAD,
        outputs=bo, overwritten=["out.blend"])
    for name, maker in {"empty": b"", "random": os.urandom(500), "grid_not_field": "@grid.npz", "measurement": "@m.npz",
                        "pickle": pickled_npz, "E_nan": npz_mut("field.npz", E=lambda a: a["E"] * np.nan),
                        "E_negative": npz_mut("field.npz", E=lambda a: -a["E"]),
                        "nu_half": npz_mut("field.npz", nu=lambda a: a["nu"] * 0 + 0.5),
                        "no_E": npz_mut("field.npz", E=None), "material_id_bad": npz_mut("field.npz", material=lambda a: a["material"] + 99)}.items():
        add(f"bake.material_file_{name}", corrupt_npz_kind(name),
            without(without(without(BAK, "--E"), "--nu"), "--density") + ["--material-file", "{d}/f.npz"],
            files={**bf, "f.npz": maker}, outputs=bo, timeout=90)
    BAKA = without(without(without(BAK, "--E"), "--nu"), "--density") + ["--alpha", "0.5", "--features", "{d}/g.npz"]
    for name, maker in {"random": os.urandom(500), "truncated": truncated("grid.npz"), "measurement": "@m.npz",
                        "wrong_dim": npz_mut("grid.npz", features=lambda a: a["features"][:, :8])}.items():
        add(f"bake.features_{name}", corrupt_npz_kind(name), BAKA, files={**bf, "g.npz": maker}, outputs=bo, timeout=90)
    add("bake.alpha_no_auto_nothing", "missing_file", without(without(without(BAK, "--E"), "--nu"), "--density") +
        ["--alpha", "0.5", "--no-auto"], files=bf, outputs=bo)
    manifest_ok = {"format": "unipixie.bake-manifest/1", "defaults": {"solver": "spring_mass", "frames": "1-3"},
                   "jobs": [{"scene": "scene.blend", "object": "Block", "out": "o.blend",
                             "material": {"E": 2e5, "nu": 0.3, "density": 800}}]}
    for name, obj in {"not_json": "{jobs", "array": "[]", "format_unknown": {**manifest_ok, "format": "x/9"},
                      "no_jobs": {**manifest_ok, "jobs": []},
                      "job_not_object": {**manifest_ok, "jobs": [1]},
                      "job_scene_missing": {**manifest_ok, "jobs": [{**manifest_ok["jobs"][0], "scene": "nope.blend"}]},
                      "job_out_is_scene": {**manifest_ok, "jobs": [{**manifest_ok["jobs"][0], "out": "scene.blend"}]},
                      "job_frames_string_numbers": {**manifest_ok, "jobs": [{**manifest_ok["jobs"][0], "frames": [1, "3"]}]},
                      "job_E_string": {**manifest_ok, "jobs": [{**manifest_ok["jobs"][0], "material": {"E": "2e5"}}]},
                      "job_unknown_key": {**manifest_ok, "jobs": [{**manifest_ok["jobs"][0], "solvr": "mpm"}]},
                      "two_jobs_same_out": {**manifest_ok, "jobs": [manifest_ok["jobs"][0], manifest_ok["jobs"][0]]},
                      "deep": "[" * 100000 + "]" * 100000}.items():
        add(f"bake.manifest_{name}", "corrupt_file" if "string" not in name else "wrong_type",
            ["bake", "--manifest", "{d}/jobs.json"], files={**bf, "jobs.json": obj if isinstance(obj, str) else json.dumps(obj)},
            outputs=["o.blend"], timeout=90)
    add("bake.manifest_control", "control", ["bake", "--manifest", "{d}/jobs.json"],
        files={**bf, "jobs.json": json.dumps(manifest_ok)}, expect=OK, outputs=["o.blend"], timeout=120,
        check=output_exists("o.blend"))
    add("bake.manifest_and_scene", "reinterpretation", ["bake", "{d}/scene.blend", "--manifest", "{d}/jobs.json"],
        files={**bf, "jobs.json": json.dumps(manifest_ok)}, outputs=["o.blend"])
    add("bake.full_disk", "full_disk", with_opt(BAK, "--out", "{d}/mnt/out.blend"), files=bf, fs="full",
        outputs=["mnt/out.blend"], timeout=120)
    add("bake.full_disk_keeps_old", "full_disk", with_opt(BAK, "--out", "{d}/mnt/out.blend"),
        files={**bf, "mnt/out.blend": b"BLENDER-old-bake"}, fs="full", outputs=["mnt/out.blend"], timeout=120)
    add("bake.read_only", "read_only", with_opt(BAK, "--out", "{d}/mnt/out.blend"), files=bf, fs="ro",
        outputs=["mnt/out.blend"], timeout=120)
    add("bake.read_only_cache", "read_only", ["--cache-dir", "{d}/mnt/cache", *without(without(without(BAK, "--E"), "--nu"), "--density"),
                                              "--alpha", "0.5"], files={**bf, "mnt/cache/x": "x"}, fs="ro", outputs=bo,
        timeout=120, expect=OKBAD, note="the auto pipeline's cache is read-only: refused, or done without caching")
    add("bake.ctrl_c", "ctrl_c", with_opt(BAK, "--frames", "1-2000"), files=bf, expect=CANCEL, interrupt=True, outputs=bo,
        timeout=120)
    add("bake.ctrl_c_twice", "ctrl_c", with_opt(BAK, "--frames", "1-2000"), files=bf, expect=CANCEL, interrupt=True,
        interrupt_twice=True, outputs=bo, timeout=120)
    add("bake.concurrent_same_out", "concurrent", BAK, files=bf, concurrent=2, expect=OKBAD, outputs=bo, timeout=150)

    # ---------------------------------------------------------------- features
    FEA = ["features", "{d}/cube.obj", "--out", "{d}/g.npz", "--offline-features", "--engine", "workbench", "--views",
           "2", "--resolution", "64", "--no-cache"]
    ff = {"cube.obj": "@cube.obj"}
    fo = ["g.npz"]
    for name, text in {"empty": "", "garbage": "this is not a mesh\n\x00\x01", "points_only": "v 0 0 0\nv 1 0 0\n",
                       "degenerate": "v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n",
                       "nan_vertex": OBJ_CUBE.replace("v 0 0 0", "v nan 0 0"),
                       "inf_vertex": OBJ_CUBE.replace("v 1 1 1", "v inf 1 1"),
                       "face_index_bad": OBJ_CUBE + "f 1 2 99\n",
                       "huge_coordinates": OBJ_CUBE.replace("v 1 1 1", "v 1e30 1 1")}.items():
        add(f"features.obj_{name}", "corrupt_file", FEA, files={"cube.obj": text}, outputs=fo, timeout=90)
    for ext, data in {"ply": b"ply\nformat ascii 1.0\nelement vertex 9999\nend_header\n1 2 3\n", "stl": b"solid x\nfacet",
                      "glb": b"glTF\x02\x00\x00\x00" + b"\0" * 20, "xyz": b"1 2 3\n"}.items():
        add(f"features.{ext}_corrupt", "corrupt_file", ["features", f"{{d}}/x.{ext}", *FEA[2:]],
            files={f"x.{ext}": data}, outputs=fo, timeout=90)
    add("features.missing", "missing_file", ["features", "{d}/nope.obj", *FEA[2:]], outputs=fo)
    add("features.blend_no_object", "impossible_value", ["features", "{d}/scene.blend", *FEA[2:], "--object", "Nope"],
        files=bf, outputs=fo, timeout=90)
    for opt, vals in {"--views": ["0", "-1", "abc"], "--resolution": ["0", "-64", "1"], "--samples": ["0", "-1"],
                      "--device": ["tpu"], "--render-device": ["nope"]}.items():
        bad_values("features", "impossible_value", FEA, opt, vals, ff, fo, timeout=90)
    add("features.clip_weights_missing", "missing_file", without(FEA, "--offline-features", False) +
        ["--clip-weights", "{d}/nope.bin"], files=ff, outputs=fo, timeout=90)
    add("features.clip_weights_corrupt", "corrupt_file", without(FEA, "--offline-features", False) +
        ["--clip-weights", "{d}/w.bin"], files={**ff, "w.bin": os.urandom(4096)}, outputs=fo, timeout=90)
    add("features.out_is_input", "symlinked_output", with_opt(FEA, "--out", "{d}/cube.obj"), files=ff)
    add("features.sheet_is_input", "symlinked_output", FEA + ["--sheet", "{d}/cube.obj"], files=ff, outputs=fo)
    add("features.sheet_same_as_out", "bad_output", FEA + ["--sheet", "{d}/g.npz"], files=ff, outputs=fo)
    add("features.out_is_dir", "bad_output", FEA, files={**ff, "g.npz": folder}, outputs=[])
    add("features.read_only", "read_only", with_opt(FEA, "--out", "{d}/mnt/g.npz"), files=ff, fs="ro",
        outputs=["mnt/g.npz"], timeout=90)
    add("features.full_disk", "full_disk", with_opt(FEA, "--out", "{d}/mnt/g.npz"), files=ff, fs="full",
        outputs=["mnt/g.npz"], timeout=120)
    add("features.ctrl_c", "ctrl_c", with_opt(with_opt(FEA, "--views", "24"), "--resolution", "224"), files=ff,
        expect=CANCEL, interrupt=True, outputs=fo, timeout=120)

    # ---------------------------------------------------------------- dataset
    add("dataset.build_count_zero", "impossible_value", ["dataset", "build", "{d}/ds", "--count", "0"], outputs=["ds"])
    for opt, vals in {"--count": ["-1", "abc"], "--shard": ["2/2", "0/0", "x"], "--split": ["0.5,0.5,0.5", "1,0", "a,b,c", "-0.2,0.6,0.6"],
                      "--resolution": ["0", "3", "-64"], "--views": ["0", "-2"], "--classes": ["nope", ""],
                      "--frames": ["0", "-1"], "--fps": ["0", "nan"], "--cells-across": ["0", "-3"],
                      "--tracked-points": ["-1"], "--spring-anchors": ["0"], "--lbs-cubature": ["0"],
                      "--fit-evaluations": ["0"], "--device": ["tpu"], "--render-resolution": ["0"]}.items():
        bad_values("dataset.build", "impossible_value", ["dataset", "build", "{d}/ds", "--count", "2", "--tiny-ground-truth"],
                   opt, vals, {}, ["ds"], timeout=90)
    add("dataset.build_out_is_file", "bad_output", ["dataset", "build", "{d}/ds", "--count", "1"], files={"ds": "x"})
    add("dataset.build_corrupt_build_json", "corrupt_file", ["dataset", "build", "{d}/ds", "--count", "1", "--tiny-ground-truth"],
        files={"ds/build.json": "{broken"}, outputs=["ds"])
    add("dataset.build_other_options", "contradictory_measurement",
        ["dataset", "build", "{d}/ds", "--count", "1", "--tiny-ground-truth", "--resolution", "16"],
        files={"ds/build.json": json.dumps({"format": "unipixie.dataset-build/1", "count": 1, "resolution": 32})},
        outputs=["ds"], note="resuming with other options than build.json records")
    add("dataset.build_read_only", "read_only", ["dataset", "build", "{d}/mnt/ds", "--count", "1", "--tiny-ground-truth",
                                                 "--resolution", "16", "--views", "2", "--render-resolution", "64"],
        fs="ro", outputs=["mnt/ds"], timeout=90)
    add("dataset.build_ctrl_c", "ctrl_c", ["dataset", "build", "{d}/ds", "--count", "3", "--tiny-ground-truth",
                                           "--resolution", "16", "--views", "2", "--render-resolution", "64"],
        expect=CANCEL, interrupt=True, outputs=[], timeout=120,
        note="finished objects may stay (resumable); no partial file under a final name")
    add("dataset.card_missing", "missing_file", ["dataset", "card", "{d}/nope"])
    add("dataset.card_empty", "corrupt_file", ["dataset", "card", "{d}/ds"], files={"ds": folder}, outputs=["ds"])
    add("dataset.card_is_file", "bad_output", ["dataset", "card", "{d}/ds"], files={"ds": "x"})
    add("dataset.card_corrupt_split", "corrupt_file", ["dataset", "card", "{d}/ds"],
        files={"ds/split.json": "[", "ds/samples/a.npz": os.urandom(100)}, outputs=["ds/CARD.md", "ds/dataset.json"])
    add("dataset.pack_missing", "missing_file", ["dataset", "pack", "{d}/nope", "{d}/pk"], outputs=["pk"])
    add("dataset.pack_empty", "corrupt_file", ["dataset", "pack", "{d}/ds", "{d}/pk"], files={"ds": folder}, outputs=["pk"])
    add("dataset.pack_into_itself", "symlinked_output", ["dataset", "pack", "{d}/ds", "{d}/ds"],
        files={"ds/split.json": json.dumps({"train": ["a"]}), "ds/samples/a.npz": "@grid.npz"})
    add("dataset.pack_part_mb_zero", "impossible_value", ["dataset", "pack", "{d}/ds", "{d}/pk", "--part-mb", "0"],
        files={"ds/split.json": json.dumps({"train": ["a"]}), "ds/samples/a.npz": "@grid.npz"}, outputs=["pk"])
    add("dataset.pack_part_mb_negative", "impossible_value", ["dataset", "pack", "{d}/ds", "{d}/pk", "--part-mb", "-5"],
        files={"ds/split.json": json.dumps({"train": ["a"]}), "ds/samples/a.npz": "@grid.npz"}, outputs=["pk"])
    add("dataset.unpack_missing", "missing_file", ["dataset", "unpack", "{d}/nope", "{d}/out"], outputs=["out"])
    add("dataset.unpack_corrupt_index", "corrupt_file", ["dataset", "unpack", "{d}/pk", "{d}/out"],
        files={"pk/index.json": "{"}, outputs=["out"])
    add("dataset.unpack_index_array", "corrupt_file", ["dataset", "unpack", "{d}/pk", "{d}/out"],
        files={"pk/index.json": "[]"}, outputs=["out"])
    add("dataset.unpack_path_traversal", "malicious_file", ["dataset", "unpack", "{d}/pk", "{d}/out"],
        files={"pk/index.json": json.dumps({"format": "unipixie.dataset-pack/1", "parts": ["../../evil.bin"],
                                            "samples": [{"name": "../../../evil", "part": 0, "offset": 0, "size": 10}]}),
               "evil.bin": b"0123456789"}, outputs=["out"])
    add("dataset.unpack_into_pack", "symlinked_output", ["dataset", "unpack", "{d}/pk", "{d}/pk"],
        files={"pk/index.json": "{}"})

    # ---------------------------------------------------------------- train / evaluate
    TR = ["train", "--data", "{d}/data", "--out", "{d}/run", "--steps", "1", "--preset", "tiny", "--device", "cpu"]
    tf = {"data/a.npz": "@grid.npz"}
    for opt, vals in {"--steps": ["0", "-1"], "--batch": ["0", "-2"], "--lr": ["-1", "nan", "0"], "--preset": ["nope"],
                      "--set": ["width=abc", "nope=1", "width", "width=-8"], "--save-every": ["0"], "--warmup": ["-1"],
                      "--device": ["tpu"], "--workers": ["-1"], "--grad-clip": ["nan", "-1"], "--stop-after": ["0"],
                      "--log-every": ["0"]}.items():
        bad_values("train", "impossible_value", TR, opt, vals, tf, ["run"], timeout=90)
    add("train.data_missing", "missing_file", with_opt(TR, "--data", "{d}/nope"), outputs=["run"])
    add("train.data_empty", "corrupt_file", TR, files={"data": folder}, outputs=["run"])
    add("train.data_corrupt_npz", "corrupt_file", TR, files={"data/a.npz": os.urandom(300)}, outputs=["run"], timeout=90)
    add("train.data_not_samples", "corrupt_file", TR, files={"data/a.npz": "@m.npz"}, outputs=["run"], timeout=90)
    add("train.out_is_file", "bad_output", TR, files={**tf, "run": "x"})
    add("train.resume_nothing", "missing_file", TR + ["--resume"], files=tf, outputs=["run"], timeout=90)
    add("train.resume_corrupt", "corrupt_file", TR + ["--resume"], files={**tf, "run/config.json": "{", "run/state.pt": os.urandom(100)},
        outputs=[], timeout=90)
    add("train.out_is_data", "symlinked_output", with_opt(TR, "--out", "{d}/data"), files=tf, timeout=90)
    EV = ["evaluate", "{d}/ck", "--data", "{d}/data", "--out", "{d}/ev", "--simulate-objects", "0", "--render-frames", "0",
          "--no-oracle"]
    ef = {"ck": checkpoint_dir(), "data/split.json": json.dumps({"test": ["a"]}), "data/samples/a.npz": "@grid.npz"}
    add("evaluate.checkpoint_missing", "missing_file", ["evaluate", "{d}/nope", *EV[2:]], files=ef,
        outputs=["ev"])
    add("evaluate.data_missing", "missing_file", with_opt(EV, "--data", "{d}/nope"), files=ef, outputs=["ev"], timeout=90)
    add("evaluate.data_empty", "corrupt_file", with_opt(EV, "--data", "{d}/empty"), files={**ef, "empty": folder},
        outputs=["ev"], timeout=90)
    add("evaluate.data_sample_corrupt", "corrupt_file", EV, files={**ef, "data/samples/a.npz": os.urandom(200)},
        outputs=["ev"], timeout=90)
    for opt, vals in {"--alphas": ["2", "a", ""], "--max-objects": ["-1", "0"], "--split": ["nope"],
                      "--oracle-draws": ["5", "-1"], "--simulate-objects": ["-1"], "--render-frames": ["-1"],
                      "--render-views": ["0"], "--render-resolution": ["0"], "--device": ["tpu"], "--seed": ["x"]}.items():
        bad_values("evaluate", "impossible_value", EV, opt, vals, ef, ["ev"], timeout=90)
    add("evaluate.out_is_file", "bad_output", EV, files={**ef, "ev": "x"}, timeout=90)
    add("evaluate.baseline_missing", "missing_file", EV + ["--baseline", "{d}/nope"], files=ef, outputs=["ev"], timeout=90)

    # ---------------------------------------------------------------- weights, doctor, build-extension, global
    add("weights.status_control", "control", ["weights", "status"], expect=OK)
    add("weights.status_checkpoint_missing", "missing_file", ["weights", "status", "--checkpoint", "{d}/nope"])
    add("weights.status_checkpoint_corrupt", "corrupt_file", ["weights", "status", "--checkpoint", "{d}/ck"],
        files={"ck": checkpoint_dir(config="{", recipe=False)})
    add("weights.status_recipe_corrupt", "corrupt_file", ["weights", "status", "--checkpoint", "{d}/ck"],
        files={"ck": checkpoint_dir(), "ck/feature_recipe.json": "[1"})
    add("weights.fetch_model_unknown", "impossible_value", ["weights", "fetch", "--model", "ViT-Nope-1", "--folder", "{d}/w"],
        outputs=["w"], timeout=120)
    add("weights.fetch_offline", "environment", ["weights", "fetch", "--folder", "{d}/w"], outputs=["w"], timeout=120,
        env={"HF_ENDPOINT": "http://127.0.0.1:9", "HF_HUB_ETAG_TIMEOUT": "5", "HF_HUB_DOWNLOAD_TIMEOUT": "5"},
        note="no network: one line, no hang")
    add("weights.fetch_folder_is_file", "bad_output", ["weights", "fetch", "--folder", "{d}/w"], files={"w": "x"}, timeout=120,
        env={"HF_ENDPOINT": "http://127.0.0.1:9"})
    add("weights.fetch_read_only", "read_only", ["weights", "fetch", "--folder", "{d}/mnt/w"], fs="ro", outputs=["mnt/w"],
        timeout=120, env={"HF_ENDPOINT": "http://127.0.0.1:9"})
    add("doctor.blender_missing", "missing_file", ["doctor", "--skip-extension", "--blender", "{d}/nope"], timeout=120)
    add("doctor.blender_not_executable", "corrupt_file", ["doctor", "--skip-extension", "--blender", "{d}/b"],
        files={"b": "not a program"}, timeout=120)
    add("doctor.blender_false", "corrupt_file", ["doctor", "--skip-extension", "--blender", "/bin/false"], timeout=120)
    add("build-extension.out_dir_is_file", "bad_output", ["build-extension", "--out-dir", "{d}/dist", "--no-validate"],
        files={"dist": "x"}, timeout=120)
    add("build-extension.read_only", "read_only", ["build-extension", "--out-dir", "{d}/mnt/dist", "--no-validate"],
        fs="ro", outputs=["mnt/dist"], timeout=120)
    add("cli.unknown_command", "impossible_value", ["frobnicate"])
    add("cli.unknown_option", "impossible_value", ["measure", "show", "--frob", "x"])
    add("cli.no_command", "control", [], expect=OK)
    add("cli.cache_dir_is_file", "bad_output", ["--cache-dir", "{d}/c", "predict", "{d}/grid.npz", "--steps", "1", "--out", "{d}/pred"],
        files={"c": "x", **pf}, expect=OKBAD, outputs=po)

    # ---------------------------------------------------------------- bench (always --out into the case folder)
    def bench(name, *opts, **kw):
        return ["bench", name, "--out", "{d}/b.json", "--device", "cpu", *opts]
    for name, opt, vals in (("mpm", "--sizes", ["0", "abc", "-5"]), ("mpm", "--runs", ["0", "-1"]), ("mpm", "--substeps", ["0"]),
                            ("mpm", "--variants", ["nope"]), ("lbs", "--cubature", ["0", "-1"]), ("lbs", "--steps", ["0"]),
                            ("lbs", "--runs", ["0"]), ("spring", "--anchors", ["0", "-1"]), ("spring", "--duration", ["0", "-1", "nan"]),
                            ("spring", "--runs", ["0"]), ("bake", "--frames", ["0", "-1"]), ("bake", "--subdivisions", ["-1", "20"]),
                            ("bake", "--solvers", ["nope"]), ("bake", "--mpm-cells", ["0"]), ("diagnose", "--effect", ["nope"]),
                            ("diagnose", "--runs", ["0"]), ("diagnose", "--setting", ["anchors=0"]),
                            ("features", "--views", ["0"]), ("features", "--resolution", ["0"]), ("features", "--runs", ["0"]),
                            ("model", "--preset", ["nope"]), ("model", "--voxels", ["0", "-1"]), ("model", "--cases", ["nope"]),
                            ("fidelity", "--scenes", ["nope"]), ("fidelity", "--solvers", ["nope"])):
        for v in vals:
            argv = bench(name, opt, v)
            if name == "model":
                argv = without(argv, "--device") + ["--device", "cpu"]
            add(f"bench.{name}.{opt.lstrip('-')}={slug(v)}", "impossible_value", argv, outputs=["b.json"], timeout=90)
    add("bench.features.views_from_corrupt", "corrupt_file", bench("features", "--views-from", "{d}/v.npz"),
        files={"v.npz": os.urandom(300)}, outputs=["b.json"], timeout=90)
    add("bench.fidelity.referee_corrupt", "corrupt_file", bench("fidelity", "--referee", "{d}/r.json", "--scenes", "drop"),
        files={"r.json": "{"}, outputs=["b.json"], timeout=90)
    add("bench.spring.out_is_dir", "bad_output", bench("spring"), files={"b.json": folder}, timeout=90)
    add("bench.spring.out_read_only", "read_only", with_opt(bench("spring"), "--out", "{d}/mnt/b.json"), fs="ro",
        outputs=["mnt/b.json"], timeout=90)
    add("bench.spring.ctrl_c", "ctrl_c", bench("spring", "--runs", "50"), expect=CANCEL, interrupt=True, outputs=["b.json"],
        timeout=120)

    # ---------------------------------------------------------------- demo
    add("demo.checkpoint_missing", "missing_file", ["demo", "--quick", "--out", "{d}/demo", "--checkpoint", "{d}/nope"],
        outputs=["demo"], timeout=120)
    add("demo.checkpoint_corrupt", "corrupt_file", ["demo", "--quick", "--out", "{d}/demo", "--checkpoint", "{d}/ck"],
        files={"ck": checkpoint_dir(config="{")}, outputs=["demo"], timeout=120)
    add("demo.device_unknown", "impossible_value", ["demo", "--quick", "--out", "{d}/demo", "--device", "tpu"],
        outputs=["demo"], timeout=120)
    add("demo.out_is_file", "bad_output", ["demo", "--quick", "--out", "{d}/demo"], files={"demo": "x"}, timeout=120)
    add("demo.diagnose_out_is_file", "bad_output", ["demo", "--diagnose", "--out", "{d}/demo"], files={"demo": "x"},
        timeout=120)
    add("demo.diagnose_read_only", "read_only", ["demo", "--diagnose", "--out", "{d}/mnt/demo"], fs="ro",
        outputs=["mnt/demo"], timeout=120)
    add("demo.diagnose_ctrl_c", "ctrl_c", ["demo", "--diagnose", "--out", "{d}/demo"], expect=CANCEL, interrupt=True,
        outputs=["demo"], timeout=120)
    add("demo.quick_ctrl_c", "ctrl_c", ["demo", "--quick", "--out", "{d}/demo"], expect=CANCEL, interrupt=True,
        outputs=["demo"], timeout=150)

    ids = [c.id for c in cases]
    dup = {i for i in ids if ids.count(i) > 1}
    assert not dup, f"duplicate case ids: {sorted(dup)}"
    return cases


def corrupt_npz_kind(name: str) -> str:
    if name in ("pickle", "bomb", "fifo", "deep_json", "dev_zero"):
        return "malicious_file"
    if any(s in name for s in ("string", "text", "float", "complex")):
        return "wrong_type"
    if name in ("times_decreasing", "times_repeated", "all_nan", "one_instant", "zero_points", "positions_inf",
                "material_E_negative", "material_nu_half", "material_density_zero", "E_nan", "E_negative", "nu_half"):
        return "impossible_value"
    return "corrupt_file"
