"""Fault injection: full disks, read-only outputs, links to inputs, corrupt and malicious files, Ctrl-C,
concurrent writers and contradictory measurements.  Every case must end in one clear error (or a
refusal with the remedy), never a traceback, a damaged input, a partial file under a final name or a
false verdict.  All fast (no simulation runs)."""

from __future__ import annotations

import errno
import importlib.util
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from unipixie.core import atomic_io, cli
from unipixie.core.errors import (EXIT_BAD_INPUT, EXIT_CANCELLED, EXIT_INTERNAL_ERROR, EXIT_SIMULATION_FAILED,
                                  SimulationDiverged, UserError, read_json)
from unipixie.core.measurement import Measurement, MeasuredMaterial, load, load_csv
from unipixie.solvers.scenario import Scenario

REPO_ROOT = Path(__file__).resolve().parents[1]


def _leftovers(folder: Path) -> list[str]:
    """Temporary or lock files an interrupted write left behind."""
    return [p.name for p in folder.iterdir() if atomic_io.is_temporary(p.name) or ".tmp" in p.name]


# --------------------------------------------------------------------------- a small measurement
CUBE = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (0.05, 0.15)], dtype=np.float64)
CUBE_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def _falling_cube(frames: int = 20, fps: float = 50.0, **scenario) -> Measurement:
    """A cube falling freely for ``frames`` instants (z up, metres), the jelly material stated."""
    t = np.arange(frames) / fps
    pos = CUBE[None] + np.array([0.0, 0.0, 1.0])[None, None] * (-0.5 * 9.81 * t ** 2)[:, None, None]
    pos = pos + np.random.default_rng(0).normal(0.0, 1e-4, pos.shape)
    sc = Scenario(**{"ground_height": -1.0, **scenario})
    return Measurement(positions=pos, times=t, scenario=sc, rest_positions=CUBE.copy(), faces=CUBE_FACES,
                       material=MeasuredMaterial(2e5, 0.3, 1000.0))


# --------------------------------------------------------------------------- full disk (simulated at write time)
def _enospc_after(nbytes: int):
    """A ``numpy.lib.format.write_array`` stand-in that writes ``nbytes`` of an archive member and then fails as a
    full disk does."""

    def fake(fp, array, *args, **kwargs):
        fp.write(b"\x93NUMPY" + b"\0" * nbytes)
        raise OSError(errno.ENOSPC, "No space left on device")

    return fake


def test_full_disk_leaves_no_partial_file_and_keeps_the_old_one(tmp_path, monkeypatch):
    m = _falling_cube()
    target = tmp_path / "m.npz"
    m.save(target)
    before = target.read_bytes()
    monkeypatch.setattr(np.lib.format, "write_array", _enospc_after(1000))
    with pytest.raises(UserError) as info:
        m.save(target)
    msg = str(info.value)
    assert str(target) in msg and "disk is full" in msg
    assert target.read_bytes() == before  # the old file is untouched
    assert _leftovers(tmp_path) == []
    fresh = tmp_path / "new.npz"
    with pytest.raises(UserError):
        m.save(fresh)
    assert not fresh.exists()  # nothing under the final name


def test_full_disk_while_writing_a_material_field(tmp_path, monkeypatch):
    from unipixie.core.types import GridGeometry, MaterialField

    occ = np.zeros((4, 4, 4), bool)
    occ[1:3, 1:3, 1:3] = True
    geo = GridGeometry(resolution=4, origin=[0, 0, 0], voxel_size=0.25)
    f = MaterialField.homogeneous(geo, occ, 1e5, 0.3, 1000.0)
    monkeypatch.setattr(np.lib.format, "write_array", _enospc_after(50))
    with pytest.raises(UserError, match="disk is full"):
        f.save(tmp_path / "material_field_a0.500.npz")
    assert list(tmp_path.iterdir()) == []


def test_pc2_cut_off_by_a_file_size_limit_is_an_error_not_a_file(tmp_path):
    """A real write failure (the process's file-size limit, EFBIG) in a child process: one line, exit 2."""
    code = textwrap.dedent(f"""
        import resource, signal, sys, numpy as np
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))
        from unipixie.core import cli, bake
        def run(args):
            bake.write_pc2({str(tmp_path / 'cache.pc2')!r}, np.zeros((50, 100, 3), np.float32))
        sys.exit(cli.run_command(run, None, "bake"))
    """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == EXIT_BAD_INPUT, res.stderr
    assert "Traceback" not in res.stderr
    assert "cache.pc2" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "cache.pc2").exists()
    assert _leftovers(tmp_path) == []


