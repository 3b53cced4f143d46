"""Running long work from an operator: progress bar, status text, Esc to cancel, errors as reports.

A job is a generator function ``make_job(self, context)`` that does its work in
short chunks and ``yield``s ``(fraction, status_text)`` between them; its
``return`` value is passed to ``finish(self, context, result)``.

* ``invoke`` (a user click in a window) runs the generator one chunk per timer
  tick as a modal operator: the UI stays responsive, the window-manager progress
  bar and the status bar show progress, and **Esc** closes the generator (its
  ``finally`` blocks clean up, so no half-written data is left).
* ``execute`` (scripts, ``bpy.ops`` calls, background mode, tests) runs it to the
  end synchronously.

A :class:`~unipixie.core.errors.UserError` becomes an ``ERROR`` report and is kept
in the object's ``unipixie.last_error`` for the panel — never a traceback popup.
"""

from __future__ import annotations

import traceback

import bpy

from ..core.errors import CancelledError, UserError


def _set_status(context, text: str | None) -> None:
    try:
        context.workspace.status_text_set(text)
    except Exception:  # no workspace in background mode
        pass
    context.window_manager.unipixie_status = text or ""


class JobOperator:
    """Mixin for operators that run a job (see the module docstring).  Subclasses define
    ``make_job(self, context)`` and may override ``finish`` and ``on_cancel``."""

    _timer = None
    _job = None
    _target_name = ""

    # -- to override ---------------------------------------------------------------
    def make_job(self, context):  # pragma: no cover - abstract
        raise NotImplementedError

    def finish(self, context, result):
        return {"FINISHED"}

    def on_cancel(self, context):
        """Called after Esc, once the generator has been closed."""

    def job_target(self, context):
        """The object whose ``unipixie.status`` / ``last_error`` reflect this job (default: active object)."""
        return getattr(context, "active_object", None)

    # -- error handling ---------------------------------------------------------------
    def _fail(self, context, exc: Exception):
        target = self.job_target(context)
        if isinstance(exc, UserError):
            msg = str(exc)
        else:
            msg = f"internal error: {type(exc).__name__}: {exc} (details in the system console)"
            traceback.print_exc()
        self.report({"ERROR"}, msg)
        if target is not None and hasattr(target, "unipixie"):
            target.unipixie.last_error = msg
            target.unipixie.status = "failed"
        _set_status(context, None)
        return {"CANCELLED"}

    def _start(self, context):
        target = self.job_target(context)
        if target is not None and hasattr(target, "unipixie"):
            target.unipixie.last_error = ""
            target.unipixie.status = "running"

    # -- synchronous path ---------------------------------------------------------------
    def execute(self, context):
        self._start(context)
        job = None
        try:
            job = self.make_job(context)
            result = None
            while True:
                try:
                    next(job)
                except StopIteration as stop:
                    result = stop.value
                    break
            return self.finish(context, result)
        except Exception as exc:
            if job is not None:
                job.close()
            return self._fail(context, exc)

    # -- modal path ---------------------------------------------------------------------
    def invoke(self, context, event):
        wm = context.window_manager
        if bpy.app.background or not wm.windows:
            return self.execute(context)
        self._start(context)
        try:
            self._job = self.make_job(context)
        except Exception as exc:
            return self._fail(context, exc)
        wm.progress_begin(0.0, 1.0)
        self._timer = wm.event_timer_add(0.01, window=context.window)
        wm.modal_handler_add(self)
        _set_status(context, f"{self.bl_label}: starting (Esc to cancel)")
        return {"RUNNING_MODAL"}

    def _stop_modal(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        _set_status(context, None)

    def modal(self, context, event):
        if event.type == "ESC":
            self._job.close()
            self._stop_modal(context)
            self.on_cancel(context)
            target = self.job_target(context)
            if target is not None and hasattr(target, "unipixie"):
                target.unipixie.status = "cancelled"
            self.report({"WARNING"}, f"{self.bl_label}: cancelled")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            fraction, status = next(self._job)
        except StopIteration as stop:
            self._stop_modal(context)
            try:
                return self.finish(context, stop.value)
            except Exception as exc:
                return self._fail(context, exc)
        except CancelledError:
            self._stop_modal(context)
            self.on_cancel(context)
            return {"CANCELLED"}
        except Exception as exc:
            self._stop_modal(context)
            return self._fail(context, exc)
        context.window_manager.progress_update(float(fraction))
        _set_status(context, f"{self.bl_label}: {status}  ({100 * float(fraction):.0f} %, Esc to cancel)")
        return {"RUNNING_MODAL"}
