"""Saving ``.blend`` files the way every UniPixie output is written (:mod:`unipixie.core.atomic_io`).

:func:`save_blend` saves a *copy* of the open session into a temporary file beside the target
(relative paths remapped to that folder, which is the target's), checks it — Blender's header and
end marker (:func:`~unipixie.core.atomic_io.check_blend`), then reopened as a library and its
objects listed — and renames it over the target.  A full disk, a read-only folder or Ctrl-C leave
the target as it was and raise one :class:`~unipixie.core.errors.UserError` naming the path.
The open session's own file path (``bpy.data.filepath``) is not changed.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Optional

import bpy

from ..atomic_io import atomic_path, check_blend, output_path
from ..errors import UserError


def _reopen_check(tmp: Path, shown: str, expect_objects: Iterable[str]) -> None:
    """Open ``tmp`` as a library (the open session is untouched) and check it lists ``expect_objects``."""
    try:
        with bpy.data.libraries.load(str(tmp)) as (data_from, _data_to):
            names = set(data_from.objects)
    except (OSError, RuntimeError, ValueError) as exc:
        raise UserError(f"cannot write {shown}: Blender cannot read the file it wrote back ({exc}); is the disk "
                        "full?") from None
    missing = sorted(set(expect_objects) - names)
    if missing:
        raise UserError(f"cannot write {shown}: the file written lacks the object(s) {', '.join(missing)}")


def save_blend(path, expect_objects: Optional[Iterable[str]] = None, quiet: bool = True,
               as_session_file: bool = False) -> Path:
    """Save the open session as ``path`` atomically and verified (see the module docstring).

    expect_objects: object names that must be in the saved file (default: every object of the
    session).  quiet: silence Blender's "Info: Saved ..." line.  as_session_file: afterwards make
    ``path`` the session's own file (``bpy.data.filepath``; bakes put their PC2 caches beside it) by
    saving it once more the ordinary way, which Blender writes to ``PATH@`` and renames, so the
    verified copy stays if that fails.  Returns ``path``.
    """
    shown = os.fspath(path)
    expect = [o.name for o in bpy.data.objects] if expect_objects is None else list(expect_objects)
    if output_path(path).suffix.lower() != ".blend":
        raise UserError(f"{shown}: a Blender file must end in .blend")

    def verify(tmp: Path) -> None:
        _reopen_check(tmp, shown, expect)

    with atomic_path(path, verify=verify) as tmp:
        backup = tmp.with_name(tmp.name + "1")  # Blender would keep the empty placeholder as "<name>1"
        tmp.unlink()
        try:
            if quiet:
                from .scene_import import quiet_blender_output

                with quiet_blender_output():
                    bpy.ops.wm.save_as_mainfile(filepath=str(tmp), copy=True, relative_remap=True)
            else:
                bpy.ops.wm.save_as_mainfile(filepath=str(tmp), copy=True, relative_remap=True)
        except RuntimeError as exc:  # Blender reports I/O errors as "Error: No space left on device"
            text = str(exc).strip().removeprefix("Error:").strip() or "Blender could not save the file"
            raise UserError(f"cannot write {shown}: {text}") from None
        finally:
            if backup.exists():
                backup.unlink()
            if not tmp.exists():  # Blender failed before creating it: let the check below say so
                tmp.touch()
    if as_session_file:
        real = output_path(path)
        try:
            if quiet:
                from .scene_import import quiet_blender_output

                with quiet_blender_output():
                    bpy.ops.wm.save_as_mainfile(filepath=str(real), relative_remap=True)
            else:
                bpy.ops.wm.save_as_mainfile(filepath=str(real), relative_remap=True)
        except RuntimeError as exc:
            text = str(exc).strip().removeprefix("Error:").strip() or "Blender could not save the file"
            raise UserError(f"cannot write {shown}: {text} (the copy saved just before is complete)") from None
        check_blend(real, shown)
    return Path(path)
