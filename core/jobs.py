"""Driving job generators: a job is a generator that yields ``(fraction, status)`` as it goes and returns its
result (rendering views, computing features, baking); the Blender add-on drives one from a modal timer, these
functions drive them to their end (the command line, scripts, tests)."""

from __future__ import annotations

from .errors import CancelledError


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
