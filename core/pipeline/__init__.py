"""The object pipeline: Render views → Features → Predict → Simulate & bake, with per-object state.

One pipeline for the panel, the command line and the demo; this package is its Blender-free part, one module
per job: the steps, their states and the per-object record (:mod:`.record`); which model is used
(:mod:`.checkpoint`); what the steps run with and the preference checks (:mod:`.settings`); whether each step
is done or stale, and why (:mod:`.states`); the Predict and Refine jobs (:mod:`.jobs`); the material-field
display (:mod:`.field_display`).  An object's prediction at any α (its :class:`ModelPlan`, the exact prediction)
is :mod:`unipixie.core.model.plan`, below both this package and the bake, re-exported here.  The Blender side
(reading objects, fingerprints, running the steps on objects) is :mod:`unipixie.core.blender_io.pipeline`.
This face re-exports the public names (``from ..pipeline import PipelineSettings``); the modules import each
other directly.  A test that replaces a function replaces it in the module that calls it.
"""

from ..model.plan import ModelPlan, exact_prediction, load_sweep, prediction_from_sweep, refined_path, sweep_heads
from .checkpoint import (checkpoint_feature_model, checkpoint_identity, default_checkpoint, feature_model_name,
                         model_feature_model, resolve_checkpoint)
from .field_display import FIELD_COLORMAP, FIELD_LUT_SIZE, FieldColourScale, field_summary, format_pascal, voxel_surface
from .jobs import predict_job, refine_job
from .record import (DONE, NOT_DONE, RECORD_FORMAT, RECORD_KEY, RUNNING, STALE, STATES, STEP_LABELS, STEPS,
                     PipelineRecord, StepState)
from .settings import (DEFAULT_HEADS, MIN_USEFUL_VIEWS, PipelineSettings, check_settings, cuda_available,
                       cuda_device_count, extractor_summary, precision_of)
from .states import (BAKE_COMPARED, CHANGE_REASONS, CurrentInputs, bake_inputs_of, first_pending, input_changes,
                     step_states)
