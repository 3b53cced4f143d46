"""Fault injection, interruption: exit statuses follow one table (README "Exit statuses"); Ctrl-C cancels with
status 130 and no leftovers, once or twice, also when a library swallows it, inside a simulation without a
progress, in a demo or in a Blender callback.

The Ctrl-C tests send SIGINT to a child process: run pytest in the foreground (a shell without job control
starts background jobs with SIGINT ignored)."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from unipixie.core import cli
from unipixie.core.errors import (EXIT_BAD_INPUT, EXIT_CANCELLED, EXIT_INTERNAL_ERROR, EXIT_SIMULATION_FAILED,
                                  SimulationDiverged, UserError)

from fault_helpers import REPO_ROOT, _leftovers


# --------------------------------------------------------------------------- exit codes, crash log
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


# --------------------------------------------------------------------------- Ctrl-C
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


def test_ctrl_c_while_the_command_line_is_starting_cancels_without_a_traceback():
    """Building the command line imports every command's modules (seconds): a Ctrl-C there printed a
    KeyboardInterrupt traceback (status 1), killed the process by the signal (-2) or broke numpy's import."""
    code = ("import os, signal, time; from unipixie import cli; cli._core_cli.guard_start_up(); "
            "os.kill(os.getpid(), signal.SIGINT); time.sleep(10); print('not stopped')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert r.returncode == EXIT_CANCELLED and "cancelled" in r.stderr, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and "not stopped" not in r.stdout


def test_the_command_takes_ctrl_c_over_from_the_start_up_guard():
    """Once the command runs, its own guard (cancel and clean up) replaces the start-up one, and after it
    Python's default handler is back."""
    from unipixie.core import cli as core_cli

    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        core_cli.guard_start_up()
        assert signal.getsignal(signal.SIGINT) is core_cli._cancel_at_once
        with core_cli.interrupt_guard():
            assert signal.getsignal(signal.SIGINT) not in (core_cli._cancel_at_once, signal.default_int_handler)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
