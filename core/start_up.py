"""Ctrl-C while the ``unipixie`` command line is starting: the process ends at once, status 130, one line.

Starting the command line takes seconds on a busy machine (the parser imports every command's modules: numpy,
scipy, torch).  Before a command's own guard (:func:`unipixie.core.cli.interrupt_guard`) takes over, a Ctrl-C
printed a ``KeyboardInterrupt`` traceback (status 1), ended the process by the signal (status −2) or broke a
half-imported library (numpy's import failed; a half-started torch aborted the interpreter's shutdown, −6).
Nothing has been written yet at that point, so the guard ends the process at once with :func:`os._exit`
(no shutdown of half-initialised libraries).

The guard is installed by the package root (``unipixie/__init__.py``), the first project code that runs, when the
process was started as the command line (:func:`started_as_command_line`: the console script or ``python -m
unipixie.cli``; never an importer such as Blender, a script or a test), and again by the entry points.  Before that
only the interpreter's own start-up runs (loading itself and its ``site`` module, some tens of milliseconds),
where Ctrl-C has Python's default effect.

This module imports nothing heavy: it runs before everything else.
"""

from __future__ import annotations

import os
import signal
import sys

from .errors import EXIT_CANCELLED

COMMAND_MODULE = "unipixie.cli"
"""The module ``python -m`` runs as the command line."""

COMMAND_SCRIPT = "unipixie"
"""The console script's name (``pyproject.toml``, ``[project.scripts]``)."""

CANCELLED_LINE = b"unipixie: cancelled (while starting)\n"


def cancel_at_once(signum, frame):
    """SIGINT while a command is still starting (importing its modules): nothing has been written yet, so the
    process ends at once with status 130 — no traceback, no half-imported library left to fail later."""
    try:
        os.write(2, CANCELLED_LINE)
    finally:
        os._exit(EXIT_CANCELLED)


def guard_start_up() -> bool:
    """From here until a command's :func:`~unipixie.core.cli.interrupt_guard` takes over, Ctrl-C ends the
    process at once (130).  Only in the main thread and where Ctrl-C still has Python's default handler (a
    background job started with SIGINT ignored keeps it ignored).  Returns whether the guard is installed."""
    try:
        current = signal.getsignal(signal.SIGINT)
        if current is cancel_at_once:
            return True
        if current is not signal.default_int_handler:
            return False
        signal.signal(signal.SIGINT, cancel_at_once)
    except ValueError:  # not the main thread (signal handlers belong to the main thread)
        return False
    return True


def started_as_command_line(orig_argv=None, main_file=None) -> bool:
    """Whether this process is the ``unipixie`` command line: ``python [options] -m unipixie.cli ...`` or the
    console script ``unipixie`` (its ``__main__`` file).  ``orig_argv`` (default ``sys.orig_argv``: the
    interpreter's own command line) and ``main_file`` (default ``__main__.__file__``) are for tests."""
    argv = list(getattr(sys, "orig_argv", ()) if orig_argv is None else orig_argv)
    i = 1
    while i < len(argv):
        token = argv[i]
        if token == "-m":
            return i + 1 < len(argv) and argv[i + 1] == COMMAND_MODULE
        if token.startswith("-m"):
            return token[2:] == COMMAND_MODULE
        if token in ("-X", "-W", "--check-hash-based-pycs"):
            i += 2
            continue
        if token == "-c" or not token.startswith("-") or token == "-":
            break  # a command string, a script or standard input: the script is checked below
        i += 1
    if main_file is None:
        main_file = getattr(sys.modules.get("__main__"), "__file__", None) or ""
    name = os.path.basename(str(main_file))
    for suffix in ("-script.pyw", "-script.py", ".exe"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
    return name == COMMAND_SCRIPT


def guard_if_command_line() -> bool:
    """:func:`guard_start_up` when this process is the command line (:func:`started_as_command_line`)."""
    return started_as_command_line() and guard_start_up()
