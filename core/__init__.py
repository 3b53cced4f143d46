"""Core: data types, the pipeline, the command line and the Python API (no bpy here except core.blender_io)."""

__version__ = "0.1.0"
"""The package's version (also ``unipixie.__version__``; blender_manifest.toml and pyproject.toml say the same)."""
