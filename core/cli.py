"""The ``unipixie`` command line.

Subcommands live one per module in a layer's ``commands`` package (:mod:`unipixie.core.commands`; the
root command line, :mod:`unipixie.cli`, adds :mod:`unipixie.training.commands`, which core never imports);
each module defines ``NAME``, ``HELP`` (one line), ``EXAMPLES`` (shown by ``--help``),
``add_arguments(parser)`` and ``run(args) -> int`` (a module with ``LAYERED = True`` gets
``add_arguments(parser, layers)``: the bench command, whose benchmarks live in each layer's ``benchmarks``
package).  Modules are discovered automatically and must stay light at import time (heavy imports go inside
``run``), so ``unipixie --help`` is instant.

User errors (:class:`~unipixie.core.errors.UserError`, bad arguments) print
one line ``unipixie: error: ...`` and exit non-zero without a traceback; the exit
statuses are the table in :mod:`unipixie.core.errors` (0 done, 1 internal error,
2 bad input, 3 simulation failed, 130 cancelled).  An internal error (a bug)
prints one line and writes its traceback to a crash log in the cache
(``UNIPIXIE_TRACEBACK=1`` prints it instead).  The first Ctrl-C cancels the
command (it cleans up: no output is left half-written); a second one while it
cleans up only says so; a third stops at once.
Inside a Blender binary the arguments after ``--`` are used.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import pkgutil
import signal
import sys
import threading
import time
import traceback
from typing import Sequence

from . import __version__
from .errors import EXIT_BAD_INPUT, EXIT_CANCELLED, EXIT_INTERNAL_ERROR, UserError
from .start_up import cancel_at_once as _cancel_at_once
from .start_up import guard_start_up  # noqa: F401 - the entry points call it (core.start_up: the whole story)


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (no usage dump) and exit with status 2."""

    def error(self, message):  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


CORE_LAYERS = ("core",)
"""The layers (subpackages of ``unipixie``) whose commands this module's :func:`main` offers by default;
:mod:`unipixie.cli` passes ``("core", "training")``."""


def layer_modules(layers: Sequence[str], kind: str) -> dict:
    """``{name: dotted module}`` of the modules in each layer's ``kind`` package (``commands``, ``benchmarks``)
    that exists, private (``_``) ones left out; a name in two layers is an error (a bug)."""
    found = {}
    for layer in layers:
        package_name = f"{__package__.rpartition('.')[0]}.{layer}.{kind}"
        try:
            package = importlib.import_module(package_name)
        except ModuleNotFoundError as exc:
            if exc.name != package_name:
                raise
            continue
        for info in pkgutil.iter_modules(package.__path__):
            if info.name.startswith("_"):
                continue
            if info.name in found:
                raise RuntimeError(f"{kind} module {info.name!r} is in two layers: {found[info.name]}, {package_name}")
            found[info.name] = f"{package_name}.{info.name}"
    return found


def _command_modules(layers: Sequence[str] = CORE_LAYERS):
    mods = []
    for name, dotted in sorted(layer_modules(layers, "commands").items()):
        mod = importlib.import_module(dotted)
        if hasattr(mod, "NAME") and hasattr(mod, "run"):
            mods.append(mod)
    return mods


