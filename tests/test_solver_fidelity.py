"""The solver floors the panel states are the bake-default rows of benchmarks/fidelity.json."""

from __future__ import annotations

import json

import pytest

from unipixie.core import solver_fidelity as sf
from unipixie.solvers.registry import SOLVER_NAMES


def _default_rows(repo_root):
    rows = json.loads((repo_root / "benchmarks" / "fidelity.json").read_text())["results"]
    return [r for r in rows if r.get("default") and r.get("solver") and r.get("error") is not None
            and r["metric"] in sf.METRIC_WORDS]


def test_every_departure_above_the_bar_is_stated_with_its_measured_worst_value(repo_root):
    worst = {}
    for r in _default_rows(repo_root):
        key = (r["solver"], r["metric"])
        if abs(r["error"]) > abs(worst.get(key, (0.0, ()))[0]):
            worst[key] = (r["error"], r["scene"])
    measured = {k: v for k, v in worst.items() if abs(v[0]) > sf.STATED_ABOVE}
    stated = {(solver, d.metric): d for solver, ds in sf.MEASURED_FLOORS.items() for d in ds}
    assert set(stated) == set(measured), (sorted(set(stated) ^ set(measured)))
    for key, (error, scene) in measured.items():
        assert stated[key].error == pytest.approx(error, abs=0.0015), key
        assert scene in stated[key].scenes, key


def test_floor_lines_name_the_solver_and_sort_by_size():
    lines = sf.floor_lines("lbs")
    assert lines[0].startswith("LBS at its bake defaults")
    assert lines[1] == "static bending sag -19 %"
    stated = lines[1:1 + len(sf.MEASURED_FLOORS["lbs"])]
    sizes = [abs(float(line.rsplit(" ", 2)[-2])) for line in stated]
    assert sizes == sorted(sizes, reverse=True)
    assert lines[1 + len(stated):] == ["refined, 40 handles and 16,000 mass samples (no LBS head):",
                                       "sag -3 %, frequency +2 %, contact +0 %"]
    assert len(sf.floor_lines("spring_mass")) == 1 + len(sf.MEASURED_FLOORS["spring_mass"])  # no refinement stated
    assert sf.floor_lines("no_such_solver") == []


def test_every_refinement_stated_is_the_benchmark_s_worst_value_at_that_level(repo_root):
    """REFINED: at its ladder level, each metric the solver's floors state, with the worst measured error over its
    scenes in benchmarks/fidelity.json (the newest row of each scene)."""
    rows = json.loads((repo_root / "benchmarks" / "fidelity.json").read_text())["results"]
    for solver, refined in sf.REFINED.items():
        assert {d.metric for d in refined.departures} == {d.metric for d in sf.MEASURED_FLOORS[solver]}, solver
        for d in refined.departures:
            newest = {r["scene"]: r["error"] for r in rows if r.get("solver") == solver and r.get("metric") == d.metric
                      and r.get("resolution") == refined.resolution and r.get("error") is not None}
            assert set(newest) == set(d.scenes), (solver, d.metric, sorted(newest))
            worst = max(newest.values(), key=abs)
            assert d.error == pytest.approx(worst, abs=0.0015), (solver, d.metric, worst)


def test_refinement_series_split_the_lbs_ladder_into_cubature_and_time_step_each_coarse_to_fine():
    """LBS's ladder varies two settings, and its handle count at a finer sampling; the figure draws one series per
    setting, the bake default in the first two at its own value (docs/figures/fidelity_drop.png: the step series
    5 → 2.5 → 1 → 0.5 ms)."""
    from unipixie.core.benchmarks.fidelity import LADDERS, refinement_series

    rows = [{"resolution": label, "settings": settings, "default": default, "value": float(i)}
            for i, (label, settings, default, _level) in enumerate(LADDERS["drop"]["lbs"])]
    series = dict(refinement_series("lbs", rows))
    assert list(series) == ["cubature_points", "max_dt", "handles"]
    assert [r["resolution"] for r in series["cubature_points"]] == [
        "200 cubature points", "500 cubature points", "1500 cubature points"]
    assert [r["resolution"] for r in series["max_dt"]] == [
        "500 points, 5 ms steps", "500 cubature points", "500 points, 1 ms steps", "500 points, 0.5 ms steps"]
    assert [r["settings"].get("handles", 10) for r in series["handles"]] == [10, 20, 40]
    one = refinement_series("spring_mass", [{"settings": s, "resolution": label}
                                            for label, s, _d, _l in LADDERS["drop"]["spring_mass"]])
    assert len(one) == 1 and [r["resolution"] for r in one[0][1]] == ["512 anchors", "2048 anchors", "8192 anchors"]


