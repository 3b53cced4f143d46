"""The demo from an empty cache compiles every solver's Warp kernels (issue 21): none of them is compiled with its
adjoint, which nothing uses (no ``wp.Tape`` differentiates through a solver) and which cost most of the compile
time (LBS 20 s -> 8 s of CPU, spring-mass 6.7 s -> 4.5 s, MPM's 135 s -> 19 s, on the 2-core machine)."""

from __future__ import annotations

import importlib
import pkgutil

import pytest


def _kernel_modules():
    wp = pytest.importorskip("warp")
    from unipixie import solvers

    found = {}
    for info in pkgutil.iter_modules(solvers.__path__):
        module = importlib.import_module(f"{solvers.__name__}.{info.name}")
        if any(isinstance(v, wp.Kernel) for v in vars(module).values()):
            found[module.__name__] = module
    return wp, found


def test_every_solver_kernel_module_compiles_forward_only():
    wp, modules = _kernel_modules()
    assert {"unipixie.solvers.lbs_kernels", "unipixie.solvers.spring_mass_kernels",
            "unipixie.solvers.mpm_kernels"} <= set(modules)
    with_adjoint = [name for name in modules if wp.get_module(name).options.get("enable_backward", True)]
    assert with_adjoint == [], f"compiled with their adjoints (slow on an empty kernel cache): {with_adjoint}"


def test_the_demo_records_wall_and_cpu_seconds_per_stage():
    """summary.json's stage_cpu_seconds: the CPU the whole process spent in each stage (all threads), beside the
    wall seconds, so a run on a busy machine still says what the demo costs."""
    import threading
    import time

    from unipixie.core.demo import _Stages
    from unipixie.core.progress import silent

    stages = _Stages(silent(), lambda text: None, {"compute": 1, "wait": 1})

    def burn(seconds):
        end = time.thread_time() + seconds
        while time.thread_time() < end:
            pass

    stages.sub("compute", "computing in a worker thread")
    worker = threading.Thread(target=burn, args=(0.3,))
    worker.start()
    worker.join()
    stages.done()
    stages.sub("wait", "waiting")
    time.sleep(0.3)
    stages.done()
    assert stages.cpu_seconds["compute"] >= 0.25            # the worker thread's CPU counts
    assert stages.cpu_seconds["wait"] < 0.15 and stages.seconds["wait"] >= 0.3


def test_the_kernel_warm_up_runs_tiny_simulations_of_every_solver(monkeypatch):
    """The demo's background warm-up compiles each solver's kernel module with a run small enough to cost next to
    nothing beyond compiling (at the bake defaults its MPM sphere alone was 120 000 particles, 15 s of CPU)."""
    wp, _ = _kernel_modules()
    from unipixie.core.demo import KernelWarmUp
    from unipixie.solvers import api

    runs = {}
    real = api.simulate

    def recording(solver, *args, **kwargs):
        traj = real(solver, *args, **kwargs)
        runs[solver] = traj.meta
        return traj

    monkeypatch.setattr(api, "simulate", recording)
    warm_up = KernelWarmUp("cpu").start()
    warm_up.wait()
    assert warm_up.error == "" and set(warm_up.seconds) == set(KernelWarmUp.SOLVERS) == set(runs)
    for name in ("mpm_kernels", "spring_mass_kernels", "lbs_kernels"):
        assert wp.get_module(f"unipixie.solvers.{name}").execs, f"{name} was not compiled"
    assert runs["mpm"]["particles"] * runs["mpm"]["substeps_total"] < 1e6
    assert runs["spring_mass"]["anchors"] <= 64
