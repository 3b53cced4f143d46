"""The ``unipixie`` command line.

Subcommands live one per module in :mod:`unipixie.core.commands`; each module
defines ``NAME``, ``HELP`` (one line), ``EXAMPLES`` (shown by ``--help``),
``add_arguments(parser)`` and ``run(args) -> int``.  Modules are discovered
automatically and must stay light at import time (heavy imports go inside
``run``), so ``unipixie --help`` is instant.

User errors (:class:`~unipixie.core.errors.UserError`, bad arguments) print
one line ``unipixie: error: ...`` and exit non-zero without a traceback.
Inside a Blender binary the arguments after ``--`` are used.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
from typing import Sequence

from .. import __version__
from .errors import UserError


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (no usage dump) and exit with status 2."""

    def error(self, message):  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _command_modules():
    from . import commands

    mods = []
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{commands.__name__}.{info.name}")
        if hasattr(mod, "NAME") and hasattr(mod, "run"):
            mods.append(mod)
    return mods


def build_parser() -> argparse.ArgumentParser:
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
    for mod in _command_modules():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP,
                           epilog=("examples:\n" + mod.EXAMPLES) if getattr(mod, "EXAMPLES", "") else None,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run, _parser=p)
    return parser


def _argv_from_environment() -> list[str]:
    """Arguments for this invocation: after ``--`` inside a Blender binary, else ``sys.argv[1:]``."""
    argv = list(sys.argv)
    if "--" in argv:
        return argv[argv.index("--") + 1:]
    return argv[1:]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (also used as ``SystemExit`` code by the script)."""
    parser = build_parser()
    args = parser.parse_args(_argv_from_environment() if argv is None else list(argv))
    if getattr(args, "cache_dir", None):
        from .paths import set_cache_root

        os.environ["UNIPIXIE_CACHE_DIR"] = args.cache_dir
        set_cache_root(args.cache_dir)
    if not getattr(args, "command", None):
        parser.print_help()
        return 0
    try:
        status = args._run(args)
    except UserError as exc:
        print(f"unipixie {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"unipixie {args.command}: cancelled", file=sys.stderr)
        return 130
    return int(status or 0)


def entry_point() -> None:  # pragma: no cover - console script
    sys.exit(main())
