"""Running Blender operators safely while other Python threads run: no context overrides.

Blender 5.0 (``bpy`` 5.0.1) crashes the whole process when Python runs an operator, or evaluates a
dependency graph, inside ``bpy.context.temp_override(...)`` while another Python thread is executing
Python code.  Measured here: a worker thread that only builds dictionaries in a loop segfaults within
a second while the main thread calls ``bpy.ops.object.mode_set`` (or ``mesh.primitive_cube_add``, or
``evaluated_depsgraph_get``) under an override; the same loops without the override run hundreds of
times without harm.  UniPixie always has such threads about — a bake's simulation in
:class:`~unipixie.core.bake.BackgroundRun`, the demo's kernel warm-up, the demo's side-by-side bakes —
so the package never uses ``temp_override`` (``tests/test_layout.py`` fails on one) and sets the real
view-layer state instead, restoring it afterwards:

* :func:`active_and_selected` — make one object active and a set of objects selected for an operator;
* :func:`selection_kept` — keep the user's selection and active object across an operator that changes
  them (an importer).
"""

from __future__ import annotations

import contextlib
from typing import Iterable

import bpy


def _objects(view_layer) -> list:
    """The view layer's objects (its list may hold ``None`` for an object removed since its last sync)."""
    return [o for o in view_layer.objects if o is not None]


def _alive(obj) -> bool:
    try:
        obj.name  # noqa: B018 - raises ReferenceError once the object was removed
    except ReferenceError:
        return False
    return True


@contextlib.contextmanager
def selection_kept():
    """Restore the current view layer's selection and active object on exit (objects removed meanwhile are
    skipped); objects created meanwhile are left deselected."""
    view_layer = bpy.context.view_layer
    selected = [o for o in _objects(view_layer) if o.select_get(view_layer=view_layer)]
    active = view_layer.objects.active
    try:
        yield
    finally:
        for o in _objects(view_layer):
            o.select_set(False, view_layer=view_layer)
        for o in selected:
            if _alive(o) and view_layer.objects.get(o.name) == o:
                o.select_set(True, view_layer=view_layer)
        view_layer.objects.active = active if active is not None and _alive(active) else None


@contextlib.contextmanager
def active_and_selected(active, selected: Iterable = ()):
    """Within the block, ``active`` is the current view layer's active object and it and ``selected`` are the
    only selected objects; objects outside the view layer are linked to the scene's master collection for the
    block.  Selection, active object and links are restored on exit (:func:`selection_kept`)."""
    scene, view_layer = bpy.context.scene, bpy.context.view_layer
    wanted = [active] + [o for o in selected if o != active]
    linked_here = [o for o in wanted if view_layer.objects.get(o.name) != o]
    for o in linked_here:
        scene.collection.objects.link(o)
    try:
        with selection_kept():
            for o in _objects(view_layer):
                o.select_set(False, view_layer=view_layer)
            for o in wanted:
                o.select_set(True, view_layer=view_layer)
            view_layer.objects.active = active
            yield
    finally:
        for o in linked_here:
            if _alive(o) and scene.collection.objects.get(o.name) == o:
                scene.collection.objects.unlink(o)
