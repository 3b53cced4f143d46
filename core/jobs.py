"""Jobs and worker threads, one toolkit for the whole package.

A *job* is a generator that yields ``(fraction, status)`` as it goes and returns its result (rendering views,
computing features, baking); the Blender add-on drives one from a modal timer, :func:`run_job` and
:func:`run_side_by_side` drive them to their end (the command line, scripts, tests).

Long work inside a job runs in a *worker thread* so that the job's driver (Blender's UI, a side-by-side loop)
stays responsive: :func:`start_worker` is the one place that starts one (a daemon thread, in a copy of the
caller's context variables, its outcome a :class:`concurrent.futures.Future`); :class:`BackgroundRun` runs
``work(progress)`` there with a cancellable :class:`~.progress.Progress`; :func:`worker_job` is that run as a job
(closing the job — Esc — cancels the work and waits for it).  Daemon threads, not a ``ThreadPoolExecutor``,
whose threads the interpreter joins at exit: a cancelled or abandoned worker must never hold Blender or the
command line open.

Uses only :mod:`.errors` and :mod:`.progress`.
"""

from __future__ import annotations

import contextvars
import threading
from concurrent.futures import Future, wait as _wait_futures
from typing import Callable, Iterator, Optional

from .errors import CancelledError
from .progress import Progress


def start_worker(fn: Callable, *args, name: str = "unipixie-worker") -> Future:
    """Run ``fn(*args)`` in a new daemon thread named ``name``, in a copy of the calling thread's context variables.

    Returns the :class:`~concurrent.futures.Future` of its outcome: ``result()`` gives the return value or re-raises
    what ``fn`` raised (any :class:`BaseException`, a cancellation included) in the caller's thread.
    """
    future: Future = Future()
    future.set_running_or_notify_cancel()
    context = contextvars.copy_context()

    def main():
        try:
            value = context.run(fn, *args)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread through the future
            future.set_exception(exc)
        else:
            future.set_result(value)

    threading.Thread(target=main, name=name, daemon=True).start()
    return future


def wait_workers(futures, timeout: Optional[float] = None) -> bool:
    """Wait until every future of :func:`start_worker` has its outcome (at most ``timeout`` s); True when all have."""
    futures = list(futures)
    _wait_futures(futures, timeout=timeout)
    return all(f.done() for f in futures)


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity where the system says, else all of them)."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def map_in_threads(fn: Callable, items, threads: int) -> list:
    """``[fn(item) for item in items]`` computed by up to ``threads`` worker threads (:func:`start_worker`), each
    taking the next item as it finishes one; results in the items' order.  Worth it where ``fn`` spends its time
    outside the interpreter lock (compiled kernels).  When a call raises, the workers take no new items and the
    first exception (in the order they happened) is raised here once every worker has stopped."""
    items = list(items)
    threads = max(1, min(int(threads), len(items)))
    if threads <= 1:
        return [fn(item) for item in items]
    results: list = [None] * len(items)
    lock = threading.Lock()
    state = {"next": 0, "error": None}

    def work() -> None:
        while True:
            with lock:
                i = state["next"]
                if i >= len(items) or state["error"] is not None:
                    return
                state["next"] = i + 1
            try:
                results[i] = fn(items[i])
            except BaseException as exc:  # noqa: BLE001 - raised in the caller's thread below
                with lock:
                    if state["error"] is None:
                        state["error"] = exc
                return

    wait_workers([start_worker(work, name=f"unipixie-map-{k}") for k in range(threads)])
    if state["error"] is not None:
        raise state["error"]
    return results