def test_a_truncated_write_is_caught_by_the_check(tmp_path):
    with pytest.raises(UserError, match="cut off"):
        with atomic_io.atomic_path(tmp_path / "x.bin", expected_size=100) as tmp:
            tmp.write_bytes(b"x" * 60)
    with pytest.raises(UserError, match="picture is incomplete"):
        with atomic_io.atomic_path(tmp_path / "x.png") as tmp:
            tmp.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)
    with pytest.raises(UserError, match="cut off"):
        with atomic_io.atomic_path(tmp_path / "x.blend") as tmp:
            tmp.write_bytes(b"BLENDER-v500REND" + b"\0" * 500)
    assert list(tmp_path.iterdir()) == []


def test_not_enough_room_is_refused_before_the_work(tmp_path):
    with pytest.raises(UserError, match="not enough free space"):
        atomic_io.check_writable(tmp_path / "big.blend", need_bytes=10 ** 18)


# --------------------------------------------------------------------------- read-only outputs
def test_read_only_file_system_is_found_before_the_work(tmp_path, monkeypatch):
    def erofs(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(atomic_io.tempfile, "mkstemp", erofs)
    with pytest.raises(UserError, match="read-only"):
        atomic_io.check_writable(tmp_path / "out.blend")
    with pytest.raises(UserError, match="read-only"):
        atomic_io.write_text(tmp_path / "a.json", "{}")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_folder(tmp_path):  # pragma: no cover - CI runs as a user
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(UserError, match="permission denied"):
            atomic_io.check_writable(ro / "out.npz")
    finally:
        ro.chmod(0o755)


def test_read_only_existing_output_is_refused(tmp_path):
    p = tmp_path / "out.npz"
    p.write_bytes(b"old")
    p.chmod(0o444)
    if os.access(p, os.W_OK):  # root
        pytest.skip("root may write read-only files")
    with pytest.raises(UserError, match="read-only"):  # pragma: no cover
        atomic_io.check_writable(p)


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


# --------------------------------------------------------------------------- CSV by column name, lossless round trip
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


def test_scenario_numbers_as_text_are_refused_in_every_key():
    base = {"format": "unipixie.measurement/1"}
    for key, value in (("gravity", ["0", "0", "-9.81"]), ("ground", {"height": "0"}),
                       ("initial_velocity", [0, "1", 0]), ("pinned_box", [[0, 0, 0], ["1", 1, 1]])):
        with pytest.raises(UserError, match=key):
            Scenario.from_dict({**base, key: value})


# --------------------------------------------------------------------------- no confident nonsense
@pytest.mark.parametrize("case", ["ground_above", "all_pinned", "times_1e9", "sentinels", "milliseconds"])
def test_contradictory_measurements_are_refused_before_fitting(case):
    from unipixie.core.diagnosis import sanity

    m = _falling_cube()
    if case == "ground_above":
        m = _falling_cube(ground_height=10.0)
    elif case == "all_pinned":
        m = _falling_cube(pinned_box=[[-1, -1, -1], [1, 1, 1]])
    elif case == "times_1e9":
        m = Measurement(positions=m.positions * 1e9, times=m.times, scenario=m.scenario, rest_positions=m.rest * 1e9,
                        faces=m.faces, material=m.material)
    elif case == "sentinels":
        m.positions[5:7, :3] = -999999999.0
    elif case == "milliseconds":
        m = Measurement(positions=m.positions, times=m.times * 1000.0, scenario=m.scenario, rest_positions=m.rest,
                        faces=m.faces, material=m.material)
    with pytest.raises(UserError) as info:
        sanity.check(m, "spring_mass")
    assert len(str(info.value).splitlines()) == 1
    sanity.check(_falling_cube(), "spring_mass")  # the honest measurement passes


def test_milliseconds_can_be_forced_with_allow_long():
    from unipixie.core.diagnosis import sanity

    m = _falling_cube(frames=40, fps=1.0)  # 39 "seconds" of a solid at rest: the times were frame numbers
    still = np.repeat(m.rest[None], 40, axis=0)
    m2 = Measurement(positions=still, times=m.times, scenario=Scenario(ground_height=None, gravity=[0, 0, 0]),
                     rest_positions=m.rest, faces=m.faces, material=m.material)
    with pytest.raises(UserError, match="milliseconds"):
        sanity.check(m2, "lbs")
    warnings = sanity.check(m2, "lbs", allow_long=True)
    assert any("milliseconds" in w for w in warnings)


def test_a_model_far_above_the_noise_never_explains_the_measurement():
    from unipixie.core.diagnosis import verdict

    far = verdict.decide(0.122, 0.0024, None)
    assert far["code"] == "not_explained" and not far["explained"]
    assert "the model explains" not in far["sentence"] and "does NOT explain" in far["sentence"]
    partly = verdict.decide(0.05, 0.002, "linear_drag", added=["linear_drag"])
    assert partly["code"] == "effect_found_partly" and "does not explain" in partly["sentence"]
    near = verdict.decide(0.003, 0.002, None)
    assert near["code"] == "explained" and "explains these measurements" in near["sentence"]
    assert verdict.decide(float("nan"), 0.002, None)["code"] == "not_explained"


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


# --------------------------------------------------------------------------- exit codes, crash log, Ctrl-C
def test_exit_codes_follow_one_table(capsys):
    def raiser(exc):
        def fn(args):
            raise exc
        return fn

    assert cli.run_command(raiser(UserError("bad")), None, "x") == EXIT_BAD_INPUT
    assert cli.run_command(raiser(SimulationDiverged("blew up")), None, "x") == EXIT_SIMULATION_FAILED
    assert cli.run_command(raiser(KeyboardInterrupt()), None, "x") == EXIT_CANCELLED
    assert cli.run_command(raiser(OSError(errno.ENOSPC, "No space left on device", "/x/y")), None, "x") == EXIT_BAD_INPUT
    os.environ.pop("UNIPIXIE_TRACEBACK", None)
    assert cli.run_command(raiser(ZeroDivisionError("bug")), None, "x") == EXIT_INTERNAL_ERROR
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" in err
    log = Path(err.strip().splitlines()[-1].split("the details are in ")[-1])
    assert log.is_file() and "ZeroDivisionError" in log.read_text()


def test_ctrl_c_cancels_cleanly_with_status_130(tmp_path):
    target = tmp_path / "out.bin"
    code = textwrap.dedent(f"""
        import signal, sys, time
        # as in a terminal: a shell without job control starts background jobs (a CI runner's) with SIGINT ignored
        signal.signal(signal.SIGINT, signal.default_int_handler)
        from unipixie.core import atomic_io, cli
        def run(args):
            with atomic_io.atomic_path({str(target)!r}, min_size=0) as tmp:
                tmp.write_bytes(b"partial")
                print("ready", flush=True)
                time.sleep(30)
        sys.exit(cli.run_command(run, None, "bake"))
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == EXIT_CANCELLED, err
    assert "cancelled" in err and "Traceback" not in err
    assert not target.exists() and _leftovers(tmp_path) == []


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


def test_blend_save_on_a_full_disk_leaves_the_old_file(tmp_path):
    """Blender's own save cut off by the file-size limit (a full disk as Blender sees it): the bake's writer
    reports it and keeps the previous output; nothing partial under the final name."""
    pytest.importorskip("bpy")
    out = tmp_path / "baked.blend"
    out.write_bytes(b"the previous bake")
    code = textwrap.dedent(f"""
        import resource, signal, sys
        import bpy
        from unipixie.core import cli
        from unipixie.core.blender_io.blend_file import save_blend
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.ops.mesh.primitive_uv_sphere_add(segments=256, ring_count=128)
        save_blend({str(tmp_path / 'ok.blend')!r})
        save_blend({str(tmp_path / 'ok.blend')!r})  # over an existing file: no backup left beside it
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))
        sys.exit(cli.run_command(lambda args: save_blend({str(out)!r}), None, "bake"))
    """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONPATH": os.environ.get("PYTHONPATH", "")})
    assert res.returncode == EXIT_BAD_INPUT, res.stderr[-2000:]
    assert "Traceback" not in res.stderr and str(out) in res.stderr
    assert out.read_bytes() == b"the previous bake"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["baked.blend", "ok.blend"]


@pytest.fixture
def full_disk(tmp_path):
    """A real, nearly full 256 KB file system (tmpfs) where the machine allows mounting one (root in a
    container or VM); skipped elsewhere — the simulated-ENOSPC tests above cover the same paths."""
    if os.name != "posix" or os.geteuid() != 0:
        pytest.skip("mounting a small file system needs root")
    mnt = tmp_path / "small"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip("this machine does not allow mounting a tmpfs")
    try:
        (mnt / "fill").write_bytes(b"\0" * (236 * 1024))
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


def test_a_real_full_disk(full_disk, tmp_path):
    m = _falling_cube(frames=200)
    (full_disk / "old.npz").write_bytes(b"old")
    for write in (lambda: m.save(full_disk / "old.npz"), lambda: m.save_csv(full_disk / "m.csv")):
        with pytest.raises(UserError, match="disk is full|cut off"):
            write()
    assert (full_disk / "old.npz").read_bytes() == b"old"
    assert sorted(p.name for p in full_disk.iterdir()) == ["fill", "old.npz"]
    with pytest.raises(UserError, match="not enough free space"):
        atomic_io.check_writable(full_disk / "baked.blend", 1_000_000)
    if importlib.util.find_spec("bpy") is None:
        return
    scene = tmp_path / "scene.blend"
    code = textwrap.dedent(f"""
        import sys
        import bpy
        from unipixie.core import cli
        from unipixie.core.blender_io.blend_file import save_blend
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.ops.mesh.primitive_uv_sphere_add(segments=128, ring_count=64)
        sys.exit(cli.run_command(lambda args: save_blend({str(full_disk / 'old.npz').replace('.npz', '.blend')!r}),
                                 None, "bake"))
    """)
    (full_disk / "old.blend").write_bytes(b"old")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.returncode == EXIT_BAD_INPUT and "old.blend" in res.stderr, res.stderr[-2000:]
    assert (full_disk / "old.blend").read_bytes() == b"old"
    assert sorted(p.name for p in full_disk.iterdir()) == ["fill", "old.blend", "old.npz"]
    del scene


def test_a_second_ctrl_c_while_cleaning_up_only_says_so():
    code = textwrap.dedent("""
        import signal, sys, time
        # as in a terminal: a shell without job control starts background jobs (a CI runner's) with SIGINT ignored
        signal.signal(signal.SIGINT, signal.default_int_handler)
        from unipixie.core import cli
        def run(args):
            try:
                print("ready", flush=True)
                time.sleep(30)
            finally:
                time.sleep(1.5)  # cleaning up
        sys.exit(cli.run_command(run, None, "bake"))
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        proc.send_signal(signal.SIGINT)
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == EXIT_CANCELLED
    assert "cleaning up" in err and err.strip().endswith("unipixie bake: cancelled") and "Traceback" not in err


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


