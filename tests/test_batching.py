"""Candidate fits side by side (core/diagnosis/batching.py): requests joined into shared batches, results
handed back to the right fit, errors and cancellation stop every fit; a diagnosis gives the same answer."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from unipixie.core.diagnosis import diagnose, resolution, synth
from unipixie.core.diagnosis.batching import BatchGate
from unipixie.core.errors import CancelledError


class Recorder:
    """A ``run`` that squares its items and records every batch (items, key, thread)."""

    def __init__(self, fail_on=None):
        self.batches = []
        self.fail_on = fail_on

    def __call__(self, items, key):
        self.batches.append((list(items), key, threading.current_thread()))
        if self.fail_on is not None and self.fail_on in items:
            raise CancelledError("cancelled by the user")
        return [x * x for x in items]


def test_requests_of_all_jobs_share_batches_and_results_go_back_in_order():
    run = Recorder()
    gate = BatchGate(run)

    def job(base, rounds):
        def go():
            out = []
            for r in range(rounds):
                items = [base + 10 * r + i for i in range(base % 3 + 1)]  # 1..3 items per request
                assert gate.in_job()
                out.append(gate.request(items))
                assert out[-1] == [x * x for x in items]
            return base, out
        return go

    jobs = [job(b, rounds) for b, rounds in ((100, 4), (200, 2), (301, 5), (402, 1))]
    results = gate.map(jobs)
    assert [r[0] for r in results] == [100, 200, 301, 402]
    assert [len(r[1]) for r in results] == [4, 2, 5, 1]
    # every batch ran on the calling thread; while all four jobs were running they shared one batch per round
    assert all(t is threading.main_thread() for _, _, t in run.batches)
    assert len(run.batches) == 5  # = the longest job's rounds, not the 12 requests
    assert sorted(len(b) for b, _, _ in run.batches) == [2, 4, 4, 7, 8]
    assert not gate.in_job()


def test_requests_with_different_keys_run_separately():
    run = Recorder()
    gate = BatchGate(run)
    a, b = object(), object()
    gate.map([lambda: gate.request([1, 2], a), lambda: gate.request([3], b), lambda: gate.request([4], a)])
    assert sorted((tuple(items), key is a) for items, key, _ in run.batches) == [((1, 2, 4), True), ((3,), False)]


def test_a_failing_batch_stops_every_job_and_is_raised():
    run = Recorder(fail_on=7)
    gate = BatchGate(run)
    reached = []

    def job(values):
        def go():
            for v in values:
                gate.request([v])
                reached.append(v)
        return go

    with pytest.raises(CancelledError, match="cancelled"):
        gate.map([job([1, 7, 8]), job([2, 3, 4, 5]), job([6])])
    assert 8 not in reached and 4 not in reached  # nothing ran after the failing batch
    # the gate is usable again afterwards
    assert gate.map([lambda: gate.request([3]), lambda: 5]) == [[9], 5]


def test_a_failing_job_stops_the_others():
    gate = BatchGate(Recorder())

    def bad():
        gate.request([1])
        raise ValueError("bad fit")

    def long():
        for i in range(50):
            gate.request([i])
        return "finished"

    with pytest.raises(ValueError, match="bad fit"):
        gate.map([bad, long])


@pytest.mark.slow
def test_diagnosis_side_by_side_gives_the_same_result(monkeypatch):
    """With the spring-mass solver (one parameter set per launch) fitting the candidates side by side gives
    bitwise the same diagnosis as fitting them one after another (the speculative half-step re-check may only add
    runs); and running a batch's simulations in threads at once (the CPU default,
    :attr:`.Problem.threads`) the same as running them one after another."""
    m = synth.synthesize(["linear_drag:c=0.5"], "spring_mass", settings={"anchors": 64}, shape="cube",
                         scenario="throw", noise=0.001, occlusion=0.1, points=60, duration=0.4, fps=50.0, seed=5)
    kw = dict(settings={"anchors": 64}, max_additions=1, candidates=["linear_drag", "wind", "stiffness_region"])
    side = diagnose.diagnose(m, "spring_mass", parallel=True, **kw)
    one = diagnose.diagnose(m, "spring_mass", parallel=False, **kw)
    assert side.identified == one.identified == "linear_drag"
    assert [c.name for c in side.candidates] == [c.name for c in one.candidates]
    for a, b in zip(side.candidates, one.candidates):
        assert a.sse == b.sse and a.evaluations == b.evaluations
        assert (a.holdout or {}).get("sse_candidate") == (b.holdout or {}).get("sse_candidate")
        assert a.dt_check == b.dt_check
    assert side.candidates[0].dt_check["ok"]  # linear drag: re-checked at half the step, with the held-out refits
    np.testing.assert_array_equal(side.final_positions, one.final_positions)
    # the same runs: the speculative half-step re-check was of the leader that passed its held-out check
    assert side.simulations == one.simulations
    from unipixie.core.diagnosis import problem

    assert problem.concurrent_run_threads() >= 2  # so the runs above went on in threads
    monkeypatch.setattr(problem, "CONCURRENT_RUNS_PER_CORE", 0.0)  # one thread: every run after the other
    alone = diagnose.diagnose(m, "spring_mass", parallel=False, **kw)
    assert [(c.name, c.sse, c.evaluations) for c in alone.candidates] == \
        [(c.name, c.sse, c.evaluations) for c in one.candidates]
    np.testing.assert_array_equal(alone.final_positions, one.final_positions)


def test_the_ground_contact_descents_go_side_by_side_with_the_same_fit(monkeypatch):
    """The ground-contact fit's descents (from its best starts) are independent: side by side they run in the
    side-by-side jobs (on a GPU one shared batch a step instead of one launch per descent and step) and give
    bitwise the contact, E/ρ and candidates of one descent after another."""
    import threading

    from unipixie.core.diagnosis import contact_fit

    m = synth.synthesize(["contact_damping:c=3e4,k=1e6"], "spring_mass", settings={"anchors": 48}, shape="cube",
                         scenario="drop", velocity=(0, 0, 0), height=0.1, noise=0.001, occlusion=0.1, points=60,
                         duration=0.3, fps=40.0, seed=3)
    threads = []
    lm = contact_fit.levenberg_marquardt

    def recording(*a, **k):
        threads.append(threading.current_thread())
        return lm(*a, **k)

    monkeypatch.setattr(contact_fit, "levenberg_marquardt", recording)
    kw = dict(settings={"anchors": 48}, max_additions=0, candidates=["linear_drag", "contact_damping"],
              resolution_budget_s=0.0, predictive_window=False)
    side = diagnose.diagnose(m, "spring_mass", parallel=True, **kw)
    side_threads = list(threads)
    threads.clear()
    one = diagnose.diagnose(m, "spring_mass", parallel=False, **kw)
    assert len(side_threads) >= 2 and len(threads) == len(side_threads)
    assert threading.main_thread() not in side_threads and set(threads) == {threading.main_thread()}
    assert side.base_contact["touches_ground"] and side.base_contact == one.base_contact
    assert side.E_scale == one.E_scale
    assert [(c.name, c.sse) for c in side.candidates] == [(c.name, c.sse) for c in one.candidates]


def test_half_step_settings_halve_every_limit_of_the_step():
    """The half-time-step re-check halves MPM's wave-speed and viscous factors together (a damping run is
    limited by the viscous one), the spring-mass safety factor, and nothing of a solver without such a knob."""
    from types import SimpleNamespace

    from unipixie.solvers import mpm, spring_mass

    half = resolution.half_step_settings(SimpleNamespace(settings=mpm.MPMSettings(cfl=0.4, viscous_cfl=0.2)), None)
    assert (half.cfl, half.viscous_cfl) == (0.2, 0.1)
    half = resolution.half_step_settings(SimpleNamespace(settings=spring_mass.SpringMassSettings(safety=0.7)), None)
    assert half.safety == 0.35
    assert resolution.half_step_settings(SimpleNamespace(settings=None), None) is None


def test_nested_jobs_join_the_running_ones():
    """A job that runs jobs of its own side by side: they share batches with the other jobs, the waiting job
    holds nothing up, and it gets their results in order."""
    run = Recorder()
    gate = BatchGate(run)

    def leaf(v, rounds):
        def go():
            return [gate.request([v + r])[0] for r in range(rounds)]
        return go

    def parent():
        first = gate.request([1000])
        inner = gate.map([leaf(10, 3), leaf(20, 1)])
        return first, inner, gate.request([2000])

    out = gate.map([parent, leaf(500, 4)])
    assert out[0] == ([1000 ** 2], [[100, 121, 144], [400]], [2000 ** 2])
    assert out[1] == [250000, 251001, 252004, 253009]
    # round 1: parent + leaf 500; rounds 2-4: the two inner leaves + leaf 500, then leaf 10 + 500, then 10 + 500;
    # the parent's last request joins whatever is still running
    assert len(run.batches) <= 5 and sum(len(b) for b, _, _ in run.batches) == 10


@pytest.mark.parametrize("hidden, added", [([], 0), (["linear_drag:c=0.5"], 1)])
def test_on_a_gpu_the_base_material_check_goes_with_round_one_and_gives_the_same_diagnosis(monkeypatch, hidden, added):
    """Where a launch's runs share a GPU (``Problem.device_batches``) the base-material check of round 1's reference runs
    side by side with its candidates; it is used when nothing is added and run again when an effect is.  Forced on
    here with the spring-mass solver (one parameter set per launch, bitwise the same runs): the same diagnosis, the
    check's runs in round 1's side-by-side jobs, and once or twice as the addition requires."""
    from unipixie.core.diagnosis import base_fit, problem

    m = synth.synthesize(hidden, "spring_mass", settings={"anchors": 64}, shape="cube", scenario="throw",
                         noise=0.001, occlusion=0.1, points=60, duration=0.4, fps=50.0, seed=5)
    kw = dict(settings={"anchors": 64}, max_additions=1, candidates=["linear_drag", "wind"], parallel=True)
    plain = diagnose.diagnose(m, "spring_mass", **kw)
    assert len(plain.added) == added

    calls = []
    check = base_fit.base_material_check

    def counted(P, *args, **kwargs):
        calls.append(P.gate.in_job())
        return check(P, *args, **kwargs)

    init = problem.Problem.__init__

    def on_gpu(self, *args, **kwargs):
        init(self, *args, **kwargs)
        self.device_batches = True

    monkeypatch.setattr(diagnose, "base_material_check", counted)
    monkeypatch.setattr(problem.Problem, "__init__", on_gpu)
    early = diagnose.diagnose(m, "spring_mass", **kw)
    assert calls == [True] + [False] * added  # with round 1's candidates; again after an addition
    assert early.base_material == plain.base_material
    assert [(c.name, c.sse, c.evaluations) for c in early.candidates] == \
        [(c.name, c.sse, c.evaluations) for c in plain.candidates]
    np.testing.assert_array_equal(early.final_positions, plain.final_positions)
    # nothing added: the same runs, earlier; an addition: the early check's runs are spent for nothing
    assert (early.simulations > plain.simulations) if added else (early.simulations == plain.simulations)
