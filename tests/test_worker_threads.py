"""The one worker-thread toolkit (core/jobs.py): start_worker, BackgroundRun, worker_job."""

import contextvars
import threading
import time

import pytest

from unipixie.core.errors import CancelledError
from unipixie.core.jobs import BackgroundRun, run_job, start_worker, wait_workers, worker_job
from unipixie.core.progress import Progress

_LABEL = contextvars.ContextVar("test_worker_label", default="unset")


def test_start_worker_returns_the_outcome_in_a_daemon_thread_with_the_callers_context():
    _LABEL.set("caller")
    seen = {}

    def fn(x):
        seen["label"] = _LABEL.get()
        seen["daemon"] = threading.current_thread().daemon
        seen["name"] = threading.current_thread().name
        _LABEL.set("worker")            # a copy: the caller's value stays
        return 2 * x

    f = start_worker(fn, 21, name="unipixie-test")
    assert wait_workers([f], timeout=5)
    assert f.result() == 42
    assert seen == {"label": "caller", "daemon": True, "name": "unipixie-test"}
    assert _LABEL.get() == "caller"


def test_start_worker_hands_any_exception_to_the_caller():
    def boom():
        raise KeyboardInterrupt("stop")

    f = start_worker(boom)
    wait_workers([f], timeout=5)
    with pytest.raises(KeyboardInterrupt, match="stop"):
        f.result()


def test_wait_workers_times_out_while_one_still_runs():
    release = threading.Event()
    slow = start_worker(release.wait, 5)
    fast = start_worker(lambda: 1)
    assert not wait_workers([slow, fast], timeout=0.05)
    release.set()
    assert wait_workers([slow, fast], timeout=5)


def test_background_run_reports_to_a_given_progress():
    progress = Progress(total=1.0, show_bar=False)

    def work(p):
        assert p is progress
        p.step(0.5, "half way")
        return "ok"

    run = BackgroundRun(work, progress=progress).start()
    assert run.wait(5)
    assert run.result() == "ok"
    assert run.fraction == pytest.approx(0.5) and run.status == "half way"


def test_worker_job_maps_its_fraction_onto_the_span_and_returns_the_result():
    gate = threading.Event()

    def work(progress):
        progress.step(0.5, "half")
        gate.wait(5)
        return 7

    job = worker_job(work, description="testing", span=(0.2, 0.6), poll_s=0.01)
    fractions = []
    for _ in range(200):
        frac, status = next(job)
        fractions.append(frac)
        if status == "half":
            break
    assert fractions[-1] == pytest.approx(0.4)          # 0.2 + 0.5 × (0.6 − 0.2)
    assert all(0.2 <= f <= 0.6 for f in fractions)
    gate.set()
    with pytest.raises(StopIteration) as stop:
        while True:
            next(job)
    assert stop.value.value == 7


def test_closing_a_worker_job_cancels_the_work_and_waits_for_it():
    ended = []

    def work(progress):
        try:
            while True:
                progress.step(0.0, "working")
                time.sleep(0.005)
        finally:
            ended.append(time.perf_counter())

    job = worker_job(work, description="testing", poll_s=0.01)
    next(job)
    job.close()
    closed = time.perf_counter()
    assert ended and ended[0] <= closed        # the worker had ended when close() returned


def test_a_worker_jobs_error_reaches_the_driver():
    def work(progress):
        raise CancelledError("cancelled in the worker")

    with pytest.raises(CancelledError, match="in the worker"):
        run_job(worker_job(work, poll_s=0.01))


def test_map_in_threads_keeps_the_order_and_runs_side_by_side():
    """Results come back in the items' order; two calls that wait for each other only finish when both run at once."""
    from unipixie.core.jobs import map_in_threads

    barrier = threading.Barrier(2, timeout=5)

    def fn(x):
        if x < 2:
            barrier.wait()  # raises BrokenBarrierError unless the first two items run at the same time
        time.sleep(0.001 * (5 - x))
        return x * x

    assert map_in_threads(fn, range(5), threads=2) == [0, 1, 4, 9, 16]
    assert map_in_threads(lambda x: x + 1, [], threads=3) == []
    assert map_in_threads(lambda x: x + 1, [1, 2], threads=1) == [2, 3]


def test_map_in_threads_raises_the_first_error_and_takes_no_new_items():
    from unipixie.core.jobs import map_in_threads

    started = []

    def fn(x):
        started.append(x)
        if x == 1:
            raise ValueError("item 1 is bad")
        time.sleep(0.05)
        return x

    with pytest.raises(ValueError, match="item 1 is bad"):
        map_in_threads(fn, range(20), threads=2)
    assert len(started) < 6  # the workers stopped taking items after the error
