"""Training: the sample format, resume, data-parallel gradients (2 gloo processes) and the command line."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from unipixie.cli import main
from unipixie.core.errors import UserError
from unipixie.core.model.checkpoint import TRAINING_JSON, is_checkpoint
from unipixie.training.sample_format import (SAMPLE_FORMAT, TrainingSample, data_fingerprint, list_samples)
from unipixie.training.synthetic import make_dataset, make_sample
from unipixie.training.train import TrainSettings, train

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = dict(preset="tiny", device="cpu", precision="fp32", save_every=10 ** 9, log_every=1, lr=1e-3, warmup=2)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("train-data") / "data"
    make_dataset(root, 4, resolution=8, feature_dim=8, anchors=6, seed=1)
    return root


# ---------------------------------------------------------------------------- sample format
def test_sample_round_trip_and_validation(tmp_path):
    s = make_sample(3, resolution=8, feature_dim=5, anchors=4)
    back = TrainingSample.load(s.save(tmp_path / "s.npz"))
    assert back.object_id == s.object_id and np.array_equal(back.grid.occupancy, s.grid.occupancy)
    assert np.array_equal(back.mpm.E_max, s.mpm.E_max) and np.array_equal(back.lbs.params, s.lbs.params)
    assert back.spring.softness_max == pytest.approx(s.spring.softness_max)
    with np.load(tmp_path / "s.npz") as z:
        d = {k: z[k] for k in z.files}
    assert str(d["format"]) == SAMPLE_FORMAT
    bad = dict(d)
    bad["mpm_E_min"] = d["mpm_E_max"] * 2.0
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(UserError, match=r"bad.npz.*mpm_E_min > mpm_E_max"):
        TrainingSample.load(tmp_path / "bad.npz")
    partial = {k: v for k, v in d.items() if k != "lbs_nu_max"}
    np.savez(tmp_path / "partial.npz", **partial)
    with pytest.raises(UserError, match="incomplete lbs group"):
        TrainingSample.load(tmp_path / "partial.npz")
    no_heads = {k: v for k, v in d.items() if not k.startswith(("lbs_", "spring_"))}  # optional groups
    np.savez(tmp_path / "mpm_only.npz", **no_heads)
    only = TrainingSample.load(tmp_path / "mpm_only.npz")
    assert only.lbs is None and only.spring is None
    nan = dict(d)
    nan["features"] = d["features"].copy()
    nan["features"][0, 0] = np.nan
    np.savez(tmp_path / "nan.npz", **nan)
    with pytest.raises(UserError, match="NaN"):
        TrainingSample.load(tmp_path / "nan.npz")


def test_dataset_listing_split_and_fingerprint(tmp_path):
    paths = make_dataset(tmp_path / "d", 3, resolution=8, feature_dim=4, anchors=4, test_fraction=0.34)
    assert [p.name for p in list_samples(tmp_path / "d", "train")] == [p.name for p in paths[:2]]
    assert [p.name for p in list_samples(tmp_path / "d", "test")] == [paths[2].name]
    f1 = data_fingerprint(paths)
    make_sample(99, resolution=8, feature_dim=4, anchors=4).save(paths[0])
    assert data_fingerprint(paths) != f1
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="no training samples"):
        list_samples(tmp_path / "empty")
    with pytest.raises(UserError, match="not found"):
        list_samples(tmp_path / "missing")


# ---------------------------------------------------------------------------- resume
def test_resume_gives_the_same_next_step_losses(data, tmp_path):
    full = train(TrainSettings(data=str(data), out=str(tmp_path / "full"), steps=5, batch=2, **TINY))
    first = train(TrainSettings(data=str(data), out=str(tmp_path / "part"), steps=5, batch=2, stop_after=3, **TINY))
    assert first["final_step"] == 3 and is_checkpoint(tmp_path / "part")
    assert json.loads((tmp_path / "part" / TRAINING_JSON).read_text())["step"] == 3
    rest = train(TrainSettings(data=str(data), out=str(tmp_path / "part"), steps=5, batch=2, resume=True, **TINY))
    assert rest["start_step"] == 3 and rest["final_step"] == 5
    assert first["losses"] == full["losses"][:3]
    assert np.allclose(rest["losses"], full["losses"][3:], rtol=1e-6, atol=0), (rest["losses"], full["losses"])
    # the finished runs hold the same weights
    a, b = load_file(str(tmp_path / "full" / "model.safetensors")), load_file(str(tmp_path / "part" / "model.safetensors"))
    assert all(torch.allclose(a[k], b[k], rtol=1e-5, atol=1e-7) for k in a)


def test_cancelled_training_keeps_a_resumable_checkpoint(data, tmp_path):
    from unipixie.core.errors import CancelledError
    from unipixie.core.progress import Progress

    progress = Progress(total=10, show_bar=False,
                        callback=lambda fraction, status: progress.cancel() if fraction >= 0.2 else None)
    with pytest.raises(CancelledError):
        train(TrainSettings(data=str(data), out=str(tmp_path / "run"), steps=10, batch=1, **TINY), progress=progress)
    assert json.loads((tmp_path / "run" / TRAINING_JSON).read_text())["step"] == 2
    rest = train(TrainSettings(data=str(data), out=str(tmp_path / "run"), steps=3, batch=1, resume=True, **TINY))
    assert rest["start_step"] == 2 and rest["final_step"] == 3


def test_training_refuses_to_overwrite_and_mismatched_resume(data, tmp_path):
    out = tmp_path / "run"
    train(TrainSettings(data=str(data), out=str(out), steps=1, batch=1, **TINY))
    with pytest.raises(UserError, match="already holds a checkpoint; pass --resume"):
        train(TrainSettings(data=str(data), out=str(out), steps=2, batch=1, **TINY))
    with pytest.raises(UserError, match="another model config: width"):
        train(TrainSettings(data=str(data), out=str(out), steps=2, batch=1, resume=True, model={"width": 32}, **TINY))
    other = tmp_path / "other-data"
    make_dataset(other, 2, resolution=8, feature_dim=8, anchors=6, seed=7)
    with pytest.raises(UserError, match="differs from the data the checkpoint was trained on"):
        train(TrainSettings(data=str(other), out=str(out), steps=2, batch=1, resume=True, **TINY))
    wrong = tmp_path / "wrong-features"
    make_dataset(wrong, 1, resolution=8, feature_dim=8, anchors=6, feature_model="another-extractor")
    with pytest.raises(UserError, match="another-extractor"):
        train(TrainSettings(data=str(wrong), out=str(out), steps=2, batch=1, resume=True, allow_new_data=True, **TINY))


# ---------------------------------------------------------------------------- data parallel
def test_two_gloo_processes_give_the_single_process_gradient(data, tmp_path):
    args = ["--data", str(data), "--steps", "2", "--batch", "4", "--preset", "tiny", "--device", "cpu",
            "--precision", "fp32", "--warmup", "2", "--lr", "1e-3", "--log-every", "1"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
           "-m", "unipixie.training.train", "--out", str(tmp_path / "ddp"), "--dump-gradients",
           str(tmp_path / "g2.safetensors"), "--stats-out", str(tmp_path / "ddp.json"), *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ddp = json.loads((tmp_path / "ddp.json").read_text())
    assert ddp["world_size"] == 2
    single = train(TrainSettings(data=str(data), out=str(tmp_path / "one"), steps=2, batch=4,
                                 dump_gradients=str(tmp_path / "g1.safetensors"), **TINY))
    g1, g2 = load_file(str(tmp_path / "g1.safetensors")), load_file(str(tmp_path / "g2.safetensors"))
    assert g1.keys() == g2.keys()
    worst = max(float((g1[k] - g2[k]).abs().max() / (g1[k].abs().max() + 1e-8)) for k in g1)
    assert worst < 1e-4, worst
    assert sum(float(g.abs().sum()) for g in g1.values()) > 0
    assert ddp["losses"] == pytest.approx(single["losses"], rel=1e-5)  # the second step too (all parameters reduced)


# ---------------------------------------------------------------------------- command line
def test_train_command_then_predict(data, tmp_path):
    out = tmp_path / "ck"
    assert main(["train", "--data", str(data), "--out", str(out), "--steps", "2", "--batch", "2", "--preset", "tiny",
                 "--device", "cpu", "--set", "latent_tokens=4", "--save-dtype", "bfloat16"]) == 0
    cfg = json.loads((out / "config.json").read_text())["config"]
    assert cfg["latent_tokens"] == 4 and cfg["feature_model"] == "synthetic-test" and cfg["spring_anchors"] == 6
    # the flow-time distribution of training goes with the weights, and the sampler steps through it
    from unipixie.core.model.checkpoint import load_model
    from unipixie.core.model.inference import Predictor
    from unipixie.core.model.objective import SamplingSettings

    _, info = load_model(out)
    assert info["sampling"]["t_mean"] == SamplingSettings().t_mean and info["sampling"]["t_std"] == SamplingSettings().t_std
    assert Predictor.load(out, device="cpu").t_mean == SamplingSettings().t_mean
    assert main(["train", "--data", str(data), "--out", str(out), "--steps", "2", "--preset", "tiny"]) == 2
    grid = TrainingSample.load(list_samples(data)[0]).grid.save(tmp_path / "grid.npz")
    assert main(["predict", str(grid), "--checkpoint", str(out), "--alpha", "0.3", "--steps", "2", "--device", "cpu",
                 "--heads", "mpm,spring", "--out", str(tmp_path / "pred")]) == 0
    assert (tmp_path / "pred" / "material_field_a0.300.npz").is_file()
    assert not (tmp_path / "pred" / "lbs_a0.300.npz").exists()


def test_train_script_runs_from_a_bare_checkout(repo_root):
    """`python training/train.py` (torchrun's file form) works without the package installed."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, "-S", "-c",
                           "import runpy, sys; sys.argv = ['train.py', '--help']; "
                           f"runpy.run_path({str(repo_root / 'training' / 'train.py')!r}, run_name='__main__')"],
                          capture_output=True, text=True, env=env, cwd="/", timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "--data" in proc.stdout and "--resume" in proc.stdout


