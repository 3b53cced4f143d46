"""The fault matrix's harness (tests/fault_matrix/run_matrix.py) on a few cases: it runs real subprocesses, passes
refusals that are right, and fails the outcomes it exists to catch (a wrong exit status, a damaged input, a partial
output)."""

from __future__ import annotations

import importlib.util
import json
import os
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


@pytest.fixture(scope="module")
def matrix():
    spec = importlib.util.spec_from_file_location("run_matrix", HERE / "fault_matrix" / "run_matrix.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up while the file runs
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def fixtures(matrix, tmp_path_factory):
    root = tmp_path_factory.mktemp("fm")
    env = {**os.environ, "PYTHONPATH": os.environ.get("PYTHONPATH") or str(matrix.REPO.parent),
           "UNIPIXIE_CACHE_DIR": str(root / "cache"), "PYTHONUNBUFFERED": "1"}
    env.pop("UNIPIXIE_TRACEBACK", None)
    fx = root / "fixtures"
    matrix.make_fixtures(fx, env, blend=False)
    return root, fx, env


def test_the_matrix_is_broad(matrix):
    cases = matrix.build_cases()
    assert len(cases) >= 200
    commands = {c.argv[0] if c.argv and c.argv[0] != "--cache-dir" else c.argv[2] if c.argv else "" for c in cases}
    assert {"bake", "predict", "features", "diagnose", "measure", "dataset", "evaluate", "train", "weights", "doctor",
            "bench", "demo", "build-extension"} <= commands
    kinds = {c.kind for c in cases}
    assert {"corrupt_file", "malicious_file", "impossible_value", "wrong_type", "full_disk", "read_only",
            "symlinked_output", "ctrl_c", "concurrent", "contradictory_measurement", "milliseconds",
            "absurd_frames", "reinterpretation", "false_verdict"} <= kinds


def test_right_refusals_pass(matrix, fixtures, tmp_path):
    root, fx, env = fixtures
    wanted = {"synth.points=0", "show.truncated", "cli.unknown_command", "convert.onto_input_via_symlink",
              "csv.id_fractional"}
    cases = [c for c in matrix.build_cases() if c.id in wanted]
    assert len(cases) == len(wanted)
    for case in cases:
        r = matrix.run_case(case, tmp_path, fx, env, fs_ok=False)
        assert r["verdict"] == "pass", r


def test_the_harness_catches_what_it_is_for(matrix, fixtures, tmp_path):
    root, fx, env = fixtures
    Case = matrix.Case
    # a refusal where success was expected: the exit status is wrong
    r = matrix.run_case(Case("x.exit", "t", ["measure", "show", "{d}/nope.npz"], expect=matrix.OK), tmp_path, fx, env, False)
    assert r["problems"] == ["exit_code"] and r["observed"]["exit"] == 2
    # an existing file the case did not declare as an output is replaced: reported as a damaged input
    r = matrix.run_case(Case("x.input", "t", ["measure", "convert", "{d}/m.npz", "{d}/o.csv", "--force"], expect=matrix.OK,
                             files={"m.npz": "@m.npz", "o.csv": "old"}), tmp_path, fx, env, False)
    assert "input_changed" in r["problems"]
    # an output present after a refusal, and an unreadable one after success: a stand-in command that writes a cut-off
    # archive under the final name, then exits with the given status
    cut = (fx / "m.npz").read_bytes()[:300]
    for status, expect in ((2, matrix.BAD), (0, matrix.OK)):
        script = f"import sys; open(sys.argv[1], 'wb').write({cut!r}); sys.exit({status})"
        fake = lambda *argv, script=script: [sys.executable, "-c", script, *argv]  # noqa: E731
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(matrix, "_cli", fake)
            r = matrix.run_case(Case(f"x.partial{status}", "t", ["{d}/o.npz"], expect=expect, outputs=["o.npz"]),
                                tmp_path, fx, env, False)
        assert r["problems"] == ["partial_output"], r
    # a success where a refusal was expected: only the exit status is wrong (its output reads well)
    r = matrix.run_case(Case("x.both", "t", ["measure", "convert", "{d}/m.npz", "{d}/o.csv"], expect=matrix.BAD,
                             files={"m.npz": "@m.npz"}, outputs=["o.csv"]), tmp_path, fx, env, False)
    assert r["problems"] == ["exit_code"] and r["observed"]["exit"] == 0
    assert matrix.readable(_write(tmp_path / "cut.npz", (fx / "m.npz").read_bytes()[:300])) is not None
    assert matrix.readable(_write(tmp_path / "cut.json", b'{"a": ')) is not None
    assert matrix.readable(fx / "m.npz") is None
    # a false claim: the check's finding makes the verdict
    r = matrix.run_case(Case("x.claim", "t", ["measure", "show", "{d}/m.npz"], expect=matrix.OK, files={"m.npz": "@m.npz"},
                             check=matrix.says("the model explains")), tmp_path, fx, env, False)
    assert r["problems"] == ["false_verdict"]
    # the results file follows the benchmarks format
    out = tmp_path / "fm.json"
    assert matrix.main(["--ids", "cli.unknown_command", "--out", str(out), "--work", str(tmp_path / "w"), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "fault_matrix" and doc["results"][0]["metric"] == "cases_failed"
    assert doc["results"][0]["value"] == 0 and doc["cases"][0]["verdict"] == "pass"


def _write(p: Path, data: bytes) -> Path:
    p.write_bytes(data)
    return p
