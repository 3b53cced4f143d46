"""The ground under an armature bake: a Geometry Nodes modifier after the bake's Armature that lifts every vertex
below the ground plane straight up onto it, as the LBS solver does with its tracked points
(:func:`add_ground_lift`).

Uses bpy, numpy and :mod:`.writing`.
"""

from __future__ import annotations

import bpy
import numpy as np

from ...bake import BakeObject
from .writing import PREFIX, WriteRecord, unique_name


def add_ground_lift(obj, bo: BakeObject, ground_height: float, record: WriteRecord) -> None:
    """A Geometry Nodes modifier right after the bake's Armature that lifts every vertex below the world
    plane z = ``ground_height`` (metres) straight up onto it, as the LBS solver does with its tracked
    points (:func:`unipixie.core.bake.plan_armature`).

    The object's transform at bake time is folded into the node constants: world z = a·p + b of the
    local position p, and a world lift dz is the local offset dz·c with c = S⁻¹ e_z (S the object's
    world-from-local map, Blender units).  The node group is the bake's own and is removed with it.
    """
    S = np.asarray(bo.matrix_world, dtype=np.float64)
    a, b = S[2, :3], float(S[2, 3])
    c = np.linalg.inv(S[:3, :3])[:, 2]
    h = float(ground_height) / bo.unit_scale
    name = unique_name(bpy.data.node_groups.keys(), f"{PREFIX} {obj.name} ground")
    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    record.node_groups.append(ng.name)
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = ng.nodes, ng.links
    gi, go = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    position = nodes.new("GeometryNodeInputPosition")
    height = nodes.new("ShaderNodeVectorMath")
    height.operation = "DOT_PRODUCT"
    height.inputs[1].default_value = tuple(float(v) for v in a)
    links.new(position.outputs["Position"], height.inputs[0])
    world_z = nodes.new("ShaderNodeMath")
    world_z.operation = "ADD"
    links.new(height.outputs["Value"], world_z.inputs[0])
    world_z.inputs[1].default_value = b
    depth = nodes.new("ShaderNodeMath")
    depth.operation = "SUBTRACT"
    depth.inputs[0].default_value = h
    links.new(world_z.outputs["Value"], depth.inputs[1])
    lift = nodes.new("ShaderNodeMath")
    lift.operation = "MAXIMUM"
    links.new(depth.outputs["Value"], lift.inputs[0])
    lift.inputs[1].default_value = 0.0
    offset = nodes.new("ShaderNodeVectorMath")
    offset.operation = "SCALE"
    offset.inputs[0].default_value = tuple(float(v) for v in c)
    links.new(lift.outputs["Value"], offset.inputs["Scale"])
    move = nodes.new("GeometryNodeSetPosition")
    links.new(gi.outputs["Geometry"], move.inputs["Geometry"])
    links.new(offset.outputs["Vector"], move.inputs["Offset"])
    links.new(move.outputs["Geometry"], go.inputs["Geometry"])
    for i, node in enumerate((gi, position, height, world_z, depth, lift, offset, move, go)):
        node.location = (200 * i, 0)
    mod = obj.modifiers.new(name=unique_name({m.name for m in obj.modifiers}, f"{PREFIX} Ground"), type="NODES")
    record.modifiers.append(mod.name)
    mod.node_group = ng
    arm_index = next(i for i, m in enumerate(obj.modifiers) if m.type == "ARMATURE" and m.name in record.modifiers)
    obj.modifiers.move(list(obj.modifiers).index(mod), arm_index + 1)