class BackgroundRun:
    """Run ``work(progress)`` in a worker thread (:func:`start_worker`); the caller polls and may cancel.

    The Blender operator yields between polls so the UI stays responsive; cancelling sets the shared
    :class:`~.progress.Progress`'s flag, which the solvers check at every step.  ``progress``: the run's progress
    (default: a new one, no bar, described by ``description``).
    """

    def __init__(self, work: Callable[[Progress], object], description: str = "", progress: Optional[Progress] = None,
                 name: str = "unipixie-bake"):
        self.progress = progress if progress is not None else Progress(description=description, show_bar=False)
        self._work = work
        self._name = name
        self._future: Optional[Future] = None

    def start(self) -> "BackgroundRun":
        self._future = start_worker(self._work, self.progress, name=self._name)
        return self

    @property
    def done(self) -> bool:
        return self._future is not None and self._future.done()

    def wait(self, timeout: Optional[float] = None) -> bool:
        if self._future is not None:
            wait_workers([self._future], timeout)
        return self.done

    @property
    def fraction(self) -> float:
        return self.progress.fraction

    @property
    def status(self) -> str:
        return self.progress.status or ""

    def cancel(self, wait: bool = True) -> None:
        self.progress.cancel()
        if wait:
            self.wait()

    def result(self):
        """The work's return value; re-raises its exception in the caller's thread."""
        if not self.done:
            raise RuntimeError("the background run has not finished")
        return self._future.result()


def worker_job(work: Callable[[Progress], object], description: str = "", progress: Optional[Progress] = None,
               span: tuple = (0.0, 1.0), poll_s: float = 0.05, name: str = "unipixie-bake",
               idle_status: str = "") -> Iterator[tuple]:
    """:class:`BackgroundRun` as a job: yields ``(fraction, status)`` while ``work(progress)`` runs, the run's
    fraction mapped onto ``span`` = (start, end) of the job's own and its status (``idle_status``, else
    ``description``, while it has none); closing the generator (Esc) cancels the work and waits for it.  Returns the
    work's result (re-raises its exception)."""
    run = BackgroundRun(work, description=description, progress=progress, name=name).start()
    lo, hi = float(span[0]), float(span[1])
    try:
        while not run.wait(poll_s):
            yield lo + (hi - lo) * run.fraction, run.status or idle_status or description
    finally:
        if not run.done:
            run.cancel(wait=True)
    return run.result()


def run_job(job, progress=None):
    """Drive a job generator that yields ``(fraction, status)`` to its end and return its return value.

    ``progress`` (a :class:`~.progress.Progress`) is advanced to each fraction; when it is cancelled its
    :class:`~.errors.CancelledError` propagates and the generator is closed (its clean-up runs).
    """
    try:
        while True:
            try:
                fraction, status = next(job)
            except StopIteration as stop:
                return stop.value
            if progress is not None:
                progress.step(max(0.0, float(fraction) * progress.total - progress.done), status)
    finally:
        job.close()


def run_side_by_side(jobs, max_running: int = 2, on_done=None) -> list:
    """Drive several job generators at once, at most ``max_running`` of them started at a time, and return their
    results in order (an exception a job raised takes the place of its result; the others go on).

    jobs: ``[(make_job, progress)]`` — ``make_job()`` creates the generator when a place is free; ``progress`` (or
    ``None``) follows its fraction.  Jobs whose heavy work runs in a worker thread (a bake's simulation: Warp's CPU
    kernels use one core each) then share the CPU cores, while their Blender parts (reading, writing) stay in this
    thread.  A :class:`~.errors.CancelledError` (a progress cancelled, Ctrl-C) closes every started job and is
    raised.  ``on_done(index, result)`` is called as each job ends (in this thread).
    """
    pending = list(enumerate(jobs))
    running: dict = {}
    results: list = [None] * len(jobs)
    try:
        while pending or running:
            while pending and len(running) < max(1, int(max_running)):
                i, (make, progress) = pending.pop(0)
                running[i] = (make(), progress)
            for i in list(running):
                gen, progress = running[i]
                try:
                    fraction, status = next(gen)
                except StopIteration as stop:
                    results[i] = stop.value
                except CancelledError:
                    raise
                except Exception as exc:        # noqa: BLE001 - handed to the caller as this job's result
                    results[i] = exc
                    gen.close()
                else:
                    if progress is not None:
                        progress.step(max(0.0, float(fraction) * progress.total - progress.done), status)
                    continue
                del running[i]
                if on_done is not None:
                    on_done(i, results[i])
    finally:
        for gen, _ in running.values():
            gen.close()
    return results
