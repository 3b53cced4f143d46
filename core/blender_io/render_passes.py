"""Surface-appearance render passes (a G-buffer) of the views, for the appearance extractor.

Cycles renders, with the colour image and the depth, per pixel of the nearest surface:

* ``base_color`` — the Principled BSDF's *Base Color* (scene-linear RGB, textures included),
* ``roughness`` and ``metallic`` — its *Roughness* and *Metallic* inputs (0–1),
* ``normal`` — Cycles' Normal pass: the shading normal in the world frame of the temporary scene, i.e.
  the axes of the normalised cube (the normalisation has no rotation, so these are the object's world axes;
  independent of where the cameras are).  Cycles turns it towards the viewer on back faces.

The first three are Arbitrary Output Variables (AOVs): every material of the subject is *copied* into the
render's temporary scene and the copy gets AOV Output nodes fed from the same sockets as its Principled
BSDF's inputs (the linked node's output when an input is linked, else the input's value).  The user's
materials are never changed; the copies are data-blocks created during the render and removed with it.
A material without a Principled BSDF at the top level of its node tree (a node group, a Diffuse BSDF only,
an emission) reports its viewport values (*Viewport Display* colour, roughness, metallic), and a face
without a material Blender's default (grey 0.8, roughness 0.5, metallic 0).
Every sample of such a render is taken at the pixel's centre (:data:`PASS_FILTER_WIDTH`).  Cycles averages a
pass over a pixel's samples, and samples that miss the object add 0, so a pixel on a
silhouette holds the value times its coverage: the passes are divided by the coverage (the colour image's
alpha) and the normal is scaled back to unit length.  Pixels less than half covered (:data:`MIN_COVERAGE`)
and background pixels are NaN (no value) in every pass.
"""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from .compositor import file_output_node

PASS_CHANNELS = {"base_color": 3, "roughness": 1, "metallic": 1, "normal": 3}
"""The passes written per view and their channel counts (what :attr:`Views.passes` holds)."""
_AOVS = {"base_color": ("unipixie_base_color", "COLOR", "Base Color"),
         "roughness": ("unipixie_roughness", "VALUE", "Roughness"),
         "metallic": ("unipixie_metallic", "VALUE", "Metallic")}
"""pass -> (AOV name, AOV type, Principled BSDF input it copies)."""
PASS_FILTER_WIDTH = 0.01
"""Cycles' pixel filter width (pixels) when the passes are rendered: Cycles' smallest, so every sample is
taken at the pixel's centre and a pixel's pass values are those of one surface point (the default 1.5-pixel
Blackman-Harris filter mixes neighbouring pixels and widens a part boundary by about a pixel).  It applies to
the colour image of such a render too, which is then not anti-aliased."""
MIN_COVERAGE = 0.5
"""Pixels whose coverage by the object (alpha) is below this hold no pass values (NaN)."""
_DEFAULT_SURFACE = {"base_color": (0.8, 0.8, 0.8), "roughness": 0.5, "metallic": 0.0}
"""What Blender renders a face without a material with (its default surface)."""