def test_a_csv_with_a_byte_order_mark_reads_as_without(tmp_path):
    m = _falling_cube()
    m.save_csv(tmp_path / "m.csv")
    text = (tmp_path / "m.csv").read_text(encoding="utf-8")
    (tmp_path / "bom.csv").write_text("\ufeff" + text, encoding="utf-8")
    (tmp_path / "bom.json").write_text((tmp_path / "m.json").read_text())
    back = load_csv(tmp_path / "bom.csv")
    np.testing.assert_array_equal(back.positions, m.positions)


# --------------------------------------------------------------------------- no measurement without motion, no silent defaults
def test_a_measurement_needs_two_instants_and_an_observed_sample():
    m = _falling_cube()
    with pytest.raises(UserError, match="at least two"):  # was accepted: `measure show` printed "valid"
        Measurement(positions=m.positions[:1], times=m.times[:1], scenario=m.scenario, rest_positions=m.rest)
    with pytest.raises(UserError, match="no observed sample"):  # was accepted: `measure convert` wrote it
        Measurement(positions=m.positions * np.nan, times=m.times, scenario=m.scenario, rest_positions=m.rest)


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


def test_five_frame_numbers_as_times_are_refused():
    from unipixie.core.diagnosis import sanity

    m = _falling_cube(frames=5)
    frames = Measurement(positions=m.positions, times=np.arange(5.0), scenario=m.scenario, rest_positions=m.rest,
                         faces=m.faces, material=m.material)  # 0..4 "s": was accepted (the rule wanted 10 s or more)
    with pytest.raises(UserError, match="look like frame numbers"):
        sanity.check(frames, "spring_mass")
    sanity.check(m, "spring_mass")


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