def test_training_needs_only_torch_numpy_safetensors(data, tmp_path, repo_root):
    """The GPU machine has torch, numpy and safetensors only: block every other third-party package."""
    code = f"""
import sys, importlib.abc, importlib.machinery
BLOCKED = ("warp", "bpy", "trimesh", "scipy", "open_clip", "matplotlib", "tqdm", "embreex", "rtree", "PIL", "torchvision")
class Missing(importlib.abc.Loader):
    def create_module(self, spec):
        raise ImportError("not installed on the GPU machine: " + spec.name)
    def exec_module(self, module):
        pass
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            return importlib.machinery.ModuleSpec(name, Missing())
sys.meta_path.insert(0, Block())
import runpy
sys.argv = ["train.py", "--data", {str(data)!r}, "--out", {str(tmp_path / "ck")!r}, "--steps", "1", "--preset", "tiny",
            "--device", "cpu"]
runpy.run_path({str(repo_root / "training" / "train.py")!r}, run_name="__main__")
"""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["OMP_NUM_THREADS"] = "1"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd="/", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert is_checkpoint(tmp_path / "ck")



def test_a_solid_with_fewer_anchors_trains_on_its_own(tmp_path):
    """A solid too small or thin for N_a anchors has fewer (its ground truth too): the model takes the largest
    count, the short object's targets are padded and masked, so what the head says past its anchors costs nothing;
    the same counts are refused while the dataset's card says its ground truth is mixed (a rebuild under way)."""
    from unipixie.core.model.network import UniPixieModel
    from unipixie.core.model.objective import SamplingSettings, TrainingObjective, make_draws
    from unipixie.training.train import Collate, build_config

    root = tmp_path / "data"
    make_dataset(root, 3, resolution=8, feature_dim=8, anchors=6, seed=2)
    files = list_samples(root)
    short = TrainingSample.load(files[0])
    short.spring.stiffness_min, short.spring.stiffness_max = short.spring.stiffness_min[:4], short.spring.stiffness_max[:4]
    short.save(files[0])
    cfg = build_config(TrainSettings(data=str(root), out="", **TINY), TrainingSample.load(files[-1]), files)
    assert cfg.spring_anchors == 6
    samples = [TrainingSample.load(f) for f in files]
    batch = Collate(cfg)([(s, i, s.object_id) for i, s in enumerate(samples)])
    assert batch.spring_mask[0].tolist() == [1, 1, 1, 1, 0, 0, 1] and bool(batch.spring_mask[1:].all())
    torch.manual_seed(0)
    objective = TrainingObjective(UniPixieModel(cfg)).eval()
    draws = make_draws(batch, cfg.spring_dim, False, SamplingSettings(), "cpu")
    with torch.no_grad():
        base = objective(batch, draws)["spring_stiffness"]
        batch.spring_lo[0, 4:6] += 5.0  # what lies past the short object's anchors is no target
        batch.spring_hi[0, 4:6] -= 5.0
        assert torch.equal(objective(batch, draws)["spring_stiffness"], base)
        batch.spring_lo[0, 3] += 5.0  # its own anchors are
        assert not torch.equal(objective(batch, draws)["spring_stiffness"], base)
    out = tmp_path / "ck"
    assert main(["train", "--data", str(root), "--out", str(out), "--steps", "2", "--batch", "3", "--preset", "tiny",
                 "--device", "cpu"]) == 0
    assert json.loads((out / "config.json").read_text())["config"]["spring_anchors"] == 6
    # while a ground-truth rebuild is under way the short counts may be another network's: refused by name
    (root / "dataset.json").write_text(json.dumps({"ground_truth_settings": [{"settings": None, "objects": 2},
                                                                             {"settings": {"spring_anchors": 4},
                                                                              "objects": 1}]}))
    with pytest.raises(UserError, match="the model expects 6 spring anchors, 1 with 4"):
        train(TrainSettings(data=str(root), out=str(tmp_path / "ck2"), steps=1, **TINY))
    # more anchors than the model has is refused whatever the card says
    (root / "dataset.json").unlink()
    longer = TrainingSample.load(files[1])
    longer.spring.stiffness_min = np.concatenate([longer.spring.stiffness_min, longer.spring.stiffness_min[:2]])
    longer.spring.stiffness_max = np.concatenate([longer.spring.stiffness_max, longer.spring.stiffness_max[:2]])
    longer.save(files[1])
    from unipixie.training.train import check_spring_anchors, spring_anchor_counts

    with pytest.raises(UserError, match="the model expects 6 spring anchors, 1 with 8"):
        check_spring_anchors(spring_anchor_counts(files), 6, root)
    assert main(["train", "--data", str(root), "--out", str(out), "--steps", "3", "--preset", "tiny", "--resume",
                 "--device", "cpu"]) == 2  # the data now asks for a model of 8
