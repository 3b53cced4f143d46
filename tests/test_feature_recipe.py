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


def test_the_extractor_comes_from_the_model_not_from_the_clip_preference(checkpoint, tmp_path, monkeypatch):
    """Features extract what the checkpoint was trained on (recipe 'extractor', else config 'feature_model'):
    an offline model ignores CLIP weights; a model trained on ViT-B-16 extracts CLIP and, without weights, the
    preference check says to fetch them."""
    from unipixie.core import clip_features as cf
    from unipixie.core import pipeline as core
    from unipixie.core.model import UniPixieModel, preset, save_model

    monkeypatch.setenv("UNIPIXIE_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv(cf.CLIP_WEIGHTS_ENV, raising=False)
    weights = tmp_path / "clip.bin"
    weights.write_bytes(b"0")
    options = PipelineSettings(checkpoint=str(checkpoint), clip_weights=str(weights)).feature_options()
    assert options.offline                                    # the offline-trained model gets offline features
    assert core.model_feature_model(checkpoint) == cf.OFFLINE_FEATURE_MODEL

    clip = save_model(UniPixieModel(preset("tiny", feature_model="ViT-B-16", feature_dim=16, patch_size=4,
                                           spring_anchors=8)), tmp_path / "clip_model")
    options = PipelineSettings(checkpoint=str(clip)).feature_options()
    assert not options.offline and options.clip_model == "ViT-B-16" and options.clip_weights is None
    (msg,) = core.check_settings(checkpoint=str(clip))
    assert msg.startswith("CLIP weights: the model was trained on 'ViT-B-16' features") and "weights fetch" in msg
    text, fetch = core.extractor_summary(checkpoint=str(clip))
    assert "expects ViT-B-16 CLIP features (D = 16); weights missing" in text and fetch == "ViT-B-16"

    # the recipe may name the extractor; it must agree with the config
    write_feature_recipe(clip, {"engine": "workbench", "view_count": 8, "resolution": 224, "samples": 1,
                                "extractor": "ViT-B-16"})
    assert read_feature_recipe(clip)["extractor"] == "ViT-B-16" and core.model_feature_model(clip) == "ViT-B-16"
    write_feature_recipe(clip, {"engine": "workbench", "view_count": 8, "resolution": 224, "samples": 1,
                                "extractor": "dinov2-vitb14"})
    with pytest.raises(UserError, match="names the extractor 'dinov2-vitb14' but .* trained on 'ViT-B-16'"):
        core.model_feature_model(clip)
