"""Long work in a worker thread: :class:`BackgroundRun` runs ``work(progress)`` (a bake's :func:`simulate`, the
pipeline's steps) in a daemon thread so that the Blender UI stays responsive; Esc cancels through the shared
:class:`~unipixie.core.progress.Progress`.

Uses only :mod:`unipixie.core.progress`.
"""

from __future__ import annotations

import threading
from typing import Callable, Optional

from ..progress import Progress


class BackgroundRun:
    """Run ``work(progress)`` in a daemon thread; the caller polls and may cancel.

    The Blender operator yields between polls so the UI stays responsive; cancelling sets the
    shared :class:`Progress`'s flag, which the solver checks at every step.
    """

    def __init__(self, work: Callable[[Progress], object], description: str = ""):
        self.progress = Progress(description=description, show_bar=False)
        self._work = work
        self._result = None
        self._error: Optional[BaseException] = None
        self._thread = threading.Thread(target=self._main, name="unipixie-bake", daemon=True)

    def _main(self):
        try:
            self._result = self._work(self.progress)
        except BaseException as exc:  # handed to the caller's thread
            self._error = exc

    def start(self) -> "BackgroundRun":
        self._thread.start()
        return self

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: Optional[float] = None) -> bool:
        self._thread.join(timeout)
        return self.done

    @property
    def fraction(self) -> float:
        return self.progress.fraction

    @property
    def status(self) -> str:
        return self.progress.status or ""

    def cancel(self, wait: bool = True) -> None:
        self.progress.cancel()
        if wait and self._thread.is_alive():
            self._thread.join()

    def result(self):
        """The work's return value; re-raises its exception in the caller's thread."""
        if not self.done:
            raise RuntimeError("the background run has not finished")
        if self._error is not None:
            raise self._error
        return self._result
