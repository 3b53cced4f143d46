"""The spring-mass substep from the network's highest frequency (``step_bound`` "spectral", solvers/spring_mass.py)
and the anchors' implicit floor spring that lets it be long (solvers/contact_kernels.py).  CPU, small networks.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import trimesh

from unipixie.core.benchmarks import _scenes
from unipixie.core.benchmarks.fidelity import run_scene
from unipixie.core.errors import UserError
from unipixie.solvers import effects as fx
from unipixie.solvers import spring_mass as sm
from unipixie.solvers import spring_mass_linear as linear
from unipixie.solvers.body import Body
from unipixie.solvers.material_sampling import HomogeneousMaterial
from unipixie.solvers.scenario import Scenario

CUBE = 0.2


def cube_sim(anchors: int = 120, nu: float = 0.3, **settings):
    body = Body.from_mesh(trimesh.creation.box(extents=(CUBE, CUBE, CUBE)))
    return sm.prepare(body, HomogeneousMaterial(2e5, nu, 1000.0), Scenario(gravity=[0, 0, 0], ground_height=None),
                      [0.0, 0.01], settings={"anchors": anchors, **settings})


def top_eigenvalue(sim, K) -> float:
    """Largest eigenvalue of M⁻¹K (1/s²) by a dense solve, independent of the solver's Lanczos call."""
    m = np.repeat(sim.network.mass, 3)
    A = (sp.diags(m ** -0.5) @ K @ sp.diags(m ** -0.5)).toarray()
    return float(np.linalg.eigvalsh(A).max())


def test_spectral_substep_is_the_networks_highest_frequency():
    """The substep is safety · 2 / ω_max with ω_max² the largest eigenvalue of M⁻¹K at rest (springs and volumetric
    term), 2–3 times the per-anchor Gershgorin step (measured 2.2–2.4 at 512–8192 anchors); dashpots enter through
    M⁻¹C's largest eigenvalue."""
    sim = cube_sim()
    env = sim.env_arrays(sim.terms_for([]))
    top = top_eigenvalue(sim, linear.stiffness_matrix(sim))
    dt = sim.stable_substep(env["kappa_s"], env["dashpot_s"], env["vol_stiffness"])
    assert dt == pytest.approx(sim.settings.safety * 2.0 / math.sqrt(top), rel=1e-6)
    dt_g = sim.stable_substep(env["kappa_s"], env["dashpot_s"], env["vol_stiffness"], "gershgorin")
    print(f"spectral / Gershgorin substep: {dt / dt_g:.2f}")
    assert 1.8 < dt / dt_g < 3.5
    # with dashpots: γ is the largest eigenvalue of M⁻¹C (C assembled like K from the dashpot constants)
    eta = 50.0
    damped = sim.env_arrays(sim.terms_for([fx.make("material_damping", eta=eta)]))
    gamma = top_eigenvalue(sim, linear.stiffness_matrix(sim, damped["dashpot_s"], np.zeros(sim.network.count)))
    expected = sim.settings.safety * 4.0 / (gamma + math.sqrt(gamma ** 2 + 4.0 * top))
    assert sim.stable_substep(damped["kappa_s"], damped["dashpot_s"], damped["vol_stiffness"]) == pytest.approx(
        expected, rel=1e-5)


def test_spectral_substep_bounds_a_stiffer_region():
    """A non-uniform E multiplier (a stiffer half) is bounded by its largest multiple times the base eigenvalue:
    never below the true largest eigenvalue of the scaled network, exact for a uniform multiple."""
    sim = cube_sim()
    n = sim.network.count
    for scale in (np.full(n, 3.0), np.where(sim.network.anchors[:, 0] > 0, 3.0, 1.0)):
        terms = sim.terms_for([])
        terms.E_scale = scale
        env = sim.env_arrays(terms)
        dt = sim.stable_substep(env["kappa_s"], env["dashpot_s"], env["vol_stiffness"])
        top = top_eigenvalue(sim, linear.stiffness_matrix(sim, env["kappa_s"], env["vol_stiffness"]))
        allowed = sim.settings.safety * 2.0 / math.sqrt(top)
        assert dt <= allowed * (1 + 1e-6)
        if np.all(scale == scale[0]):
            assert dt == pytest.approx(allowed, rel=1e-6)


def test_step_bound_is_checked_and_recorded():
    with pytest.raises(UserError, match="step_bound"):
        cube_sim(step_bound="exact")
    sim = cube_sim(anchors=64)
    assert sim.run([]).meta["step_bound"] == "spectral"
    assert cube_sim(anchors=64, step_bound="gershgorin").run([]).meta["step_bound"] == "gershgorin"


