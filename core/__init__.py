"""Core: data types, the pipeline, the command line and the Python API (no bpy here except core.blender_io)."""
