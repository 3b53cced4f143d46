"""The independent FEM simulator (training/independent_fem.py) against analytic answers, and its files.

The simulator makes the measurements the diagnosis is validated on (training/validate_diagnosis.py), so its
physics is checked here on its own: free fall, a clamped bar's axial period, linear-drag decay, the Coulomb
stopping distance, the Kelvin–Voigt decay rate and undamped rigid motion, and the measurement file it
writes read back by the project's loader.  Small meshes: the whole file runs in well under a minute.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from unipixie.core import measurement
from unipixie.core.errors import UserError
from unipixie.training import independent_fem as fem

from motion_helpers import rotation_degrees

MATERIAL = {"E": 1.0e5, "nu": 0.3, "density": 1000.0}
DROP_MESH_BOUND = 0.005
"""m: the canonical drop's rebound peak moves by less than this from 4 to 8 cells a side (hard law)."""


def _com(model, x):
    """(3,) mass-weighted mean of node values x (n, 3)."""
    return (model.mass[:, None] * x).sum(0) / model.mass.sum()


def _cube(size=0.1, centre=(0.0, 0.0, 1.0)):
    return fem.box_tet_mesh((size, size, size), centre=centre, spacing=size / 2)


def test_free_fall_matches_the_parabola():
    g = np.array([0.0, 0.0, -9.81])
    v0 = np.array([1.0, 0.0, 2.0])
    model = fem.FEMModel(_cube(), MATERIAL, {"gravity": g.tolist(), "ground": None, "initial_velocity": v0.tolist()})
    times = np.linspace(0.0, 0.5, 11)
    x = model.run(times)
    com = np.array([_com(model, xi) for xi in x])
    expected = np.array([0.0, 0.0, 1.0]) + np.outer(times, v0) + np.outer(0.5 * times ** 2, g)
    displacement = np.linalg.norm(expected - expected[0], axis=1)
    err = np.linalg.norm(com - expected, axis=1)
    assert np.all(err[1:] <= 0.01 * displacement[1:]), (err, displacement)


def _clamped_bar(eta=0.0, L=0.4, E=1.0e5, rho=1000.0, amplitude=0.05, nu=0.0):
    """A bar L × 0.04 × 0.04 m along x, clamped at x = 0 (ν = 0: exactly a 1-D rod; a slender bar otherwise),
    started in its first axial mode with velocity amplitude ``amplitude`` m/s at the free end."""
    mesh = fem.box_tet_mesh((L, 0.04, 0.04), centre=(L / 2, 0.0, 0.0), spacing=0.04)
    sc = {"gravity": [0.0, 0.0, 0.0], "ground": None, "pinned_box": [[-1.0, -1.0, -1.0], [1e-9, 1.0, 1.0]]}
    effects = [f"material_damping:eta={eta}"] if eta > 0 else []
    model = fem.FEMModel(mesh, {"E": E, "nu": nu, "density": rho}, sc, effects)
    assert model.pinned.sum() == 4  # the x = 0 face
    v0 = np.zeros_like(model.X)
    v0[:, 0] = amplitude * np.sin(0.5 * np.pi * model.X[:, 0] / L)
    model.v0 = v0 * model.free
    tip = np.isclose(model.X[:, 0], L)
    return model, tip


def _zero_crossings(t, u):
    s = np.sign(u)
    i = np.nonzero(((s[:-1] < 0) & (s[1:] >= 0)) | ((s[:-1] > 0) & (s[1:] <= 0)))[0]
    return t[i] - u[i] * (t[i + 1] - t[i]) / (u[i + 1] - u[i])


@pytest.mark.parametrize("nu", [0.0, 0.3])
def test_clamped_bar_axial_period(nu):
    L, E, rho = 0.4, 1.0e5, 1000.0
    model, tip = _clamped_bar(L=L, E=E, rho=rho, nu=nu)
    period = 4.0 * L / math.sqrt(E / rho)  # fixed-free slender rod, first mode: λ = 4 L, c = √(E/ρ)
    times = np.arange(0.0, 2.6 * period, period / 100)
    u = model.run(times)[:, tip, 0].mean(1) - L
    crossings = _zero_crossings(times, u)
    assert len(crossings) >= 4
    measured = 2.0 * float(np.mean(np.diff(crossings)))
    assert abs(measured - period) <= 0.05 * period, (measured, period)
    assert np.max(np.abs(u)) > 1e-4  # it did vibrate