def test_gravity_in_millimetres_is_refused_and_an_odd_one_warned():
    from unipixie.core.diagnosis import sanity

    with pytest.raises(UserError, match="mm/s²"):  # was accepted: the model fell a thousand times too fast
        sanity.check(_falling_cube(gravity=[0, 0, -9810.0]), "spring_mass")
    assert any("gravity is 50" in w for w in sanity.check(_falling_cube(gravity=[0, 0, -50.0]), "spring_mass"))
    assert not any("gravity" in w for w in sanity.check(_falling_cube(), "spring_mass"))


def test_measure_show_says_what_a_diagnosis_would_refuse(tmp_path, capsys):
    m = _falling_cube()
    Measurement(positions=m.positions, times=m.times * 1000.0, scenario=m.scenario, rest_positions=m.rest,
                faces=m.faces, material=m.material).save(tmp_path / "ms.npz")
    assert cli.main(["measure", "show", str(tmp_path / "ms.npz")]) == 0
    assert "warning: unipixie diagnose would refuse it" in capsys.readouterr().out  # was silent
    m.save(tmp_path / "ok.npz")
    assert cli.main(["measure", "show", str(tmp_path / "ok.npz")]) == 0
    assert "refuse" not in capsys.readouterr().out


def test_a_csv_without_header_says_how_its_columns_are_read(tmp_path):
    (tmp_path / "n.csv").write_text("0,0,0,0,1\n0.1,0,0,0,0.95\n")
    assert any("no header" in w for w in load_csv(tmp_path / "n.csv").warnings)
    (tmp_path / "h.csv").write_text("t,id,x,y,z\n0,0,0,0,1\n0.1,0,0,0,0.95\n")
    assert not any("no header" in w for w in load_csv(tmp_path / "h.csv").warnings)


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