def _principled(tree):
    """The Principled BSDF that feeds the active Material Output, else any Principled BSDF, else None."""
    if tree is None:
        return None
    nodes = [n for n in tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"]
    if not nodes:
        return None
    outputs = [n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial" and n.is_active_output]
    if outputs:
        fed, todo = set(), [outputs[0]]
        while todo:                                  # walk the links upstream of the output
            node = todo.pop()
            for socket in node.inputs:
                for link in socket.links:
                    if link.from_node.name not in fed:
                        fed.add(link.from_node.name)
                        todo.append(link.from_node)
        for n in nodes:
            if n.name in fed:
                return n
    return nodes[0]


def _add_aovs(material, fallback: dict) -> None:
    """AOV Output nodes in ``material`` (a temporary copy) carrying its base colour, roughness and metallic."""
    tree = material.node_tree
    if tree is None:
        material.use_nodes = True
        tree = material.node_tree
    bsdf = _principled(tree)
    for key, (aov_name, kind, socket_name) in _AOVS.items():
        node = tree.nodes.new("ShaderNodeOutputAOV")
        node.aov_name = aov_name
        target = node.inputs["Color" if kind == "COLOR" else "Value"]
        source = bsdf.inputs.get(socket_name) if bsdf is not None else None
        if source is not None and source.is_linked:
            tree.links.new(source.links[0].from_socket, target)
        else:
            value = source.default_value if source is not None else fallback[key]
            if kind == "COLOR":
                target.default_value = (*tuple(value)[:3], 1.0)
            else:
                target.default_value = float(value)


def prepare_pass_materials(meshes) -> None:
    """Give the temporary mesh copies ``meshes`` (``[(object, mesh, matrix)]`` of
    :func:`.render.evaluated_meshes`) copies of their materials with the AOV nodes (module docstring).
    Only data-blocks created here are changed; the caller's ``remove_new_ids`` removes them."""
    copies: dict = {}
    default = None
    for _, mesh, _ in meshes:
        if len(mesh.materials) == 0:
            if default is None:
                default = bpy.data.materials.new("UniPixie default surface")
                _add_aovs(default, _DEFAULT_SURFACE)
            mesh.materials.append(default)
            continue
        for i, mat in enumerate(mesh.materials):
            if mat is None:
                if default is None:
                    default = bpy.data.materials.new("UniPixie default surface")
                    _add_aovs(default, _DEFAULT_SURFACE)
                mesh.materials[i] = default
                continue
            if mat.name_full not in copies:
                copy = mat.copy()
                _add_aovs(copy, {"base_color": tuple(mat.diffuse_color)[:3], "roughness": mat.roughness,
                                 "metallic": mat.metallic})
                copies[mat.name_full] = copy
            mesh.materials[i] = copies[mat.name_full]


def setup_pass_outputs(scene, tree, layers, out_dir: Path):
    """Enable the Normal pass and the AOVs on the scene's view layer and write every pass as a 32-bit float
    EXR through one File Output node of the compositor ``tree`` (fed by the Render Layers node ``layers``).
    Returns the node (set its ``file_name`` per view)."""
    view_layer = scene.view_layers[0]
    view_layer.use_pass_normal = True
    for aov_name, kind, _ in _AOVS.values():
        aov = view_layer.aovs.add()
        aov.name = aov_name
        aov.type = kind
    node = file_output_node(tree, out_dir, "OPEN_EXR", "RGB", "32")
    for name in PASS_CHANNELS:
        source = "Normal" if name == "normal" else _AOVS[name][0]
        node.file_output_items.new("VECTOR" if name == "normal" else ("RGBA" if name == "base_color" else "FLOAT"),
                                   f"pass_{name}")
        tree.links.new(layers.outputs[source], node.inputs[f"pass_{name}"])
    return node


def unpremultiplied(passes: dict, alpha: np.ndarray, depth: np.ndarray) -> dict:
    """One view's passes (name -> (H, W, C)) divided by the pixels' coverage ``alpha`` (H, W) in [0, 1], the
    normal rescaled to unit length; NaN where ``alpha`` < :data:`MIN_COVERAGE` or ``depth`` (H, W) is not
    finite (background)."""
    valid = (np.asarray(alpha) >= MIN_COVERAGE) & np.isfinite(depth)
    a = np.maximum(np.asarray(alpha, dtype=np.float32), MIN_COVERAGE)[..., None]
    out = {}
    for name, px in passes.items():
        if name == "normal":
            length = np.linalg.norm(px, axis=-1, keepdims=True)
            value = px / np.maximum(length, 1e-6)
        else:
            value = px / a
        out[name] = np.where(valid[..., None], value, np.nan).astype(np.float32)
    return out


def read_passes(out_dir: Path, prefix: str, read_exr, find_output) -> dict:
    """The passes of one view written by :func:`setup_pass_outputs`: name -> (H, W, C) float32, rows top-down.
    ``read_exr(path)`` returns the (H, W, channels) pixels top-down, ``find_output`` finds the file."""
    out = {}
    for name, channels in PASS_CHANNELS.items():
        px = read_exr(find_output(out_dir, prefix, f"pass_{name}", ".exr"))
        out[name] = np.ascontiguousarray(px[..., :channels], dtype=np.float32)
    return out


SPLIT_BOX_LOOKS = (("red rough", (0.8, 0.05, 0.05), 0.9, 0.0), ("blue metal", (0.05, 0.1, 0.8), 0.2, 1.0))
"""(name, base colour (linear RGB), roughness, metallic) of the two halves of :func:`split_box`."""


def split_box(scene, looks=SPLIT_BOX_LOOKS):
    """A 1 × 0.5 × 0.5 m box cut at x = 0 into two materials (x < 0: ``looks[0]``, x > 0: ``looks[1]``), built
    by hand and linked into ``scene`` (the caller removes it): the object whose part boundary the appearance
    tests and the feature probe measure.  Returns the object."""
    import bmesh

    mesh = bpy.data.meshes.new("split box")
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=1.0)
    bmesh.ops.scale(bm, vec=(1.0, 0.5, 0.5), verts=bm.verts)
    bmesh.ops.bisect_plane(bm, geom=bm.verts[:] + bm.edges[:] + bm.faces[:], plane_co=(0, 0, 0), plane_no=(1, 0, 0))
    for f in bm.faces:
        f.material_index = 0 if f.calc_center_median().x < 0 else 1
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new("split box", mesh)
    scene.collection.objects.link(obj)
    for name, colour, roughness, metallic in looks:
        mat = bpy.data.materials.new(name)
        if mat.node_tree is None:
            mat.use_nodes = True
        bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (*colour, 1.0)
        bsdf.inputs["Roughness"].default_value = roughness
        bsdf.inputs["Metallic"].default_value = metallic
        mesh.materials.append(mat)
    return obj
