"""Baking simulations into keyframes: everything that does not touch Blender, one module per job.

The object and its solid (:mod:`.body`), the frames (:mod:`.frames`), where the material comes from
(:mod:`.sources`), the request (:mod:`.options`) and its simulation (:mod:`.simulation`, in a worker thread:
:class:`BackgroundRun` of :mod:`unipixie.core.jobs`), how the motion is stored (:mod:`.output`; LBS handles as bones: :mod:`.armature`; PC2 files:
:mod:`.pc2`), batch jobs and shards (:mod:`.jobs`), job manifests (:mod:`.manifest`) and the record a bake leaves
on its object (:mod:`.record`).  The Blender side is :mod:`unipixie.core.blender_io.bake`.  This face re-exports
the public names, so callers write ``from ..bake import BakeOptions``; the modules import each other directly.
"""

from .armature import (ArmaturePlan, armature_deform, chain_channels, chain_deform, continuous_svd, lbs_blend_form,
                       plan_armature)
from ..jobs import BackgroundRun
from .body import SIZE_REFUSE_RANGE, SIZE_WARN_RANGE, BakeObject, build_body, check_size
from .frames import FrameRange, parse_frame_list, parse_frames
from .jobs import (JOB_KEYS, SCENARIO_OVERRIDE_KEYS, BakeJob, check_job_outputs, expand_jobs, expand_out,
                   group_jobs, safe_name, select_objects, shard_groups)
from .manifest import MANIFEST_FORMAT, load_manifest
from .options import BakeOptions
from .output import (ARMATURE_TOLERANCE, INTERPOLATIONS, MESH_CACHE_FRAME_LIMIT, OUTPUT_LABELS, OUTPUT_MODES,
                     SHAPE_KEY_VERTEX_FRAME_LIMIT, choose_output, trajectory_to_local, vertex_output)
from .pc2 import PC2_SIGNATURE, PC2_VERSION, PointCache, read_pc2, write_pc2
from .record import BAKE_RECORD_FORMAT, BAKE_RECORD_KEY, effects_to_json, make_record, parse_record
from .simulation import FrameProgress, SimulationResult, check_trajectory, lbs_vertex_weights, simulate
from .sources import (DEFAULT_HOMOGENEOUS, MATERIAL_RULE, MATERIAL_SOURCE_LABELS, MATERIAL_SOURCES, MODEL_HEADS,
                      FieldFileSource, HomogeneousSource, MaterialSource, ModelSource, ResolvedMaterial,
                      material_from_prediction, material_source_from_dict, no_prediction, plan_material,
                      predict_material)
