"""Progress reporting and cancellation shared by the command line and Blender.

Long work takes a :class:`Progress` and calls :meth:`Progress.step` as it goes.
Headless, progress is a tqdm bar on stderr; in Blender the add-on passes a
``Progress`` whose callback updates the window-manager progress bar and the
status text, and whose :meth:`cancel` is triggered by Esc.  Work checks
cancellation at every step and raises :class:`~.errors.CancelledError`.
"""

from __future__ import annotations

import sys
import threading
from typing import Callable, Optional

from .errors import CancelledError

Callback = Callable[[float, str], None]
"""Called with (fraction done in [0, 1], status text)."""

INTERRUPTED = threading.Event()
"""Set by the command line's Ctrl-C handler (:func:`unipixie.core.cli.interrupt_guard`): every progress check
then raises :class:`CancelledError`, so a run stops at its next step even when a library swallowed the
``KeyboardInterrupt`` (seen in the fault matrix: a Ctrl-C during Warp's start-up, and the job ran on)."""


class Progress:
    """A cancellable progress sink.

    Parameters
    ----------
    total:
        Number of steps of the whole job (``step`` adds to a counter).
    description:
        Short text shown before the status.
    callback:
        Receives (fraction, status text) after every update; ``None`` uses a
        tqdm bar when ``show_bar`` is true, else nothing.
    """

    def __init__(self, total: float = 1.0, description: str = "", callback: Optional[Callback] = None,
                 show_bar: bool = True):
        self.total = max(float(total), 1e-12)
        self.done = 0.0
        self.description = description
        self.status = description
        self._callback = callback
        self._cancel = threading.Event()
        self._bar = None
        if callback is None and show_bar:
            try:
                from tqdm.auto import tqdm

                self._bar = tqdm(total=self.total, desc=description, file=sys.stderr, leave=False,
                                 dynamic_ncols=True, disable=None)
            except Exception:  # tqdm missing is not fatal
                self._bar = None

    # -- cancellation -------------------------------------------------------
    def cancel(self) -> None:
        """Ask the running work to stop at its next step."""
        self._cancel.set()

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set()

    def check(self) -> None:
        """Raise :class:`CancelledError` if :meth:`cancel` was called (or Ctrl-C pressed: :data:`INTERRUPTED`)."""
        if self._cancel.is_set() or INTERRUPTED.is_set():
            raise CancelledError()

    # -- reporting ------------------------------------------------------------
    @property
    def fraction(self) -> float:
        return min(1.0, self.done / self.total)

    def step(self, amount: float = 1.0, status: str | None = None) -> None:
        """Advance by ``amount`` steps, optionally changing the status text; checks cancellation."""
        self.done += amount
        if status is not None:
            self.status = status
        if self._bar is not None:
            self._bar.update(amount)
            if status is not None:
                self._bar.set_postfix_str(status, refresh=False)
        if self._callback is not None:
            self._callback(self.fraction, self.status)
        self.check()

    def set_status(self, status: str) -> None:
        self.step(0.0, status)

    def sub(self, span: float, total: float, description: str = "") -> "SubProgress":
        """A child progress that maps its own ``total`` steps onto ``span`` steps of this one."""
        return SubProgress(self, span, total, description)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class SubProgress(Progress):
    """Progress of a sub-task, forwarded to its parent (same cancellation)."""

    def __init__(self, parent: Progress, span: float, total: float, description: str = ""):
        self.parent = parent
        self.span = float(span)
        self.total = max(float(total), 1e-12)
        self.done = 0.0
        self.description = description
        self.status = description
        self._callback = None
        self._bar = None
        self._cancel = parent._cancel

    def step(self, amount: float = 1.0, status: str | None = None) -> None:
        self.done += amount
        if status is not None:
            self.status = status
        text = f"{self.description}: {status}" if (status and self.description) else (status or self.description or None)
        self.parent.step(amount * self.span / self.total, text)


def frame_done(progress: Optional["Progress"], amount: float, status: str) -> None:
    """A solver's end of a frame: ``progress.step(amount, status)``, or without a progress (benchmarks, batches)
    still the Ctrl-C check (:data:`INTERRUPTED`), so that no simulation outlives a cancelled command."""
    if progress is not None:
        progress.step(amount, status)
    elif INTERRUPTED.is_set():
        raise CancelledError()


def silent() -> Progress:
    """A progress that shows nothing (for library calls and tests)."""
    return Progress(show_bar=False)
