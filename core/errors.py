"""Errors a user can act on.

Every problem caused by input (a bad file, a wrong argument, a missing model
file) is raised as :class:`UserError` with a message that names the problem
and, where there is one, the remedy.  The command line prints such errors as
one line and exits with status 2; the Blender add-on shows them as a report.
Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import json
from pathlib import Path


class UserError(Exception):
    """A problem with the user's input or environment, with a one-line explanation."""

    exit_code = 2


class CancelledError(UserError):
    """The user cancelled a long-running job (Esc in Blender, Ctrl-C headless)."""

    exit_code = 130

    def __init__(self, message: str = "cancelled by the user"):
        super().__init__(message)


class SimulationDiverged(UserError):
    """A solver produced NaN/inf or lost particles; the message names the frame and a remedy."""

    exit_code = 3


def read_json(path):
    """The parsed contents of the JSON file ``path``; a file that is not valid JSON is a :class:`UserError`
    that names it (whether the file exists is the caller's check, with its own remedy)."""
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON ({exc})") from None
