"""``unipixie build-extension``: build (and validate) the Blender extension zip."""

from __future__ import annotations

NAME = "build-extension"
HELP = "build dist/unipixie-<version>.zip with Blender's blender_ext.py and validate it"
EXAMPLES = """  unipixie build-extension
  unipixie build-extension --out-dir /tmp/dist
  # then in Blender: Edit > Preferences > Get Extensions > Install from Disk..."""


def add_arguments(p):
    p.add_argument("--out-dir", default="dist", help="output directory (default: ./dist)")
    p.add_argument("--no-validate", action="store_true", help="skip 'blender_ext.py validate'")


def run(args) -> int:
    from .. import extension

    path = extension.build(args.out_dir)
    print(f"built {path} ({path.stat().st_size / 1e6:.1f} MB)")
    if not args.no_validate:
        print(f"validate: {extension.validate(path)}")
    return 0
