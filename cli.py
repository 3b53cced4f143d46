"""Command-line entry point: ``unipixie <command>`` (the console script is :func:`entry_point`).

The command line of every layer: core's commands (:mod:`unipixie.core.commands`) and the training commands
(:mod:`unipixie.training.commands`); core never imports training, so the list of layers is given here, above
both (:func:`unipixie.core.cli.main` alone offers core's commands).

Also usable from a Blender binary (4.2+), where the enabled extension is
``bl_ext.user_default.unipixie``::

    blender -b --python-expr "import bl_ext.user_default.unipixie.cli as c; c.main()" -- doctor

Arguments after ``--`` are the command line.
"""

from __future__ import annotations

import sys
from typing import Sequence

from .core import cli as _core_cli

LAYERS = ("core", "training")
"""The layers whose ``commands`` (and ``benchmarks``) packages the command line offers."""

__all__ = ["LAYERS", "build_parser", "entry_point", "main"]


def build_parser():
    """The parser of every command (see :func:`unipixie.core.cli.build_parser`)."""
    return _core_cli.build_parser(LAYERS)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line (every layer's commands); returns the exit status."""
    return _core_cli.main(argv, LAYERS)


def entry_point() -> None:  # pragma: no cover - console script
    _core_cli.guard_start_up()
    sys.exit(_core_cli.finish(main()))


if __name__ == "__main__":  # pragma: no cover - `python -m unipixie.cli`
    _core_cli.guard_start_up()
    raise SystemExit(_core_cli.finish(main()))