def test_linear_drag_decays_velocity_exponentially():
    c, v0, t_end = 2.0, 2.0, 1.0
    model = fem.FEMModel(_cube(), MATERIAL, {"gravity": [0.0, 0.0, 0.0], "ground": None,
                                             "initial_velocity": [v0, 0.0, 0.0]}, [f"linear_drag:c={c}"])
    times = np.linspace(0.0, t_end, 5)
    x = model.run(times)
    v_end = _com(model, model.final_state[1])[0]
    assert v_end == pytest.approx(v0 * math.exp(-c * t_end), rel=0.03)
    # the displacement integrates it: x(t) = v0 (1 − e^{−ct}) / c
    dx = np.array([_com(model, xi)[0] for xi in x]) - _com(model, x[0])[0]
    assert dx == pytest.approx(v0 * (1 - np.exp(-c * times)) / c, rel=0.03, abs=1e-9)


def test_coulomb_friction_stopping_distance():
    mu, v0, g = 0.5, 1.0, 9.81
    model = fem.FEMModel(fem.box_tet_mesh((0.1, 0.1, 0.1), centre=(0.0, 0.0, 0.05), spacing=0.05),
                         {"E": 1.0e6, "nu": 0.3, "density": 1000.0},
                         {"gravity": [0.0, 0.0, -g], "ground": {"height": 0.0}, "initial_velocity": [v0, 0.0, 0.0]},
                         [f"ground_friction:mu={mu}"])
    t_stop = v0 / (mu * g)
    times = np.linspace(0.0, 2.0 * t_stop, 41)
    x = model.run(times)
    cx = np.array([_com(model, xi)[0] for xi in x])
    distance = cx[-1] - cx[0]
    assert distance == pytest.approx(v0 ** 2 / (2 * mu * g), rel=0.10)
    assert abs(cx[-1] - cx[-5]) < 1e-3  # it has stopped (sticking), not still creeping
    assert np.min(x[-1][:, 2]) > -2e-3  # and it rests on the ground


def test_kelvin_voigt_damps_vibration_at_the_analytic_rate():
    L, E, rho, eta = 0.4, 1.0e5, 1000.0, 50.0
    omega = 0.5 * np.pi * math.sqrt(E / rho) / L
    rate = eta * omega ** 2 / E  # σ = E ε + 2η ε̇ (ν = 0): amplitude ∝ exp(−η ω² t / E)
    period = 2 * np.pi / omega
    times = np.arange(0.0, 3.0 * period, period / 80)
    amplitudes = {}
    for e in (0.0, eta):
        model, tip = _clamped_bar(eta=e, L=L, E=E, rho=rho)
        u = model.run(times)[:, tip, 0].mean(1) - L
        first, last = times < period, times >= 2.0 * period
        amplitudes[e] = (np.max(np.abs(u[first])), np.max(np.abs(u[last])))
    a0, a1 = amplitudes[0.0]
    assert a1 == pytest.approx(a0, rel=0.01)  # undamped: no decay (RK4's own dissipation is negligible)
    d0, d1 = amplitudes[eta]
    measured = math.log(d0 / d1) / (2.0 * period)
    assert measured == pytest.approx(rate, rel=0.10), (measured, rate)


def test_kelvin_voigt_leaves_rigid_motion_alone():
    sc = {"gravity": [0.0, 0.0, 0.0], "ground": None, "initial_velocity": [1.0, 0.0, 0.5],
          "initial_angular_velocity": [0.0, 5.0, 3.0]}
    model = fem.FEMModel(_cube(), MATERIAL, sc, ["material_damping:eta=50"])
    e0 = model.energy(model.X, model.v0)["total"]
    model.run(np.linspace(0.0, 0.5, 6))
    x, v = model.final_state
    e1 = model.energy(x, v)["total"]
    assert e1 == pytest.approx(e0, rel=1e-3)  # a spinning, flying block keeps its energy
    r = x - _com(model, x)
    L0 = np.sum(model.mass[:, None] * np.cross(model.X - _com(model, model.X), model.v0), axis=0)
    L1 = np.sum(model.mass[:, None] * np.cross(r, v), axis=0)
    np.testing.assert_allclose(L1, L0, rtol=1e-6, atol=1e-9)