# --------------------------------------------------------------------------- one writer (issue 20, item 1)
_DIRECT_WRITE = __import__("re").compile(
    r"np\.savez|\.savefig\(|save_as_mainfile\(|\.write_text\(|\.write_bytes\(|np\.save\(|save_file\(|json\.dump\(|"
    r"open\([^)]*['\"](?:w|wb|a|ab|x|w\+)['\"]|\.tmp[\"']|\.partial\.|\.save\(\w*tmp\b")
_ALLOWED_DIRECT_WRITES = {
    # (file, text on the line): why it is not a bypass
    ("core/model/checkpoint.py", "save_file(tensors, str(tmp)"): "inside atomic_path",
    ("core/blender_io/blend_file.py", "save_as_mainfile(filepath=str(tmp)"): "inside atomic_path",
    ("core/blender_io/blend_file.py", "save_as_mainfile(filepath=str(real)"): "after the verified copy; Blender's PATH@",
    ("core/blender_io/extension_check.py", 'os.fdopen(fd, "w")'): "standalone script: its own mkstemp + rename",
    ("core/blender_io/extension_check.py", "json.dump(report, f"): "standalone script: its own mkstemp + rename",
    ("core/demo.py", "sheet.save(tmp"): "inside atomic_path",
    ("training/pack.py", "np.savez_compressed(buf"): "into memory",
    ("training/pack.py", "open(tmp_parts[name]"): "a unique mkstemp part, size-checked, renamed",
    ("training/pack.py", "tempfile.mkstemp(prefix="): "a unique temporary name",
    ("training/baselines.py", "save_file(state, str(tmp))"): "inside atomic_path",
    ("training/train.py", "save_file(grads, str(tmp)"): "inside atomic_path",
    ("training/train.py", 'open(out / LOG_FILE, "a")'): "an append-only log, not an output file",
    ("training/validate_diagnosis.py", 'open(out / "results.jsonl", "a")'): "an append-only log of finished cases",
}


