"""Command-line entry point: ``unipixie <command>``.

Also usable from a Blender binary (4.2+), where the enabled extension is
``bl_ext.user_default.unipixie``::

    blender -b --python-expr "import bl_ext.user_default.unipixie.cli as c; c.main()" -- doctor

Arguments after ``--`` are the command line.
"""

from .core.cli import main

__all__ = ["main"]

if __name__ == "__main__":  # pragma: no cover - `python -m unipixie.cli`
    raise SystemExit(main())
