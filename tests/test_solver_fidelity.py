"""The solver floors the panel states are the bake-default rows of benchmarks/fidelity.json."""

from __future__ import annotations

import json

import pytest

from unipixie.core import solver_fidelity as sf


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
    sizes = [abs(float(line.rsplit(" ", 2)[-2])) for line in lines[1:]]
    assert sizes == sorted(sizes, reverse=True) and len(lines) == 1 + len(sf.MEASURED_FLOORS["lbs"])
    assert sf.floor_lines("no_such_solver") == []


def test_refinement_series_split_the_lbs_ladder_into_cubature_and_time_step_each_coarse_to_fine():
    """LBS's ladder varies two settings; the figure draws one series per setting, the bake default in both at its
    own value (docs/figures/fidelity_drop.png: the step series 5 → 2.5 → 1 → 0.5 ms)."""
    from unipixie.core.benchmarks.fidelity import LADDERS, refinement_series

    rows = [{"resolution": label, "settings": settings, "default": default, "value": float(i)}
            for i, (label, settings, default, _level) in enumerate(LADDERS["drop"]["lbs"])]
    series = dict(refinement_series("lbs", rows))
    assert list(series) == ["cubature_points", "max_dt"]
    assert [r["resolution"] for r in series["cubature_points"]] == [
        "200 cubature points", "500 cubature points", "1500 cubature points"]
    assert [r["resolution"] for r in series["max_dt"]] == [
        "500 points, 5 ms steps", "500 cubature points", "500 points, 1 ms steps", "500 points, 0.5 ms steps"]
    one = refinement_series("spring_mass", [{"settings": s, "resolution": label}
                                            for label, s, _d, _l in LADDERS["drop"]["spring_mass"]])
    assert len(one) == 1 and [r["resolution"] for r in one[0][1]] == ["512 anchors", "2048 anchors", "8192 anchors"]
