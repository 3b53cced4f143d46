"""The base model of a diagnosis: ground contact fitted with E/ρ (contact_fit.py) and the resolution check
(resolution.py).  Fast unit tests, plus one small end-to-end diagnosis of a drop onto a damped floor."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from unipixie.core.diagnosis import contact_fit, resolution
from unipixie.solvers.lbs import LBSSettings
from unipixie.solvers.mpm import MPMSettings
from unipixie.solvers.spring_mass_settings import SpringMassSettings


def _measurement(lowest: float, ground=0.0):
    rest = np.random.default_rng(0).uniform(0, 0.2, (50, 3))
    pos = np.repeat(rest[None], 5, axis=0)
    pos[..., 2] += lowest - rest[:, 2].min()
    return SimpleNamespace(rest=rest, positions=pos, scenario=SimpleNamespace(ground_height=ground))


def test_touches_ground_only_near_the_ground():
    assert contact_fit.touches_ground(_measurement(0.001), 0.001)
    assert not contact_fit.touches_ground(_measurement(0.05), 0.001)
    assert not contact_fit.touches_ground(_measurement(0.0, ground=None), 0.001)


def test_without_contact_nothing_is_fitted_and_the_candidates_stay():
    names = ["linear_drag", "contact_damping"]
    P = SimpleNamespace(sigma=0.001)  # no attribute a fit would need: it must not be touched
    cf = contact_fit.fit_base_contact(P, _measurement(0.05), None, 1.0, 1.0, 1.0, names, 6, None)
    assert cf.effect is None and not cf.adopted and names == ["linear_drag", "contact_damping"]
    assert not hasattr(P, "base_effects")
    assert cf.to_dict(10) == {"touches_ground": False, "adopted": False, "reason": cf.reason}


def test_ground_effects_are_not_tried_where_the_solid_never_touches_the_ground():
    """Friction and a yielding floor (``Effect.acts_at_ground``) change nothing without contact: not tried, with the
    reason (each fit costs simulations: the referee's damped clamped bar took 214 s with it on this CPU, 189 s without)."""
    from unipixie.core.diagnosis.candidates import not_applicable_effects

    names = ["linear_drag", "ground_friction", "contact_damping", "material_damping"]
    skipped = not_applicable_effects(names, _measurement(0.0, ground=None), 0.001)
    assert skipped == {"ground_friction": "the scenario has no ground", "contact_damping": "the scenario has no ground"}
    skipped = not_applicable_effects(names, _measurement(0.05), 0.001)
    assert set(skipped) == {"ground_friction", "contact_damping"} and "50 mm" in skipped["contact_damping"]
    assert not_applicable_effects(names, _measurement(0.001), 0.001) == {}


def test_contact_scales():
    k, c = contact_fit.contact_scales(2e5, 1000.0, 0.2)
    assert k == pytest.approx(math.pi ** 2 * 2e5 / 0.2)
    assert c == pytest.approx(2 * math.sqrt(k * 1000.0 * 0.2))


@pytest.mark.parametrize("settings, refined", [
    (SpringMassSettings(anchors=96), {"anchors": 192, "safety": 0.35}),
    (MPMSettings(cells_across=12, viscous_cfl=0.2), {"cells_across": 18, "cells_across_thinnest": 0}),  # N given: N
    (MPMSettings(viscous_cfl=0.2), {"cells_across": 48, "cells_across_thinnest": 6}),                 # bake default
    (LBSSettings(), {}),
])
def test_finer_settings_refine_space_and_time(settings, refined):
    fine = resolution.finer_settings(SimpleNamespace(settings=settings))
    for key, value in refined.items():
        assert getattr(fine, key) == pytest.approx(value)
    if isinstance(settings, MPMSettings):
        assert fine.cfl == pytest.approx(0.5 * settings.cfl) and fine.viscous_cfl == pytest.approx(0.1)
    if isinstance(settings, LBSSettings):
        assert fine.cubature_points == 2 * settings.cubature_points
        assert fine.max_dt == pytest.approx(0.5 * settings.max_dt)
    assert resolution.finer_settings(SimpleNamespace(settings=None)) is None


def test_floor_refuses_effects_that_only_imitate_the_discretisation_error():
    """An effect whose change of the trajectory lies along the discretisation error must gain more than it could by
    imitating that error; one whose change is unrelated to it is judged by the noise tests alone."""
    rng = np.random.default_rng(0)
    n = 1000
    delta = 0.002 * rng.normal(size=3 * n)  # finer − coarse, floor ≈ 2 mm · √3
    other = rng.normal(size=3 * n)
    other -= (other @ delta) / (delta @ delta) * delta  # orthogonal to the discretisation error
    other *= 0.001 / np.sqrt(np.mean(other ** 2))
    r_ref = 0.6 * delta + 0.3 * other  # the reference leaves some of each
    check = resolution.ResolutionCheck(checked=True, floor=float(np.sqrt(np.mean(delta ** 2) * 3)),
                                       enforce_floor=True, difference=delta)

    def candidate(change):
        r = r_ref - change
        return SimpleNamespace(residual=r, sse=float(r @ r), significant=True, reasons=[])

    imitator = candidate(0.6 * delta)  # removes exactly the discretisation-like part
    unrelated = candidate(0.3 * other)  # removes the part refinement does not explain
    resolution.apply_floor(check, [imitator, unrelated], r_ref, n)
    assert not imitator.significant and "discretisation" in imitator.reasons[0]
    assert unrelated.significant and not unrelated.reasons
    off = dataclasses.replace(check, enforce_floor=False)  # resolved or refined: no floor
    again = candidate(0.6 * delta)
    resolution.apply_floor(off, [again], r_ref, n)
    assert again.significant


class _TwoResolutions:
    """A stand-in diagnosis problem whose coarse model is 30 % stiffer than its finer one (what the base fit can
    take up) and whose finer one also sits ``offset`` m higher (what it cannot).  A model run is a bar's points
    swinging at ω ∝ √(E/ρ scale)."""

    def __init__(self, offset: float, stiffer: float = 1.3):
        self.sim = SimpleNamespace(settings=SpringMassSettings(anchors=96), fine=False)
        self.fine_sim = SimpleNamespace(settings=None, fine=True)
        t = np.linspace(0.0, 0.6, 31)[:, None]
        self.t, self.x = t, np.linspace(0.05, 0.4, 12)[None, :]
        self.offset, self.stiffer = offset, stiffer
        self.obs_all = self.obs = np.ones((31, 12), dtype=bool)
        self.runs = 0

    def trajectory(self, scale: float, fine: bool) -> np.ndarray:
        omega = 20.0 * math.sqrt(scale * (1.0 if fine else self.stiffer))
        z = 0.3 * self.x ** 2 * np.sin(omega * self.t) + (self.offset if fine else 0.0)
        return np.stack(np.broadcast_arrays(self.x + 0 * self.t, 0 * z, z), axis=-1)

    def run(self, effect_lists, sim=None, full=False):
        assert not full, "the check compares the runs over the samples the fits use: no whole-record runs"
        self.runs += len(effect_lists)
        return [self.trajectory(effects[0], bool(getattr(sim or self.sim, "fine", False))) for effects in effect_lists]


@pytest.mark.parametrize("offset", [0.0, 0.004])
def test_the_floor_is_what_refinement_moves_beyond_a_different_e(offset):
    """Refinement that only softens the solid is taken up by the base fit's E/ρ: the finer model's scale is refitted
    (here × 1.3) before the two are compared, and only what remains (an offset) is a floor."""
    P = _TwoResolutions(offset)
    check, use = resolution.check_resolution(P, lambda scale: [scale], 1.0, lambda s: P.fine_sim, sigma=0.0005,
                                             remaining_runs=10 ** 6, budget_s=0.0)
    assert check.floor_before_refit > 0.01  # the same E: a large difference
    assert check.finer_E_factor == pytest.approx(1.3, rel=0.01)
    assert check.floor == pytest.approx(offset, abs=2e-4)
    assert check.enforce_floor is (offset > 0) and use is None
    assert np.allclose(check.difference.reshape(-1, 3)[:, 2], offset, atol=2e-3)
    assert check.to_dict()["finer_E_factor"] == pytest.approx(1.3, rel=0.01)
    assert P.runs <= 2 + len(resolution.REFIT_FACTORS) + resolution.REFIT_PARABOLAS


class _ChaoticLater(_TwoResolutions):
    """Both resolutions alike (no stiffness bias) until instant 12; after it the finer run departs by 5 cm, as a
    chaotic contact's does under any change of the model."""

    def trajectory(self, scale: float, fine: bool) -> np.ndarray:
        out = super().trajectory(scale, fine)
        if fine:
            out = out.copy()
            out[12:, :, 2] += 0.05
        return out


def test_the_floor_is_over_the_samples_the_fits_use():
    """With a predictive window the floor is measured where effects are fitted and judged: a finer model that
    departs only after the window (chaotic contact) leaves no floor; over the whole record it would be centimetres."""
    P = _ChaoticLater(0.0, stiffer=1.0)
    check, use = resolution.check_resolution(P, lambda scale: [scale], 1.0, lambda s: P.fine_sim, sigma=0.0005,
                                             remaining_runs=100, budget_s=0.0)
    assert check.floor > 0.02 and check.enforce_floor  # the whole record
    P = _ChaoticLater(0.0, stiffer=1.0)
    P.obs = P.obs_all.copy()
    P.obs[12:] = False  # the predictive window: instants 0 … 11
    check, use = resolution.check_resolution(P, lambda scale: [scale], 1.0, lambda s: P.fine_sim, sigma=0.0005,
                                             remaining_runs=100, budget_s=0.0)
    assert check.floor < 1e-9 and not check.enforce_floor and use is None
    assert "its resolution is sufficient" in check.verdict


def test_the_budget_decides_finer_or_floor_and_the_verdict_says_which_machine_decided():
    """A model unresolved by 4 mm: budget 0 enforces the floor and says so (the same on every machine); a budget the
    finer runs fit uses the finer model and says the choice was this machine's speed; an unlimited one always
    refines."""
    P = _TwoResolutions(0.004)
    check, use = resolution.check_resolution(P, lambda scale: [scale], 1.0, lambda s: P.fine_sim, sigma=0.0005,
                                             remaining_runs=100, budget_s=0.0)
    assert check.enforce_floor and use is None
    assert "budget 0 s: the coarse model on every machine" in check.verdict and "would cost" not in check.verdict
    P = _TwoResolutions(0.004)
    check, use = resolution.check_resolution(P, lambda scale: [scale], 1.0, lambda s: P.fine_sim, sigma=0.0005,
                                             remaining_runs=100, budget_s=3600.0)
    assert check.used_finer and use is P.fine_sim
    assert "follows this machine's speed" in check.verdict and "budget of 0 s makes it the same" in check.verdict
    P = _TwoResolutions(0.004)
    check, use = resolution.check_resolution(P, lambda scale: [scale], 1.0, lambda s: P.fine_sim, sigma=0.0005,
                                             remaining_runs=10 ** 9, budget_s=math.inf)
    assert check.used_finer and "budget unlimited" in check.verdict and check.to_dict()["budget_s"] is None


def test_a_skipped_refit_is_said_and_its_floor_is_an_upper_bound(monkeypatch):
    """When the finer runs are too slow for the E/ρ refit (on a loaded CPU an MPM bar's finer run took 5.7 s, six
    of them over the 30 s allowed, and the floor came out 21.9 mm where the refit gives 4.7 mm), the verdict says the
    refit was skipped and that the floor is an upper bound."""
    monkeypatch.setattr(resolution, "REFIT_BUDGET_S", 0.0)
    P = _TwoResolutions(0.004)
    check, _ = resolution.check_resolution(P, lambda scale: [scale], 1.0, lambda s: P.fine_sim, sigma=0.0005,
                                           remaining_runs=10 ** 6, budget_s=0.0)
    assert check.finer_E_factor == 1.0 and check.floor == check.floor_before_refit > 0.01
    assert "refit for the finer model was skipped" in check.verdict and "upper bound" in check.verdict
    assert P.runs == 2
    monkeypatch.setattr(resolution, "REFIT_BUDGET_S", 30.0)
    check, _ = resolution.check_resolution(_TwoResolutions(0.004), lambda scale: [scale], 1.0,
                                           lambda s: P.fine_sim, sigma=0.0005, remaining_runs=10 ** 6, budget_s=0.0)
    assert "skipped" not in check.verdict


@pytest.mark.slow
def test_drop_on_a_damped_floor_fits_the_contact_in_the_base(tmp_path):
    """A cube dropped onto a damped, yielding floor (spring-mass made, 48 anchors): the base fit adopts the floor
    with c within 25 % (k sits near this coarse network's rigid limit, where it is barely identifiable), nothing
    is identified, the error ends at the noise, and the report carries the contact and the resolution check."""
    import json

    from unipixie.core.diagnosis import diagnose, synth

    m = synth.synthesize(["contact_damping:c=3e4,k=1e6"], "spring_mass", settings={"anchors": 48}, shape="cube",
                         scenario="drop", velocity=(0, 0, 0), height=0.1, noise=0.001, occlusion=0.1, points=80,
                         duration=0.4, fps=40.0, seed=3)
    d = diagnose.diagnose(m, "spring_mass", settings={"anchors": 48}, max_additions=1,
                          candidates=["linear_drag", "contact_damping"], out_dir=tmp_path,
                          resolution_budget_s=0.0)  # deterministic: never switch to the finer model
    bc = d.base_contact
    assert bc["touches_ground"] and bc["adopted"]
    assert bc["params"]["c"] == pytest.approx(3e4, rel=0.25)
    assert [c.name for c in d.candidates] == ["linear_drag"] and d.identified is None
    assert d.final.rmse <= 2.0 * math.sqrt(3.0) * 0.001
    doc = json.loads((tmp_path / "diagnosis.json").read_text())
    assert doc["base_contact"]["adopted"] and doc["resolution"]["checked"] and doc["resolution"]["floor_rmse"] > 0
    assert doc["resolution"]["enforce_floor"] and not doc["resolution"]["used_finer"]
    caveat = next(w for w in d.warnings if "material damping takes energy from an impact too" in w)
    assert caveat in doc["warnings"] and "free vibration" in caveat
    html = (tmp_path / "diagnosis.html").read_text()
    assert "Ground contact fitted with E/ρ" in html and "Resolution check" in html


def test_the_floor_caveat_is_said_only_when_a_lossy_floor_may_hide_material_damping():
    from unipixie.core.diagnosis.contact_fit import ContactFit, floor_caveat
    from unipixie.solvers import effects as fx

    floor = fx.make("contact_damping", c=3.2e4, k=3.4e6)
    caveat = floor_caveat(ContactFit(effect=floor, adopted=True), ["ground_friction"])
    assert "c = 3.2e+04 Pa·s/m" in caveat and "not ruled out" in caveat
    assert floor_caveat(ContactFit(effect=floor, adopted=True), ["material_damping"]) is None  # it was named
    assert floor_caveat(ContactFit(effect=floor, adopted=False), []) is None  # the rigid floor was kept
    assert floor_caveat(ContactFit(), []) is None  # no ground contact


def test_default_solver_is_the_most_faithful_the_device_affords():
    from unipixie.core.diagnosis import diagnose

    assert diagnose.default_solver("cpu") == "spring_mass"
    assert diagnose.default_solver("cuda") == diagnose.default_solver("cuda:1") == "mpm"


def test_a_setting_given_changes_only_its_key_of_the_diagnosis_defaults():
    """``--setting layout=lattice`` once dropped the diagnosis's 192 anchors for the bake's 2048 (ten times the cost)."""
    from unipixie.core.diagnosis import diagnose

    assert diagnose.diagnosis_settings("spring_mass", {"layout": "lattice"}) == {"anchors": 192, "layout": "lattice"}
    assert diagnose.diagnosis_settings("spring_mass", {"anchors": 384}) == {"anchors": 384}
    assert diagnose.diagnosis_settings("mpm", {"cells_across": 16}) == {"cells_across": 16, "viscous_cfl": 0.2}
    assert diagnose.diagnosis_settings("spring_mass", None) == {"anchors": 192}
    given = SpringMassSettings(anchors=96)
    assert diagnose.diagnosis_settings("spring_mass", given) is given  # a settings object is used as it is



class _CountingSimulation:
    """A stand-in prepared simulation: each run is its frame count's positions (the instant index everywhere); it
    counts the instants it simulated."""

    def __init__(self, frames: int, points: int, log: list):
        self.frame_times = np.linspace(0.0, 1.0, frames)
        self.sample_positions = np.zeros((1, 3))
        self.points, self.log = points, log

    def up_to(self, frames):
        view = _CountingSimulation(frames, self.points, self.log)
        view.frame_times = self.frame_times[:frames]
        return view

    def run_batch(self, effect_lists):
        T = len(self.frame_times)
        self.log.append((T, len(effect_lists)))
        pos = np.broadcast_to(np.arange(T, dtype=float)[:, None, None], (T, self.points, 3))
        return [SimpleNamespace(positions=pos.copy()) for _ in effect_lists]


def test_runs_stop_at_the_predictive_window_unless_the_full_record_is_asked_for():
    """After :meth:`Problem.set_window` a run simulates only up to the window's last instant (its later instants
    NaN), one view per simulation shared by every batch; ``full`` runs (what is reported over every sample) and runs
    before a window cover the whole record; fits running side by side share the shortened runs' batches."""
    from unipixie.core.diagnosis.problem import Problem
    from unipixie.core.progress import silent

    T, N = 20, 4
    rest = np.zeros((N, 3))
    m = SimpleNamespace(positions=np.zeros((T, N, 3)), observed=np.ones((T, N), dtype=bool), rest=rest,
                        times=np.linspace(0.0, 1.0, T))
    log = []
    sim = _CountingSimulation(T, N, log)
    P = Problem(m, sim, [], silent(), max_batch=8)
    assert P.run([[]])[0].shape == (T, N, 3) and log[-1] == (T, 1)
    P.set_window(np.arange(T) < 8)
    runs = P.run([[], []])
    assert log[-1] == (8, 2)
    for r in runs:
        assert r.shape == (T, N, 3)
        np.testing.assert_array_equal(r[:8, 0, 0], np.arange(8.0))
        assert np.all(np.isnan(r[8:]))
    assert P.residual_of(runs[0]).shape == (3 * 8 * N,) and np.all(np.isfinite(P.residual_of(runs[0])))
    assert np.all(np.isfinite(P.run([[]], full=True)[0])) and log[-1] == (T, 1)
    assert P.positions_for(1.0, [], full=True).shape == (T, N, 3) and log[-1] == (T, 1)
    assert P._simulation_for(sim, False) is P._simulation_for(sim, False)  # one view, so batches can join
    finer = _CountingSimulation(T, N, log)
    P.run([[]], sim=finer)
    assert log[-1] == (8, 1)
    log.clear()
    P.parallel = True
    P.side_by_side([lambda: P.run([[]]), lambda: P.run([[], []])])
    assert log == [(8, 3)]
