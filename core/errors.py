"""Errors a user can act on.

Every problem caused by input (a bad file, a wrong argument, a missing model
file, an output that cannot be written) is raised as :class:`UserError` with a
message that names the problem and, where there is one, the remedy.  The
command line prints such errors as one line and exits with the error's
``exit_code``; the Blender add-on shows them as a report.  Anything else is a
bug: the command line prints one line, writes the traceback to a crash log
and exits with status 1 (``UNIPIXIE_TRACEBACK=1`` shows it instead).

Exit statuses of every ``unipixie`` command (one table, README.md "Exit statuses"):

====  ==========================================================================
 0    done (a diagnosis verdict of "not explained" is a result, not a failure)
 1    internal error (a bug): one line, the traceback in a crash log
 2    bad input or environment: a wrong argument or file, an output that
      cannot be written (full disk, read-only, locked by another run)
 3    the simulation ran and failed (diverged, blew up, needed too many steps)
130   cancelled (Ctrl-C, Esc)
====  ==========================================================================
"""

from __future__ import annotations

# imports nothing at the top: the command line's start-up guard (core/start_up.py) needs EXIT_CANCELLED first


EXIT_OK = 0
EXIT_INTERNAL_ERROR = 1
EXIT_BAD_INPUT = 2
EXIT_SIMULATION_FAILED = 3
EXIT_CANCELLED = 130
EXIT_CODES = {EXIT_OK: "done", EXIT_INTERNAL_ERROR: "internal error (a bug)",
              EXIT_BAD_INPUT: "bad input or environment (refused with a one-line message)",
              EXIT_SIMULATION_FAILED: "the simulation failed", EXIT_CANCELLED: "cancelled"}
"""The exit statuses of every command (see the module docstring)."""


class UserError(Exception):
    """A problem with the user's input or environment, with a one-line explanation."""

    exit_code = EXIT_BAD_INPUT


class CancelledError(UserError):
    """The user cancelled a long-running job (Esc in Blender, Ctrl-C headless)."""

    exit_code = EXIT_CANCELLED

    def __init__(self, message: str = "cancelled by the user"):
        super().__init__(message)


class SimulationDiverged(UserError):
    """A solver produced NaN/inf or lost particles; the message names the frame and a remedy."""

    exit_code = EXIT_SIMULATION_FAILED


def read_npz(path, what: str = "archive") -> dict:
    """Every array of the ``.npz`` file ``path``, by key, loaded without pickles (an object array is refused); a
    missing file, or one that is not a readable ``.npz``, is a :class:`UserError` that names the file and ``what``
    it should have been (``"archive"``, ``"training sample"``)."""
    from pathlib import Path

    import numpy as np

    if not Path(path).is_file():
        raise UserError(f"{path}: file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # a corrupt zip, not an npz, a lone .npy array (no .files), an object array, ...
        raise UserError(f"{path}: not a readable .npz {what} ({type(exc).__name__}: {exc})") from None


def read_json(path):
    """The parsed contents of the JSON file ``path``; a file that is not valid JSON is a :class:`UserError`
    that names it (whether the file exists is the caller's check, with its own remedy)."""
    import json
    from pathlib import Path

    try:
        return json.loads(Path(path).read_bytes().decode("utf-8"))
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON ({exc})") from None
    except UnicodeDecodeError:
        raise UserError(f"{path}: not valid JSON (not UTF-8 text)") from None
    except RecursionError:
        raise UserError(f"{path}: not valid JSON (nested too deeply)") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read it ({exc.strerror or exc})") from None
