"""Who registers the add-on's object properties (``Object.unipixie``) where the add-on is not enabled.

:mod:`unipixie.core.blender_io` reads and writes the settings the add-on stores on objects; outside an enabled
add-on (the command line, scripts, tests) it registers their property group for the duration
(:func:`unipixie.core.blender_io.bake.registered_properties`).  That property group is the add-on's
(``unipixie_addon/properties.py``), a layer above core, so core does not import it: the package root
(``unipixie/__init__.py``, imported before any of its modules) hands it over with :func:`set_registrar`.
This module imports nothing (importing it never imports bpy).
"""

from __future__ import annotations

from typing import Callable, Optional

_REGISTRAR: list = [None]


def set_registrar(register: Callable[[], Callable[[], None]]) -> None:
    """Install ``register``: a function that registers the property group and returns the function that
    unregisters it again."""
    _REGISTRAR[0] = register


def registrar() -> Callable[[], Callable[[], None]]:
    """The installed registrar (see :func:`set_registrar`); a ``RuntimeError`` (a bug) when none is."""
    register: Optional[Callable] = _REGISTRAR[0]
    if register is None:
        raise RuntimeError("no registrar of the add-on's object properties is installed "
                           "(the package root installs it when it is imported)")
    return register
