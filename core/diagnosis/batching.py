"""Fits side by side, their simulations batched together.

A diagnosis fits every candidate effect; each fit is a short sequence of simulation requests (a start
grid, then one Levenberg–Marquardt iteration after another), each request only a few parameter sets.  On
a GPU a batch of a few environments costs about as much as one, so running the fits one after another
leaves it mostly idle.  :class:`BatchGate` runs each fit in its own thread; whenever every fit still
running waits for simulations, the calling thread runs all their parameter sets as one batch and hands
each fit its results.  The simulations themselves (Warp launches, progress callbacks) are run from the
calling thread (which may share a batch's runs among threads of its own where the solver allows it:
:meth:`.problem.Problem._run_now`); the fits' own work between requests is small NumPy algebra.  A job may itself run jobs
side by side (a fit of two regions, say): they join the others while it waits for them.

With a solver whose batched environments do not influence each other (MPM: each has its own time step)
the results are identical to running the fits one after another; a solver whose batch shares a time step
is run one parameter set per launch (``max_batch`` 1), with the same guarantee.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Sequence

from ..jobs import start_worker, wait_workers


@dataclass
class _Request:
    """The parameter sets one fit waits for: ``items`` go to ``run(items, key)`` together with other fits' items
    of the same ``key``; ``result`` (a list, one entry per item) or ``error`` is set by the calling thread."""

    items: list
    key: Any
    result: Optional[list] = None
    error: Optional[BaseException] = None
    done: bool = False


@dataclass
class BatchGate:
    """Joins the simulation requests of jobs running in threads into shared batches.

    run: ``run(items, key) -> list`` simulates ``items`` (parameter sets of one kind ``key``, e.g. one prepared
    simulation) and returns one result per item; it is only ever called on the thread that calls :meth:`map`.
    """

    run: Callable[[list, Any], list]
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _pending: list = field(default_factory=list)
    _running: int = 0  # jobs alive
    _waiting: int = 0  # jobs waiting for their own nested jobs (they make no requests meanwhile)
    _failed: Optional[BaseException] = None
    _local: threading.local = field(default_factory=threading.local)

    def in_job(self) -> bool:
        """Is the current thread one of :meth:`map`'s jobs (whose requests must go through :meth:`request`)?"""
        return getattr(self._local, "job", False)

    def request(self, items: list, key: Any = None) -> list:
        """From a job: wait until ``items`` have been run (with the other jobs' requests) and return their results."""
        req = _Request(list(items), key)
        with self._cond:
            if self._failed is not None:
                raise self._failed
            self._pending.append(req)
            self._cond.notify_all()
            while not req.done:
                self._cond.wait()
        if req.error is not None:
            raise req.error
        return req.result

    def map(self, jobs: Sequence[Callable[[], Any]]) -> list:
        """Run ``jobs`` (callables without arguments) side by side; returns their results in order.

        If a job raises (or a batch does, e.g. a cancellation), every other job is stopped at its next request
        and the first such exception is raised here once all jobs have ended.
        """
        jobs = list(jobs)
        if not jobs:
            return []
        if self.in_job():
            return self._map_nested(jobs)
        self._failed = None
        self._running = len(jobs)
        self._waiting = 0
        workers, results, _ = self._spawn(jobs)
        while True:
            with self._cond:
                while not self._batch_ready():
                    self._cond.wait()
                batch, self._pending = self._pending, []
                if self._failed is not None:
                    self._finish(batch, error=self._failed)
                    if not self._running:
                        break
                    continue
                if not batch:  # every job has ended
                    break
            try:
                self._execute(batch)
            except BaseException as exc:  # noqa: BLE001 - stops every job, raised below
                with self._cond:
                    if self._failed is None:
                        self._failed = exc
                    self._finish(batch, error=exc)
        wait_workers(workers)
        failed, self._failed = self._failed, None
        if failed is not None:
            raise failed
        return results

    def _spawn(self, jobs: list) -> tuple[list, list, list]:
        """Start one worker per job (already counted in ``_running``); returns (their futures, results, [jobs ended]).
        A job's exception stops every job (``_failed``) and is raised by the outermost :meth:`map`."""
        results: list = [None] * len(jobs)
        done = [0]

        def work(i: int) -> None:
            self._local.job = True
            try:
                results[i] = jobs[i]()
            except BaseException as exc:  # noqa: BLE001 - handed to the calling thread
                with self._cond:
                    if self._failed is None:
                        self._failed = exc
            finally:
                with self._cond:
                    self._running -= 1
                    done[0] += 1
                    self._cond.notify_all()

        # each job runs in a copy of the starting thread's context (its context variables, e.g. counters)
        return [start_worker(work, i, name=f"unipixie-fit-{i}") for i in range(len(jobs))], results, done

    def _batch_ready(self) -> bool:
        """Should the calling thread act now (the lock held)?  Yes when every job has ended, or when every job that
        can make requests is waiting in one (after a failure: as soon as any request waits, to fail it)."""
        if not self._running:
            return True
        if self._failed is not None:
            return bool(self._pending)
        return bool(self._pending) and len(self._pending) >= self._running - self._waiting

    def _map_nested(self, jobs: list) -> list:
        """:meth:`map` called from a job: its jobs join the running ones (the calling job waits for them and
        makes no requests meanwhile); the batches are still run by the thread of the outer :meth:`map`."""
        with self._cond:
            self._running += len(jobs)
            self._waiting += 1  # the caller makes no requests while its jobs run
            self._cond.notify_all()
        workers, results, done = self._spawn(jobs)
        with self._cond:
            while done[0] < len(jobs):
                self._cond.wait()
            self._waiting -= 1
            self._cond.notify_all()
            failed = self._failed
        wait_workers(workers)
        if failed is not None:
            raise failed
        return results

    # ------------------------------------------------------------------ the calling thread
    def _execute(self, batch: list) -> None:
        """Run the pending requests: one ``run`` per key with every request's items, in request order."""
        by_key: dict = {}
        for req in batch:
            by_key.setdefault(id(req.key), []).append(req)
        for reqs in by_key.values():
            items = [item for req in reqs for item in req.items]
            out = self.run(items, reqs[0].key)
            at = 0
            with self._cond:
                for req in reqs:
                    req.result = list(out[at:at + len(req.items)])
                    at += len(req.items)
                self._finish(reqs)

    def _finish(self, reqs: list, error: Optional[BaseException] = None) -> None:
        """Mark ``reqs`` done (with ``error`` if given) and wake their jobs; the caller holds the lock."""
        for req in reqs:
            if not req.done:
                req.error = error if req.result is None else None
                req.done = True
        self._cond.notify_all()