def test_every_output_goes_through_the_atomic_writer():
    """No module writes a final file directly or through a fixed temporary name (two processes would share it):
    everything goes through core/atomic_io.py (unique temporary beside the target, checked, renamed)."""
    found = []
    for path in sorted(REPO_ROOT.rglob("*.py")):
        rel = path.relative_to(REPO_ROOT).as_posix()
        if rel.startswith(("tests/", "build/", "dist/")) or rel.startswith(".") or rel == "core/atomic_io.py":
            continue  # hidden folders (.venv, a developer's scratch) are not the package
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if _DIRECT_WRITE.search(line) and not any(f == rel and text in line for f, text in _ALLOWED_DIRECT_WRITES):
                found.append(f"{rel}:{n}: {line.strip()}")
    assert found == [], "writes that bypass core/atomic_io.py:\n" + "\n".join(found)


def test_temporary_names_are_unique_per_write(tmp_path):
    names = set()
    for _ in range(3):
        with atomic_io.atomic_path(tmp_path / "x.npz") as tmp:
            names.add(tmp.name)
            raise_after = False
            np.savez(tmp, a=np.zeros(3))
        assert not raise_after
    assert len(names) == 3 and all(n.startswith(".x.") and n.endswith(".tmp.npz") for n in names)


def test_the_lbs_skinning_cache_is_written_atomically(tmp_path, monkeypatch):
    from unipixie.core import paths

    target = tmp_path / "k.npy"
    monkeypatch.setattr(np.lib.format, "write_array", _enospc_after(10))
    with pytest.raises(UserError, match="disk is full"):
        paths.save_cached_array(target, np.arange(5.0))
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    paths.save_cached_array(target, np.arange(5.0))
    assert np.load(target).tolist() == [0, 1, 2, 3, 4]


# --------------------------------------------------------------------------- found by the fault matrix (round 2)
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


def test_a_solver_setting_that_is_not_a_number_is_named_by_the_cost_estimate():
    from unipixie.core.cost import estimate
    from unipixie.core.types import MaterialField  # noqa: F401 - the estimate reads E, nu, density

    spec = type("M", (), {"E": 2e5, "nu": 0.3, "density": 1000.0})
    with pytest.raises(UserError, match="setting 'anchors' must be a finite number, got 'abc'"):
        estimate("x", "spring_mass", size=0.1, times=np.linspace(0, 1, 5), material_spec=spec, points=8,
                 settings={"anchors": "abc"})  # was ValueError from int('abc')


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


def test_an_error_that_follows_ctrl_c_is_a_cancellation_not_a_bug(capsys):
    """A KeyboardInterrupt that lands inside a library (an import half done) can come out as another exception
    (the fault matrix met NameError from scipy.ndimage): after Ctrl-C the run is cancelled (130), never 'a bug'."""
    def work(args):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
        except KeyboardInterrupt:
            pass  # a library swallowed it ...
        raise NameError("name '_ndimage_api' is not defined")  # ... and failed later

    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert cli.run_command(work, None, "measure") == EXIT_CANCELLED
    err = capsys.readouterr().err
    assert err.strip().endswith("unipixie measure: cancelled") and "internal error" not in err

    def bug(args):
        raise NameError("a real bug")

    assert cli.run_command(bug, None, "measure") == EXIT_INTERNAL_ERROR  # without Ctrl-C a bug stays a bug