def build_parser(layers: Sequence[str] = CORE_LAYERS) -> argparse.ArgumentParser:
    """The parser of the commands of ``layers`` (see :data:`CORE_LAYERS`)."""
    parser = _Parser(
        prog="unipixie",
        description="UniPixie: look at a 3D object and give it physics (features, material prediction, "
                    "MPM / LBS / spring-mass simulation, Blender baking, measurement diagnosis).",
        epilog="Run 'unipixie COMMAND --help' for a command's options and examples.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"unipixie {__version__}")
    parser.add_argument("--cache-dir", metavar="DIR", help="cache directory (default: $UNIPIXIE_CACHE_DIR or ~/.cache/unipixie)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for mod in _command_modules(layers):
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP,
                           epilog=("examples:\n" + mod.EXAMPLES) if getattr(mod, "EXAMPLES", "") else None,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        if getattr(mod, "LAYERED", False):
            mod.add_arguments(p, layers)
        else:
            mod.add_arguments(p)
        p.set_defaults(_run=mod.run, _parser=p)
    return parser


def _argv_from_environment() -> list[str]:
    """Arguments for this invocation: after ``--`` inside a Blender binary, else ``sys.argv[1:]``."""
    argv = list(sys.argv)
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    return argv[1:]


def empty_argument(argv: Sequence[str]) -> str | None:
    """The first empty (or blank) value on a command line, as the user would read it (``--out ''``), or ``None``.

    No command takes an empty value: an empty path is the current folder (``--out ''`` wrote a diagnosis report
    there and printed it as ``/diagnosis.json``), an empty list every item.  Refused before any work.
    """
    for i, token in enumerate(argv):
        if token.startswith("--") and "=" in token:
            name, value = token.split("=", 1)
        elif i > 0 and argv[i - 1].startswith("--") and "=" not in argv[i - 1]:
            name, value = argv[i - 1], token
        else:
            name, value = None, token
        if not value.strip():
            return f"{name} {value!r}" if name else f"argument {i + 1} ({value!r})"
    return None


def main(argv: Sequence[str] | None = None, layers: Sequence[str] = CORE_LAYERS) -> int:
    """Run the command line of ``layers``' commands; returns the exit status (also used as ``SystemExit`` code
    by the script).  The ``unipixie`` script is :func:`unipixie.cli.main` (every layer's commands)."""
    parser = build_parser(layers)
    argv = _argv_from_environment() if argv is None else list(argv)
    empty = empty_argument(argv)
    if empty:
        print(f"{parser.prog}: error: {empty} is empty: give a value (see '{parser.prog} --help')", file=sys.stderr)
        return EXIT_BAD_INPUT
    args = parser.parse_args(argv)
    if getattr(args, "cache_dir", None):
        from .paths import set_cache_root

        os.environ["UNIPIXIE_CACHE_DIR"] = args.cache_dir
        set_cache_root(args.cache_dir)
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    return run_command(args._run, args, args.command)


def run_command(fn, args, command: str) -> int:
    """Run ``fn(args)`` with the command line's error handling; returns the exit status (see the module
    docstring)."""
    prefix = f"unipixie {command}"
    with interrupt_guard(prefix) as presses:
        try:
            try:
                status = fn(args)
            except Exception as exc:
                if not presses:
                    raise
                # Ctrl-C was pressed: its KeyboardInterrupt may have landed inside a library (an import half done,
                # a handler that swallowed it) and come out as another error; the run was cancelled all the same
                if not isinstance(exc, UserError):
                    _crash_log(command, exc)
                raise KeyboardInterrupt from None
        except UserError as exc:
            print(f"{prefix}: error: {exc}", file=sys.stderr)
            return exc.exit_code
        except KeyboardInterrupt:
            print(f"{prefix}: cancelled", file=sys.stderr)
            return EXIT_CANCELLED
        except MemoryError:
            print(f"{prefix}: error: out of memory; use fewer frames, points or a coarser resolution", file=sys.stderr)
            return EXIT_BAD_INPUT
        except OSError as exc:  # an I/O problem no writer turned into a UserError: still one line
            from .atomic_io import describe_os_error

            where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
            print(f"{prefix}: error: cannot access{where}: {describe_os_error(exc)}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except Exception as exc:  # a bug: one line here, the traceback in a crash log
            if os.environ.get("UNIPIXIE_TRACEBACK"):
                raise
            log = _crash_log(command, exc)
            where = f"; the details are in {log}" if log else ""
            print(f"{prefix}: internal error (a bug, please report it): {type(exc).__name__}: {exc}{where}",
                  file=sys.stderr)
            if not log:
                traceback.print_exc()
            return EXIT_INTERNAL_ERROR
    return int(status or 0)


def _crash_log(command: str, exc: BaseException):
    """Write the traceback of ``exc`` to ``<cache>/crash/``; returns the path (``None`` if that fails)."""
    try:
        from .atomic_io import write_text
        from .paths import cache_dir

        path = cache_dir("crash") / f"{command}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.txt"
        text = (f"unipixie {__version__}, command {command!r}, argv {sys.argv!r}\n"
                + "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
        return write_text(path, text)
    except Exception:
        return None


@contextlib.contextmanager
def interrupt_guard(prefix: str = "unipixie"):
    """While the block runs, the first Ctrl-C raises ``KeyboardInterrupt`` (the command cancels and cleans
    up), a second one only says that it is cleaning up, a third exits at once (status 130).  Outputs are
    written atomically, so even the third leaves no partial file under a final name.

    A first Ctrl-C that lands while a module is being imported (commands import torch, Warp, scipy lazily, seconds)
    is raised when that import has ended (:data:`IMPORT_RETRY_S`): a ``KeyboardInterrupt`` inside an import leaves
    a half-imported library, which failed later (numpy, scipy) or aborted the process (a C++ extension such as
    torch's: status −6)."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) not in (signal.default_int_handler, _cancel_at_once):
        yield []
        return
    from .progress import INTERRUPTED

    presses: list = []
    asked_again: list = []      # the held-back press, signalled again (not a new press)

    def ask_again():
        if signal.getsignal(signal.SIGINT) is handler:  # the command may have ended meanwhile
            asked_again.append(True)
            if hasattr(signal, "pthread_kill"):
                signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)  # a signal also ends a sleep
            else:  # Windows
                import _thread

                _thread.interrupt_main()

    def handler(signum, frame):
        if asked_again:
            asked_again.clear()
        else:
            presses.append(time.monotonic())
        INTERRUPTED.set()  # every progress check now cancels, even if this KeyboardInterrupt is swallowed
        if len(presses) == 1:
            if _in_blender_callback(frame):
                return  # Blender would print the exception's traceback and swallow it: the flag cancels instead
            if _importing(frame):
                retry = threading.Timer(IMPORT_RETRY_S, ask_again)
                retry.daemon = True
                retry.start()
                return
            raise KeyboardInterrupt
        if len(presses) == 2:
            print(f"\n{prefix}: cancelling: cleaning up so that nothing is left half-written "
                  "(press Ctrl-C again to stop at once)", file=sys.stderr, flush=True)
            return
        os._exit(EXIT_CANCELLED)

    signal.signal(signal.SIGINT, handler)
    try:
        yield presses
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        INTERRUPTED.clear()


IMPORT_RETRY_S = 0.05
"""Seconds between the checks whether the import a first Ctrl-C landed in has ended (see :func:`interrupt_guard`)."""


def _importing(frame) -> bool:
    """True when the interrupted Python code runs inside an import (Python's import machinery is on its stack)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib._bootstrap"):
            return True
        frame = frame.f_back
    return False


def _in_blender_callback(frame) -> bool:
    """True when the interrupted Python code is one of Blender's own scripts (an app handler, an add-on of its
    bundle), which Blender calls from C: an exception raised there is printed with its traceback and dropped."""
    name = frame.f_code.co_filename if frame is not None else ""
    return f"{os.sep}scripts{os.sep}" in name and f"{os.sep}bpy{os.sep}" in name


def finish(status: int) -> int:
    """The exit status of a command-line process, handed to ``sys.exit``.  After a cancellation the process only
    exits: a late Ctrl-C (the second press arriving after the cleanup ended) is ignored instead of killing the
    interpreter's shutdown with a signal (the status would then read -2, or a traceback appear)."""
    if status == EXIT_CANCELLED and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return status


def entry_point() -> None:  # pragma: no cover - console script of installs made before unipixie.cli:entry_point
    """Core's commands only: the ``unipixie`` script of an install older than the layered command line (which
    pointed here).  Re-installing (``setup.sh``: ``pip install -e .``) points the script at
    :func:`unipixie.cli.entry_point`, every layer's commands."""
    guard_start_up()
    sys.exit(finish(main()))
