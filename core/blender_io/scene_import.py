"""Bringing objects from files into Blender for the pipeline, and taking them out again.

:func:`loaded_objects` imports a mesh file (``.glb`` / ``.gltf`` / ``.obj`` /
``.ply`` / ``.stl``, through Blender's own importers, so materials and textures
come along) or appends an object from a ``.blend`` file into a *temporary
scene*; on exit it removes every data-block the import created, so the
current file (the user's session, when called from inside Blender) is left
as it was.

    with loaded_objects("chair.glb") as objects:      # list of bpy Objects with geometry
        views = render_views(objects, settings)
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from pathlib import Path

import bpy

from ..errors import UserError
from .context_safety import selection_kept

MESH_FILE_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl")
SUPPORTED_SUFFIXES = MESH_FILE_SUFFIXES + (".blend",)
GEOMETRY_TYPES = ("MESH", "CURVE", "SURFACE", "META", "FONT")
"""Object types that can be turned into a triangle mesh (``bpy.data.meshes.new_from_object``)."""


@contextlib.contextmanager
def quiet_blender_output():
    """Send what Blender prints on standard output (per-render "Saved: ..." lines, importer timings) to a
    temporary log instead of the terminal; yields a function returning the log's last lines (for error
    messages)."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:              # no usable standard output: nothing to silence
        yield lambda: ""
        return
    log = tempfile.TemporaryFile(mode="w+b")

    def tail(lines: int = 5) -> str:
        log.flush()
        log.seek(0)
        return "\n".join(log.read().decode(errors="replace").strip().splitlines()[-lines:])

    try:
        os.dup2(log.fileno(), 1)
        yield tail
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        log.close()


def _importer(suffix: str):
    return {
        ".glb": bpy.ops.import_scene.gltf,
        ".gltf": bpy.ops.import_scene.gltf,
        ".obj": bpy.ops.wm.obj_import,
        ".ply": bpy.ops.wm.ply_import,
        ".stl": bpy.ops.wm.stl_import,
    }[suffix]


def _id_collections():
    """Every ``bpy.data`` collection of data-blocks (objects, meshes, materials, images, ...)."""
    skip = {"window_managers", "screens", "workspaces"}
    return [getattr(bpy.data, p.identifier) for p in bpy.data.bl_rna.properties
            if p.type == "COLLECTION" and p.identifier not in skip]


def snapshot_ids() -> set:
    """The set of all data-blocks now present (to find those created later)."""
    ids = set()
    for coll in _id_collections():
        ids.update(idb for idb in coll if isinstance(idb, bpy.types.ID))
    return ids


def remove_new_ids(before: set) -> None:
    """Remove every data-block created since ``before`` (a :func:`snapshot_ids` result)."""
    new = [idb for idb in snapshot_ids() if idb not in before and isinstance(idb, bpy.types.ID)]
    if new:
        bpy.data.batch_remove(new)


def geometry_objects(objects) -> list:
    """The objects among ``objects`` that have renderable geometry; a clear error when there are none."""
    objs = [o for o in objects if o is not None and o.type in GEOMETRY_TYPES]
    if not objs:
        kinds = ", ".join(sorted({f"{o.name} ({o.type.lower()})" for o in objects if o is not None})) or "nothing"
        raise UserError(f"no object with geometry to look at (got {kinds}); select a mesh object")
    return objs


@contextlib.contextmanager
def temporary_scene(name: str = "UniPixie temporary"):
    """A new empty scene that is removed (with everything created meanwhile) on exit."""
    before = snapshot_ids()
    scene = bpy.data.scenes.new(name)
    try:
        yield scene
    finally:
        remove_new_ids(before)


