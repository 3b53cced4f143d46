"""Compositor File Output nodes for the view renders (colour PNG, depth and pass EXRs): one place that says how
an image leaves Blender's compositor (Blender 5.0: compositor node groups, ``file_output_items``)."""

from __future__ import annotations

from pathlib import Path


def file_output_node(tree, out_dir: Path, file_format: str, color_mode: str, color_depth: str):
    """A File Output node in ``tree`` writing into ``out_dir``.

    file_format: ``"PNG"`` or ``"OPEN_EXR"``; color_mode: ``"RGBA"``, ``"RGB"``, ...; color_depth: ``"8"`` (PNG) or
    ``"32"`` (float EXR).  Add its inputs with ``node.file_output_items.new(socket_type, name)``.
    """
    node = tree.nodes.new("CompositorNodeOutputFile")
    node.directory = str(out_dir)
    node.format.media_type = "IMAGE"
    node.format.file_format = file_format
    node.format.color_mode = color_mode
    node.format.color_depth = color_depth
    return node