def test_measurement_file_loads_and_validates(tmp_path):
    case = fem.Case("tiny", shape="cube", scenario="throw", effects=["wind:acceleration=0.5,0,0"], spacing=0.1,
                    duration=0.2, fps=25.0, noise=0.001, occlusion=0.1, stated_E_scale=1.25, seed=3)
    arrays = fem.make_case(case)
    path = tmp_path / "tiny.npz"
    np.savez_compressed(path, **arrays)
    m = measurement.load(path)
    T, N = len(arrays["times"]), len(arrays["rest_positions"])
    assert m.positions.shape == (T, N, 3) and T == 6
    assert not m.warnings, m.warnings  # closed, outward faces; nothing repaired
    assert m.faces is not None and m.faces.max() == N - 1
    # the faces enclose the solid, outward: their signed volume is the cube's (0.2 m)³
    a, b, c = (m.rest[m.faces[:, i]] for i in range(3))
    assert np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0 == pytest.approx(0.2 ** 3, rel=1e-9)
    assert m.scenario.ground_height is None  # a throw: no ground
    np.testing.assert_allclose(m.scenario.gravity, [0.0, 0.0, -9.81])
    assert m.material is not None and m.material.E == pytest.approx(case.E / 1.25)
    occluded = 1.0 - m.observed_count / (T * N)
    assert 0.05 < occluded < 0.2 and m.observed[0].all()
    truth = __import__("json").loads(str(m.extra_arrays["independent_truth"]))
    assert truth["effects"] == [{"effect": "wind", "params": {"acceleration": [0.5, 0.0, 0.0]}}]
    # noise of the stated size around the first (rigid, undeformed) instant
    resid = m.positions[0] - m.rest
    assert np.std(resid) == pytest.approx(case.noise, rel=0.3)
    m.save(tmp_path / "again.npz")  # and the project writes it back
    assert measurement.load(tmp_path / "again.npz").positions.shape == (T, N, 3)


@pytest.mark.parametrize("bad, match", [
    (lambda: fem.FEMModel(_cube(), {"E": -1.0, "nu": 0.3, "density": 1000.0}, {}), "'E'"),
    (lambda: fem.FEMModel(_cube(), {"E": 1e5, "nu": 0.5, "density": 1000.0}, {}), "'nu'"),
    (lambda: fem.FEMModel(_cube(), {"E": 1e5, "nu": 0.3}, {}), "density"),
    (lambda: fem.FEMModel(_cube(), MATERIAL, {}, ["gravity_fudge:c=1"]), "unknown effect"),
    (lambda: fem.FEMModel(_cube(), MATERIAL, {}, ["linear_drag:c=-1"]), "'c'"),
    (lambda: fem.FEMModel(_cube(), MATERIAL, {}, ["linear_drag:k=1"]), "unknown parameter"),
    (lambda: fem.FEMModel(_cube(), MATERIAL, {}, ["wind:acceleration=1,2"]), "3-vector"),
    (lambda: fem.FEMModel(_cube(), MATERIAL, {}, [{"effect": "stiffness_region", "params": {"factor": 2.0}}]),
     "region"),
    (lambda: fem.FEMModel(_cube(), MATERIAL, {"initial_velocity": [1.0, 0.0]}), "initial_velocity"),
    (lambda: fem.FEMModel(_cube(), MATERIAL, {"ground": None}).run([0.0, 0.1, 0.1]), "increasing"),
    (lambda: fem.Case("x", shape="torus").mesh(), "unknown shape"),
    (lambda: fem.make_case(fem.Case("x", scenario="orbit", spacing=0.1)), "unknown scenario"),
    (lambda: fem.make_case(fem.Case("x", spacing=0.1, duration=0.1, occlusion=1.5)), "occlusion"),
])
def test_bad_input_is_a_user_error(bad, match):
    with pytest.raises(UserError, match=match):
        bad()