@contextlib.contextmanager
def loaded_objects(path, object_name: str | None = None):
    """Import ``path`` into a temporary scene and yield its objects with geometry (see module docstring).

    object_name: for ``.blend`` files, the object to append (needed when the file holds several objects
        with geometry); for mesh files, keep only the imported object of that name.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise UserError(f"{path}: file not found")
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise UserError(f"{path}: unsupported file type {suffix or '(none)'!r}; supported: "
                        f"{', '.join(SUPPORTED_SUFFIXES)}")
    with temporary_scene("UniPixie import") as scene:
        if suffix == ".blend":
            objects = _append_from_blend(path, object_name, scene)
        else:
            if suffix == ".obj":
                check_obj_file(path)
            before = set(bpy.data.objects)
            try:
                # into the current scene (no context override: see .context_safety), then moved to the temporary one
                with selection_kept(), quiet_blender_output():
                    result = _importer(suffix)(filepath=str(path))
            except RuntimeError as exc:
                raise UserError(f"{path}: Blender could not import it: {str(exc).strip().splitlines()[-1]}") from None
            objects = [o for o in bpy.data.objects if o not in before]
            _move_to_scene(objects, scene)
            if "FINISHED" not in result:
                raise UserError(f"{path}: Blender's {suffix} importer failed ({', '.join(sorted(result))})")
            if object_name:
                chosen = [o for o in objects if o.name == object_name]
                if not chosen:
                    raise UserError(f"{path}: no object named {object_name!r}; it holds "
                                    f"{', '.join(sorted(o.name for o in objects)) or 'no objects'}")
                objects = chosen
            if not objects:
                raise UserError(f"{path}: the file holds no objects")
        yield geometry_objects(objects)


def check_obj_file(path: Path) -> None:
    """Refuse an OBJ file that Blender's importer would quietly change: a vertex coordinate that is not a finite
    number (Blender reads ``nan`` and ``inf`` as 0) or a face that names a vertex the file does not have (Blender
    drops the face with a warning).  One pass over the text; raises :class:`UserError` naming the line."""
    import math

    vertices, faces, worst = 0, [], (0, 0)
    try:
        with open(path, "rb") as f:
            for n, raw in enumerate(f, 1):
                line = raw.split(b"#", 1)[0].strip()
                if line.startswith(b"v "):
                    vertices += 1
                    try:
                        xyz = [float(x) for x in line.split()[1:4]]
                    except ValueError:
                        raise UserError(f"{path}: line {n}: a vertex with a coordinate that is not a number "
                                        f"({raw.strip()[:60].decode(errors='replace')!r})") from None
                    if len(xyz) < 3 or not all(math.isfinite(x) for x in xyz):
                        raise UserError(f"{path}: line {n}: a vertex needs three finite coordinates, got "
                                        f"{raw.strip()[:60].decode(errors='replace')!r}")
                elif line.startswith(b"f "):
                    for ref in line.split()[1:]:
                        try:
                            index = int(ref.split(b"/", 1)[0])
                        except ValueError:
                            raise UserError(f"{path}: line {n}: a face with a vertex reference that is not a whole "
                                            f"number ({ref[:20].decode(errors='replace')!r})") from None
                        if index == 0 or (index < 0 and -index > vertices):
                            raise UserError(f"{path}: line {n}: face vertex {index} does not exist (OBJ counts "
                                            "vertices from 1)")
                        if index > worst[0]:
                            worst = (index, n)
    except OSError as exc:
        raise UserError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    if worst[0] > vertices:
        raise UserError(f"{path}: line {worst[1]}: a face names vertex {worst[0]}, the file has {vertices} vertices")


def _move_to_scene(objects, scene) -> None:
    """Unlink ``objects`` from every collection they are in and link them to ``scene``'s master collection."""
    for o in objects:
        for collection in list(o.users_collection):
            collection.objects.unlink(o)
        scene.collection.objects.link(o)


def _append_from_blend(path: Path, object_name: str | None, scene) -> list:
    try:
        with bpy.data.libraries.load(str(path), link=False) as (src, dst):
            names = list(src.objects)
            if object_name is not None:
                if object_name not in names:
                    raise UserError(f"{path}: no object named {object_name!r}; it holds "
                                    f"{', '.join(sorted(names)) or 'no objects'}")
                dst.objects = [object_name]
            else:
                dst.objects = names
    except OSError as exc:
        raise UserError(f"{path}: not a readable .blend file ({exc})") from None
    objects = [o for o in dst.objects if o is not None]
    for o in objects:
        scene.collection.objects.link(o)
    if object_name is None:
        geo = [o for o in objects if o.type in GEOMETRY_TYPES]
        if len(geo) > 1:
            raise UserError(f"{path} holds several objects with geometry ({', '.join(sorted(o.name for o in geo))}); "
                            "choose one with --object NAME")
    else:
        objects = [o for o in objects if o.name == object_name] or objects
    return objects
