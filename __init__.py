"""UniPixie: give a 3D object physics.

Outside Blender this directory is the Python package ``unipixie``; inside
Blender (4.2+) it is the extension ``bl_ext.<repo>.unipixie``.  Importing it
never imports ``bpy``: only :func:`register` does, through
:mod:`.unipixie_addon`.
"""

from .core import __version__  # noqa: F401 - the version lives in core (below everything that prints it)


def register():
    """Blender entry point: register the add-on's UI (properties, operators, panels)."""
    from . import unipixie_addon

    unipixie_addon.register()


def unregister():
    """Blender entry point: remove everything :func:`register` added."""
    from . import unipixie_addon

    unipixie_addon.unregister()
