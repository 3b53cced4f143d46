"""core/benchmarks/demo_plant.py: the sway and difference metrics (no solver, no Blender) and its input checks."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from unipixie.core.benchmarks import demo_plant as dp
from unipixie.core.errors import UserError


def _swaying_plant(freq=0.9, decay=0.0, lean=(0.03, 0.0), amplitude=0.1, frames=48, fps=24.0):
    """(T, N, 3): a stem of 20 vertices on the z axis whose crown sways along (1, 1)/√2 about a lean."""
    t = np.arange(frames) / fps
    z = np.linspace(0.0, 1.0, 20)
    rest = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    direction = np.array([1.0, 1.0]) / math.sqrt(2.0)
    sway = amplitude * np.exp(-decay * t) * np.sin(2 * math.pi * freq * t)
    horizontal = sway[:, None] * direction + np.asarray(lean) * (1.0 - np.exp(-5.0 * t))[:, None]
    pos = np.repeat(rest[None], frames, axis=0)
    pos[:, :, :2] += horizontal[:, None, :] * (z ** 2)[None, :, None]     # the top moves most
    return pos


def test_crown_sway_reads_the_frequency_the_swing_and_the_lean():
    s = dp.crown_sway(_swaying_plant(freq=0.9), fps=24.0)
    assert s["frequency_hz"] == pytest.approx(0.9, rel=0.03)
    top = (1.0 ** 2 + (18 / 19) ** 2) / 2            # the crown's two highest vertices carry z² of the motion
    assert len(s["swings_m"]) == 4
    assert s["lean_m"] == pytest.approx(0.03 * top, rel=0.15)
    # halves of 0.9 periods each hold a crest and a trough: peak to peak is twice the amplitude
    halves = dp.crown_sway(_swaying_plant(freq=0.9, lean=(0.0, 0.0)), fps=24.0, windows=2)["swings_m"]
    assert halves == pytest.approx([2 * 0.1 * top] * 2, rel=0.03)
    # a damped sway keeps less of its swing in the last quarter; an undamped one keeps it
    damped = dp.crown_sway(_swaying_plant(decay=1.5), fps=24.0)
    assert damped["swings_m"][-1] < 0.2 * damped["swings_m"][0]
    assert s["swings_m"][-1] > 0.8 * s["swings_m"][0]
    # too short a clip to cross three times: no frequency
    assert math.isnan(dp.crown_sway(_swaying_plant(frames=10), fps=24.0)["frequency_hz"])


def test_displacement_rms_compares_displacements_not_positions():
    a = _swaying_plant()
    assert dp.displacement_rms(a, a + 5.0) < 1e-12                      # the same motion elsewhere
    b = a.copy()
    b[1:, :, 0] += 0.02                                                 # 2 cm more along x after frame 1
    assert dp.displacement_rms(a, b) == pytest.approx(0.02)
    with pytest.raises(ValueError, match="cannot be compared"):
        dp.displacement_rms(a, a[:, :5])


def test_levels_and_scene_files_are_checked(tmp_path):
    assert dp._levels("17, 32,default", True) == ["17", "32", "default"]
    with pytest.raises(UserError, match="'default' is not a resolution"):
        dp._levels("2048,default", False)
    with pytest.raises(UserError, match="'1' is not a resolution"):
        dp._levels("1", True)
    with pytest.raises(UserError, match="no such scene file"):
        dp.load_scene(tmp_path / "missing.pkl")
    (tmp_path / "junk.pkl").write_bytes(b"not a pickle")
    with pytest.raises(UserError, match="not a scene file written by --export"):
        dp.load_scene(tmp_path / "junk.pkl")
    (tmp_path / "other.pkl").write_bytes(pickle.dumps({"format": "something else"}))
    with pytest.raises(UserError, match="not a scene file"):
        dp.load_scene(tmp_path / "other.pkl")
    scene = {"format": dp.SCENE_FORMAT, "object": "plant"}
    assert dp.load_scene(dp.save_scene(scene, tmp_path / "s.pkl")) == scene


def test_bench_refuses_cells_without_a_reference(tmp_path):
    from unipixie.cli import main as cli

    assert cli(["bench", "demo_plant", "--scene", str(tmp_path / "none.pkl"), "--cells", "default", "--no-record"]) == 2