def test_validation_cases_are_well_formed():
    from unipixie.training import validate_diagnosis as validate

    cases = validate.cases()
    assert len({c.name for c in cases}) == len(cases)
    hidden = {name for c in cases for name in fem._effect_params(c.effects)}
    assert set(fem.EFFECT_NAMES) <= hidden  # every spec effect is hidden in some case
    from unipixie.solvers import effects as fx

    assert set(fem.EFFECT_NAMES) <= set(fx.EFFECTS)  # the same vocabulary as the project's solvers
    for c in cases:
        mesh, sc = c.placed()
        c.effect_dicts(mesh.nodes)
    # issue 18's referee matrix: both contact laws, a floor that keeps energy, σ 0.5 and 1 mm, five or more cases
    # with nothing hidden (drops that bounce among them), and drops, throws, slides and clamped bars
    assert {c.contact_law for c in cases} == set(fem.CONTACT_LAWS)
    assert any(c.contact_law == "penalty" and c.contact_damping_ratio < 0.5 for c in cases)
    assert {c.noise for c in cases} == {0.0005, 0.001}
    nothing = [c for c in cases if not c.effects]
    assert len(nothing) >= 5 and sum(c.scenario == "drop" for c in nothing) >= 3
    assert {c.scenario for c in cases} == {"drop", "throw", "slide", "clamped"}
    with pytest.raises(UserError, match="unknown validation case"):
        validate.select_cases("none_throw,bogus")
    assert [c.name for c in validate.select_cases("quick")] == list(validate.QUICK)


# ------------------------------------------------------------------- the referee: contact laws and convergence
def _dropped_cube(law, damping=0.0, height=0.05, size=0.1):
    """A 0.1 m cube (2 cells a side) released at rest with its lower face ``height`` m above the ground."""
    settings = fem.FEMSettings(contact_law=law, contact_damping_ratio=damping)
    mesh = fem.box_tet_mesh((size, size, size), centre=(0.0, 0.0, height + size / 2), spacing=size / 2)
    sc = {"gravity": [0.0, 0.0, -9.81], "ground": {"height": 0.0}, "initial_velocity": [0.0, 0.0, 0.0]}
    return fem.FEMModel(mesh, MATERIAL, sc, settings=settings)


def _energy_above_rest(model, x, v, size=0.1):
    return model.energy(x, v)["total"] - model.mass.sum() * 9.81 * size / 2


@pytest.mark.parametrize("mirrored", [True, False])
def test_a_cube_dropped_flat_spins_only_on_an_unmirrored_mesh(mirrored):
    """A homogeneous cube dropped flat onto a frictionless floor cannot start to spin (the floor's forces are
    mirror-symmetric).  The one-diagonal (Kuhn) mesh is not, and spun the validation drops up to 16 degrees by
    their second bounce; the mirrored mesh (the default) keeps the cube's symmetries.  Measured at 2 cells a
    side, 0.45 s (two impacts): 0.0000 degrees mirrored, 2.48 unmirrored."""
    size = 0.2
    mesh = fem.box_tet_mesh((size, size, size), centre=(0.0, 0.0, 0.1 + size / 2), spacing=size / 2,
                            mirrored=mirrored)
    sc = {"gravity": [0.0, 0.0, -9.81], "ground": {"height": 0.0}, "initial_velocity": [0.0, 0.0, 0.0]}
    material = {"E": 2.0e5, "nu": 0.3, "density": 1000.0}  # the validation cubes' material
    x = fem.FEMModel(mesh, material, sc).run(np.linspace(0.0, 0.45, 10))
    tilt = rotation_degrees(mesh.nodes, x[-1])
    if mirrored:
        assert tilt < 1e-3
    else:
        assert tilt > 1.0


def test_free_fall_is_the_parabola_under_the_hard_law_too():
    model = _dropped_cube("hard", height=2.0)
    times = np.linspace(0.0, 0.3, 4)
    x = model.run(times)
    com = np.array([_com(model, xi)[2] for xi in x])
    np.testing.assert_allclose(com - com[0], -0.5 * 9.81 * times ** 2, atol=1e-6)