def test_a_ctrl_c_after_the_cancellation_is_ignored_while_the_process_exits():
    """The fault matrix's second Ctrl-C sometimes arrived after the first had already cancelled the run: the
    interpreter's shutdown died of the signal (status -2).  After a cancellation the process only exits, 130."""
    code = ("import os, signal, sys; from unipixie.core import cli; status = cli.finish(130); "
            "os.kill(os.getpid(), signal.SIGINT); sys.exit(status)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert r.returncode == EXIT_CANCELLED and "Traceback" not in r.stderr, r.stderr


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


@pytest.mark.parametrize("index", ["{bad json", "[1, 2]"])
def test_a_corrupt_pack_index_is_one_line(index, tmp_path, capsys):
    from unipixie import cli as root_cli

    (tmp_path / "pk").mkdir()
    (tmp_path / "pk" / "index.json").write_text(index)
    assert root_cli.main(["dataset", "unpack", str(tmp_path / "pk"), str(tmp_path / "out")]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "index.json" in err and "internal error" not in err, err  # was JSONDecodeError / AttributeError


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


def test_a_second_features_run_writing_the_same_grid_is_refused(tmp_path, capsys):
    obj = tmp_path / "cube.obj"
    obj.write_text("".join(f"v {x} {y} {z}\n" for x in (0, 1) for y in (0, 1) for z in (0, 1)) + "f 1 2 4 3\n")
    with atomic_io.OutputLock(tmp_path / "g.npz"):  # the first run, still working
        status = cli.main(["features", str(obj), "--out", str(tmp_path / "g.npz"), "--offline-features"])
    err = capsys.readouterr().err
    assert status == EXIT_BAD_INPUT and "being written by another UniPixie run" in err, err
    assert not (tmp_path / "g.npz").exists()


def test_a_swallowed_ctrl_c_still_stops_the_work_at_its_next_progress_step(capsys):
    """The fault matrix's Ctrl-C during Warp's start-up was swallowed and the simulation ran on for minutes: the
    handler also raises the flag every progress check reads."""
    from unipixie.core.progress import INTERRUPTED, Progress

    steps = []

    def work(args):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
        except KeyboardInterrupt:
            pass  # a library swallowed it
        with Progress(total=1000, show_bar=False) as p:
            for _ in range(1000):
                steps.append(1)
                p.step(1)
        return 0

    assert cli.run_command(work, None, "measure") == EXIT_CANCELLED
    assert len(steps) == 1 and "cancelled" in capsys.readouterr().err
    assert not INTERRUPTED.is_set()  # cleared when the command ends


def test_a_simulation_without_a_progress_stops_after_ctrl_c():
    """Benchmarks and batches run the solvers without a Progress: after Ctrl-C (the flag) the frame loop stops."""
    import trimesh

    from unipixie.core.progress import INTERRUPTED
    from unipixie.core.errors import CancelledError
    from unipixie.core import api

    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    mesh.apply_translation([0, 0, 0.2])
    body = api.Body.from_mesh(mesh)
    sim = api.prepare("spring_mass", body, api.HomogeneousMaterial(E=2e4, nu=0.3, density=800), api.Scenario(),
                      np.linspace(0, 0.1, 6), device="cpu", settings={"anchors": 16})
    INTERRUPTED.set()
    try:
        with pytest.raises(CancelledError):
            sim.run([])
    finally:
        INTERRUPTED.clear()
    assert sim.run([]).positions.shape[0] == 6  # without the flag it runs


def test_a_cancelled_demo_removes_only_what_it_made(tmp_path, monkeypatch):
    """The fault matrix's Ctrl-C found a demo folder holding the objects of a demo that never finished."""
    from unipixie.core import demo
    from unipixie.core.errors import CancelledError

    out = tmp_path / "demo"
    out.mkdir()
    (out / "mine.txt").write_text("the user's")

    def half_done(out_dir, *args):
        Path(out_dir).mkdir(exist_ok=True)  # as the demo does
        (Path(out_dir) / "objects").mkdir()
        (Path(out_dir) / "objects" / "potted_plant.glb").write_bytes(b"glTF")
        raise CancelledError()

    monkeypatch.setattr(demo, "_run_demo", half_done)
    with pytest.raises(CancelledError):
        demo.run_demo(out)
    assert sorted(p.name for p in out.rglob("*")) == ["mine.txt"]
    with pytest.raises(CancelledError):
        demo.run_demo(tmp_path / "fresh")
    assert not (tmp_path / "fresh").exists()


def test_ctrl_c_inside_a_blender_callback_only_raises_the_flag():
    """Blender prints and drops an exception raised in its own scripts (an app handler): the first Ctrl-C there
    leaves the cancellation to the flag (the fault matrix met a traceback from pose_library's load handler)."""
    import types

    blender_script = os.path.join(os.sep, "venv", "site-packages", "bpy", "5.0", "scripts", "addons_core", "x.py")
    frame = types.SimpleNamespace(f_code=types.SimpleNamespace(co_filename=blender_script))
    assert cli._in_blender_callback(frame)
    ours = types.SimpleNamespace(f_code=types.SimpleNamespace(co_filename=str(REPO_ROOT / "core" / "bake.py")))
    assert not cli._in_blender_callback(ours) and not cli._in_blender_callback(None)
