"""Fault injection, impossible arguments: values the commands used to reinterpret, ignore or crash on (zero
steps, negative seeds, NaN velocities, absurd frame counts, empty candidate lists, settings that are not
numbers) are refused with exit 2 and a line that names the option; nothing is written."""

from __future__ import annotations

import numpy as np
import pytest

from unipixie.core import cli
from unipixie.core.errors import EXIT_BAD_INPUT, UserError

from fault_helpers import _falling_cube


# --------------------------------------------------------------------------- long jobs
def test_absurd_frame_counts_need_allow_long():
    from unipixie.core.cost import estimate, frames_estimate
    from unipixie.solvers.material_sampling import HomogeneousMaterial

    with pytest.raises(UserError, match="--allow-long"):
        frames_estimate("baking 'Cube' over frames 1-1000000", 1_000_000).check()
    frames_estimate("x", 1_000_000).check(allow_long=True)
    frames_estimate("x", 240).check()
    est = estimate("a stiff bake", "spring_mass", size=1.0, times=np.arange(2400) / 24.0,
                   material_spec=HomogeneousMaterial(1e11, 0.3, 1000.0, "metal"), points=1000)
    assert est.total_substeps > 1e6 and "substeps" in est.describe()
    with pytest.raises(UserError, match="substeps"):
        est.check()


# --------------------------------------------------------------------------- quiet reinterpretations
@pytest.mark.parametrize("argv, needle", [
    (["measure", "synth", "--out", "{tmp}/m.npz", "--points", "0"], "--points"),
    (["measure", "synth", "--out", "{tmp}/m.npz", "--duration", "0"], "--duration"),
])
def test_impossible_values_are_refused_not_reinterpreted(argv, needle, tmp_path, capsys):
    status = cli.main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and needle in err and "Traceback" not in err
    assert not (tmp_path / "m.npz").exists()


def test_predict_refuses_zero_steps_and_a_file_as_out(tmp_path, capsys):
    grid = tmp_path / "grid.npz"
    grid.write_bytes(b"x")
    with pytest.raises(SystemExit) as info:
        cli.main(["predict", str(grid), "--steps", "0", "--out", str(tmp_path / "o")])
    assert info.value.code == EXIT_BAD_INPUT
    capsys.readouterr()
    status = cli.main(["predict", str(grid), "--out", str(grid)])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and "existing file" in err
    assert grid.read_bytes() == b"x"


# --------------------------------------------------------------------------- found by the fault matrix (tests/fault_matrix)
@pytest.mark.parametrize("argv, needle", [
    (["--seed", "-1"], "--seed"),                      # was an internal error (numpy's ValueError)
    (["--height", "-1"], "--height"),                  # was exit 0: the object started inside the ground
    (["--velocity", "nan,0,0"], "--velocity"),         # was exit 3 "diverged" for a bad argument
    (["--spin", "inf"], "--spin"),
    (["--fps", "1e7"], "--allow-long"),                # 2,000,001 instants: was a silent hang
    (["--duration", "1e6", "--fps", "1000"], "--allow-long"),  # was an internal error (a 312 GB allocation)
    (["--nu", "-1.1"], "Poisson's ratio"),             # the cost estimate must not fail before the material check
])
def test_synth_refuses_what_the_fault_matrix_found(argv, needle, tmp_path, capsys):
    status = cli.main(["measure", "synth", "--out", str(tmp_path / "m.npz"), "--solver", "spring_mass",
                       "--duration", "0.2", "--fps", "20", "--points", "30", *argv])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and needle in err and "internal error" not in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, needle", [
    (["--candidates", ""], "--candidates ''"),          # was exit 0: every effect tried
    (["--candidates", " , "], "no effect named"),
    (["--setting", "anchors=abc"], "'anchors' must be a positive whole number"),  # was an internal error
])
def test_diagnose_refuses_what_it_used_to_reinterpret(argv, needle, tmp_path, capsys):
    _falling_cube().save(tmp_path / "m.npz")
    status = cli.main(["diagnose", str(tmp_path / "m.npz"), "--solver", "spring_mass", "--out", str(tmp_path / "rep"),
                       "--max-additions", "0", "--quiet", *argv])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and needle in err and "internal error" not in err, err
    assert not (tmp_path / "rep" / "diagnosis.json").exists()


def test_the_diagnosis_api_refuses_an_empty_candidate_list():
    from unipixie.core.diagnosis import diagnose

    with pytest.raises(UserError, match="empty"):
        diagnose.diagnose(_falling_cube(), "spring_mass", candidates=[], max_additions=0)


