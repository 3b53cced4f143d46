"""The feature recipe: a model remembers how its training objects were rendered, and the pipeline renders
new objects the same way (dataset build settings → pack → training data → checkpoint → pipeline)."""

from __future__ import annotations

import json

import pytest

from unipixie.core.errors import UserError
from unipixie.core.model.checkpoint import RECIPE_FILE, read_feature_recipe, write_feature_recipe
from unipixie.core.pipeline import PipelineSettings


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    from unipixie.core.demo import untrained_checkpoint

    return untrained_checkpoint(tmp_path_factory.mktemp("ckpt"), "tiny")


def test_pipeline_renders_as_the_model_was_trained(checkpoint):
    base = PipelineSettings(view_count=24, resolution=224, engine="cycles", checkpoint=str(checkpoint))
    assert base.with_model_recipe() == base          # no recipe: the settings stay
    write_feature_recipe(checkpoint, {"engine": "workbench", "view_count": 8, "resolution": 160, "samples": 4})
    try:
        s = base.with_model_recipe()
        assert (s.engine, s.view_count, s.resolution, s.samples) == ("workbench", 8, 160, 4)
        assert s.checkpoint == base.checkpoint and s.device == base.device
    finally:
        (checkpoint / RECIPE_FILE).unlink()


def test_bad_recipe_is_refused(tmp_path):
    (tmp_path / RECIPE_FILE).write_text(json.dumps({"engine": "eevee", "view_count": 8, "resolution": 224, "samples": 1}))
    with pytest.raises(UserError, match="engine must be cycles or workbench"):
        read_feature_recipe(tmp_path)
    (tmp_path / RECIPE_FILE).write_text("{not json")
    with pytest.raises(UserError, match="not a readable feature recipe"):
        read_feature_recipe(tmp_path)
    assert read_feature_recipe(tmp_path / "nothing-here") is None


def test_pack_index_gives_the_recipe_of_the_build():
    from unipixie.training.pack import _recipe_of

    index = {"dataset_card": {"settings": {"engine": "Workbench", "views": 8, "render_resolution": 224, "samples": 8}}}
    assert _recipe_of(index) == {"engine": "workbench", "view_count": 8, "resolution": 224, "samples": 8}
    assert _recipe_of({}) is None