def test_the_contact_laws_differ_as_stated():
    """The hard law never lets a node below the ground and loses energy at the impact; the undamped penalty
    spring keeps much more (measured 0.59 against 0.93 of the energy above rest after the bounce: the rest goes
    into the coarse mesh's fastest vibrations, which RK4 damps)."""
    times = np.linspace(0.0, 0.22, 45)  # the impact at 0.10 s, in the air again by 0.13 s
    kept = {}
    for law in ("hard", "penalty"):
        model = _dropped_cube(law)
        x = model.run(times)
        e0 = _energy_above_rest(model, model.X, model.v0)
        kept[law] = _energy_above_rest(model, *model.final_state) / e0
        if law == "hard":
            assert np.min(x[:, :, 2]) >= -1e-12  # no penetration at any frame
            assert np.min(model.final_state[0][:, 2]) >= -1e-12
        else:
            assert np.min(x[:, :, 2]) < 0.0  # the penalty spring works by penetrating
    assert kept["hard"] < 0.8, kept
    assert kept["penalty"] > 0.85, kept
    assert kept["penalty"] > kept["hard"] + 0.15, kept


def test_the_damped_penalty_default_is_unchanged_and_loses_energy():
    assert fem.FEMSettings().contact_law == "penalty" and fem.FEMSettings().contact_damping_ratio == 1.0
    model = _dropped_cube("penalty", damping=1.0)
    model.run(np.linspace(0.0, 0.22, 45))
    kept = _energy_above_rest(model, *model.final_state) / _energy_above_rest(model, model.X, model.v0)
    assert kept < 0.95


@pytest.mark.slow
def test_hard_contact_friction_stops_a_slide():
    """Coulomb friction under the hard law: the stopping distance v²/(2μg) (about 25 s on a loaded 2-core CPU)."""
    mu, v0, g = 0.5, 1.0, 9.81
    model = fem.FEMModel(fem.box_tet_mesh((0.1, 0.1, 0.1), centre=(0.0, 0.0, 0.05), spacing=0.05),
                         {"E": 1.0e6, "nu": 0.3, "density": 1000.0},
                         {"gravity": [0.0, 0.0, -g], "ground": {"height": 0.0}, "initial_velocity": [v0, 0.0, 0.0]},
                         [f"ground_friction:mu={mu}"], fem.FEMSettings(contact_law="hard"))
    t_stop = v0 / (mu * g)
    x = model.run(np.linspace(0.0, 2.0 * t_stop, 41))
    cx = np.array([_com(model, xi)[0] for xi in x])
    assert cx[-1] - cx[0] == pytest.approx(v0 ** 2 / (2 * mu * g), rel=0.10)
    assert np.min(x[:, :, 2]) >= -1e-12


def test_a_case_takes_its_contact_law_to_the_referee():
    """A validation case's contact law reaches the referee and its measurement file says which law made it; under
    the hard law no node is below the ground at any frame."""
    import json

    case = fem.Case("hard_tiny", scenario="drop", velocity=(0.0, 0.0, 0.0), height=0.02, spacing=0.1, duration=0.2,
                    fps=50.0, noise=0.0, occlusion=0.0, contact_law="hard")
    arrays = fem.make_case(case)
    truth = json.loads(str(arrays["independent_truth"]))
    assert truth["contact_law"] == "hard" and "hard ground" in truth["simulator"]
    assert np.nanmin(arrays["positions"][..., 2]) >= -1e-9
    soft = json.loads(str(fem.make_case(fem.Case("soft_tiny", scenario="drop", spacing=0.1, duration=0.04,
                                                 fps=50.0, noise=0.0, occlusion=0.0,
                                                 contact_damping_ratio=0.1))["independent_truth"]))
    assert soft["contact_law"] == "penalty" and soft["contact_damping_ratio"] == 0.1


def test_unknown_contact_law_is_a_user_error():
    with pytest.raises(UserError, match="contact law"):
        fem.FEMSettings(contact_law="sticky")


def test_clamped_bar_sag_and_frequency_against_euler_bernoulli():
    """Quadratic tetrahedra, 2 cells through the thickness: tip sag and first frequency of the canonical bar
    (across its thin side) within 2 % of Euler–Bernoulli, which ignores shear and the clamp's 3-D stiffening."""
    from unipixie.training.independent_fem import study

    f = study.cantilever_figures("z", 2)
    assert f["tip_sag"] == pytest.approx(f["euler_bernoulli_sag"], rel=0.02)
    assert f["frequency"] == pytest.approx(f["euler_bernoulli_frequency"], rel=0.02)
    assert f["euler_bernoulli_sag"] == pytest.approx(8.98e-3, rel=2e-3)