def test_the_long_substep_keeps_the_drop():
    """The canonical drop at 512 anchors: the spectral substep (2.3 times the Gershgorin one) rebounds within 0.5 mm
    of the Gershgorin step's and of a 4 times finer fixed step's, contacts as long, and keeps every tracked point on
    or above the floor (measured: 0.1575 / 0.1578 m)."""
    scene = _scenes.scene("drop")
    runs = {}
    for name, settings in (("spectral", {"anchors": 512}), ("gershgorin", {"anchors": 512, "step_bound": "gershgorin"}),
                           ("fine", {"anchors": 512, "substeps": 8})):
        runs[name] = run_scene(scene, "spring_mass", settings, "cpu")
    (m_s, traj_s, _), (m_g, traj_g, _), (m_f, _, _) = runs["spectral"], runs["gershgorin"], runs["fine"]
    assert traj_s.meta["substep_s"] > 2.0 * traj_g.meta["substep_s"]
    assert abs(m_s["rebound_peak"] - m_g["rebound_peak"]) < 5e-4
    assert abs(m_s["rebound_peak"] - m_f["rebound_peak"]) < 5e-4
    assert abs(m_s["contact_duration"] - m_g["contact_duration"]) <= 1.5e-3
    assert traj_s.positions[..., 2].min() >= -1e-3


def test_a_run_that_diverges_at_the_spectral_step_is_run_again_at_the_gershgorin_step(monkeypatch):
    """If the network stiffens beyond the safety factor's room, the run is repeated at the per-anchor bound and says
    so (here forced: the spectral estimate is made 100 times too small, so the first run blows up)."""
    body = Body.from_mesh(trimesh.creation.box(extents=(CUBE, CUBE, CUBE)))
    frames = np.linspace(0.0, 0.2, 21)
    material = HomogeneousMaterial(2e5, 0.3, 1000.0)
    scenario = Scenario(ground_height=0.0)
    reference = sm.prepare(body, material, scenario, frames, settings={"anchors": 64, "step_bound": "gershgorin"}).run([])
    sim = sm.prepare(body, material, scenario, frames, settings={"anchors": 64})
    real = sm.SpringMassSimulation.spectral_rates
    monkeypatch.setattr(sm.SpringMassSimulation, "spectral_rates", lambda self, kind: real(self, kind) / 100.0)
    traj = sim.run([])
    assert traj.meta["step_bound"] == "gershgorin"
    assert any("diverged" in w for w in traj.meta["warnings"])
    np.testing.assert_allclose(traj.positions, reference.positions, atol=1e-6)
    assert not any("diverged" in w for w in sim.warnings)  # the note belongs to that run only


def potted_block(held_E: float, anchors: int = 150):
    """A 0.2 m block: its lower half a held class (stationary, E ``held_E``) like the demo plant's pot, its upper half
    jelly (200 kPa) clamped up to 2 cm above the interface like the plant's soil; gravity, no ground."""
    from unipixie.solvers import materials
    from unipixie.solvers.material_sampling import PointMaterial

    body = Body.from_mesh(trimesh.creation.box(extents=(CUBE, CUBE, CUBE)))
    g = np.linspace(-CUBE / 2, CUBE / 2, 21)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pot = pts[:, 2] < 0.0
    material = PointMaterial(pts, np.where(pot, held_E, 2e5), np.where(pot, 0.3, 0.35), np.where(pot, 2000.0, 1000.0),
                             np.where(pot, materials.get("stationary").id, materials.get("jelly").id))
    scenario = Scenario(ground_height=None, pinned_box=[[-1, -1, -1], [1, 1, 0.02]])
    return sm.prepare(body, material, scenario, np.linspace(0.0, 0.05, 3), settings={"anchors": anchors})


def test_held_material_does_not_stiffen_the_free_material():
    """A held class never deforms and its E is no material's (the stationary class's prior is 10⁸–10¹¹ Pa): the
    jelly above it moves and steps the same whatever that E.  The springs joining free anchors to held ones take the
    free end's stiffness, and a clamped anchor's cell mean of E leaves out the held fill points in its cell; with the
    held end's own stiffness or the mixed cell mean, the demo plant's soil anchors on its pot set a 7.5 µs substep
    (61.5 µs with the rule).  At 200 kPa and 2 GPa the substep and motion agree; before the rule the 2 GPa pot gave a
    substep ~60 times shorter."""
    soft, hard = potted_block(2e5), potted_block(2e9)
    held = soft.network.held
    assert held.any() and (soft.network.pinned & ~held).any() and (~soft.network.pinned).any()
    steps = [s.stable_substep(s.spring_kappa, np.zeros_like(s.spring_kappa), s.star_stiffness) for s in (soft, hard)]
    assert steps[1] == pytest.approx(steps[0], rel=1e-9)
    np.testing.assert_allclose(hard.run([]).positions, soft.run([]).positions, atol=1e-7)
    # a spring from a free anchor to a held one is the free anchor's at both ends
    s, ends = hard.network.springs, hard.spring_ends
    joins = held[s[:, 0]] & ~hard.network.pinned[s[:, 1]]
    assert joins.any() and np.all(ends[joins, 0] == s[joins, 1]) and np.all(ends[joins, 1] == s[joins, 1])
