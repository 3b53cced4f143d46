"""The checks a round's leader must pass (core/diagnosis/checks.py): when the leader fails one, the next
significant candidate leads and must pass the same checks.  Numerical dissipation that imitates one damping-like
effect imitates the others as well (MPM on a clamped bar with hidden material damping named linear drag, which was
never re-checked at half the step, after material damping failed that check)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from unipixie.core.diagnosis import checks


def _cand(name, significant=True):
    return SimpleNamespace(name=name, significant=significant, reasons=[], holdout=None, dt_check=None)


def _run(monkeypatch, cands, half_step_ok: dict, parallel=True):
    """Run check_leading with the refits replaced: the held-out check passes, the half-step check's verdict per
    effect is ``half_step_ok[name]``.  Returns the list of (effect, reference refit given) half-step checks made."""
    made = []

    def holdout_jobs(P, ref, leading, sigma, progress):
        return [lambda: 0.0], lambda results: [{"ok": True, "verdict": "ok"} for _ in leading]

    def half_step_jobs(P, ref, c, sigma, sim2, lm_iterations, progress, reference_fit=None, reference_store=None):
        made.append((c.name, reference_fit))

        def finish(results):
            if reference_store is not None:
                reference_store["fit"] = reference_fit or "reference at half the step"
            ok = half_step_ok[c.name]
            return {"ok": ok, "verdict": "still needed" if ok else "numerical dissipation"}
        return [lambda: None], finish

    monkeypatch.setattr(checks, "_holdout_jobs", holdout_jobs)
    monkeypatch.setattr(checks, "_half_step_jobs", half_step_jobs)
    P = SimpleNamespace(parallel=parallel, side_by_side=lambda jobs: [j() for j in jobs])
    checks.check_leading(P, None, cands, 0.001, holdout=True, dt_check=True, half_step_sim=lambda: "sim",
                         lm_iterations=6, progress=SimpleNamespace(set_status=lambda text: None), round_no=1)
    return made


def test_a_damping_like_effect_that_takes_the_lead_is_re_checked_at_half_the_step(monkeypatch):
    md, ld, qd, wind = _cand("material_damping"), _cand("linear_drag"), _cand("quadratic_drag"), _cand("wind", False)
    made = _run(monkeypatch, [md, ld, qd, wind], {"material_damping": False, "linear_drag": False,
                                                  "quadratic_drag": False})
    assert [m[0] for m in made] == ["material_damping", "linear_drag", "quadratic_drag"]
    assert not any(c.significant for c in (md, ld, qd))  # each failed its own re-check: nothing is named
    assert ld.reasons == ["numerical dissipation"] and ld.dt_check["ok"] is False
    # the reference refitted at half the step once, then shared by the later re-checks
    assert made[0][1] is None and made[1][1] == made[2][1] == "reference at half the step"


def test_the_next_leader_that_passes_is_kept(monkeypatch):
    for parallel in (True, False):
        md, ld, wind = _cand("material_damping"), _cand("linear_drag"), _cand("wind")
        made = _run(monkeypatch, [md, ld, wind], {"material_damping": False, "linear_drag": True}, parallel)
        assert [m[0] for m in made] == ["material_damping", "linear_drag"]
        assert not md.significant and ld.significant and ld.dt_check["ok"] and wind.significant
        # a leader that is not damping-like needs no half-step check
        md, wind, ld = _cand("material_damping"), _cand("wind"), _cand("linear_drag")
        made = _run(monkeypatch, [md, wind, ld], {"material_damping": False}, parallel)
        assert [m[0] for m in made] == ["material_damping"] and wind.significant and ld.dt_check is None


def test_a_leader_beyond_the_first_three_gets_its_held_out_check(monkeypatch):
    cands = [_cand(n) for n in ("material_damping", "linear_drag", "quadratic_drag", "wind")]
    _run(monkeypatch, cands, {"material_damping": False, "linear_drag": False, "quadratic_drag": False})
    assert cands[3].significant and cands[3].holdout == {"ok": True, "verdict": "ok"}


def test_a_failed_half_step_check_says_what_it_measured():
    """The verdict gives the share removed at half the step and the parameter at both steps (MPM on the clamped
    bar: η 374 → 139 Pa·s, its dissipation grows with the number of steps)."""
    import numpy as np

    from unipixie.solvers import effects as fx

    fitted, half = fx.make("material_damping", eta=374.0), fx.make("material_damping", eta=139.0)
    c = SimpleNamespace(name="material_damping", threshold=15.0, effect=fitted, fit=SimpleNamespace(u=np.zeros(1)),
                        parametrisation=SimpleNamespace(realise=lambda u: (1.0, [half])))
    n, sigma = 1000, 0.001
    P = SimpleNamespace(sse=lambda r: float(np.sum(np.square(r))), n_obs=n)
    noise = np.full(3 * n, sigma)
    reference = SimpleNamespace(residual=noise * 2.0)  # 3σ² above the noise per coordinate
    jobs, finish = checks._half_step_jobs(P, None, c, sigma, "half-step simulation", 6, None,
                                          reference_fit=reference)
    assert len(jobs) == 1  # the reference's refit is given: only the candidate is refitted
    check = finish([SimpleNamespace(residual=noise * 1.8, u=None)])  # removes (4 − 3.24) / 3 = 25 % of the excess
    assert check["ok"] is False and check["params_half_step"] == {"eta": 139.0}
    assert "removes 25 %" in check["verdict"] and "eta=374 → eta=139" in check["verdict"]
    check = finish([SimpleNamespace(residual=noise * 1.1, u=None)])  # 93 %
    assert check["ok"] is True and check["verdict"] == "the effect is still needed at half the time step"


def test_noise_thresholds_are_the_chi_square_and_chi_bar_square_quantiles():
    """Λ's threshold at the false-alarm level: the χ² quantile for unbounded parameters (χ²₁ at 10⁻³: 10.83;
    χ²₂: 13.82), half of it in the tail for one parameter at a bound (½ χ²₀ + ½ χ²₁: P(χ²₁ > c) = 2·10⁻³ at
    c = 9.55), and Bonferroni-split over tests (10⁻³ / 10 for χ²₁: 15.14)."""
    from unipixie.core.diagnosis import significance as sig

    assert sig.lr_threshold(1, 0) == pytest.approx(10.828, abs=2e-3)
    assert sig.lr_threshold(2, 0) == pytest.approx(13.816, abs=2e-3)
    assert sig.lr_threshold(0, 1) == pytest.approx(9.550, abs=2e-3)
    assert sig.lr_threshold(1, 0, tests=10) == pytest.approx(15.137, abs=2e-3)
    assert sig.lr_threshold(0, 0) == float("inf")
    assert sig.chibar_tail(0.0, 1, 0) == 1.0