def test_a_solver_setting_that_is_not_a_number_is_named_by_the_cost_estimate():
    from unipixie.core.cost import estimate
    from unipixie.core.types import MaterialField  # noqa: F401 - the estimate reads E, nu, density

    spec = type("M", (), {"E": 2e5, "nu": 0.3, "density": 1000.0})
    with pytest.raises(UserError, match="setting 'anchors' must be a finite number, got 'abc'"):
        estimate("x", "spring_mass", size=0.1, times=np.linspace(0, 1, 5), material_spec=spec, points=8,
                 settings={"anchors": "abc"})  # was ValueError from int('abc')


@pytest.mark.parametrize("argv, needle", [
    (["bench", "lbs", "--steps", "0"], "--steps"),                    # was the default (30 steps), exit 0
    (["bench", "spring", "--duration", "0"], "--duration"),
    (["bench", "mpm", "--substeps", "0"], "--substeps"),              # was minutes of the default
    (["bench", "diagnose", "--runs", "0"], "--runs"),                 # was silently one long run
    (["bench", "bake", "--subdivisions", "20"], "--subdivisions 20"),  # was a hang (terabytes)
    (["doctor", "--skip-extension", "--blender", "/nonexistent/blender"], "--blender"),  # was ignored, exit 0
    (["doctor", "--blender", "/nonexistent/blender"], "does not exist"),
    (["dataset", "build", "{tmp}/ds", "--count", "1", "--fps", "0"], "--fps"),  # was built with fps 0 ignored
    (["dataset", "build", "{tmp}/ds", "--count", "1", "--tracked-points", "-1"], "--tracked-points"),
    (["dataset", "build", "{tmp}/ds", "--count", "1", "--classes", ""], "--classes"),  # was every class
])
def test_commands_refuse_what_the_fault_matrix_found(argv, needle, tmp_path, capsys):
    from unipixie import cli as root_cli

    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv] + (["--out", str(tmp_path / "b.json")]
                                                               if argv[0] == "bench" else [])
    try:
        status = root_cli.main(argv)
    except SystemExit as exc:  # argparse's one-line refusal
        status = exc.code
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and needle in err and "internal error" not in err, err
    assert not (tmp_path / "b.json").exists() and not (tmp_path / "ds").exists()


@pytest.mark.parametrize("value", ["-1", "nan", "soon"])
def test_a_resolution_budget_that_is_no_duration_is_refused(value, tmp_path, capsys):
    """``--resolution-budget`` takes seconds, 0 or more (inf: no limit); anything else is refused in one line before
    any work, and the Python API refuses it too."""
    from unipixie import cli as root_cli
    from unipixie.core.diagnosis import diagnose

    _falling_cube().save(tmp_path / "m.npz")
    try:
        status = root_cli.main(["diagnose", str(tmp_path / "m.npz"), "--out", str(tmp_path / "rep"),
                                "--resolution-budget", value])
    except SystemExit as exc:
        status = exc.code
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and "--resolution-budget" in err and "seconds, 0 or more" in err, err
    assert not (tmp_path / "rep").exists()
    if value != "soon":
        from unipixie.core.measurement import load

        with pytest.raises(UserError, match="resolution_budget_s must be 0 or more seconds"):
            diagnose.diagnose(load(tmp_path / "m.npz"), "spring_mass", resolution_budget_s=float(value))
    else:
        with pytest.raises(UserError, match="resolution_budget_s must be 0 or more seconds"):
            diagnose.diagnose(_falling_cube(), "spring_mass", resolution_budget_s=value)


@pytest.mark.parametrize("argv", [
    ["diagnose", "m.npz", "--out", ""],                   # wrote the report into the current folder, said "/diagnosis.json"
    ["diagnose", "m.npz", "--out="],
    ["measure", "show", " "],
    ["predict", "grid.npz", "--out", "  "],
])
def test_an_empty_value_on_the_command_line_is_refused_before_any_work(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _falling_cube().save(tmp_path / "m.npz")
    status = cli.main(argv)
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and "is empty" in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz"]


@pytest.mark.parametrize("E, density, words", [(2e5, 1e9, "denser than any solid"),
                                               (1e15, 1000.0, "stiffer than any solid")])
def test_a_material_no_solid_has_is_refused_by_every_solver_path(E, density, words, tmp_path, capsys):
    """`bake --density 1e9` baked and said "saved" (exit 0); the same rule refuses it in a measurement."""
    from unipixie.solvers.material_sampling import HomogeneousMaterial

    with pytest.raises(UserError, match=words):
        HomogeneousMaterial(E, 0.3, density)
    HomogeneousMaterial(1.2e12, 0.1, 22590.0)  # diamond's E, osmium's density: the stiffest and densest solids
    status = cli.main(["measure", "synth", "--out", str(tmp_path / "m.npz"), "--solver", "spring_mass",
                       "--duration", "0.2", "--fps", "20", "--points", "30", "--E", str(E), "--density", str(density)])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and words in err and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []
