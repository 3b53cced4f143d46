"""Fault injection, outputs that are inputs and outputs written twice: an output linked (symbolic or hard link) to
an input is refused, writing through a link keeps the link; a second writer of the same output, report folder,
benchmark file or feature grid waits or is refused."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from unipixie.core import atomic_io, cli
from unipixie.core.errors import EXIT_BAD_INPUT, UserError

from fault_helpers import _leftovers, _falling_cube


# --------------------------------------------------------------------------- links
def test_symlinked_and_hard_linked_output_to_the_input_is_refused(tmp_path):
    inp = tmp_path / "scene.blend"
    inp.write_bytes(b"precious")
    link = tmp_path / "out.blend"
    link.symlink_to(inp)
    with pytest.raises(UserError, match="symbolic link"):
        atomic_io.refuse_overwriting_inputs(link, [inp])
    hard = tmp_path / "hard.blend"
    os.link(inp, hard)
    with pytest.raises(UserError, match="hard link"):
        atomic_io.refuse_overwriting_inputs(hard, [inp])
    atomic_io.refuse_overwriting_inputs(tmp_path / "other.blend", [inp])  # a different file is fine

    from unipixie.core.bake import BakeJob, check_job_outputs

    for out in (link, hard, inp):
        with pytest.raises(UserError, match="would overwrite its input scene"):
            check_job_outputs([BakeJob(scene=str(inp), object="Cube", out=str(out))])
    assert inp.read_bytes() == b"precious"


def test_measure_convert_onto_its_own_input_through_a_link_is_refused(tmp_path, capsys):
    m = _falling_cube()
    src = tmp_path / "m.npz"
    m.save(src)
    before = src.read_bytes()
    link = tmp_path / "link.npz"
    link.symlink_to(src)
    status = cli.main(["measure", "convert", str(src), str(link), "--force"])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and "would overwrite the input" in err
    assert src.read_bytes() == before


def test_writing_through_a_symlink_replaces_the_target_and_keeps_the_link(tmp_path):
    real = tmp_path / "real.json"
    real.write_text("{}")
    link = tmp_path / "link.json"
    link.symlink_to(real)
    atomic_io.write_json(link, {"a": 1})
    assert link.is_symlink() and json.loads(real.read_text()) == {"a": 1}


def test_predict_refuses_a_negative_seed_and_an_output_linked_to_its_grid(tmp_path, capsys):
    grid = tmp_path / "grid.npz"
    grid.write_bytes(b"not looked at: the refusals come first")
    with pytest.raises(SystemExit) as info:  # an argument error: argparse's one line, status 2
        cli.main(["predict", str(grid), "--seed", "-1", "--out", str(tmp_path / "p")])
    assert info.value.code == EXIT_BAD_INPUT and "--seed" in capsys.readouterr().err  # was exit 0
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "material_field_a0.500.npz").symlink_to(grid)
    assert cli.main(["predict", str(grid), "--out", str(tmp_path / "p")]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "would overwrite the input" in err and "symbolic link" in err
    assert grid.read_bytes() == b"not looked at: the refusals come first"


# --------------------------------------------------------------------------- concurrent writers
def test_a_second_writer_of_the_same_output_is_refused(tmp_path):
    out = tmp_path / "baked.blend"
    with atomic_io.OutputLock(out):
        with pytest.raises(UserError, match=f"process {os.getpid()}"):
            atomic_io.OutputLock(out).acquire()
        code = (f"from unipixie.core import atomic_io\n"
                f"atomic_io.OutputLock({str(out)!r}).acquire()\n")
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert res.returncode != 0 and "being written by another UniPixie run" in res.stderr
    with atomic_io.OutputLock(out):  # released: free again
        pass
    assert _leftovers(tmp_path) == []


def test_a_report_folder_in_use_is_refused(tmp_path):
    from unipixie.core.diagnosis import report

    with atomic_io.OutputLock(tmp_path / report.JSON_NAME, "report"):
        with pytest.raises(UserError, match="being written"):
            report.write_report(object(), tmp_path)


def test_two_benchmarks_recording_into_one_file_take_turns(tmp_path):
    """``record`` merges into benchmarks/<name>.json (read, merge, write): a second recorder waits for the first
    instead of overwriting its results (or being refused after a long benchmark)."""
    from unipixie.core import benchmarks

    path = tmp_path / "b.json"
    entry = lambda case: {"case": case, "device": "cpu", "metric": "m", "value": 1.0, "runs": 1}  # noqa: E731
    benchmarks.record("b", [entry("first")], path)
    holder = atomic_io.OutputLock(path, "benchmark file").acquire()
    done = []
    import threading

    t = threading.Thread(target=lambda: done.append(benchmarks.record("b", [entry("second")], path)))
    t.start()
    time.sleep(0.5)
    assert not done  # waiting for the holder
    holder.release()
    t.join(10)
    assert done and {r["case"] for r in json.loads(path.read_text())["results"]} == {"first", "second"}
    with atomic_io.OutputLock(path, "benchmark file"):
        with pytest.raises(UserError, match="being written by another UniPixie run"):
            atomic_io.OutputLock(path, "benchmark file", wait=0.2).acquire()  # waits, then refuses


def test_each_benchmark_entry_keeps_the_commit_it_was_measured_at(tmp_path, monkeypatch):
    """The file's ``commit`` is its latest write's; an entry recorded earlier keeps its own (a GPU figure is not
    relabelled by a later CPU run), and an entry that names its commit keeps that one."""
    from unipixie.core import benchmarks

    path = tmp_path / "b.json"
    entry = lambda case, **kw: {"case": case, "device": "cpu", "metric": "m", "value": 1.0, "runs": 1, **kw}  # noqa: E731
    monkeypatch.setattr(benchmarks, "git_commit", lambda: "aaaaaaa")
    benchmarks.record("b", [entry("gpu figure")], path)
    monkeypatch.setattr(benchmarks, "git_commit", lambda: "bbbbbbb")
    benchmarks.record("b", [entry("cpu figure"), entry("older code", commit="ccccccc")], path)
    doc = json.loads(path.read_text())
    assert doc["commit"] == "bbbbbbb"
    assert {r["case"]: r["commit"] for r in doc["results"]} == {"gpu figure": "aaaaaaa", "cpu figure": "bbbbbbb",
                                                               "older code": "ccccccc"}
    assert all(r["date"] for r in doc["results"])


def test_a_second_features_run_writing_the_same_grid_is_refused(tmp_path, capsys):
    obj = tmp_path / "cube.obj"
    obj.write_text("".join(f"v {x} {y} {z}\n" for x in (0, 1) for y in (0, 1) for z in (0, 1)) + "f 1 2 4 3\n")
    with atomic_io.OutputLock(tmp_path / "g.npz"):  # the first run, still working
        status = cli.main(["features", str(obj), "--out", str(tmp_path / "g.npz"), "--offline-features"])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and "being written by another UniPixie run" in err, err
    assert not (tmp_path / "g.npz").exists()
