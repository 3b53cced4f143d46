"""Blender I/O: the only part of ``unipixie.core`` that imports bpy.

Submodules read and write Blender data for the rest of the pipeline:
rendering views, importing meshes, writing bakes, reading measured motion,
colouring objects.  Import them only where Blender is present.
``extension_check.py`` is a standalone script run inside a Blender process.
"""

import bpy  # noqa: F401 - importing this package means Blender is required
