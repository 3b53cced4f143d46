"""MPM solver, GPU code paths, checked without a GPU.

* The CUDA kernels (both Warp modules, with the native warp-level and vector-reduction snippets) compile for
  sm_90 with Warp's NVRTC, through ptxas (cubin), so a typo in CUDA-only code cannot reach a GPU run.
* The warp-aggregation snippets' logic runs on the CPU with every lane a thread (tests/warp_emulation.cpp).
* The GPU-tuned kernels, the captured substep graphs and the re-sorting within a chunk give the plain CPU
  kernels' results (bitwise; the native parts fall back to plain atomics and loads on the CPU).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from unipixie.core.errors import UserError
from unipixie.solvers import effects as fx
from unipixie.solvers import mpm
from unipixie.solvers.body import Body
from unipixie.solvers.material_sampling import HomogeneousMaterial
from unipixie.solvers.scenario import Scenario

G = 9.81
TESTS = Path(__file__).resolve().parent


def _lattice(n, spacing, origin):
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return np.asarray(origin) + (idx + 0.5) * spacing


def test_cuda_kernels_compile_for_sm90(tmp_path):
    """Both kernel modules compile to sm_90 cubins (NVRTC + ptxas); skipped where Warp has no NVRTC."""
    from unipixie.solvers.warp_runtime import init_warp

    wp = init_warp()
    if 90 not in wp.get_cuda_supported_archs():
        pytest.skip("this Warp cannot compile CUDA code for sm_90 (no NVRTC)")
    paths = mpm.compile_cuda_kernels(90, module_dir=tmp_path)
    assert len(paths) == 2
    for path in paths:
        assert path.suffix == ".cubin" and path.stat().st_size > 10_000, path
    source = next(tmp_path.glob("*mpm_kernels_cuda*.cu")).read_text()
    for construct in ("__match_any_sync", "__shfl_sync", "red.global.add.v4.f32", "__ldg"):
        assert construct in source  # the native snippets are part of the compiled module
    with pytest.raises(UserError, match="sm_12"):
        mpm.compile_cuda_kernels(12, module_dir=tmp_path)


def test_warp_aggregation_snippets_emulated(tmp_path):
    """The warp-grouping and aggregated-scatter snippets, run with one thread per lane: every node gets the
    exact sum of its group's contributions in one reduction (random groups, sorted runs, padding lanes)."""
    compiler = shutil.which("g++")
    if compiler is None:
        pytest.skip("no g++ to build the warp emulation")
    from unipixie.solvers import mpm_kernels_cuda as kc

    scatter = kc.SCATTER_WARP_SNIPPET.replace(kc.VECTOR_RED_SNIPPET, "    red4(grid, index, a, b, c, d);\n")
    assert scatter != kc.SCATTER_WARP_SNIPPET
    (tmp_path / "snippets.inc").write_text(
        "static vec4i warp_groups(bool active, int key) {\n" + kc.WARP_GROUPS_SNIPPET + "\n}\n"
        "static void scatter_warp(Grid& grid, int index, vec4f value, vec4i plan) {\n" + scatter + "\n}\n")
    exe = tmp_path / "warp_emulation"
    build = subprocess.run([compiler, "-std=c++20", "-O1", "-pthread", f"-I{tmp_path}",
                            str(TESTS / "warp_emulation.cpp"), "-o", str(exe)], capture_output=True, text=True)
    if build.returncode != 0 and "barrier" in build.stderr and "error" in build.stderr and "snippets" not in build.stderr:
        pytest.skip(f"g++ lacks C++20 <barrier>: {build.stderr[:200]}")
    assert build.returncode == 0, build.stderr
    run = subprocess.run([str(exe), "120"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.startswith("ok")


def test_gpu_tuned_kernels_match_plain_kernels_on_cpu():
    """Warp-aggregated and vector scatters, split G2P, graphs of substeps and other block sizes give bitwise the
    plain kernels' trajectories (batched: plasticity = general law, stiffness region, clamp, tracked points);
    re-sorting every few substeps changes only the summation order; the per-kernel profile adds up."""
    points = _lattice(6, 0.005, (0.0, 0.0, 0.01))
    points = points[np.random.default_rng(3).permutation(len(points))]  # unsorted, as from a point cloud
    body = Body(points=points, point_volume=0.005 ** 3, tracked_points=points[::5])
    scenario = Scenario(gravity=[0, 0, -G], ground_height=0.0, initial_velocity=[0.3, 0, 0],
                        initial_angular_velocity=[0, 0, 2.0], pinned_box=[[-1, -1, -1], [0.006, 1, 1]])
    sim = mpm.prepare(body, HomogeneousMaterial(1e5, 0.3, 1000.0, "jelly"), scenario, np.linspace(0.0, 0.06, 4))
    envs = [[], [fx.make("plasticity", yield_stress=2e3)],
            [fx.make("stiffness_region", factor=2.0, region={"box": [[-1, -1, -1], [0.015, 1, 1]]}),
             fx.make("ground_friction", mu=0.5)]]
    plain = sim.run_batch(envs)
    assert sim._tuning().scatter == "atomic" and sim._tuning().graph_substeps == 0  # CPU defaults
    for tuning in ({"p2g_scatter": "warp", "split_g2p": True, "graph_substeps": 4, "block_dim": 64},
                   {"p2g_scatter": "vector", "graph_substeps": 3}):
        sim.settings = mpm.MPMSettings(**tuning)
        tuned = sim.run_batch(envs)
        for a, b in zip(plain, tuned):
            np.testing.assert_array_equal(a.positions, b.positions)
            assert a.meta["substeps"] == b.meta["substeps"]
    sim.settings = mpm.MPMSettings(p2g_scatter="warp", sort_interval=7)
    resorted = sim.run_batch(envs)
    for a, b in zip(plain, resorted):
        np.testing.assert_allclose(a.positions, b.positions, atol=1e-6)
    sim.settings = mpm.MPMSettings(p2g_scatter="warp", split_g2p=True)
    profile = sim.profile([])
    assert {"p2g", "grid_update", "g2p", "g2p_tracked", "sort", "frame_stats"} <= set(profile)
    assert profile["substeps"] == plain[0].meta["substeps_total"]
    kernels = sum(v for k, v in profile.items() if k not in ("wall", "substeps", "particle_substeps"))
    assert 0 < kernels <= profile["wall"]


@pytest.mark.parametrize("settings, message", [
    ({"p2g_scatter": "shared"}, "p2g_scatter"),
    ({"block_dim": 100}, "block_dim"),
    ({"graph_substeps": -1}, "graph_substeps"),
    ({"sort_interval": "often"}, "sort_interval"),
])
def test_bad_gpu_settings(settings, message):
    with pytest.raises(UserError, match=message):
        mpm.MPMSettings.from_any(settings)