def test_the_lbs_handle_ladder_is_its_own_series_ordered_by_handles():
    """The bars' LBS ladder adds runs that set the handles and a finer sampling at once: they form one more series,
    named by the setting that varies among them (handles, the first at the default 10), coarse → fine."""
    from unipixie.core.benchmarks.fidelity import LADDERS, refinement_series

    ladder = LADDERS["cantilever_z"]["lbs"]
    rows = [{"resolution": label, "settings": settings, "default": default, "value": float(i)}
            for i, (label, settings, default, _level) in enumerate(ladder)][::-1]
    series = dict(refinement_series("lbs", rows))
    assert sorted(series) == ["cubature_points", "handles", "max_dt"] and list(series)[-1] == "handles"
    assert [r["settings"].get("handles", 10) for r in series["handles"]] == [10, 20, 40]
    assert all(r["settings"]["cubature_points"] == 3000 for r in series["handles"])
    assert [r["resolution"] for r in series["cubature_points"]] == [
        "200 cubature points", "500 cubature points", "1500 cubature points"]


def test_every_drift_above_one_percent_is_stated_with_its_measured_value(repo_root):
    rows = json.loads((repo_root / "benchmarks" / "fidelity.json").read_text())["results"]
    worst = {}
    for r in rows:
        if r.get("default") and r.get("metric") == "mean_drift_per_period" and "relative_to_static_reference" in r:
            rel = r["relative_to_static_reference"]
            if abs(rel) > abs(worst.get(r["solver"], (None, 0.0))[1]):
                worst[r["solver"]] = (r["scene"], rel)
    measured = {s: v for s, v in worst.items() if abs(v[1]) > 0.01}
    assert set(sf.DRIFTS) == set(measured)
    for solver, (scene, rel) in measured.items():
        assert scene in sf.DRIFTS[solver].scenes and sf.DRIFTS[solver].error == pytest.approx(rel, abs=0.0015), solver
    for solver in SOLVER_NAMES:  # the panel's drift line exactly where a drift is stated
        assert any("sinks" in line for line in sf.floor_lines(solver)) == (solver in sf.DRIFTS), solver


def test_mean_drift_per_period_reads_the_drift_not_the_swing():
    """The drift of the mean a bar swings about, over windows of the *measured* period: a swing alone reads none,
    a sinking mean reads its rate; windows of another period (an LBS bar's 7.19 Hz read with Euler–Bernoulli's
    6.54 Hz) would read the swing itself as a drift."""
    import numpy as np

    from unipixie.core.benchmarks._scenes import mean_drift_per_period

    t = np.linspace(0.0, 1.0, 1001)
    f = 7.19
    swing = -9e-3 + 7e-3 * np.cos(2 * np.pi * f * t)
    assert abs(mean_drift_per_period(t, swing, f)) < 1e-5  # the windows' edges fall between 1 ms samples
    assert mean_drift_per_period(t, swing - 2e-4 * f * t, f) == pytest.approx(-2e-4, rel=0.05)
    assert abs(mean_drift_per_period(t, swing, 6.539)) > 1e-4
    assert np.isnan(mean_drift_per_period(t[:200], swing[:200], f))


