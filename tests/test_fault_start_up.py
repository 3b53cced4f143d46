"""Fault injection, Ctrl-C while the command line starts (issue 20): from the first line of the project's code on,
SIGINT ends ``unipixie`` with status 130 and one line — no traceback, no death by the signal (−2), no abort (−6).

The early moments are hit exactly: a ``sitecustomize`` module (imported by Python at the end of its own start-up)
installs an audit hook that sends SIGINT to the process when a chosen module starts to be imported.  Then real
SIGINTs come from outside at several delays after Python's start-up, repeated.

The Ctrl-C tests send SIGINT to a child process: run pytest in the foreground (a shell without job control
starts background jobs with SIGINT ignored; the children here get the default handler back)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from unipixie.core import start_up
from unipixie.core.errors import EXIT_CANCELLED

SITECUSTOMIZE = textwrap.dedent("""
    import os, signal, sys, time

    os.write(1, b"python started\\n")              # the end of the interpreter's own start-up (site)
    _at = os.environ.get("UNIPIXIE_TEST_SIGINT_AT")
    _slow = os.environ.get("UNIPIXIE_TEST_SLOW_OPEN")

    def _slow_disk(event, args):
        if event == "open" and isinstance(args[0], (str, os.PathLike)) and os.fspath(args[0]) == _slow:
            time.sleep(60)                          # the input file sits on a slow disk

    if _slow:
        sys.addaudithook(_slow_disk)

    def _hook(event, args, _sent=[]):
        if event == "import" and args[0] == _at and not _sent:
            _sent.append(1)
            os.write(1, b"signalled\\n")
            os.kill(os.getpid(), signal.SIGINT)

    if _at:
        sys.addaudithook(_hook)
""")


def _default_sigint():
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # as in a terminal


@pytest.fixture(scope="module")
def command(tmp_path_factory):
    """(argv, env) of ``python -m unipixie.cli predict ...`` with the test's sitecustomize on the path."""
    d = tmp_path_factory.mktemp("start_up")
    (d / "site").mkdir()
    (d / "site" / "sitecustomize.py").write_text(SITECUSTOMIZE)
    (d / "grid.npz").write_bytes(b"never read: the command is cancelled before")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(d / "site")] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env.pop("UNIPIXIE_TRACEBACK", None)
    # The command reads the grid about 1.7 s after start-up here, and then ends (the file is not an archive); on a
    # fast machine the latest SIGINT below (1.5 s) came after that.  Opening the grid takes a minute instead, so
    # every SIGINT falls before the command has ended — during start-up or during its own first work.
    env["UNIPIXIE_TEST_SLOW_OPEN"] = str(d / "grid.npz")
    argv = [sys.executable, "-m", "unipixie.cli", "predict", str(d / "grid.npz"), "--alpha", "0.5", "--steps", "1",
            "--out", str(d / "pred")]
    return argv, env


def _one_cancelled_line(returncode, err):
    lines = err.strip().splitlines()
    assert returncode == EXIT_CANCELLED, (returncode, err[-2000:])
    assert len(lines) == 1 and "cancelled" in lines[0] and "Traceback" not in err, err[-2000:]


# the package root's first import after the guard, the command line's modules, the parser's libraries, and torch,
# which predict imports when it runs (under the command's own guard: raised once the import has ended)
EARLY_IMPORTS = ["unipixie.core.property_registration", "unipixie.core.cli", "argparse",
                 "numpy", "torch"]


@pytest.mark.parametrize("module", EARLY_IMPORTS)
def test_ctrl_c_at_an_early_import_ends_with_130_and_one_line(command, module):
    argv, env = command
    r = subprocess.run(argv, env={**env, "UNIPIXIE_TEST_SIGINT_AT": module}, capture_output=True, text=True,
                       timeout=120, preexec_fn=_default_sigint)
    assert "signalled" in r.stdout, (module, r.stdout, r.stderr[-2000:])   # the signal was sent at that import
    _one_cancelled_line(r.returncode, r.stderr)


def test_ctrl_c_at_several_early_moments_ends_with_130_and_one_line(command):
    """Real SIGINTs from outside, 0.1 s to 1.5 s after the interpreter's own start-up, each twice."""
    argv, env = command
    outcomes = []
    for delay in (0.1, 0.3, 0.7, 1.5):
        for _ in range(2):
            proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                    preexec_fn=_default_sigint)
            try:
                assert proc.stdout.readline().strip() == "python started"
                time.sleep(delay)
                proc.send_signal(signal.SIGINT)
                _, err = proc.communicate(timeout=120)
            finally:
                if proc.poll() is None:
                    proc.kill()
            outcomes.append((delay, proc.returncode, err))
    for delay, returncode, err in outcomes:
        assert returncode == EXIT_CANCELLED and len(err.strip().splitlines()) == 1, (delay, returncode, err[-2000:])
        assert "cancelled" in err and "Traceback" not in err, (delay, err[-2000:])


def test_a_ctrl_c_inside_an_import_is_raised_when_the_import_has_ended(tmp_path):
    """A KeyboardInterrupt raised inside an import leaves a half-imported library (numpy failed later; torch's C++
    start-up aborted the process, −6): the command's guard raises it once the import is over."""
    (tmp_path / "slow_library.py").write_text(textwrap.dedent("""
        import os, signal, time
        os.kill(os.getpid(), signal.SIGINT)     # Ctrl-C while this module is being imported
        time.sleep(0.5)
        print("imported to the end", flush=True)
    """))
    code = textwrap.dedent(f"""
        import signal, sys, time
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.path.insert(0, {str(tmp_path)!r})
        from unipixie.core import cli
        def run(args):
            import slow_library
            print("running on", flush=True)
            time.sleep(30)
        sys.exit(cli.finish(cli.run_command(run, None, "predict")))
    """)
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       preexec_fn=_default_sigint)
    assert "imported to the end" in r.stdout, (r.stdout, r.stderr[-2000:])
    _one_cancelled_line(r.returncode, r.stderr)
    assert time.monotonic() - t0 < 25  # cancelled when the import ended, not after the 30 s sleep


def test_the_command_line_is_recognised_from_the_interpreter_command_line():
    py = "/usr/bin/python3"
    assert start_up.started_as_command_line([py, "-m", "unipixie.cli", "predict"], "")
    assert start_up.started_as_command_line([py, "-X", "importtime", "-u", "-munipixie.cli"], "")
    assert start_up.started_as_command_line([py, "/venv/bin/unipixie", "demo"], "/venv/bin/unipixie")
    assert start_up.started_as_command_line([py, "C:/venv/Scripts/unipixie-script.py"], "C:/venv/Scripts/unipixie-script.py")
    # importers are never guarded: Blender, a script, python -c, another module, pytest
    assert not start_up.started_as_command_line(["blender", "-b", "--python-expr", "import unipixie"], "")
    assert not start_up.started_as_command_line([py, "-c", "import unipixie"], "")
    assert not start_up.started_as_command_line([py, "-m", "unipixie.core.cli"], "")
    assert not start_up.started_as_command_line([py, "-m", "pytest", "-m", "unipixie.cli"], "")
    assert not start_up.started_as_command_line([py, "/home/u/bake_all.py"], "/home/u/bake_all.py")
    assert not start_up.started_as_command_line([py, "-m", "pytest", "tests"], "")


def test_importing_the_package_in_this_process_installed_no_guard():
    """The test process (an importer) keeps its own Ctrl-C handling."""
    assert signal.getsignal(signal.SIGINT) is not start_up.cancel_at_once
