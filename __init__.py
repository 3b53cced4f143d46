"""UniPixie: give a 3D object physics.

Outside Blender this directory is the Python package ``unipixie``; inside
Blender (4.2+) it is the extension ``bl_ext.<repo>.unipixie``.  Importing it
never imports ``bpy``: only :func:`register` does, through
:mod:`.unipixie_addon`.  It sits above every layer (docs/DEVELOPING.md, Map): it hands core the way
to register the add-on's object properties (:mod:`.core.property_registration`).
"""

from .core import start_up as _start_up

_start_up.guard_if_command_line()  # first: Ctrl-C while the command line starts ends it at once (core/start_up.py)

from .core import __version__  # noqa: E402,F401 - the version lives in core (below everything that prints it)
from .core import property_registration as _property_registration  # noqa: E402


def _register_object_properties():
    """Register the add-on's object properties alone (for core.blender_io outside an enabled add-on); returns
    the function that unregisters them."""
    from .unipixie_addon import properties

    properties.register()
    return properties.unregister


_property_registration.set_registrar(_register_object_properties)


def register():
    """Blender entry point: register the add-on's UI (properties, operators, panels)."""
    from . import unipixie_addon

    unipixie_addon.register()


def unregister():
    """Blender entry point: remove everything :func:`register` added."""
    from . import unipixie_addon

    unipixie_addon.unregister()