def test_cantilever_static_sag_is_measured_settled_under_drag():
    """The bars' static sag comes from a companion run settled under a mass-proportional drag (which does not move
    the equilibrium); the undamped release gives the frequency and the mean it swings about."""
    import numpy as np
    from types import SimpleNamespace

    from unipixie.core.benchmarks import _scenes

    sc = _scenes.scene("cantilever_z")
    settle = sc.settle
    assert [e.name for e in settle.effects] == ["linear_drag"]
    assert settle.effects[0].values["c"] == _scenes.SETTLE_DRAG
    assert settle.frame_times[-1] == pytest.approx(_scenes.SETTLE_TIME)
    assert settle.reference["tip_sag"][0] == sc.reference["oscillation_mean"][0]
    assert "tip_sag" not in sc.reference and not settle.cross_solver
    # a tip that rings down to 8.9 mm below its rest position: the static sag is where it came to rest
    t = settle.frame_times
    tip0 = sc.body.tracked_points[0]
    z = tip0[2] - 8.9e-3 * (1.0 - np.exp(-20.0 * t) * np.cos(2 * np.pi * 6.5 * t))
    positions = np.repeat(sc.body.tracked_points[None], len(t), 0)
    positions[:, 0, 2] = z
    measured = settle.measure(SimpleNamespace(times=t, positions=positions))
    assert measured["tip_sag"] == pytest.approx(8.9e-3, rel=1e-4)
    assert measured["settle_residual"] < 1e-7
    # the undamped release of a bar stiffer than Euler–Bernoulli's (LBS's 7.19 Hz): its own period, no drift
    t = sc.frame_times
    positions = np.repeat(sc.body.tracked_points[None], len(t), 0)
    positions[:, 0, 2] = tip0[2] - 7.3e-3 * (1.0 - np.cos(2 * np.pi * 7.19 * t))
    swung = sc.measure(SimpleNamespace(times=t, positions=positions))
    assert swung["oscillation_mean"] == pytest.approx(7.3e-3, rel=1e-3)
    assert swung["frequency"] == pytest.approx(7.19, rel=1e-3)
    assert abs(swung["mean_drift_per_period"]) < 1e-5


def test_ladder_defaults_runs_each_solvers_bake_default_only_and_compares_them(monkeypatch):
    """``bench fidelity --ladder defaults``: one run per solver, at its bake default, and the cross-solver rows of
    those runs (what the GPU re-measure of 2026-11-28 used); ``fast`` runs the fast levels."""
    import argparse

    import numpy as np

    from unipixie.core.benchmarks import fidelity

    ran = []

    def fake_run(scene, solver, settings, device):
        ran.append((solver, dict(settings)))
        offset = {"mpm": 0.0, "spring_mass": 0.001, "lbs": 0.002}[solver]
        return {"stopping_distance": 0.38}, type("T", (), {"positions": np.full((3, 2, 3), offset)})(), 0.0

    monkeypatch.setattr(fidelity, "run_scene", fake_run)
    args = argparse.Namespace(device="cpu", scenes="slide", solvers="mpm,spring_mass,lbs", ladder="defaults",
                              referee=None, trajectories=None, plots=None)
    rows = fidelity.run(args)
    defaults = {s: [st for _l, st, d, _v in fidelity.LADDERS["slide"][s] if d] for s in ("mpm", "spring_mass", "lbs")}
    assert sorted(ran, key=str) == sorted([(s, st[0]) for s, st in defaults.items()], key=str)
    cross = {tuple(r["solvers"]): r["rmse_m"] for r in rows if r.get("metric") == "trajectory_rmse_over_size"}
    assert cross[("lbs", "mpm")] == pytest.approx(0.002 * np.sqrt(3)) and len(cross) == 3
    ran.clear()
    fidelity.run(argparse.Namespace(**{**vars(args), "ladder": "fast"}))
    assert len(ran) == sum(1 for s in defaults for *_x, level in fidelity.LADDERS["slide"][s] if level == "fast")
