"""Baking into Blender data, one module per job; everything Blender-free is :mod:`unipixie.core.bake`.

Reading: the object (:mod:`.reading`), its panel settings and options (:mod:`.options`), the scene's scenario
(:mod:`.scenario`).  Writing, with bulk ``foreach_set`` calls and Blender 5.0 layered actions (shared parts:
:mod:`.writing`): shape keys (:mod:`.shape_keys`), a Mesh Cache on a PC2 file (:mod:`.mesh_cache`), an armature
for LBS (:mod:`.armature`) with its ground lift (:mod:`.ground_lift`), the MPM particles (:mod:`.particles`), a
finished simulation (:mod:`.result`).  Undo and removal (:mod:`.removal`); the whole bake for the modal operator
and the Python API (:mod:`.steps`); timing the writers (:mod:`.timing`).  Jobs on .blend files are
:mod:`unipixie.core.blender_io.bake_jobs`.  This face re-exports the public names.
"""

from .armature import write_armature
from .ground_lift import add_ground_lift
from .mesh_cache import cache_folder, write_mesh_cache
from .options import (material_source_from_settings, object_settings, options_from_settings, registered_properties,
                      scene_fps)
from .particles import write_particles
from .reading import evaluated_positions, read_object, unit_scale, world_vertices
from .removal import bake_record, clear_bake, empty_trash, restore_trashed_files
from .result import BakeReport, write_result
from .scenario import clamp_box, ground_height, scenario_from_scene
from .shape_keys import write_shape_keys
from .steps import bake_object, bake_steps
from .timing import time_writes
from .writing import PREFIX, WriteRecord