def test_clamped_bar_converges_in_the_mesh():
    """Refining the bar (1 → 2 cells through the thickness, quadratic tetrahedra) moves the wide-side sag by
    under 0.5 mm and the thin-side sag by under 0.5 mm too (the diagnosis' noise level)."""
    from unipixie.training.independent_fem import study

    for direction in ("z", "y"):
        coarse, fine = study.convergence_study(f"cantilever_{direction}", [{"across": 1}, {"across": 2}])
        assert abs(fine["figures"]["tip_sag"] - coarse["figures"]["tip_sag"]) < 5e-4
        assert fine["figures"]["dofs"] > coarse["figures"]["dofs"]


def test_linear_module_mass_is_exact():
    from unipixie.training.independent_fem import linear

    mesh = fem.box_tet_mesh((0.2, 0.1, 0.1), spacing=0.05)
    K, M = linear.assemble(linear.quadratic_mesh(mesh), {"E": 1e5, "nu": 0.3, "density": 800.0})
    ones = np.zeros(M.shape[0])
    ones[0::3] = 1.0
    assert ones @ M @ ones == pytest.approx(800.0 * 0.2 * 0.1 * 0.1, rel=1e-12)  # total mass
    assert np.abs(K @ ones).max() < 1e-6 * abs(K).max()  # a rigid translation stores no energy


@pytest.mark.slow
def test_drop_converges_between_two_meshes():
    """The canonical drop under the hard law at 4 and 8 cells a side: the rebound peak of the centre of mass
    and the contact duration agree within the stated bounds (measured 0.8 mm and 0 ms on the mirrored mesh, 3.4 mm
    and 0 ms on the earlier one-diagonal mesh: benchmarks/referee_fem.json)."""
    from unipixie.training.independent_fem import study

    coarse, fine = study.convergence_study("drop", [{"cells": 4, "safety": 0.25}, {"cells": 8, "safety": 0.25}])
    a, b = coarse["figures"], fine["figures"]
    assert a["lowest"] >= -1e-12 and b["lowest"] >= -1e-12
    assert abs(a["first_contact"] - math.sqrt(2 * 0.1 / 9.81)) <= 1.5e-3
    assert abs(a["rebound_peak"] - b["rebound_peak"]) < DROP_MESH_BOUND
    assert abs(a["contact_duration"] - b["contact_duration"]) <= 0.004


def test_a_floor_that_gives_holds_a_block_at_its_weight_and_returns_what_it_stores():
    """The ``contact_damping`` floor (k Pa/m, c Pa·s/m per unit footprint): a stiff block resting on it sinks
    ρ g h / k (closed form), and undamped it gives back what it stores (the drop rebounds higher than on the hard
    law, which takes the touching nodes' normal energy)."""
    h, rho, k = 0.2, 1000.0, 1.0e5
    mesh = fem.box_tet_mesh((h, h, h), centre=(0.0, 0.0, h / 2), spacing=h / 2)
    model = fem.FEMModel(mesh, {"E": 2.0e6, "nu": 0.3, "density": rho}, {"gravity": [0, 0, -9.81], "ground": {"height": 0.0}},
                         [f"contact_damping:k={k},c={2.0 * math.sqrt(k * rho * h)}"])
    assert model.floor_area.sum() == pytest.approx(h * h, rel=1e-12)  # the footprint is the lower face
    x = model.run([0.0, 0.6])
    sink = h - x[-1, :, 2].max()
    assert sink == pytest.approx(rho * 9.81 * h / k, rel=0.02), sink
    from unipixie.training.independent_fem.study import drop_figures

    soft = drop_figures(4, duration=0.3, floor=(1.0e6, 0.0))
    hard = drop_figures(4, duration=0.3)
    assert soft["rebound_peak"] > hard["rebound_peak"] + 0.02 and soft["lowest"] < -0.01, (soft, hard)
    with pytest.raises(UserError, match="'k' must be positive"):
        fem.FEMModel(mesh, {"E": 2.0e6, "nu": 0.3, "density": rho}, {}, ["contact_damping:k=0,c=1"])
